"""Report stage, side by side: this tree against the code before the report was reworked.

Issue 15's report row (``bench_speed`` (a)) measures this tree alone; this one runs the report
stage of quadrotor_hill_flythrough with an empty figure cache alternately with ``BASELINE``
(exported by ``git archive`` into a temporary folder; ``REPORT_BASELINE=REV`` picks another
revision), each in a fresh interpreter on its own copy of one finished run, so that both see the
same machine load. The baseline knew quadrotor_hill_flythrough as ``quadrotor_hill`` (renamed
2026-11-27): each tree loads it by the name its own ``scenarios/`` has. Prints every round and the
medians; skipped outside a git checkout, or (with the baseline's error) where the baseline cannot
write this tree's run.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.bench_speed import ROOT, finished_run

BASELINE = "c7777b6"  # main before issue 18's report rework (matplotlib-paginated PDF)
ROUNDS = 3
PROGRAM = """
import shutil, sys, time
from pathlib import Path
from pipeline.model.scenario import load_scenario
from pipeline.runtime.stored import load_report_data
from stages.report import write_reports
out = Path(sys.argv[1])
scenario = load_scenario(sys.argv[2])
shutil.rmtree(out / "artifacts" / "figures", ignore_errors=True)
start = time.perf_counter()
result = write_reports(load_report_data(scenario, out))
print(f"{time.perf_counter() - start:.3f}|{result.message}")
"""


SCENARIO = "quadrotor_hill_flythrough"
FORMER_NAME = "quadrotor_hill"  # the same scenario's name before 2026-11-27


def _scenario_in(tree: Path) -> str:
    """The name ``tree``'s own ``scenarios/`` gives quadrotor_hill_flythrough."""
    return SCENARIO if (tree / "scenarios" / SCENARIO).is_dir() else FORMER_NAME


def _once(tree: Path, run: Path, copy: Path) -> tuple[float, str]:
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run, copy)
    done = subprocess.run(
        [sys.executable, "-c", PROGRAM, str(copy), _scenario_in(tree)],
        cwd=tree,
        env={**os.environ, "PYTHONPATH": str(tree)},
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"report stage in {tree} failed: {done.stderr[-1500:]}")
    seconds, message = done.stdout.strip().splitlines()[-1].split("|", 1)
    return float(seconds), message


def run() -> None:
    baseline = os.environ.get("REPORT_BASELINE", BASELINE)
    with tempfile.TemporaryDirectory(prefix="bench_report_") as tmp:
        folder = Path(tmp)
        old = folder / "baseline"
        old.mkdir()
        archive = subprocess.run(
            ["git", "archive", baseline], cwd=ROOT, capture_output=True, check=False
        )
        if archive.returncode != 0:
            print(f"skipped: cannot export {baseline} ({archive.stderr.decode().strip()})")
            return
        subprocess.run(["tar", "-x", "-C", str(old)], input=archive.stdout, check=True)
        run_folder, source = finished_run(folder)
        print(f"report stage of quadrotor_hill_flythrough, empty figure cache, run {source}")
        trees = {f"baseline {baseline}": old, "this tree": ROOT}
        times: dict[str, list[float]] = {name: [] for name in trees}
        for k in range(ROUNDS):
            for name, tree in trees.items():
                try:
                    seconds, message = _once(tree, run_folder, folder / f"copy-{k}")
                except RuntimeError as error:
                    if tree is not old:
                        raise
                    last = str(error).strip().splitlines()[-1]
                    print(f"skipped: the baseline {baseline} cannot write this tree's run ({last})")
                    return
                times[name].append(seconds)
                load = os.getloadavg()[0]
                print(f"  round {k + 1} {name:>18}: {seconds:5.2f} s (load {load:.1f}) {message}")
        old_median, new_median = (statistics.median(t) for t in times.values())
        print(
            f"  median: baseline {old_median:.2f} s, this tree {new_median:.2f} s "
            f"({new_median / old_median:.2f} of the baseline)"
        )
