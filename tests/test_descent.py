"""The minimisers on toy problems with known answers (the real cost is tested elsewhere)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from pipeline.numerics.descent import gradient_descent, lbfgs


@dataclass(frozen=True)
class Hinge:
    """``J(u) = sum(max(0, |u - c| - w)^2)``: zero on a box around ``c``, like the penalties."""

    centre: np.ndarray
    width: float
    input_lower: np.ndarray
    input_upper: np.ndarray

    def cost(self, u: np.ndarray) -> float:
        excess = np.maximum(np.abs(u - self.centre) - self.width, 0.0)
        return float(np.sum(excess**2))

    def cost_and_gradient(self, u: np.ndarray, method: str = "adjoint") -> tuple[float, np.ndarray]:
        excess = np.maximum(np.abs(u - self.centre) - self.width, 0.0)
        return float(np.sum(excess**2)), 2 * excess * np.sign(u - self.centre)


@dataclass(frozen=True)
class Bowl(Hinge):
    """A cost with a positive minimum: the descent must stop on the step-size test."""

    def cost(self, u: np.ndarray) -> float:
        return float(np.sum((u - self.centre) ** 2) + 1.0)

    def cost_and_gradient(self, u: np.ndarray, method: str = "adjoint") -> tuple[float, np.ndarray]:
        return self.cost(u), 2 * (u - self.centre)


def _problem(kind: type[Hinge] = Hinge) -> Hinge:
    rng = np.random.default_rng(1)
    return kind(rng.normal(size=(20, 2)), 0.1, np.full(2, -10.0), np.full(2, 10.0))


@pytest.mark.parametrize("minimise", [gradient_descent, lbfgs])
def test_reaches_zero_cost_from_a_bad_seed(minimise):
    problem = _problem()
    result = minimise(problem, np.full((20, 2), 3.0))
    assert result.feasible and result.cost == 0.0
    assert problem.cost(result.u) == 0.0


def test_gradient_descent_is_monotone_and_never_worse_than_the_seed():
    problem = _problem(Bowl)
    seed = np.full((20, 2), 3.0)
    result = gradient_descent(problem, seed, max_iterations=200)
    accepted = result.log.cost[result.log.accepted]
    assert np.all(np.diff(result.log.cost) <= 0)  # the logged J is the current iterate's
    assert np.all(np.diff(accepted) < 0)
    assert result.cost <= problem.cost(seed)
    assert not result.feasible and "local minimum" in result.message
    assert result.cost == pytest.approx(1.0, abs=1e-6)


def test_step_grows_on_acceptance_and_shrinks_on_rejection():
    problem = _problem(Bowl)
    result = gradient_descent(problem, np.zeros((20, 2)), alpha=2.0, beta=0.25, max_iterations=30)
    steps, accepted = result.log.step, result.log.accepted
    for k in range(1, len(steps)):
        assert steps[k] == pytest.approx(steps[k - 1] * (2.0 if accepted[k] else 0.25))


def test_rejects_bad_parameters():
    with pytest.raises(ValueError, match="alpha > 1"):
        gradient_descent(_problem(), np.zeros((20, 2)), alpha=0.9)


def test_log_table_has_a_row_per_iteration():
    result = gradient_descent(_problem(), np.full((20, 2), 3.0))
    assert len(result.log.table().splitlines()) == result.iterations + 2


@pytest.mark.parametrize("minimise", [gradient_descent, lbfgs])
def test_a_goal_test_replaces_zero_cost(minimise):
    bowl, seed = _problem(Bowl), np.full((20, 2), 3.0)  # J >= 1: zero is never reached
    assert not minimise(bowl, seed, max_iterations=40).feasible
    threshold = (bowl.cost(seed) + 1.0) / 2
    tested = []

    def reached(u, J):
        tested.append(J)
        return J <= threshold

    early = minimise(bowl, seed, reached=reached)
    assert early.feasible and 1.0 < early.cost <= threshold
    assert tested[-1] == early.cost  # stopped on the first iterate that passed the test
    never = minimise(_problem(), seed, reached=lambda u, J: False, max_iterations=40)
    assert not never.feasible and never.cost == 0.0  # J = 0 alone no longer stops it
