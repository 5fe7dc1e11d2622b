"""Stage ``optimize``: make every nominal trajectory as fast as possible while keeping its radius.

For one demo with ``N_demo`` samples (paper §IV-A, Remark 4): the feasibility test of a horizon
``N'`` is ``min_u J(u) == 0`` for the penalty cost whose Unsafe sets are bloated by ``d + eps_d``,
Goal shrunk by ``d + eps_g``, inputs shrunk by ``eps_i`` plus the feedback's margin at the required
radius, and operating region and ``state_bounds`` shrunk by the tube's extent. Once the demo itself
is made feasible at ``N_demo``, a short feasible ``N'`` is searched by bisection between 0 and
``N_demo`` (the paper's Remark 4, ``search="bisection"``) or by continuation, shortening the last
feasible horizon by a tenth at a time (the default: feasibility is not monotone in ``N'`` for a
local optimiser, and small steps keep each seed near a solution). Each try is seeded from the
nearest feasible solution, time-compressed (default) or truncated (the paper) to ``N'`` samples.
Each descent runs on the cost with every margin tightened by ``overshoot`` and stops as soon as the
problem's own cost is zero: a descent that approaches ``J = 0`` from outside only reaches it in the
limit (measured: most failed tries ended at J ~ 1e-10 after the iteration cap). The result is
re-verified in continuous time independently of the cost (``pipeline.numerics.verify.nominal``).

Funnels (issue 16 part 4): ``reoptimize_with_funnels`` runs the same search from each optimized
nominal again, with the margins of the funnel synthesized around it (per sample interval,
``pipeline.numerics.optimize.margins``; ``ConstraintMargins.of_funnel``) in place of the
constant tube's, and the scenario's ``state_bounds`` in place of the operating region. One call
is one round of the alternation nominal -> funnel -> nominal; the caller synthesizes and checks
the new funnels.

A hold run of the funnel certificate (``stages.certificates.Targets``) ends every nominal in a
box of its terminal ellipsoid's core, read as Goal's extra bounds, on the nominal alone
(``end_unshrunk``): the funnel, not the tube's extent, certifies where the flight ends (inside
that ellipsoid). Measured on double_integrator_hold: the constant tube's extent at ``T`` (0.5 m)
and, under a declared gust of 0.02 m/s^2, the funnels' (0.12-0.18) exceed the core box's half
width (0.115), which the shrunk bound left empty.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pipeline.io.executor import Executor, SerialExecutor, preload_in_workers
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.funnel.check import Funnel
from pipeline.numerics.optimize.descent import DescentResult, IterationLog
from pipeline.numerics.optimize.footprint import ConstraintMargins, verify_within
from pipeline.numerics.optimize.horizon import (
    minimise,
    reseed,
    shortest_by_continuation,
    smallest_feasible,
    warm_up,
)
from pipeline.numerics.optimize.penalties import MarginError
from pipeline.numerics.optimize.problem import Problem, make_problem
from pipeline.numerics.settings import DESCENT_METHODS, HORIZON_SEARCHES
from pipeline.results.optimize import BisectionTry as BisectionTry
from pipeline.results.optimize import OptimizeOptions as OptimizeOptions
from pipeline.results.optimize import OptimizeResult as OptimizeResult
from pipeline.results.optimize import TrajectoryOptimization as TrajectoryOptimization
from pipeline.results.stage import Stage, StageInputs

preload_in_workers(__name__)  # its chunks run in worker processes

METHODS = DESCENT_METHODS
SEARCHES = HORIZON_SEARCHES


def optimize_demo(
    scenario: Scenario, demo: int, margins: ConstraintMargins, options: OptimizeOptions
) -> TrajectoryOptimization:
    """Minimum-time search (Remark 4) for demo number ``demo``; its ``seconds`` exclude the
    one-off compilation of the scenario's kernels (``warm_up``)."""
    chosen = scenario.demos[demo]
    return optimize_from(
        scenario, chosen.name, chosen.x0, chosen.us, margins, options, N_demo=len(chosen.us)
    )


def optimize_from(
    scenario: Scenario,
    name: str,
    x0: FloatArray,
    us: FloatArray,
    margins: ConstraintMargins,
    options: OptimizeOptions,
    *,
    N_demo: int,
    infeasible_hint: str = "record a demonstration with more clearance",
    N_min: int = 1,
) -> TrajectoryOptimization:
    """Minimum-time search from the flight ``x0 (n,)``, ``us (N, m)`` (a demo, or an optimized
    nominal to optimize again under new margins): first made feasible at its own ``N``, then
    shortened, never below ``N_min`` samples (a horizon under it counts as infeasible without a
    try). ``N_demo``: the demonstration's length, for the speedup; ``infeasible_hint``: what to do
    when the flight cannot be made feasible at its own length."""
    region, region_margin = margins.nominal_box(scenario)  # a constant tube's: in state_bounds
    box = scenario.operating_region if region is None else region

    def constrained(extra: float) -> Problem:
        return make_problem(
            scenario,
            x0=x0,
            u_seed=us,
            input_margin=margins.input_margin,
            region_margin={
                key: region_margin.get(key, 0.0)
                + extra
                + (options.eps_r if key in scenario.state_names else 0.0)
                for key in box
            },
            eps_d=options.eps_d + extra,
            eps_g=options.eps_g + extra,
            eps_i=options.eps_i + extra,
            clearance=margins.clearance,
            goal_margin={key: extent + extra for key, extent in margins.goal_margin.items()},
            region=region,
            profile=margins.profile,
        )

    def unchanged(
        seconds: float,
        message: str,
        tries: tuple[BisectionTry, ...] = (),
        log: IterationLog | None = None,
    ) -> TrajectoryOptimization:
        return TrajectoryOptimization(
            demo=name, x0=np.asarray(x0, dtype=np.float64), N_demo=N_demo, N=len(us), u=us,
            Ts=scenario.Ts, tries=tries, feasible_inputs=(), log=log or IterationLog.empty(),
            verification=None, seconds=seconds, success=False, message=message,
        )  # fmt: skip

    try:
        problem, tightened = constrained(0.0), constrained(options.overshoot)
    except MarginError as error:  # e.g. a tube too wide for Goal: this demo cannot be optimized
        return unchanged(0.0, f"demo '{name}' was not optimized: {error}")
    warm_up(problem, margins.gain, options)
    start = time.perf_counter()
    N_start = problem.N
    tries: list[BisectionTry] = []
    feasible_inputs: list[FloatArray] = []

    def attempt(N: int, seed: FloatArray) -> DescentResult:
        t0 = time.perf_counter()
        outcome, u = minimise(
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

    first = attempt(N_start, problem.u_seed)
    if not first.feasible:
        return unchanged(
            time.perf_counter() - start,
            f"demo '{name}' could not be made feasible at its own length "
            f"({first.message}); {infeasible_hint}",
            tries=tuple(tries),
            log=first.log,
        )
    nearest = first  # the shortest feasible solution so far

    def feasible(N: int) -> bool:
        nonlocal nearest
        if N < N_min:
            return False
        outcome = attempt(N, reseed(nearest.u, N, options.seed_mode))
        if outcome.feasible:
            nearest = outcome
        return outcome.feasible

    if options.search == "bisection":
        hi = smallest_feasible(feasible, 0, N_start)
    elif options.search == "continuation":
        hi = shortest_by_continuation(feasible, N_start, options.step_fraction)
    else:
        raise ValueError(f"search must be one of {SEARCHES}, got {options.search!r}")
    best, best_log = nearest.u, nearest.log
    verification = verify_within(scenario, problem.with_horizon(hi, best), best, margins)
    success = verification.passed
    message = (
        f"{N_start} -> {hi} samples ({1 - hi / N_start:.0%} faster), {verification.message}"
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


def end_unshrunk(
    scenario: Scenario, margins: ConstraintMargins, names: Sequence[str]
) -> ConstraintMargins:
    """``margins`` whose tube extent at ``T`` (``goal_margin``, the profile's ``final_state``)
    no longer shrinks Goal's extra bounds on the states ``names``: they bound the nominal's end
    itself. Their ``goal_margin`` is 0, not absent, so that the descent's tightened problem
    still moves them by its ``overshoot`` (absent, the tightened and the real bound were the
    same and the descent crept to the bound without reaching it: quadrotor_hill_flythrough with
    ``terminal: hold`` stopped at J = 3e-22 > 0 on demo_06)."""
    if not names:
        return margins
    goal = {**margins.goal_margin, **dict.fromkeys(names, 0.0)}
    profile = margins.profile
    if profile is not None:
        final = np.array(profile.final_state, dtype=np.float64)
        final[[scenario.state_names.index(k) for k in names]] = 0.0
        profile = dataclasses.replace(profile, final_state=final)
    return dataclasses.replace(margins, goal_margin=goal, profile=profile)


def _optimize_in_worker(
    task: tuple[Scenario, int, ConstraintMargins, OptimizeOptions],
) -> TrajectoryOptimization:
    scenario, demo, margins, options = task  # the scenario given, pickled to a worker process
    return optimize_demo(scenario, demo, margins, options)


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
    tasks = [(scenario, i, margins, options) for i in indices]
    executor = executor or SerialExecutor()
    results = executor.map(
        _optimize_in_worker, tasks, done=None if progress is None else lambda _i: progress(1)
    )
    return _result(results, options, "optimized and verified")


def _result(
    results: Sequence[TrajectoryOptimization], options: OptimizeOptions, done: str
) -> OptimizeResult:
    """The stage's result: successful iff every trajectory is; the message lists the failures."""
    failed = [r for r in results if not r.success]
    message = (
        f"all {len(results)} trajectories {done}"
        if not failed
        else "; ".join(r.message for r in failed)
    )
    return OptimizeResult(
        trajectories=tuple(results), options=options, success=not failed, message=message
    )


def _reoptimize_in_worker(
    task: tuple[Scenario, TrajectoryOptimization, ConstraintMargins, OptimizeOptions, int],
) -> TrajectoryOptimization:
    scenario, previous, margins, options, N_min = task
    return optimize_from(
        scenario,
        previous.demo,
        previous.x0,
        previous.u,
        margins,
        options,
        N_demo=previous.N_demo,
        infeasible_hint="its funnel's margins leave it no room: keep the previous round",
        N_min=N_min,
    )


def reoptimize_with_funnels(
    scenario: Scenario,
    trajectories: Sequence[TrajectoryOptimization],
    funnels: Sequence[Funnel],
    options: OptimizeOptions,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
    *,
    clearance: float = 0.0,
    level: float | None = None,
    at_least: float | None = None,
    shortest: Sequence[int] | None = None,
    core: Sequence[str] = (),
) -> OptimizeResult:
    """Optimise each trajectory again, keeping its funnel's tube inside the constraints (issue 16
    part 4: one round of the alternation nominal -> funnel -> nominal).

    Trajectory ``i`` (an optimized nominal, ``u (N_i, m)``) is first made feasible at its own
    ``N_i`` and then shortened as in ``optimize``, with the margins of ``funnels[i]`` (synthesized
    around that nominal) instead of the constant certificate's: Unsafe bloated by ``clearance +
    eps_d`` plus the funnel's position extent on each sample interval, the input bounds shrunk by
    its input extents, and no operating region: the scenario's ``state_bounds`` shrunk by its
    state extents (``pipeline.numerics.optimize.margins.funnel_margins`` at ``level``, default each
    funnel's rho; on a shorter horizon the extents are read by normalised time, maximum over the
    window). ``clearance`` (m): how far beyond the tube the nominal must stay from Unsafe (0: the
    tube itself must clear Unsafe, which is what the funnel certifies); ``at_least`` (m, default
    the scenario's d): the nominal's own distance to Unsafe never drops below it, as the constant
    certificate's nominals and the uncertified comparison keep d. The shooting is
    stabilised by the mean of the funnel's gains ``K[k]``. ``shortest`` (one per trajectory,
    default 1): trajectory ``i`` is shortened to no fewer than ``shortest[i]`` samples, so that
    a round moves its nominal only as far as the next funnel can follow (the caller's
    continuation); one already at its floor, or whose funnel was not certified, is returned
    unchanged, unsuccessful. ``core``: states whose Goal bound holds the nominal's end alone
    (``end_unshrunk``; a hold run's). Nothing here is certified: synthesize and check the funnel
    around each new nominal before using it.
    """
    if len(trajectories) != len(funnels):
        raise ValueError(
            f"reoptimize_with_funnels: {len(trajectories)} trajectories but {len(funnels)}"
            " funnels; give one funnel per trajectory, in the same order"
        )
    floors = [1] * len(trajectories) if shortest is None else [int(n) for n in shortest]
    if len(floors) != len(trajectories):
        raise ValueError(
            f"reoptimize_with_funnels: {len(floors)} shortest horizons for {len(trajectories)}"
            " trajectories; give one per trajectory, in the same order"
        )
    tasks, kept = [], {}
    for i, (previous, funnel) in enumerate(zip(trajectories, funnels, strict=True)):
        if floors[i] >= previous.N:
            kept[i] = dataclasses.replace(
                previous,
                success=False,
                message=f"'{previous.demo}' not optimized again: it may not be shortened below "
                f"{floors[i]} samples, and it has {previous.N}",
            )
            continue
        if not funnel.success or funnel.K.shape[0] != previous.N:
            kept[i] = dataclasses.replace(
                previous,
                success=False,
                message=f"'{previous.demo}' not optimized again: its funnel "
                + (
                    f"was not certified ({funnel.message})"
                    if not funnel.success
                    else f"has {funnel.K.shape[0]} intervals, the trajectory {previous.N}"
                ),
            )
            continue
        margins = ConstraintMargins.of_funnel(
            scenario,
            funnel,
            clearance=clearance,
            level=level,
            at_least=scenario.clearance if at_least is None else at_least,
        )
        task = (scenario, previous, end_unshrunk(scenario, margins, core), options, floors[i])
        tasks.append((i, task))
    executor = executor or SerialExecutor()
    done = [] if not tasks else executor.map(
        _reoptimize_in_worker,
        [task for _, task in tasks],
        done=None if progress is None else lambda _i: progress(1),
    )  # fmt: skip
    by_index = kept | {i: result for (i, _), result in zip(tasks, done, strict=True)}
    results = [by_index[i] for i in range(len(trajectories))]
    if progress is not None:
        progress(len(kept))
    return _result(results, options, "optimized again within their funnels and verified")


@dataclass(frozen=True, kw_only=True)
class OptimizeInputs(StageInputs):
    """What stage ``optimize`` reads: the demos, the margins every tube keeps and the
    optimizer."""

    scenario_fields: ClassVar = (
        "Ts",
        "demos",
        "dynamics",
        "goal",
        "goal_bounds",
        "input_lower",
        "input_upper",
        "operating_region",
        "position_index",
        "state_bounds",
        "unsafe",
    )
    scenario: Scenario
    margins: ConstraintMargins
    options: OptimizeOptions


def _optimize_stage(
    inputs: OptimizeInputs,
    *,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> OptimizeResult:
    return optimize(
        inputs.scenario, inputs.margins, inputs.options, executor=executor, progress=progress
    )


@dataclass(frozen=True, kw_only=True)
class ReoptimizeInputs(StageInputs):
    """What stage ``reoptimize`` (round k of the funnel certificate) reads: each trajectory's
    previous optimization (its nominal replaced by the kept one), its funnel, the optimizer,
    the fewest samples each may end with (``shortest``) and the states whose Goal bound holds
    the nominal's end alone (``core``, ``end_unshrunk``)."""

    scenario_fields: ClassVar = (
        "Ts",
        "clearance",
        "dynamics",
        "goal",
        "goal_bounds",
        "input_lower",
        "input_upper",
        "position_index",
        "state_bounds",
        "unsafe",
    )
    scenario: Scenario
    trajectories: tuple[TrajectoryOptimization, ...]
    funnels: tuple[Funnel, ...]
    options: OptimizeOptions
    shortest: tuple[int, ...]
    core: tuple[str, ...] = ()


def _reoptimize_stage(
    inputs: ReoptimizeInputs,
    *,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> OptimizeResult:
    return reoptimize_with_funnels(
        inputs.scenario,
        inputs.trajectories,
        inputs.funnels,
        inputs.options,
        executor,
        progress,
        shortest=inputs.shortest,
        core=inputs.core,
    )


OPTIMIZE = Stage("optimize", _optimize_stage, OptimizeInputs, OptimizeResult)
REOPTIMIZE = Stage("reoptimize", _reoptimize_stage, ReoptimizeInputs, OptimizeResult)
