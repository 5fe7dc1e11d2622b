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

Where the hull of ``H_i``'s corners has more vertices than the program takes (``MAX_CORNERS``;
fine cells in five dimensions give it hundreds), start ``i`` is asked for the polytope cut from
its cells' bounding box by the bisectors of (C1) (normals ``a_ij``), each moved out just far
enough to keep every owned cell:

    G_i = {z in box_i : a_ij^T z <= max_{v in H_i} a_ij^T v, j != i},  a_ij = M (x0_j - x0_i),  (C2)

``box_i`` the bounding box of ``H_i``.

``G_i`` is convex and holds every owned cell, so it holds ``H_i``; as the cells shrink it tends
to start ``i``'s Voronoi region, whose reach in ``M`` is the covering radius. Only when ``G_i``
too has more vertices than ``MAX_CORNERS`` is the bounding box asked for.

This is only a request: the coverage stage certifies Init against the funnels' initial
ellipsoids at their levels by its own sound subdivision. With ``g`` a power of two the cells are
boxes of that subdivision, each inside one funnel when every level reaches 1; ``g^D <=
MAX_CELLS`` keeps that depth within the subdivision's budget
(``pipeline.numerics.verify.cover.MAX_BOXES``: at most ``(g/2)^D`` boxes split into ``2^D``).

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

import functools
import itertools

import numpy as np
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from pipeline.model.dynamics import FloatArray

PAD = 1e-3  # relative push of each corner away from its start: > LEVEL_SLACK / (1 - LEVEL_SLACK)
DIVISIONS = 64  # g, cells per free side, halved while g^D exceeds MAX_CELLS
MAX_CELLS = 32_768  # g = 8 in five free states, 32 in three, 64 in two
MAX_CORNERS = 96  # corners per start: the hull's, else (C2)'s, else the bounding box's 2^D


def init_cells(
    lower: FloatArray,
    upper: FloatArray,
    starts: FloatArray,
    metric: FloatArray,
    divisions: int | None = None,
) -> tuple[FloatArray, ...]:
    """Per start, the offsets ``v - x0_i (p_i, n)`` of the corners of ``H_i`` (module
    docstring, (C1)), or of ``G_i`` (C2) where ``H_i`` has more than ``MAX_CORNERS``, padded by
    ``PAD``; ``(0, n)`` for a start that owns no cell.

    Args:
      lower, upper: (n,) Init; starts: (k, n) ``x0_i``; metric: (n, n) ``M`` of (C1),
      positive semidefinite; divisions: ``g``, cells per free side (default ``DIVISIONS``,
      halved while ``g^D > MAX_CELLS``).

    The offsets are read-only; the last few answers are kept (the funnel stages of one run ask
    the same question each round).
    """
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    starts = np.atleast_2d(np.asarray(starts, dtype=np.float64))
    M = np.asarray(metric, dtype=np.float64)
    key = tuple((a.shape, a.tobytes()) for a in (lower, upper, starts, M))
    return _kept_cells(key, divisions)


@functools.lru_cache(maxsize=8)
def _kept_cells(
    key: tuple[tuple[tuple[int, ...], bytes], ...], divisions: int | None
) -> tuple[FloatArray, ...]:
    """``init_cells`` of the arrays ``key`` holds (shape and bytes of each), frozen."""
    lower, upper, starts, M = (np.frombuffer(b).reshape(shape) for shape, b in key)
    cells = _init_cells(lower, upper, starts, M, divisions)
    for offsets in cells:
        offsets.flags.writeable = False
    return cells


def _init_cells(
    lower: FloatArray,
    upper: FloatArray,
    starts: FloatArray,
    M: FloatArray,
    divisions: int | None,
) -> tuple[FloatArray, ...]:
    """``init_cells`` computed (arguments as its own, as float64 arrays)."""
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
    base = (g + 1) ** np.arange(D)  # a grid point's digits in base g + 1: one integer each
    weighted = (starts @ M)[:, free]  # (k, D): the normals of (C2) are differences of rows
    result = []
    for i, x0 in enumerate(starts):
        mine = index[owner == i]
        if len(mine) == 0:
            result.append(np.zeros((0, n)))
            continue
        codes, shared = np.unique(
            ((mine[:, None, :] + corners[None]) @ base).reshape(-1), return_counts=True
        )
        codes = codes[shared < len(corners)]  # a corner of 2^D owned cells is inside their union
        grid = codes[:, None] // base % (g + 1)  # (q, D) grid indices
        bisectors = weighted - weighted[i]  # (k, D) a_ij of (C2), row i zero
        points = _hull_corners(lower[free] + grid * steps, bisectors)  # of the owned corners
        V = np.repeat(lower[None], len(points), axis=0)
        V[:, free] = points
        result.append((V - x0) * (1 + PAD))
    return tuple(result)


def _hull_corners(points: FloatArray, normals: FloatArray | None = None) -> FloatArray:
    """Points ``(r, D)`` whose convex hull holds that of ``points (q, D)``, at most
    ``max(MAX_CORNERS, 2^D)`` of them (each is one matrix inequality of the funnel program): the
    hull's vertices (all points when they do not span ``D`` dimensions); failing that, the
    vertices of the polytope (C2) cut from the points' bounding box by ``normals (m, D)`` (zero
    rows ignored); failing that, the bounding box's ``2^D`` corners. Each fallback holds the
    hull, so the request only grows."""
    D = points.shape[1]
    if D == 1:
        return np.array([points.min(axis=0), points.max(axis=0)])
    if len(points) <= D + 1:
        return points
    most = max(MAX_CORNERS, 2**D)
    try:
        vertices = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):  # e.g. points in a flat slab: the box below holds them
        vertices = None
    if vertices is not None and len(vertices) <= most:
        return vertices
    low, high = points.min(axis=0), points.max(axis=0)
    if vertices is not None and normals is not None:
        polytope = _polytope_vertices(points, normals, low, high)
        if polytope is not None and len(polytope) <= most:
            return polytope
    box = np.array(list(itertools.product((0, 1), repeat=D)))  # (2^D, D)
    return low + box * (high - low)


def _polytope_vertices(
    points: FloatArray, normals: FloatArray, low: FloatArray, high: FloatArray
) -> FloatArray | None:
    """The vertices ``(r, D)`` of (C2): the box ``[low, high] (D,)`` cut by ``a^T z <= max_p a^T
    p`` for each row ``a`` of ``normals (m, D)`` (rows of norm below 1e-12 of the largest
    dropped), over ``points (q, D)``, which span ``D`` dimensions; None when Qhull fails.

    The mean of the points is strictly inside every cut (a cut it touched would hold every point
    on its plane, but they span ``D`` dimensions) and strictly inside the box for the same
    reason, so it is the interior point ``HalfspaceIntersection`` needs."""
    D = points.shape[1]
    norms = np.linalg.norm(normals, axis=1)
    normals = normals[norms > 1e-12 * norms.max(initial=0.0)] if np.any(norms > 0) else normals[:0]
    eye = np.eye(D)
    A = np.vstack([normals, eye, -eye])  # (m + 2D, D): rows of A z <= b
    b = np.concatenate([(points @ normals.T).max(axis=0), high, -low])
    try:
        cut = HalfspaceIntersection(np.c_[A, -b], points.mean(axis=0))
        corners = np.unique(cut.intersections, axis=0)
        return corners[ConvexHull(corners).vertices]
    except (QhullError, ValueError):
        return None
