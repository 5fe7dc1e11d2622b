"""The report as one self-contained HTML file: a Jinja2 template, figures inlined as SVG.

No network access is needed to read it: no scripts, no stylesheets or fonts from elsewhere; the
SVGs' raster parts (dense paths) are embedded as base64 PNG data. Element ids inside each SVG are
prefixed with the figure's key, so several inlined SVGs never share an id.
"""

from __future__ import annotations

import io
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jinja2
import matplotlib
from matplotlib.figure import Figure as MplFigure

from pipeline.io.artifacts import atomic_save
from pipeline.io.files import printable
from pipeline.reporting.content import Figure, Section
from pipeline.reporting.plotting import STYLE

TEMPLATES = Path(__file__).resolve().parent / "templates"
BADGES = {
    "certified": "certified",
    "statistically validated": "validated",
    "falsification-searched": "searched",
}


def _render(figure: Figure, save: Callable[[Any], None]) -> None:
    """Draw ``figure`` at its size and hand the matplotlib figure to ``save``.

    A bare ``matplotlib.figure.Figure``, not pyplot: no global backend or figure registry is
    touched, so importing the report modules changes nothing for the caller (e.g. a notebook)."""
    with matplotlib.rc_context({**STYLE, "svg.hashsalt": figure.key}):
        fig = MplFigure(figsize=figure.size, layout="constrained")
        figure.draw(fig)
        save(fig)


def figure_svg(figure: Figure) -> str:
    """The figure drawn at its size as an inline ``<svg>`` element (no XML prolog, scalable)."""
    buffer = io.StringIO()
    _render(figure, lambda fig: fig.savefig(buffer, format="svg", metadata={"Date": None}))
    return inline_svg(buffer.getvalue(), figure.key)


def save_figure_png(figure: Figure, path: Path, dpi: int = 130) -> None:
    """The figure as a PNG file, written atomically (e.g. ``scenario.png`` beside the report)."""
    _render(
        figure,
        lambda fig: atomic_save(
            path, lambda stream: fig.savefig(stream, format="png", dpi=dpi), ".png"
        ),
    )


def inline_svg(svg: str, key: str) -> str:
    """An SVG file's text as an inline ``<svg>`` element: ids prefixed with ``key``, no fixed
    size (CSS scales it with its viewBox)."""
    svg = svg[svg.index("<svg") :]
    svg = re.sub(r"<metadata>.*?</metadata>", "", svg, flags=re.S)
    svg = re.sub(r'\bid="([^"]+)"', rf'id="{key}-\1"', svg)
    svg = re.sub(r"url\(#([^)]+)\)", rf"url(#{key}-\1)", svg)
    svg = re.sub(r'href="#([^"]+)"', rf'href="#{key}-\1"', svg)
    # drop the fixed size on the root element: CSS scales it with its viewBox
    head, rest = svg.split(">", 1)
    head = re.sub(r'\s(width|height)="[^"]*"', "", head)
    return f'{head} role="img" preserveAspectRatio="xMidYMid meet">{rest}'


def _badge(kind: str) -> str:
    return BADGES.get(kind, "missing")


def render_html(
    title: str,
    subtitle: str,
    sections: Sequence[Section],
    context: Mapping[str, Any],
    svgs: Mapping[str, str] | None = None,
) -> str:
    """The page: ``sections`` in order, each figure inlined (from ``svgs``, figure key ->
    inline SVG, where given; else drawn here), plus ``context`` for the header."""
    environment = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    environment.filters["badge"] = _badge
    given = dict(svgs or {})
    svgs = {
        block.key: given.get(block.key) or figure_svg(block)  # trusted: drawn here, |safe
        for section in sections
        for block in section.blocks
        if isinstance(block, Figure)
    }
    template = environment.get_template("report.html.j2")
    # a path with bytes that are not UTF-8 (lone surrogates) is shown with them as \xNN
    page = template.render(title=title, subtitle=subtitle, sections=sections, svgs=svgs, **context)
    return printable(page)
