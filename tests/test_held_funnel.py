"""A funnel's law evaluated every h seconds and held in between (``funnel.law`` (I6), the
terminal law's (T4) of ``terminal.check``).

The bound ``|x(t_j) - xhat(t_j) - e(t)| <= Delta + h Edot`` is checked against brute force (the
held law flown from the funnel's boundary under bang-bang and outward-pushing disturbances);
a robust double-integrator funnel holds a short period and is refused at a long one, naming the
hold; with ``h = 0`` every number is the continuous law's (the old ``law_offset`` kept here as
the reference); the held terminal law's box is checked the same way. The slow test synthesizes
double_integrator_hold with a gust and the funnel certificate at 5 ms: certified, the Monte
Carlo flies the held law, and certify refuses the file with its period edited upward.
"""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

import pipeline
from pipeline.controller import inverse_linear, load
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate, simulate_graded
from pipeline.numerics.closed_loop.simulate import held_steps
from pipeline.numerics.funnel.held import held_rates
from pipeline.numerics.funnel.law import BASE_SUBSTEPS, LawOffset, law_offset, law_substeps
from pipeline.numerics.terminal.check import check_level, hold_bound, largest_level
from pipeline.numerics.terminal.equilibrium import equilibrium, lqr_terminal
from pipeline.numerics.verify.recertify import rebuild_funnel, recheck_as_shipped
from stages.certify import certify_controller
from stages.funnel import HOLD_DESIGN, design_disturbance
from tests.helpers.held import per_state_hold
from tests.helpers.robust import (
    DISTURBANCE,
    GUST,
    gusty_hold_scenario,
    held_hover_flights,
    rk4_step,
    robust_double_integrator,
)


@pytest.fixture(scope="module")
def robust_case():
    """The robust double-integrator funnel of ``tests.helpers.robust`` (gust 0.05 m/s^2)."""
    return robust_double_integrator()


def _old_law_offset(vertices, rate_bound, K, P, rho, rate, Ts, substeps, centre_error=0.0):
    """``law_offset`` as it was before (I6) (commit 6b82c35), the reference for ``h = 0``."""
    N, m, n = K.shape
    steps = Ts / np.asarray(substeps, dtype=np.float64)
    Q_diagonal = np.diagonal(np.linalg.inv(P), axis1=1, axis2=2)
    centre = centre_error * np.sqrt(np.maximum(Q_diagonal[:-1], Q_diagonal[1:]))
    deviation, input_offset, lmi_term = np.zeros((N, n)), np.zeros((N, m)), np.zeros(N)
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))[: 2 ** (n - 1)]
    for k in range(N):
        A, B = vertices[k][:, :, :n], vertices[k][:, :, n:]
        acceleration = (np.abs(A) @ rate_bound[k]).max(axis=0)
        deviation[k] = steps[k] ** 2 / 8 * acceleration + centre[k]
        input_offset[k] = np.abs(K[k]) @ deviation[k]
        offsets = (B @ K[k]) @ (signs * deviation[k]).T
        w = max(
            float(np.sqrt(np.einsum("vic,ij,vjc->vc", offsets, P[k + e], offsets).max()))
            for e in (0, 1)
        )
        lmi_term[k] = 2 * w / (rho * math.exp(-rate * Ts * (k + 1)))
    return steps, deviation, input_offset, lmi_term


def test_without_a_period_every_number_is_the_continuous_laws(robust_case):
    """``period = 0``: ``law_offset`` is bit for bit the function before (I6) on random funnels
    and on the robust case's hulls, ``law_substeps`` picks the same grid, and the re-check is
    the same with and without the argument."""
    rng = np.random.default_rng(11)
    N, n, m = 4, 4, 2
    root = rng.standard_normal((N + 1, n, n))
    P = np.einsum("kij,klj->kil", root, root) + n * np.eye(n)
    K = rng.standard_normal((N, m, n))
    vertices = tuple(rng.standard_normal((3, n, n + m)) for _ in range(N))
    rate_bound = np.abs(rng.standard_normal((N, n)))
    args = (vertices, rate_bound, K, P, 0.7, 0.3, 0.1, np.array([20, 7, 33, 20]), 1e-4)
    new, old = law_offset(*args), _old_law_offset(*args)
    for a, b in zip((new.steps, new.deviation, new.input_offset, new.lmi_term), old, strict=True):
        assert np.array_equal(a, b)
    assert new.period == 0 and new.hold is None and new.held_input is None
    margins, room = -np.abs(rng.standard_normal(N)) * 1e-3, np.abs(rng.standard_normal((N, m)))
    old_offset = LawOffset(
        steps=old[0], deviation=old[1], input_offset=old[2], lmi_term=old[3],
        disturbance=np.zeros(n),
    )  # fmt: skip
    assert np.array_equal(
        law_substeps(new, margins, room, 0.1), law_substeps(old_offset, margins, room, 0.1)
    )
    scenario, trajectory, shipped = robust_case
    plain = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE)
    zero = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE, 0.0)
    assert plain == zero and plain.failure is None


def test_a_short_period_is_certified_and_a_long_one_refused_naming_the_hold(robust_case):
    scenario, trajectory, shipped = robust_case
    short = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE, 0.002)
    assert short.failure is None, short.failure
    continuous = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE)
    assert short.margin > continuous.margin  # the hold costs room
    assert short.disturbance_multiple < continuous.disturbance_multiple
    long = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE, 0.05)
    assert long.failure is not None
    assert "the hold's term (I6)" in long.failure
    assert "not certifiable with the law held every 0.05 s" in long.failure


@pytest.mark.parametrize("period", [0.01, 0.025])
def test_the_held_offset_stays_within_its_bound_flown_from_the_boundary(robust_case, period):
    """The held law ``u = u_ref + K (x(t_j) - xhat(t_j))`` (``xhat`` interpolated on a coarse
    grid of 4 steps per sample) flown from 64 boundary points at 3 sample times under
    disturbances at the corners of ``|w| <= d``, switching at random or pushing outward, on RK4
    steps of ``h / 25``: while the state is in the funnel, ``|x(t_j) - xhat(t_j) - e(t)| <=
    Delta_h[k]`` componentwise, the push ``|B K (e(t_j) - e(t))| <= H[k]`` and ``|K (e(t_j) -
    e(t))| <= held_input[k]`` (I6); and the flights reach at least half of the first in the
    speeds (measured: 82-97% in every state) and of ``H`` (measured: 64-69%)."""
    scenario, trajectory, shipped = robust_case
    Ts, n, N = scenario.Ts, scenario.n, len(shipped.K)
    nominal = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, BASE_SUBSTEPS)
    funnel = rebuild_funnel(scenario, nominal, shipped, {}, 1)
    grid = np.full(N, 4)
    law = law_offset(
        funnel.vertices, funnel.enclosure.rate_bound, shipped.K, shipped.P, shipped.rho,
        shipped.rate, Ts, grid, 0.0, period, DISTURBANCE,
    )  # fmt: skip
    windows, per_window = round(Ts / period), 25
    fine_steps = windows * per_window
    dt = Ts / fine_steps
    exact = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, fine_steps)
    coarse = simulate_graded(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, grid)
    xhat = np.stack(
        [np.interp(exact.dense_ts, coarse.dense_ts, coarse.dense_xs[:, i]) for i in range(n)], -1
    )
    P_t = inverse_linear(shipped.P, Ts, exact.dense_ts)
    rng = np.random.default_rng(5)
    worst, reached = np.zeros(n), np.zeros(2)
    B_u = scenario.dynamics.f_u(trajectory.xs[0], trajectory.us[0])  # constant: Bbar = B_u
    for start in (0, N // 2, N - 3):
        B = 64
        v = rng.standard_normal((B, n))
        j0 = start * fine_steps
        rho_t = shipped.rho * np.exp(-shipped.rate * exact.dense_ts[j0])
        e = rho_t * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P_t[j0], v))[:, None]
        x = exact.dense_xs[j0] + 0.999 * e
        outward = np.arange(B) % 2 == 0
        signs = rng.choice([-1.0, 1.0], size=(B, n))
        inside = np.ones(B, dtype=bool)
        for j in range(j0, N * fine_steps):
            k = j // fine_steps
            if (j - j0) % per_window == 0:  # a sample t_j: the law is evaluated and held
                measured, e_j = x - xhat[j], x - exact.dense_xs[j]
                u = trajectory.us[k] + measured @ shipped.K[k].T
                window_inside = inside.copy()
            if rng.random() < 0.2:
                signs = rng.choice([-1.0, 1.0], size=(B, n))

            def field(state, j=j, u=u, signs=signs, outward=outward):
                push = np.sign((state - exact.dense_xs[j]) @ P_t[j])
                w = DISTURBANCE * np.where(outward[:, None], push, signs)
                return scenario.dynamics.f(state, u) + w

            x = rk4_step(field, x, dt)
            e = x - exact.dense_xs[j + 1]
            rho_t = shipped.rho * np.exp(-shipped.rate * exact.dense_ts[j + 1])
            inside &= np.einsum("bi,ij,bj->b", e, P_t[j + 1], e) <= rho_t**2
            if (j + 1) % fine_steps == 0:
                continue  # t = t_k+1 belongs to the next interval (its own bound)
            check = window_inside & inside
            offset = np.abs(measured - e)[check]  # |x(t_j) - xhat(t_j) - e(t)|
            push = np.abs((e_j - e)[check] @ (B_u @ shipped.K[k]).T)  # Bbar K (e(t_j) - e(t))
            swing = np.abs((e_j - e)[check] @ shipped.K[k].T)  # K (e(t_j) - e(t))
            if len(offset):
                assert np.all(offset <= law.deviation[k] * (1 + 1e-9) + 1e-12), (k, j)
                assert np.all(push <= law.hold[k] * (1 + 1e-9) + 1e-12), (k, j)
                assert np.all(swing <= law.held_input[k] * (1 + 1e-9) + 1e-12), (k, j)
                worst = np.maximum(worst, (offset / law.deviation[k]).max(axis=0))
                reached = np.maximum(reached, (push[:, 2:] / law.hold[k, 2:]).max(axis=0))
    assert np.all(worst[2:] > 0.5), worst  # the speeds' bound is at most 2x what is flown
    assert np.all(reached > 0.5), reached  # so is the push's box


def _random_funnel(rng, N, n, m, V):
    """A random funnel ``(vertices, rate_bound, K, P)`` with ``V`` hull vertices per interval."""
    root = rng.standard_normal((N + 1, n, n))
    P = np.einsum("kij,klj->kil", root, root) + 0.5 * np.eye(n)
    K = rng.standard_normal((N, m, n))
    vertices = tuple(rng.standard_normal((V, n, n + m)) for _ in range(N))
    return vertices, np.abs(rng.standard_normal((N, n))), K, P


@pytest.mark.parametrize("seed", range(8))
def test_the_support_bound_is_never_above_the_per_state_box(seed):
    """(I6)'s box ``H[k]`` (vertex pairs, the ellipsoid's support function) and the input's
    ``held_input`` are at most the per-state box's ``max_v |B_v K| (h Edot + E)`` and ``|K| (h
    Edot + E)`` (``tests.helpers.held``, the bound before) on random funnels with 1-7 vertices,
    a disturbance and a measurement box on some states; ``deviation`` (the per-state box
    ``Delta + E + h Edot``) is unchanged and the input offset shrinks with ``held_input``."""
    rng = np.random.default_rng(seed)
    N, n, m, V = 5, 4, 2, 1 + seed % 7
    vertices, rate_bound, K, P = _random_funnel(rng, N, n, m, V)
    d = np.abs(rng.standard_normal(n)) * (rng.random(n) < 0.6)
    E = np.abs(rng.standard_normal(n)) * 1e-2 * (rng.random(n) < 0.5) if seed % 2 else None
    substeps, period = rng.integers(4, 40, N), (0.001, 0.01, 0.05)[seed % 3]
    args = (vertices, rate_bound, K, P, 0.8, 0.4, 0.1, substeps, 1e-4)
    held = law_offset(*args, period, d, E)
    plain = law_offset(*args, 0.0, d, E)
    old_hold, old_input, drift = per_state_hold(
        vertices, K, P, 0.8, 0.4, 0.1, plain.deviation, period, d, E
    )
    assert np.all(held.hold <= old_hold * (1 + 1e-12) + 1e-15)
    assert np.all(held.held_input <= old_input * (1 + 1e-12) + 1e-15)
    assert held.hold.sum() < 0.9 * old_hold.sum()  # on random funnels the bound is tighter
    assert np.allclose(held.deviation, plain.deviation + drift, rtol=1e-14, atol=0)
    measured = np.zeros((N, m)) if E is None else np.abs(K) @ E
    swing = held.held_input - measured  # the hold's part, h times the bound on |K e'|
    assert np.allclose(held.input_offset, plain.input_offset + swing, rtol=1e-14, atol=0)
    assert np.array_equal(held.lmi_term, plain.lmi_term)


def test_a_pushed_redesign_asks_for_the_remainder_only_where_the_declaration_pushes():
    """``stages.funnel.design_disturbance``: with the push to first order the remainder on a
    state the declaration does not push (omega') is left to the check; the box design (period
    0), a measured law and an exact model ask for the whole box."""
    declared = np.array([0.0, 0.0, 0.0, 0.15, 0.13, 0.0])
    remainder = np.array([0.0, 0.0, 0.0, 0.002, 0.004, 0.006])
    whole = declared + HOLD_DESIGN * remainder
    pushed = design_disturbance(declared, remainder, 0.005, measured=False)
    assert pushed[5] == 0.0 and np.array_equal(pushed[:5], whole[:5])
    for period, measured, bound in (
        (0.0, False, declared),
        (0.005, True, declared),
        (0.005, False, np.zeros(6)),
    ):
        asked = design_disturbance(bound, remainder, period, measured)
        assert np.array_equal(asked, bound + HOLD_DESIGN * remainder)


def test_the_push_of_random_hulls_stays_in_its_box():
    """(I6) brute force on one interval of a random funnel with 5 hull vertices: ``e' = Abar(s)
    e + Bbar(s) K (e(t_j) + c) + w`` with ``[Abar Bbar]`` switched among the vertices and
    random convex weights, ``c`` at the corners of ``Delta``, ``w`` at those of ``d``, from
    points of the ellipsoid at ``t_j`` (half on its boundary), ``Q = P^-1`` linear in t: while
    ``e`` stays in the funnel, ``|B_v K (e(t_j) - e(t))| <= H[k]`` for every vertex ``v`` (the
    loop's ``Bbar(t)``; ``funnel.held``'s rate ``|B_v K e'(s)|`` per vertex on the way) and
    ``|K (e(t_j) - e(t))| <= held_input[k]``; the flights reach at
    least a fifth of both (measured: 29-32% of ``H``, 24-32% of ``held_input``)."""
    rng = np.random.default_rng(3)
    N, n, m, V, Ts, h, rho, rate = 1, 4, 2, 5, 0.1, 0.02, 1.0, 0.5
    vertices, rate_bound, K, P = _random_funnel(rng, N, n, m, V)
    vertices = (vertices[0] * 0.5,)
    d = np.array([0.0, 0.3, 0.0, 0.2])
    law = law_offset(vertices, rate_bound, K, P, rho, rate, Ts, np.array([5]), 0.0, h, d)
    Delta = law_offset(vertices, rate_bound, K, P, rho, rate, Ts, np.array([5]), 0.0).deviation[0]
    A, Bv = vertices[0][:, :, :n], vertices[0][:, :, n:]
    Q0, Q1 = np.linalg.inv(P[0]), np.linalg.inv(P[1])
    push_rate, _ = held_rates(A, Bv, K[0], np.stack([Q0, Q1]), rho, Delta, d)  # (V, n)
    assert np.allclose(h * push_rate.max(axis=0), law.hold[0], rtol=1e-14, atol=0)
    batch, steps = 4000, 40
    dt = h / steps
    worst_push, worst_input = np.zeros(n), np.zeros(m)
    for start in np.linspace(0.0, Ts - h, 5):
        v = rng.standard_normal((batch, n))
        P_j = np.linalg.inv(Q0 + start / Ts * (Q1 - Q0))
        scale = np.where(np.arange(batch) % 2, 0.999, rng.random(batch))
        radius = rho * math.exp(-rate * start) * scale
        e = radius[:, None] * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P_j, v))[:, None]
        e_j, inside = e.copy(), np.ones(batch, dtype=bool)
        c = Delta * rng.choice([-1.0, 1.0], size=(batch, n))
        for step in range(steps):
            weights = rng.dirichlet(np.full(V, 0.3), size=batch)  # near the vertices
            Ab, Bb = np.einsum("bv,vij->bij", weights, A), np.einsum("bv,vij->bij", weights, Bv)
            w = d * rng.choice([-1.0, 1.0], size=(batch, n))
            u = (e_j + c) @ K[0].T
            drive = np.einsum("bij,bj->bi", Bb, u) + w

            def field(x, Ab=Ab, drive=drive):
                return np.einsum("bij,bj->bi", Ab, x) + drive

            rates = np.abs(np.einsum("vij,jl,bl->bvi", Bv, K[0], field(e)[inside]))
            assert np.all(rates <= push_rate * (1 + 1e-9) + 1e-12), step  # B_v K e'(s)
            e = rk4_step(field, e, dt)
            t = start + (step + 1) * dt
            P_t = np.linalg.inv(Q0 + t / Ts * (Q1 - Q0))
            inside &= np.einsum("bi,ij,bj->b", e, P_t, e) <= (rho * math.exp(-rate * t)) ** 2
            moved = (e_j - e)[inside]
            push = np.abs(np.einsum("vij,jl,bl->bvi", Bv, K[0], moved)).max(axis=1)
            swing = np.abs(moved @ K[0].T)
            assert np.all(push <= law.hold[0] * (1 + 1e-9) + 1e-12), step
            assert np.all(swing <= law.held_input[0] * (1 + 1e-9) + 1e-12), step
            if len(moved):
                worst_push = np.maximum(worst_push, (push / law.hold[0]).max(axis=0))
                worst_input = np.maximum(worst_input, (swing / law.held_input[0]).max(axis=0))
    assert inside.mean() > 0.5
    assert np.all(worst_push > 0.2) and np.all(worst_input > 0.2), (worst_push, worst_input)


def test_the_held_terminal_law_stays_in_its_box_and_ellipsoid():
    """(T4) on double_integrator_hold with its LQR terminal law held every 20 ms: the largest
    certified level, flown from 64 boundary points under outward and bang-bang gusts of 0.02:
    ``|Bbar K (e(t_j) - e(t))| <= b_h`` componentwise (reached to 51%, measured) and ``V <= c``
    throughout; a period of 0.5 s is refused."""
    scenario = load_scenario("double_integrator_hold", check_demos=False)
    x_eq, u_eq = equilibrium(scenario)
    K, P = lqr_terminal(scenario, x_eq, u_eq)
    b, h = np.array([0.0, 0.0, GUST, GUST]), 0.02
    check = largest_level(scenario, x_eq, u_eq, K, P, disturbance=b, held_period=h)
    assert check.success, check.failures
    r = np.sqrt(check.level)
    extent = np.sqrt(np.diag(np.linalg.inv(P)))
    reach = r * np.sqrt(np.einsum("ji,il,jl->j", K, np.linalg.inv(P), K))
    A, B = scenario.dynamics.f_x(x_eq, u_eq)[None], scenario.dynamics.f_u(x_eq, u_eq)[None]
    box = hold_bound(A, B, K, r * extent, reach, scenario.dynamics.f(x_eq, u_eq), b, h)
    continuous = check_level(scenario, x_eq, u_eq, K, P, check.level, disturbance=b)
    assert check.disturbance > continuous.disturbance  # the hold's box joins the gust's
    worst, level = 0.0, 0.0
    flights = held_hover_flights(scenario, x_eq, u_eq, K, P, check.level, b, h, substeps=20, seed=2)
    for e_j, x in flights:
        pushed = np.abs((e_j - (x - x_eq)) @ (B[0] @ K).T)
        assert np.all(pushed <= box * (1 + 1e-9) + 1e-12)
        worst = max(worst, float((pushed[:, 2:] / box[2:]).max()))
        level = max(level, float(np.einsum("bi,ij,bj->b", x - x_eq, P, x - x_eq).max()))
    assert level <= check.level and worst > 0.25, (level, check.level, worst)
    too_long = check_level(scenario, x_eq, u_eq, K, P, check.level, disturbance=b, held_period=0.5)
    assert not too_long.success


@pytest.mark.slow
@pytest.mark.xdist_group("hold-funnel-held")
def test_a_gusty_hold_run_held_every_5_ms_is_certified_and_flown_held(tmp_path):
    """double_integrator_hold with a gust, the funnel certificate and ``feedback_period: 0.005``
    in the scenario (no option: the scenario's period is the run's): certified and validated,
    the claims say the law is held, the Monte Carlo flies the held law (``held_steps``: windows
    of the file's period) with 0 failures; the same file with its period edited to 0.05 s
    (still dividing Ts) or 0.03 s is refused."""
    path = gusty_hold_scenario(tmp_path / "gusty", GUST)
    path.write_text(path.read_text() + "feedback_period: 0.005  # the vehicle's control period\n")
    out = tmp_path / "out"
    result = pipeline.synthesize(path, out=out, samples=300)
    assert result.success, result.message
    claims = [c.claim for c in result.claims]
    assert any("evaluated every 0.005 s and held in between: no flight" in c for c in claims)
    assert any(c.startswith("after T") and "held in between" in c for c in claims)
    controller = load(out / "controller.json")
    assert controller.funnel and controller.feedback_period == 0.005
    assert held_steps(controller, 4) == (20, 1)  # the Monte Carlo's RK4 steps and windows
    summary = json.loads((out / "summary.json").read_text())
    assert summary["montecarlo"]["failures"]["after_T"] == 0
    scenario = load_scenario(path)
    assert certify_controller(scenario, out / "controller.json").success
    for period, message in (
        (0.05, "not certifiable with the law held every 0.05 s"),
        (0.03, "feedback_period 0.03 s does not divide Ts 0.1 s"),
    ):
        document = json.loads((out / "controller.json").read_text())
        document["feedback_period"] = period
        edited = tmp_path / f"controller_{period}.json"
        edited.write_text(json.dumps(document))
        refused = certify_controller(scenario, edited)
        assert not refused.success
        assert message in refused.message, refused.message
