"""Rendered figures and the typeset PDF, kept under ``OUT/artifacts/figures/`` by what they draw.

A figure's digest hashes its key, size and ``inputs`` (the fingerprint of the data it reads,
``ReportData.fingerprint``) with the reporting code and the matplotlib version, so a figure whose
data did not change is not drawn again: its SVG (for the HTML, ``KEY-DIGEST.svg``) and PNG
(``scenario.png``, ``KEY-DIGEST.png``) are read back. Each figure is drawn once; the PNG is saved
from the same drawing as the SVG. The PDF is kept as ``report-DIGEST.pdf`` by the digest of its
inputs (``reporting.pdf``). Files this report did not use are deleted at the end (``prune``).
The folder is the run's cache: read and written without following links (``pipeline.io.files``);
a cached file that is not a regular file is drawn again and replaced.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import matplotlib
from matplotlib.figure import Figure as MplFigure

from pipeline.io.artifacts import atomic_save, atomic_write_text
from pipeline.io.files import (
    TEXT_MAX_BYTES,
    FileRefused,
    is_regular,
    open_folder,
    read_bytes,
    read_text,
    remove_files,
)
from pipeline.reporting.content import Figure
from pipeline.reporting.html import inline_svg
from pipeline.reporting.plotting import STYLE

PNG_DPI = 160


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
    """SVGs (``KEY-DIGEST.svg``), PNGs (``KEY-DIGEST.png``) and typeset PDFs
    (``report-DIGEST.pdf``) in ``folder``; with ``folder=None`` (or for a figure without a
    digest) a private temporary folder, nothing reused."""

    def __init__(self, folder: Path | None) -> None:
        self._scratch = Path(tempfile.mkdtemp(prefix="report_figures_"))
        self.folder = Path(folder) if folder is not None else self._scratch
        os.close(open_folder(self.folder, create=True))  # a link or a file there is refused
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

    def figure_file(self, figure: Figure, suffix: str) -> Path:
        digest = figure_digest(figure)
        return self._file(None if digest is None else f"{figure.key}-{digest}", suffix)

    def pdf_file(self, digest: str) -> Path:
        """Where the PDF typeset from the inputs of ``digest`` is kept."""
        return self._file(f"report-{digest}", ".pdf")

    def svg(self, figure: Figure, png: bool = False) -> str:
        """``figure`` as an inline SVG (and its PNG on disk if ``png``): read back when its
        inputs did not change, else drawn once at its size and saved in both formats."""
        svg_file = self.figure_file(figure, ".svg")
        png_file = self.figure_file(figure, ".png") if png else None
        if svg_file.parent != self._scratch and (png_file is None or is_regular(png_file)):
            try:
                self.svgs[figure.key] = read_text(svg_file, TEXT_MAX_BYTES)
                return self.svgs[figure.key]
            except (OSError, FileRefused):
                pass  # not kept (or not a regular file there): drawn and replaced below
        with matplotlib.rc_context({**STYLE, "svg.hashsalt": figure.key}):
            # a bare Figure, not pyplot: no global backend or figure registry is touched
            fig = MplFigure(figsize=figure.size, layout="constrained")
            figure.draw(fig)
            buffer = io.StringIO()
            fig.savefig(buffer, format="svg", metadata={"Date": None})
            svg = inline_svg(buffer.getvalue(), figure.key)
            atomic_write_text(svg_file, svg, cache=True)
            if png_file is not None:
                fig.set_layout_engine("none")  # keep the SVG's layout: not computed again
                atomic_save(
                    png_file,
                    lambda stream: fig.savefig(stream, format="png", dpi=PNG_DPI),
                    ".png",
                    cache=True,
                )
        self.svgs[figure.key] = svg
        self.drawn.append(figure.key)
        return svg

    def copy_png(self, figure: Figure, target: Path) -> None:
        """The figure's PNG (saved with its SVG) to ``target``, atomically."""
        png = read_bytes(self.figure_file(figure, ".png"), TEXT_MAX_BYTES)
        atomic_save(target, lambda stream: stream.write(png), ".png")

    def prune(self) -> None:
        """Delete this folder's cached files that this report did not use."""
        if self.folder != self._scratch:
            used = {path.name for path in self.used}
            remove_files(self.folder, lambda name: name not in used and not name.startswith("."))

    def close(self) -> None:
        """Delete the private temporary folder (after the report is written, or failed)."""
        shutil.rmtree(self._scratch, ignore_errors=True)
