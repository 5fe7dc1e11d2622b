"""The report's content, independent of its format: sections made of blocks.

Both writers (``reporting.html``, ``reporting.typeset``) render the same ``Section`` list, so the
two formats cannot drift apart. Numbers are formatted once, in ``reporting.numbers`` (re-exported
here).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

from matplotlib.figure import Figure as MplFigure
from matplotlib.figure import SubFigure

from pipeline.reporting.numbers import (
    check,
    fixed,
    formatted,
    number,
    percent,
    scientific,
    seconds,
    vector,
)

# the formatting helpers are re-exported: the writers and sections import them from here
__all__ = [
    "Block",
    "Figure",
    "FigureLike",
    "Headline",
    "Headlines",
    "Paragraph",
    "Section",
    "Table",
    "Verdict",
    "check",
    "fixed",
    "formatted",
    "number",
    "percent",
    "scientific",
    "seconds",
    "vector",
]

FigureLike = MplFigure | SubFigure


@dataclass(frozen=True)
class Paragraph:
    text: str
    tone: str = ""  # "" or "note"
    kind: ClassVar[str] = "paragraph"


@dataclass(frozen=True)
class Verdict:
    """The run's verdict; ``passed`` when certified and validated."""

    passed: bool
    text: str
    reasons: tuple[str, ...] = ()
    kind: ClassVar[str] = "verdict"


@dataclass(frozen=True)
class Headline:
    """One headline number: ``label``, formatted ``value``, and what it compares to."""

    label: str
    value: str
    note: str


@dataclass(frozen=True)
class Headlines:
    items: tuple[Headline, ...]
    kind: ClassVar[str] = "headlines"


@dataclass(frozen=True)
class Table:
    """A table of preformatted cells; ``numeric[c]`` right-aligns column ``c``; the cells of
    column ``badges`` (if any) are claim kinds, drawn as coloured labels; ``stack``: on a
    narrow screen each row is shown as a card of "header: cell" lines (HTML)."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    caption: str = ""
    numeric: tuple[bool, ...] = ()
    badges: int | None = None
    stack: bool = False
    kind: ClassVar[str] = "table"

    def __post_init__(self) -> None:
        for row in self.rows:
            if len(row) != len(self.header):
                raise ValueError(f"table row {row} has {len(row)} cells, header {self.header}")

    def right(self, column: int) -> bool:
        return column < len(self.numeric) and self.numeric[column]


@dataclass(frozen=True)
class Figure:
    """A figure drawn by ``draw(fig)`` into a matplotlib figure or subfigure of ``size``
    (width, height) inches; the same drawing serves the HTML (SVG) and the PDF page.
    ``inputs``: a fingerprint of all the data ``draw`` reads (``ReportData.fingerprint``), by
    which its rendering is kept and reused (``reporting.figure_cache``); "" never reuses it."""

    key: str
    caption: str
    draw: Callable[[FigureLike], None]
    size: tuple[float, float] = (10.0, 5.0)
    inputs: str = ""
    kind: ClassVar[str] = "figure"


Block = Paragraph | Verdict | Headlines | Table | Figure


@dataclass(frozen=True)
class Section:
    key: str
    number: int
    title: str
    blocks: tuple[Block, ...]

    @property
    def heading(self) -> str:
        return f"{self.number}. {self.title}"
