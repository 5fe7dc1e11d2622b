"""Figures: the scenario (Unsafe, Goal, Init, trajectories) over the position plane."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from shapely.geometry import box  # noqa: E402
from shapely.geometry.base import BaseGeometry  # noqa: E402

from pipeline import geometry  # noqa: E402
from pipeline.artifacts import atomic_save  # noqa: E402
from pipeline.dynamics import FloatArray  # noqa: E402
from pipeline.scenario import Scenario  # noqa: E402


def _fill(ax: Axes, shape: BaseGeometry, **style: object) -> None:
    polygons = getattr(shape, "geoms", [shape])
    for poly in polygons:
        if not poly.is_empty:
            x, y = poly.exterior.xy
            ax.fill(x, y, **style)


def draw_scenario(ax: Axes, scenario: Scenario) -> None:
    """Unsafe sets (grey, bloated by d dashed), Goal (green), ModGoal (dashed) and Init (blue)."""
    for name, region in scenario.unsafe.items():
        _fill(ax, region, color="0.55", alpha=0.9, zorder=1)
        rx, ry = region.representative_point().xy
        ax.annotate(name, (rx[0], ry[0]), color="white", ha="center", fontsize=8, zorder=2)
        bloated = geometry.bloat(region, scenario.clearance)
        for poly in getattr(bloated, "geoms", [bloated]):
            ax.plot(*poly.exterior.xy, color="0.4", ls=":", lw=0.8, zorder=1)
    _fill(ax, scenario.goal, color="tab:green", alpha=0.25, zorder=1, label="Goal")
    mod_goal = geometry.shrink(scenario.goal, scenario.clearance)
    for poly in getattr(mod_goal, "geoms", [mod_goal]):
        if not poly.is_empty:
            ax.plot(*poly.exterior.xy, color="tab:green", ls="--", lw=1, label="Goal shrunk by d")
    i, j = scenario.position_index
    lo, hi = scenario.init_lower, scenario.init_upper
    ax.add_patch(
        Rectangle(
            (lo[i], lo[j]),
            hi[i] - lo[i],
            hi[j] - lo[j],
            fill=False,
            edgecolor="tab:blue",
            lw=1.5,
            label="Init",
            zorder=3,
        )
    )
    # Frame Init and Goal with a margin; Unsafe sets are clipped to that frame.
    frame = geometry.polygon([(lo[i], lo[j]), (hi[i], lo[j]), (hi[i], hi[j]), (lo[i], hi[j])])
    xmin, ymin, xmax, ymax = frame.union(scenario.goal).buffer(4.0).bounds
    for region in scenario.unsafe.values():  # show at least 1 m of every set beside the frame
        strip = region.intersection(box(xmin, -1e9, xmax, 1e9))
        if not strip.is_empty:
            low, high = strip.bounds[1], strip.bounds[3]
            ymax = max(ymax, low + 1.0) if low >= ymax - 1.0 else ymax
            ymin = min(ymin, high - 1.0) if high <= ymin + 1.0 else ymin
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xlabel(scenario.state_names[i])
    ax.set_ylabel(scenario.state_names[j])


def draw_paths(
    ax: Axes,
    scenario: Scenario,
    paths: Sequence[FloatArray],
    labels: Sequence[str],
    marker_every: int | None = None,
    **style: object,
) -> None:
    """Trajectories ``(T, n)`` projected on position; markers every ``marker_every`` points."""
    for xs, label in zip(paths, labels, strict=True):
        p = scenario.positions(xs)
        (line,) = ax.plot(p[:, 0], p[:, 1], label=label, zorder=4, **style)
        if marker_every:
            ax.plot(
                p[::marker_every, 0],
                p[::marker_every, 1],
                "o",
                ms=2.5,
                color=line.get_color(),
                zorder=4,
            )


def save_scenario_figure(
    path: Path,
    scenario: Scenario,
    paths: Sequence[FloatArray],
    labels: Sequence[str],
    title: str,
    marker_every: int | None = None,
) -> None:
    """Write the scenario figure with ``paths`` to ``path`` (PNG) atomically."""
    fig, ax = plt.subplots(figsize=(10, 5), constrained_layout=True)
    draw_scenario(ax, scenario)
    draw_paths(ax, scenario, paths, labels, marker_every=marker_every, lw=1.2)
    ax.set_title(title)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    atomic_save(path, lambda p: fig.savefig(p, dpi=130), suffix=".png")
    plt.close(fig)
