"""Stabilised shooting: exact gradient of J(u(v)) and the inputs it produces."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import load_scenario
from pipeline.numerics.optimize.problem import make_problem
from pipeline.numerics.optimize.shooting import StabilisedProblem
from stages.feedback import lqr_gain


@pytest.fixture(scope="module")
def stabilised():
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    problem = make_problem(scenario, demo=3, N=60)
    return problem, StabilisedProblem.around(problem, lqr_gain(scenario), problem.u_seed)


def test_at_the_seed_the_inputs_are_the_seed(stabilised):
    problem, shooting = stabilised
    np.testing.assert_allclose(shooting.inputs(problem.u_seed), problem.u_seed, atol=1e-12)
    assert shooting.cost(problem.u_seed) == pytest.approx(problem.cost(problem.u_seed), rel=1e-12)


def test_cost_is_the_problems_cost_of_the_produced_inputs(stabilised):
    problem, shooting = stabilised
    v = problem.u_seed + 0.05 * np.random.default_rng(3).normal(size=problem.u_seed.shape)
    assert shooting.cost(v) == pytest.approx(problem.cost(shooting.inputs(v)), rel=1e-12)


def test_gradient_matches_central_differences(stabilised):
    problem, shooting = stabilised
    rng = np.random.default_rng(4)
    v = problem.u_seed + 0.05 * rng.normal(size=problem.u_seed.shape)
    J, q = shooting.cost_and_gradient(v)
    assert J > 0  # penalties active: the test is not vacuous
    for _ in range(3):
        w = rng.normal(size=v.shape)
        eps = 1e-6
        fd = (shooting.cost(v + eps * w) - shooting.cost(v - eps * w)) / (2 * eps)
        assert np.sum(q * w) == pytest.approx(fd, rel=1e-6)
    # a single entry too, where the feedback chain matters most (early samples)
    e = np.zeros_like(v)
    e[2, 1] = 1e-6
    fd = (shooting.cost(v + e) - shooting.cost(v - e)) / 2e-6
    assert q[2, 1] == pytest.approx(fd, rel=1e-5)


def test_only_the_adjoint_exists(stabilised):
    _, shooting = stabilised
    with pytest.raises(ValueError, match="adjoint"):
        shooting.cost_and_gradient(shooting.problem.u_seed, method="sensitivity")
