"""Stages ``montecarlo`` and ``stress`` fly a ``safety-controller/2`` file (one funnel per
trajectory) as they fly ``/1``: the runs from starts inside the funnel never fail, the starts
outside it are counted as uncovered, and the stress campaign compares the funnel's feedback with
the reference flown open loop."""

from __future__ import annotations

from stages.montecarlo import validate_closed_loop
from stages.stress import stress_test


def test_monte_carlo_and_stress_fly_a_funnel_file(quadrotor_funnel_artifact):
    scenario, path = quadrotor_funnel_artifact
    result = validate_closed_loop(scenario, path, samples=400, chunk=200, seed=3)
    uncovered = result.failures.pop("uncovered")
    assert 0 < uncovered < 400  # one funnel covers part of Init
    assert result.failures == dict.fromkeys(result.failures, 0), result.message
    assert result.min_clearance > 0
    stress = stress_test(scenario, path, samples=60, seed=1)
    assert stress.success, stress.message
    assert stress.with_feedback.samples == stress.without_feedback.samples == 60
    assert stress.with_feedback.failed_fraction < stress.without_feedback.failed_fraction
