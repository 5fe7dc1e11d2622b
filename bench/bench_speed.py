"""Issue 15's remaining rows, each measured here and printed as a ratio against its limit.

A finished run of quadrotor_hill_flythrough is needed: ``reports/quadrotor_hill_flythrough`` is
copied to a temporary folder (so that a concurrent ``make synthesize`` cannot change it mid-run); if
it is missing, the pipeline is run into the temporary folder first (``--samples 1000``).

(a) Report stage, as ``synthesize`` runs it (``write_reports(staged_report_data(...))``: read
    the artifacts, write report.html, scenario.png and report.pdf (typeset by Typst) into the
    staging folder; the scenario and the run's summary loaded before; ``report`` adds certify,
    ~0.3 s): with an empty figure cache (every figure drawn, the PDF typeset) and again with the
    cache of the first (nothing changed: every figure and the PDF reused); limit 3 s.
    ``bench_report`` runs the same stage side by side with the code before the report rework.
(b) Monte Carlo stage at the default size (``RunOptions().samples``) with 2 worker processes,
    as ``synthesize --jobs 2`` runs it (pool start-up and the falsification search included);
    limit 10 s. The rollouts/s against the flop anchor and the 10^6-run wall time are in
    ``bench_montecarlo``.
(c) Start-up: ``python -m pipeline --help`` in a fresh interpreter, best of 5; limit 0.5 s.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.timing import best_time
from pipeline.io.errors import UserError
from pipeline.io.executor import make_executor
from pipeline.io.folders import default_output_folder
from pipeline.model.scenario import load_scenario
from pipeline.reporting.summary import Summary
from pipeline.runtime.api import synthesize
from pipeline.runtime.options import RunOptions
from pipeline.runtime.orchestrator import rebuild_reports
from pipeline.runtime.stored import staged_report_data
from stages.certify import certify_controller
from stages.montecarlo import validate_closed_loop
from stages.report import write_reports

SCENARIO = "quadrotor_hill_flythrough"
REPORT_LIMIT = 3.0  # s
MONTE_CARLO_LIMIT = 10.0  # s, at the default size on 2 cores
STARTUP_LIMIT = 0.5  # s
ROOT = Path(__file__).resolve().parents[1]


def finished_run(folder: Path) -> tuple[Path, str]:
    """A private copy of a finished run of ``SCENARIO`` and where it came from."""
    shipped = default_output_folder(SCENARIO)  # ./reports/NAME
    target = folder / SCENARIO
    if (shipped / "summary.json").is_file() and (shipped / "artifacts").is_dir():
        shutil.copytree(shipped, target)
        try:
            rebuild_reports(SCENARIO, target)  # the run must be current to be reported
            return target, str(shipped)
        except UserError as error:  # stale or failed run: make a fresh one below
            print(f"{shipped} cannot be reported ({error}); synthesizing a fresh run")
            shutil.rmtree(target)
    result = synthesize(SCENARIO, out=target, samples=1000)
    if not (target / "summary.json").is_file():
        raise RuntimeError(f"synthesize {SCENARIO}: {result.message}; no summary written")
    return target, f"freshly synthesized ({result.verdict.value})"


def _row(what: str, seconds: float, limit: float) -> None:
    verdict = "met" if seconds <= limit else "MISSED"
    ratio = seconds / limit
    print(f"  [{verdict}] {what}: {seconds:6.2f} s = {ratio:.2f} of the {limit:g} s limit")


def run() -> None:
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(prefix="bench_speed_") as tmp:
        out, source = finished_run(Path(tmp))
        print(f"(a) report stage of {SCENARIO}, run {source}:")
        scenario = load_scenario(SCENARIO)
        summary = Summary.from_json(json.loads((out / "summary.json").read_text()))
        staging = out / ".staging"  # where a run writes its controller.json and reports
        staging.mkdir(exist_ok=True)
        shutil.copy(out / "controller.json", staging / "controller.json")
        # certify's check of the file, as the run hands it to the report (not timed; no stress)
        certification = certify_controller(scenario, staging / "controller.json")
        for case in ("empty figure cache", "nothing changed (figures and PDF reused)"):
            if case.startswith("empty"):
                shutil.rmtree(out / "artifacts" / "figures", ignore_errors=True)
            start = time.perf_counter()
            data = staged_report_data(scenario, out, staging, summary, certification, None)
            result = write_reports(data)
            _row(case, time.perf_counter() - start, REPORT_LIMIT)
            print(f"      {result.message}")

        samples = RunOptions().samples
        executor = make_executor(None, 2)
        start = time.perf_counter()
        try:
            mc = validate_closed_loop(
                scenario, out / "controller.json", samples=samples, executor=executor
            )
        finally:
            executor.close()
        print(f"(b) Monte Carlo stage, default {samples:,} samples, --jobs 2: {mc.message}")
        _row("montecarlo stage", time.perf_counter() - start, MONTE_CARLO_LIMIT)

    command = [sys.executable, "-m", "pipeline", "--help"]
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}

    def start_up() -> None:
        subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, check=True)

    print("(c) start-up of `python -m pipeline --help`, best of 5:")
    _row("start-up", best_time(start_up, repeat=5), STARTUP_LIMIT)
