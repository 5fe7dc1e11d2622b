"""Sound coverage of a box by ellipsoidal balls ``{x : (x - x0_i)^T P_i (x - x0_i) <= r_i^2}``, by
subdivision; each ball has its own metric ``P_i`` (a funnel's ``P_i(0)``), the constant
certificate's balls are the same code with one ``P`` repeated.

The box's degenerate intervals (e.g. "at rest") are fixed and drop out, leaving a box of
dimension ``D`` over the free states. A box is covered when all ``2^D`` of its vertices lie in
one ball (balls are convex, so the whole box does); a box is certainly not covered by ball ``i``
when even its nearest point is outside, ``lambda_min(P_i) dist(x0_i, box)^2 > r_i^2``; a box that
no ball can cover yet is split into ``2^D`` halves, up to ``max_depth`` halvings per side (and
at most ``MAX_BOXES`` open vertices). What remains is uncovered: the test is sound, not
complete (an uncovered box at the depth limit may still be covered by several balls together).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray

DEFAULT_DEPTH = 8
MAX_BOXES = 200_000


@dataclass(frozen=True, kw_only=True)
class Subdivision:
    """The outcome of ``subdivide``.

    Attributes:
      boxes: (B, 2, n) covered boxes ``[lower, upper]``; assignment: (B,) the ball covering each.
      uncovered: (U, 2, n) boxes not certified covered.
      covered_volume, total_volume: over the free states (1 each if the box is a covered point).
      free: indices of the box's non-degenerate states; depth: halvings per side reached.
    """

    boxes: FloatArray = field(repr=False)
    assignment: np.ndarray = field(repr=False)
    uncovered: FloatArray = field(repr=False)
    covered_volume: float
    total_volume: float
    free: tuple[int, ...]
    depth: int

    @property
    def covered(self) -> bool:
        return len(self.uncovered) == 0

    @property
    def fraction(self) -> float:
        """Covered volume / total volume (a lower bound on the true fraction)."""
        if self.total_volume > 0:
            return self.covered_volume / self.total_volume
        return float(self.covered)


def _farthest_vertex(vertices: FloatArray, centers: FloatArray, P: FloatArray) -> FloatArray:
    """``max_v ||v - x0_i||^2_P_i`` (B, k) over each box's ``vertices (B, V, n)``, for the balls'
    ``centers (k, n)`` and metrics ``P (k, n, n)``: one matrix product per ball."""
    B, V, n = vertices.shape
    flat = vertices.reshape(B * V, n)
    worst = np.empty((B, len(centers)))
    for i, (center, metric) in enumerate(zip(centers, P, strict=True)):
        e = flat - center
        worst[:, i] = np.sum((e @ metric) * e, axis=1).reshape(B, V).max(axis=1)
    return worst


def subdivide(
    P: FloatArray,
    lower0: FloatArray,
    upper0: FloatArray,
    centers: FloatArray,
    radii: FloatArray,
    max_depth: int = DEFAULT_DEPTH,
    margin: float = 0.0,
) -> Subdivision:
    """Certify that the box ``[lower0, upper0]`` (n,) lies in the union of the balls with
    ``centers (k, n)``, ``radii (k,)`` (radii <= 0 are ignored) and metrics ``P (k, n, n)``, one
    per ball (``P (n, n)``: the same metric for every ball); a box is covered when its vertices
    are within ``(1 - margin)`` of a ball's squared radius."""
    lower0 = np.asarray(lower0, dtype=np.float64)
    upper0 = np.asarray(upper0, dtype=np.float64)
    n = lower0.shape[0]
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, n)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    k = centers.shape[0]
    if radii.shape[0] != k:
        raise ValueError(f"coverage: {k} centers but {radii.shape[0]} radii")
    P = np.asarray(P, dtype=np.float64)
    if P.shape == (n, n):
        P = np.broadcast_to(P, (k, n, n))
    if P.shape != (k, n, n):
        raise ValueError(
            f"coverage: metrics of shape {P.shape} for {k} balls in {n} states; expected "
            f"({k}, {n}, {n}) or ({n}, {n})"
        )
    if not np.all(np.isfinite(P)):
        raise ValueError("coverage: non-finite metric")
    if not (np.all(np.isfinite(centers)) and np.all(np.isfinite(radii))):
        raise ValueError("coverage: non-finite center or radius")
    free = tuple(int(i) for i in np.flatnonzero(upper0 > lower0))
    D = len(free)
    corners = np.array(list(itertools.product((0.0, 1.0), repeat=D)), float).reshape(2**D, D)
    lambda_min = np.linalg.eigvalsh(P)[:, 0] if k else np.zeros(0)  # (k,)
    r2 = np.where(radii > 0, radii, 0.0) ** 2
    usable = r2 > 0  # a radius whose square underflows covers nothing

    lower = lower0[None, :].copy()  # (B, n) the boxes still open
    upper = upper0[None, :].copy()
    covered_boxes, assignment, uncovered = [], [], []
    covered_volume, depth = 0.0, 0
    free_index = list(free)
    total_volume = float(np.prod(upper0[free_index] - lower0[free_index])) if D else 1.0
    while len(lower):
        # Vertices (B, 2^D, n): the box's lower corner plus 0/1 of its free widths.
        vertices = np.repeat(lower[:, None, :], len(corners), axis=1)
        vertices[:, :, free_index] += corners[None] * (upper - lower)[:, None, free_index]
        worst = _farthest_vertex(vertices, centers, P)  # (B, k)
        fits = (worst <= (1.0 - margin) * r2[None]) & usable[None]
        room = np.where(fits, 1.0 - worst / np.where(usable, r2, 1.0)[None], -np.inf)
        done = fits.any(axis=1)
        widths = (upper - lower)[:, free_index]
        volumes = np.prod(widths, axis=1) if D else np.ones(len(lower))
        covered_boxes.append(np.stack([lower[done], upper[done]], axis=1))
        assignment.append(np.argmax(room[done], axis=1))
        covered_volume += float(volumes[done].sum())
        # Boxes that some ball may still cover (nearest point of the box inside the ball).
        nearest = np.clip(centers[None], lower[:, None], upper[:, None])  # (B, k, n)
        gap = np.sum((nearest - centers[None]) ** 2, axis=-1)  # (B, k)
        hopeful = ~done & np.any(usable[None] & (lambda_min[None] * gap <= r2[None]), axis=1)
        hopeless = ~done & ~hopeful
        uncovered.append(np.stack([lower[hopeless], upper[hopeless]], axis=1))
        lower, upper = lower[hopeful], upper[hopeful]
        if not len(lower):
            break
        if D == 0 or depth >= max_depth or len(lower) * len(corners) > MAX_BOXES:
            uncovered.append(np.stack([lower, upper], axis=1))
            break
        # Split every open box into 2^D halves.
        middle = (lower + upper) / 2
        children_lower = np.repeat(lower[:, None, :], len(corners), axis=1)
        children_upper = np.repeat(upper[:, None, :], len(corners), axis=1)
        children_lower[:, :, free_index] = np.where(
            corners[None] > 0, middle[:, None, free_index], lower[:, None, free_index]
        )
        children_upper[:, :, free_index] = np.where(
            corners[None] > 0, upper[:, None, free_index], middle[:, None, free_index]
        )
        lower, upper = children_lower.reshape(-1, n), children_upper.reshape(-1, n)
        depth += 1

    gaps = np.concatenate(uncovered).reshape(-1, 2, n) if uncovered else np.zeros((0, 2, n))
    return Subdivision(
        boxes=np.concatenate(covered_boxes).reshape(-1, 2, n),
        assignment=np.concatenate(assignment).astype(np.int64),
        uncovered=gaps,
        covered_volume=covered_volume,
        total_volume=total_volume,
        free=free,
        depth=depth,
    )


def balls_to_cover(
    P: FloatArray, radius: float, lower: FloatArray, upper: FloatArray, fraction: float
) -> int:
    """About how many balls ``{x : ||x - c||_P <= radius}`` (``P (n, n)``) a part ``fraction``
    of the box ``[lower, upper]`` (n,) needs: its volume over the free states divided by that of
    the largest box inside one ball's slice along them, ``prod_i 2 a_i / sqrt(D)`` (``a_i`` the
    slice's ``D`` semi-axes; the box along the ellipsoid's axes), at least 1. An estimate for
    advice (how many more demos), not a bound; 0 for nothing to cover."""
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    free = np.flatnonzero(upper > lower)
    if fraction <= 0:
        return 0
    if free.size == 0:
        return 1
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius!r}")
    D = free.size
    axes = radius / np.sqrt(np.linalg.eigvalsh(np.asarray(P)[np.ix_(free, free)]))
    box = np.minimum(2 * axes / np.sqrt(D), (upper - lower)[free].max())  # (D,)
    volume = fraction * float(np.prod((upper - lower)[free]))
    return max(1, int(np.ceil(volume / float(np.prod(box)) - 1e-9)))  # 2.0000000001 is 2
