"""The penalty cost (eqs. (40)-(42)): its pieces, ``J == 0`` as the feasibility test, the compiled
kernels against the NumPy/shapely reference, and the ``Problem`` API."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline import available_scenarios, load_scenario
from pipeline.model import geometry
from pipeline.model.simulate import simulate
from pipeline.numerics.optimize.penalties import barrier, box_penalty
from pipeline.numerics.optimize.problem import make_problem


@pytest.fixture(scope="module")
def quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


def _hover(scenario, position, N=10):
    """A hover at ``position`` (quadrotor): the start at rest, thrust balancing gravity."""
    x0 = np.zeros(scenario.n)
    x0[list(scenario.position_index)] = position
    return x0, np.tile([9.81, 0.0], (N, 1))


# ---- the penalty functions -------------------------------------------------------------------


def test_barrier_is_zero_with_zero_slope_at_the_margin_and_infinite_inside():
    d = 1.05
    value, slope = barrier(np.array([2.0, d, d * (1 - 1e-15), d * (1 - 1e-9), 0.0]), d)
    assert value[0] == 0.0 and slope[0] == 0.0
    assert value[1] == 0.0 and slope[1] == 0.0
    assert value[2] > 0.0 and value[3] > 0.0  # J == 0 only with the full margin
    assert value[4] == np.inf and slope[4] == 0.0


def test_barrier_matches_the_corrected_eq_42_and_its_derivative():
    d = 1.05
    r = np.linspace(0.01, 0.999, 50) * d
    value, slope = barrier(r, d)
    assert np.allclose(value, -np.log(r / d) + (r - d) / d, rtol=1e-12, atol=1e-15)
    assert np.allclose(slope, -1 / r + 1 / d, rtol=1e-12)
    e = 1e-6
    fd = (barrier(r + e, d)[0] - barrier(r - e, d)[0]) / (2 * e)
    assert np.allclose(fd, slope, rtol=1e-6)


@given(st.floats(1e-6, 1.0 - 1e-12))
@settings(max_examples=200, deadline=None)
def test_barrier_is_positive_and_decreasing_inside_the_margin(t):
    value, slope = barrier(np.array([t, min(t * 1.001, 1.0)]), 1.0)
    assert value[0] > 0.0 and slope[0] < 0.0 and value[1] <= value[0]


def test_box_penalty_is_squared_distance_outside():
    z = np.array([[-1.0, 0.5], [3.0, 2.5], [0.0, 2.0]])
    value, gradient = box_penalty(z, np.array([0.0, 0.0]), np.array([2.0, 2.0]))
    assert np.array_equal(value, [1.0, 1.25, 0.0])
    assert np.array_equal(gradient, [[-2.0, 0.0], [2.0, 1.0], [0.0, 0.0]])


@pytest.mark.parametrize("name", available_scenarios())
def test_compiled_polygon_queries_match_shapely(name):
    scenario = load_scenario(name, check_demos=False)
    problem = make_problem(scenario, x0=scenario.init_lower, u_seed=np.zeros((2, scenario.m)))
    kernels, data, _ = problem._compiled
    rng = np.random.default_rng(0)
    shapes = [(data.goal_vertices, data.goal_ring_start, 0, data.goal_ring_start.size - 1)]
    regions = [problem.constraints.goal_region]
    for S, region in enumerate(scenario.unsafe.values()):
        r0, r1 = data.unsafe_set_rings[S], data.unsafe_set_rings[S + 1]
        shapes.append((data.unsafe_vertices, data.unsafe_ring_start, r0, r1))
        regions.append(region)
    for (V, start, r0, r1), region in zip(shapes, regions, strict=True):
        lo, hi = np.array(region.bounds[:2]) - 2, np.array(region.bounds[2:]) + 2
        points = rng.uniform(lo, hi, size=(300, 2))
        distance = geometry.distance(points, region)
        nearest = geometry.nearest_points(points, region)
        inside = geometry.contains(region, points)
        for p, r, c, i in zip(points, distance, nearest, inside, strict=True):
            got_inside, got_r, cx, cy = kernels.polygon_query(p[0], p[1], V, start, r0, r1)
            assert got_inside == i
            if not i:
                assert got_r == pytest.approx(r, rel=1e-12, abs=1e-12)
                assert np.allclose([cx, cy], c, atol=1e-9)


# ---- J == 0 is the feasibility test ---------------------------------------------------------


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_cost_is_exactly_zero_when_every_constraint_holds(quadrotor, backend):
    x0, u = _hover(quadrotor, [19.0, 2.5])  # ModGoal's centre, 2.5 above the ground
    problem = make_problem(quadrotor, x0=x0, u_seed=u, backend=backend)
    assert problem.cost(u) == 0.0
    J, q = problem.cost_and_gradient(u)
    assert J == 0.0 and not q.any()
    frozen = u.copy()
    frozen.flags.writeable = False  # e.g. a controller file's u_ref: read, never written
    assert problem.cost(frozen) == 0.0 and problem.cost_and_gradient(frozen)[0] == 0.0


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize(
    "case",
    ["input bound", "input margin", "operating region", "region margin", "goal", "unsafe"],
)
def test_cost_is_positive_when_one_constraint_fails(quadrotor, backend, case):
    x0, u = _hover(quadrotor, [19.0, 2.5])
    options: dict = {}
    if case == "input bound":
        u[3, 0] = 15.0  # above 14.9 (eq. (40))
    elif case == "input margin":
        options["input_margin"] = [5.2, 0.0]  # u1 in [5.2, 9.7]: the hover's 9.81 is outside
    elif case == "operating region":
        u[3, 0] = 4.9  # below the region's u1 >= 5
    elif case == "region margin":
        options["region_margin"] = {"u1": 2.45}  # u1 in [7.45, 12.45]
        u[3, 0] = 7.4
    elif case == "goal":
        x0, u = _hover(quadrotor, [17.5, 2.5])  # inside Goal, not inside ModGoal
    elif case == "unsafe":
        options["eps_d"] = 1.6  # d' = 2.6 > 2.5, the height above the ground
    problem = make_problem(quadrotor, x0=x0, u_seed=u, backend=backend, **options)
    assert 0.0 < problem.cost(u) < np.inf


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_cost_is_infinite_when_the_grid_enters_unsafe(quadrotor, backend):
    x0, u = _hover(quadrotor, [8.0, 5.0], N=15)
    u[:, 0] = 0.0  # free fall onto the hill
    problem = make_problem(quadrotor, x0=x0, u_seed=u, backend=backend)
    assert problem.cost(u) == np.inf
    J, q = problem.cost_and_gradient(u, method="sensitivity")
    assert J == np.inf and np.all(np.isfinite(q))


def test_penalties_between_samples_are_seen(quadrotor):
    """A dip below the margin between two samples is caught by the intermediate points."""
    x0, u = _hover(quadrotor, [19.0, 2.9], N=4)
    u[:3, 0] = [5.0, 14.9, 14.9]  # drop, recover: lowest between samples 1 and 2
    problem = make_problem(quadrotor, x0=x0, u_seed=u, penalty_points=7)
    heights = problem.trajectory(u).dense_xs[:, 1]  # = distance to the flat ground at X = 19
    lowest_sample = heights[:: problem.substeps].min()
    assert heights.min() < lowest_sample
    eps_d = 0.5 * (heights.min() + lowest_sample) - quadrotor.clearance
    between = make_problem(quadrotor, x0=x0, u_seed=u, penalty_points=7, eps_d=eps_d)
    samples_only = make_problem(quadrotor, x0=x0, u_seed=u, penalty_points=0, eps_d=eps_d)
    assert problem.cost(u) == samples_only.cost(u) == 0.0
    assert between.cost(u) > 0.0


# ---- compiled against the reference --------------------------------------------------------


@pytest.mark.parametrize("name", available_scenarios())
@pytest.mark.parametrize("penalty_points", [0, 3])
def test_compiled_cost_and_trajectory_match_the_numpy_reference(name, penalty_points):
    scenario = load_scenario(name, check_demos=False)
    x0 = 0.5 * (scenario.init_lower + scenario.init_upper)
    rng = np.random.default_rng(1)
    span = scenario.input_upper - scenario.input_lower
    u = 0.5 * (scenario.input_lower + scenario.input_upper) + 0.2 * span * rng.normal(size=(12, 2))
    kwargs = dict(x0=x0, u_seed=u, penalty_points=penalty_points, eps_d=3.0)
    compiled = make_problem(scenario, **kwargs)
    reference = make_problem(scenario, backend="numpy", **kwargs)
    expected = simulate(scenario.dynamics, x0, u, scenario.Ts, penalty_points + 1)
    assert np.allclose(compiled.trajectory(u).dense_xs, expected.dense_xs, rtol=1e-13, atol=1e-12)
    assert np.array_equal(compiled.trajectory(u).ts, expected.ts)
    J, J_ref = compiled.cost(u), reference.cost(u)
    assert J > 0.0
    assert J == pytest.approx(J_ref, rel=1e-12) or J == J_ref == np.inf


# ---- the Problem API -----------------------------------------------------------------------


def test_demo_problem_and_horizons():
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    if not scenario.demos:
        pytest.skip("no demos yet")
    demo = scenario.demos[0]
    problem = make_problem(scenario, demo=0)
    assert problem.N == len(demo.us) and np.array_equal(problem.x0, demo.x0)
    assert np.array_equal(problem.u_seed, demo.us)
    short = make_problem(scenario, demo=0, N=40)
    assert short.N == 40 and np.array_equal(short.u_seed, demo.us[:40])
    long = problem.with_horizon(problem.N + 5)
    assert long.N == problem.N + 5 and np.array_equal(
        long.u_seed[-6:], np.tile(demo.us[-1], (6, 1))
    )
    assert long._cache is problem._cache  # compiled kernels shared across horizons
    assert np.isfinite(problem.cost(problem.u_seed))


def test_a_replaced_problem_does_not_reuse_the_penalty_data_of_another():
    scenario = load_scenario("double_integrator", check_demos=False)
    problem = make_problem(scenario, demo=0)
    u = problem.u_seed
    assert problem.cost(u) == 0.0  # the demo keeps d = 0.5 (its penalty data now memoised)
    wider = make_problem(scenario, demo=0, clearance=0.9)
    replaced = dataclasses.replace(problem, constraints=wider.constraints)
    assert replaced._cache is not problem._cache
    assert replaced.cost(u) == wider.cost(u) > 0.0


def test_margins_shrink_the_bounds_and_the_region(quadrotor):
    problem = make_problem(
        quadrotor,
        x0=quadrotor.init_lower,
        u_seed=np.zeros((3, 2)),
        eps_i=0.1,
        input_margin=[0.5, 1.0],
        region_margin={"theta": 0.2},
    )
    assert np.allclose(problem.input_lower, quadrotor.input_lower + [0.6, 1.1])
    assert np.allclose(problem.input_upper, quadrotor.input_upper - [0.6, 1.1])
    assert problem.region["theta"] == pytest.approx((-0.4, 0.4))
    assert problem.region["u1"] == (5.0, 14.9)
    assert problem.constraints.unsafe_margin == pytest.approx(quadrotor.clearance + 0.05)
    goal = geometry.shrink(quadrotor.goal, quadrotor.clearance + 0.05)
    assert problem.constraints.goal_region.equals(goal)


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(method="newton"), "method must be one of"),
        (dict(u=np.zeros((4, 2))), "expected (3, 2)"),
        (dict(u=np.array([[np.nan, 0.0]] * 3)), "not finite at sample 0, 'u1'"),
        (dict(input_margin=[8.0, 0.0]), "input bounds of 'u1' are empty"),
        (dict(input_margin=[1.0]), "input_margin must be a number or 2 numbers"),
        (dict(region_margin={"vX": 0.1}), "'vX', which is not in the scenario's operating_region"),
        (dict(region_margin={"theta": 0.7}), "operating region of 'theta'"),
        (dict(eps_g=5.0), "Goal shrunk by d + eps_g = 6 (d = "),
        (dict(eps_d=-1.0), "eps_d must be a finite number >= 0"),
        (dict(penalty_points=-1), "penalty_points must be a whole number >= 0"),
        (dict(backend="jax"), "backend must be one of"),
        (dict(x0=np.zeros(3)), "x0 must be 6 finite numbers"),
        (dict(N=0), "horizon N must be a whole number >= 1"),
        (dict(demo=99, x0=None), "demo 99 does not exist"),
    ],
)
def test_bad_arguments_say_what_to_do(quadrotor, options, message):
    method = options.pop("method", "adjoint")
    u = options.pop("u", np.zeros((3, 2)))
    kwargs = dict(x0=quadrotor.init_lower, u_seed=np.zeros((3, 2))) | options
    with pytest.raises(ValueError) as error:
        make_problem(quadrotor, **kwargs).cost_and_gradient(u, method=method)
    assert message in str(error.value)
