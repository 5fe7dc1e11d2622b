"""Shortening the horizon of a feasible flight (paper Remark 4): the searches, their seeds, and
the descent that decides one horizon.

``feasible(N)`` is one optimisation of the horizon ``N`` (``stages.optimize``): ``minimise``
drives the cost to zero; ``smallest_feasible`` and ``shortest_by_continuation`` decide which
horizons to try and ``reseed`` how to seed them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.optimize.descent import DescentResult, Stall, gradient_descent, lbfgs
from pipeline.numerics.optimize.problem import Problem
from pipeline.numerics.optimize.shooting import StabilisedProblem
from pipeline.numerics.settings import DESCENT_METHODS

SEED_MODES = ("compress", "truncate")
PARAMETERIZATIONS = ("feedback", "open_loop")


class DescentOptions(Protocol):
    """The options ``minimise`` reads (``stages.optimize.OptimizeOptions``)."""

    @property
    def method(self) -> str: ...

    @property
    def parameterization(self) -> str: ...

    @property
    def overshoot(self) -> float: ...

    @property
    def max_iterations(self) -> int: ...

    @property
    def stall_window(self) -> int: ...

    @property
    def stall_margin(self) -> float: ...


def reseed(u: FloatArray, N: int, mode: str) -> FloatArray:
    """A seed of ``N`` samples from a feasible input ``u (N_u, m)``: its first ``N`` samples
    (``truncate``, the paper's Remark 4) or the same input played faster (``compress``)."""
    if mode == "truncate":
        return np.array(u[:N]) if N <= len(u) else np.vstack([u, np.repeat(u[-1:], N - len(u), 0)])
    if mode == "compress":
        source = (np.arange(len(u)) + 0.5) / len(u)
        target = (np.arange(N) + 0.5) / N
        return np.stack([np.interp(target, source, column) for column in u.T], axis=-1)
    raise ValueError(f"seed mode must be one of {SEED_MODES}, got {mode!r}")


def smallest_feasible(feasible: Callable[[int], bool], lo: int, hi: int) -> int:
    """Bisection on the horizon (Remark 4): the smallest ``N`` in ``(lo, hi]`` with
    ``feasible(N)``, given ``lo`` infeasible and ``hi`` feasible and feasibility monotone in
    ``N``. Each call of ``feasible`` is one optimisation; there are ``ceil(log2(hi - lo))``."""
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if feasible(mid):
            hi = mid
        else:
            lo = mid
    return hi


def shortest_by_continuation(feasible: Callable[[int], bool], N: int, fraction: float) -> int:
    """Shorten a feasible horizon ``N`` step by step: try ``N - step`` (``step`` a ``fraction``
    of ``N``), keep it when feasible, halve the step when not, stop below one sample.

    Each try is warm-started from the last feasible solution, which stays close to it; measured
    on quadrotor_hill_flythrough this finds 13% shorter flights than the bisection's long jumps,
    whose seeds are far from any solution (docs/architecture.md)."""
    step = max(1, int(fraction * N))
    while step >= 1:
        if N - step >= 1 and feasible(N - step):
            N -= step
            step = max(1, int(fraction * N))
        else:
            step //= 2
    return N


def minimise(
    problem: Problem,
    tightened: Problem,
    seed: FloatArray,
    gain: FloatArray,
    options: DescentOptions,
) -> tuple[DescentResult, FloatArray]:
    """Drive ``problem``'s cost to zero from ``seed (N, m)`` by descending on ``tightened``'s
    (the same problem with larger margins); returns the outcome, whose ``cost`` is
    ``problem``'s, and its nominal input ``(N, m)``.

    With ``parameterization="feedback"`` the descent runs over ``v`` of
    ``pipeline.numerics.optimize.shooting`` (the same cost, better conditioned); ``"open_loop"`` is
    the paper's literal ``u``.
    """
    if options.parameterization == "feedback":
        target: Any = StabilisedProblem.around(tightened, gain, seed)
        check: Any = dataclasses.replace(target, problem=problem)
    elif options.parameterization == "open_loop":
        target, check = tightened, problem
    else:
        raise ValueError(f"parameterization must be one of {PARAMETERIZATIONS}")
    gate = max(options.overshoot, 1e-6) ** 2  # evaluate the real cost only once this close
    stall = Stall(target=gate, window=options.stall_window, margin=options.stall_margin)

    def reached(v: FloatArray, J_tightened: float) -> bool:
        return J_tightened == 0.0 or (J_tightened <= gate and check.cost(v) == 0.0)

    if options.method == "gd":
        outcome = gradient_descent(
            target, seed, max_iterations=options.max_iterations, reached=reached, stall=stall
        )
    elif options.method == "lbfgs":
        outcome = lbfgs(
            target,
            seed,
            max_iterations=options.max_iterations,
            box=options.parameterization == "open_loop",
            reached=reached,
            stall=stall,
        )
    else:
        raise ValueError(f"method must be one of {DESCENT_METHODS}, got {options.method!r}")
    cost = check.cost(outcome.u)
    outcome = dataclasses.replace(outcome, cost=cost, feasible=cost == 0.0)
    u = target.inputs(outcome.u) if options.parameterization == "feedback" else outcome.u
    return outcome, u


def warm_up(problem: Problem, gain: FloatArray, options: DescentOptions) -> None:
    """Compile (or load from numba's disk cache) the kernels one descent step uses, on a
    two-sample horizon, so that per-demo wall times measure the optimization only."""
    seed = np.asarray(problem.u_seed[:2], dtype=np.float64)
    short = problem.with_horizon(2, seed)
    short.cost(seed)
    short.cost_and_gradient(seed)
    if options.parameterization == "feedback":
        StabilisedProblem.around(short, gain, seed).cost_and_gradient(seed)
