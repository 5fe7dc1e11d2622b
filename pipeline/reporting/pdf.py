"""The report as a PDF, paginated with matplotlib's ``PdfPages`` (no system libraries needed).

A4 landscape pages. Every section starts on a new page with its heading; text, headline numbers,
tables and figures flow down the page. A table that does not fit continues on the next page
under its header (one short enough for a page starts on a new page instead); a figure is drawn
into a subfigure of the page by the same code as the HTML's SVG, scaled to the page width.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import matplotlib
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure as MplFigure
from matplotlib.font_manager import FontProperties
from matplotlib.layout_engine import ConstrainedLayoutEngine
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from matplotlib.textpath import TextToPath

from pipeline.reporting.content import (
    Block,
    Figure,
    Headlines,
    Paragraph,
    Section,
    Table,
    Verdict,
)
from pipeline.reporting.plotting import STYLE

PAGE = (11.69, 8.27)  # A4 landscape (in)
MARGIN = 0.6
TOP = MARGIN + 0.5  # below the page heading
BOTTOM = PAGE[1] - MARGIN - 0.3  # above the footer
TEXT = 9.0
SMALL = 7.5
HEADING = 15.0
PAD = 0.12  # between table columns (in)
BADGE_COLOURS = {
    "certified": "#1B7F3B",
    "statistically validated": "#1F5FA8",
    "falsification-searched": "#A86B00",
}
_TEXT_TO_PATH = TextToPath()


@lru_cache(maxsize=20_000)
def _width(text: str, size: float, bold: bool = False) -> float:
    """Width of ``text`` in inches at ``size`` points."""
    font = FontProperties(size=size, weight="bold" if bold else "normal")
    width, _, _ = _TEXT_TO_PATH.get_text_width_height_descent(text, font, ismath=False)
    return width / 72.0


def _wrap(text: str, size: float, width: float, bold: bool = False) -> list[str]:
    """Greedy word wrap of ``text`` to ``width`` inches (explicit newlines kept); a line's width
    is the sum of its words' and spaces' widths (kerning across words ignored, 2% slack)."""
    space = _width("x x", size, bold) - 2 * _width("x", size, bold)
    lines: list[str] = []
    for paragraph in text.split("\n"):
        if _width(paragraph, size, bold) <= width:
            lines.append(paragraph)
            continue
        line, used = "", 0.0
        for word in paragraph.split(" "):
            w = _width(word, size, bold)
            if line and 1.02 * (used + space + w) > width:
                lines.append(line)
                line, used = word, w
            else:
                line, used = (f"{line} {word}", used + space + w) if line else (word, w)
        lines.append(line)
    return lines


def _line_height(size: float) -> float:
    return 1.4 * size / 72.0


def _fit(natural: Sequence[float], total: float) -> list[float]:
    """Column widths: the natural ones if they fit in ``total``, else the widest columns are
    narrowed (their text wraps) until the sum fits."""
    widths = list(natural)
    while sum(widths) > total:
        excess = sum(widths) - total
        widest = max(widths)
        others = [w for w in widths if w < widest]
        floor = max(max(others, default=0.0), widest - excess / widths.count(widest), 0.6)
        if floor >= widest:
            break
        widths = [floor if w == widest else w for w in widths]
    return widths


class _Writer:
    """Flows blocks down A4 pages; ``y`` is the cursor's distance from the page top (in)."""

    def __init__(self, pdf: PdfPages, title: str) -> None:
        self.pdf, self.title = pdf, title
        self.page: MplFigure | None = None
        self.y = 0.0
        self.count = 0
        self.heading = ""

    @property
    def width(self) -> float:
        return PAGE[0] - 2 * MARGIN

    def _text(self, x: float, y: float, text: str, size: float, **style: Any) -> None:
        """``text`` at ``(x, y)`` from the top left; ``style``: matplotlib text properties."""
        assert self.page is not None
        self.page.text(x / PAGE[0], 1 - y / PAGE[1], text, fontsize=size, va="top", **style)

    def _rule(self, y: float, width: float, colour: str, lw: float) -> None:
        assert self.page is not None
        self.page.add_artist(
            Line2D(
                [MARGIN / PAGE[0], (MARGIN + width) / PAGE[0]],
                [1 - y / PAGE[1]] * 2,
                color=colour,
                lw=lw,
                transform=self.page.transFigure,
            )
        )

    def new_page(self, heading: str) -> None:
        self.finish()
        engine = ConstrainedLayoutEngine(w_pad=0.4 * MARGIN, h_pad=0.04)
        self.page = MplFigure(figsize=PAGE, layout=engine)  # no pyplot: see html._render
        self.heading = heading
        self._text(MARGIN, MARGIN, heading, HEADING, weight="bold")
        self.y = TOP

    def continue_page(self) -> None:
        self.new_page(f"{self.heading.removesuffix(' (continued)')} (continued)")

    def finish(self) -> None:
        """Save the current page with its footer; a page holding only its heading is dropped."""
        if self.page is None:
            return
        if self.y > TOP:
            self.count += 1
            for x, text, ha in (
                (MARGIN, self.title, "left"),
                (PAGE[0] - MARGIN, str(self.count), "right"),
            ):
                self.page.text(
                    x / PAGE[0], 0.35 / PAGE[1], text, fontsize=SMALL, color="0.45", ha=ha
                )
            self.pdf.savefig(self.page)
        self.page = None

    def room(self, height: float) -> None:
        """Start a continuation page unless ``height`` inches still fit."""
        if self.page is None or self.y + height > BOTTOM:
            self.continue_page()

    def paragraph(self, block: Paragraph) -> None:
        style = {"color": "0.35", "style": "italic"} if block.tone == "note" else {}
        for line in _wrap(block.text, TEXT, self.width):
            self.room(_line_height(TEXT))
            self._text(MARGIN, self.y, line, TEXT, **style)
            self.y += _line_height(TEXT)
        self.y += 0.14

    def verdict(self, block: Verdict) -> None:
        size = TEXT + 2
        lines = _wrap(f"Verdict: {block.text}", size, self.width - 0.3, bold=True)
        reasons = [line for r in block.reasons for line in _wrap(f"- {r}", TEXT, self.width - 0.3)]
        height = len(lines) * _line_height(size) + len(reasons) * _line_height(TEXT) + 0.2
        self.room(height)
        assert self.page is not None
        self.page.patches.append(
            Rectangle(
                (MARGIN / PAGE[0], 1 - (self.y + height) / PAGE[1]),
                self.width / PAGE[0],
                height / PAGE[1],
                transform=self.page.transFigure,
                facecolor="#E3F4E8" if block.passed else "#FBE6E6",
                edgecolor="#1B7F3B" if block.passed else "#B3261E",
            )
        )
        y = self.y + 0.1
        for line in lines:
            self._text(MARGIN + 0.15, y, line, size, weight="bold")
            y += _line_height(size)
        for line in reasons:
            self._text(MARGIN + 0.15, y, line, TEXT)
            y += _line_height(TEXT)
        self.y += height + 0.2

    def table(self, block: Table) -> None:
        size = SMALL if len(block.header) > 6 else TEXT - 0.5
        line = _line_height(size)
        natural = [
            max(
                _width(h, size, bold=True),
                *(_width(c, size, bold=k == block.badges) for c in column),
            )
            for k, (h, *column) in enumerate(zip(block.header, *block.rows, strict=True))
        ]
        widths = _fit(natural, self.width - PAD * len(natural))
        span = sum(widths) + PAD * (len(widths) - 1)
        header = [
            _wrap(h, size, w + 1e-6, bold=True) for h, w in zip(block.header, widths, strict=True)
        ]
        rows = [
            [
                _wrap(c, size, w + 1e-6, bold=k == block.badges)
                for k, (c, w) in enumerate(zip(row, widths, strict=True))
            ]
            for row in block.rows
        ]
        heights = [max(len(c) for c in cells) * line + 0.05 for cells in rows]
        header_height = max(len(h) for h in header) * line + 0.05
        caption = 1.3 * line if block.caption else 0.0
        whole = caption + header_height + sum(heights)
        if self.y + whole > BOTTOM and whole <= BOTTOM - TOP:
            self.continue_page()  # keep a table that fits on one page together
        self.room(caption + header_height + (heights[0] if heights else 0.0))
        if block.caption:
            self._text(MARGIN, self.y, block.caption, size + 0.5, weight="bold")
            self.y += caption

        def draw_row(cells: list[list[str]], bold: bool) -> None:
            x = MARGIN
            for k, (lines, w) in enumerate(zip(cells, widths, strict=True)):
                right = block.right(k) and not bold
                badge = block.badges == k and not bold
                colour = BADGE_COLOURS.get(" ".join(lines), "#B3261E") if badge else "black"
                for i, text in enumerate(lines):
                    self._text(
                        x + (w if right else 0.0),
                        self.y + 0.03 + i * line,
                        text,
                        size,
                        ha="right" if right else "left",
                        weight="bold" if bold or badge else "normal",
                        color=colour,
                    )
                x += w + PAD
            self.y += max(len(c) for c in cells) * line + 0.05
            self._rule(self.y, span, "0.2" if bold else "0.85", 0.8 if bold else 0.4)

        draw_row(header, True)
        for cells, height in zip(rows, heights, strict=True):
            if self.y + height > BOTTOM:
                self.continue_page()
                draw_row(header, True)
            draw_row(cells, False)
        self.y += 0.25

    def headlines(self, block: Headlines) -> None:
        rows = tuple((h.label, h.value, h.note) for h in block.items)
        self.table(Table(("headline", "value", "compared with"), rows, "Headline numbers"))

    def figure(self, block: Figure) -> None:
        """The figure at the page's width (its height scaled alike, at most a page), here if
        most of it fits, else on a continuation page; its caption below."""
        caption = _wrap(block.caption, TEXT, self.width)
        caption_height = len(caption) * _line_height(TEXT) + 0.15
        wanted = min(block.size[1] * self.width / block.size[0], BOTTOM - TOP - caption_height)
        if self.page is None or BOTTOM - self.y - caption_height < 0.85 * wanted:
            self.continue_page()
        assert self.page is not None
        body = min(wanted, BOTTOM - self.y - caption_height)
        _, drawing, _ = self.page.subfigures(
            3, 1, squeeze=False, height_ratios=[self.y, body, PAGE[1] - self.y - body]
        )[:, 0]
        block.draw(drawing)
        y = self.y + body + 0.1
        for text in caption:
            self._text(MARGIN, y, text, TEXT, color="0.2")
            y += _line_height(TEXT)
        self.y = PAGE[1]  # one figure per page: the page's layout belongs to it
        self.finish()

    def block(self, block: Block) -> None:
        if isinstance(block, Paragraph):
            self.paragraph(block)
        elif isinstance(block, Verdict):
            self.verdict(block)
        elif isinstance(block, Headlines):
            self.headlines(block)
        elif isinstance(block, Table):
            self.table(block)
        elif isinstance(block, Figure):
            self.figure(block)
        else:
            raise TypeError(f"unknown report block {type(block).__name__}")


def write_pdf(path: Path, title: str, sections: Sequence[Section]) -> int:
    """Write the sections to ``path`` (the caller renames it into place); returns the number
    of pages. Every section starts on a new page."""
    metadata = {"Title": title, "Creator": "safety-synthesis", "CreationDate": None}
    with matplotlib.rc_context(STYLE), PdfPages(path, metadata=metadata) as pdf:
        writer = _Writer(pdf, title)
        for section in sections:
            writer.new_page(section.heading)
            for block in section.blocks:
                writer.block(block)
        writer.finish()
        return writer.count
