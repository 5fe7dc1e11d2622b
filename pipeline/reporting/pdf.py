"""``report.pdf``: ``report.html`` printed by a headless Chromium (one source for both files).

The page's print style (``templates/report.html.j2``, ``@media print``) lays it out on A4: the
title on page 1, sections flowing on without half-empty pages, no figure or table row cut in
two. The browser is a system program, not a Python package: the first of ``BROWSERS`` on
``PATH``. Chromium's headless shell comes first: the same engine without the browser around it,
it prints the same PDF (quadrotor_hill: 8 of 9 pages pixel-identical, one line of the last
wrapped at another letter) for 0.8 s of CPU instead of 2.1 s. Where none is found or it fails,
no PDF is written, an older ``report.pdf`` is removed (never left looking current) and the
outcome's message says why and how to get one. The browser is started before the figures are
drawn and driven over a pipe (``reporting.browser``), so that its start-up overlaps the drawing.
A PDF printed from the same HTML is reused (kept by the HTML's digest).
"""

from __future__ import annotations

import hashlib
import shutil
from dataclasses import dataclass
from pathlib import Path

from pipeline.io.artifacts import atomic_save
from pipeline.io.files import (
    ARTIFACT_MAX_BYTES,
    TEXT_MAX_BYTES,
    FileRefused,
    is_regular,
    read_bytes,
    unlink,
)
from pipeline.reporting.browser import BrowserError, Printer
from pipeline.reporting.figure_cache import FigureStore, digest_of

BROWSERS = (
    "chromium-headless-shell",
    "chromium",
    "chromium-browser",
    "google-chrome",
    "google-chrome-stable",
)
TIMEOUT = 120.0  # s
INSTALL = "Debian/Ubuntu: apt-get install chromium-headless-shell, or chromium"


@dataclass(frozen=True, kw_only=True)
class PdfOutcome:
    """``path``: the PDF written (None: none, see ``message``); ``pages``: its page count."""

    path: Path | None
    pages: int
    reused: bool
    message: str


def find_browser() -> Path | None:
    """The first of ``BROWSERS`` on ``PATH``; None if there is none."""
    for name in BROWSERS:
        found = shutil.which(name)
        if found:
            return Path(found)
    return None


def _pages(path: Path) -> int:
    from pypdf import PdfReader

    return len(PdfReader(path).pages)


class PdfJob:
    """``report.pdf`` for one report: made before the figures are drawn, so that the browser
    starts meanwhile (``early``); ``finish`` prints the written HTML; ``close`` ends the browser.
    """

    def __init__(self, store: FigureStore, early: bool) -> None:
        self.store = store
        self.browser = find_browser()
        self.printer: Printer | None = None
        self.error = ""
        if self.browser is not None and early:
            self._start(self.browser)

    def _start(self, browser: Path) -> Printer | None:
        try:
            self.printer = Printer(browser, self.store.scratch_folder(), TIMEOUT)
        except OSError as error:
            self.error = f"{browser.name} could not be started: {error}"
        return self.printer

    def finish(self, html: Path, target: Path) -> PdfOutcome:
        """Print the written ``html`` file to ``target`` (or reuse the PDF of the same HTML);
        see the module docstring for a missing or failing browser."""
        if self.browser is None:
            unlink(target)
            return PdfOutcome(
                path=None,
                pages=0,
                reused=False,
                message=f"report.pdf not written: no Chromium on PATH to print report.html "
                f"({INSTALL}; or print report.html from any browser)",
            )
        stat = self.browser.resolve().stat()
        text = hashlib.sha256(read_bytes(html, TEXT_MAX_BYTES)).hexdigest()
        kept = self.store.pdf_file(digest_of("pdf", text, str(self.browser), stat.st_mtime_ns))
        reused = is_regular(kept)
        try:
            if not reused:
                printer = self.printer or self._start(self.browser)
                if printer is None:
                    raise BrowserError(self.error)
                printed = printer.print_pdf(html)
                atomic_save(kept, lambda stream: stream.write(printed), ".pdf", cache=True)
            else:
                printed = read_bytes(kept, ARTIFACT_MAX_BYTES)
            atomic_save(target, lambda stream: stream.write(printed), ".pdf")
        except (OSError, BrowserError, FileRefused) as error:
            unlink(target)
            unlink(kept)
            return PdfOutcome(
                path=None, pages=0, reused=False, message=f"report.pdf not written: {error}"
            )
        finally:
            self.close()
        pages = _pages(target)
        return PdfOutcome(
            path=target,
            pages=pages,
            reused=reused,
            message=f"report.pdf ({pages} pages{', reused' if reused else ''})",
        )

    def close(self) -> None:
        if self.printer is not None:
            self.printer.close()
