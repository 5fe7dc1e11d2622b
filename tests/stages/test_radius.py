"""Stage ``radius``: known answers on a planar double integrator beside the half-plane Y <= 0.

With ``Sigma = C P^-1 C^T`` the tube's position ellipse at P-radius ``rho`` reaches
``rho sqrt(n^T Sigma n)`` along a unit normal ``n``, so a stationary point at height ``y0`` has
radius ``y0 / sqrt(Sigma_YY)`` exactly; a moving one loses at most the motion bound
``|W v| h / 2`` (first order in the grid spacing ``h``).
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from pipeline.model.geometry import distance
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS
from stages.feedback import design_feedback
from stages.radius import robustness_radius

# A coupled metric and gain (states X, Y, vX, vY; inputs aX, aY).
P = np.array(
    [
        [2.0, 0.3, 0.4, 0.1],
        [0.3, 1.5, 0.1, 0.5],
        [0.4, 0.1, 1.2, 0.2],
        [0.1, 0.5, 0.2, 1.0],
    ]
)
K = -np.array([[1.0, 0.0, 1.5, 0.0], [0.0, 1.0, 0.0, 1.5]])
RATE = 0.5
SIGMA = np.linalg.inv(P)[:2, :2]
W = np.linalg.inv(scipy.linalg.sqrtm(SIGMA).real)


def tube(region=None):
    return Tube(
        K=K,
        P=P,
        rate=RATE,
        region=region or {},
        state_names=("X", "Y", "vX", "vY"),
        input_names=("aX", "aY"),
        position_index=(0, 1),
    )


def run(scenario, x0, us, substeps=4, region=None):
    x0, us = np.array(x0, float), np.array(us, float)
    trajectory = simulate(scenario.dynamics, x0, us, 0.1, substeps)
    return robustness_radius(scenario, tube(region), trajectory)


def test_stationary_beside_half_plane_is_exact(double_integrator):
    scenario = double_integrator()
    result = run(scenario, [0.5, 2.0, 0, 0], np.zeros((30, 2)))
    exact = 2.0 / np.sqrt(SIGMA[1, 1])
    assert result.radius == pytest.approx(exact, rel=1e-12)
    assert result.binding == "unsafe 'wall'" and result.binding_time == 0.0
    assert result.success
    assert result.position_clearance == pytest.approx(
        exact * np.sqrt(np.linalg.eigvalsh(SIGMA)[-1])
    )
    assert result.nominal_clearance == pytest.approx(2.0)


@pytest.mark.parametrize("substeps", [2, 4, 8])
def test_moving_parallel_loses_exactly_the_motion_bound(double_integrator, substeps):
    scenario = double_integrator()
    v = 1.5
    result = run(scenario, [0.0, 2.0, v, 0.0], np.zeros((30, 2)), substeps=substeps)
    exact = 2.0 / np.sqrt(SIGMA[1, 1])
    h = 0.1 / substeps
    slack = np.linalg.norm(W @ [v, 0.0]) * h / 2
    assert result.radius == pytest.approx(exact - slack, rel=1e-9)  # first order in h
    assert result.radius < exact


def test_approach_and_retreat_binds_at_the_known_time(double_integrator):
    """Y(t) = 3 - 2 t + t^2 / 2 (aY = 1): Y(t) e^{t/2} is smallest at t* = sqrt(2)."""
    scenario = double_integrator()
    us = np.column_stack([np.zeros(40), np.ones(40)])
    result = run(scenario, [0.0, 3.0, 0.0, -2.0], us, substeps=20)
    t_star = np.sqrt(2.0)
    exact = (3 - 2 * t_star + t_star**2 / 2) * np.exp(RATE * t_star) / np.sqrt(SIGMA[1, 1])
    assert exact - 0.01 <= result.radius <= exact
    assert result.binding == "unsafe 'wall'"
    assert abs(result.binding_time - t_star) <= 0.05


def test_goal_at_the_final_time(double_integrator):
    """Goal [4, 6] x [1, 3], the flight ends at rest at (5.2, 2.5): the final disk in W
    coordinates touches the nearest transformed edge."""
    scenario = double_integrator(goal="[[4, 1], [6, 1], [6, 3], [4, 3]]")
    T = 2.0
    result = run(scenario, [5.2, 2.5, 0, 0], np.zeros((20, 2)))
    edges = [((1, 0), 6 - 5.2), ((-1, 0), 5.2 - 4), ((0, 1), 3 - 2.5), ((0, -1), 2.5 - 1)]
    exact = min(room / np.sqrt(np.array(n) @ SIGMA @ n) for n, room in edges) * np.exp(RATE * T)
    wall = 2.5 / np.sqrt(SIGMA[1, 1])
    assert exact < wall
    assert result.radius == pytest.approx(exact, rel=1e-9)
    assert result.binding == "goal" and result.binding_time == pytest.approx(T)


def test_goal_missed_means_no_tube(double_integrator):
    scenario = double_integrator(goal="[[4, 1], [6, 1], [6, 3], [4, 3]]")
    result = run(scenario, [0.5, 2.5, 0, 0], np.zeros((20, 2)))
    assert result.radius == 0 and not result.success and result.binding == "goal"


def test_input_bound_of_the_tube_input(double_integrator):
    """u_ref + K e stays in [-1, 1]: with aX = 0.4 held, r <= 0.6 / ||K_0 P^-1/2|| at t = 0."""
    scenario = double_integrator()
    us = np.column_stack([np.full(20, 0.4), np.zeros(20)])
    result = run(scenario, [0.0, 50.0, 0, 0], us, region={"aX": (-1.0, 1.0)})
    gain = np.sqrt(K[0] @ np.linalg.inv(P) @ K[0])
    assert result.radius == pytest.approx(0.6 / gain, rel=1e-12)
    assert result.binding == "region 'aX' upper" and result.binding_time == 0.0


def test_operating_region_state(double_integrator):
    """vX = 0.5 held; the region |vX| <= 1 allows r = 0.5 / sqrt((P^-1)_vXvX) at t = 0."""
    scenario = double_integrator()
    result = run(scenario, [0.0, 50.0, 0.5, 0], np.zeros((20, 2)), region={"vX": (-1.0, 1.0)})
    assert result.radius == pytest.approx(0.5 / np.sqrt(np.linalg.inv(P)[2, 2]), rel=1e-12)
    assert result.binding == "region 'vX' upper"


def test_nominal_inside_unsafe_has_no_tube(double_integrator):
    scenario = double_integrator()
    result = run(scenario, [0.0, 1.0, 0.0, -1.0], np.zeros((20, 2)))
    assert result.radius == 0 and not result.success
    assert "no tube" in result.message and result.binding == "unsafe 'wall'"


def test_non_finite_state_is_an_error_naming_it(double_integrator):
    scenario = double_integrator()
    trajectory = simulate(scenario.dynamics, np.array([0.0, 2.0, 0, 0]), np.zeros((5, 2)), 0.1)
    trajectory.dense_xs[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"non-finite state 'Y' at time index 3"):
        robustness_radius(scenario, tube(), trajectory)


def test_with_a_designed_feedback(double_integrator):
    scenario = double_integrator()
    feedback = design_feedback(scenario)
    assert feedback.success, feedback.message
    trajectory = simulate(scenario.dynamics, np.array([0.5, 2.0, 0, 0]), np.zeros((20, 2)), 0.1)
    result = robustness_radius(scenario, feedback.certified_tube, trajectory)
    # Stationary: the wall binds at t = 0 and the position clearance is the height.
    assert result.binding == "unsafe 'wall'"
    sigma_yy = feedback.position_shape[1, 1]
    assert result.radius == pytest.approx(2.0 / np.sqrt(sigma_yy), rel=1e-9)


def test_the_between_grid_bound_holds_on_a_much_finer_grid():
    """The two quadrotor demos that pass closest to the hill, checked on the pipeline's grid
    (16 RK4 substeps per sample): the clearance it certifies is below the clearance seen on an
    8x finer grid, by little."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    feedback = design_feedback(scenario)
    for demo in (scenario.demos[3], scenario.demos[7]):
        coarse = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts, VERIFY_SUBSTEPS)
        certified = robustness_radius(scenario, feedback.certified_tube, coarse).nominal_clearance
        fine = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts, 8 * VERIFY_SUBSTEPS)
        positions = scenario.positions(fine.dense_xs)
        seen = min(float(distance(positions, u).min()) for u in scenario.unsafe.values())
        assert certified <= seen < certified + 0.02, demo.name
