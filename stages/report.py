"""Stage ``report``: ``report.html``, ``report.pdf`` and ``scenario.png`` from the saved artifacts
(no recomputation).

Takes the run's summary and stage results as ``ReportData`` (read from ``summary.json`` and
``artifacts/*`` by the stage cache, which alone knows the result types), builds the eight
sections once (``pipeline.reporting.sections``) and writes them twice: one self-contained HTML
page (Jinja2 template, inline SVG figures) and a paginated PDF (matplotlib's ``PdfPages``, at
least one page per section). Both files are written atomically.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from pipeline.io.artifacts import atomic_save, atomic_write_text
from pipeline.reporting.content import Figure
from pipeline.reporting.data import ReportData
from pipeline.reporting.html import render_html, save_figure_png
from pipeline.reporting.pdf import write_pdf
from pipeline.reporting.sections import build_sections


@dataclass(frozen=True)
class ReportResult:
    html: Path
    pdf: Path | None
    success: bool
    message: str


def _version() -> str:
    try:
        return metadata.version("safety-synthesis")
    except metadata.PackageNotFoundError:
        return "(not installed)"


def write_reports(data: ReportData) -> ReportResult:
    """Write ``report.html``, ``report.pdf`` and ``scenario.png`` into ``data.out`` from the run's
    summary and stage results (read by the stage cache: ``pipeline.runtime.stored``)."""
    start = time.perf_counter()
    scenario, out = data.scenario, data.out
    sections = build_sections(data)
    verdict = data.summary.text
    title = f"Safety controller synthesis report: {scenario.name}"
    html = render_html(
        title,
        f"Verdict: {verdict}. Winn & Julius, Optimization of Human Generated Trajectories for "
        "Safety Controller Synthesis.",
        sections,
        {"version": _version(), "out": str(out), "scenario": scenario.name},
    )
    atomic_write_text(out / "report.html", html)
    pages: list[int] = []
    atomic_save(
        out / "report.pdf",
        lambda path: pages.append(write_pdf(path, title, sections)),
        suffix=".pdf",
    )
    overview = [
        block
        for section in sections
        for block in section.blocks
        if isinstance(block, Figure) and block.key == "overview"
    ]
    for figure in overview:  # the scenario figure on its own, for slides and notes
        save_figure_png(figure, out / "scenario.png")
    seconds = time.perf_counter() - start
    return ReportResult(
        out / "report.html",
        out / "report.pdf",
        True,
        f"report.html ({len(html) // 1024} KiB) and report.pdf ({pages[0]} pages) written "
        f"in {seconds:.1f} s",
    )
