"""The stage cache read back for a report: ``summary.json``, ``artifacts/<stage>`` and the run's
input manifest ``artifacts/inputs.json`` (the scenario file's hash, each demo's parsed values,
the hash of the ``controller.json`` the run certified and the content hash of every stage result
the report reads).

``report`` rebuilds from these without recomputing a stage, but it does not take the verdict
from ``summary.json``: it certifies ``controller.json`` again (stage ``certify``), reads the
Monte Carlo result whose key names that file's hash, and derives the verdict, the claims' kinds
and the numbers that carry them with the run's own functions (``pipeline.runtime.verdict``).
From ``summary.json`` it keeps only what describes the run and carries no verdict: the per-demo
table, the durations and clearances, the claims' wording, timings and versions. Any missing,
corrupt, mismatched or incomplete file is a ``UserError`` naming it and the command that writes
it again.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.controller import Controller, ControllerFormatError, load
from pipeline.io.artifacts import (
    ArtifactError,
    atomic_write_json,
    file_hash,
    inputs_key,
    read_stored,
)
from pipeline.io.errors import UserError
from pipeline.io.files import TEXT_MAX_BYTES, FileRefused, is_regular, read_text
from pipeline.model.scenario import Scenario
from pipeline.reporting.data import STAGES, ReportData, report_data
from pipeline.reporting.summary import StressSummary, Summary, Verdict
from pipeline.results.certify import CertificationResult
from pipeline.results.stage import FileInput
from pipeline.results.stress import StressResult
from pipeline.runtime import run_inputs
from pipeline.runtime.outdir import INCOMPLETE, MANIFEST, check_complete
from pipeline.runtime.registry import RESULT_TYPES
from pipeline.runtime.runner import stage_key
from pipeline.runtime.summary import stress_summary
from pipeline.runtime.verdict import (
    Evidence,
    after_horizon,
    certificate_claims,
    certification_summary,
    controller_summary,
    feedback_summary,
    montecarlo_claims,
    montecarlo_summary,
)
from stages.certify import certify_controller
from stages.coverage import CoverageResult, cover_balls
from stages.montecarlo import MONTECARLO, MonteCarloInputs
from stages.stress import STRESS, StressInputs

# the stage results the report and the verdict read; the manifest names each by content hash
# (and "stress" when the run had the stress test)
EVIDENCE_STAGES = (*STAGES, "covering_radius")
CLAIMS = 5  # the certificate's two, after T, Monte Carlo, falsification (runtime.summary)


def demo_fingerprints(scenario: Scenario) -> dict[str, str]:
    """Demo name -> hash of its parsed ``x0`` and inputs (not the file's bytes: comments and
    formatting do not count)."""
    return {d.name: inputs_key(d.x0, d.us) for d in scenario.demos}


def write_manifest(
    scenario: Scenario,
    folder: Path,
    controller_sha256: str,
    stages: Mapping[str, str],
    report_key: str,
) -> None:
    """Write ``folder/inputs.json``: what the run was made from (for ``report`` to check against
    the current files), the hash of the ``controller.json`` it certified, the content hash of
    each stage result in ``stages`` (name -> hash) and the key of the reports it published."""
    atomic_write_json(
        Path(folder) / MANIFEST,
        {
            "scenario": scenario.name,
            "scenario_sha256": scenario.source_hash,
            "demos": demo_fingerprints(scenario),
            "controller_sha256": controller_sha256,
            "stages": dict(stages),
            "report_key": report_key,
        },
    )


def published_report_key(out: Path) -> str | None:
    """The key of the reports published in ``out`` (None: none, or a publish cut short)."""
    if (Path(out) / INCOMPLETE).exists():
        return None
    try:
        manifest = json.loads(read_text(Path(out) / "artifacts" / MANIFEST, TEXT_MAX_BYTES))
    except (OSError, FileRefused, ValueError, RecursionError):
        return None
    key = manifest.get("report_key") if isinstance(manifest, dict) else None
    return key if isinstance(key, str) else None


def _rerun(path: Path, scenario: Scenario, what: str) -> UserError:
    folder = path.parent.parent if path.parent.name == "artifacts" else path.parent
    return UserError(
        f"{what}; run `python -m pipeline synthesize {scenario.name} --out {folder}` "
        "first (the report is built from a finished run's output folder)",
        file=path,
    )


def _read_json(path: Path, scenario: Scenario, what: str) -> Any:
    """``path`` parsed: a regular file of at most ``TEXT_MAX_BYTES`` (``pipeline.io.files``)."""
    try:
        return json.loads(read_text(path, TEXT_MAX_BYTES))
    except FileNotFoundError:
        raise _rerun(path, scenario, f"{what} not found") from None
    except FileRefused as error:
        raise _rerun(path, scenario, f"{what} {error.reason}") from None
    except (OSError, ValueError, RecursionError) as error:
        raise _rerun(path, scenario, f"{what} unreadable ({type(error).__name__})") from None


def _check_inputs(scenario: Scenario, out: Path, summary: Any) -> dict[str, Any]:
    """The run was made from the scenario file and demo values as they are now; its manifest."""
    if isinstance(summary, dict) and summary.get("status") == "failed":
        raise _rerun(
            out / "summary.json",
            scenario,
            f"the last run failed at stage '{summary.get('stage')}' ({summary.get('reason')})",
        )
    manifest_path = out / "artifacts" / MANIFEST
    manifest = _read_json(manifest_path, scenario, "the run's input manifest")
    if not isinstance(manifest, dict) or manifest.get("scenario_sha256") != scenario.source_hash:
        raise _rerun(
            manifest_path, scenario, f"the run was made from another version of {scenario.path}"
        )
    stored, current = manifest.get("demos"), demo_fingerprints(scenario)
    if stored != current:
        changed = sorted(
            name
            for name in set(current) | set(stored if isinstance(stored, dict) else {})
            if not isinstance(stored, dict) or stored.get(name) != current.get(name)
        )
        files = [str(d.file) for d in scenario.demos if d.name in changed] or changed
        raise _rerun(manifest_path, scenario, f"demos changed since the run: {', '.join(files)}")
    if not isinstance(manifest.get("stages"), dict):
        what = "the run's input manifest names no stage results (written by an older version)"
        raise _rerun(manifest_path, scenario, what)
    return manifest


def _read_stages(
    scenario: Scenario, out: Path, names: Sequence[str], digests: Mapping[str, Any] | None
) -> tuple[dict[str, Any], dict[str, str]]:
    """Stage name -> stored result and -> its input key, for ``names`` in ``out/artifacts``;
    with ``digests``, each result's content hash must be the one named there."""
    results, keys = {}, {}
    for stage in names:
        stem = out / "artifacts" / stage
        try:
            stored = read_stored(stem, RESULT_TYPES)
        except ArtifactError as error:
            raise _rerun(stem.with_suffix(".json"), scenario, error.reason) from None
        if stored is None:
            what = f"artifact of stage '{stage}' not found"
            raise _rerun(stem.with_suffix(".json"), scenario, what)
        if digests is not None and stored.sha256 != digests.get(stage):
            what = (
                f"artifact of stage '{stage}' is not the result the finished run used (a later "
                "run changed it and did not finish)"
            )
            raise _rerun(stem.with_suffix(".json"), scenario, what)
        results[stage], keys[stage] = stored.result, stored.key
    if len(results["optimize"].trajectories) != len(scenario.demos):
        raise _rerun(
            out / "artifacts" / "optimize.json",
            scenario,
            f"artifact holds {len(results['optimize'].trajectories)} trajectories for "
            f"{len(scenario.demos)} demos",
        )
    return results, keys


def staged_report_data(
    scenario: Scenario,
    out: Path,
    staging: Path,
    summary: Summary,
    certification: CertificationResult,
    stress: StressResult | None,
) -> ReportData:
    """``ReportData`` for a run's report: the summary it just derived, the stage results in
    ``out/artifacts``, its ``controller.json`` in ``staging``, where the reports are written,
    certify's check of that file and the stress test's result (None: not run)."""
    results, keys = _read_stages(scenario, Path(out), STAGES, None)
    return report_data(
        scenario,
        Path(out),
        summary,
        results,
        keys,
        certification=certification,
        stress=stress,
        staging=staging,
    )


def load_report_data(scenario: Scenario, out: Path, write_to: Path | None = None) -> ReportData:
    """Read a finished run in ``out`` into ``ReportData`` (whose reports go to ``write_to``,
    default ``out``), its verdict derived again (module docstring); a missing, unreadable,
    corrupt, stale or mismatched file, or a publish cut short, is a ``UserError`` naming it
    and the fix."""
    out = Path(out)
    check_complete(out, scenario.name)
    summary_path = out / "summary.json"
    document = _read_json(summary_path, scenario, "summary.json")
    manifest = _check_inputs(scenario, out, document)
    try:
        summary = Summary.from_json(document)
    except ValueError as error:
        raise _rerun(summary_path, scenario, f"not a run summary ({error})") from None
    controller = out / "controller.json"
    if not is_regular(controller):
        raise _rerun(controller, scenario, "controller.json not found")
    sha256 = file_hash(controller)
    if sha256 != manifest.get("controller_sha256"):
        raise _rerun(controller, scenario, "controller.json is not the file the run wrote")
    names = (*EVIDENCE_STAGES, *(("stress",) if summary.stress is not None else ()))
    results, keys = _read_stages(scenario, out, names, manifest["stages"])
    scenario = results["feedback"].applied_to(scenario)  # as the run: a tuned design's region
    mc = results["montecarlo"]
    shipped = FileInput(path=controller, sha256=sha256)
    montecarlo = MonteCarloInputs(
        scenario=scenario, controller=shipped, samples=mc.samples, seed=mc.seed
    )
    if keys["montecarlo"] != stage_key(MONTECARLO, montecarlo):
        what = (
            "the Monte Carlo result is not of this controller.json (its key names another "
            "file, or an earlier version of the code)"
        )
        raise _rerun(out / "artifacts" / "montecarlo.json", scenario, what)
    stress = None
    if summary.stress is not None:
        stressed = StressInputs(scenario=scenario, controller=shipped, seed=mc.seed)
        if keys["stress"] != stage_key(STRESS, stressed):
            what = "the stress test's result is not of this controller.json"
            raise _rerun(out / "artifacts" / "stress.json", scenario, what)
        stress = stress_summary(results["stress"])
    try:
        law = load(controller)
    except ControllerFormatError as error:
        raise _rerun(controller, scenario, f"controller.json unreadable ({error})") from None
    feedback = results["feedback"]
    if law.feedback_period > 0 and not law.funnel:  # the run's tube was at the held rate
        feedback, held = run_inputs.held_feedback(scenario, feedback, law.feedback_period)
        if not held.success:
            what = f"no held feedback every {law.feedback_period:g} s: {held.held_rate:.3g}/s"
            raise _rerun(controller, scenario, what)
    evidence = Evidence(
        scenario=scenario,
        certificate="funnel" if law.funnel else "constant",
        feedback=feedback,
        covering=results["covering_radius"],
        demo_coverage=results["coverage_demos"],
        coverage=_shipped_coverage(scenario, law, results["coverage_optimized"]),
        optimized=results["optimize"],
        final_radii=results["radius_optimized"],
        controller=results["controller"],
        certification=certify_controller(scenario, controller),
        montecarlo=mc,
        feedback_period=law.feedback_period,
    )
    try:
        summary = rederive(summary, evidence, stress)
    except ValueError as error:
        raise _rerun(summary_path, scenario, f"not this run's summary ({error})") from None
    keys = {stage: keys[stage] for stage in STAGES}  # the ones the report lists
    target = out if write_to is None else Path(write_to)
    return report_data(
        scenario, target, summary, results, keys, certification=evidence.certification,
        stress=results.get("stress"), source=None if target == out else out,
    )  # fmt: skip


def _shipped_coverage(
    scenario: Scenario, law: Controller, constant: CoverageResult
) -> CoverageResult:
    """Init's coverage by the shipped certificate's initial sets: the constant balls (stage
    ``coverage_optimized``), or each funnel's ``E_i(0)`` in ``controller.json`` (as the funnel
    stage covers them: ``||x - x0_i||_{P_i[0]} <= rho_i``)."""
    if not law.funnel:
        return constant
    trajectories = law.trajectories
    return cover_balls(
        scenario,
        np.stack([tr.P[0] for tr in trajectories]),
        np.stack([tr.x0 for tr in trajectories]),
        np.array([tr.radius for tr in trajectories]),
        noun="funnel start",
    )


def rederive(stored: Summary, evidence: Evidence, stress: StressSummary | None) -> Summary:
    """``stored`` (``summary.json`` as read) with every field that carries the verdict derived
    from ``evidence`` by the functions ``summarise`` uses: the verdict and its reasons, the
    claims' kinds and the Monte Carlo and after-T claims, the headline's coverage and Monte
    Carlo numbers, the feedback, Monte Carlo, controller and certification blocks, the
    certificate, the stress test (``stress``). Raises ``ValueError`` when ``stored`` is not a
    summary of the evidence's scenario and demos."""
    scenario, mc = evidence.scenario, evidence.montecarlo
    demos = tuple(d.name for d in scenario.demos)
    if stored.scenario != scenario.name or tuple(d.demo for d in stored.demos) != demos:
        raise ValueError(
            f"scenario {stored.scenario!r} with demos {[d.demo for d in stored.demos]}; "
            f"expected {scenario.name!r} with {list(demos)}"
        )
    if len(stored.claims) != CLAIMS:
        raise ValueError(f"claims: {len(stored.claims)} found, expected {CLAIMS}")
    certified = evidence.certified
    claims = (
        *certificate_claims(evidence, certified),
        after_horizon(evidence, certified),
        *montecarlo_claims(mc),
    )
    return dataclasses.replace(
        stored,
        verdict=Verdict.of(certified=certified, validated=bool(mc.success)),
        reasons=evidence.reasons(),
        claims=claims,
        headline=dataclasses.replace(
            stored.headline, required_clearance=scenario.clearance, **evidence.headline()
        ),
        feedback=feedback_summary(evidence),
        montecarlo=montecarlo_summary(mc),
        controller=controller_summary(evidence),
        certification=certification_summary(evidence.certification),
        reproducibility=dataclasses.replace(
            stored.reproducibility, scenario_sha256=scenario.source_hash, montecarlo_seed=mc.seed
        ),
        stress=stress,
        certificate=evidence.certificate,
    )
