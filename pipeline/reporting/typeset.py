"""``report.pdf`` typeset by Typst from the same ``Section`` list and SVG figures as
``report.html``.

Engine: the Typst compiler embedded in the ``typst`` wheel on PyPI (a pip dependency, a compiled
extension with no system program, no browser and no network). A fresh machine writes the PDF
with nothing else installed, and the PDF does not depend on what is: the fonts are matplotlib's
DejaVu Sans (the figures' own font, shipped in matplotlib's wheel) and Typst's embedded ones,
system fonts are ignored. It reads SVG (the figures stay vectors, their text set in the same
font) and breaks long tables across pages with their header repeated. It replaced a headless
Chromium printing ``report.html``, a system program absent on a fresh machine; WeasyPrint needs
the Pango system library; ReportLab has no SVG reader of its own.

Escaping: the template (``templates/report.typ``) is fixed; the content enters it as one JSON
document in ``sys.inputs`` and every text (scenario names and descriptions, captions, cells)
is a Typst string, shown verbatim. No user string is parsed as Typst markup or code, so ``#``,
``$``, ``*``, ``_``, ``<``, ``@``, brackets and backslashes need no escaping. Typst takes only
valid Unicode: a path's bytes that are not UTF-8 (lone surrogates, ``os.fsdecode``) are shown as
``\\xNN``, as in ``report.html`` (``pipeline.io.files.printable``).

Layout: A4; figures at their drawn size (their 10 pt text beside the 8.5 pt body), never wider
than the column nor taller than ``TALLEST``; a table of at most 15 rows on one page, a longer
one broken across pages with its header repeated.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import matplotlib
import typst

from pipeline.io.files import printable
from pipeline.reporting.content import Block, Figure, Headlines, Paragraph, Section, Table, Verdict
from pipeline.reporting.html import BADGES

TEMPLATE = Path(__file__).resolve().parent / "templates" / "report.typ"
FONTS = Path(matplotlib.get_data_path()) / "fonts" / "ttf"  # DejaVu Sans, as in the figures
INCH = 25.4  # mm
COLUMN = 188.0  # mm: A4's 210 mm less the two 11 mm margins of the template
TALLEST = 215.0  # mm: a figure's height, leaving room on the page for its caption
ENGINE = f"typst {metadata.version('typst')}"  # part of the kept PDF's digest


class TypesetError(RuntimeError):
    """Typst rejected the document (a bug of the template or of this module, not of the run)."""


def figure_width(size: tuple[float, float]) -> float:
    """The width (mm) of a figure drawn at ``size`` (width, height) inches on the page."""
    width, height = size[0] * INCH, size[1] * INCH
    return min(width, COLUMN, TALLEST * width / height)


def _block(block: Block) -> dict[str, Any]:
    if isinstance(block, Paragraph):
        return {"kind": "paragraph", "text": block.text, "tone": block.tone}
    if isinstance(block, Verdict):
        return {
            "kind": "verdict",
            "passed": block.passed,
            "text": block.text,
            "reasons": list(block.reasons),
        }
    if isinstance(block, Headlines):
        return {
            "kind": "headlines",
            "items": [{"label": h.label, "value": h.value, "note": h.note} for h in block.items],
        }
    if isinstance(block, Table):
        column = block.badges
        return {
            "kind": "table",
            "header": list(block.header),
            "rows": [list(row) for row in block.rows],
            "caption": block.caption,
            "right": [block.right(c) for c in range(len(block.header))],
            "badges": column,
            "badge_kinds": [
                BADGES.get(row[column], "missing") if column is not None else ""
                for row in block.rows
            ],
        }
    if isinstance(block, Figure):
        return {
            "kind": "figure",
            "key": block.key,
            "caption": block.caption,
            "width": round(figure_width(block.size), 2),
        }
    raise TypeError(f"no Typst rendering for {type(block).__name__}")


def document_inputs(
    title: str,
    subtitle: str,
    sections: Sequence[Section],
    colophon: str,
    svgs: Mapping[str, str],
) -> dict[str, str]:
    """The template's ``sys.inputs``: ``report``, the document as JSON, and ``figure-KEY``, the
    SVG of each figure (``svgs``: figure key -> SVG text, as ``FigureStore.svgs``)."""
    report = {
        "title": title,
        "subtitle": subtitle,
        "colophon": colophon,
        "sections": [
            {"key": s.key, "heading": s.heading, "blocks": [_block(b) for b in s.blocks]}
            for s in sections
        ],
    }
    figures = [b.key for s in sections for b in s.blocks if isinstance(b, Figure)]
    missing = [key for key in figures if key not in svgs]
    if missing:
        raise ValueError(f"no SVG for the figures {missing}")
    inputs = {"report": json.dumps(_printable(report), ensure_ascii=False)}
    inputs.update({f"figure-{key}": printable(svgs[key]) for key in figures})
    return inputs


def _printable(value: Any) -> Any:
    """``value`` (JSON-like) with every string ``printable``: before the JSON encoding, which
    then escapes the backslash of ``\\xNN`` as JSON requires."""
    if isinstance(value, str):
        return printable(value)
    if isinstance(value, list):
        return [_printable(item) for item in value]
    if isinstance(value, dict):
        return {key: _printable(item) for key, item in value.items()}
    return value


def typeset(inputs: Mapping[str, str]) -> bytes:
    """The PDF of the template with ``inputs`` (``document_inputs``)."""
    try:
        pdf = typst.compile(
            TEMPLATE,
            format="pdf",
            font_paths=[FONTS],
            ignore_system_fonts=True,
            sys_inputs=dict(inputs),
        )
    except typst.TypstError as error:
        raise TypesetError(f"typst: {error.message}") from error
    assert isinstance(pdf, bytes)
    return pdf
