"""The uncertified comparison of ``make bench`` (issue 16): its constraints are the scenario's real
limits with nothing reserved for a certificate."""

from __future__ import annotations

import numpy as np

from bench.uncertified import uncertified_constraints
from pipeline.model.scenario import load_scenario


def test_uncertified_constraints_are_the_scenarios_own_limits() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    constraints = uncertified_constraints(scenario)
    np.testing.assert_array_equal(constraints.input_lower, scenario.input_lower)
    np.testing.assert_array_equal(constraints.input_upper, scenario.input_upper)
    assert constraints.unsafe_margin == scenario.clearance  # d, no tube
    assert constraints.region == {"theta": (-0.8, 0.8)}  # state_bounds, not the operating region
    assert constraints.goal_region.equals(scenario.goal)  # Goal itself, not shrunk
    grid = constraints.grid(4, 2)  # no time-varying margin on top
    assert np.all(grid.input_lower == scenario.input_lower)
    assert np.all(grid.unsafe_margin == scenario.clearance)


def test_at_rest_asks_the_design_equilibrium_in_every_state_but_the_position() -> None:
    """quadrotor_hill_flythrough arrives hovering: theta, vX, vY, omega at 0
    (feedback.reference_state),
    X and Y anywhere in Goal."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    constraints = uncertified_constraints(scenario, at_rest=True)
    named = [scenario.state_names[i] for i in constraints.goal_index]
    assert sorted(named) == ["omega", "theta", "vX", "vY"]
    assert np.all(constraints.goal_lower == 0) and np.all(constraints.goal_upper == 0)
