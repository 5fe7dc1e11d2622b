"""The compiled closed-loop kernel against its NumPy oracle: same margins to 1e-9, same failures,
for a ``safety-controller/1`` file (constant K, P) and a ``/2`` file (K per interval, P(t))."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from pipeline.numerics.closed_loop.rollouts import check_runs_compiled
from pipeline.numerics.closed_loop.simulate import check_runs
from tests.helpers.controller_files import scale_gains

MARGINS = ("clearance", "goal_margin", "input_slack", "tube_tightness", "tube_final")


def _starts(scenario, count, seed, widen=0.0):
    """``count`` starts uniform on Init widened by ``widen`` of its width on each side."""
    lo, hi = scenario.init_lower, scenario.init_upper
    span = hi - lo
    u = np.random.default_rng(seed).uniform(-widen, 1 + widen, size=(count, scenario.n))
    return lo + span * u


def _assert_same(numpy_checks, compiled_checks):
    assert np.array_equal(numpy_checks.finite, compiled_checks.finite)
    assert np.array_equal(numpy_checks.covered, compiled_checks.covered)
    for name in MARGINS:
        expected, found = getattr(numpy_checks, name), getattr(compiled_checks, name)
        # 1e-9, relative for margins above 1 (a destabilised gain's tube ratio reaches 3e4,
        # where 1e-9 absolute is ~100 ulps of RK4 round-off)
        np.testing.assert_allclose(found, expected, rtol=1e-9, atol=1e-9, err_msg=name)
    for kind, mask in numpy_checks.failures().items():
        assert np.array_equal(mask, compiled_checks.failures()[kind]), kind


@pytest.mark.parametrize("widen", [0.0, 0.5])
def test_compiled_rollouts_match_the_numpy_oracle(synthesized, widen):
    """Seeded starts in Init, and in Init widened by half its width (uncovered starts, larger
    errors): every margin agrees to 1e-9."""
    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    controller = load(out / "controller.json")
    x0 = _starts(scenario, 120, seed=7, widen=widen)
    _assert_same(
        check_runs(scenario, controller, x0)[0], check_runs_compiled(scenario, controller, x0)
    )


def test_compiled_rollouts_report_the_same_failures_of_a_broken_gain(synthesized, tmp_path):
    """A destabilising gain: the kernel finds the same failing runs as the oracle, and some."""
    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    document = json.loads((out / "controller.json").read_text())
    scale_gains(document, -3.0)
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(document))
    controller = load(path)
    x0 = _starts(scenario, 60, seed=3)
    numpy_checks = check_runs(scenario, controller, x0)[0]
    _assert_same(numpy_checks, check_runs_compiled(scenario, controller, x0))
    assert any(mask.any() for mask in numpy_checks.failures().values())


def _variant(out, tmp_path, change):
    document = json.loads((out / "controller.json").read_text())
    change(document)
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(document))
    return load(path)


def test_held_feedback_matches_the_numpy_oracle(synthesized, tmp_path):
    """The law held every 0.01 s (zero-order hold): kernel and oracle agree to 1e-9, and the
    held runs differ from the continuous ones (the hold is simulated, not ignored)."""
    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    controller = _variant(out, tmp_path, lambda d: d.update(feedback_period=0.01))
    x0 = _starts(scenario, 60, seed=11, widen=0.2)
    held = check_runs(scenario, controller, x0)[0]
    _assert_same(held, check_runs_compiled(scenario, controller, x0))
    continuous = check_runs_compiled(scenario, load(out / "controller.json"), x0)
    assert np.abs(held.input_slack - continuous.input_slack).max() > 1e-6


@pytest.mark.parametrize("period", [0.0, 0.02])
def test_runs_continued_past_T_match_the_numpy_oracle(synthesized, tmp_path, period):
    """A terminal law at hover added to the quadrotor's file: the continuation 10 s past T on
    the kernel agrees with the oracle's (final state, V / level, slack, clearance, Goal), also
    when continued from the states at T the checks kept."""
    from pipeline.numerics.closed_loop.rollouts import hold_runs_compiled
    from pipeline.numerics.closed_loop.simulate import hold_runs
    from pipeline.numerics.terminal.design import design_terminal
    from pipeline.numerics.terminal.equilibrium import equilibrium

    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    x_eq, _ = equilibrium(scenario)
    design = design_terminal(scenario, np.zeros((2, 6)), np.eye(6), [x_eq], [0.0])
    block = {
        "x_eq": design.x_eq.tolist(),
        "u_eq": design.u_eq.tolist(),
        "K": design.K.tolist(),
        "P": design.P.tolist(),
        "level": 1e4 * design.check.level,  # large: most continuations stay inside
    }
    controller = _variant(out, tmp_path, lambda d: d.update(terminal=block, feedback_period=period))
    x0 = _starts(scenario, 24, seed=5)
    oracle = hold_runs(scenario, controller, x0, duration=10.0)
    compiled = hold_runs_compiled(scenario, controller, x0, duration=10.0)
    at_T = check_runs(scenario, controller, x0)[0].final_state
    np.testing.assert_allclose(
        check_runs_compiled(scenario, controller, x0).final_state, at_T, rtol=0, atol=1e-9
    )
    continued = hold_runs_compiled(scenario, controller, x0, duration=10.0, ends=at_T)
    with pytest.raises(ValueError, match=r"ends \(23, 6\) for x0 \(24, 6\)"):
        hold_runs_compiled(scenario, controller, x0, duration=10.0, ends=at_T[1:])
    np.testing.assert_allclose(compiled.final_state, oracle.final_state, rtol=0, atol=1e-9)
    for name in (
        "level_ratio",
        "input_slack",
        "clearance",
        "final_goal_margin",
        "path_goal_margin",
        "bounds_margin",
    ):
        for kernel in (compiled, continued):
            np.testing.assert_allclose(
                getattr(kernel, name), getattr(oracle, name), rtol=1e-9, atol=1e-9, err_msg=name
            )
    assert np.isfinite(oracle.final_state).all()


@pytest.mark.parametrize("gain", [1.0, -3.0])
def test_funnel_rollouts_match_the_numpy_oracle(funnel_artifact, tmp_path, gain):
    """safety-controller/2 (time-varying K[k] and tube metric P(t)): seeded starts in Init
    widened by half its width agree to 1e-9; the funnel's own gain keeps every covered run in
    its tube (ratio ||e(t)||_P(t) / ||e(0)||_P(0) <= 1), a destabilising one does not."""
    scenario, path = funnel_artifact
    document = json.loads(path.read_text())
    for item in document["trajectories"]:
        item["K"] = (gain * np.asarray(item["K"])).tolist()
    variant = tmp_path / "controller.json"
    variant.write_text(json.dumps(document))
    controller = load(variant)
    assert controller.funnel and controller.K is None
    x0 = _starts(scenario, 80, seed=13, widen=0.5)
    numpy_checks = check_runs(scenario, controller, x0)[0]
    _assert_same(numpy_checks, check_runs_compiled(scenario, controller, x0))
    covered = numpy_checks.covered
    assert 0 < covered.sum() < len(x0)
    failures = numpy_checks.failures()
    if gain == 1.0:
        assert not any(mask[covered].any() for mask in failures.values())
        assert numpy_checks.tube_tightness[covered].max() <= 1 + 1e-6
    else:
        assert failures["tube"][covered].any()


def test_quadrotor_funnel_rollouts_match_the_numpy_oracle(quadrotor_funnel_artifact):
    """A nonlinear funnel (quadrotor_hill_flythrough, one demo): kernel and oracle agree to 1e-9 on
    starts
    around the funnel's start, and the covered runs stay in their funnel and clear of the hill."""
    scenario, path = quadrotor_funnel_artifact
    controller = load(path)
    centre = controller.trajectories[0].x0
    rng = np.random.default_rng(17)
    x0 = centre + rng.uniform(-1.5, 1.5, size=(40, scenario.n)) * (scenario.init_upper > 0)
    x0[:, 2:] = 0.0  # at rest, as Init
    numpy_checks = check_runs(scenario, controller, x0)[0]
    _assert_same(numpy_checks, check_runs_compiled(scenario, controller, x0))
    covered = numpy_checks.covered
    assert 0 < covered.sum() < len(x0)
    assert not any(mask[covered].any() for mask in numpy_checks.failures().values())
