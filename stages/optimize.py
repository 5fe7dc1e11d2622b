"""Stage ``optimize``: make every nominal trajectory as fast as possible while keeping its radius.

For one demo with ``N_demo`` samples (paper §IV-A, Remark 4): the feasibility test of a horizon
``N'`` is ``min_u J(u) == 0`` for the penalty cost whose Unsafe sets are bloated by ``d + eps_d``,
Goal shrunk by ``d + eps_g``, inputs shrunk by ``eps_i`` plus the feedback's margin at the
required radius, and operating region shrunk by the tube's extent. Once the demo itself is made
feasible at ``N_demo``, a short feasible ``N'`` is searched by bisection between 0 and ``N_demo``
(the paper's Remark 4, ``search="bisection"``) or by continuation, shortening the last feasible
horizon by a tenth at a time (the default: feasibility is not monotone in ``N'`` for a local
optimiser, and small steps keep each seed near a solution). Each try is seeded from the
nearest feasible solution, time-compressed (default) or truncated (the paper) to ``N'``
samples. Each descent runs on the cost with every margin tightened by ``overshoot`` and stops
as soon as the problem's own cost is zero: a descent that approaches ``J = 0`` from outside only
reaches it in the limit (measured: most failed tries ended at J ~ 1e-10 after the iteration cap).
The result is re-verified in continuous time independently of the cost
(``pipeline.numerics.verify``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.executor import Executor, SerialExecutor
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario, load_scenario_cached
from pipeline.numerics.descent import DescentResult, IterationLog, gradient_descent, lbfgs
from pipeline.numerics.penalties import MarginError
from pipeline.numerics.problem import Problem, make_problem
from pipeline.numerics.settings import DESCENT_METHODS, EPS_D, EPS_G, EPS_I, HORIZON_SEARCHES
from pipeline.numerics.shooting import StabilisedProblem
from pipeline.numerics.tube import Tube
from pipeline.numerics.verify import Verification, verify_nominal

METHODS = DESCENT_METHODS
SEED_MODES = ("compress", "truncate")
PARAMETERIZATIONS = ("feedback", "open_loop")
SEARCHES = HORIZON_SEARCHES


@dataclass(frozen=True, kw_only=True)
class ConstraintMargins:
    """The tube's footprint at the required radius, from the feedback stage.

    Attributes:
      input_margin: (m,) how much the tube's feedback may add to ``u_ref``, per input.
      region_margin: state/input name -> how far the tube extends along it.
      gain: (m, n) the feedback gain, which also stabilises the shooting
        (``pipeline.numerics.shooting``).
      clearance: the tube's position extent, kept from Unsafe and Goal's boundary (default: the
        scenario's ``d``; larger when coverage of Init needs a radius above ``r_d``).
      goal_margin: state name -> how far the tube extends along it (shrinks Goal's extra bounds).
    """

    input_margin: FloatArray
    region_margin: Mapping[str, float]
    gain: FloatArray
    clearance: float | None = None
    goal_margin: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def of_tube(cls, tube: Tube, radius: float) -> ConstraintMargins:
        """The footprint of the feedback's tube of P-norm radius ``radius``."""
        return cls(
            input_margin=tube.input_margin(radius),
            region_margin=tube.region_extent(radius),
            gain=tube.K,
            clearance=tube.position_extent(radius),
            goal_margin=dict(
                zip(tube.state_names, map(float, tube.state_extent(radius)), strict=True)
            ),
        )


@dataclass(frozen=True, kw_only=True)
class OptimizeOptions:
    method: str = METHODS[0]
    seed_mode: str = "compress"
    parameterization: str = "feedback"
    search: str = SEARCHES[0]
    step_fraction: float = 0.1  # continuation: shorten by this fraction of the horizon
    eps_d: float = EPS_D
    eps_g: float = EPS_G
    eps_i: float = EPS_I
    eps_r: float = 0.01  # operating-region states: room for motion between penalty points
    overshoot: float = 0.01  # the descent's extra margin (m, N, rad: the constraints' units)
    max_iterations: int = 1000

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.seed_mode not in SEED_MODES:
            raise ValueError(f"seed_mode must be one of {SEED_MODES}, got {self.seed_mode!r}")
        if self.search not in SEARCHES:
            raise ValueError(f"search must be one of {SEARCHES}, got {self.search!r}")
        if not self.overshoot >= 0.0:
            raise ValueError(f"overshoot must be >= 0, got {self.overshoot!r}")
        if self.parameterization not in PARAMETERIZATIONS:
            raise ValueError(
                f"parameterization must be one of {PARAMETERIZATIONS}, "
                f"got {self.parameterization!r}"
            )


@dataclass(frozen=True, kw_only=True)
class BisectionTry:
    """One horizon tried: ``N`` samples, whether ``J`` reached 0, and at what effort."""

    N: int
    feasible: bool
    iterations: int
    cost: float
    seconds: float


@dataclass(frozen=True, kw_only=True)
class TrajectoryOptimization:
    """The optimisation of one demo.

    Attributes:
      x0: (n,) its start; u: (N, m) the fastest feasible input found (the demo's if none).
      tries: every horizon tried, in order; feasible_inputs: the feasible ``(N_i, m)`` inputs
      met on the way (the paper's Fig. 2 intermediate trajectories); log: iteration log of the
      final horizon's descent (its cost is the tightened one the descent minimised).
    """

    demo: str
    x0: FloatArray
    N_demo: int
    N: int
    u: FloatArray
    Ts: float
    tries: tuple[BisectionTry, ...]
    feasible_inputs: tuple[FloatArray, ...] = field(repr=False)
    log: IterationLog = field(repr=False)
    verification: Verification | None
    seconds: float
    success: bool
    message: str

    @property
    def speedup(self) -> float:
        """Fraction of the demo's duration saved: ``1 - N / N_demo``."""
        return 1.0 - self.N / self.N_demo


@dataclass(frozen=True, kw_only=True)
class OptimizeResult:
    trajectories: tuple[TrajectoryOptimization, ...]
    options: OptimizeOptions
    success: bool
    message: str


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
    on quadrotor_hill this finds 13% shorter flights than the bisection's long jumps, whose
    seeds are far from any solution (see the README)."""
    step = max(1, int(fraction * N))
    while step >= 1:
        if N - step >= 1 and feasible(N - step):
            N -= step
            step = max(1, int(fraction * N))
        else:
            step //= 2
    return N


def _minimise(
    problem: Problem,
    tightened: Problem,
    seed: FloatArray,
    gain: FloatArray,
    options: OptimizeOptions,
) -> tuple[DescentResult, FloatArray]:
    """Drive ``problem``'s cost to zero from ``seed (N, m)`` by descending on ``tightened``'s
    (the same problem with larger margins); returns the outcome, whose ``cost`` is
    ``problem``'s, and its nominal input ``(N, m)``.

    With ``parameterization="feedback"`` the descent runs over ``v`` of
    ``pipeline.numerics.shooting`` (the same cost, better conditioned); ``"open_loop"`` is the
    paper's literal ``u``.
    """
    if options.parameterization == "feedback":
        target: Any = StabilisedProblem.around(tightened, gain, seed)
        check: Any = dataclasses.replace(target, problem=problem)
    elif options.parameterization == "open_loop":
        target, check = tightened, problem
    else:
        raise ValueError(f"parameterization must be one of {PARAMETERIZATIONS}")
    gate = max(options.overshoot, 1e-6) ** 2  # evaluate the real cost only once this close

    def reached(v: FloatArray, J_tightened: float) -> bool:
        return J_tightened == 0.0 or (J_tightened <= gate and check.cost(v) == 0.0)

    if options.method == "gd":
        outcome = gradient_descent(
            target, seed, max_iterations=options.max_iterations, reached=reached
        )
    elif options.method == "lbfgs":
        outcome = lbfgs(
            target,
            seed,
            max_iterations=options.max_iterations,
            box=options.parameterization == "open_loop",
            reached=reached,
        )
    else:
        raise ValueError(f"method must be one of {METHODS}, got {options.method!r}")
    cost = check.cost(outcome.u)
    outcome = dataclasses.replace(outcome, cost=cost, feasible=cost == 0.0)
    u = target.inputs(outcome.u) if options.parameterization == "feedback" else outcome.u
    return outcome, u


def _warm_up(problem: Problem, gain: FloatArray, options: OptimizeOptions) -> None:
    """Compile (or load from numba's disk cache) the kernels one descent step uses, on a
    two-sample horizon, so that per-demo wall times measure the optimization only."""
    seed = np.asarray(problem.u_seed[:2], dtype=np.float64)
    short = problem.with_horizon(2, seed)
    short.cost(seed)
    short.cost_and_gradient(seed)
    if options.parameterization == "feedback":
        StabilisedProblem.around(short, gain, seed).cost_and_gradient(seed)


def optimize_demo(
    scenario: Scenario, demo: int, margins: ConstraintMargins, options: OptimizeOptions
) -> TrajectoryOptimization:
    """Minimum-time search (Remark 4) for demo number ``demo``; its ``seconds`` exclude the
    one-off compilation of the scenario's kernels (``_warm_up``)."""

    def constrained(extra: float) -> Problem:
        return make_problem(
            scenario,
            demo=demo,
            input_margin=margins.input_margin,
            region_margin={
                name: extent + extra + (options.eps_r if name in scenario.state_names else 0.0)
                for name, extent in margins.region_margin.items()
            },
            eps_d=options.eps_d + extra,
            eps_g=options.eps_g + extra,
            eps_i=options.eps_i + extra,
            clearance=margins.clearance,
            goal_margin={name: extent + extra for name, extent in margins.goal_margin.items()},
        )

    name = scenario.demos[demo].name
    try:
        problem, tightened = constrained(0.0), constrained(options.overshoot)
    except MarginError as error:  # e.g. a tube too wide for Goal: this demo cannot be optimized
        us = scenario.demos[demo].us
        return TrajectoryOptimization(
            demo=name,
            x0=scenario.demos[demo].x0,
            N_demo=len(us),
            N=len(us),
            u=us,
            Ts=scenario.Ts,
            tries=(),
            feasible_inputs=(),
            log=IterationLog.empty(),
            verification=None,
            seconds=0.0,
            success=False,
            message=f"demo '{name}' was not optimized: {error}",
        )
    _warm_up(problem, margins.gain, options)
    start = time.perf_counter()
    N_demo = problem.N
    tries: list[BisectionTry] = []
    feasible_inputs: list[FloatArray] = []

    def attempt(N: int, seed: FloatArray) -> DescentResult:
        t0 = time.perf_counter()
        outcome, u = _minimise(
            problem.with_horizon(N, seed),
            tightened.with_horizon(N, seed),
            seed,
            margins.gain,
            options,
        )
        tries.append(
            BisectionTry(
                N=N,
                feasible=outcome.feasible,
                iterations=outcome.iterations,
                cost=outcome.cost,
                seconds=time.perf_counter() - t0,
            )
        )
        if outcome.feasible:
            feasible_inputs.append(u)
        return dataclasses.replace(outcome, u=u)

    first = attempt(N_demo, problem.u_seed)
    if not first.feasible:
        return TrajectoryOptimization(
            demo=name,
            x0=problem.x0,
            N_demo=N_demo,
            N=N_demo,
            u=problem.u_seed,
            Ts=scenario.Ts,
            tries=tuple(tries),
            feasible_inputs=(),
            log=first.log,
            verification=None,
            seconds=time.perf_counter() - start,
            success=False,
            message=f"demo '{name}' could not be made feasible at its own length "
            f"({first.message}); record a demonstration with more clearance",
        )
    nearest = first  # the shortest feasible solution so far

    def feasible(N: int) -> bool:
        nonlocal nearest
        outcome = attempt(N, reseed(nearest.u, N, options.seed_mode))
        if outcome.feasible:
            nearest = outcome
        return outcome.feasible

    if options.search == "bisection":
        hi = smallest_feasible(feasible, 0, N_demo)
    elif options.search == "continuation":
        hi = shortest_by_continuation(feasible, N_demo, options.step_fraction)
    else:
        raise ValueError(f"search must be one of {SEARCHES}, got {options.search!r}")
    best, best_log = nearest.u, nearest.log
    verification = verify_nominal(
        scenario,
        problem.x0,
        best,
        input_lower=problem.input_lower,
        input_upper=problem.input_upper,
        region=_shrunk(scenario.operating_region, margins.region_margin),
        clearance=margins.clearance,
        goal_bounds=_shrunk(scenario.goal_bounds, margins.goal_margin),
    )
    success = verification.passed
    message = (
        f"{N_demo} -> {hi} samples ({1 - hi / N_demo:.0%} faster), {verification.message}"
        if success
        else f"optimized trajectory failed verification: {verification.message}"
    )
    return TrajectoryOptimization(
        demo=name,
        x0=problem.x0,
        N_demo=N_demo,
        N=hi,
        u=best,
        Ts=scenario.Ts,
        tries=tuple(tries),
        feasible_inputs=tuple(feasible_inputs),
        log=best_log,
        verification=verification,
        seconds=time.perf_counter() - start,
        success=success,
        message=message,
    )


def _shrunk(
    box: Mapping[str, tuple[float, float]], margin: Mapping[str, float]
) -> dict[str, tuple[float, float]]:
    """``box`` (name -> (lower, upper)) shrunk on both sides by ``margin`` (name -> amount)."""
    return {
        name: (lower + margin.get(name, 0.0), upper - margin.get(name, 0.0))
        for name, (lower, upper) in box.items()
    }


def _optimize_in_worker(
    task: tuple[Path, str, int, ConstraintMargins, OptimizeOptions],
) -> TrajectoryOptimization:
    path, source_hash, demo, margins, options = task
    return optimize_demo(load_scenario_cached(path, source_hash), demo, margins, options)


def optimize(
    scenario: Scenario,
    margins: ConstraintMargins,
    options: OptimizeOptions,
    demos: Sequence[int] | None = None,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> OptimizeResult:
    """Optimise the given demos (default all) on ``executor`` (default: here, in order); the
    result does not depend on the executor (every demo's computation is deterministic)."""
    indices = list(range(len(scenario.demos))) if demos is None else list(demos)
    tasks = [(scenario.path, scenario.source_hash, i, margins, options) for i in indices]
    executor = executor or SerialExecutor()
    results = executor.map(
        _optimize_in_worker, tasks, done=None if progress is None else lambda _i: progress(1)
    )
    failed = [r for r in results if not r.success]
    message = (
        f"all {len(results)} trajectories optimized and verified"
        if not failed
        else "; ".join(r.message for r in failed)
    )
    return OptimizeResult(
        trajectories=tuple(results), options=options, success=not failed, message=message
    )
