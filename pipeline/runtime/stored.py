"""The stage cache read back for a report: ``summary.json``, ``artifacts/<stage>`` and the run's
input manifest ``artifacts/inputs.json`` (the scenario file's hash and each demo's parsed values).

``report`` rebuilds from these without recomputing; any missing, corrupt or mismatched file is a
``UserError`` naming it and the command that writes it again.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

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
from pipeline.reporting.summary import Summary
from pipeline.runtime.registry import RESULT_TYPES

MANIFEST = "inputs.json"


def demo_fingerprints(scenario: Scenario) -> dict[str, str]:
    """Demo name -> hash of its parsed ``x0`` and inputs (not the file's bytes: comments and
    formatting do not count)."""
    return {d.name: inputs_key(d.x0, d.us) for d in scenario.demos}


def write_manifest(scenario: Scenario, out: Path, controller_sha256: str) -> None:
    """Record what the run was made from (for ``report`` to check against the current files)
    and the hash of the ``controller.json`` it certified."""
    atomic_write_json(
        Path(out) / "artifacts" / MANIFEST,
        {
            "scenario": scenario.name,
            "scenario_sha256": scenario.source_hash,
            "demos": demo_fingerprints(scenario),
            "controller_sha256": controller_sha256,
        },
    )


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


def _check_inputs(scenario: Scenario, out: Path, summary: Any) -> None:
    """The run was made from the scenario file and demo values as they are now."""
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


def load_report_data(scenario: Scenario, out: Path, write_to: Path | None = None) -> ReportData:
    """Read ``out/summary.json`` and ``out/artifacts/<stage>`` into ``ReportData`` (whose reports
    go to ``write_to``, default ``out``); a missing, unreadable, corrupt or stale file is a
    ``UserError`` naming it and the fix."""
    out = Path(out)
    summary_path = out / "summary.json"
    document = _read_json(summary_path, scenario, "summary.json")
    _check_inputs(scenario, out, document)
    try:
        summary = Summary.from_json(document)
    except ValueError as error:
        raise _rerun(summary_path, scenario, f"not a run summary ({error})") from None
    results, keys = {}, {}
    for stage in STAGES:
        stem = out / "artifacts" / stage
        try:
            stored = read_stored(stem, RESULT_TYPES)
        except ArtifactError as error:
            raise _rerun(stem.with_suffix(".json"), scenario, error.reason) from None
        if stored is None:
            what = f"artifact of stage '{stage}' not found"
            raise _rerun(stem.with_suffix(".json"), scenario, what)
        results[stage], keys[stage] = stored.result, stored.key
    controller = out / "controller.json"
    if not is_regular(controller):
        raise _rerun(controller, scenario, "controller.json not found")
    manifest = _read_json(out / "artifacts" / MANIFEST, scenario, "the run's input manifest")
    if file_hash(controller) != manifest.get("controller_sha256"):
        raise _rerun(controller, scenario, "controller.json is not the file the run wrote")
    if len(results["optimize"].trajectories) != len(scenario.demos):
        raise _rerun(
            out / "artifacts" / "optimize.json",
            scenario,
            f"artifact holds {len(results['optimize'].trajectories)} trajectories for "
            f"{len(scenario.demos)} demos",
        )
    if write_to is None or Path(write_to) == out:
        return report_data(scenario, out, summary, results, keys)
    return report_data(scenario, Path(write_to), summary, results, keys, source=out)
