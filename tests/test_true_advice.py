"""Advice that is true (issue 31, item 4): more demonstrations are asked for only when a few
can close a coverage gap (and how many); otherwise the feedback is named as the limit with a fix
in the scenario file's fields; the optimizer's margin errors name fields the file has."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.numerics.optimize.margins import MarginProfile
from pipeline.numerics.optimize.penalties import MarginError, build_constraints
from pipeline.numerics.verify.cover import balls_to_cover
from pipeline.runtime.verdict import Evidence
from stages.coverage import cover_init
from stages.feedback import design_feedback
from stages.radius import RadiusResult


def test_balls_to_cover_a_square_with_disks():
    """A disk of radius r holds a square of side sqrt(2) r: area 2 r^2."""
    P, lower, upper = np.eye(2), np.zeros(2), np.ones(2)
    assert balls_to_cover(P, 0.5, lower, upper, 1.0) == 2
    assert balls_to_cover(P, 0.05, lower, upper, 1.0) == 200
    assert balls_to_cover(P, 0.05, lower, upper, 0.5) == 100
    assert balls_to_cover(P, 0.05, lower, upper, 0.0) == 0
    assert balls_to_cover(P, 10.0, lower, upper, 1.0) == 1


def _evidence(scenario, feedback, radius: float) -> Evidence:
    starts = np.array([d.x0 for d in scenario.demos])
    radii = np.full(len(starts), radius)
    final = [
        RadiusResult(
            radius=radius, position_clearance=0.0, binding="region 'uy' upper",
            binding_time=0.0, limits={}, nominal_clearance=1.0, success=True, message="",
        )
        for _ in starts
    ]  # fmt: skip
    return Evidence(
        scenario=scenario,
        certificate="constant",
        feedback=feedback,
        covering=None,  # type: ignore[arg-type]
        demo_coverage=None,  # type: ignore[arg-type]
        coverage=cover_init(scenario, feedback, starts, radii),
        optimized=None,  # type: ignore[arg-type]
        final_radii=final,
        controller=None,  # type: ignore[arg-type]
        certification=None,  # type: ignore[arg-type]
        montecarlo=None,  # type: ignore[arg-type]
    )


@pytest.fixture(scope="module")
def double_integrator():
    scenario = load_scenario("double_integrator")
    return scenario, design_feedback(scenario)


def test_a_small_gap_asks_for_a_few_more_demonstrations(double_integrator):
    scenario, feedback = double_integrator
    advice = _evidence(scenario, feedback, 0.25).gap_advice()  # covering radius 0.305
    print(advice)
    assert advice.startswith("; record about ") and "more demonstration" in advice
    assert int(advice.split()[3]) <= len(scenario.demos)


def test_tiny_tubes_name_the_feedback_not_the_demos(double_integrator):
    """The issue's car: radii 1000x below the covering radius; hundreds of demos would not do."""
    scenario, feedback = double_integrator
    advice = _evidence(scenario, feedback, 3e-4).gap_advice()
    print(advice)
    assert "record" not in advice and "new demonstration" not in advice
    assert "the feedback, not the demos, is the limit" in advice
    assert "limited by region 'uy' upper: widen operating_region.uy" in advice
    assert "or let the search tune the feedback (feedback: auto)" in advice  # explicit block


def test_margin_errors_name_fields_of_the_scenario_file():
    scenario = load_scenario("double_integrator")
    profile = MarginProfile.zero(scenario.n, scenario.m)
    wide = MarginProfile(
        clearance=profile.clearance,
        input=np.full_like(profile.input, 5.0),
        state=profile.state,
        final_clearance=profile.final_clearance,
        final_state=profile.final_state,
    )
    with pytest.raises(MarginError) as error:
        build_constraints(scenario, profile=wide)
    print(error.value)
    assert "smaller margin" not in str(error.value)
    assert "widen input_bounds.ux, or lower feedback.rate" in str(error.value)
