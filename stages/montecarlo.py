"""Stage ``montecarlo``: closed-loop validation of the emitted controller from sampled starts.

Initial states are drawn i.i.d. uniformly from Init (one ``SeedSequence`` child stream per
chunk, so results do not depend on how chunks are scheduled), the closed loop is simulated with
the controller read back from ``controller.json``, and each run is checked in continuous time
(dense grid plus the motion bound between grid points): never in Unsafe, ends in Goal, no input
clipping, error inside the predicted tube ``||e(t)||_P <= e^{-lambda t} ||e(0)||_P + 2 delta``
(``delta``: the stated interpolation error of the emitted reference). A
non-finite state is a failure. The runs go through the compiled kernel
(``pipeline.numerics.rollouts``), which agrees with the NumPy oracle
(``pipeline.numerics.closed_loop.check_runs``, a test checks 1e-9), and so do the few paths the
report shows (``run_paths_compiled``). The failure probability gets an exact one-sided 95%
Clopper-Pearson upper bound (``scipy.stats.binomtest``), valid because the samples are i.i.d.

When the file has a terminal controller, every covered run is continued to ``T +
HOLD_SECONDS`` on the kernel (``hold_runs_compiled``, which agrees with the oracle
``hold_runs``): each must stay in its terminal ellipsoid (which lies in Goal), end in Goal, never
clip and never come near Unsafe ("after_T" failures). A file with ``feedback_period > 0`` is flown
with the law held for that period (both the oracle and the kernel).

A falsification search (Init's corners, a Sobol set, then a local search) is reported
separately: it is evidence, not a bound.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from scipy.optimize import minimize
from scipy.stats import binomtest, qmc

from pipeline.controller import Controller, load
from pipeline.io.executor import Executor, SerialExecutor, preload_in_workers
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.closed_loop import RunChecks, check_runs
from pipeline.numerics.rollouts import (
    check_runs_compiled,
    hold_runs_compiled,
    run_paths_compiled,
)
from pipeline.results.montecarlo import Falsification as Falsification
from pipeline.results.montecarlo import MonteCarloResult as MonteCarloResult
from pipeline.results.stage import FileInput, Stage, StageInputs

preload_in_workers(__name__)  # its chunks run in worker processes

FAILURE_KINDS = ("unsafe", "goal", "clipping", "tube", "non_finite", "uncovered", "after_T")
HOLD_SECONDS = 10.0


def _uniform_init(scenario: Scenario, rng: np.random.Generator, count: int) -> FloatArray:
    lo, hi = scenario.init_lower, scenario.init_upper
    return lo + (hi - lo) * rng.random((count, len(lo)))


def falsify(
    scenario: Scenario,
    controller: Controller,
    sobol_points: int = 128,
    local_searches: int = 2,
    seed: int = 0,
    evaluations_per_search: int = 25,
) -> Falsification:
    """Corners of Init, a scrambled Sobol set, then Nelder-Mead from the worst starts."""
    lo, hi = scenario.init_lower, scenario.init_upper
    free = np.flatnonzero(hi > lo)
    if free.size == 0:  # Init is a single state: the only start there is to try
        checks = check_runs(scenario, controller, lo[None])[0]
        return Falsification(
            worst_x0=lo.copy(),
            worst_margin=float(checks.margin()[0]),
            evaluations=1,
            binding=checks.binding()[0],
        )
    corners = (
        np.array(np.meshgrid(*[[lo[i], hi[i]] for i in free], indexing="ij"))
        .reshape(len(free), -1)
        .T
    )
    sobol = qmc.Sobol(len(free), scramble=True, seed=seed).random(sobol_points)
    candidates = np.vstack([corners, qmc.scale(sobol, lo[free], hi[free])])

    def full(z: FloatArray) -> FloatArray:
        x = np.tile(lo, (len(z), 1))
        x[:, free] = np.clip(z, lo[free], hi[free])
        return x

    margins = check_runs_compiled(scenario, controller, full(candidates)).margin()
    evaluations = len(candidates)
    best_z, best = candidates[np.argmin(margins)], float(np.min(margins))
    for start in candidates[np.argsort(margins)[:local_searches]]:
        outcome = minimize(
            lambda z: float(check_runs_compiled(scenario, controller, full(z[None])).margin()[0]),
            start,
            method="Nelder-Mead",
            bounds=list(zip(lo[free], hi[free], strict=True)),
            options={"maxfev": evaluations_per_search, "xatol": 1e-3, "fatol": 1e-4},
        )
        evaluations += int(outcome.nfev)
        if outcome.fun < best:
            best_z, best = outcome.x, float(outcome.fun)
    worst = full(best_z[None])
    binding = check_runs_compiled(scenario, controller, worst).binding()[0]
    return Falsification(
        worst_x0=worst[0], worst_margin=best, evaluations=evaluations, binding=binding
    )


Hold = tuple[int, FloatArray, float]  # runs continued, failed (B,), largest V / level


def _run_chunk(
    scenario: Scenario, controller_path: Path, size: int, stream: np.random.SeedSequence
) -> tuple[RunChecks, FloatArray, Hold]:
    controller = load(controller_path)
    x0 = _uniform_init(scenario, np.random.default_rng(stream), size)
    checks = check_runs_compiled(scenario, controller, x0)
    hold: Hold = (0, np.zeros(size, dtype=bool), float("nan"))
    if controller.terminal is not None:
        after = hold_runs_compiled(scenario, controller, x0[checks.covered], HOLD_SECONDS)
        failures = np.zeros(size, dtype=bool)
        failures[checks.covered] = after.failures()
        hold = (int(checks.covered.sum()), failures, float(np.max(after.level_ratio, initial=0)))
    failed = np.any([*checks.failures().values(), hold[1]], axis=0)
    return checks, x0[failed], hold


def _drawn_paths(
    scenario: Scenario,
    controller: Controller,
    chunks: list[int],
    streams: list[np.random.SeedSequence],
    count: int,
) -> list[FloatArray]:
    """The first ``count`` paths drawn in the report, each ``(K, 2)`` positions thinned to about
    200 points: the first two runs around each trajectory of chunk 0, then chunk 1, ...,
    simulated on the compiled kernel from the same starts the chunks drew (only as many chunks
    as needed), in one batch."""
    starts: list[FloatArray] = []
    for size, stream in zip(chunks, streams, strict=True):
        if len(starts) >= count:
            break
        x0 = _uniform_init(scenario, np.random.default_rng(stream), size)
        index, _ = controller.select(x0)
        drawn = np.concatenate([np.flatnonzero(index == i)[:2] for i in np.unique(index)])
        starts += list(x0[drawn])  # by trajectory, then by draw
    if not starts:
        return []
    paths = run_paths_compiled(scenario, controller, np.array(starts[:count]))
    return [path[:: max(1, len(path) // 200)] for path in paths]


def _run_chunk_in_worker(
    task: tuple[Scenario, Path, int, np.random.SeedSequence],
) -> tuple[RunChecks, FloatArray, Hold]:
    scenario, controller_path, size, stream = task  # the scenario given, pickled to a worker
    return _run_chunk(scenario, controller_path, size, stream)


def validate_closed_loop(
    scenario: Scenario,
    controller_path: Path,
    samples: int = 10_000,
    seed: int = 0,
    chunk: int = 2_500,
    drawn_paths: int = 60,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> MonteCarloResult:
    """Monte Carlo validation of ``controller.json`` (read back from disk, as emitted).

    Chunk ``i`` draws from ``SeedSequence(seed).spawn(chunks)[i]``, so the result is the same
    for any executor and worker count; ``progress(runs)`` is called as chunks finish.
    """
    controller = load(controller_path)
    chunks = [chunk] * (samples // chunk) + ([samples % chunk] if samples % chunk else [])
    streams = np.random.SeedSequence(seed).spawn(len(chunks))
    tasks = [
        (scenario, Path(controller_path), size, stream)
        for size, stream in zip(chunks, streams, strict=True)
    ]
    executor = executor or SerialExecutor()
    # the report's paths and the falsification search run here while the chunks run in the
    # executor's workers (with the serial executor the two threads take turns)
    side = ThreadPoolExecutor(max_workers=1, thread_name_prefix="montecarlo-side")
    try:
        drawn = side.submit(_drawn_paths, scenario, controller, chunks, streams, drawn_paths)
        searched = side.submit(falsify, scenario, controller, seed=seed)
        outcomes = executor.map(
            _run_chunk_in_worker,
            tasks,
            done=None if progress is None else lambda i: progress(chunks[i]),
        )
        paths, falsification = drawn.result(), searched.result()
    finally:  # a failed chunk (or Ctrl-C) does not wait for the side work
        side.shutdown(wait=False, cancel_futures=True)
    parts = [o[0] for o in outcomes]
    failed = [o[1] for o in outcomes]
    merged = {
        f: np.concatenate([getattr(p, f) for p in parts]) for f in RunChecks.__dataclass_fields__
    }
    checks = RunChecks(**merged)
    after_T = np.concatenate([o[2][1] for o in outcomes])
    held = sum(o[2][0] for o in outcomes)
    hold_level = max((o[2][2] for o in outcomes if o[2][0]), default=float("nan"))
    counts = {kind: int(mask.sum()) for kind, mask in checks.failures().items()}
    counts["after_T"] = int(after_T.sum())
    failing = int(np.any([*checks.failures().values(), after_T], axis=0).sum())
    bound = float(binomtest(failing, samples, alternative="less").proportion_ci(0.95).high)
    success = failing == 0
    after = (
        f"; {held} continued to T + {HOLD_SECONDS:g} s stayed in Goal (V / level <= "
        f"{hold_level:.3g})"
        if held and not counts.get("after_T")
        else ""
    )
    message = (
        (
            f"{samples} closed-loop runs, 0 failures; failure probability <= {bound:.2e} "
            f"(95% Clopper-Pearson){after}"
        )
        if success
        else (
            f"{failing} of {samples} closed-loop runs failed: "
            + ", ".join(f"{k} {v}" for k, v in counts.items() if v)
        )
    )
    return MonteCarloResult(
        samples=samples,
        seed=seed,
        failures=counts,
        failed_x0=np.vstack(failed),
        min_clearance=float(checks.clearance.min()),
        min_goal_margin=float(checks.goal_margin.min()),
        max_tube_tightness=float(checks.tube_tightness.max()),
        failure_bound=bound,
        clearance=checks.clearance,
        tube_tightness=checks.tube_tightness,
        paths=tuple(paths),
        falsification=falsification,
        success=success,
        message=message,
        tube_final=checks.tube_final,
        hold_runs=held,
        hold_max_level_ratio=hold_level,
    )


@dataclass(frozen=True, kw_only=True)
class MonteCarloInputs(StageInputs):
    """What stage ``montecarlo`` reads: the ``controller.json`` it flies (keyed by its bytes),
    the number of runs and the seed."""

    scenario_fields: ClassVar = (
        "dynamics",
        "goal",
        "goal_bounds",
        "init_lower",
        "init_upper",
        "position_index",
        "unsafe",
    )
    scenario: Scenario
    controller: FileInput
    samples: int
    seed: int


def _montecarlo_stage(
    inputs: MonteCarloInputs,
    *,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> MonteCarloResult:
    return validate_closed_loop(
        inputs.scenario,
        inputs.controller.path,
        samples=inputs.samples,
        seed=inputs.seed,
        executor=executor,
        progress=progress,
    )


MONTECARLO = Stage("montecarlo", _montecarlo_stage, MonteCarloInputs, MonteCarloResult)
