"""Stage ``report``: ``report.html``, ``report.pdf`` and ``scenario.png`` from the saved artifacts
(no recomputation).

Takes the run's summary and stage results as ``ReportData`` (read from ``summary.json`` and
``artifacts/*`` by the stage cache, which alone knows the result types), builds the eight
sections once (``pipeline.reporting.sections``) and writes one self-contained HTML page (Jinja2
template, each figure drawn once as inline SVG; figures whose inputs did not change are read
back from ``out/artifacts/figures``). ``report.pdf`` is that page printed by a headless Chromium
(``pipeline.reporting.pdf``; without one, no PDF and a message saying why). Files are written
atomically.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

from pipeline.io.artifacts import atomic_write_text
from pipeline.reporting.content import Figure
from pipeline.reporting.data import ReportData
from pipeline.reporting.figure_cache import FigureStore
from pipeline.reporting.html import render_html
from pipeline.reporting.pdf import PdfJob
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
    """Write ``report.html``, ``report.pdf`` and ``scenario.png`` into ``data.out`` (a run's
    staging folder during the run: ``data.staging``) from the run's summary and stage results
    (read by the stage cache: ``pipeline.runtime.stored``).

    Each figure is drawn once (SVG for the HTML, and the overview's PNG from the same drawing);
    figures whose inputs did not change, and a PDF printed from the same HTML, are reused from
    ``out/artifacts/figures/`` (``pipeline.reporting.figure_cache``). ``pdf`` is None when no
    PDF could be printed (the message says why)."""
    start = time.perf_counter()
    scenario, out, target = data.scenario, data.out, data.reports_folder
    sections = build_sections(data)
    verdict = data.summary.text
    title = f"Safety controller synthesis report: {scenario.name}"
    # kept beside the run's artifacts; not when writing elsewhere (the run is only read)
    store = FigureStore(out / "artifacts" / FIGURES if data.source is None else None)
    figures = [
        block for section in sections for block in section.blocks if isinstance(block, Figure)
    ]
    # the browser starts while the figures are drawn (not when they are all reused: then the
    # PDF printed from the same page is most likely kept too)
    pdf = PdfJob(store, early=not all(store.cached(figure) for figure in figures))
    try:
        for figure in figures:
            store.svg(figure, png=figure.key == OVERVIEW)
        html = render_html(
            title,
            f"Verdict: {verdict}. Method: Winn & Julius, Optimization of Human Generated "
            "Trajectories for Safety Controller Synthesis.",
            sections,
            {"version": _version(), "out": str(data.run_folder), "scenario": scenario.name},
            store.svgs,
        )
        atomic_write_text(target / "report.html", html)
        for figure in figures:  # the scenario figure on its own, for slides and notes
            if figure.key == OVERVIEW:
                store.copy_png(figure, target / "scenario.png")
        printed = pdf.finish(target / "report.html", target / "report.pdf")
        store.prune()
    finally:
        pdf.close()
        store.close()
    seconds = time.perf_counter() - start
    drawn = f"{len(store.drawn)} figures drawn" if store.drawn else "every figure reused"
    return ReportResult(
        html=target / "report.html",
        pdf=printed.path,
        success=True,
        message=f"report.html ({len(html) // 1024} KiB) and {printed.message} written in "
        f"{seconds:.1f} s ({drawn})"
        if printed.path is not None
        else f"report.html ({len(html) // 1024} KiB) written in {seconds:.1f} s ({drawn}); "
        f"{printed.message}",
    )
