"""The compiled closed-loop kernel against its NumPy oracle: same margins to 1e-9, same failures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from pipeline.numerics.closed_loop import check_runs
from pipeline.numerics.rollouts import check_runs_compiled

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
        np.testing.assert_allclose(found, expected, rtol=0, atol=1e-9, err_msg=name)
    for kind, mask in numpy_checks.failures().items():
        assert np.array_equal(mask, compiled_checks.failures()[kind]), kind


@pytest.mark.parametrize("widen", [0.0, 0.5])
def test_compiled_rollouts_match_the_numpy_oracle(synthesized, widen):
    """Seeded starts in Init, and in Init widened by half its width (uncovered starts, larger
    errors): every margin agrees to 1e-9."""
    _, out = synthesized
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    controller = load(out / "controller.json")
    x0 = _starts(scenario, 120, seed=7, widen=widen)
    _assert_same(
        check_runs(scenario, controller, x0)[0], check_runs_compiled(scenario, controller, x0)
    )


def test_compiled_rollouts_report_the_same_failures_of_a_broken_gain(synthesized, tmp_path):
    """A destabilising gain: the kernel finds the same failing runs as the oracle, and some."""
    _, out = synthesized
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    document = json.loads((out / "controller.json").read_text())
    document["feedback"]["K"] = (-3.0 * np.asarray(document["feedback"]["K"])).tolist()
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(document))
    controller = load(path)
    x0 = _starts(scenario, 60, seed=3)
    numpy_checks = check_runs(scenario, controller, x0)[0]
    _assert_same(numpy_checks, check_runs_compiled(scenario, controller, x0))
    assert any(mask.any() for mask in numpy_checks.failures().values())
