"""Both gradient methods against central finite differences and each other, on inputs whose
trajectories have every penalty active, with constant margins and with margins that vary along the
trajectory (a funnel's); the pruned sensitivity system of Remark 3."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline import available_scenarios, load_scenario
from pipeline.model import geometry
from pipeline.numerics.optimize.margins import MarginProfile
from pipeline.numerics.optimize.problem import make_problem
from pipeline.numerics.optimize.sensitivity import interval_sensitivities, sensitivity_pattern

METHODS = ("adjoint", "sensitivity")


def _relative_error(q: np.ndarray, reference: np.ndarray) -> float:
    return float(np.max(np.abs(q - reference)) / np.max(np.abs(reference)))


def _finite_differences(problem, u: np.ndarray) -> np.ndarray:
    """Central differences, step ``1e-6`` of each input's range."""
    span = problem.scenario.input_upper - problem.scenario.input_lower
    q = np.empty_like(u)
    for k, j in np.ndindex(*u.shape):
        e = np.zeros_like(u)
        e[k, j] = 1e-6 * span[j]
        q[k, j] = (problem.cost(u + e) - problem.cost(u - e)) / (2 * e[k, j])
    return q


def _active_case(name: str, penalty_points: int, N: int = 16):
    """A start, an input and margins for which every penalty term is active (and J finite).

    The input is the reference input plus noise, one sample pushed past each input bound; the
    margins are chosen from the trajectory itself: ``d'`` above the median distance to Unsafe
    (the barrier is active on part of the grid), the operating region shrunk to its middle
    tenth. The goal term is active since the final state is not in ModGoal.
    """
    scenario = load_scenario(name, check_demos=False)
    x0 = 0.5 * (scenario.init_lower + scenario.init_upper)
    lower, upper = scenario.input_lower, scenario.input_upper
    span = upper - lower
    reference = np.clip(np.asarray(scenario.feedback.reference_input, float), lower, upper)
    rng = np.random.default_rng(7)
    for scale in (0.1, 0.05, 0.02, 0.01):
        u = reference + scale * span * rng.normal(size=(N, scenario.m))
        u[2] = upper + 0.05 * span
        u[5] = lower - 0.05 * span
        problem = make_problem(scenario, x0=x0, u_seed=u, penalty_points=penalty_points)
        positions = scenario.positions(problem.trajectory(u).dense_xs)
        distances = np.min([geometry.distance(positions, s) for s in scenario.unsafe.values()], 0)
        if distances.min() > 0.05:
            break
    else:
        raise AssertionError(f"{name}: no random input avoids Unsafe; adjust the test")
    eps_d = max(float(np.median(distances)) - scenario.clearance, 0.0)
    region_margin = {k: 0.45 * (hi - lo) for k, (lo, hi) in scenario.operating_region.items()}
    problem = make_problem(
        scenario,
        x0=x0,
        u_seed=u,
        penalty_points=penalty_points,
        eps_d=eps_d,
        region_margin=region_margin,
    )
    # every term is active somewhere
    c = problem.constraints
    dense = problem.trajectory(u).dense_xs
    assert np.sum(distances < c.unsafe_margin) >= 3
    assert c.final_terms(dense[-1])[0] > 0.0
    assert np.sum(c.input_terms(u)[0] > 0.0) >= 2
    if len(c.region_state_index):
        assert np.any(c.state_terms(dense)[0] > 0.0)
    return problem, u


@pytest.fixture(scope="module", params=[(n, p) for n in available_scenarios() for p in (0, 3)])
def case(request):
    name, penalty_points = request.param
    problem, u = _active_case(name, penalty_points)
    return problem, u, _finite_differences(problem, u)


@pytest.mark.parametrize("method", METHODS)
def test_gradient_matches_central_differences(case, method):
    problem, u, q_fd = case
    J, q = problem.cost_and_gradient(u, method=method)
    assert np.isfinite(J) and J > 0.0
    assert _relative_error(q, q_fd) <= 1e-6


def test_methods_and_backends_agree(case):
    problem, u, _ = case
    reference = dataclasses.replace(problem, backend="numpy")  # its own (empty) cache
    results = {
        (backend.backend, method): backend.cost_and_gradient(u, method=method)
        for backend in (problem, reference)
        for method in METHODS
    }
    J0, q0 = results[("numba", "adjoint")]
    for J, q in results.values():
        assert J == pytest.approx(J0, rel=1e-12)
        assert _relative_error(q, q0) <= 1e-9
    assert problem.gradient(u, method="sensitivity").shape == u.shape


def _varying(problem, M: int = 7):
    """``problem`` with margins that vary along the trajectory on a grid of ``M`` intervals
    (another horizon than the problem's: the regridding is exercised), small enough to leave
    every shrunk box non-empty."""
    scenario = problem.scenario
    rng = np.random.default_rng(11)
    region = scenario.operating_region
    span = scenario.input_upper - scenario.input_lower
    input_width = np.array(
        [region[k][1] - region[k][0] if k in region else w for k, w in zip(
            scenario.input_names, span, strict=True)]
    )  # fmt: skip
    state_width = np.array(
        [region[k][1] - region[k][0] if k in region else 1.0 for k in scenario.state_names]
    )
    profile = MarginProfile(
        clearance=rng.uniform(0.0, 0.3, M),
        input=rng.uniform(0.0, 0.02, (M, scenario.m)) * input_width,
        state=rng.uniform(0.0, 0.02, (M, scenario.n)) * state_width,
        final_clearance=0.05,
        final_state=np.full(scenario.n, 0.01),
    )
    c = problem.constraints
    return make_problem(
        scenario,
        x0=problem.x0,
        u_seed=problem.u_seed,
        penalty_points=problem.penalty_points,
        eps_d=c.unsafe_margin - scenario.clearance,
        region_margin={k: 0.45 * (hi - lo) for k, (lo, hi) in region.items()},
        profile=profile,
    )


@pytest.fixture(scope="module", params=available_scenarios())
def varying_case(request):
    problem, u = _active_case(request.param, 3)
    varying = _varying(problem)
    return problem, varying, u, _finite_differences(varying, u)


@pytest.mark.parametrize("method", METHODS)
def test_gradient_with_margins_along_the_trajectory_matches_central_differences(
    varying_case, method
):
    constant, problem, u, q_fd = varying_case
    J, q = problem.cost_and_gradient(u, method=method)
    assert np.isfinite(J) and J > constant.cost(u)  # the time-varying margins add cost
    assert _relative_error(q, q_fd) <= 1e-6
    reference = dataclasses.replace(problem, backend="numpy")  # its own (empty) cache
    J_numpy, q_numpy = reference.cost_and_gradient(u, method=method)
    assert J_numpy == pytest.approx(J, rel=1e-12)
    assert _relative_error(q_numpy, q) <= 1e-9


def test_gradient_of_a_quadrotor_flight_near_the_hill():
    """Default margins: the barrier near the hill, the goal and the input bound all active."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    x0 = np.array([2.0, 2.5, 0.0, 0.0, 0.0, 0.0])
    u = np.zeros((40, 2))
    u[:, 0] = 9.5
    u[:3, 1], u[3:6, 1] = -1.5, 1.5  # pitch forward, then stop rotating
    u[20:23, 1], u[23:26, 1] = 1.0, -1.0
    u[30, 0] = 15.2  # over the thrust bound
    problem = make_problem(scenario, x0=x0, u_seed=u)
    positions = scenario.positions(problem.trajectory(u).dense_xs)
    r = geometry.distance(positions, scenario.unsafe["hill"])
    assert 0.0 < r.min() < problem.constraints.unsafe_margin
    q_fd = _finite_differences(problem, u)
    for method in METHODS:
        assert _relative_error(problem.gradient(u, method=method), q_fd) <= 1e-6


def test_quadrotor_pruned_sensitivity_system_has_33_equations():
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    pattern = sensitivity_pattern(scenario.dynamics)
    assert (pattern.phi.sum(), pattern.gamma.sum()) == (17, 10)
    assert pattern.equations == 33 == 6 + 17 + 10  # Remark 3
    assert pattern.dense_equations == 54


@pytest.mark.parametrize("name", available_scenarios())
def test_pruned_entries_are_exactly_zero(name):
    """The dense (unpruned) sensitivities vanish outside the structural pattern."""
    problem, u = _active_case(name, 1, N=6)
    dense = problem.trajectory(u).dense_xs
    J_x = np.ones_like(dense)
    s = interval_sensitivities(problem.scenario.dynamics, dense, u, problem.Ts, 2, J_x)
    assert not s.Phi[:, ~problem.pattern.phi].any()
    assert not s.Gamma[:, ~problem.pattern.gamma].any()
    assert np.all(s.Phi[:, problem.pattern.phi] != 0.0)
