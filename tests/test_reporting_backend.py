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
from pipeline.reporting import figures, html, pdf, plotting, typeset
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


def test_coverage_boxes_are_drawn_once_per_distinct_shadow() -> None:
    """A subdivision of a many-dimensional Init projects many boxes onto the same rectangle of
    the two states shown: each distinct rectangle is drawn once, none is lost."""
    import numpy as np
    from matplotlib.figure import Figure

    from pipeline.reporting.figures import _projected_boxes

    rng = np.random.default_rng(0)
    grid = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5], [0.5, 0.5]])  # four shadows
    lower = np.zeros((400, 5))
    lower[:, :2] = grid[rng.integers(0, 4, 400)]
    lower[:, 2:] = rng.random((400, 3))  # the other states differ from box to box
    boxes = np.stack([lower, lower + 0.5], axis=1)  # (400, 2, 5)
    ax = Figure().add_subplot()
    _projected_boxes(ax, boxes, [0, 1], facecolor="none", edgecolor="0.75")
    (collection,) = ax.collections
    drawn = sorted(tuple(path.vertices[:4].min(axis=0)) for path in collection.get_paths())
    assert drawn == sorted(map(tuple, grid))
    _projected_boxes(ax, boxes[:0], [0, 1])  # no boxes: nothing drawn
    assert len(ax.collections) == 1
