"""Rendered report pages and figures, kept under ``OUT/artifacts/figures/`` by what they draw.

Each PDF page is rendered once into its own one-page PDF named by the SHA-256 of everything on
it (texts with their positions and styles, rules, boxes, and the digest of its figure); the
report is these pages joined. A figure's digest hashes its key, size and ``inputs`` (the
fingerprint of the data it reads, ``ReportData.fingerprint``) with the reporting code and the
matplotlib version, so a figure whose data did not change is neither drawn nor rendered again.
A figure is drawn once, into its PDF page; its SVG (for the HTML) and PNG (``scenario.png``) are
cut from that same drawing. Files this report did not use are deleted at the end (``prune``).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import matplotlib
from matplotlib.figure import Figure as MplFigure
from matplotlib.figure import SubFigure
from matplotlib.transforms import Bbox

from pipeline.io.artifacts import atomic_save, atomic_write_text
from pipeline.reporting.content import Figure
from pipeline.reporting.html import inline_svg
from pipeline.reporting.plotting import STYLE

PNG_DPI = 130


@functools.cache
def code_digest() -> str:
    """SHA-256 of the reporting package's sources and templates and the matplotlib version."""
    folder = Path(__file__).resolve().parent
    digest = hashlib.sha256(matplotlib.__version__.encode())
    for path in sorted([*folder.glob("*.py"), *folder.glob("templates/*")]):
        digest.update(path.name.encode() + b"\x00" + path.read_bytes())
    return digest.hexdigest()


def digest_of(*parts: object) -> str:
    """SHA-256 of ``parts`` (JSON-encodable, or their ``repr``) with ``code_digest()``."""
    text = json.dumps([code_digest(), STYLE, *parts], default=repr, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def figure_digest(figure: Figure) -> str | None:
    """The digest of what ``figure`` draws; None if it does not say (``inputs`` empty)."""
    if not figure.inputs:
        return None
    return digest_of("figure", figure.key, figure.size, figure.inputs)


class FigureStore:
    """Pages (``page-DIGEST.pdf``), SVGs (``KEY-DIGEST.svg``) and PNGs (``KEY-DIGEST.png``) in
    ``folder``; with ``folder=None`` (or for a figure without a digest) a private temporary
    folder, nothing reused."""

    def __init__(self, folder: Path | None) -> None:
        self._scratch = Path(tempfile.mkdtemp(prefix="report_pages_"))
        self.folder = Path(folder) if folder is not None else self._scratch
        self.folder.mkdir(parents=True, exist_ok=True)
        self.used: set[Path] = set()
        self.svgs: dict[str, str] = {}  # figure key -> inline SVG, for the HTML
        self.drawn: list[str] = []  # figure keys drawn in this run (not reused)
        self._count = 0

    def _file(self, name: str | None, suffix: str) -> Path:
        if name is None:  # not cacheable: a unique file in the scratch folder
            self._count += 1
            return self._scratch / f"{self._count}{suffix}"
        path = self.folder / f"{name}{suffix}"
        self.used.add(path)
        return path

    def page_file(self, digest: str | None) -> Path:
        return self._file(None if digest is None else f"page-{digest}", ".pdf")

    def figure_file(self, figure: Figure, suffix: str) -> Path:
        digest = figure_digest(figure)
        return self._file(None if digest is None else f"{figure.key}-{digest}", suffix)

    def cached(self, page: Path, figure: Figure | None, png: bool) -> bool:
        """Are ``page`` and its figure's SVG (and PNG if ``png``) all on disk?"""
        if not page.is_file() or page.parent == self._scratch:
            return False
        if figure is None:
            return True
        svg = self.figure_file(figure, ".svg")
        if not svg.is_file() or (png and not self.figure_file(figure, ".png").is_file()):
            return False
        self.svgs[figure.key] = svg.read_text()
        return True

    def save_figure(self, figure: Figure, page: MplFigure, drawing: SubFigure, png: bool) -> None:
        """Cut ``figure``'s SVG (and PNG) from ``page``, where it was drawn into ``drawing``
        and the page already saved: everything else on the page is hidden, the layout kept."""
        page.set_layout_engine("none")  # keep the positions of the PDF page's layout
        for artist in [*page.texts, *page.artists, *page.patches, *page.lines]:
            artist.set_visible(False)
        for other in page.subfigs:
            if other is not drawing:
                other.set_visible(False)
        box = Bbox(drawing.bbox.get_points() / page.dpi)  # inches
        buffer = io.StringIO()
        with matplotlib.rc_context({**STYLE, "svg.hashsalt": figure.key}):
            page.savefig(buffer, format="svg", bbox_inches=box, metadata={"Date": None})
            svg = inline_svg(buffer.getvalue(), figure.key)
            atomic_write_text(self.figure_file(figure, ".svg"), svg)
            if png:
                atomic_save(
                    self.figure_file(figure, ".png"),
                    lambda p: page.savefig(p, format="png", dpi=PNG_DPI, bbox_inches=box),
                    ".png",
                )
        self.svgs[figure.key] = svg
        self.drawn.append(figure.key)

    def copy_png(self, figure: Figure, target: Path) -> None:
        """The figure's PNG (cut from its page) to ``target``, atomically."""
        source = self.figure_file(figure, ".png")

        def copy(path: Path) -> None:
            shutil.copyfile(source, path)

        atomic_save(target, copy, ".png")

    def scratch_file(self, suffix: str) -> Path:
        """A new file name in the private temporary folder."""
        return self._file(None, suffix)

    def join(
        self, pages: Sequence[tuple[Path, int | None]], fresh: Path, path: Path, title: str
    ) -> None:
        """The report's pages, in order, into ``path``: ``(file, None)`` a kept page,
        ``(file, k)`` page ``k`` of ``fresh`` (rendered now), also kept as ``file``."""
        from pypdf import PdfReader, PdfWriter

        reader = PdfReader(fresh) if any(k is not None for _, k in pages) else None
        writer = PdfWriter()
        for file, k in pages:
            if k is None:
                writer.append(str(file))
                continue
            assert reader is not None
            single = PdfWriter()
            single.add_page(reader.pages[k])

            def keep(target: Path, single: PdfWriter = single) -> None:
                single.write(target)

            atomic_save(file, keep, ".pdf")
            writer.add_page(reader.pages[k])
        writer.compress_identical_objects()  # the fonts each kept page carries, once
        writer.add_metadata({"/Title": title, "/Creator": "safety-synthesis"})
        with open(path, "wb") as handle:
            writer.write(handle)

    def prune(self) -> None:
        """Delete this folder's cached files that this report did not use."""
        if self.folder != self._scratch:
            for path in self.folder.iterdir():
                if path.is_file() and path not in self.used and not path.name.startswith("."):
                    path.unlink(missing_ok=True)

    def close(self) -> None:
        """Delete the private temporary folder (after the report is written, or failed)."""
        shutil.rmtree(self._scratch, ignore_errors=True)
