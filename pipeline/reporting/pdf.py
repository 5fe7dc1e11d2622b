"""``report.pdf``: ``report.html`` printed by a headless Chromium (one source for both files).

The page's print style (``templates/report.html.j2``, ``@media print``) lays it out on A4: the
title on page 1, sections flowing on without half-empty pages, no figure or table row cut in
two. The browser is a system program, not a Python package: where none is found (``chromium``,
``chromium-browser``, ``google-chrome`` on ``PATH``) or it fails, no PDF is written, an older
``report.pdf`` is removed (never left looking current) and the outcome's message says why and
how to get one. A PDF printed from the same HTML is reused (kept by the HTML's digest).
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from pipeline.io.artifacts import atomic_save
from pipeline.reporting.figure_cache import FigureStore, digest_of

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
TIMEOUT = 120.0  # s
INSTALL = "Debian/Ubuntu: apt-get install chromium"


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


def _print(browser: Path, html: Path, target: Path, profile: Path) -> None:
    """``html`` printed to ``target`` by ``browser`` (headless; no network, no profile kept)."""
    command = [
        str(browser),
        "--headless",
        "--no-sandbox",  # as root (CI, containers) Chromium refuses to start otherwise
        "--disable-gpu",
        "--no-first-run",
        "--disable-extensions",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-pdf-header-footer",
        f"--user-data-dir={profile}",
        f"--print-to-pdf={target}",
        html.resolve().as_uri(),
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT, check=False)
    if done.returncode != 0 or not target.is_file() or target.stat().st_size == 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"{browser.name} exited with code {done.returncode}: {last}")


def _copy(source: Path, target: Path) -> None:
    shutil.copyfile(source, target)


def _pages(path: Path) -> int:
    from pypdf import PdfReader

    return len(PdfReader(path).pages)


def write_pdf(html: Path, target: Path, store: FigureStore) -> PdfOutcome:
    """Print the written ``html`` file to ``target``; see the module docstring for a missing
    or failing browser."""
    browser = find_browser()
    if browser is None:
        target.unlink(missing_ok=True)
        return PdfOutcome(
            path=None,
            pages=0,
            reused=False,
            message=f"report.pdf not written: no Chromium on PATH to print report.html "
            f"({INSTALL}; or print report.html from any browser)",
        )
    text = html.read_bytes()
    stat = browser.resolve().stat()
    digest = digest_of("pdf", hashlib.sha256(text).hexdigest(), str(browser), stat.st_mtime_ns)
    kept = store.pdf_file(digest)
    reused = kept.is_file()
    try:
        if not reused:
            printed = store.scratch_folder() / "report.pdf"
            _print(browser, html, printed, store.scratch_folder())
            atomic_save(kept, partial(_copy, printed), ".pdf")
        atomic_save(target, partial(_copy, kept), ".pdf")
    except (OSError, RuntimeError, subprocess.TimeoutExpired) as error:
        target.unlink(missing_ok=True)
        kept.unlink(missing_ok=True)
        timed_out = isinstance(error, subprocess.TimeoutExpired)
        reason = f"Chromium timed out after {TIMEOUT:g} s" if timed_out else str(error)
        return PdfOutcome(
            path=None, pages=0, reused=False, message=f"report.pdf not written: {reason}"
        )
    pages = _pages(target)
    return PdfOutcome(
        path=target,
        pages=pages,
        reused=reused,
        message=f"report.pdf ({pages} pages{', reused' if reused else ''})",
    )
