"""Stage ``report``: ``report.html``, ``report.pdf`` and ``scenario.png`` from the saved artifacts
(no recomputation).

Takes the run's summary and stage results as ``ReportData`` (read from ``summary.json`` and
``artifacts/*`` by the stage cache, which alone knows the result types), builds the eight
sections once (``pipeline.reporting.sections``) and writes them twice: a paginated PDF (one
matplotlib figure per page, at least one page per section, pages kept by the digest of their
content) and one self-contained HTML page (Jinja2 template, inline SVG figures cut from the PDF
pages' drawings). Both files are written atomically.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from pipeline.io.artifacts import atomic_save, atomic_write_text
from pipeline.reporting.content import Figure
from pipeline.reporting.data import ReportData
from pipeline.reporting.figure_cache import FigureStore
from pipeline.reporting.html import render_html
from pipeline.reporting.pdf import write_pdf
from pipeline.reporting.sections import build_sections

FIGURES = "figures"  # out/artifacts/figures: rendered pages and figures, by digest
OVERVIEW = "overview"  # the figure also written as scenario.png


@dataclass(frozen=True, kw_only=True)
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
    summary and stage results (read by the stage cache: ``pipeline.runtime.stored``).

    The PDF is written first: each figure is drawn once, into its page, and the HTML's SVG and
    the PNG are cut from that drawing; pages and figures whose inputs did not change are reused
    from ``out/artifacts/figures/`` (``pipeline.reporting.figure_cache``)."""
    start = time.perf_counter()
    scenario, out = data.scenario, data.out
    sections = build_sections(data)
    verdict = data.summary.text
    title = f"Safety controller synthesis report: {scenario.name}"
    # kept beside the run's artifacts; not when writing elsewhere (the run is only read)
    store = FigureStore(out / "artifacts" / FIGURES if data.source is None else None)
    try:
        pages: list[int] = []

        def pdf(path: Path) -> None:
            pages.append(write_pdf(path, title, sections, store, frozenset([OVERVIEW])))

        atomic_save(out / "report.pdf", pdf, suffix=".pdf")
        html = render_html(
            title,
            f"Verdict: {verdict}. Winn & Julius, Optimization of Human Generated Trajectories for "
            "Safety Controller Synthesis.",
            sections,
            {"version": _version(), "out": str(out), "scenario": scenario.name},
            store.svgs,
        )
        atomic_write_text(out / "report.html", html)
        overview = [
            block
            for section in sections
            for block in section.blocks
            if isinstance(block, Figure) and block.key == OVERVIEW
        ]
        for figure in overview:  # the scenario figure on its own, for slides and notes
            store.copy_png(figure, out / "scenario.png")
        store.prune()
    finally:
        store.close()
    seconds = time.perf_counter() - start
    drawn = f"{len(store.drawn)} figures drawn" if store.drawn else "every figure reused"
    return ReportResult(
        html=out / "report.html",
        pdf=out / "report.pdf",
        success=True,
        message=f"report.html ({len(html) // 1024} KiB) and report.pdf ({pages[0]} pages) written "
        f"in {seconds:.1f} s ({drawn})",
    )
