"""Tube ends inside the terminal ellipsoid: the exact level (a check) and an LMI (the synthesis).

The terminal ellipsoid (``pipeline.numerics.terminal.design``) is ``E_T = {x : (x - x_eq)^T P_T (x -
x_eq) <= c}``. A tube ends in ``{x : ||x - a||_P <= rho}``, ``a = x_ref(T)``, ``d = a - x_eq``.

Exact level. The smallest ``c`` whose ``E_T`` holds the end is ``max_{||y||_P <= rho} (y +
d)^T P_T (y + d)``. By the S-procedure (lossless for one constraint) containment holds iff some
``tau >= 0`` makes

    [[tau P - P_T, -P_T d], [-d^T P_T, c - d^T P_T d - tau rho^2]] >= 0,

i.e. (Schur complement, ``tau > sigma_max``) ``c >= phi(tau) = d^T P_T d + tau rho^2 + sum_k
w_k^2 / (tau - sigma_k)`` with ``sigma_k`` the generalized eigenvalues of ``(P_T, P)`` and ``w =
U^T P^-1/2 P_T d`` in their eigenbasis. ``phi`` is convex; its minimum is the level and any
``tau`` gives a sound upper bound (``containing_level``).

The LMI (T2), for the funnel program whose unknown is ``Q = P^-1`` at level 1 (``rho = 1``). The
end ``{d + Q^1/2 v : |v| <= 1}`` lies in ``E_T`` iff some ``lambda > 0`` makes (Boyd et al.,
*LMIs in System and Control Theory*, 3.7.1: ellipsoid in ellipsoid, with ``E_T`` as ``{z : z^T
(P_T / c) z <= 1}``)

    [[c P_T^-1, d, Q^1/2], [d^T, 1 - lambda, 0], [Q^1/2, 0, lambda I]] >= 0,

and by the Schur complement on the ``lambda I`` block (``Q^1/2 Q^1/2 = Q``)

    [[c P_T^-1 - Q / lambda, d], [d^T, 1 - lambda]] >= 0,                                  (T2)

LINEAR in ``Q`` for a fixed ``lambda``: ``bound - C Q C^T >= 0`` with ``C = [I; 0] / sqrt(lambda)``
(n+1, n) and the constant ``bound = [[c P_T^-1, d], [d^T, 1 - lambda]]``, a cap of
``pipeline.numerics.funnel.lmi``. The multiplier is fixed at ``lambda = 1 - delta``, ``delta =
||d||_P_T / sqrt(c)`` (the end's centre's share of the radius; ``delta < 1`` is necessary): then
every ``Q <= (1 - delta)^2 c P_T^-1`` (the triangle inequality's end, ``||y + d||_P_T <= ||y||_P_T
+ ||d||_P_T``) satisfies (T2), since ``c P_T^-1 - Q / lambda >= delta c P_T^-1`` and ``d^T (delta c
P_T^-1)^-1 d = delta <= 1 - lambda``; so (T2) is never more restrictive than that bound, and less
where the end is thin along ``d``. ``delta`` is kept at least ``MIN_SHARE`` so that the cone has an
interior when ``d = 0``. (T2) shapes the funnel; what certifies the end is the exact level.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from pipeline.model.dynamics import FloatArray

MIN_SHARE = 1e-2  # the least delta in (T2)'s multiplier lambda = 1 - delta
RADIUS_BISECTIONS = 60


@dataclass(frozen=True, kw_only=True)
class TerminalTarget:
    """The ellipsoid a tube must end in: ``{x : (x - x_eq)^T P (x - x_eq) <= level}``.

    Attributes:
      x_eq: (n,) its centre (an equilibrium); P: (n, n) ``P_T``; level: ``c`` (> 0).
    """

    x_eq: FloatArray
    P: FloatArray
    level: float

    def share(self, end: FloatArray) -> float:
        """``delta = ||end - x_eq||_P / sqrt(level)`` for ``end (n,)``: < 1 when inside."""
        d = np.asarray(end, dtype=np.float64) - self.x_eq
        return float(np.sqrt(d @ self.P @ d / self.level))

    def end_cap(self, end: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(T2) as a cap ``bound - C Q C^T >= 0`` for a tube ending at ``end (n,)``: ``(C (n+1,
        n), bound (n+1, n+1))``. ``ValueError`` when ``end`` is not inside the ellipsoid."""
        delta = self.share(end)
        if not delta < 1:
            raise ValueError(
                f"the tube's end is outside the terminal ellipsoid ({delta:.3g} of its radius)"
            )
        lam = 1.0 - max(delta, MIN_SHARE)
        n = len(self.x_eq)
        C = np.vstack([np.eye(n), np.zeros((1, n))]) / np.sqrt(lam)
        bound = np.zeros((n + 1, n + 1))
        bound[:n, :n] = self.level * np.linalg.inv(self.P)
        bound[:n, n] = bound[n, :n] = np.asarray(end, dtype=np.float64) - self.x_eq
        bound[n, n] = 1.0 - lam
        return C, (bound + bound.T) / 2

    def core_box(self, fraction: float) -> FloatArray:
        """(n,) half-widths ``h`` of a box ``x_eq +- h`` inside the ellipsoid at ``fraction``
        (in (0, 1]) of its level: ``h`` along the ellipsoid's extents ``sqrt(diag(P^-1) level)``,
        scaled so that its worst corner lies on it. Sound: the quadratic form is convex, so its
        maximum over the box is at one of the ``2^n`` corners, all checked."""
        if not 0 < fraction <= 1:
            raise ValueError(f"core_box: fraction {fraction!r}; expected a number in (0, 1]")
        extent = np.sqrt(np.diag(np.linalg.inv(self.P)) * self.level)
        corners = np.array(list(itertools.product((-1.0, 1.0), repeat=len(extent)))) * extent
        worst = float(np.einsum("ki,ij,kj->k", corners, self.P, corners).max())
        return extent * np.sqrt(fraction * self.level / worst)

    def end_radius(self, end: FloatArray, P: FloatArray) -> float:
        """The largest ``rho`` with ``{x : ||x - end||_P <= rho}`` inside (``containing_level``
        at most ``level``), by bisection; 0 when ``end (n,)`` is not inside. ``P (n, n)``."""
        d = np.asarray(end, dtype=np.float64) - self.x_eq
        if not self.share(end) < 1:
            return 0.0
        # with d = 0 the level is rho^2 sigma_max: that radius is an upper end
        L_inv = np.linalg.inv(np.linalg.cholesky(P))
        hi = float(np.sqrt(self.level / np.linalg.eigvalsh(L_inv @ self.P @ L_inv.T)[-1]))
        lo = 0.0
        for _ in range(RADIUS_BISECTIONS):
            mid = 0.5 * (lo + hi)
            if containing_level(self.P, d, P, mid) <= self.level:
                lo = mid
            else:
                hi = mid
        return lo


def containing_level(Q: FloatArray, centre: FloatArray, P: FloatArray, rho: float) -> float:
    """The smallest ``c`` with ``{x : ||x - a||_P <= rho} in {e : e^T Q e <= c}`` for ``d =
    centre = a - x_eq (n,)``: ``min_tau phi(tau)`` of the module docstring (an upper bound at any
    ``tau``, exact at the minimum)."""
    d = np.asarray(centre, dtype=np.float64)
    values, vectors = np.linalg.eigh(P)
    P_inv_half = vectors @ np.diag(values**-0.5) @ vectors.T
    sigma, U = np.linalg.eigh(P_inv_half @ Q @ P_inv_half)
    w = U.T @ (P_inv_half @ (Q @ d))
    base = float(d @ Q @ d)
    if rho <= 0:
        return base
    top = float(sigma[-1])

    def phi(tau: float) -> float:
        return base + tau * rho**2 + float(np.sum(w**2 / (tau - sigma)))

    def slope(tau: float) -> float:
        return rho**2 - float(np.sum(w**2 / (tau - sigma) ** 2))

    near = top + 1e-12 * max(1.0, abs(top))
    if slope(near) >= 0:  # the hard case: the infimum is at the pole
        return phi(near)
    far = top + 1.0
    while slope(far) < 0:
        far = top + 2 * (far - top)
    return phi(brentq(slope, near, far, xtol=1e-14 * far, rtol=1e-14))


def end_levels(
    terminal_P: FloatArray,
    x_eq: FloatArray,
    P: FloatArray,
    ends: Sequence[FloatArray],
    radii: Sequence[float],
) -> FloatArray:
    """(k,) the smallest level holding each end tube ``||x - ends[i]||_P <= radii[i]``; ``P``
    is ``(n, n)``, or ``(k, n, n)``: one metric per end tube (a funnel's ``P_i[N]``)."""
    P = np.asarray(P, dtype=np.float64)
    metrics = np.broadcast_to(P, (len(ends), *P.shape[-2:]))
    return np.array(
        [
            containing_level(terminal_P, a - x_eq, P_i, rho)
            for a, P_i, rho in zip(ends, metrics, radii, strict=True)
        ]
    )
