"""The terminal controller: equilibrium in Goal, certified invariant ellipsoid, end tubes inside.

A double integrator at rest in a 3 m x 3 m Goal around Init: the controller stage emits a
terminal block (radii lowered to the covering radius so that the end tubes fit), the certify
stage re-verifies it from the file, and tampering with it (a perturbed ``P_T``, a level too
large, a moved equilibrium) is caught. Runs continued 10 s past ``T`` stay in Goal and in the
ellipsoid. The S-procedure containment level is checked against its closed form for equal
shapes and against sampled boundary points.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.controller import BeyondHorizonError, load
from pipeline.model.scenario import load_scenario
from pipeline.numerics.closed_loop.simulate import hold_runs
from pipeline.numerics.terminal.design import design_terminal
from pipeline.numerics.terminal.equilibrium import equilibrium
from pipeline.numerics.terminal.fit import containing_level
from stages.certify import certify_controller, verify_terminal
from tests.helpers.double_integrator import AT_REST_STARTS, DOUBLE_INTEGRATOR, emit_at_rest

GOAL = "[[-1, 1], [2, 1], [2, 4], [-1, 4]]"


def _emit(scenario, path, floor):
    return emit_at_rest(scenario, path, radius_floor=floor)


@pytest.fixture
def held(double_integrator, tmp_path):
    """``(scenario, path)``: a certified controller.json with a terminal block."""
    scenario = double_integrator(goal=GOAL)
    path = tmp_path / "controller.json"
    result = _emit(scenario, path, floor=1.2)
    assert result.terminal, result.terminal_message
    return scenario, path


def test_the_terminal_block_is_emitted_and_certified(held):
    scenario, path = held
    result = certify_controller(scenario, path)
    assert result.success, result.message
    assert result.terminal and result.terminal_decay > 0 and result.terminal_fit <= 1
    controller = load(path)
    assert all(tr.radius == pytest.approx(1.2) for tr in controller.trajectories)
    terminal = controller.terminal
    np.testing.assert_allclose(scenario.dynamics.f(terminal.x_eq, terminal.u_eq), 0, atol=1e-12)
    assert scenario.in_goal(terminal.x_eq)


def _tamper(path, change):
    document = json.loads(path.read_text())
    change(document["terminal"])
    path.write_text(json.dumps(document))


def _flip_coupling(terminal):
    """``D P_T D`` with ``D = diag(1, 1, -1, -1)``: still positive definite, same level and
    extents, but the position-velocity coupling has the wrong sign for a Lyapunov function."""
    D = np.diag([1.0, 1.0, -1.0, -1.0])
    terminal["P"] = (D @ np.array(terminal["P"]) @ D).tolist()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t: t.update(level=4 * t["level"]), "leaves Goal"),
        (lambda t: t.update(P=np.diag([1.0, 1.0, 0.05, 0.05]).tolist()), "does not decrease"),
        (_flip_coupling, "does not decrease"),
        (lambda t: t["x_eq"].__setitem__(0, t["x_eq"][0] + 0.6), "not inside the terminal"),
    ],
    ids=["level 4x", "P_T not a Lyapunov matrix", "P_T coupling flipped", "x_eq moved"],
)
def test_a_tampered_terminal_block_is_not_certified(held, change, message):
    scenario, path = held
    _tamper(path, change)
    result = certify_controller(scenario, path)
    assert not result.success
    assert any(message in failure for failure in result.failures), result.failures
    assert verify_terminal(scenario, load(path))[2]


def test_runs_continued_ten_seconds_past_T_stay_in_goal(held):
    scenario, path = held
    controller = load(path)
    rng = np.random.default_rng(0)
    x0 = scenario.init_lower + (scenario.init_upper - scenario.init_lower) * rng.random((64, 4))
    x0[:, 2:] = rng.uniform(-0.3, 0.3, (64, 2))  # moving starts, covered ones kept
    x0 = x0[controller.select(x0)[1] < 1]
    assert len(x0) > 10
    checks = hold_runs(scenario, controller, x0, duration=10.0)
    assert not checks.failures().any()
    assert checks.level_ratio.max() <= 1 and checks.path_goal_margin.min() > 0


def test_without_a_fit_there_is_no_terminal_block_and_the_law_refuses_past_T(
    double_integrator, tmp_path
):
    scenario = double_integrator(goal=GOAL)
    path = tmp_path / "controller.json"
    result = _emit(scenario, path, floor=None)  # the radii stay at their largest: no fit
    assert not result.terminal and "do not fit" in result.terminal_message
    controller = load(path)
    assert controller.terminal is None
    index, _ = controller.select(AT_REST_STARTS[0])
    controller(1.0, AT_REST_STARTS[0], index)  # up to T: fine
    with pytest.raises(BeyondHorizonError):
        controller(1.01, AT_REST_STARTS[0], index)
    assert "no terminal controller" in certify_controller(scenario, path).message


def test_containment_level_is_exact():
    rng = np.random.default_rng(1)
    for _ in range(20):
        L = rng.normal(size=(4, 4))
        P = L @ L.T + 0.5 * np.eye(4)
        M = rng.normal(size=(4, 4))
        Q = M @ M.T + 0.5 * np.eye(4)
        d, rho = rng.normal(size=4), float(rng.uniform(0.1, 2))
        c = containing_level(Q, d, P, rho)
        # sampled points of the ball's boundary stay below c, and come close to it
        z = rng.normal(size=(20000, 4))
        z /= np.linalg.norm(z, axis=1, keepdims=True)
        values, vectors = np.linalg.eigh(P)
        y = rho * z @ (vectors @ np.diag(values**-0.5) @ vectors.T)
        sampled = np.einsum("ki,ij,kj->k", y + d, Q, y + d)
        assert sampled.max() <= c * (1 + 1e-9)
        assert sampled.max() >= 0.9 * c
        # equal shapes: the closed form (||d||_P + rho)^2
        assert containing_level(P, d, P, rho) == pytest.approx(
            (np.sqrt(d @ P @ d) + rho) ** 2, rel=1e-9
        )


def test_quadrotor_hover_is_the_equilibrium_and_has_a_certified_ellipsoid():
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    x_eq, u_eq = equilibrium(scenario)
    np.testing.assert_allclose(scenario.dynamics.f(x_eq, u_eq), 0, atol=1e-9)
    # hover against the wind mu wX = -0.25 N: thrust sqrt(9.81^2 + 0.25^2), tilted into it
    assert u_eq[0] == pytest.approx(np.hypot(9.81, 0.25), rel=1e-9)
    design = design_terminal(scenario, np.zeros((2, 6)), np.eye(6), [x_eq], [0.0])
    assert design.check.success and design.check.level > 0 and design.fit == 0


def test_a_hold_scenario_certifies_only_with_a_terminal_controller(tmp_path):
    path = tmp_path / "hold" / "scenario.yaml"
    path.parent.mkdir()
    text = DOUBLE_INTEGRATOR % {"goal": GOAL, "region": "{aX: [-100.0, 100.0]}", "rate": 0.5}
    path.write_text(text + "terminal: hold\n")
    scenario = load_scenario(path, check_demos=False)
    assert scenario.terminal == "hold"
    without = _emit(scenario, tmp_path / "without.json", floor=None)
    assert not without.terminal
    result = certify_controller(scenario, tmp_path / "without.json")
    assert not result.success and "terminal: hold" in result.message
    assert _emit(scenario, tmp_path / "with.json", floor=1.2).terminal
    assert certify_controller(scenario, tmp_path / "with.json").success
