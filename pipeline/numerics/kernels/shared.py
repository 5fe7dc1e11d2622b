"""The kernels' numba functions that do not depend on the dynamics: compiled once per machine.

A normal module (numba caches it beside this file, ``cache=True``): the per-scenario kernel
modules that ``pipeline.numerics.kernels.compiled`` generates from ``loops.py``, ``rollout.py`` and
the scenario's ``f_eval`` import these functions instead of compiling their own copies (numba links
the compiled callee into each caller). Each generated module's name hashes this file's source too,
the source this process imported (``SOURCE``), so an edit here gives new kernel modules; numba
stamps this module's own cache with the SHA-256 of the file's contents.

Penalties (eqs. (40)-(42), as ``pipeline.numerics.optimize.penalties``), polygon queries, the pruned
right-hand sides of (33)-(34), and the closed loop's reference, clearance and metric helpers.
Shapes: ``n`` states, ``m`` inputs; ``P`` is a ``pipeline.numerics.kernels.compiled.PenaltyData``
tuple (margins per RK4 grid point ``(N s + 1, ...)`` and per sample ``(N, ...)``); polygons are
vertex arrays ``V (v, 2)`` with rings ``ring_start[r]:ring_start[r+1]`` (not closed), Unsafe set
``S`` owning rings ``set_rings[S]:set_rings[S+1]``.
"""

import math
from pathlib import Path

import numpy as np
from numba import njit

SOURCE = Path(__file__).read_text()  # as imported: what the generated modules' key hashes
_SERIES_BELOW = 1e-4  # as pipeline.numerics.optimize.penalties

# The functions below except ``copy_vector`` and the penalties are not inlined
# (``inline="always"`` types and lowers a copy in every caller, once per scenario): a call costs
# the closed loop nothing measurable (bench montecarlo, same rollouts/s). The penalties, called
# at every grid point of every cost evaluation, are: unicycle_slalom demo 1's cost and
# gradient 157 -> 139 us, for 0.24 s more compilation per scenario.


@njit(cache=True, inline="always")
def copy_vector(source, target):
    """``target[:] = source`` for 1-D arrays, as a loop: numba compiles an array-to-array slice
    assignment with a shape-mismatch message built from strings, ~1.6 s once per process."""
    for i in range(source.size):
        target[i] = source[i]


@njit(cache=True, inline="always")
def segment_distance_squared(px, py, x1, y1, x2, y2):
    """Squared distance from ``(px, py)`` to the segment ``(x1, y1)-(x2, y2)``, and the
    segment's nearest point."""
    dx = x2 - x1
    dy = y2 - y1
    L = dx * dx + dy * dy
    t = 0.0
    if L > 0.0:
        t = min(max(((px - x1) * dx + (py - y1) * dy) / L, 0.0), 1.0)
    qx = x1 + t * dx
    qy = y1 + t * dy
    return (px - qx) * (px - qx) + (py - qy) * (py - qy), qx, qy


@njit(cache=True)
def polygon_scan(px, py, V, ring_start, r0, r1):
    """Rings ``r0..r1-1`` seen from ``(px, py)``: inside (even-odd rule), the squared distance
    to the nearest edge and to the next nearest (inf: no other edge), the nearest point, and
    the nearest edge's end vertices ``V[j] -> V[i]``."""
    inside = False
    best = np.inf
    second = np.inf
    cx = px
    cy = py
    j_best = -1
    i_best = -1
    for r in range(r0, r1):
        a = ring_start[r]
        b = ring_start[r + 1]
        j = b - 1
        for i in range(a, b):
            x1 = V[j, 0]
            y1 = V[j, 1]
            x2 = V[i, 0]
            y2 = V[i, 1]
            if (y2 > py) != (y1 > py):
                if px < x2 + (py - y2) * (x1 - x2) / (y1 - y2):
                    inside = not inside
            dd, qx, qy = segment_distance_squared(px, py, x1, y1, x2, y2)
            if dd < best:
                second = best
                best = dd
                cx = qx
                cy = qy
                j_best = j
                i_best = i
            elif dd < second:
                second = dd
            j = i
    return inside, best, second, cx, cy, j_best, i_best


@njit(cache=True)
def polygon_query(px, py, V, ring_start, r0, r1):
    """Inside (even-odd rule), distance and nearest point of rings ``r0..r1-1``."""
    inside, best, _, cx, cy, _, _ = polygon_scan(px, py, V, ring_start, r0, r1)
    return inside, math.sqrt(best), cx, cy


@njit(cache=True, inline="always")
def state_penalty(x, w, grad, P, i_grid):
    """``w (g_unsafe + g_reg)(x)`` at RK4 grid point ``i_grid`` (its margins); sets ``grad (n,)``
    to its derivative."""
    grad[:] = 0.0
    value = 0.0
    p0 = P.position[0]
    p1 = P.position[1]
    px = x[p0]
    py = x[p1]
    d = P.unsafe_margin[i_grid]
    for S in range(P.unsafe_set_rings.size - 1):
        # distance to the bounding box <= r: the barrier is zero when it exceeds d'
        ex = max(P.unsafe_box[S, 0] - px, 0.0, px - P.unsafe_box[S, 2])
        ey = max(P.unsafe_box[S, 1] - py, 0.0, py - P.unsafe_box[S, 3])
        if ex * ex + ey * ey > d * d:
            continue
        inside, r, cx, cy = polygon_query(
            px,
            py,
            P.unsafe_vertices,
            P.unsafe_ring_start,
            P.unsafe_set_rings[S],
            P.unsafe_set_rings[S + 1],
        )
        if inside or r <= 0.0:
            value = np.inf
        elif r < d:
            z = (r - d) / d  # eq. (42), corrected: b = -log(r/d') + (r - d')/d' = z - log1p(z)
            if z > -_SERIES_BELOW:
                value += z * z * (0.5 - z * (1.0 / 3.0 - z * (0.25 - z / 5.0)))
            else:
                value += z - math.log1p(z)
            slope = w * z / (1.0 + z) / d / r
            grad[p0] += slope * (px - cx)
            grad[p1] += slope * (py - cy)
    for j in range(P.region_state_index.size):
        i = P.region_state_index[j]
        lo = P.region_state_lower[i_grid, j]
        e = x[i] - min(max(x[i], lo), P.region_state_upper[i_grid, j])
        value += e * e
        grad[i] += w * 2.0 * e
    return w * value


@njit(cache=True, inline="always")
def input_penalty(u, grad, P, k):
    """``(g_in + g_reg)(u)`` (eq. (40)) for sample ``k`` (its margins); sets ``grad (m,)``."""
    value = 0.0
    for i in range(u.size):
        e = u[i] - min(max(u[i], P.input_lower[k, i]), P.input_upper[k, i])
        value += e * e
        grad[i] = 2.0 * e
    for j in range(P.region_input_index.size):
        i = P.region_input_index[j]
        e = u[i] - min(max(u[i], P.region_input_lower[k, j]), P.region_input_upper[k, j])
        value += e * e
        grad[i] += 2.0 * e
    return value


@njit(cache=True)
def final_penalty(x, grad, P):
    """``G(x)`` (eq. (41)); adds its derivative to ``grad (n,)``."""
    p0 = P.position[0]
    p1 = P.position[1]
    inside, r, cx, cy = polygon_query(
        x[p0], x[p1], P.goal_vertices, P.goal_ring_start, 0, P.goal_ring_start.size - 1
    )
    value = 0.0
    if not inside:
        value += r * r
        grad[p0] += 2.0 * (x[p0] - cx)
        grad[p1] += 2.0 * (x[p1] - cy)
    for j in range(P.goal_index.size):
        i = P.goal_index[j]
        e = x[i] - min(max(x[i], P.goal_lower[j]), P.goal_upper[j])
        value += e * e
        grad[i] += 2.0 * e
    return value


@njit(cache=True)
def all_finite(x):
    for i in range(x.size):
        if not math.isfinite(x[i]):
            return False
    return True


@njit(cache=True)
def variational_slope(A, B, zP, zQ, S, KP, KQ):
    """Right-hand sides of (33)-(34) on the pruned entries: ``KP = (A Phi)_P``,
    ``KQ = (A Gamma + B)_Q``; ``S`` = (phi_ptr, phi_a, phi_src, gamma_ptr, gamma_a, gamma_src,
    gamma_b) term lists of the sparse products."""
    phi_ptr, phi_a, phi_src, gamma_ptr, gamma_a, gamma_src, gamma_b = S
    for e in range(KP.size):
        acc = 0.0
        for t in range(phi_ptr[e], phi_ptr[e + 1]):
            acc += A[phi_a[t]] * zP[phi_src[t]]
        KP[e] = acc
    for e in range(KQ.size):
        acc = B[gamma_b[e]]
        for t in range(gamma_ptr[e], gamma_ptr[e + 1]):
            acc += A[gamma_a[t]] * zQ[gamma_src[t]]
        KQ[e] = acc


@njit(cache=True)
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
    # bisection: the emitted grid may be finer on some sample intervals than on others
    j, high = 0, r - 1  # t_ref[j] <= t < t_ref[high]
    while high - j > 1:
        middle = (j + high) // 2
        if t_ref[middle] <= t:
            j = middle
        else:
            high = middle
    w = (t - t_ref[j]) / (t_ref[j + 1] - t_ref[j])
    for i in range(out.size):
        out[i] = x_ref[j, i] + w * (x_ref[j + 1, i] - x_ref[j, i])


@njit(cache=True)
def unsafe_distance(px, py, nearest, scene, edge):
    """``min(nearest, distance from (px, py) to the nearest Unsafe set)`` (0 inside one).

    A set whose bounding box is at least ``nearest`` away cannot lower the minimum: skipped.
    ``scene = (V, ring_start, set_rings, boxes (sets, 4) as xmin, ymin, xmax, ymax)``. Into
    ``edge (8,)``, for ``cached_distance``: the nearest edge ``(x1, y1, x2, y2)``, a lower bound
    on the distance to every other edge of every set, the point ``(px, py)`` and its distance;
    ``edge[4] = -1`` when the result is not an edge's distance (inside a set, or ``nearest``
    itself).
    """
    V, ring_start, set_rings, boxes = scene
    cap = nearest
    best = np.inf  # squared, over the sets measured
    others = np.inf  # a lower bound on the distance to every edge but the nearest
    j_best = -1
    i_best = -1
    inside_any = False
    for S in range(set_rings.size - 1):
        dx = max(boxes[S, 0] - px, 0.0, px - boxes[S, 2])
        dy = max(boxes[S, 1] - py, 0.0, py - boxes[S, 3])
        box = math.sqrt(dx * dx + dy * dy)
        if box >= nearest:
            others = min(others, box)  # its edges are at least that far
            continue
        inside, dd, second, _, _, j, i = polygon_scan(
            px, py, V, ring_start, set_rings[S], set_rings[S + 1]
        )
        inside_any = inside_any or inside
        if dd < best:
            others = min(others, math.sqrt(best), math.sqrt(second))
            best, j_best, i_best = dd, j, i
        else:
            others = min(others, math.sqrt(dd))
        nearest = min(nearest, 0.0 if inside else math.sqrt(dd))
    edge[4] = -1.0
    if not inside_any and j_best >= 0 and math.sqrt(best) < cap:
        edge[0], edge[1] = V[j_best, 0], V[j_best, 1]
        edge[2], edge[3] = V[i_best, 0], V[i_best, 1]
        edge[4] = others
        edge[5], edge[6], edge[7] = px, py, nearest
    return nearest


@njit(cache=True, inline="always")
def cached_distance(px, py, edge, rounding):
    """The distance from ``(px, py)`` to Unsafe from the nearest edge that ``unsafe_distance``
    recorded in ``edge`` at the point ``edge[5:7]``, ``edge[7]`` away from Unsafe; -1 when that
    does not decide it (or nothing was recorded: ``edge[4] < 0``). Exact when returned: the move
    ``m`` from that point is shorter than its distance (this point is outside every set, as that
    one was), and every other edge is at least ``edge[4] - m`` away (the distance is
    1-Lipschitz), not nearer than this edge's own distance, the same float as ``polygon_scan``
    gives (``rounding``: the allowance for the rounding of ``m`` and the bound)."""
    if not edge[4] >= 0.0:
        return -1.0
    m = math.sqrt((px - edge[5]) ** 2 + (py - edge[6]) ** 2)
    if m + rounding >= edge[7]:
        return -1.0
    dd, _, _ = segment_distance_squared(px, py, edge[0], edge[1], edge[2], edge[3])
    d = math.sqrt(dd)
    if d + m + rounding > edge[4]:
        return -1.0
    return d


@njit(cache=True)
def metric_norm(x, xr, M, g):
    """``|x - xr|_M[g]`` for ``x, xr (n,)``, ``M (G, n, n)`` metrics on the RK4 grid."""
    q = 0.0
    for i in range(x.size):
        e_i = x[i] - xr[i]
        for j in range(x.size):
            q += e_i * M[g, i, j] * (x[j] - xr[j])
    return math.sqrt(max(q, 0.0))
