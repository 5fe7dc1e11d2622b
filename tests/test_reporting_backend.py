"""The report modules draw on bare ``matplotlib.figure.Figure`` objects: importing them (and
rendering a figure) leaves matplotlib's backend and pyplot alone, e.g. in a user's notebook."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

PROGRAM = """
import sys
import matplotlib
before = dict.__getitem__(matplotlib.rcParams, "backend")
import stages.report
from pipeline.reporting import figures, html, pdf, plotting
from pipeline.reporting.content import Figure
figure = Figure(key="k", caption="", size=(2, 1), draw=lambda fig: fig.subplots().plot([0, 1]))
svg = html.figure_svg(figure)
assert "<svg" in svg[:500], svg[:200]
assert dict.__getitem__(matplotlib.rcParams, "backend") is before, "the backend was changed"
assert "matplotlib.pyplot" not in sys.modules, "pyplot was imported"
print("ok")
"""


def test_reporting_neither_selects_a_backend_nor_imports_pyplot() -> None:
    result = subprocess.run(
        [sys.executable, "-c", PROGRAM], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"
