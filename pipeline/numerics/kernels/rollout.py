"""Numba closed-loop rollouts with their safety checks fused in: a template, compiled per scenario.

Not imported directly: ``pipeline.numerics.kernels.compiled`` appends it to ``loops.py`` and the
scenario's generated ``f_eval``. The maths is that of the NumPy oracle
``pipeline.numerics.closed_loop.simulate`` (``simulate_closed_loop`` and ``check_runs``), step for
step:

    xdot = f(x, clip(u_ref[k] + K[k] (x - x_ref(t)), lower, upper)),  k = floor(t / Ts)

integrated by RK4 with ``s`` substeps per sample interval, the controller evaluated at every RK4
stage (the stage at an interval's right end uses the left limit of the input), ``x_ref``
linearly interpolated on the emitted grid ``t_ref``; with ``hold > 0`` the input is computed at the
first stage of every ``hold``-th step and held (zero-order-hold feedback). Per run it returns,
without storing the path (only the positions of the first few runs, when asked): clearance to
Unsafe minus half the longest grid step (the motion bound between grid points), the signed
distance of the final position to Goal's boundary, the smallest input slack before clipping, the
tube ratio ``max_t max(|e(t)|_P(t) - slack, 0) e^(rate t) / |e(0)|_P(0)`` and its value at ``T``
(``P(t)`` given on the RK4 grid: one metric repeated for a ``/1`` file, a funnel's time-varying
metric for ``/2``), whether every state stayed finite, the smallest margin to the state bounds
less half the longest step of a bounded state, and the final state. The running minima of
Unsafe's distance and Goal's signed distance skip the grid points where the position is still
closer to the last measured point than that measurement was above the minimum: both distances
are 1-Lipschitz in the position, so the skipped points cannot lower the minimum (the oracle,
which measures every point, gives the same numbers). A point measured near the last full
measurement of Unsafe is measured against that measurement's nearest edge alone where the
other edges cannot have come nearer (``shared.cached_distance``: the same float).

Under a declared uncertainty (``pipeline.numerics.closed_loop.gusts``) each run flies ``f(x, (u,
p_b))`` (the parametric dynamics, its parameters ``p_b`` appended to the input) plus the gust
``w_b`` in force at the step's start, and the law sees ``x + eta_b`` (the measurement error in
force at the step's start; the law's reference shifted by ``-eta_b``, the same input); with
``every_goal`` the Goal margin is the smallest over
the grid less half the longest step (the continuation past ``T``: "in Goal at all times").

Shapes: ``B`` runs, ``n`` states, ``m`` inputs, ``N`` sample intervals, ``r`` reference points.
"""

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from pipeline.numerics.kernels.shared import (
    cached_distance,
    copy_vector,
    metric_norm,
    polygon_query,
    reference_state,
    unsafe_distance,
)

if TYPE_CHECKING:  # defined in the module this template is compiled into
    from pipeline.numerics.kernels.loops import f_eval

LEFT_LIMIT = 1e-9  # as pipeline.numerics.closed_loop.simulate
SAMPLE_ROUNDING = 1e-9  # as pipeline.controller: floor(t / Ts + 1e-9)
CLEARANCE, GOAL, SLACK, TUBE, TUBE_FINAL, FINITE, BOUNDS = 0, 1, 2, 3, 4, 5, 6
CHECKS = 7
GUST_ROUNDING = 1e-9  # as pipeline.numerics.closed_loop.gusts
LOOKAHEAD = 1.0  # m: Unsafe sets farther than the running minimum plus this are not measured
LIPSCHITZ_ROUNDING = 1e-12  # m: the skip's allowance for the rounding of a distance

# The law is inlined into the loop (``inline="always"``): called, with its array arguments, it
# costs ~20% of the rollouts/s. numba types and lowers every inlined copy (~0.3 s of compilation
# each, once per scenario), so the four RK4 stages are one loop with one copy.


@njit(cache=True, inline="always")
def closed_loop_slope(t, x, xr, law, raw, u, out):
    """``out (n,) = f(x, clip(raw))`` with ``raw (m,) = u_ref[k] + K[k] (x - xr)``, ``xr`` the
    reference state at ``t``; returns the input slack ``min(raw - lower, upper - raw)``.

    ``law = (Ts, u_ref (N, m), K (N, m, n), lower (m,), upper (m,))``; ``u (m,)``: workspace.
    """
    Ts, u_ref, K, lower, upper = law
    k = min(max(int(math.floor(t / Ts + SAMPLE_ROUNDING)), 0), u_ref.shape[0] - 1)
    slack = np.inf
    for j in range(raw.size):
        value = u_ref[k, j]
        for i in range(x.size):
            value += K[k, j, i] * (x[i] - xr[i])
        raw[j] = value
        slack = min(slack, value - lower[j], upper[j] - value)
        u[j] = min(max(value, lower[j]), upper[j])
    f_eval(x, u, out)
    return slack


@njit(cache=True)
def rollout_kernel(
    x0,
    s,
    hold,
    law,
    t_ref,
    x_ref,
    M,
    rate,
    slack,
    position,
    scene,
    goal,
    bounds,
    draws,
    every_goal,
    out,
    path,
):
    """Roll out every ``x0[b] (n,)`` around one reference; write its checks into
    ``out (B, CHECKS + n)``: the checks, then the final state; and the positions of the first
    ``R`` runs at every grid point into ``path (R, N s + 1, 2)`` (``R = 0``: none, the path is
    not stored).

    Args: ``hold``: RK4 steps per zero-order-hold window (0: the law at every stage); ``law`` as
    in ``closed_loop_slope`` (``K[k]`` held on sample interval ``k``),
    ``t_ref (r,)`` and ``x_ref (r, n)`` the reference grid, ``M (N s + 1, n, n)`` the tube
    metric at the RK4 grid times ``j Ts / s`` and ``rate`` its decay, ``slack`` the allowed
    interpolation error, ``position (2,)`` the position state indices, ``scene`` Unsafe as in
    ``unsafe_distance``, ``goal = (V, ring_start, index, lower, upper)``: Goal's rings and its extra
    bounds on states ``index`` at ``T``; ``bounds = (index (c,), lower (c,), upper (c,))`` the
    state bounds; ``draws = (parameters (B, q), gusts (B, G, n), start (B,), period, errors (B,
    G', n))`` as ``pipeline.numerics.closed_loop.gusts.Draws`` (``q = 0``, ``G = 0``: the exact
    model; ``G' = 0``: the state measured exactly, else ``G' = G``).
    """
    B, n = x0.shape
    m = law[1].shape[1]
    N = law[1].shape[0]
    h = law[0] / s
    p0 = position[0]
    p1 = position[1]
    # Stage times and reference states, the same for every run: at step j the RK4 stages are
    # taken at t_j = j h (column 0), t_j + h/2 (1, stages 2 and 3) and the left limit of t_{j+1}
    # (2); row N s holds T for the final checks.
    times = np.empty((N * s + 1, 3))
    XR = np.empty((N * s + 1, 3, n))
    for j in range(N * s + 1):
        times[j, 0] = j * h
        times[j, 1] = j * h + h / 2
        times[j, 2] = (j + 1) * h - (LEFT_LIMIT if (j + 1) % s == 0 else 0.0)
        for c in range(3):
            reference_state(times[j, c], t_ref, x_ref, XR[j, c])
    column = (0, 1, 1, 2)  # the time column of each RK4 stage
    step = (0.0, 0.5 * h, 0.5 * h, h)  # stage r evaluates at x + step[r] K[r - 1]
    K = np.empty((4, n))
    y = np.empty(n)
    raw = np.empty(m)
    parameters, gusts, start, period, errors = draws
    q = parameters.shape[1]
    G = gusts.shape[1]
    measured = errors.shape[1] > 0
    seen = np.empty(n)  # the law's reference shifted by -eta: u_ref + K (x + eta - x_ref)
    u = np.empty(m + q)  # the inputs, then the run's parameters
    bound_index, bound_lower, bound_upper = bounds
    rings = goal[1].size - 1
    lipschitz_goal = goal[2].size == 0  # Goal's extra state bounds are not distances
    unsafe_at = np.zeros(2)
    edge = np.empty(8)  # unsafe_distance's record of its nearest edge (cached_distance)
    goal_at = np.zeros(2)
    for b in range(B):
        x = x0[b].copy()
        for i in range(q):
            u[m + i] = parameters[b, i]
        bound_margin = np.inf
        bound_step = 0.0
        goal_margin = np.inf
        finite = True
        input_slack = np.inf
        nearest = np.inf
        longest_squared = 0.0
        denominator = 1.0
        tube = 0.0
        ratio = 0.0
        unsafe_floor = -1.0  # evaluate at the first grid point
        edge[4] = -1.0  # no nearest edge yet
        goal_floor = -1.0
        for j in range(N * s + 1):
            # the checks at grid point j (its state x(j h)), then the step to j + 1
            if b < path.shape[0]:
                path[b, j, 0] = x[p0]
                path[b, j, 1] = x[p1]
            # Unsafe's distance and Goal's signed distance are 1-Lipschitz in the position: one
            # measured ``floor`` above its running minimum cannot lower that minimum while the
            # position stays within ``floor`` of where it was measured (no result changes)
            # (squared: math.hypot cost ~10% of a held law's rollout)
            if _moved_beyond(x[p0] - unsafe_at[0], x[p1] - unsafe_at[1], unsafe_floor):
                # near the last full measurement its nearest edge alone may decide (exact)
                found = cached_distance(x[p0], x[p1], edge, LIPSCHITZ_ROUNDING)
                if found < 0.0:
                    found = unsafe_distance(x[p0], x[p1], nearest + LOOKAHEAD, scene, edge)
                nearest = min(nearest, found)
                unsafe_floor = found - nearest - LIPSCHITZ_ROUNDING
                unsafe_at[0], unsafe_at[1] = x[p0], x[p1]
            for c in range(bound_index.size):
                value = x[bound_index[c]]
                bound_margin = min(bound_margin, value - bound_lower[c], bound_upper[c] - value)
            if every_goal and (
                not lipschitz_goal
                or _moved_beyond(x[p0] - goal_at[0], x[p1] - goal_at[1], goal_floor)
            ):
                found = _goal_margin(x, p0, p1, goal, rings)
                goal_margin = min(goal_margin, found)
                goal_floor = found - goal_margin - LIPSCHITZ_ROUNDING
                goal_at[0], goal_at[1] = x[p0], x[p1]
            norm = metric_norm(x, XR[j, 0], M, j)
            if j == 0:
                denominator = max(norm, 1e-12)
            ratio = max(norm - slack, 0.0) * math.exp(rate * (j * h)) / denominator
            tube = ratio if j == 0 else max(tube, ratio)
            if j == N * s:
                break
            g = -1
            if G > 0:
                g = int(math.floor((start[b] + j * h) / period + GUST_ROUNDING))
                g = min(max(g, 0), G - 1)
            for r in range(4):
                if r == 0:
                    copy_vector(x, y)
                else:
                    for i in range(n):
                        y[i] = x[i] + step[r] * K[r - 1, i]
                if hold == 0 or (r == 0 and j % hold == 0):
                    # the law at every stage, or at the first stage of a zero-order-hold window
                    c = column[r]
                    if measured and g >= 0:
                        for i in range(n):
                            seen[i] = XR[j, c, i] - errors[b, g, i]
                        stage_slack = closed_loop_slope(times[j, c], y, seen, law, raw, u, K[r])
                    else:
                        stage_slack = closed_loop_slope(times[j, c], y, XR[j, c], law, raw, u, K[r])
                    input_slack = min(input_slack, stage_slack)
                else:  # u held from the window's first state
                    f_eval(y, u, K[r])
                if g >= 0:
                    for i in range(n):
                        K[r, i] += gusts[b, g, i]
            px = x[p0]
            py = x[p1]
            for c in range(bound_index.size):
                y[c] = x[bound_index[c]]
            for i in range(n):
                x[i] = x[i] + (h / 6.0) * (K[0, i] + 2.0 * K[1, i] + 2.0 * K[2, i] + K[3, i])
                if not math.isfinite(x[i]):
                    finite = False
            longest_squared = max(longest_squared, (x[p0] - px) ** 2 + (x[p1] - py) ** 2)
            for c in range(bound_index.size):
                bound_step = max(bound_step, abs(x[bound_index[c]] - y[c]))
        longest = math.sqrt(longest_squared)
        out[b, CLEARANCE] = nearest - longest / 2
        if every_goal:
            out[b, GOAL] = goal_margin - longest / 2
        else:
            out[b, GOAL] = _goal_margin(x, p0, p1, goal, rings)
        out[b, BOUNDS] = bound_margin - bound_step / 2
        out[b, SLACK] = input_slack
        out[b, TUBE] = tube
        out[b, TUBE_FINAL] = ratio
        out[b, FINITE] = 1.0 if finite else 0.0
        for i in range(n):
            out[b, CHECKS + i] = x[i]


@njit(cache=True, inline="always")
def _moved_beyond(dx, dy, floor):
    """Whether the move ``(dx, dy)`` is at least ``floor`` long: always when ``floor < 0`` (-1
    at the first point, down to ``-LIPSCHITZ_ROUNDING`` after a new minimum), never when it is
    NaN (no Unsafe set within reach: ``inf - inf``), as ``math.hypot(dx, dy) >= floor`` was."""
    return floor < 0.0 or dx * dx + dy * dy >= floor * floor


@njit(cache=True)
def _goal_margin(x, p0, p1, goal, rings):
    """Signed distance of ``x``'s position to Goal's boundary (negative: outside Goal or its
    extra bounds ``goal[2:]``)."""
    goal_V, goal_start, goal_index, goal_lower, goal_upper = goal
    inside, to_edge, _, _ = polygon_query(x[p0], x[p1], goal_V, goal_start, 0, rings)
    for g in range(goal_index.size):
        value = x[goal_index[g]]
        inside = inside and goal_lower[g] <= value <= goal_upper[g]
    return to_edge if inside else -to_edge
