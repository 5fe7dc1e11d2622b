"""The report's figures, each drawn into a matplotlib figure or subfigure from ``ReportData``.

Colours follow ``pipeline.reporting.plotting``: demonstrations blue, optimized orange, intermediate
feasible trajectories purple, closed loop teal, failures and gaps red.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.cm import ScalarMappable
from matplotlib.colors import ListedColormap, Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.ticker import MaxNLocator

from pipeline.model.dynamics import FloatArray
from pipeline.model.simulate import Trajectory
from pipeline.numerics.closed_loop import simulate_closed_loop
from pipeline.numerics.tube import projection_shape, slice_shape
from pipeline.reporting.content import FigureLike
from pipeline.reporting.data import ReportData, simulate_all
from pipeline.reporting.plotting import (
    BOUND,
    CLOSED_LOOP,
    DEMO,
    FAILURE,
    FIGURE_WIDTH,
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
MARKER_PERIOD = 1.0  # s between the time markers on a path


def _legend_below(fig: FigureLike, handles: Sequence[object], ncols: int = 2) -> None:
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


def draw_tube(ax: Axes, tube: TubeSections, color: str, alpha: float = 0.07) -> None:
    """The tube shaded along its path and outlined at its first time (the start)."""
    if not np.any(tube.radii > 0):
        return
    ellipses(ax, tube.shapes, tube.centres, tube.radii, color, filled=True, alpha=alpha, lw=0)
    ellipses(ax, tube.shapes[:1], tube.centres[:1], tube.radii[:1], color, lw=0.9, alpha=0.9)


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
    """Scenario, every demonstration and its optimized trajectory with its tube."""
    s = data.scenario
    ax = fig.subplots()
    draw_scenario(ax, s, _all_positions([*data.demo_paths, *data.final_paths], data))
    for k, (demo, final) in enumerate(zip(data.demo_paths, data.final_paths, strict=True)):
        draw_path(ax, s, demo.dense_ts, demo.dense_xs, DEMO, None, MARKER_PERIOD, lw=0.8)
        draw_path(ax, s, final.dense_ts, final.dense_xs, OPTIMIZED, None, MARKER_PERIOD, lw=1.3)
        tube = constant_tube(data, final, data.radius_optimized[k].radius, _along(final))
        draw_tube(ax, tube, OPTIMIZED, alpha=0.06)
    handles = [
        *ax.get_legend_handles_labels()[0],
        Line2D([], [], color=DEMO, lw=0.8, marker="o", ms=2.6, label="demonstrations"),
        Line2D([], [], color=OPTIMIZED, lw=1.3, marker="o", ms=2.6, label="optimized"),
        Patch(facecolor=OPTIMIZED, alpha=0.25, edgecolor=OPTIMIZED, label="tube (optimized)"),
    ]
    _legend_below(fig, handles)


def bisection_demo(data: ReportData) -> int:
    """The demo shown like the paper's Fig. 2: the one flown closest to Unsafe."""
    clearances = [d.clearance_before for d in data.summary.demos]
    return int(np.argmin(clearances))


def draw_bisection(fig: FigureLike, data: ReportData, index: int) -> None:
    """The paper's Fig. 2: one demo, the search's intermediate feasible trajectories coloured by
    their horizon ``T'`` (one colour scale), the optimal one, and the tubes of the demo and of
    the optimal trajectory along their paths."""
    s = data.scenario
    opt = data.optimize.trajectories[index]
    demo, final = data.demo_paths[index], data.final_paths[index]
    inputs = list(opt.feasible_inputs[:-1])
    feasible = simulate_all(s, [opt.x0] * len(inputs), inputs) if inputs else []
    ax = fig.subplots()
    draw_scenario(ax, s, _all_positions([demo, final, *feasible], data))
    draw_tube(ax, constant_tube(data, demo, data.radius_demos[index].radius, _along(demo)), DEMO)
    tube = constant_tube(data, final, data.radius_optimized[index].radius, _along(final))
    draw_tube(ax, tube, OPTIMIZED)
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
    label = f"optimal, T' = {final.duration:.1f} s"
    draw_path(ax, s, final.dense_ts, final.dense_xs, OPTIMIZED, label, TUBE_PERIOD, lw=1.6)
    handles = [
        *ax.get_legend_handles_labels()[0],
        Patch(facecolor=DEMO, alpha=0.3, edgecolor=DEMO, label="tube of the demonstration"),
        Patch(facecolor=OPTIMIZED, alpha=0.3, edgecolor=OPTIMIZED, label="tube of the optimal"),
    ]
    _legend_below(fig, handles)


def draw_optimization(fig: FigureLike, data: ReportData) -> None:
    """Per demo: J and the step size over the final horizon's descent; the horizons tried."""
    cost, step, tries = fig.subplots(3, 1)
    colours = colormaps["tab10"]
    for k, opt in enumerate(data.optimize.trajectories):
        colour = colours(k % 10)
        log = opt.log
        positive = log.cost > 0
        cost.step(log.iteration[positive], log.cost[positive], where="post", color=colour, lw=1)
        if len(log.cost) and opt.success:  # the real J reached 0: a triangle on the bottom axis
            cost.plot(
                log.iteration[-1],
                0.0,
                "v",
                color=colour,
                ms=5,
                transform=cost.get_xaxis_transform(),
            )
        step.plot(log.iteration, log.step, color=colour, lw=0.9, label=opt.demo)
        n = np.arange(1, len(opt.tries) + 1)
        T = np.array([t.N for t in opt.tries]) * opt.Ts
        ok = np.array([t.feasible for t in opt.tries], dtype=bool)
        tries.plot(n, T, color=colour, lw=0.8, alpha=0.7)
        tries.plot(n[ok], T[ok], "o", color=colour, ms=3.5)
        tries.plot(n[~ok], T[~ok], "x", color=colour, ms=4)
    cost.set(
        yscale="log", xlabel="iteration", ylabel="penalty cost J", title="cost at the final T'"
    )
    step.set(yscale="log", xlabel="iteration", ylabel="step size λ", title="step size λ")
    tries.set(xlabel="try", ylabel="horizon T' (s)", title="horizons tried")
    log_axis(cost.yaxis)
    log_axis(step.yaxis)
    tries.legend(
        handles=[
            Line2D([], [], color="0.3", marker="o", ls="", label="feasible (J = 0)"),
            Line2D([], [], color="0.3", marker="x", ls="", label="infeasible"),
        ],
        loc="upper right",
        frameon=False,
    )
    fig.legend(
        *step.get_legend_handles_labels(), loc="outside lower center", ncols=3, frameon=False
    )


def _box(ax: Axes, lower: FloatArray, upper: FloatArray, **style: Any) -> None:
    """The box ``[lower, upper]`` (2,); ``style``: matplotlib's (``Any``-typed) patch properties."""
    width, height = np.asarray(upper) - lower
    ax.add_patch(Rectangle((lower[0], lower[1]), width, height, **style))


def draw_coverage(fig: FigureLike, data: ReportData) -> None:
    """Init over its free states with the tube slices at the starts, before and after."""
    s = data.scenario
    free = list(data.coverage_demos.free)
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    starts = np.array([d.x0 for d in s.demos])
    cases = (
        ("demonstrations", data.coverage_demos, data.radius_demos, DEMO),
        ("optimized", data.coverage_optimized, data.radius_optimized, OPTIMIZED),
    )
    for ax, (name, coverage, radii, colour) in zip(axes, cases, strict=True):
        r = np.array([max(x.radius, 0.0) for x in radii])
        ax.set_title(f"{name}:\n{coverage.covered_fraction:.1%} of Init covered")
        if len(free) == 0:
            ax.text(0.5, 0.5, "Init is a single point", ha="center", transform=ax.transAxes)
            continue
        pair = free[:2] if len(free) >= 2 else [free[0], free[0]]
        for lower, upper in coverage.boxes[:, :, pair]:
            _box(ax, lower, upper, fill=False, edgecolor="0.75", lw=0.5, zorder=2)
        for lower, upper in coverage.uncovered_boxes[:, :, pair]:
            _box(ax, lower, upper, facecolor=FAILURE, alpha=0.6, lw=0, zorder=2)
        if len(free) >= 2:
            shape = slice_shape(data.feedback.certified_tube.P, pair)
            ellipses(ax, shape, starts[:, pair], r, colour, filled=True, alpha=0.08, lw=0)
            ellipses(ax, shape, starts[:, pair], r, colour, lw=1.0)
        else:
            half = r / np.sqrt(data.feedback.certified_tube.P[free[0], free[0]])
            for c, h in zip(starts[:, free[0]], half, strict=True):
                ax.plot([c - h, c + h], [c, c], color=colour, lw=2)
        ax.plot(*starts[:, pair].T, "o", color=colour, ms=3, zorder=4)
        lo, hi = s.init_lower[pair], s.init_upper[pair]
        _box(ax, lo, hi, fill=False, edgecolor=INIT, lw=1.4, zorder=5)
        pad = 0.6 * max(hi - lo)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.set_xlabel(axis_label(s, s.state_names[pair[0]]))
        ax.set_ylabel(axis_label(s, s.state_names[pair[1]]))
    handles = [
        Rectangle((0, 0), 1, 1, fill=False, edgecolor=INIT, lw=1.4, label="Init"),
        Patch(facecolor=DEMO, alpha=0.3, edgecolor=DEMO, label="tube slice, demonstrations"),
        Patch(facecolor=OPTIMIZED, alpha=0.3, edgecolor=OPTIMIZED, label="tube slice, optimized"),
        Rectangle((0, 0), 1, 1, fill=False, edgecolor="0.75", label="certified box"),
        Patch(facecolor=FAILURE, alpha=0.6, label="uncovered box"),
    ]
    _legend_below(fig, handles)


def draw_montecarlo(fig: FigureLike, data: ReportData) -> None:
    """Closed-loop paths (a subsample), failures, and the distributions of the margins."""
    s, mc = data.scenario, data.montecarlo
    axes = fig.subplot_mosaic([["paths"], ["clearance"], ["tube"]], height_ratios=[1.6, 1, 1])
    ax = axes["paths"]
    paths = [np.asarray(p) for p in mc.paths]
    draw_scenario(ax, s, np.concatenate(paths) if paths else None)
    for k, p in enumerate(paths):
        label = f"closed loop ({len(paths)} of {mc.samples} runs)" if k == 0 else None
        ax.plot(p[:, 0], p[:, 1], color=CLOSED_LOOP, lw=0.6, alpha=0.55, label=label, zorder=4)
    failed = s.positions(np.asarray(mc.failed_x0).reshape(-1, s.n))
    if len(failed):
        ax.plot(
            *failed.T, "x", color=FAILURE, ms=5, zorder=6, label=f"failed start ({len(failed)})"
        )
    worst = s.positions(np.asarray(mc.falsification.worst_x0))
    ax.plot(*worst, "*", color=FAILURE, mec="white", mew=0.5, ms=9, zorder=6)
    ax.plot([], [], "*", color=FAILURE, ms=8, label="worst start found by falsification")
    _legend_below(fig, ax.get_legend_handles_labels()[0])
    _histogram(
        axes["clearance"],
        np.asarray(mc.clearance),
        failed=lambda v: v <= 0,
        threshold=0.0,
        reference=(s.clearance, f"d = {s.clearance:g} m"),
        xlabel="minimum clearance to Unsafe (m)",
    )
    _histogram(
        axes["tube"],
        np.asarray(mc.tube_tightness),
        failed=lambda v: v > 1.0 + 1e-6,
        threshold=1.0,
        reference=None,
        xlabel="tube tightness max_t ||e(t)||_P e^(λt) / ||e(0)||_P",
        log=True,
    )


def _histogram(
    ax: Axes,
    values: FloatArray,
    failed: Callable[[FloatArray], npt.NDArray[np.bool_]],
    threshold: float,
    reference: tuple[float, str] | None,
    xlabel: str,
    log: bool = False,
) -> None:
    finite = values[np.isfinite(values)]
    bad = failed(finite)
    low = min(float(finite.min()), threshold) if len(finite) else threshold
    high = max(float(finite.max()), threshold) if len(finite) else threshold + 1
    bins = np.linspace(low, high + 1e-12, 41).tolist()  # a list: matplotlib's stub wants one
    ax.hist(finite[~bad], bins=bins, color=CLOSED_LOOP, alpha=0.8, label="passed")
    if bad.any():
        ax.hist(finite[bad], bins=bins, color=FAILURE, label=f"failed ({int(bad.sum())})")
    ax.axvline(threshold, color=FAILURE, lw=1.2, ls="--", label="failure threshold")
    if reference is not None:
        ax.axvline(reference[0], color="0.3", lw=0.9, ls=":", label=reference[1])
    ax.set(xlabel=xlabel, ylabel="runs (log scale)" if log else "runs")
    ax.xaxis.set_major_locator(MaxNLocator(6))
    if log:
        ax.set_yscale("log")
        log_axis(ax.yaxis)
    ax.legend(loc="best", frameon=False)


def inputs_trajectory(data: ReportData) -> tuple[int, FloatArray]:
    """The reference trajectory of the inputs figure and the closed-loop starts simulated around
    it ``(B, n)``: the falsification's worst start (first), and Init's corners that the controller
    assigns to the same trajectory."""
    s = data.scenario
    worst = np.asarray(data.montecarlo.falsification.worst_x0, dtype=np.float64)
    controller = data.law
    index = int(controller.select(worst[None])[0][0])
    free = np.flatnonzero(s.init_upper > s.init_lower)
    corners = np.tile(s.init_lower, (2 ** len(free), 1))
    for k, i in enumerate(free):
        corners[:, i] = np.where(
            (np.arange(len(corners)) >> k) & 1, s.init_upper[i], s.init_lower[i]
        )
    corners = corners[controller.select(corners)[0] == index]
    return index, np.vstack([worst[None], corners])


def draw_inputs(fig: FigureLike, data: ReportData) -> None:
    """``u_ref`` of one reference trajectory and the closed-loop inputs (before clipping)
    against the input bounds and the operating region."""
    s = data.scenario
    controller = data.law
    index, starts = inputs_trajectory(data)
    reference = controller.trajectories[index]
    run = simulate_closed_loop(s.dynamics, controller, starts, index)
    t = run.ts[:-1]
    demo = next((d for d in s.demos if np.allclose(d.x0, reference.x0)), None)
    axes = np.atleast_1d(fig.subplots(s.m, 1, sharex=True))
    for j, ax in enumerate(axes):
        name = s.input_names[j]
        if demo is not None:
            T = s.Ts * np.arange(demo.N + 1)
            u = np.append(demo.us[:, j], demo.us[-1, j])
            ax.step(T, u, where="post", color=DEMO, lw=0.8, alpha=0.6, label="demo input as flown")
        for b in range(1, len(starts)):
            label = "closed loop, Init corners" if b == 1 else None
            ax.plot(t, run.unclipped[b, :, 0, j], color=CLOSED_LOOP, lw=0.6, alpha=0.5, label=label)
        worst = run.unclipped[0, :, 0, j]
        ax.plot(t, worst, color=CLOSED_LOOP, lw=2.4, alpha=0.55, label="closed loop, worst start")
        T = controller.Ts * np.arange(len(reference.u_ref) + 1)
        u = np.append(reference.u_ref[:, j], reference.u_ref[-1, j])
        ax.step(T, u, where="post", color=OPTIMIZED, lw=1.1, label="u_ref (optimized)")
        lo, hi = s.input_lower[j], s.input_upper[j]
        ax.axhline(lo, color=BOUND, ls="--", lw=1, label="input bounds")
        ax.axhline(hi, color=BOUND, ls="--", lw=1)
        if name in s.operating_region:
            for v in s.operating_region[name]:
                ax.axhline(v, color="0.45", ls=":", lw=1.2)
            ax.plot([], [], color="0.45", ls=":", label="operating region")
        ax.set_title(axis_label(s, name), loc="left")
        ax.set_ylabel(f"[{s.unit(name)}]" if s.unit(name) else name)
        span = hi - lo
        ax.set_ylim(lo - 0.08 * span, hi + 0.08 * span)
    axes[-1].set_xlabel("t (s)")
    handles, labels = axes[0].get_legend_handles_labels()
    for ax in axes[1:]:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    fig.legend(handles, labels, loc="outside lower center", ncols=2, frameon=False)
