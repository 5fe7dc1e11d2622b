"""Screenshots of a run's report.html for the README, at desktop and phone width::

    python -m bench.screenshots reports/quadrotor_hill    # -> docs/report-1280.png,
                                                          #    docs/report-390.png

Headless Chromium (``chromium-headless-shell`` or ``chromium`` on PATH) draws the page's first
``HEIGHT`` pixels at each width. A headless window is never narrower than 500 px, so the phone
width is shown in an iframe of that width and the screenshot cut to it. Not a benchmark (its
name does not start with ``bench_``, so ``make bench`` does not run it).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from html import escape
from pathlib import Path

import matplotlib.image

BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome")
WIDTHS = (1280, 390)
HEIGHT = {1280: 1500, 390: 2200}  # px of the page shown from its top


def screenshot(report: Path, width: int, target: Path, browser: str) -> None:
    """``report`` (an HTML file) ``width`` px wide, its first ``HEIGHT[width]`` px, as PNG."""
    height = HEIGHT[width]
    with tempfile.TemporaryDirectory() as folder:
        page = Path(folder) / "page.html"
        page.write_text(
            '<!doctype html><html><head><meta charset="utf-8"></head><body style="margin:0">'
            '<iframe style="border:0;'
            f'width:{width}px;height:{height}px" srcdoc="{escape(report.read_text(), quote=True)}">'
            "</iframe></body></html>"
        )
        shot = Path(folder) / "shot.png"
        subprocess.run(
            [
                browser,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--hide-scrollbars",
                f"--user-data-dir={folder}/profile",
                f"--window-size={max(width, 500)},{height}",
                f"--screenshot={shot}",
                page.as_uri(),
            ],
            check=True,
            capture_output=True,
            timeout=180,
        )
        pixels = matplotlib.image.imread(shot)[:height, :width]
        matplotlib.image.imsave(target, pixels)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.screenshots", description=__doc__)
    parser.add_argument("run", type=Path, help="a finished run's folder (holds report.html)")
    parser.add_argument("--docs", type=Path, default=Path("docs"), help="where to write")
    args = parser.parse_args(argv)
    browser = next((found for name in BROWSERS if (found := shutil.which(name))), None)
    if browser is None:
        print("error: no Chromium on PATH (chromium-headless-shell or chromium)", file=sys.stderr)
        return 2
    report = args.run / "report.html"
    if not report.is_file():
        print(f"error: {report}: not found; run python -m pipeline synthesize", file=sys.stderr)
        return 2
    for width in WIDTHS:
        target = args.docs / f"report-{width}.png"
        screenshot(report, width, target, browser)
        print(f"{target}: {width} x {HEIGHT[width]} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())
