"""Monte Carlo throughput: closed-loop rollouts per second, measured side by side in one run.

The controller is ``reports/quadrotor_hill_flythrough/controller.json`` (copied to a temporary
folder so that a concurrent ``make synthesize`` cannot change it mid-run); if it is missing, the
pipeline is run into a temporary folder first (``--samples 1000``).

(a) Batched NumPy oracle: ``pipeline.numerics.closed_loop.simulate.check_runs`` on 10,000 initial
states
    drawn uniformly from Init: RK4 (4 substeps per Ts) on the whole batch around each selected
    trajectory, with every continuous-time check (clearance, goal, clipping, tube).
(a') Compiled: ``pipeline.numerics.closed_loop.rollouts.check_runs_compiled`` on the same states
(numba, one
    core), its largest difference to (a), and its rate against the issue's anchor of ~25,000
    rollouts/s per core (~75 kflop per quadrotor rollout at 2 Gflop/s).
(b) One at a time: ``select(x0)`` then ``xdot = f(x, controller(t, x))`` by ``solve_ivp``
    (DOP853, rtol = atol = 1e-8), one sample interval per call since ``u_ref`` jumps at the
    sample times, for 20 of the same initial states; only the clearance is checked.
(c) ``validate_closed_loop`` on 100,000 samples (10 chunks of 10,000) with 1 and 2 worker
    processes (``make_executor(None, jobs)``; the 2-worker time includes spawning the pool), then
    on 1,000,000 with 2 workers, measured. The falsification search and the report's paths run
    in the parent beside the chunks (the search is timed alone too).
(d) quadrotor_hill's shipped file (``make synthesize``), 2,000 runs under its declared
uncertainty continued to T + 10 s under its terminal law: ``hold_runs_compiled`` flying them to T
again against continuing from the states ``check_runs_compiled`` kept (``ends``, as the Monte
Carlo does), side by side, and whether the margins are the same.
Targets: (a) at least 50x the rollouts per second of (b) (issue 6); (a') >= 20,000 rollouts/s
on one core and (c) 10^6 samples under 60 s on 2 cores (issue 15).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from pipeline.controller import Controller, load
from pipeline.io.executor import make_executor
from pipeline.io.folders import default_output_folder
from pipeline.model import geometry
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.numerics.closed_loop.gusts import sample
from pipeline.numerics.closed_loop.rollouts import (
    HOLD_SECONDS,
    check_runs_compiled,
    hold_runs_compiled,
)
from pipeline.numerics.closed_loop.simulate import check_runs
from pipeline.numerics.closed_loop.worst_case import horizon
from pipeline.runtime.api import synthesize
from stages.montecarlo import falsify, validate_closed_loop

SCENARIO = "quadrotor_hill_flythrough"
HOLD_SCENARIO = "quadrotor_hill"  # (d): a file with a terminal law and a declared uncertainty
HOLD_BATCH = 2_000
BATCH = 10_000
SCALE_OUT = 100_000
SCALE_OUT_CHUNK = 10_000
PROJECTED = 1_000_000
ONE_AT_A_TIME = 20
ANCHOR_ROLLOUTS_PER_S = 25_000  # issue 15: ~75 kflop per rollout at 2 Gflop/s, one core
TARGET_ROLLOUTS_PER_S = 20_000
TARGET_MILLION_SECONDS = 60.0
SEED = 0


def _controller_file(folder: Path) -> tuple[Path, str]:
    """A private copy of the controller and where it came from (synthesized if missing)."""
    shipped = default_output_folder(SCENARIO) / "controller.json"  # ./reports/NAME
    target = folder / "controller.json"
    if shipped.is_file():
        shutil.copyfile(shipped, target)
        return target, str(shipped.relative_to(Path.cwd()))
    print(f"{shipped} is missing: synthesizing {SCENARIO} into a temporary folder (1000 samples)")
    result = synthesize(SCENARIO, out=folder / "out", samples=1000)
    if result.outputs.controller is None:
        raise RuntimeError(f"synthesize {SCENARIO}: {result.message}; no controller written")
    shutil.copyfile(result.outputs.controller, target)
    return target, f"freshly synthesized ({result.verdict.value})"


def rollout_solve_ivp(
    scenario: Scenario, controller: Controller, x0: np.ndarray, rtol: float = 1e-8
) -> float:
    """One closed-loop run from ``x0 (n,)`` by ``solve_ivp``; returns its smallest clearance."""
    index, _ = controller.select(x0)
    N = len(controller.trajectories[int(index)].u_ref)
    Ts = controller.Ts
    x, points = np.array(x0, dtype=np.float64), [np.asarray(x0)[None]]

    def field(t: float, state: np.ndarray) -> np.ndarray:
        return scenario.dynamics.f(state, controller(t, state, index))

    for k in range(N):  # u_ref is piecewise constant: integrate each sample interval on its own
        end = (k + 1) * Ts - 1e-9  # the left limit, as pipeline.numerics.closed_loop.simulate does
        solution = solve_ivp(field, (k * Ts, end), x, method="DOP853", rtol=rtol, atol=rtol)
        if not solution.success:
            raise RuntimeError(f"solve_ivp failed on interval {k}: {solution.message}")
        x = solution.y[:, -1]
        points.append(solution.y.T[1:])
    positions = scenario.positions(np.concatenate(points))
    return float(
        min(geometry.distance(positions, unsafe).min() for unsafe in scenario.unsafe.values())
    )


def run() -> None:
    scenario = load_scenario(SCENARIO, check_demos=False)
    with tempfile.TemporaryDirectory(prefix="bench_montecarlo_") as tmp:
        path, source = _controller_file(Path(tmp))
        controller = load(path)
        rng = np.random.default_rng(SEED)
        lo, hi = scenario.init_lower, scenario.init_upper
        x0 = lo + (hi - lo) * rng.random((BATCH, scenario.n))
        lengths = [len(tr.u_ref) for tr in controller.trajectories]
        print(
            f"{SCENARIO}, controller {source}: {len(lengths)} trajectories of "
            f"{min(lengths)}-{max(lengths)} samples (Ts = {controller.Ts:g} s);"
            f" {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}"
        )

        check_runs(scenario, controller, x0[:50])  # warm-up
        start = time.perf_counter()
        checks, _ = check_runs(scenario, controller, x0)
        batched = time.perf_counter() - start
        failed = int(np.any(list(checks.failures().values()), axis=0).sum())

        start = time.perf_counter()
        clearance = [rollout_solve_ivp(scenario, controller, x) for x in x0[:ONE_AT_A_TIME]]
        single = time.perf_counter() - start
        excess = np.array(clearance) - checks.clearance[:ONE_AT_A_TIME]
        rate_batched, rate_single = BATCH / batched, ONE_AT_A_TIME / single
        print(
            f"(a) batched check_runs, {BATCH:,} rollouts: {batched:7.2f} s ="
            f" {rate_batched:9.1f} rollouts/s ({failed} failed checks)"
        )
        print(
            f"(b) solve_ivp DOP853 rtol 1e-8, {ONE_AT_A_TIME} one at a time: {single:7.2f} s ="
            f" {rate_single:9.2f} rollouts/s"
            f" (its clearance minus (a)'s bound: {excess.min():.3f}..{excess.max():.3f} m)"
        )
        check_runs_compiled(scenario, controller, x0[:50])  # compilation (cached on disk)
        start = time.perf_counter()
        compiled = check_runs_compiled(scenario, controller, x0)
        rate_compiled = BATCH / (time.perf_counter() - start)
        difference = max(
            float(np.max(np.abs(getattr(compiled, name) - getattr(checks, name))))
            for name in ("clearance", "goal_margin", "input_slack", "tube_tightness")
        )
        print(
            f"(a') compiled kernel, {BATCH:,} rollouts: {rate_compiled:9.1f} rollouts/s ="
            f" {rate_compiled / rate_batched:.1f}x (a), {rate_compiled / ANCHOR_ROLLOUTS_PER_S:.2f}"
            f" of the ~{ANCHOR_ROLLOUTS_PER_S:,}/s flop anchor; largest margin difference to (a)"
            f" {difference:.1e}"
        )
        print(
            f"  [{'met' if rate_compiled >= TARGET_ROLLOUTS_PER_S else 'MISSED'}] >= "
            f"{TARGET_ROLLOUTS_PER_S:,} rollouts/s on one core"
        )
        ratio = rate_batched / rate_single
        print(
            f"  [{'met' if ratio >= 50 else 'MISSED'}] batched >= 50x one-at-a-time: {ratio:.0f}x"
        )

        start = time.perf_counter()
        falsify(scenario, controller, seed=SEED)
        search = time.perf_counter() - start
        seconds = {}
        for jobs in (1, 2):
            executor = make_executor(None, jobs)
            start = time.perf_counter()
            try:
                result = validate_closed_loop(
                    scenario,
                    path,
                    samples=SCALE_OUT,
                    seed=SEED,
                    chunk=SCALE_OUT_CHUNK,
                    executor=executor,
                )
            finally:
                executor.close()
            seconds[jobs] = time.perf_counter() - start
            print(
                f"(c) validate_closed_loop, {SCALE_OUT:,} samples, jobs={jobs}:"
                f" {seconds[jobs]:6.2f} s"
                f" ({result.message})"
            )
        print(
            f"  speed-up with 2 workers: {seconds[1] / seconds[2]:.2f}x (the pool's start-up"
            f" included); the falsification search alone: {search:.2f} s"
        )
        executor = make_executor(None, 2)
        start = time.perf_counter()
        try:
            result = validate_closed_loop(
                scenario,
                path,
                samples=PROJECTED,
                seed=SEED,
                chunk=4 * SCALE_OUT_CHUNK,
                executor=executor,
            )
        finally:
            executor.close()
        million = time.perf_counter() - start
        print(
            f"(c) validate_closed_loop, {PROJECTED:,} samples, jobs=2: {million:6.2f} s"
            f" ({result.message})"
        )
        print(
            f"  [{'met' if million < TARGET_MILLION_SECONDS else 'MISSED'}] 10^6 runs under"
            f" {TARGET_MILLION_SECONDS:.0f} s on 2 cores: {million / TARGET_MILLION_SECONDS:.2f} of"
            " the limit"
        )
        _continuation()


def _continuation() -> None:
    """(d) Runs continued to T + 10 s under quadrotor_hill's terminal law (its shipped file,
    uncertainty drawn as the Monte Carlo draws it), side by side: flown to T again inside
    ``hold_runs_compiled`` against continued from the states the checks kept (``ends``, as the
    Monte Carlo does)."""
    shipped = default_output_folder(HOLD_SCENARIO) / "controller.json"
    if not shipped.is_file():
        print(f"(d) skipped: {shipped} is missing (make synthesize writes it)")
        return
    scenario = load_scenario(HOLD_SCENARIO, check_demos=False)
    controller = load(shipped)
    rng = np.random.default_rng(SEED)
    lo, hi = scenario.init_lower, scenario.init_upper
    x0 = lo + (hi - lo) * rng.random((HOLD_BATCH, scenario.n))
    draws = sample(scenario.uncertainty, rng, HOLD_BATCH, horizon(controller, HOLD_SECONDS))
    hold_runs_compiled(scenario, controller, x0[:20], draws=draws.rows(np.arange(20)))  # compile
    start = time.perf_counter()
    checks = check_runs_compiled(scenario, controller, x0, draws=draws)
    to_T = time.perf_counter() - start
    start = time.perf_counter()
    again = hold_runs_compiled(scenario, controller, x0, draws=draws)
    flown_again = time.perf_counter() - start
    start = time.perf_counter()
    continued = hold_runs_compiled(scenario, controller, x0, draws=draws, ends=checks.final_state)
    from_ends = time.perf_counter() - start
    same = all(
        np.array_equal(getattr(again, name), getattr(continued, name))
        for name in ("level_ratio", "clearance", "path_goal_margin", "final_state")
    )
    print(
        f"(d) {HOLD_SCENARIO}, {HOLD_BATCH:,} runs under the declared uncertainty: checks to T "
        f"{to_T:.2f} s; the continuation to T + {HOLD_SECONDS:g} s flown to T again "
        f"{flown_again:.2f} s, from the checks' end states {from_ends:.2f} s (the same margins: "
        f"{same})"
    )
    ratio = (to_T + flown_again) / (to_T + from_ends)
    print(f"  a Monte Carlo run with its continuation: {ratio:.2f}x the throughput of flying twice")
