"""The report's figures, each drawn into a matplotlib figure or subfigure from ``ReportData``.

Colours follow ``pipeline.reporting.plotting``: demonstrations blue, optimized orange, intermediate
feasible trajectories purple, closed loop teal, failures and gaps red.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.ticker import MaxNLocator

from pipeline.controller import load
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.closed_loop import simulate_closed_loop
from pipeline.numerics.tube import projection_shape, slice_shape
from pipeline.reporting.content import FigureLike
from pipeline.reporting.data import ReportData
from pipeline.reporting.plotting import (
    BOUND,
    CLOSED_LOOP,
    DEMO,
    FAILURE,
    INIT,
    INTERMEDIATE,
    OPTIMIZED,
    draw_path,
    draw_scenario,
    ellipses,
)

TUBE_PERIOD = 0.5  # s between the tube ellipses drawn along a path
MARKER_PERIOD = 1.0  # s between the time markers on a path


def _legend_below(fig: FigureLike, ax: Axes, handles: Sequence[object] | None = None) -> None:
    entries = ax.get_legend_handles_labels() if handles is None else (handles, None)
    if handles is None:
        fig.legend(*entries, loc="outside lower center", ncols=4, frameon=False)
    else:
        fig.legend(handles=handles, loc="outside lower center", ncols=4, frameon=False)


def _tube_along(
    ax: Axes, data: ReportData, path: Trajectory, radius: float, color: str, along: bool
) -> None:
    """The tube's position projection at the start (outlined) and every ``TUBE_PERIOD`` s."""
    s, feedback = data.scenario, data.feedback
    if radius <= 0:
        return
    shape = projection_shape(feedback.certified_tube.P, s.position_index)
    t = np.arange(0.0, path.duration + 1e-9, TUBE_PERIOD) if along else np.zeros(1)
    p = s.positions(path.dense_xs)
    centres = np.stack([np.interp(t, path.dense_ts, p[:, 0]), np.interp(t, path.dense_ts, p[:, 1])])
    rho = radius * np.exp(-feedback.rate * t)  # the tube's P-radius at t
    if along:
        ellipses(ax, shape, centres.T, rho, color, filled=True, alpha=0.06, lw=0)
    ellipses(ax, shape, centres.T[:1], rho[:1], color, lw=0.8, alpha=0.8)


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
        _tube_along(ax, data, final, data.radius_optimized[k].radius, OPTIMIZED, along=True)
    handles = [
        *ax.get_legend_handles_labels()[0],
        Line2D([], [], color=DEMO, lw=0.8, marker="o", ms=2.6, label="demonstrations"),
        Line2D([], [], color=OPTIMIZED, lw=1.3, marker="o", ms=2.6, label="optimized"),
        Patch(facecolor=OPTIMIZED, alpha=0.25, edgecolor=OPTIMIZED, label="tube (optimized)"),
    ]
    _legend_below(fig, ax, handles)


def bisection_demo(data: ReportData) -> int:
    """The demo shown like the paper's Fig. 2: the one flown closest to Unsafe."""
    clearances = [d.clearance_before for d in data.summary.demos]
    return int(np.argmin(clearances))


def draw_bisection(fig: FigureLike, data: ReportData, index: int) -> None:
    """The paper's Fig. 2: one demo, the bisection's intermediate feasible trajectories, the
    optimal one, and the tubes about the initial point."""
    s = data.scenario
    opt = data.optimize.trajectories[index]
    demo, final = data.demo_paths[index], data.final_paths[index]
    feasible = [simulate(s.dynamics, opt.x0, u, s.Ts) for u in opt.feasible_inputs[:-1]]
    ax = fig.subplots()
    draw_scenario(ax, s, _all_positions([demo, final, *feasible], data))
    shades = colormaps[INTERMEDIATE](np.linspace(0.35, 0.75, max(len(feasible), 1)))
    for path, shade in zip(feasible, shades, strict=False):
        draw_path(
            ax,
            s,
            path.dense_ts,
            path.dense_xs,
            shade,
            f"feasible, T' = {path.duration:.1f} s",
            TUBE_PERIOD,
            lw=0.9,
        )
    label = f"{opt.demo} as flown, T = {demo.duration:.1f} s"
    draw_path(ax, s, demo.dense_ts, demo.dense_xs, DEMO, label, TUBE_PERIOD, lw=1.3)
    label = f"optimal, T' = {final.duration:.1f} s"
    draw_path(ax, s, final.dense_ts, final.dense_xs, OPTIMIZED, label, TUBE_PERIOD, lw=1.6)
    _tube_along(ax, data, demo, data.radius_demos[index].radius, DEMO, along=False)
    _tube_along(ax, data, final, data.radius_optimized[index].radius, OPTIMIZED, along=False)
    handles = [
        *ax.get_legend_handles_labels()[0],
        Line2D(
            [], [], color=DEMO, marker="o", ls="", mfc="none", ms=9, label="tube at start, demo"
        ),
        Line2D(
            [],
            [],
            color=OPTIMIZED,
            marker="o",
            ls="",
            mfc="none",
            ms=9,
            label="tube at start, optimal",
        ),
    ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)


def draw_optimization(fig: FigureLike, data: ReportData) -> None:
    """Per demo: J and the step size over the final horizon's descent; the horizons tried."""
    cost, step, tries = fig.subplots(1, 3)
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
    tries.legend(
        handles=[
            Line2D([], [], color="0.3", marker="o", ls="", label="feasible (J = 0)"),
            Line2D([], [], color="0.3", marker="x", ls="", label="infeasible"),
        ],
        loc="upper right",
        frameon=False,
    )
    fig.legend(
        *step.get_legend_handles_labels(), loc="outside lower center", ncols=9, frameon=False
    )


def _box(ax: Axes, lower: FloatArray, upper: FloatArray, **style: Any) -> None:
    """The box ``[lower, upper]`` (2,); ``style``: matplotlib's (``Any``-typed) patch properties."""
    width, height = np.asarray(upper) - lower
    ax.add_patch(Rectangle((lower[0], lower[1]), width, height, **style))


def _state_label(scenario: Scenario, index: int) -> str:
    name = scenario.state_names[index]
    return f"{name} (m)" if index in scenario.position_index else name


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
        ax.set_title(f"{name}: {coverage.covered_fraction:.1%} of Init certified covered")
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
        ax.set_xlabel(_state_label(s, pair[0]))
        ax.set_ylabel(_state_label(s, pair[1]))
    handles = [
        Rectangle((0, 0), 1, 1, fill=False, edgecolor=INIT, lw=1.4, label="Init"),
        Patch(facecolor=DEMO, alpha=0.3, edgecolor=DEMO, label="tube slice, demonstrations"),
        Patch(facecolor=OPTIMIZED, alpha=0.3, edgecolor=OPTIMIZED, label="tube slice, optimized"),
        Rectangle((0, 0), 1, 1, fill=False, edgecolor="0.75", label="certified box"),
        Patch(facecolor=FAILURE, alpha=0.6, label="uncovered box"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=5, frameon=False)


def draw_montecarlo(fig: FigureLike, data: ReportData) -> None:
    """Closed-loop paths (a subsample), failures, and the distributions of the margins."""
    s, mc = data.scenario, data.montecarlo
    axes = fig.subplot_mosaic([["paths", "paths"], ["clearance", "tube"]], height_ratios=[1.5, 1])
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
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
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
        xlabel="tube tightness  max_t ||e(t)||_P e^(λt) / ||e(0)||_P",
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
    ax.legend(loc="best", frameon=False)


def inputs_trajectory(data: ReportData) -> tuple[int, FloatArray]:
    """The reference trajectory of the inputs figure and the closed-loop starts simulated around
    it ``(B, n)``: the falsification's worst start (first), and Init's corners that the controller
    assigns to the same trajectory."""
    s = data.scenario
    worst = np.asarray(data.montecarlo.falsification.worst_x0, dtype=np.float64)
    controller = load(data.controller_path)
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
    controller = load(data.controller_path)
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
        ax.set_ylabel(name)
        span = hi - lo
        ax.set_ylim(lo - 0.08 * span, hi + 0.08 * span)
    axes[-1].set_xlabel("t (s)")
    handles, labels = axes[0].get_legend_handles_labels()
    for ax in axes[1:]:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    fig.legend(handles, labels, loc="outside right upper", frameon=False)
