"""Drawing helpers over the position plane: the scenario's sets, trajectories, tubes.

One palette for every figure: demonstrations blue, optimized trajectories orange, the bisection's
intermediate feasible trajectories in purples, closed-loop runs teal, failures and gaps red.

Tubes: the set ``{x : ||x - x_ref(t)||_P <= rho}`` projects on the position plane to the ellipse
``{p : (p - p_ref)^T Sigma^-1 (p - p_ref) <= rho^2}`` with ``Sigma = C P^-1 C^T``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.axis import Axis
from matplotlib.collections import EllipseCollection
from matplotlib.patches import Rectangle
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
from shapely.geometry import box
from shapely.geometry.base import BaseGeometry

from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

DEMO = "#4C72B0"
OPTIMIZED = "#DD8452"
CLOSED_LOOP = "#2A9D8F"
FAILURE = "#C44E52"
GOAL = "#55A868"
INIT = "0.15"
UNSAFE = "0.62"
BOUND = "#8C1C13"
INTERMEDIATE = "Purples"
FUNNEL = "#00838F"  # the shipped funnels E_i(t): dark cyan outlines, apart from the orange nominals

# Figures are drawn ``FIGURE_WIDTH`` in wide and shown the column's full width: up to ~1170 px
# on a desktop (2.5x) and down to a phone's column (~365 px, 0.85x), where 10 pt text is 8.5 px.
FIGURE_WIDTH = 6.0  # in
STYLE: dict[RcKeyType, object] = {
    "font.size": 10,
    "axes.titlesize": 10.5,
    "axes.labelsize": 10,
    "legend.fontsize": 10,
    "xtick.labelsize": 10,
    "ytick.labelsize": 10,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.color": "0.9",
    "grid.linewidth": 0.6,
    "svg.fonttype": "none",
    "pdf.fonttype": 42,
}


SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _power_of_ten(value: float, _: object = None) -> str:
    """A decade as ``10⁻²`` (plain text, not mathtext: building its parser costs ~1 s)."""
    if value <= 0:
        return ""
    exponent = round(float(np.log10(value)))
    if abs(value / 10.0**exponent - 1) > 1e-9:
        return ""
    return {0: "1", 1: "10"}.get(exponent, "10" + str(exponent).translate(SUPERSCRIPT))


def log_axis(axis: Axis) -> None:
    """A log-scaled ``axis`` labelled at decades in plain text (call after ``set_yscale``)."""
    axis.set_major_locator(LogLocator(base=10, numticks=6))
    axis.set_major_formatter(FuncFormatter(_power_of_ten))
    axis.set_minor_formatter(NullFormatter())


# ``**style``: matplotlib artist properties, ``Any`` as matplotlib's own stubs type them.
def _fill(ax: Axes, shape: BaseGeometry, **style: Any) -> None:
    for poly in getattr(shape, "geoms", [shape]):
        if not poly.is_empty:
            x, y = poly.exterior.xy
            ax.fill(x, y, **style)
            style.pop("label", None)  # one legend entry per set


def _outline(ax: Axes, shape: BaseGeometry, **style: Any) -> None:
    for poly in getattr(shape, "geoms", [shape]):
        if not poly.is_empty:
            ax.plot(*poly.exterior.xy, **style)
            style.pop("label", None)


def scenario_frame(
    scenario: Scenario, positions: FloatArray | None = None, margin: float = 4.0
) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)``: Init and Goal (and ``positions (..., 2)``) with a margin,
    widened so that at least 1 of every Unsafe set beside the frame shows."""
    i, j = scenario.position_index
    lo, hi = scenario.init_lower, scenario.init_upper
    frame = box(lo[i], lo[j], hi[i], hi[j]).union(scenario.goal)
    xmin, ymin, xmax, ymax = frame.buffer(margin).bounds
    if positions is not None and np.size(positions):
        p = np.asarray(positions).reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p):
            xmin, ymin = min(xmin, p[:, 0].min() - 1.0), min(ymin, p[:, 1].min() - 1.0)
            xmax, ymax = max(xmax, p[:, 0].max() + 1.0), max(ymax, p[:, 1].max() + 1.0)
    for region in scenario.unsafe.values():
        strip = region.intersection(box(xmin, -1e9, xmax, 1e9))
        if not strip.is_empty:
            low, high = strip.bounds[1], strip.bounds[3]
            ymax = max(ymax, low + 1.0) if low >= ymax - 1.0 else ymax
            ymin = min(ymin, high - 1.0) if high <= ymin + 1.0 else ymin
    return xmin, xmax, ymin, ymax


def draw_scenario(
    ax: Axes,
    scenario: Scenario,
    positions: FloatArray | None = None,
    goal_label: str = "Goal",
) -> None:
    """Unsafe sets (grey; bloated by ``d`` dotted), Goal (green), ModGoal (Goal shrunk by ``d``,
    dashed) and Init (dark outline), framed to include ``positions (..., 2)``."""
    xmin, xmax, ymin, ymax = scenario_frame(scenario, positions)
    view = box(xmin, ymin, xmax, ymax)
    for k, (name, region) in enumerate(scenario.unsafe.items()):
        _fill(ax, region, color=UNSAFE, zorder=1, lw=0, label="Unsafe" if k == 0 else None)
        bloated = geometry.bloat(region, scenario.clearance)
        _outline(
            ax,
            bloated,
            color="0.35",
            ls=":",
            lw=0.9,
            zorder=1,
            label=f"Unsafe bloated by d = {scenario.clearance:g} m" if k == 0 else None,
        )
        visible = region.intersection(view)
        if not visible.is_empty:
            where = visible.representative_point()
            ax.annotate(
                name,
                (where.x, where.y),
                color="0.1",
                fontsize=10,
                ha="center",
                va="center",
                zorder=6,
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75},
            )
    _fill(ax, scenario.goal, color=GOAL, alpha=0.22, lw=0, zorder=1, label=goal_label)
    _outline(
        ax,
        geometry.shrink(scenario.goal, scenario.clearance),
        color=GOAL,
        ls="--",
        lw=1.1,
        zorder=2,
        label="ModGoal (Goal shrunk by d)",
    )
    i, j = scenario.position_index
    lo, hi = scenario.init_lower, scenario.init_upper
    ax.add_patch(
        Rectangle(
            (lo[i], lo[j]),
            hi[i] - lo[i],
            hi[j] - lo[j],
            fill=False,
            edgecolor=INIT,
            lw=1.3,
            label="Init",
            zorder=5,
        )
    )
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.grid(False)
    ax.set_xlabel(axis_label(scenario, scenario.state_names[i], "m"))
    ax.set_ylabel(axis_label(scenario, scenario.state_names[j], "m"))


def axis_label(scenario: Scenario, name: str, unit: str = "") -> str:
    """``name`` with its label and unit (``Scenario.label``); ``unit`` where none is declared."""
    if scenario.unit(name) or not unit:
        return scenario.label(name)
    return f"{scenario.label(name)} [{unit}]"


def draw_path(
    ax: Axes,
    scenario: Scenario,
    ts: FloatArray,
    xs: FloatArray,
    color: str,
    label: str | None = None,
    marker_period: float | None = 1.0,
    marker: str = "o",
    **style: Any,
) -> None:
    """One trajectory ``xs (K, n)`` at times ``ts (K,)``; markers every ``marker_period``
    seconds (evenly spaced in time, so their spacing shows the speed)."""
    p = scenario.positions(xs)
    ax.plot(p[:, 0], p[:, 1], color=color, label=label, zorder=4, **style)
    if marker_period:
        t = np.arange(0.0, ts[-1] + 1e-9, marker_period)
        ax.plot(
            np.interp(t, ts, p[:, 0]),
            np.interp(t, ts, p[:, 1]),
            marker,
            ms=2.6,
            color=color,
            alpha=float(style.get("alpha", 1.0)),
            zorder=4,
        )


def ellipses(
    ax: Axes,
    shape: FloatArray,
    centers: FloatArray,
    radii: FloatArray,
    color: str,
    filled: bool = False,
    label: str | None = None,
    **style: object,
) -> None:
    """The ellipses ``{p : (p - c_k)^T shape_k^-1 (p - c_k) <= r_k^2}`` for ``centers (k, 2)``
    and ``radii (k,)``; ``shape (2, 2)`` (one for all, from ``projection_shape`` or
    ``slice_shape``) or ``(k, 2, 2)`` (one each, e.g. a funnel's ellipsoids along a path)."""
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    shapes = np.broadcast_to(np.asarray(shape, dtype=np.float64), (len(radii), 2, 2))
    values, vectors = np.linalg.eigh(shapes)  # (k, 2), (k, 2, 2); ascending
    angle = np.degrees(np.arctan2(vectors[:, 1, 1], vectors[:, 0, 1]))  # the major axes
    collection = EllipseCollection(
        widths=2 * radii * np.sqrt(values[:, 1]),
        heights=2 * radii * np.sqrt(values[:, 0]),
        angles=angle,
        units="xy",
        offsets=np.asarray(centers, dtype=np.float64).reshape(-1, 2),
        offset_transform=ax.transData,
        facecolors=color if filled else "none",
        edgecolors=color,
        zorder=3,
        **style,
    )
    if label:
        collection.set_label(label)
    ax.add_collection(collection)
