"""Issue 29 item 4: the Monte Carlo stage samples the declared uncertainty.

The controller is double_integrator_hold's session synthesis (a terminal controller: the runs
are flown to T + 10 s). Its scenario is flown with a declared uncertainty written into a copy of
the scenario file, with the accelerations scaled by a parameter ``k`` (nominal 1: the same model
the controller was certified for): ``vx' = k ux + w_vx``, ``vy' = k uy + w_vy``.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.closed_loop import gusts
from pipeline.numerics.closed_loop.rollouts import check_runs_compiled, hold_runs_compiled
from pipeline.numerics.closed_loop.simulate import check_runs, hold_runs
from stages.montecarlo import _uniform_init, validate_closed_loop
from stages.stress import stress_test

HOLD = "double_integrator_hold"


def _declaring(tmp_path: Path, gust: float, k: tuple[float, float] = (0.9, 1.1)) -> Scenario:
    """double_integrator_hold with ``vx' = k ux``, ``vy' = k uy`` (k = 1 nominal), declaring
    ``k`` in ``k`` and a gust ``|w| <= gust`` on vx', vy'."""
    folder = tmp_path / f"declared_{gust:g}_{k[0]:g}_{k[1]:g}"
    shutil.copytree(Path("scenarios") / HOLD, folder)
    path = folder / "scenario.yaml"
    text = path.read_text().replace("  vx: ux\n  vy: uy\n", "  vx: k*ux\n  vy: k*uy\n")
    text = text.replace("position: [x, y]\n", "position: [x, y]\nparameters: {k: 1.0}\n")
    text += (
        "\nuncertainty:\n"
        f"  disturbance: {{vx: {gust}, vy: {gust}}}\n"
        f"  parameters: {{k: [{k[0]}, {k[1]}]}}\n"
    )
    path.write_text(text)
    return load_scenario(folder, check_demos=False)


def _is_corner(draws: gusts.Draws, uncertainty: Uncertainty) -> np.ndarray:
    """(B,) True where every parameter is at an end of its interval and every gust of a
    disturbed state at +-its bound."""
    at_end = np.isin(draws.parameters, uncertainty.parameter_lower) | np.isin(
        draws.parameters, uncertainty.parameter_upper
    )
    disturbed = uncertainty.disturbance > 0
    bang = np.abs(draws.gusts[..., disturbed]) == uncertainty.disturbance[disturbed]
    return at_end.all(axis=1) & bang.all(axis=(1, 2))


def test_draws_stay_in_the_declared_boxes_and_bang_bang_runs_reach_their_corners(tmp_path):
    scenario = _declaring(tmp_path, 0.05)
    uncertainty = scenario.uncertainty
    rng = np.random.default_rng(3)
    worst = gusts.corners(uncertainty, np.array([[1.0]]), rng.choice([-1.0, 1.0], (1, 9, 4)))
    draws = gusts.sample(uncertainty, rng, 4000, horizon=20.0, worst=worst)
    assert draws.gusts.shape == (4000, gusts.gust_count(20.0), 4) == (4000, 41, 4)
    assert np.all(draws.parameters >= 0.9) and np.all(draws.parameters <= 1.1)
    assert np.all(np.abs(draws.gusts) <= uncertainty.disturbance)
    assert np.all(draws.gusts[..., :2] == 0)  # x', y' declare no gust
    corner = _is_corner(draws, uncertainty)
    as_worst = np.all(draws.gusts[:, :9] == worst.gusts, axis=(1, 2))
    # a quarter at random corners, a quarter the worst case (at corners too), half uniform
    assert 0.45 < corner.mean() < 0.55 and 0.2 < as_worst.mean() < 0.3
    assert np.all(corner[as_worst])
    assert np.all(draws.gusts[as_worst, 9:] == worst.gusts[0, -1])  # its last gust held
    uniform = ~corner
    assert np.ptp(draws.parameters[uniform]) > 0.19  # spread over the interval
    # both signs at every corner: each parameter end and each gust sign is reached
    assert set(np.unique(draws.parameters[corner & ~as_worst])) == {0.9, 1.1}
    assert set(np.unique(draws.gusts[corner][..., 2:])) == {-0.05, 0.05}


@pytest.mark.xdist_group("synthesis-double_integrator_hold")  # its session run
def test_gusty_parametric_runs_agree_with_the_numpy_oracle(synthesis, tmp_path):
    """Kernel and oracle fly the same parameters and gusts: margins to T, and past T, to
    1e-9; the gusts change the runs (they are flown, not ignored)."""
    _, out = synthesis(HOLD)
    scenario = _declaring(tmp_path, 0.1)
    from pipeline.controller import load

    controller = load(out / "controller.json")
    rng = np.random.default_rng(5)
    x0 = _uniform_init(scenario, rng, 24)
    draws = gusts.sample(scenario.uncertainty, rng, 24, horizon=30.0)
    oracle = check_runs(scenario, controller, x0, draws=draws)[0]
    compiled = check_runs_compiled(scenario, controller, x0, draws=draws)
    for name in ("clearance", "goal_margin", "input_slack", "tube_tightness"):
        np.testing.assert_allclose(
            getattr(compiled, name), getattr(oracle, name), rtol=1e-9, atol=1e-9, err_msg=name
        )
    nominal = check_runs_compiled(scenario, controller, x0)
    assert np.abs(nominal.goal_margin - compiled.goal_margin).max() > 1e-3
    held = hold_runs(scenario, controller, x0, draws=draws)
    held_compiled = hold_runs_compiled(scenario, controller, x0, draws=draws)
    for name in ("final_state", "level_ratio", "input_slack", "clearance", "path_goal_margin"):
        np.testing.assert_allclose(
            getattr(held_compiled, name), getattr(held, name), rtol=1e-9, atol=1e-9, err_msg=name
        )


@pytest.mark.xdist_group("synthesis-double_integrator_hold")  # its session run
def test_an_empty_or_zero_width_uncertainty_flies_the_exact_model(synthesis, tmp_path):
    """No declaration: the starts and runs of the exact model (the oracle on the same streams,
    no draws); a declaration of zero width (k in [1, 1], no gust) flies the same runs."""
    _, out = synthesis(HOLD)
    path = out / "controller.json"
    scenario = load_scenario(HOLD, check_demos=False)
    assert scenario.uncertainty.empty
    result = validate_closed_loop(scenario, path, samples=300, chunk=150, seed=2)
    from pipeline.controller import load

    controller = load(path)
    x0 = np.vstack(
        [
            _uniform_init(scenario, np.random.default_rng(stream), 150)
            for stream in np.random.SeedSequence(2).spawn(2)
        ]
    )
    oracle = check_runs(scenario, controller, x0)[0]
    assert result.min_clearance == pytest.approx(oracle.clearance.min(), abs=1e-12)
    assert result.min_goal_margin == pytest.approx(oracle.goal_margin.min(), abs=1e-12)
    assert result.max_tube_tightness == pytest.approx(oracle.tube_tightness.max(), abs=1e-12)
    assert result.failures == dict.fromkeys(
        ("unsafe", "goal", "clipping", "tube", "non_finite", "uncovered", "after_T"), 0
    )
    assert result.falsification.worst_draws is None
    zero = _declaring(tmp_path, 0.0, k=(1.0, 1.0))
    assert not zero.uncertainty.empty  # k is declared: the runs draw (its one value)
    flown = validate_closed_loop(zero, path, samples=300, chunk=150, seed=2)
    assert "under the declared uncertainty" in flown.message
    assert flown.min_clearance == pytest.approx(result.min_clearance, abs=1e-12)
    assert flown.min_goal_margin == pytest.approx(result.min_goal_margin, abs=1e-12)
    assert flown.success and result.success


@pytest.mark.xdist_group("synthesis-double_integrator_hold")  # its session run
def test_a_gust_larger_than_the_controller_holds_fails_counted_runs(synthesis, tmp_path):
    """The controller is certified for the exact model: under a small declared gust and +-10%
    on k every run (to T + 10 s) stays in Goal; under a gust of 0.3 m/s^2 runs fail and are
    counted (the verdict's count is the failed starts); the falsification search finds its
    worst case at the boxes' corners."""
    _, out = synthesis(HOLD)
    path = out / "controller.json"
    small = validate_closed_loop(_declaring(tmp_path, 0.02), path, samples=400, chunk=200)
    assert small.success, small.message
    assert small.hold_runs == 400
    large_scenario = _declaring(tmp_path, 0.3)
    large = validate_closed_loop(large_scenario, path, samples=400, chunk=200)
    assert not large.success
    failing = len(large.failed_x0)
    assert 0 < failing <= 400 and f"{failing} of 400" in large.message
    assert "tube" not in large.failures  # the exact model's decay is not claimed under gusts
    assert small.tube_final.size == large.tube_final.size == 0  # nor reported (summary: none)
    assert _exact_run_reports_the_decay(path)
    worst = large.falsification.worst_draws
    assert worst is not None and large.falsification.worst_margin < 0
    assert _is_corner(worst, large_scenario.uncertainty).all()


@pytest.mark.xdist_group("synthesis-double_integrator_hold")  # its session run
def test_stress_flies_twice_the_declared_uncertainty(synthesis, tmp_path):
    """--stress with a declaration: 2x its gust and intervals (0.05 -> 0.1 m/s^2, k in
    [0.8, 1.2]), out of the certificate: the declared bound passes the Monte Carlo stage while
    the stress campaign beyond it reports failures."""
    _, out = synthesis(HOLD)
    path = out / "controller.json"
    scenario = _declaring(tmp_path, 0.05)
    declared = validate_closed_loop(scenario, path, samples=400, chunk=200)
    assert declared.success, declared.message
    stress = stress_test(scenario, path, samples=300, seed=1)
    assert stress.beyond_declared == 2.0 and "2x" in stress.message
    assert stress.with_feedback.failed_fraction > 0
    assert set(stress.with_feedback.failures) == {
        "unsafe",
        "goal",
        "clipping",
        "non_finite",
        "after_T",
    }
    widened = dataclasses.replace(scenario, uncertainty=scenario.uncertainty.scaled(2.0))
    assert widened.uncertainty.disturbance[2] == pytest.approx(0.1)
    assert tuple(widened.uncertainty.parameter_lower) == pytest.approx((0.8,))


def _exact_run_reports_the_decay(path) -> bool:
    """The exact model's run still reports the decay used (its tube ratio)."""
    from pipeline.model.scenario import load_scenario

    exact = load_scenario("double_integrator_hold", check_demos=False)
    return validate_closed_loop(exact, path, samples=60, chunk=60).tube_final.size == 60
