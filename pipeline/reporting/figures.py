"""The report's figures, each drawn into a matplotlib figure or subfigure from ``ReportData``.

Colours follow ``pipeline.reporting.plotting``: demonstrations blue, optimized orange, intermediate
feasible trajectories purple, closed loop teal, failures and gaps red.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.collections import PolyCollection
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from pipeline.model.dynamics import FloatArray
from pipeline.model.simulate import Trajectory
from pipeline.numerics.tube.geometry import projection_shape, slice_shape
from pipeline.reporting.content import FigureLike
from pipeline.reporting.data import ReportData, simulate_all
from pipeline.reporting.plotting import (
    DEMO,
    FAILURE,
    FIGURE_WIDTH,
    FUNNEL,
    INIT,
    INTERMEDIATE,
    OPTIMIZED,
    axis_label,
    draw_path,
    draw_scenario,
    ellipses,
    log_axis,
    scenario_frame,
)

TUBE_PERIOD = 0.5  # s between the tube ellipses drawn along a path
ARROW_SECONDS = 0.15  # an arrival arrow's length: this many seconds of travel at its velocity
ARRIVAL = "0.1"  # the arrival velocity arrows
FUNNEL_PERIOD = 0.5  # s between the funnel outlines of the funnel figure
MARKER_PERIOD = 1.0  # s between the time markers on a path


def legend_below(fig: FigureLike, handles: Sequence[object], ncols: int = 2) -> None:
    """One legend under the axes, inside the figure (constrained layout makes room for it)."""
    fig.legend(handles=handles, loc="outside lower center", ncols=ncols, frameon=False)


@dataclass(frozen=True, kw_only=True)
class TubeSections:
    """A tube's position projection at times ``t (k,)``: the ellipses
    ``{p : (p - centres_k)^T shapes_k^-1 (p - centres_k) <= radii_k^2}``, ``centres (k, 2)``,
    ``shapes (k, 2, 2)``, ``radii (k,)``. The constant-metric tube builds it here; a funnel
    certificate (``E_i(t)``) gives its own shapes per time and draws with the same code."""

    t: FloatArray
    centres: FloatArray
    shapes: FloatArray
    radii: FloatArray


def constant_tube(data: ReportData, path: Trajectory, radius: float, t: FloatArray) -> TubeSections:
    """The tube ``||x - x_ref(t)||_P <= radius e^(-λt)`` about ``path`` at times ``t (k,)``."""
    s = data.scenario
    shape = projection_shape(data.feedback.certified_tube.P, s.position_index)
    rate = data.feedback.rate if data.law.rate is None else data.law.rate  # None: no feedback block
    p = s.positions(path.dense_xs)
    centres = np.stack([np.interp(t, path.dense_ts, p[:, 0]), np.interp(t, path.dense_ts, p[:, 1])])
    return TubeSections(
        t=t,
        centres=centres.T,
        shapes=np.broadcast_to(shape, (len(t), 2, 2)),
        radii=max(radius, 0.0) * np.exp(-rate * t),  # the tube's P-radius at t
    )


def funnel_tube(data: ReportData, index: int, t: FloatArray) -> TubeSections:
    """The shipped funnel ``E_i(t) = {x : ||x - x_ref_i(t)||_{P_i(t)} <= radius_i e^(-rate_i t)}``
    of controller.json's trajectory ``index`` at times ``t (k,)``, projected on the position:
    shapes ``C P_i(t)^-1 C^T (k, 2, 2)`` (``P_i(t)`` interpolated as the file says, Q = P^-1
    linear in t), centres ``p_ref(t)`` on the file's fine grid."""
    s, tr = data.scenario, data.law.trajectories[index]
    c = list(s.position_index)
    Q = np.linalg.inv(tr.metric(t, data.law.Ts))  # (k, n, n)
    p = s.positions(tr.x_ref)
    centres = np.stack([np.interp(t, tr.t, p[:, 0]), np.interp(t, tr.t, p[:, 1])])
    return TubeSections(
        t=t,
        centres=centres.T,
        shapes=Q[:, c][:, :, c],
        radii=tr.radius * np.exp(-tr.rate * t),
    )


def shipped_tube(data: ReportData, index: int, t: FloatArray) -> TubeSections:
    """The tube the run ships around its trajectory ``index`` (``shipped_paths``): the funnel in
    a funnel run, the constant-metric tube otherwise."""
    if data.funnel:
        return funnel_tube(data, index, t)
    return constant_tube(data, data.final_paths[index], data.radius_optimized[index].radius, t)


def draw_tube(ax: Axes, tube: TubeSections, color: str, alpha: float = 0.07) -> None:
    """The tube shaded along its path and outlined at its first time (the start)."""
    if not np.any(tube.radii > 0):
        return
    ellipses(ax, tube.shapes, tube.centres, tube.radii, color, filled=True, alpha=alpha, lw=0)
    ellipses(ax, tube.shapes[:1], tube.centres[:1], tube.radii[:1], color, lw=0.9, alpha=0.9)


def draw_outlines(ax: Axes, tube: TubeSections, color: str = FUNNEL, lw: float = 0.8) -> None:
    """A funnel as outlines at each of its times (no shading: the path under it stays visible)."""
    if np.any(tube.radii > 0):
        ellipses(ax, tube.shapes, tube.centres, tube.radii, color, lw=lw, alpha=0.9)


def _ends(path: Trajectory) -> FloatArray:
    """The times ``(k,)`` at which a funnel is outlined: every ``TUBE_PERIOD`` s and at T."""
    t = np.arange(0.0, path.duration - 1e-9, TUBE_PERIOD)
    return np.append(t, path.duration)


def draw_arrivals(ax: Axes, data: ReportData, scale: float = ARROW_SECONDS) -> bool:
    """At each shipped nominal's end, its velocity as an arrow ``scale`` s of travel long
    (``Summary.funnels``: ``arrival_velocity``); False when the summary has none."""
    s, drawn = data.scenario, False
    for funnel, path in zip(data.summary.funnels, data.shipped_paths, strict=False):
        v = np.asarray(funnel.arrival_velocity, dtype=float)
        if v.shape != (2,) or not np.all(np.isfinite(v)):
            continue
        end = s.positions(path.dense_xs[-1])
        ax.annotate(
            "",
            xy=(end[0] + scale * v[0], end[1] + scale * v[1]),
            xytext=(end[0], end[1]),
            arrowprops={"arrowstyle": "-|>", "color": ARRIVAL, "lw": 1.2, "mutation_scale": 9},
            zorder=7,
        )
        drawn = True
    return drawn


def _along(path: Trajectory) -> FloatArray:
    """The times ``(k,)`` at which a tube is drawn along ``path``: every ``TUBE_PERIOD`` s."""
    return np.arange(0.0, path.duration + 1e-9, TUBE_PERIOD)


def scene_height(data: ReportData, paths: Sequence[Trajectory], below: float) -> float:
    """A figure height (in) for a ``FIGURE_WIDTH`` wide scene of ``paths`` at equal aspect,
    with ``below`` in under the axes (legend, colour bar)."""
    xmin, xmax, ymin, ymax = scenario_frame(data.scenario, _all_positions(paths, data))
    axes_width = FIGURE_WIDTH - 0.8  # less the y label and tick labels
    return axes_width * (ymax - ymin) / (xmax - xmin) + 0.7 + below


def _all_positions(paths: Sequence[Trajectory], data: ReportData) -> FloatArray:
    return np.concatenate([data.scenario.positions(p.dense_xs) for p in paths])


def draw_overview(fig: FigureLike, data: ReportData) -> None:
    """Scenario, every demonstration and the shipped (optimized) trajectories with their tubes:
    the constant-metric tube, or in a funnel run the funnel ``E_i(t)`` of controller.json."""
    s = data.scenario
    ax = fig.subplots()
    draw_scenario(ax, s, _all_positions([*data.demo_paths, *data.shipped_paths], data))
    for demo in data.demo_paths:
        draw_path(ax, s, demo.dense_ts, demo.dense_xs, DEMO, None, MARKER_PERIOD, lw=0.8)
    for k, path in enumerate(data.shipped_paths):
        draw_path(ax, s, path.dense_ts, path.dense_xs, OPTIMIZED, None, MARKER_PERIOD, lw=1.3)
        if data.funnel:
            draw_outlines(ax, funnel_tube(data, k, _ends(path)), lw=0.6)
        else:
            draw_tube(ax, shipped_tube(data, k, _along(path)), OPTIMIZED, alpha=0.06)
    arrows = data.funnel and draw_arrivals(ax, data)
    tube = (
        Line2D([], [], color=FUNNEL, lw=0.8, label="shipped funnels E_i(t)")
        if data.funnel
        else Patch(facecolor=OPTIMIZED, alpha=0.25, edgecolor=OPTIMIZED, label="tube (optimized)")
    )
    handles = [
        *ax.get_legend_handles_labels()[0],
        Line2D([], [], color=DEMO, lw=0.8, marker="o", ms=2.6, label="demonstrations"),
        Line2D(
            [],
            [],
            color=OPTIMIZED,
            lw=1.3,
            marker="o",
            ms=2.6,
            label="shipped nominals" if data.funnel else "optimized",
        ),
        tube,
        *([_arrow_handle()] if arrows else []),
    ]
    legend_below(fig, handles)


def _arrow_handle() -> Line2D:
    return Line2D(
        [],
        [],
        color=ARRIVAL,
        lw=1.2,
        marker=">",
        ms=5,
        label="arrival velocity",
    )


def draw_funnels(fig: FigureLike, data: ReportData) -> None:
    """The shipped funnels: the position projection of each ``E_i(t)`` along its path every
    ``FUNNEL_PERIOD`` s (outlined at ``t = 0`` and ``t = T``), over Unsafe, Goal and Init."""
    s = data.scenario
    ax = fig.subplots()
    draw_scenario(ax, s, _all_positions(data.shipped_paths, data))
    for k, path in enumerate(data.shipped_paths):
        draw_path(ax, s, path.dense_ts, path.dense_xs, OPTIMIZED, None, MARKER_PERIOD, lw=1.2)
        t = np.append(np.arange(0.0, path.duration - 1e-9, FUNNEL_PERIOD), path.duration)
        draw_outlines(ax, funnel_tube(data, k, t), lw=0.8)
    arrows = draw_arrivals(ax, data)
    handles = [
        *ax.get_legend_handles_labels()[0],
        Line2D([], [], color=OPTIMIZED, lw=1.2, marker="o", ms=2.6, label="shipped nominal"),
        Line2D(
            [],
            [],
            color=FUNNEL,
            lw=0.8,
            label="funnel E_i(t), position",
        ),
        *([_arrow_handle()] if arrows else []),
    ]
    legend_below(fig, handles)


def bisection_demo(data: ReportData) -> int:
    """The demo shown like the paper's Fig. 2: the one flown closest to Unsafe."""
    clearances = [d.clearance_before for d in data.summary.demos]
    return int(np.argmin(clearances))


def bisection_paths(data: ReportData, index: int) -> list[Trajectory]:
    """The nominal paths of the Fig. 2 analogue for demo ``index``: the demonstration, the
    constant certificate's optimum and, in a funnel run, the trajectory shipped from it."""
    shipped = data.shipped_index(index) if data.funnel else None
    extra = [] if shipped is None else [data.shipped_paths[shipped]]
    return [data.demo_paths[index], data.final_paths[index], *extra]


def draw_bisection(fig: FigureLike, data: ReportData, index: int) -> None:
    """The paper's Fig. 2: one demo, the search's intermediate feasible trajectories coloured by
    their horizon ``T'`` (one colour scale), the optimal one, and the tubes of the demo and of
    the optimal trajectory along their paths."""
    s = data.scenario
    opt = data.optimize.trajectories[index]
    demo, final = data.demo_paths[index], data.final_paths[index]
    inputs = list(opt.feasible_inputs[:-1])
    feasible = simulate_all(s, [opt.x0] * len(inputs), inputs) if inputs else []
    shipped = data.shipped_index(index) if data.funnel else None
    optimal = final if shipped is None else data.shipped_paths[shipped]
    ax = fig.subplots()
    draw_scenario(ax, s, _all_positions([demo, final, optimal, *feasible], data))
    draw_tube(ax, constant_tube(data, demo, data.radius_demos[index].radius, _along(demo)), DEMO)
    if shipped is None:
        tube = constant_tube(data, final, data.radius_optimized[index].radius, _along(final))
        draw_tube(ax, tube, OPTIMIZED)
    else:
        draw_outlines(ax, funnel_tube(data, shipped, _ends(optimal)))
    if feasible:
        horizons = np.array([path.duration for path in feasible])
        top = max(float(horizons.max()), float(horizons.min()) + s.Ts)
        colours = ListedColormap(colormaps[INTERMEDIATE](np.linspace(0.95, 0.4, 256)))
        norm = Normalize(float(horizons.min()), top)  # shorter T': darker
        scale = ScalarMappable(norm, colours)
        shades = colours(norm(horizons))  # (k, 4)
        for k in np.argsort(-horizons):  # shorter drawn on top
            p = s.positions(feasible[k].dense_xs)
            ax.plot(*p.T, color=shades[k], lw=0.9, zorder=4)
        bar = fig.colorbar(scale, ax=ax, location="bottom", shrink=0.8, aspect=35, pad=0.02)
        bar.set_label("T' of the intermediate feasible trajectories (s)")
        bar.ax.set_gid("colorbar")
    label = f"{opt.demo} as flown, T = {demo.duration:.1f} s"
    draw_path(ax, s, demo.dense_ts, demo.dense_xs, DEMO, label, TUBE_PERIOD, lw=1.3)
    moved = optimal.us.shape != final.us.shape or not np.allclose(optimal.us, final.us)
    if shipped is not None and moved:  # the nominal re-optimized against its funnel
        p = s.positions(final.dense_xs)
        label = f"optimal, constant certificate, T' = {final.duration:.1f} s"
        ax.plot(*p.T, color=OPTIMIZED, lw=1.0, ls="--", label=label, zorder=5)
    label = f"{'shipped' if shipped is not None else 'optimal'}, T' = {optimal.duration:.1f} s"
    draw_path(ax, s, optimal.dense_ts, optimal.dense_xs, OPTIMIZED, label, TUBE_PERIOD, lw=1.6)
    tube_handle = (
        Line2D([], [], color=FUNNEL, lw=0.8, label="funnel of the shipped")
        if shipped is not None
        else Patch(facecolor=OPTIMIZED, alpha=0.3, edgecolor=OPTIMIZED, label="tube of the optimal")
    )
    handles = [
        *ax.get_legend_handles_labels()[0],
        Patch(facecolor=DEMO, alpha=0.3, edgecolor=DEMO, label="tube of the demonstration"),
        tube_handle,
    ]
    legend_below(fig, handles, ncols=2 if len(handles) <= 4 else 1)  # one column fits a phone


def draw_optimization(fig: FigureLike, data: ReportData) -> None:
    """Per demo: J over the final horizon's descent (and, for gradient descent, its step size);
    the horizons tried. The demos' legend sits beside the cost panel it colours first."""
    gd = data.optimize.options.method == "gd"  # L-BFGS-B has no step size to show
    axes = fig.subplots(3 if gd else 2, 1)
    cost, tries = axes[0], axes[-1]
    step = axes[1] if gd else None
    colours = colormaps["tab10"]
    for k, opt in enumerate(data.optimize.trajectories):
        colour = colours(k % 10)
        log = opt.log
        positive = log.cost > 0
        cost.step(
            log.iteration[positive],
            log.cost[positive],
            where="post",
            color=colour,
            lw=1,
            label=opt.demo,
        )
        if len(log.cost) and opt.success:  # the real J reached 0: a triangle on the bottom axis
            cost.plot(
                log.iteration[-1],
                0.0,
                "v",
                color=colour,
                ms=5,
                transform=cost.get_xaxis_transform(),
            )
        if step is not None:
            step.plot(log.iteration, log.step, color=colour, lw=0.9)
        n = np.arange(1, len(opt.tries) + 1)
        T = np.array([t.N for t in opt.tries]) * opt.Ts
        ok = np.array([t.feasible for t in opt.tries], dtype=bool)
        tries.plot(n, T, color=colour, lw=0.8, alpha=0.7)
        tries.plot(n[ok], T[ok], "o", color=colour, ms=3.5)
        tries.plot(n[~ok], T[~ok], "x", color=colour, ms=4)
    cost.set(
        yscale="log", xlabel="iteration", ylabel="penalty cost J", title="cost at the final T'"
    )
    log_axis(cost.yaxis)
    cost.legend(loc="upper right", ncols=3, frameon=True, framealpha=0.85)
    if step is not None:
        step.set(yscale="log", xlabel="iteration", ylabel="step size λ", title="step size λ")
        log_axis(step.yaxis)
    tries.set(xlabel="try", ylabel="horizon T' (s)", title="horizons tried")
    tries.legend(
        handles=[
            Line2D([], [], color="0.3", marker="o", ls="", label="feasible (J = 0)"),
            Line2D([], [], color="0.3", marker="x", ls="", label="infeasible"),
        ],
        loc="upper right",
        frameon=False,
    )


def _box(ax: Axes, lower: FloatArray, upper: FloatArray, **style: Any) -> None:
    """The box ``[lower, upper]`` (2,); ``style``: matplotlib's (``Any``-typed) patch properties."""
    width, height = np.asarray(upper) - lower
    ax.add_patch(Rectangle((lower[0], lower[1]), width, height, **style))


def _projected_boxes(ax: Axes, boxes: FloatArray, pair: Sequence[int], **style: Any) -> None:
    """The boxes ``(B, 2, n)`` (lower, upper corners) projected on the states ``pair``, each
    distinct rectangle once, as one collection: a subdivision of a 5-dimensional Init has
    hundreds of thousands of boxes but far fewer distinct shadows (quadrotor_hill_gusty_flythrough:
    the coverage figure was 51 MB of SVG)."""
    if len(boxes) == 0:
        return
    shadows = np.unique(np.asarray(boxes)[:, :, list(pair)].reshape(len(boxes), 4), axis=0)
    x0, y0, x1, y1 = shadows.T
    corners = np.stack([np.c_[x0, y0], np.c_[x1, y0], np.c_[x1, y1], np.c_[x0, y1]], axis=1)
    ax.add_collection(PolyCollection(list(corners), zorder=2, **style))


def _coverage_panel(
    ax: Axes,
    data: ReportData,
    title: str,
    slices: tuple[FloatArray, FloatArray, FloatArray],
    colour: str,
    boxes: tuple[FloatArray, FloatArray] | None,
) -> None:
    """One panel of the coverage figure: Init over its first two free states (one free state:
    the interval twice), the certified and uncovered ``boxes`` ``(B, 2, n)`` when given, and
    the ellipsoid slices ``slices = (metrics (k, n, n), centres (k, n), radii (k,))``."""
    s = data.scenario
    free = list(data.coverage_demos.free)
    ax.set_title(title)
    if len(free) == 0:
        ax.text(0.5, 0.5, "Init is a single point", ha="center", transform=ax.transAxes)
        return
    pair = free[:2] if len(free) >= 2 else [free[0], free[0]]
    if boxes is not None:
        certified, uncovered = boxes
        _projected_boxes(ax, certified, pair, facecolor="none", edgecolor="0.75", lw=0.5)
        _projected_boxes(ax, uncovered, pair, facecolor=FAILURE, alpha=0.6, lw=0)
    metrics, centres, radii = slices
    if len(free) >= 2:
        shapes = np.stack([slice_shape(P, pair) for P in metrics])
        ellipses(ax, shapes, centres[:, pair], radii, colour, filled=True, alpha=0.08, lw=0)
        ellipses(ax, shapes, centres[:, pair], radii, colour, lw=1.0)
    else:
        half = radii / np.sqrt(metrics[:, free[0], free[0]])
        for c, h in zip(centres[:, free[0]], half, strict=True):
            ax.plot([c - h, c + h], [c, c], color=colour, lw=2)
    ax.plot(*centres[:, pair].T, "o", color=colour, ms=3, zorder=4)
    lo, hi = s.init_lower[pair], s.init_upper[pair]
    _box(ax, lo, hi, fill=False, edgecolor=INIT, lw=1.4, zorder=5)
    pad = 0.6 * max(hi - lo)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(axis_label(s, s.state_names[pair[0]]))
    ax.set_ylabel(axis_label(s, s.state_names[pair[1]]))
    ax.label_outer()  # shared axes: each label once


def draw_coverage(fig: FigureLike, data: ReportData) -> None:
    """Init over its free states with the slices at the starts: the constant balls of the
    demonstrations and of the optimized nominals, and in a funnel run the shipped funnels'
    initial ellipsoids ``E_i(0)`` (each in its own metric ``P_i[0]``, from controller.json)."""
    starts = np.array([d.x0 for d in data.scenario.demos])
    P = data.feedback.certified_tube.P
    cases = [
        ("demonstrations", data.coverage_demos, data.radius_demos, DEMO),
        ("optimized", data.coverage_optimized, data.radius_optimized, OPTIMIZED),
    ]
    axes = fig.subplots(1, 3 if data.funnel else 2, sharex=True, sharey=True)
    for ax, (name, coverage, radii, colour) in zip(axes, cases, strict=False):
        r = np.array([max(x.radius, 0.0) for x in radii])
        _coverage_panel(
            ax,
            data,
            f"{name}:\n{coverage.covered_fraction:.1%} covered",
            (np.broadcast_to(P, (len(r), *P.shape)), starts, r),
            colour,
            (coverage.boxes, coverage.uncovered_boxes),
        )
    handles = [
        Rectangle((0, 0), 1, 1, fill=False, edgecolor=INIT, lw=1.4, label="Init"),
        Patch(facecolor=DEMO, alpha=0.3, edgecolor=DEMO, label="ball slice, demonstrations"),
        Patch(facecolor=OPTIMIZED, alpha=0.3, edgecolor=OPTIMIZED, label="ball slice, optimized"),
        Rectangle((0, 0), 1, 1, fill=False, edgecolor="0.75", label="certified box"),
        Patch(facecolor=FAILURE, alpha=0.6, label="uncovered box"),
    ]
    if data.funnel:
        shipped = data.law.trajectories
        _coverage_panel(
            axes[-1],
            data,
            f"shipped funnels:\n{data.summary.headline.coverage_after:.1%} covered",
            (
                np.stack([tr.P[0] for tr in shipped]),
                np.stack([tr.x0 for tr in shipped]),
                np.array([tr.radius for tr in shipped]),
            ),
            FUNNEL,
            None,
        )
        handles.insert(
            3, Patch(facecolor=FUNNEL, alpha=0.3, edgecolor=FUNNEL, label="funnel slice E_i(0)")
        )
        for ax in (axes[0], axes[2]):  # three panels: the shared x label once, in the middle
            ax.set_xlabel("")
    legend_below(fig, handles)
