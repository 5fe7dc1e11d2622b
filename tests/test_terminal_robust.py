"""The terminal ellipsoid robust to an additive disturbance (T1') and the funnel end in it (T2).

Known answer: the planar double integrator ``x'' = u + w`` (two decoupled axes) with the fixed gain
``u = -x - 2 v`` per axis, ``A_cl = [[0, 1], [-1, -2]]``, and ``P`` from the Lyapunov equation
``A_cl^T P + P A_cl = -I``: ``P = [[3/2, 1/2], [1/2, 1/2]]`` per axis, so ``V' = -|e|^2 <= -V /
lambda_max(P)`` and the decay is ``alpha = 1 / (1 + 1/sqrt 2) = 2 - sqrt 2`` (exact: the Jacobian is
constant, the hull one vertex). A disturbance ``|w| <= beta`` on both velocity derivatives has
``omega = max ||w||_P = beta sqrt(1/2 + 1/2) = beta``, so (T1') certifies exactly the levels above
``c* = (2 beta / (2 - sqrt 2))^2``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.numerics.terminal.check import check_level, largest_level
from pipeline.numerics.terminal.design import ROOM, design_terminal, hold_design
from pipeline.numerics.terminal.equilibrium import equilibrium, lqr_terminal
from pipeline.numerics.terminal.fit import TerminalTarget, containing_level
from pipeline.numerics.terminal.robust import SHARES, largest_metric, robust_metric
from pipeline.numerics.uncertainty import additive_bound

BETA = 0.05
ALPHA = 2 - np.sqrt(2)
FLOOR = (2 * BETA / ALPHA) ** 2  # the closed form c*
# states [x, y, vx, vy]: the per-axis gain and Lyapunov matrix, placed on both axes
K_FIXED = np.array([[-1.0, 0.0, -2.0, 0.0], [0.0, -1.0, 0.0, -2.0]])
P_FIXED = np.array(
    [[1.5, 0.0, 0.5, 0.0], [0.0, 1.5, 0.0, 0.5], [0.5, 0.0, 0.5, 0.0], [0.0, 0.5, 0.0, 0.5]]
)


def gusty(tmp_path: Path, beta: float = BETA):
    """double_integrator_hold with a declared gust ``|w| <= beta`` on vx' and vy'."""
    source = Path(__file__).resolve().parents[1] / "scenarios" / "double_integrator_hold"
    folder = tmp_path / "gusty"
    shutil.copytree(source, folder)
    path = folder / "scenario.yaml"
    text = path.read_text().replace("name: double_integrator_hold", "name: gusty")
    path.write_text(text + f"\nuncertainty: {{disturbance: {{vx: {beta}, vy: {beta}}}}}\n")
    return load_scenario(folder, check_demos=False)


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return gusty(tmp_path_factory.mktemp("terminal_robust"))


def test_the_lyapunov_pair_is_the_stated_one(scenario):
    A = scenario.dynamics.f_x(np.zeros(4), np.zeros(2))
    B = scenario.dynamics.f_u(np.zeros(4), np.zeros(2))
    A_cl = A + B @ K_FIXED
    np.testing.assert_allclose(A_cl.T @ P_FIXED + P_FIXED @ A_cl, -np.eye(4), atol=1e-12)
    np.testing.assert_allclose(additive_bound(scenario), [0, 0, BETA, BETA])


def exact_level(beta: float) -> float:
    """The smallest level ``c`` at which ``V' = -|e|^2 + 2 e^T P w`` is <= 0 on ``V = c`` for
    every ``|w_vx|, |w_vy| <= beta`` (K_FIXED, P_FIXED), by brute force on a fine grid: the corner
    ``(beta, beta)`` is worst, and rotating the two identical axes by 45 degrees makes it one
    axis pushed by ``sqrt(2) beta``, whose level is ``(2 sqrt(2) beta max |p^T u| / |u|^2)^2``
    over ``u^T P_2 u = 1`` (``P_2`` one axis's block, ``p`` its speed row)."""
    P2, p = P_FIXED[np.ix_([0, 2], [0, 2])], P_FIXED[2, [0, 2]]
    theta = np.linspace(0, 2 * np.pi, 200_001)
    u = np.stack([np.cos(theta), np.sin(theta)])
    u = u / np.sqrt(np.einsum("it,ij,jt->t", u, P2, u))
    ratio = np.abs(p @ u) / np.einsum("it,it->t", u, u)
    return float((2 * np.sqrt(2) * beta * ratio.max()) ** 2)


def test_the_robust_level_is_the_closed_form(scenario):
    """(T1')'s floor is its closed form ``(2 beta / alpha)^2``; the level certified is the exact
    one (the S-procedure (T1'') is lossless here), about half of it: passes 0.1% above, fails
    0.1% below."""
    x_eq, u_eq = equilibrium(scenario)
    b = additive_bound(scenario)
    exact = exact_level(BETA)
    above = check_level(scenario, x_eq, u_eq, K_FIXED, P_FIXED, exact * 1.001, disturbance=b)
    below = check_level(scenario, x_eq, u_eq, K_FIXED, P_FIXED, exact * 0.999, disturbance=b)
    assert above.decay == pytest.approx(ALPHA, rel=1e-12)
    assert above.disturbance == pytest.approx(BETA, rel=1e-12)
    assert above.floor == pytest.approx(FLOOR, rel=1e-9) and exact < 0.6 * FLOOR
    assert above.success, above.failures
    assert not below.success and below.below_floor
    assert any("disturbance" in failure for failure in below.failures)
    # without the disturbance the small level is certified (the floor is 0)
    assert check_level(scenario, x_eq, u_eq, K_FIXED, P_FIXED, FLOOR * 0.999).success


def test_trajectories_from_the_boundary_stay_inside_under_bang_bang_and_random_gusts(scenario):
    """``e' = A_cl e + w`` from the boundary of ``c = 1.01 c*``: the worst gust ``w = beta
    sign(B^T P e)`` (it maximises ``V'``) and random piecewise-constant gusts never leave."""
    x_eq, u_eq = equilibrium(scenario)
    A = scenario.dynamics.f_x(x_eq, u_eq)
    B = scenario.dynamics.f_u(x_eq, u_eq)
    A_cl = A + B @ K_FIXED
    level = 1.01 * FLOOR
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(64, 4))
    e = directions / np.sqrt(np.einsum("ki,ij,kj->k", directions, P_FIXED, directions))[:, None]
    e = e * np.sqrt(level)  # (64, 4) on the boundary
    dt, steps = 1e-3, 15000
    worst, largest = e.copy(), 0.0
    random = e.copy()
    gust = BETA * rng.choice([-1.0, 1.0], size=(64, 2))
    for k in range(steps):
        w_worst = BETA * np.sign(worst @ P_FIXED @ B)  # (64, 2)
        if k % 100 == 0:  # a new gust every 0.1 s
            gust = rng.uniform(-BETA, BETA, size=(64, 2))
        for state, w in ((worst, w_worst), (random, gust)):
            # RK4 with the gust held over the step
            def f(z, w=w):
                return z @ A_cl.T + w @ B.T

            k1 = f(state)
            k2 = f(state + dt / 2 * k1)
            k3 = f(state + dt / 2 * k2)
            k4 = f(state + dt * k3)
            state += dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        for state in (worst, random):
            largest = max(largest, float(np.einsum("ki,ij,kj->k", state, P_FIXED, state).max()))
    assert largest <= level * (1 + 1e-9)
    # the worst gust keeps the states away from the centre: they end near the floor, not at 0
    assert np.einsum("ki,ij,kj->k", worst, P_FIXED, worst).max() > 0.2 * FLOOR


def test_zero_disturbance_is_the_exact_model_exactly(scenario):
    x_eq, u_eq = equilibrium(scenario)
    K, P = lqr_terminal(scenario, x_eq, u_eq)
    zeros = np.zeros(4)
    for level in (0.01, 0.2, 0.29, 5.0):
        assert check_level(scenario, x_eq, u_eq, K, P, level, disturbance=zeros) == check_level(
            scenario, x_eq, u_eq, K, P, level
        )
    assert largest_level(scenario, x_eq, u_eq, K, P, disturbance=zeros) == largest_level(
        scenario, x_eq, u_eq, K, P
    )
    end = [x_eq + 0.05]
    exact = design_terminal(scenario, K, P, end, [0.01])
    again = design_terminal(scenario, K, P, end, [0.01], disturbance=zeros)
    assert exact.check == again.check and exact.fit == again.fit


def test_the_robust_design_keeps_a_level_above_its_floor(scenario):
    """On one metric (the Riccati one) the gust may only cost level; the design keeps the metric
    shaped for it (T3), certified from its design level 1 up; a gust too strong for any level in
    Goal has no design."""
    b = additive_bound(scenario)
    x_eq, u_eq = equilibrium(scenario)
    K, P = lqr_terminal(scenario, x_eq, u_eq)
    robust = largest_level(scenario, x_eq, u_eq, K, P, disturbance=b)
    exact = largest_level(scenario, x_eq, u_eq, K, P)
    assert robust.success and robust.level <= exact.level
    design = hold_design(scenario, b)
    assert design.shaped and design.check.success and design.check.level >= 1.0
    assert design.check.level >= ROOM**2 and design.arrival is None  # (T6) not needed
    with pytest.raises(ValueError, match="disturbance"):
        hold_design(scenario, 40 * b)


def test_the_end_cap_is_sound_and_no_worse_than_the_triangle_inequality():
    """(T2) with ``lambda = 1 - delta``: every ``Q`` it admits ends inside (the exact level), and
    every ``Q <= (1 - delta)^2 c P_T^-1`` is admitted."""
    rng = np.random.default_rng(3)
    for _ in range(40):
        M = rng.normal(size=(4, 4))
        P_T = M @ M.T + 0.3 * np.eye(4)
        target = TerminalTarget(x_eq=rng.normal(size=4), P=P_T, level=float(rng.uniform(0.5, 2)))
        d = rng.normal(size=4)
        d *= rng.uniform(0.0, 0.9) * np.sqrt(target.level / (d @ P_T @ d))
        end = target.x_eq + d
        C, bound = target.end_cap(end)
        delta = max(target.share(end), 1e-2)
        # the triangle inequality's ellipsoid is admitted
        Q = (1 - delta) ** 2 * target.level * np.linalg.inv(P_T)
        assert np.linalg.eigvalsh(bound - C @ Q @ C.T)[0] >= -1e-9
        # a random admitted Q (scaled to the cap's edge) ends inside
        L = rng.normal(size=(4, 4))
        Q = L @ L.T + 0.1 * np.eye(4)
        lo, hi = 0.0, 1e3
        for _ in range(60):
            mid = (lo + hi) / 2
            ok = np.linalg.eigvalsh(bound - C @ (mid * Q) @ C.T)[0] >= 0
            lo, hi = (mid, hi) if ok else (lo, mid)
        needed = containing_level(P_T, d, np.linalg.inv(lo * Q), 1.0)
        assert needed <= target.level * (1 + 1e-7)
        # the radius limit is the exact level's
        rho = target.end_radius(end, np.linalg.inv(Q))
        assert containing_level(P_T, d, np.linalg.inv(Q), rho) == pytest.approx(
            target.level, rel=1e-6
        )
    with pytest.raises(ValueError, match="outside"):
        target.end_cap(target.x_eq + 2 * d)


def test_a_robust_funnel_ends_inside_the_terminal_ellipsoid_only_when_asked(scenario):
    """A nominal flown to rest at Goal's centre in 2 s, the gust declared: the robust funnel
    alone ends outside a quarter of the robust terminal ellipsoid; with ``terminal=`` (T2)
    shapes it to end inside, by the exact level."""
    from pipeline.model.simulate import simulate
    from pipeline.numerics.funnel.synthesis import synthesize_funnel

    b = additive_bound(scenario)
    x_eq, u_eq = equilibrium(scenario)
    K_T, P_T = lqr_terminal(scenario, x_eq, u_eq)  # the Riccati metric: (T2) is the point here
    level = largest_level(scenario, x_eq, u_eq, K_T, P_T, disturbance=b).level
    target = TerminalTarget(x_eq=x_eq, P=P_T, level=level)
    us = np.vstack([np.tile([1.0, 0.5], (10, 1)), np.tile([-1.0, -0.5], (10, 1))])
    nominal = simulate(scenario.dynamics, np.array([9.0, 0.0, 0.0, 0.0]), us, scenario.Ts)
    np.testing.assert_allclose(nominal.xs[-1], x_eq, atol=1e-12)

    def needed(funnel):
        return containing_level(target.P, nominal.xs[-1] - target.x_eq, funnel.P[-1], funnel.rho)

    alone = synthesize_funnel(scenario, nominal, disturbance=b)
    quarter = TerminalTarget(x_eq=target.x_eq, P=target.P, level=target.level / 4)
    assert alone.success and needed(alone) > 1.5 * quarter.level
    held = synthesize_funnel(scenario, nominal, disturbance=b, terminal=quarter)
    assert held.success, held.message
    assert needed(held) <= quarter.level and held.rho > 0.3
    # a smaller target: the exact level binds rho (sound whatever the program returned)
    small = TerminalTarget(x_eq=target.x_eq, P=target.P, level=0.3 * target.level)
    tight = synthesize_funnel(scenario, nominal, terminal=small)
    assert tight.success and needed(tight) <= small.level
    assert tight.limits["terminal"] < 1.0
    # a nominal that ends outside has no funnel
    with pytest.raises(ValueError, match="outside the terminal ellipsoid"):
        synthesize_funnel(scenario, nominal, terminal=TerminalTarget(
            x_eq=target.x_eq + np.array([0.9, 0, 0, 0]), P=target.P, level=target.level
        ))  # fmt: skip


@pytest.fixture(scope="module")
def shipped(scenario, tmp_path_factory):
    """``(path, design)``: a ``/2`` file of one robust funnel ending in the robust terminal set."""
    from pipeline.model.simulate import simulate
    from pipeline.numerics.funnel.synthesis import synthesize_funnel
    from stages.controller import emit_funnel_controller

    b = additive_bound(scenario)
    design = hold_design(scenario, b)
    target = TerminalTarget(x_eq=design.x_eq, P=design.P, level=design.check.level)
    us = np.vstack([np.tile([1.0, 0.5], (10, 1)), np.tile([-1.0, -0.5], (10, 1))])
    nominal = simulate(scenario.dynamics, np.array([9.0, 0.0, 0.0, 0.0]), us, scenario.Ts)
    funnel = synthesize_funnel(scenario, nominal, disturbance=b, terminal=target)
    path = tmp_path_factory.mktemp("shipped") / "controller.json"
    result = emit_funnel_controller(
        scenario, [nominal], [funnel], path, disturbance=b, terminal=design
    )
    assert result.terminal, result.terminal_message
    return path, design


def test_the_funnel_file_carries_the_robust_block_and_the_law_switches_at_T(scenario, shipped):
    from pipeline.controller import load
    from stages.certify import verify_terminal

    path, design = shipped
    controller = load(path)
    terminal = controller.terminal
    assert controller.funnel and terminal is not None
    np.testing.assert_array_equal(terminal.disturbance, additive_bound(scenario))
    assert terminal.level == design.check.level
    decay, fit, failures = verify_terminal(scenario, controller)
    assert not failures and decay > 0 and fit <= 1
    x = design.x_eq + np.array([0.1, -0.1, 0.05, 0.0])
    T = controller.trajectories[0].T
    np.testing.assert_array_equal(
        controller(T + 0.5, x, 0), np.clip(design.u_eq + design.K @ (x - design.x_eq), -2, 2)
    )


def _velocity_gains_flipped(block):
    K = np.array(block["K"])
    K[:, 2:] *= -1
    block["K"] = K.tolist()


SHORT = "terminal: the file holds |w_vx| <= 0, the scenario declares"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t: t.update(level=1.01 * t["level"]), "leaves Goal"),
        (_velocity_gains_flipped, "does not decrease"),
        (
            lambda t: t.update(disturbance=[0.0] * 4),
            "terminal: the file holds |w_vx| <= 0, the scenario declares",
        ),
        (
            lambda t: t.pop("disturbance"),
            "terminal: the file holds |w_vx| <= 0, the scenario declares",
        ),
        (lambda t: t.update(disturbance=[0, 0, 40 * BETA, 40 * BETA]), "disturbance"),
    ],
    ids=["level +1%", "K_T velocity gains flipped", "bound 0", "no bound", "bound 40x claimed"],
)
def test_a_tampered_robust_terminal_block_is_refused(scenario, shipped, tmp_path, change, message):
    import json

    from pipeline.controller import load
    from stages.certify import certify_controller, verify_terminal

    path, _ = shipped
    document = json.loads(path.read_text())
    change(document["terminal"])
    tampered = tmp_path / "controller.json"
    tampered.write_text(json.dumps(document))
    failures = verify_terminal(scenario, load(tampered))[2]
    assert any(message in failure for failure in failures), failures
    result = certify_controller(scenario, tampered)
    assert not result.success
    assert any(message in failure for failure in result.failures if "terminal" in failure)


def test_the_shaped_metric_is_the_smaller_certified_set(scenario):
    """(T3): for the same LQR gain, the metric shaped for the gust certifies (T1'') at level 1,
    about the smallest set the gust leaves, and that set's position extent is below the smallest
    the Riccati metric certifies (its floor's); hold_design keeps it and says so."""
    x_eq, u_eq = equilibrium(scenario)
    b = additive_bound(scenario)
    K, P_riccati = lqr_terminal(scenario, x_eq, u_eq)
    P = robust_metric(scenario, x_eq, u_eq, K, b)
    assert P is not None
    assert check_level(scenario, x_eq, u_eq, K, P, 1.001, disturbance=b).success
    assert not check_level(scenario, x_eq, u_eq, K, P, 0.5, disturbance=b).success

    def position_extent(metric, level):
        return float(np.sqrt(level * np.linalg.inv(metric)[0, 0]))

    lo, hi = 1e-6, largest_level(scenario, x_eq, u_eq, K, P_riccati, disturbance=b).level
    for _ in range(40):  # the Riccati metric's smallest certified level
        mid = (lo + hi) / 2
        ok = check_level(scenario, x_eq, u_eq, K, P_riccati, mid, disturbance=b).success
        lo, hi = (lo, mid) if ok else (mid, hi)
    assert position_extent(P, 1.0) < position_extent(P_riccati, hi)
    design = hold_design(scenario, b)
    assert design.shaped and np.array_equal(design.P, P)
    assert not hold_design(scenario).shaped  # the exact model keeps the Riccati metric


def test_a_tight_shaped_set_gives_way_to_the_largest_certified_one(tmp_path):
    """(T6) under a gust seven times BETA: the shaped set (T3) certifies less than ``ROOM^2``
    its design level, so the terminal is the largest set of the same gain, certified from scratch
    at its level, of a larger volume, with the shaped set as the one the nominals arrive in. A
    nominal flown to rest at the centre: its robust funnel holds only part of its required set
    when it must end in the shaped set, all of it in the larger one (at six times BETA both
    hold all of it since ``ROBUST_MULTIPLIERS`` is searched in finer steps)."""
    from pipeline.model.simulate import simulate
    from pipeline.numerics.funnel.synthesis import synthesize_funnel

    scenario = gusty(tmp_path, 7 * BETA)
    b = additive_bound(scenario)
    design = hold_design(scenario, b)
    shaped = design.arrival
    assert shaped is not None and shaped.shaped and shaped.check.level < ROOM**2
    assert design.arrives_in is shaped and not design.shaped
    np.testing.assert_array_equal(design.K, shaped.K)
    assert design.log_volume > shaped.log_volume + 0.05
    x_eq, u_eq = design.x_eq, design.u_eq
    again = check_level(scenario, x_eq, u_eq, design.K, design.P, design.check.level, disturbance=b)
    assert again.success and again == design.check
    # the (T6) metric itself is one of largest_metric's, for one of the boxes
    candidates = [largest_metric(scenario, x_eq, u_eq, design.K, b, share) for share in SHARES]
    assert any(found is not None and np.array_equal(found[1], design.P) for found in candidates)
    us = np.vstack([np.tile([1.0, 0.5], (10, 1)), np.tile([-1.0, -0.5], (10, 1))])
    nominal = simulate(scenario.dynamics, np.array([9.0, 0.0, 0.0, 0.0]), us, scenario.Ts)
    levels = []
    for terminal in (shaped, design):
        target = TerminalTarget(x_eq=x_eq, P=terminal.P, level=terminal.check.level)
        funnel = synthesize_funnel(scenario, nominal, disturbance=b, terminal=target)
        assert funnel.success, funnel.message
        needed = containing_level(target.P, nominal.xs[-1] - x_eq, funnel.P[-1], funnel.rho)
        assert needed <= target.level * (1 + 1e-9)
        levels.append(funnel.rho)
    assert levels[0] < levels[1] - 0.03 and levels[1] > 0.999, levels


def test_the_nominals_end_in_the_shaped_set_and_keep_its_reserve(tmp_path):
    """``core_targets`` of a (T6) design: Goal's bounds are the core box of the shaped set the
    nominals arrive in, and the reserve is sized from it (the larger set's would starve them),
    while the funnels' target is the larger set."""
    from stages.certificates.targets import core_targets, reserve_of, target_of

    scenario = gusty(tmp_path, 6 * BETA)
    design = hold_design(scenario, additive_bound(scenario))
    shaped = design.arrival
    assert shaped is not None
    targets = core_targets(scenario, design)
    assert targets.terminal is design
    half = target_of(shaped).core_box(1.0)
    assert not np.allclose(half, target_of(design).core_box(1.0))  # the two boxes differ
    for name, centre, h in zip(scenario.state_names, design.x_eq, half, strict=True):
        lower, upper = scenario.goal_bounds.get(name, (-np.inf, np.inf))
        expected = (max(lower, float(centre - h)), min(upper, float(centre + h)))
        assert targets.scenario.goal_bounds[name] == expected
    assert dict(targets.reserve) == reserve_of(scenario, shaped) != {}


def test_where_no_metric_of_the_lqr_gain_holds_a_gain_designed_with_its_metric_does(tmp_path):
    """(T6) with ``Y = K Q`` under a gust eight times BETA: neither the Riccati matrix nor (T3)'s
    metric of the LQR gain certifies a level, a gain designed with the largest set does; its own
    (T3) set, the one the nominals arrive in, certifies too, and both pass ``check_level`` from
    scratch. At 40 times (the test above) nothing does."""
    scenario = gusty(tmp_path, 8 * BETA)
    b = additive_bound(scenario)
    x_eq, u_eq = equilibrium(scenario)
    K_lqr, P_lqr = lqr_terminal(scenario, x_eq, u_eq)
    assert not largest_level(scenario, x_eq, u_eq, K_lqr, P_lqr, disturbance=b).success
    shaped_lqr = robust_metric(scenario, x_eq, u_eq, K_lqr, b)
    assert shaped_lqr is None or not (
        largest_level(scenario, x_eq, u_eq, K_lqr, shaped_lqr, disturbance=b).success
    )
    design = hold_design(scenario, b)
    arrival = design.arrival
    assert design.gain == "codesigned" and arrival is not None and arrival.shaped
    assert not np.allclose(design.K, K_lqr) and np.array_equal(arrival.K, design.K)
    for terminal in (design, arrival):
        again = check_level(
            scenario, x_eq, u_eq, terminal.K, terminal.P, terminal.check.level, disturbance=b
        )
        assert again.success and again == terminal.check
    assert design.log_volume > arrival.log_volume
    # the first nominals' reserve is the LQR gain's over the arrival set, not the designed gain's
    from stages.certificates.targets import RESERVE, reserve_of

    Q = RESERVE**2 * np.linalg.inv(arrival.P)
    reserve = reserve_of(scenario, arrival)
    for j, name in enumerate(scenario.input_names):
        assert reserve[name] == pytest.approx(np.sqrt(K_lqr[j] @ Q @ K_lqr[j]), rel=1e-12)
        assert reserve[name] < np.sqrt(design.K[j] @ Q @ design.K[j])
