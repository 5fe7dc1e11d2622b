"""Stage ``montecarlo``: closed-loop validation of the emitted controller from sampled starts.

Initial states are drawn i.i.d. uniformly from Init (one ``SeedSequence`` child stream per
chunk, so results do not depend on how chunks are scheduled), the closed loop is simulated with
the controller read back from ``controller.json``, and each run is checked in continuous time
(dense grid plus the motion bound between grid points): never in Unsafe, ends in Goal, no input
clipping, error inside the predicted tube ``||e(t)||_P <= e^{-lambda t} ||e(0)||_P + 2 delta``
(``delta``: the stated interpolation error of the emitted reference). A
non-finite state is a failure. The runs go through the compiled kernel
(``pipeline.numerics.closed_loop.rollouts``), which agrees with the NumPy oracle
(``pipeline.numerics.closed_loop.simulate.check_runs``, a test checks 1e-9), and so do the few paths
the report shows (``run_paths_compiled``). The failure probability gets an exact one-sided 95%
Clopper-Pearson upper bound (``scipy.stats.binomtest``), valid because the samples are i.i.d.

When the file has a terminal controller, every covered run is continued to ``T +
HOLD_SECONDS`` on the kernel (``hold_runs_compiled``, which agrees with the oracle
``hold_runs``): each must stay in its terminal ellipsoid (which lies in Goal), be in Goal at every
grid point, never clip, keep the state bounds and never come near Unsafe ("after_T" failures).
Every run must keep the scenario's ``state_bounds`` ("bounds", counted when it has any). A file
with ``feedback_period > 0`` is flown with the law held for that period (oracle and kernel).

A falsification search (Init's corners, a Sobol set, then a local search) is reported
separately: it is evidence, not a bound.

Under a declared uncertainty (``scenario.uncertainty`` not empty) every run also draws the
uncertainty (``pipeline.numerics.closed_loop.gusts``): the uncertain parameters uniformly from their
intervals (constant during the run, flown with the parametric dynamics ``f(x, (u, p))``) and a
gust ``w(t)`` in the disturbance box, piecewise constant with a new value every 0.5 s
(``GUST_PERIOD``); a quarter of the runs fly bang-bang at random corners of both boxes and a
quarter the falsification's worst bang-bang case (``pipeline.numerics.closed_loop.worst_case``: the
search then also covers the boxes' corners, and runs before the chunks, which need its result). Runs
are flown to ``T`` and, with a law past ``T``, to ``T + HOLD_SECONDS`` with the same parameters
and gusts. A declared measurement error ``eta`` is drawn on the gusts' periods (uniform in its
box, at random corners for the bang-bang and worst-case runs) and added to the state the law
sees (the falsification search does not vary it).
A run fails if it ever enters Unsafe, clips, leaves the state bounds, or is outside Goal at any
time after ``T`` (issue 29's criterion); the exact model's own claims are not counted under a
disturbance: the tube's decay ratio; the terminal ellipsoid's level is counted when its block
states it invariant for the declared uncertainty (``claims_invariance``). With an
empty uncertainty nothing is drawn beyond the starts: the runs, their numbers and the random
streams are those of the exact model.
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
from pipeline.numerics.closed_loop import worst_case
from pipeline.numerics.closed_loop.gusts import Draws, sample
from pipeline.numerics.closed_loop.rollouts import (
    HOLD_SECONDS,
    check_runs_compiled,
    hold_runs_compiled,
    run_paths_compiled,
)
from pipeline.numerics.closed_loop.simulate import RunChecks, check_runs
from pipeline.numerics.verify.declared import terminal_claim
from pipeline.results.montecarlo import Falsification as Falsification
from pipeline.results.montecarlo import MonteCarloResult as MonteCarloResult
from pipeline.results.stage import FileInput, Stage, StageInputs

preload_in_workers(__name__)  # its chunks run in worker processes

FAILURE_KINDS = (
    "unsafe",
    "goal",
    "clipping",
    "tube",
    "non_finite",
    "uncovered",
    "bounds",
    "after_T",
)


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
    hold_seconds: float = HOLD_SECONDS,
) -> Falsification:
    """Corners of Init, a scrambled Sobol set, then Nelder-Mead from the worst starts (of the
    nominal closed loop); under a declared uncertainty, then the bang-bang search of
    ``pipeline.numerics.closed_loop.worst_case`` from the worst starts found."""
    nominal, starts = _falsify_starts(
        scenario, controller, sobol_points, local_searches, seed, evaluations_per_search
    )
    if scenario.uncertainty.empty:
        return nominal
    worst = worst_case.search(scenario, controller, starts, hold_seconds, seed=seed)
    return Falsification(
        worst_x0=worst.x0,
        worst_margin=worst.margin,
        evaluations=nominal.evaluations + worst.evaluations,
        binding=worst.binding,
        worst_draws=worst.draws,
    )


def _falsify_starts(
    scenario: Scenario,
    controller: Controller,
    sobol_points: int,
    local_searches: int,
    seed: int,
    evaluations_per_search: int,
) -> tuple[Falsification, FloatArray]:
    """The nominal search, and its worst start with the ``local_searches`` worst candidates
    ``(S, n)``."""
    lo, hi = scenario.init_lower, scenario.init_upper
    free = np.flatnonzero(hi > lo)
    if free.size == 0:  # Init is a single state: the only start there is to try
        checks = check_runs(scenario, controller, lo[None])[0]
        found = Falsification(
            worst_x0=lo.copy(),
            worst_margin=float(checks.margin()[0]),
            evaluations=1,
            binding=checks.binding()[0],
        )
        return found, lo[None].copy()
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
    found = Falsification(
        worst_x0=worst[0], worst_margin=best, evaluations=evaluations, binding=binding
    )
    starts = np.vstack([worst, full(candidates[np.argsort(margins)[:local_searches]])])
    return found, starts


Hold = tuple[int, FloatArray, float]  # runs continued, failed (B,), largest V / level


def _draw(
    scenario: Scenario,
    controller: Controller,
    size: int,
    stream: np.random.SeedSequence,
    worst: Draws | None,
) -> tuple[FloatArray, Draws | None]:
    """A chunk's starts ``(size, n)`` and, under a declared uncertainty, its draws (from the
    same stream, after the starts: the exact model's starts are unchanged)."""
    rng = np.random.default_rng(stream)
    x0 = _uniform_init(scenario, rng, size)
    if scenario.uncertainty.empty:
        return x0, None
    span = worst_case.horizon(controller, HOLD_SECONDS)
    return x0, sample(scenario.uncertainty, rng, size, span, worst=worst)


def _counted(scenario: Scenario, checks: RunChecks) -> dict[str, np.ndarray]:
    """The failure masks counted: no tube ratio under a declared uncertainty, no state bounds
    for a scenario without them."""
    masks = checks.failures()
    if not scenario.uncertainty.empty:
        masks.pop("tube")
    if not scenario.state_bounds:
        masks.pop("bounds")
    return masks


def claims_invariance(scenario: Scenario, controller: Controller) -> bool:
    """The file's terminal block states its ellipsoid invariant for the scenario's declared
    uncertainty (its ``disturbance`` what certify re-checks it under, ``terminal_claim``: the
    additive bound, or (T7)'s at its equilibrium): a run that leaves the ellipsoid after ``T``
    then contradicts the certificate and is counted failed. A block for less (the exact
    model's) claims nothing under the draws."""
    terminal = controller.terminal
    if terminal is None or terminal.disturbance is None:
        return False
    bound, _, failures = terminal_claim(scenario, terminal)
    return not failures and bound is not None and bool(np.all(np.isfinite(bound)))


def _run_chunk(
    scenario: Scenario,
    controller_path: Path,
    size: int,
    stream: np.random.SeedSequence,
    worst: Draws | None = None,
) -> tuple[RunChecks, FloatArray, Hold]:
    controller = load(controller_path)
    x0, draws = _draw(scenario, controller, size, stream, worst)
    checks = check_runs_compiled(scenario, controller, x0, draws=draws)
    hold: Hold = (0, np.zeros(size, dtype=bool), float("nan"))
    if controller.terminal is not None:
        covered = checks.covered
        after = hold_runs_compiled(
            scenario,
            controller,
            x0[covered],
            HOLD_SECONDS,
            draws=None if draws is None else draws.rows(covered),
            ends=checks.final_state[covered],
        )
        failures = np.zeros(size, dtype=bool)
        ellipsoid = draws is None or claims_invariance(scenario, controller)
        failures[covered] = after.failures(ellipsoid=ellipsoid)
        hold = (int(covered.sum()), failures, float(np.max(after.level_ratio, initial=0)))
    failed = np.any([*_counted(scenario, checks).values(), hold[1]], axis=0)
    return checks, x0[failed], hold


def _drawn_paths(
    scenario: Scenario,
    controller: Controller,
    chunks: list[int],
    streams: list[np.random.SeedSequence],
    count: int,
    worst: Draws | None = None,
) -> list[FloatArray]:
    """The first ``count`` paths drawn in the report, each ``(K, 2)`` positions thinned to about
    200 points: the first two runs around each trajectory of chunk 0, then chunk 1, ...,
    simulated on the compiled kernel from the same starts the chunks drew (only as many chunks
    as needed), in one batch."""
    starts: list[FloatArray] = []
    draws: list[Draws] = []
    for size, stream in zip(chunks, streams, strict=True):
        if len(starts) >= count:
            break
        x0, drawn_draws = _draw(scenario, controller, size, stream, worst)
        index, _ = controller.select(x0)
        drawn = np.concatenate([np.flatnonzero(index == i)[:2] for i in np.unique(index)])
        starts += list(x0[drawn])  # by trajectory, then by draw
        if drawn_draws is not None:
            draws.append(drawn_draws.rows(drawn))
    if not starts:
        return []
    flown = None
    if draws:  # the same parameters and gusts as the chunks fly
        flown = Draws(
            parameters=np.concatenate([d.parameters for d in draws])[:count],
            gusts=np.concatenate([d.gusts for d in draws])[:count],
            start=np.zeros(min(count, len(starts))),
            errors=None
            if draws[0].errors is None
            else np.concatenate([d.errors for d in draws if d.errors is not None])[:count],
        )
    paths = run_paths_compiled(scenario, controller, np.array(starts[:count]), draws=flown)
    return [path[:: max(1, len(path) // 200)] for path in paths]


def _run_chunk_in_worker(
    task: tuple[Scenario, Path, int, np.random.SeedSequence, Draws | None],
) -> tuple[RunChecks, FloatArray, Hold]:
    scenario, controller_path, size, stream, worst = task  # the scenario given, pickled
    return _run_chunk(scenario, controller_path, size, stream, worst)


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
    for any executor and worker count; ``progress(runs)`` is called as chunks finish. Under a
    declared uncertainty (the module's docstring) the falsification search runs first: a share
    of every chunk's runs flies the worst case it found.
    """
    controller = load(controller_path)
    chunks = [chunk] * (samples // chunk) + ([samples % chunk] if samples % chunk else [])
    streams = np.random.SeedSequence(seed).spawn(len(chunks))
    searched_first = (
        None if scenario.uncertainty.empty else falsify(scenario, controller, seed=seed)
    )
    worst = None if searched_first is None else searched_first.worst_draws
    tasks = [
        (scenario, Path(controller_path), size, stream, worst)
        for size, stream in zip(chunks, streams, strict=True)
    ]
    executor = executor or SerialExecutor()
    # the report's paths and the falsification search run here while the chunks run in the
    # executor's workers (with the serial executor the two threads take turns)
    side = ThreadPoolExecutor(max_workers=1, thread_name_prefix="montecarlo-side")
    try:
        drawn = side.submit(_drawn_paths, scenario, controller, chunks, streams, drawn_paths, worst)
        searched = (
            side.submit(falsify, scenario, controller, seed=seed)
            if searched_first is None
            else None
        )
        outcomes = executor.map(
            _run_chunk_in_worker,
            tasks,
            done=None if progress is None else lambda i: progress(chunks[i]),
        )
        paths = drawn.result()
        falsification = searched.result() if searched is not None else searched_first
        assert falsification is not None  # searched first, or beside the chunks
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
    masks = _counted(scenario, checks)
    counts = {kind: int(mask.sum()) for kind, mask in masks.items()}
    counts["after_T"] = int(after_T.sum())
    failing = int(np.any([*masks.values(), after_T], axis=0).sum())
    bound = float(binomtest(failing, samples, alternative="less").proportion_ci(0.95).high)
    success = failing == 0
    after = (
        f"; {held} continued to T + {HOLD_SECONDS:g} s stayed in Goal (V / level <= "
        f"{hold_level:.3g})"
        if held and not counts.get("after_T")
        else ""
    )
    sampled = (
        ""
        if scenario.uncertainty.empty
        else " under the declared uncertainty (sampled parameters and gusts"
        + (", and measurement errors)" if scenario.uncertainty.measured else ")")
    )
    message = (
        (
            f"{samples} closed-loop runs{sampled}, 0 failures; failure probability <= {bound:.2e} "
            f"(95% Clopper-Pearson){after}"
        )
        if success
        else (
            f"{failing} of {samples} closed-loop runs{sampled} failed: "
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
        # the decay used, ||e(T)|| e^(lambda T) / ||e(0)||, means nothing when gusts push e(t)
        # from e(0) = 0 (the funnel still holds it: certified, and counted above)
        tube_final=checks.tube_final if scenario.uncertainty.empty else np.zeros(0),
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
        "uncertainty",
        "state_bounds",
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
