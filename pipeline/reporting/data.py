"""What a report is made from: ``summary.json`` and the stage artifacts of one output folder.

Nothing is recomputed except re-simulating the nominal trajectories from their saved inputs (for
drawing) and one closed-loop run for the inputs figure.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.io.artifacts import read_result
from pipeline.io.errors import UserError
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.reporting.summary import Summary

if TYPE_CHECKING:  # the stage results, read from artifacts (reporting sits below stages)
    from stages.controller import ControllerResult
    from stages.coverage import CoverageResult
    from stages.feedback import FeedbackResult
    from stages.montecarlo import MonteCarloResult
    from stages.optimize import OptimizeResult
    from stages.radius import RadiusResult

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


@dataclass(frozen=True)
class ReportData:
    """The run's summary and stage results (as the stages returned them).

    Attributes:
      feedback ... montecarlo: the stage results (``FeedbackResult``, ``OptimizeResult``, ...).
      keys: stage name -> the input key its artifact was stored under.
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
    keys: Mapping[str, str]
    demo_paths: tuple[Trajectory, ...]
    final_paths: tuple[Trajectory, ...]

    @property
    def controller_path(self) -> Path:
        return self.out / "controller.json"


def _simulate_all(
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


def _missing(path: Path, scenario: Scenario, what: str) -> UserError:
    return UserError(
        f"{what}; run `python -m pipeline synthesize {scenario.name} --out {path.parent}` "
        "first (the report is built from a finished run's output folder)",
        file=path,
    )


def load_report_data(scenario: Scenario, out: Path) -> ReportData:
    """Read ``out/summary.json`` and ``out/artifacts/<stage>``; a missing or unreadable file is a
    ``UserError`` naming it and the command that writes it."""
    out = Path(out)
    summary_path = out / "summary.json"
    if not summary_path.is_file():
        raise _missing(summary_path, scenario, "summary.json not found")
    try:
        summary = Summary.from_json(json.loads(summary_path.read_text()))
    except json.JSONDecodeError as error:
        raise _missing(summary_path, scenario, f"not valid JSON ({error})") from None
    except ValueError as error:
        raise _missing(summary_path, scenario, f"not a run summary ({error})") from None
    found = summary.reproducibility.scenario_sha256
    if found != scenario.source_hash:
        raise UserError(
            f"the run was made from another version of {scenario.path.name}",
            file=summary_path,
            found=found,
            expected=f"scenario sha256 {scenario.source_hash}; re-run synthesize",
        )
    results, keys = {}, {}
    for stage in STAGES:
        stem = out / "artifacts" / stage
        json_path = stem.with_suffix(".json")
        if not json_path.is_file():
            raise _missing(json_path, scenario, f"artifact of stage '{stage}' not found")
        try:
            results[stage] = read_result(stem)
            keys[stage] = str(json.loads(json_path.read_text())["key"])
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
            what = f"artifact of stage '{stage}' unreadable ({error})"
            raise _missing(json_path, scenario, what) from None
    if not (out / "controller.json").is_file():
        raise _missing(out / "controller.json", scenario, "controller.json not found")
    if len(results["optimize"].trajectories) != len(scenario.demos):
        raise _missing(
            out / "artifacts" / "optimize.json",
            scenario,
            f"artifact holds {len(results['optimize'].trajectories)} trajectories for "
            f"{len(scenario.demos)} demos",
        )
    final_inputs = [
        opt.u if opt.success else demo.us
        for demo, opt in zip(scenario.demos, results["optimize"].trajectories, strict=True)
    ]
    paths = _simulate_all(
        scenario, [d.x0 for d in scenario.demos] * 2, [d.us for d in scenario.demos] + final_inputs
    )
    demo_paths, final_paths = paths[: len(scenario.demos)], paths[len(scenario.demos) :]
    return ReportData(
        scenario=scenario,
        out=out,
        summary=summary,
        keys=keys,
        demo_paths=tuple(demo_paths),
        final_paths=tuple(final_paths),
        **results,
    )
