"""Init split among the starts: the cell of Init that each funnel must hold (issue 16).

Init is a box ``[lower, upper] (n,)`` whose free states (``upper > lower``, ``D`` of them) span a
box of dimension ``D``. Cut it into ``g^D`` equal cells (``g`` per free side) and give each cell
to the start nearest its centre in the metric ``M (n, n)``:

    owner(c) = argmin_i (z_c - x0_i)^T M (z_c - x0_i),  z_c the centre of cell c.           (C1)

Start ``i`` must then hold ``H_i``, the convex hull of the corners of its cells. The cells tile
Init, so ``Init = U_c c  is inside  U_i H_i``; an ellipsoid centred at ``x0_i`` holds ``H_i`` iff
it holds every corner (it is convex), which the funnel program states as one linear matrix
inequality per corner ``v`` (``pipeline.numerics.funnel.synthesis``: ``Q[0] >= tau (v - x0_i)(v -
x0_i)^T`` with ``tau`` the fraction held, ``sqrt(tau)`` the level). Only the corners of ``H_i``
itself are kept (``scipy.spatial.ConvexHull``), and each is pushed ``PAD`` (relative) away from
``x0_i``, so that a funnel at its level ``1 - LEVEL_SLACK`` still holds the unpadded corner.

This is only a request: the coverage stage certifies Init against the funnels' initial
ellipsoids at their levels by its own sound subdivision. With ``g`` a power of two the cells are
boxes of that subdivision, each inside one funnel when every level reaches 1.

The finest ``g`` (``DIVISIONS``, halved while ``g^D > MAX_CELLS``): (C1) on the cells is the
nearest-start (Voronoi) split of Init up to one cell, and ``H_i`` reaches at most one cell beyond
start ``i``'s Voronoi region. Coarse cells that do not line up with the starts hand whole cells
to a middle start: with three starts per side and ``g = 4`` the middle one owns two of the four
cells, a side 1.5x its Voronoi region's (half of Init's side against a third), and its funnel,
wider by as much, keeps more of the input bounds from its nominal.

Why (measured on quadrotor_hill_gusty_flythrough, Init with velocity and pitch spread): the constant
certificate's ball slice that the funnels were asked to hold before reached +-0.30 rad in pitch
and +-0.95 m/s in horizontal speed from every start, 4-6x what Init spans; a cell stays inside
Init.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from pipeline.model.dynamics import FloatArray

PAD = 1e-3  # relative push of each corner away from its start: > LEVEL_SLACK / (1 - LEVEL_SLACK)
DIVISIONS = 64  # g, cells per free side, halved while g^D exceeds MAX_CELLS
MAX_CELLS = 4096
MAX_CORNERS = 64  # hull vertices per start; beyond, the bounding box's 2^D corners


def init_cells(
    lower: FloatArray,
    upper: FloatArray,
    starts: FloatArray,
    metric: FloatArray,
    divisions: int | None = None,
) -> tuple[FloatArray, ...]:
    """Per start, the offsets ``v - x0_i (p_i, n)`` of the corners of ``H_i`` (module
    docstring, (C1)), padded by ``PAD``; ``(0, n)`` for a start that owns no cell.

    Args:
      lower, upper: (n,) Init; starts: (k, n) ``x0_i``; metric: (n, n) ``M`` of (C1),
      positive semidefinite; divisions: ``g``, cells per free side (default ``DIVISIONS``,
      halved while ``g^D > MAX_CELLS``).
    """
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    starts = np.atleast_2d(np.asarray(starts, dtype=np.float64))
    M = np.asarray(metric, dtype=np.float64)
    n = lower.shape[0]
    if starts.shape[1] != n or M.shape != (n, n):
        raise ValueError(
            f"init_cells: starts {starts.shape} and metric {M.shape} for a box of {n} states; "
            f"expected (k, {n}) and ({n}, {n})"
        )
    free = np.flatnonzero(upper > lower)
    D = len(free)
    if divisions is None:
        divisions = DIVISIONS
        while divisions > 1 and divisions**D > MAX_CELLS:
            divisions //= 2
    if int(divisions) != divisions or divisions < 1:
        raise ValueError(f"init_cells: divisions must be a whole number >= 1, got {divisions!r}")
    g = int(divisions)
    if D == 0:  # Init is one point: the nearest start holds it (none, if that start is it:
        e = lower[None] - starts  # an empty request falls back to the ball slice (I1))
        owner = int(np.argmin(np.einsum("ki,ij,kj->k", e, M, e)))
        return tuple(
            (e[i : i + 1] * (1 + PAD)) if i == owner and np.any(e[i]) else np.zeros((0, n))
            for i in range(len(starts))
        )
    steps = (upper[free] - lower[free]) / g
    index = np.array(list(itertools.product(range(g), repeat=D)))  # (g^D, D) cell indices
    centres = np.repeat(lower[None], len(index), axis=0)
    centres[:, free] = lower[free] + (index + 0.5) * steps
    e = centres[:, None, :] - starts[None]  # (cells, k, n)
    owner = np.argmin(np.einsum("cki,ij,ckj->ck", e, M, e), axis=1)  # eq. (C1)
    corners = np.array(list(itertools.product((0, 1), repeat=D)))  # (2^D, D)
    result = []
    for i, x0 in enumerate(starts):
        mine = index[owner == i]
        if len(mine) == 0:
            result.append(np.zeros((0, n)))
            continue
        grid = np.unique((mine[:, None, :] + corners[None]).reshape(-1, D), axis=0)
        points = _hull_corners(lower[free] + grid * steps)  # of the owned cells' corners
        V = np.repeat(lower[None], len(points), axis=0)
        V[:, free] = points
        result.append((V - x0) * (1 + PAD))
    return tuple(result)


def _hull_corners(points: FloatArray) -> FloatArray:
    """Points ``(r, D)`` whose convex hull holds that of ``points (q, D)``: the hull's vertices
    (all points when they do not span ``D`` dimensions), or the corners of their bounding box
    when Qhull fails or the hull has more than ``max(MAX_CORNERS, 2^D)`` vertices (each corner is
    one matrix inequality of the funnel program; the box holds the hull, so the request only
    grows)."""
    D = points.shape[1]
    if D == 1:
        return np.array([points.min(axis=0), points.max(axis=0)])
    if len(points) <= D + 1:
        return points
    try:
        vertices = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # e.g. points in a flat slab: the box below holds them
        vertices = None
    if vertices is not None and len(vertices) <= max(MAX_CORNERS, 2**D):
        return vertices
    box = np.array(list(itertools.product((0, 1), repeat=D)))  # (2^D, D)
    low, high = points.min(axis=0), points.max(axis=0)
    return low + box * (high - low)
