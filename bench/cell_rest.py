"""The uncertified minimum time to rest from every corner of a start's cell of Init (issue 29).

A funnel must take every start in its cell of Init (``pipeline.numerics.funnel.cells``) to Goal
by its ``T``, so ``max over the cell of T_rest(x0)`` is a fairer floor for it than ``T_rest``
from the demonstration's start alone (``bench.bench_certificates``). The largest over the
cell's corners is printed beside the start's (a corner, not a proof that no interior start is
slower: the minimum time is not convex in ``x0``).

Run: ``python -m bench.cell_rest SCENARIO RUN_FOLDER [DEMO_INDICES]`` (0-based, comma-separated)
on a finished funnel run of ``SCENARIO`` (its ``feedback`` artifact assigns the cells among all
the scenario's demos, as the funnel stage does; its ``summary.json`` gives each demo's ``T``),
e.g. ``python -m bench.cell_rest quadrotor_hill_gusty reports/quadrotor_hill_gusty 1,3``. Each
corner is one IPOPT minimum-time solve (``bench.bench_optimize``): 32 corners took 182 s for
quadrotor_hill_gusty's demo_02. Needs the ``bench`` extra (casadi).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.bench_optimize import ipopt_minimum_time
from bench.uncertified import uncertified_constraints
from pipeline.io.artifacts import read_stored
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.numerics.funnel.cells import PAD, init_cells
from pipeline.numerics.optimize.penalties import Constraints
from pipeline.runtime.registry import RESULT_TYPES


def _rest_time(scenario: Scenario, rest: Constraints, demo: int, x0: np.ndarray) -> float:
    """IPOPT's minimum time to rest in Goal (``rest``: ``uncertified_constraints`` at rest) from
    ``x0 (n,)`` (demo ``demo``'s flight as the initial guess); NaN where it finds none."""
    moved = dataclasses.replace(scenario.demos[demo], x0=x0)
    demos = tuple(moved if j == demo else d for j, d in enumerate(scenario.demos))
    found = ipopt_minimum_time(dataclasses.replace(scenario, demos=demos), demo, rest)
    return found.N * scenario.Ts if found.U is not None else float("nan")


def compare(name: str, run: Path, only: list[int] | None = None) -> None:
    """One line per demo: its certified ``T``, ``T_rest`` from its start and the largest from
    its cell's corners (those IPOPT solved, counted), with both ratios and the slowest corner's
    offset from the start."""
    scenario = load_scenario(name)
    stored = read_stored(run / "artifacts" / "feedback", RESULT_TYPES)
    if stored is None or stored.result.P is None:
        raise SystemExit(f"{run}: no certified feedback artifact (run the synthesis first)")
    starts = np.array([demo.x0 for demo in scenario.demos])
    cells = init_cells(scenario.init_lower, scenario.init_upper, starts, stored.result.P)
    summary = json.loads((run / "summary.json").read_text())
    T_of = {row["demo"]: row["T_optimized"] for row in summary["demos"]}
    rest = uncertified_constraints(scenario, at_rest=True)
    for i, demo in enumerate(scenario.demos):
        if only is not None and i not in only:
            continue
        if not len(cells[i]):
            print(f"{demo.name}: owns no cell of Init", flush=True)
            continue
        start = time.perf_counter()
        T = T_of[demo.name]
        from_start = _rest_time(scenario, rest, i, starts[i])
        corners = starts[i] + cells[i] / (1 + PAD)  # the cell's own corners, unpadded
        times = np.array([_rest_time(scenario, rest, i, corner) for corner in corners])
        solved = np.isfinite(times)
        worst = max(from_start, float(np.nanmax(times, initial=from_start)))
        offset = (
            np.round(corners[int(np.nanargmax(times))] - starts[i], 3).tolist()
            if solved.any() and np.nanmax(times) > from_start
            else "none slower than the start"
        )
        print(
            f"{demo.name}: T {T:.2f} s, T_rest from the start {from_start:.2f} s (ratio "
            f"{T / from_start:.3f}), largest over the {solved.sum()} of the cell's "
            f"{len(corners)} corners IPOPT solved "
            f"{worst:.2f} s (ratio {T / worst:.3f}, corner {offset}); "
            f"{time.perf_counter() - start:.0f} s",
            flush=True,
        )


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        raise SystemExit("usage: python -m bench.cell_rest SCENARIO RUN_FOLDER [DEMO_INDICES]")
    demos = [int(v) for v in sys.argv[3].split(",")] if len(sys.argv) == 4 else None
    compare(sys.argv[1], Path(sys.argv[2]), demos)
