"""``terminal: hold`` on a shipped scenario: double_integrator_hold stays safe for all time.

The scenario is double_integrator with ``terminal: hold`` and ``|vx|, |vy| <= 0.5`` m/s at T
(goal.bounds). Its session synthesis (shared with ``test_end_to_end``) must certify WITH a
terminal controller: the certify stage re-checks the file's invariant ellipsoid (decay at every
hull vertex, inside Goal, no clipping, every end tube inside), the Monte Carlo stage continues its
runs 10 s past T, and here the NumPy-only controller is flown in a plain RK4 loop from a few
starts to ``T + 10`` s: it stays in Goal and in the certified ellipsoid.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from stages.certify import certify_controller, verify_terminal

HOLD = "double_integrator_hold"
PAST_T = 10.0  # seconds flown beyond each trajectory's T
STEP = 0.01  # RK4 step (s)


@pytest.mark.parametrize("name", [HOLD])
def test_hold_run_is_certified_with_a_rechecked_terminal_controller(synthesis, name):
    code, out = synthesis(name)
    summary = json.loads((out / "summary.json").read_text())
    assert code == 0 and summary["verdict"]["certified"] and summary["verdict"]["validated"]
    claims = {c["claim"]: c["kind"] for c in summary["claims"]}
    after = [claim for claim in claims if claim.startswith("after T")]
    assert after and "for all time" in after[0] and claims[after[0]] == "certified"
    scenario = load_scenario(name, check_demos=False)
    controller = load(out / "controller.json")
    assert scenario.terminal == "hold" and controller.terminal is not None
    decay, fit, failures = verify_terminal(scenario, controller)  # the certify stage's re-check
    assert not failures and decay > 0 and 0 <= fit <= 1
    ends = np.array([tr.x_ref[-1] for tr in controller.trajectories])  # (k, n)
    speeds = np.abs(ends[:, [scenario.state_names.index(v) for v in ("vx", "vy")]])
    assert speeds.max() <= 0.5  # goal.bounds at T, which the optimizer keeps
    # the Monte Carlo stage continued its runs past T, none left Goal
    assert summary["montecarlo"]["failures"]["after_T"] == 0
    assert "continued to T + 10 s stayed in Goal" in summary["montecarlo"]["message"]


@pytest.mark.parametrize("name", [HOLD])
def test_a_level_too_large_for_goal_fails_the_recheck(synthesis, name, tmp_path):
    _, out = synthesis(name)
    document = json.loads((out / "controller.json").read_text())
    document["terminal"]["level"] *= 25.0  # radius x5: leaves Goal and clips
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(document))
    result = certify_controller(load_scenario(name, check_demos=False), path)
    assert not result.success and any("terminal" in f for f in result.failures)


@pytest.mark.parametrize("name", [HOLD])
def test_the_numpy_controller_flown_past_T_stays_in_goal(synthesis, name):
    _, out = synthesis(name)
    scenario = load_scenario(name, check_demos=False)
    controller = load(out / "controller.json")
    terminal = controller.terminal
    assert terminal is not None
    rng = np.random.default_rng(7)
    x0 = scenario.init_lower + (scenario.init_upper - scenario.init_lower) * rng.random((5, 4))
    index, ratio = controller.select(x0)
    assert np.all(ratio < 1)
    for start, i in zip(x0, index, strict=True):
        T = float(controller.horizons(np.array([i]))[0])
        x, t, worst_level, in_goal = start.copy(), 0.0, 0.0, True
        rows = np.array([i])

        def f(t: float, x: np.ndarray, rows: np.ndarray = rows) -> np.ndarray:
            return scenario.dynamics.f(x, controller(t, x[None], rows)[0])

        while t < T + PAST_T:  # plain RK4 with the input re-evaluated at every stage
            h = min(STEP, T + PAST_T - t)
            k1 = f(t, x)
            k2 = f(t + h / 2, x + h / 2 * k1)
            k3 = f(t + h / 2, x + h / 2 * k2)
            k4 = f(t + h, x + h * k3)
            x, t = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), t + h
            if t > T + 1e-9:
                worst_level = max(worst_level, float(terminal.value(x)) / terminal.level)
                in_goal &= bool(scenario.in_goal(x))
        assert in_goal and worst_level <= 1.0, (start, worst_level)
        assert np.linalg.norm(x - terminal.x_eq) < 0.1  # caught: 10 s after T it is near x_eq
