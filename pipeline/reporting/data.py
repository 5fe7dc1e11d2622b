"""What a report is made from: ``summary.json`` and the stage results of one output folder.

The stage cache (``pipeline.runtime.stored``) reads them; nothing is recomputed here except
re-simulating the nominal trajectories from their saved inputs (for drawing) and one closed-loop
run for the inputs figure.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.controller import Controller, load
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.reporting.summary import Summary

if TYPE_CHECKING:  # the stage results, read from artifacts (reporting sits below stages)
    from pipeline.results.certify import CertificationResult
    from pipeline.results.controller import ControllerResult
    from pipeline.results.coverage import CoverageResult
    from pipeline.results.feedback import FeedbackResult
    from pipeline.results.montecarlo import MonteCarloResult
    from pipeline.results.optimize import OptimizeResult
    from pipeline.results.radius import RadiusResult
    from pipeline.results.stress import StressResult

STAGES = (
    "feedback",
    "radius_demos",
    "coverage_demos",
    "optimize",
    "radius_optimized",
    "coverage_optimized",
    "controller",
    "montecarlo",
)


@dataclass(frozen=True, kw_only=True)
class ReportData:
    """The run's summary and stage results (as the stages returned them).

    Attributes:
      feedback ... montecarlo: the stage results (``FeedbackResult``, ``OptimizeResult``, ...).
      keys: stage name -> the input key its artifact was stored under.
      certification: certify's check of the run's ``controller.json`` (the run's own; a report
        rebuilt from the folder certifies the file again, ``pipeline.runtime.stored``).
      stress: the stress test's result (None: the run had none).
      demo_paths, final_paths: the demonstrations and the final nominal trajectories (the
        optimized input where optimization succeeded, the demo's otherwise), simulated again.
    """

    scenario: Scenario
    out: Path
    summary: Summary
    feedback: FeedbackResult
    radius_demos: tuple[RadiusResult, ...]
    coverage_demos: CoverageResult
    optimize: OptimizeResult
    radius_optimized: tuple[RadiusResult, ...]
    coverage_optimized: CoverageResult
    controller: ControllerResult
    montecarlo: MonteCarloResult
    certification: CertificationResult
    stress: StressResult | None = None
    keys: Mapping[str, str]
    demo_paths: tuple[Trajectory, ...]
    final_paths: tuple[Trajectory, ...]
    source: Path | None = None  # the run's folder when the report is written elsewhere
    # a run's staging folder (OUT/.staging, ``pipeline.runtime.outdir``): its controller.json
    # is the one reported, and the reports are written there, then published into ``out``
    staging: Path | None = None

    @property
    def run_folder(self) -> Path:
        """The folder of the run (``summary.json``, ``controller.json``, ``artifacts/``)."""
        return self.out if self.source is None else self.source

    @property
    def reports_folder(self) -> Path:
        """Where the report files are written: ``staging`` during a run, else ``out``."""
        return self.out if self.staging is None else self.staging

    @property
    def controller_path(self) -> Path:
        return (self.run_folder if self.staging is None else self.staging) / "controller.json"

    @functools.cached_property
    def law(self) -> Controller:
        """controller.json as written (its tube ``rate`` is the held law's with a feedback
        period; ``feedback.rate`` is the continuous design's)."""
        return load(self.controller_path)

    @property
    def funnel(self) -> bool:
        """The run shipped the funnel certificate (``safety-controller/2``, one funnel per
        trajectory); the constant certificate's stage results are then verified, not shipped."""
        return self.summary.certificate == "funnel"

    @functools.cached_property
    def shipped_paths(self) -> tuple[Trajectory, ...]:
        """The nominal trajectories the run ships: ``final_paths`` in a constant run; in a funnel
        run controller.json's (re-optimized nominals and dropped funnels included), in the file's
        order, each with ``ts (N+1,)``, ``us = u_ref (N, m)`` and the file's fine grid ``t``,
        ``x_ref`` as ``dense_ts``, ``dense_xs`` (``xs`` read off it at ``k Ts``)."""
        if not self.funnel:
            return self.final_paths
        Ts = self.law.Ts
        paths = []
        for tr in self.law.trajectories:
            ts = Ts * np.arange(len(tr.u_ref) + 1, dtype=np.float64)
            xs = np.stack([np.interp(ts, tr.t, tr.x_ref[:, i]) for i in range(tr.x_ref.shape[1])])
            paths.append(Trajectory(ts=ts, xs=xs.T, us=tr.u_ref, dense_ts=tr.t, dense_xs=tr.x_ref))
        return tuple(paths)

    @functools.cached_property
    def shipped_demos(self) -> tuple[int, ...]:
        """For each shipped trajectory, the index of the demonstration it starts from (the
        optimizer keeps each demonstration's start)."""
        if not self.funnel:
            return tuple(range(len(self.final_paths)))
        starts = np.stack([demo.x0 for demo in self.scenario.demos])  # (D, n)
        return tuple(
            int(np.argmin(np.abs(starts - tr.x0).max(axis=1))) for tr in self.law.trajectories
        )

    def shipped_index(self, demo: int) -> int | None:
        """The shipped trajectory started from demonstration ``demo`` (None: none shipped)."""
        return next((i for i, d in enumerate(self.shipped_demos) if d == demo), None)

    def fingerprint(self, *reads: object) -> str:
        """SHA-256 of what a figure reads: the scenario file, the demonstrations, and for each
        of ``reads`` the stored key of that stage (a name in ``STAGES``) or the value itself."""
        digest = hashlib.sha256(self.scenario.source_hash.encode())
        for demo in self.scenario.demos:
            digest.update(np.ascontiguousarray(demo.x0, dtype=np.float64).tobytes())
            digest.update(np.ascontiguousarray(demo.us, dtype=np.float64).tobytes())
        for item in reads:
            value = self.keys[item] if isinstance(item, str) and item in STAGES else item
            digest.update(f"\x00{item}={value}".encode())
        return digest.hexdigest()


def simulate_all(
    scenario: Scenario, starts: Sequence[FloatArray], inputs: Sequence[FloatArray]
) -> list[Trajectory]:
    """Simulate every ``(x0 (n,), us (N_i, m))`` in one batch: inputs padded to the longest
    with their last sample (RK4 is causal, so each trajectory's first ``N_i`` steps are its own),
    then cut back."""
    longest = max(len(us) for us in inputs)
    padded = np.stack([np.vstack([us, np.repeat(us[-1:], longest - len(us), 0)]) for us in inputs])
    batch = simulate(scenario.dynamics, np.stack(starts), padded, scenario.Ts)
    s = (len(batch.dense_ts) - 1) // longest  # substeps
    return [
        Trajectory(
            ts=batch.ts[: len(us) + 1],
            xs=batch.xs[i, : len(us) + 1],
            us=np.asarray(us),
            dense_ts=batch.dense_ts[: len(us) * s + 1],
            dense_xs=batch.dense_xs[i, : len(us) * s + 1],
        )
        for i, us in enumerate(inputs)
    ]


def report_data(
    scenario: Scenario,
    out: Path,
    summary: Summary,
    results: Mapping[str, Any],
    keys: Mapping[str, str],
    *,
    certification: CertificationResult,
    stress: StressResult | None = None,
    source: Path | None = None,
    staging: Path | None = None,
) -> ReportData:
    """``ReportData`` from a run's summary and stage ``results`` (stage name -> result, as read by
    the stage cache, ``pipeline.runtime.stored``), certify's check of its ``controller.json``
    and its stress test (if any); re-simulates the nominal trajectories."""
    final_inputs = [
        opt.u if opt.success else demo.us
        for demo, opt in zip(scenario.demos, results["optimize"].trajectories, strict=True)
    ]
    paths = simulate_all(
        scenario, [d.x0 for d in scenario.demos] * 2, [d.us for d in scenario.demos] + final_inputs
    )
    demo_paths, final_paths = paths[: len(scenario.demos)], paths[len(scenario.demos) :]
    return ReportData(
        scenario=scenario,
        out=Path(out),
        summary=summary,
        keys=keys,
        certification=certification,
        stress=stress,
        demo_paths=tuple(demo_paths),
        final_paths=tuple(final_paths),
        source=None if source is None else Path(source),
        staging=None if staging is None else Path(staging),
        **{stage: results[stage] for stage in STAGES},
    )
