"""The uncertified comparison of ``make bench`` (issue 16): its constraints are the scenario's real
limits with nothing reserved for a certificate."""

from __future__ import annotations

import numpy as np
import pytest

from bench.bench_known_floor import ASKED
from bench.uncertified import uncertainty_corners, uncertified_constraints
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


def test_uncertainty_corners_are_every_admissible_extreme_model() -> None:
    """issue 29's asked bound on quadrotor_hill: 2 parameters x 2 pushed speeds, 16 corners, each
    inside the bound, no two alike."""
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    parameters, disturbance = ASKED["quadrotor_hill"]
    corners = uncertainty_corners(scenario, parameters, disturbance)
    assert len(corners) == 16
    names = scenario.uncertainty.parameter_names
    lower = np.array([parameters[name][0] for name in names])
    upper = np.array([parameters[name][1] for name in names])
    box = np.array([disturbance.get(name, 0.0) for name in scenario.state_names])
    for corner in corners:
        assert np.all((corner.parameters == lower) | (corner.parameters == upper))
        np.testing.assert_array_equal(np.abs(corner.push), box)
    keys = {(*c.parameters.tolist(), *c.push.tolist()) for c in corners}
    assert len(keys) == 16
    assert corners[0].describe(scenario) == "wX=-1, m=0.95, vX'+=-0.25, vY'+=-0.25"


def test_uncertainty_corners_refuse_parameters_the_scenario_does_not_declare() -> None:
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    with pytest.raises(ValueError, match="exactly"):
        uncertainty_corners(scenario, {"wX": (-1.0, 0.0)}, {"vX": 0.25})


def test_a_known_corner_flies_the_parametric_model_plus_its_push() -> None:
    """The floor's NLP integrates f(x, (u, p)) + push: CasADi's field against the scenario's own
    parametric dynamics at random states."""
    ca = pytest.importorskip("casadi")
    from bench.bench_optimize import _casadi_field

    scenario = load_scenario("quadrotor_hill", check_demos=False)
    corner = uncertainty_corners(scenario, *ASKED["quadrotor_hill"])[5]
    x, u = ca.SX.sym("x", scenario.n), ca.SX.sym("u", scenario.m)
    field = ca.Function("f", [x, u], [_casadi_field(scenario, x, u, corner)])
    rng = np.random.default_rng(3)
    for _ in range(5):
        xv, uv = rng.normal(size=scenario.n), rng.uniform(5, 12, size=scenario.m)
        expected = scenario.uncertainty.parametric.f(xv, np.concatenate([uv, corner.parameters]))
        np.testing.assert_allclose(np.ravel(field(xv, uv)), expected + corner.push, rtol=1e-12)
