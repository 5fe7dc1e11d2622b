"""Numba closed-loop rollouts with their safety checks fused in: a template, compiled per scenario.

Not imported directly: ``pipeline.numerics.kernels.compiled`` appends it to ``loops.py`` and the
scenario's generated ``f_eval``. The maths is that of the NumPy oracle
``pipeline.numerics.closed_loop`` (``simulate_closed_loop`` and ``check_runs``), step for step:

    xdot = f(x, clip(u_ref[k] + K[k] (x - x_ref(t)), lower, upper)),  k = floor(t / Ts)

integrated by RK4 with ``s`` substeps per sample interval, the controller evaluated at every RK4
stage (the stage at an interval's right end uses the left limit of the input), ``x_ref``
linearly interpolated on the emitted grid ``t_ref``; with ``hold > 0`` the input is computed at the
first stage of every ``hold``-th step and held (zero-order-hold feedback). Per run it returns,
without storing the path: clearance to Unsafe minus half the longest grid step (the motion bound
between grid points), the signed distance of the final position to Goal's boundary, the smallest
input slack before clipping, the tube ratio ``max_t max(|e(t)|_P(t) - slack, 0) e^(rate t) /
|e(0)|_P(0)`` and its value at ``T`` (``P(t)`` given on the RK4 grid: one metric repeated for a
``/1`` file, a funnel's time-varying metric for ``/2``), whether every state stayed finite, and
the final state.

Shapes: ``B`` runs, ``n`` states, ``m`` inputs, ``N`` sample intervals, ``r`` reference points.
"""

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:  # defined in the module this template is compiled into
    from pipeline.numerics.kernels.loops import f_eval, polygon_query

LEFT_LIMIT = 1e-9  # as pipeline.numerics.closed_loop
SAMPLE_ROUNDING = 1e-9  # as pipeline.controller: floor(t / Ts + 1e-9)
CLEARANCE, GOAL, SLACK, TUBE, TUBE_FINAL, FINITE = 0, 1, 2, 3, 4, 5
CHECKS = 6

# The helpers are inlined into the loop (``inline="always"``): a call with array arguments would
# otherwise pay numba's reference counting on every RK4 stage.


@njit(cache=True, inline="always")
def reference_state(t, t_ref, x_ref, out):
    """``out (n,) = x_ref(t)`` by linear interpolation on ``t_ref (r,)`` (as ``np.interp``)."""
    r = t_ref.size
    # element loops, not slice copies (a slice copy's error message costs ~1.6 s to compile)
    if t <= t_ref[0]:
        for i in range(out.size):
            out[i] = x_ref[0, i]
        return
    if t >= t_ref[r - 1]:
        for i in range(out.size):
            out[i] = x_ref[r - 1, i]
        return
    # the emitted grid is uniform up to rounding: guess the interval, then correct the guess
    j = min(max(int((t - t_ref[0]) / (t_ref[r - 1] - t_ref[0]) * (r - 1)), 0), r - 2)
    while j > 0 and t_ref[j] > t:
        j -= 1
    while j < r - 2 and t_ref[j + 1] <= t:
        j += 1
    w = (t - t_ref[j]) / (t_ref[j + 1] - t_ref[j])
    for i in range(out.size):
        out[i] = x_ref[j, i] + w * (x_ref[j + 1, i] - x_ref[j, i])


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


@njit(cache=True, inline="always")
def unsafe_distance(px, py, nearest, scene):
    """``min(nearest, distance from (px, py) to the nearest Unsafe set)`` (0 inside one).

    A set whose bounding box is at least ``nearest`` away cannot lower the minimum: skipped.
    ``scene = (V, ring_start, set_rings, boxes (sets, 4) as xmin, ymin, xmax, ymax)``.
    """
    V, ring_start, set_rings, boxes = scene
    for S in range(set_rings.size - 1):
        dx = max(boxes[S, 0] - px, 0.0, px - boxes[S, 2])
        dy = max(boxes[S, 1] - py, 0.0, py - boxes[S, 3])
        if math.sqrt(dx * dx + dy * dy) >= nearest:
            continue
        inside, d, _, _ = polygon_query(px, py, V, ring_start, set_rings[S], set_rings[S + 1])
        nearest = min(nearest, 0.0 if inside else d)
    return nearest


@njit(cache=True, inline="always")
def metric_norm(x, xr, M, g):
    """``|x - xr|_M[g]`` for ``x, xr (n,)``, ``M (G, n, n)`` metrics on the RK4 grid."""
    q = 0.0
    for i in range(x.size):
        for j in range(x.size):
            q += (x[i] - xr[i]) * M[g, i, j] * (x[j] - xr[j])
    return math.sqrt(max(q, 0.0))


@njit(cache=True)
def rollout_kernel(x0, s, hold, law, t_ref, x_ref, M, rate, slack, position, scene, goal, out):
    """Roll out every ``x0[b] (n,)`` around one reference; write its checks into
    ``out (B, CHECKS + n)``: the checks, then the final state.

    Args: ``hold``: RK4 steps per zero-order-hold window (0: the law at every stage); ``law`` as
    in ``closed_loop_slope`` (``K[k]`` held on sample interval ``k``),
    ``t_ref (r,)`` and ``x_ref (r, n)`` the reference grid, ``M (N s + 1, n, n)`` the tube
    metric at the RK4 grid times ``j Ts / s`` and ``rate`` its decay, ``slack`` the allowed
    interpolation error, ``position (2,)`` the position state indices, ``scene`` Unsafe as in
    ``unsafe_distance``, ``goal = (V, ring_start, index, lower, upper)``: Goal's rings and its extra
    bounds on states ``index`` at ``T``.
    """
    B, n = x0.shape
    m = law[1].shape[1]
    N = law[1].shape[0]
    h = law[0] / s
    p0 = position[0]
    p1 = position[1]
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    y = np.empty(n)
    xr_now = np.empty(n)
    xr_mid = np.empty(n)
    xr_end = np.empty(n)
    raw = np.empty(m)
    u = np.empty(m)
    for b in range(B):
        x = x0[b].copy()
        finite = True
        input_slack = np.inf
        reference_state(0.0, t_ref, x_ref, xr_now)
        norm0 = metric_norm(x, xr_now, M, 0)
        denominator = max(norm0, 1e-12)
        ratio = max(norm0 - slack, 0.0) / denominator
        tube = ratio
        nearest = unsafe_distance(x[p0], x[p1], np.inf, scene)
        longest = 0.0
        for j in range(N * s):
            t = j * h
            t_end = (j + 1) * h - (LEFT_LIMIT if (j + 1) % s == 0 else 0.0)
            reference_state(t + h / 2, t_ref, x_ref, xr_mid)
            reference_state(t_end, t_ref, x_ref, xr_end)
            if hold == 0:
                slack_1 = closed_loop_slope(t, x, xr_now, law, raw, u, k1)
                for i in range(n):
                    y[i] = x[i] + 0.5 * h * k1[i]
                slack_2 = closed_loop_slope(t + h / 2, y, xr_mid, law, raw, u, k2)
                for i in range(n):
                    y[i] = x[i] + 0.5 * h * k2[i]
                slack_3 = closed_loop_slope(t + h / 2, y, xr_mid, law, raw, u, k3)
                for i in range(n):
                    y[i] = x[i] + h * k3[i]
                slack_4 = closed_loop_slope(t_end, y, xr_end, law, raw, u, k4)
                input_slack = min(input_slack, slack_1, slack_2, slack_3, slack_4)
            else:  # zero-order hold: u from the window's first state, held for hold steps
                if j % hold == 0:
                    slack_1 = closed_loop_slope(t, x, xr_now, law, raw, u, k1)
                    input_slack = min(input_slack, slack_1)
                else:
                    f_eval(x, u, k1)
                for i in range(n):
                    y[i] = x[i] + 0.5 * h * k1[i]
                f_eval(y, u, k2)
                for i in range(n):
                    y[i] = x[i] + 0.5 * h * k2[i]
                f_eval(y, u, k3)
                for i in range(n):
                    y[i] = x[i] + h * k3[i]
                f_eval(y, u, k4)
            px = x[p0]
            py = x[p1]
            for i in range(n):
                x[i] = x[i] + (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
                if not math.isfinite(x[i]):
                    finite = False
            longest = max(longest, math.hypot(x[p0] - px, x[p1] - py))
            nearest = unsafe_distance(x[p0], x[p1], nearest, scene)
            reference_state((j + 1) * h, t_ref, x_ref, xr_now)  # the next step's first stage
            norm = metric_norm(x, xr_now, M, j + 1)
            ratio = max(norm - slack, 0.0) * math.exp(rate * ((j + 1) * h)) / denominator
            tube = max(tube, ratio)
        goal_V, goal_start, goal_index, goal_lower, goal_upper = goal
        rings = goal_start.size - 1
        inside, to_edge, _, _ = polygon_query(x[p0], x[p1], goal_V, goal_start, 0, rings)
        for g in range(goal_index.size):
            value = x[goal_index[g]]
            inside = inside and goal_lower[g] <= value <= goal_upper[g]
        out[b, CLEARANCE] = nearest - longest / 2
        out[b, GOAL] = to_edge if inside else -to_edge
        out[b, SLACK] = input_slack
        out[b, TUBE] = tube
        out[b, TUBE_FINAL] = ratio
        out[b, FINITE] = 1.0 if finite else 0.0
        for i in range(n):
            out[b, CHECKS + i] = x[i]
