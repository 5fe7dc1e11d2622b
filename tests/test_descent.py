"""The minimisers on toy problems with known answers (the real cost is tested elsewhere)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
import pytest

from pipeline.numerics.optimize.descent import Stall, gradient_descent, lbfgs


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


@dataclass(frozen=True)
class Ridge(Hinge):
    """``J(u) = 1 + 1 / (1 + |u - c|^2)``: falls for ever towards 1 ever more slowly (a descent
    on a plateau that never reaches its goal)."""

    def cost(self, u: np.ndarray) -> float:
        return float(1.0 + 1.0 / (1.0 + np.sum((u - self.centre) ** 2)))

    def cost_and_gradient(self, u: np.ndarray, method: str = "adjoint") -> tuple[float, np.ndarray]:
        r2 = float(np.sum((u - self.centre) ** 2))
        return 1.0 + 1.0 / (1.0 + r2), -2 * (u - self.centre) / (1.0 + r2) ** 2


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


def test_stall_extrapolates_the_recent_rate_to_the_budget():
    stall = Stall(target=1e-4, window=10, margin=100.0)
    falling = [0.5 ** (k / 10) for k in range(11)]  # halves per window, now J = 0.5
    assert not stall.hopeless(falling, budget=100)  # 9 windows left: 0.5^10 < 100 x 1e-4
    assert stall.hopeless(falling, budget=50)  # 4 windows left: 0.5^5 > 100 x 1e-4
    plateau = [1.0] * 11
    assert stall.hopeless(plateau, budget=10_000)
    assert not stall.hopeless(plateau[:10], budget=10_000)  # fewer than a window: too early
    assert not Stall(target=1e-4, window=10, margin=1e6).hopeless([1e-3] * 11, budget=20)
    assert not stall.hopeless([*plateau[:10], 0.0], budget=20)  # reached zero
    with pytest.raises(ValueError, match="margin >= 1"):
        Stall(target=1e-4, margin=0.5)


# L-BFGS-B without the box: with it, it stops on the box's face before any window
@pytest.mark.parametrize(
    "minimise", [gradient_descent, partial(lbfgs, box=False)], ids=["gd", "lbfgs"]
)
def test_a_stalled_descent_stops_early_and_a_converging_one_is_untouched(minimise):
    stall = Stall(target=1e-4, window=20)
    ridge, seed = _problem(Ridge), _problem().centre + 0.3
    capped = minimise(ridge, seed, max_iterations=300)
    stopped = minimise(ridge, seed, max_iterations=300, stall=stall)
    assert not capped.feasible and not stopped.feasible
    assert 20 <= stopped.iterations < capped.iterations
    assert "stalled at J" in stopped.message
    assert stopped.cost >= capped.cost  # it gave up, so never better than going on
    hinge, far = _problem(), np.full((20, 2), 3.0)
    free, watched = minimise(hinge, far), minimise(hinge, far, stall=stall)
    assert watched.feasible and watched.iterations == free.iterations
    np.testing.assert_array_equal(watched.u, free.u)
