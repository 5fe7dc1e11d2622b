"""The report's closed-loop figures (Monte Carlo, inputs), drawn from ``ReportData`` with the
controller read back from controller.json. Colours as in ``pipeline.reporting.figures``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt
from matplotlib.axes import Axes
from matplotlib.ticker import MaxNLocator

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.closed_loop.simulate import simulate_closed_loop
from pipeline.reporting.content import FigureLike
from pipeline.reporting.data import ReportData
from pipeline.reporting.figures import legend_below
from pipeline.reporting.plotting import (
    BOUND,
    CLOSED_LOOP,
    DEMO,
    FAILURE,
    OPTIMIZED,
    axis_label,
    draw_scenario,
    log_axis,
)


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
    legend_below(fig, ax.get_legend_handles_labels()[0])
    _histogram(
        axes["clearance"],
        np.asarray(mc.clearance),
        failed=lambda v: v <= 0,
        threshold=0.0,
        reference=(s.clearance, "nominal clearance (not a closed-loop requirement)"),
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
