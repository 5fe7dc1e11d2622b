"""A funnel's invariance under a bounded disturbance, by the S-procedure (I5).

Problem. ``x' = f(x, u) + w`` with any measurable ``|w_i| <= d_i`` (a box, ``d (n,)``). On
interval ``k`` the funnel's error obeys ``e' = Acl e + w`` with ``Acl = A + B K[k]``, ``[A B]`` in
the hull ``conv{[A_v B_v]}`` (``funnel.law`` (I2)), and with ``Q(t) = P(t)^-1`` linear on the
interval, ``V = e^T P e`` and the (F2) operator ``L = -Q' + Acl Q + Q Acl^T + 2 lambda Q``:

    d/dt (V e^{2 lambda t}) e^{-2 lambda t} = e^T P L P e + 2 e^T P w.

The funnel is invariant when this is negative on its boundary ``V = rho_t^2``. (I4) bounds the two
terms apart (``L <= m Q`` and Cauchy-Schwarz): their maxima are at different boundary points, and
on a slow quadrotor loop that costs a factor of 2-4 in the disturbance a funnel holds. Here they
are bounded together. With ``Q = Lc Lc^T``, ``e = rho Lc z`` (``|z| = 1`` on the boundary),
``Mhat = Lc^-1 L Lc^-T`` and ``a = Lc^-1 w / rho``, the rate is ``rho^2 (z^T Mhat z + 2 z^T a)``.
For any multiplier ``alpha >= 0`` and ``|z| = 1`` (the S-procedure: Boyd et al., LMIs in System and
Control Theory, section 2.6.3; lossless for one quadratic constraint),

    z^T Mhat z + 2 z^T a = [z; 1]^T S(alpha) [z; 1],
    S(alpha) = [[Mhat + alpha I, a], [a^T, -alpha]],

so ``lambda_max(S(alpha)) <= -mu`` gives a rate at most ``-2 mu rho^2`` (``|[z; 1]|^2 = 2``). Over
the interval: ``S`` scaled back, ``N(t) = [[L + alpha Q, w], [w^T, -alpha rho^2]]``, is affine in
``t`` (``Q`` linear, ``K`` and the vertex held) and in ``[A B]`` and ``w`` for a fixed ``alpha``,
and ``N + mu diag(Q, rho^2) <= 0`` is that eigenvalue bound; so with one ``alpha`` per interval it
holds on the whole interval, for every hull point and every ``w`` in the box once it holds at both
ends, every vertex and every corner (``w`` and ``-w`` give congruent ``S``: one of each pair).
``rho`` is taken at the interval's end, where ``rho_t`` is smallest: with ``alpha >= mu`` the
corner entry ``-(alpha - mu) rho^2`` is then no more negative than the true one, and on ``V =
rho_t^2 >= rho^2`` the rate is still at most ``-2 mu rho_t^2``. The shipped law's offset (I2) adds
``2 rho_t w_k``, so the funnel holds under it when

    2 r_k + lmi_term_k < 0,  r_k = min_alpha max_{v, ends, corners} lambda_max(S(alpha)),   (I5)

``lmi_term_k = 2 w_k / rho`` as in (I2) (and ``LMI_MARGIN`` below zero on top). ``r_k`` is convex
in ``alpha`` (a maximum of largest eigenvalues of matrices affine in it); ``robust_margins``
minimises it by golden-section search, but soundness does not depend on finding the minimum: the
eigenvalues are evaluated, with numpy, at the ``alpha`` returned. The search's own evaluations
skip each matrix whose eigenvalue a cheap bracket places below another's (``funnel.secular``):
the maximum, numpy's eigenvalue of the same matrix, is the same bit for bit, so is the search.
Without a disturbance ``S`` is block diagonal and ``r_k = m_k / 2`` at ``alpha = -m_k / 2``: (I5)
is (F2)'s own check.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.linalg import solve_continuous_lyapunov

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.funnel.law import LMI_MARGIN, corners
from pipeline.numerics.funnel.sampled import pushed_rows
from pipeline.numerics.funnel.secular import brackets

GOLDEN_STEPS = 40  # golden-section steps on alpha: the bracket shrinks by 0.618^40 ~ 4e-9
MULTIPLE_STEPS = 14  # bisection steps on the reported disturbance multiple (2^-14 of its bracket)


def invariant_ellipsoid(
    Acl: FloatArray, bound: FloatArray, weight: FloatArray
) -> FloatArray | None:
    """A guess ``(n, n)`` of the smallest invariant ellipsoid of ``e' = Acl e + w``, ``|w| <=
    bound (n,)`` (``Acl (n, n)``): for ``w w^T <= E E^T``, ``E = sqrt(r) diag(bound)`` over the
    ``r`` disturbed states (an ellipsoid holding the box) and a decay ``a`` in ``(0, 2 sigma)``,
    ``sigma`` the loop's slowest decay, the solution of ``(Acl + a/2 I) Q + Q (Acl + a/2 I)^T +
    E E^T / a = 0`` (Boyd et al., LMIs in System and Control Theory, section 6.1.3), the ``a``
    with the least ``tr(weight Q)`` kept. None when ``Acl`` is not stable. A guess, to size
    boxes: nothing that uses it relies on it for soundness."""
    n = len(Acl)
    acting = np.flatnonzero(bound > 0)
    E = np.zeros((n, len(acting)))
    E[acting, np.arange(len(acting))] = np.sqrt(len(acting)) * bound[acting]
    sigma = -float(np.linalg.eigvals(Acl).real.max())
    if not sigma > 0:
        return None
    # Bartels-Stewart (scipy), one equation per decay: the Kronecker system solved by LU gave
    # seeds that left 1.9% of Init uncovered on quadrotor_hill at twice its bound
    candidates = [
        solve_continuous_lyapunov(Acl + a / 2 * np.eye(n), -E @ E.T / a)
        for a in np.geomspace(0.02, 1.98, 25) * sigma
    ]
    best = min(candidates, key=lambda Q: float(np.trace(weight @ Q)))
    return ((best + best.T) / 2).astype(np.float64)


def _blocks(
    Q: FloatArray,
    K: FloatArray,
    vertices: tuple[FloatArray, ...],
    rate: float,
    Ts: float,
    period: float = 0.0,
) -> tuple[FloatArray, FloatArray, np.ndarray, np.ndarray, np.ndarray]:
    """``Mhat`` (R, n, n) for every (interval, end, vertex), the inverse factors ``Lc^-1`` (N, 2,
    n, n) at each interval's ends, the interval of each row (R,), its end (R,: 0 or 1) and
    whether it is a probe row (R,: below). ``period > 0``: a held law's pairs too
    (``funnel.sampled`` (I6')), ``V (V + 1)`` rows per end: the plain ones (``tau = 0``) and one
    per vertex pair at ``tau = h``; the probes are the plain rows and the pairs ``v = v'``."""
    n, N = Q.shape[1], len(K)
    L_inv = np.linalg.inv(np.linalg.cholesky(Q))  # (N+1, n, n)
    rows, owner, end, probe = [], [], [], []
    for k in range(N):
        D = (Q[k + 1] - Q[k]) / Ts  # eq. (F1)
        A, B = vertices[k][:, :, :n], vertices[k][:, :, n:]
        Acl = A + B @ K[k]  # (V, n, n)
        for side, e in enumerate((k, k + 1)):
            M = -D + Acl @ Q[e] + Q[e] @ np.swapaxes(Acl, 1, 2) + 2 * rate * Q[e]  # eq. (F2)
            V = len(M)
            probe.append(np.ones(V, dtype=bool))
            if period > 0:  # funnel.sampled (I6'): every (v, v') at tau = h
                pushed = M[:, None] + pushed_rows(A, B, K[k], Q[e], period)  # (V, V, n, n)
                M = np.concatenate([M, pushed.reshape(-1, n, n)])
                probe.append(np.eye(V, dtype=bool).reshape(-1))
            M = L_inv[e] @ M @ L_inv[e].T
            rows.append((M + np.swapaxes(M, 1, 2)) / 2)
            owner.append(np.full(len(M), k))
            end.append(np.full(len(M), side))
    ends = np.stack([L_inv[:-1], L_inv[1:]], axis=1)
    return (
        np.concatenate(rows), ends, np.concatenate(owner), np.concatenate(end),
        np.concatenate(probe),
    )  # fmt: skip


class RobustCheck:
    """(I5) for one funnel: ``Q (N+1, n, n)``, held gains ``K (N, m, n)``, hull ``vertices`` (N
    arrays (V, n, n+m)), ``rate``, sample time ``Ts`` and level ``rho``; ``margins(bound)`` per
    interval for any disturbance box, ``multiple`` the largest scale of one that still holds."""

    def __init__(
        self,
        Q: FloatArray,
        K: FloatArray,
        vertices: tuple[FloatArray, ...],
        rate: float,
        Ts: float,
        rho: float,
        period: float = 0.0,
    ) -> None:
        # the end of each row (0, 1), for its factor Lc^-1; rho at the interval's end
        self.M, self.L_inv, self.owner, self.end, self.probe = _blocks(
            Q, K, vertices, rate, Ts, period
        )
        self.paired = period > 0
        self._eigen: tuple[FloatArray, FloatArray, FloatArray] | None = None  # of M, once
        N, n = len(K), Q.shape[1]
        self.N, self.n = N, n
        self.rho_end = rho * np.exp(-rate * Ts * np.arange(1, N + 1))  # (N,)

    def _largest(
        self, alpha: FloatArray, a: FloatArray, rows: np.ndarray | None = None
    ) -> FloatArray:
        """(N,) the largest eigenvalue of ``S(alpha_k)`` over each interval's rows and corners;
        ``alpha (N,)``, ``a (R, C, n)`` the scaled corners of each row; ``rows``: only these
        rows' (indices; -inf for an interval with none)."""
        M, owner = (self.M, self.owner) if rows is None else (self.M[rows], self.owner[rows])
        a = a if rows is None else a[rows]
        R, C, n = a.shape
        S = np.zeros((R, C, n + 1, n + 1))
        al = alpha[owner][:, None]  # (R, 1)
        S[:, :, :n, :n] = M[:, None] + al[..., None, None] * np.eye(n)
        S[:, :, :n, n] = S[:, :, n, :n] = a
        S[:, :, n, n] = -al
        top = np.linalg.eigvalsh(S)[..., -1].max(axis=1)  # (R,)
        out = np.full(self.N, -np.inf)
        np.maximum.at(out, owner, top)
        return out

    def _evaluator(
        self, a: FloatArray, rows: np.ndarray | None
    ) -> Callable[[FloatArray], FloatArray]:
        """``_largest(., a, rows)`` as a function of ``alpha (N,)``, the same values: each
        (row, corner) whose eigenvalue is bracketed below another's (``funnel.secular`` (S2))
        is skipped, and numpy's eigenvalues of the others' matrices (the same matrices,
        element by element) give the maximum."""
        if self._eigen is None:
            w, U = np.linalg.eigh(self.M)
            self._eigen = (w, U, np.sqrt((self.M * self.M).sum(axis=(1, 2))))
        w, U, norm = self._eigen
        M, owner = (self.M, self.owner) if rows is None else (self.M[rows], self.owner[rows])
        if rows is not None:
            a, w, U, norm = a[rows], w[rows], U[rows], norm[rows]
        n = a.shape[2]

        def largest(alpha: FloatArray) -> FloatArray:
            al = alpha[owner]  # (R,)
            lo, hi = brackets(w, U, norm, a, al)  # (R, C)
            best = np.full(self.N, -np.inf)
            np.maximum.at(best, owner, lo.max(axis=1, initial=-np.inf))
            r, c = np.nonzero(hi >= best[owner][:, None])  # the others are below best's
            S = np.zeros((len(r), n + 1, n + 1))
            S[:, :n, :n] = M[r] + al[r][:, None, None] * np.eye(n)
            S[:, :n, n] = S[:, n, :n] = a[r, c]
            S[:, n, n] = -al[r]
            out = np.full(self.N, -np.inf)
            np.maximum.at(out, owner[r], np.linalg.eigvalsh(S)[:, -1])
            return out

        return largest

    def _scaled(self, bound: FloatArray) -> FloatArray:
        """(R, C, n) ``a = Lc^-1 w_c / rho_end`` for the corners ``w_c`` of ``|w| <= bound``:
        one box ``(n,)`` for every interval, or one per interval ``(N, n)`` (a held law's,
        ``funnel.law`` (I6))."""
        bound = np.asarray(bound, dtype=np.float64)
        factor = self.L_inv[self.owner, self.end]  # (R, n, n)
        if bound.ndim == 2:  # the corners' signs over every state any interval's box acts on
            acting = np.asarray((bound > 0).any(axis=0), dtype=np.float64)
            signs = corners(acting)  # (C, n) of +-1 and 0
            if not len(signs):
                signs = np.zeros((1, self.n))
            w = signs[None] * bound[self.owner][:, None, :]  # (R, C, n)
            return np.einsum("rij,rcj->rci", factor, w) / self.rho_end[self.owner][:, None, None]
        w = corners(bound)
        if not len(w):
            w = np.zeros((1, self.n))
        return np.einsum("rij,cj->rci", factor, w) / self.rho_end[self.owner][:, None, None]

    def margins(
        self,
        bound: FloatArray,
        intervals: np.ndarray | None = None,
        needed: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """``(r (N,), alpha (N,))``: (I5)'s ``r_k`` at the multiplier found for each interval,
        for the box ``bound`` (``(n,)``, or ``(N, n)`` one per interval); ``intervals (N,)``:
        search only where True (-inf elsewhere; each interval's search is its own, so the ones
        searched are as in a full search). With a held law's pairs (I6') the search runs on the
        probe rows (the plain ones and ``v = v'``) and every row is evaluated at the multiplier
        found; where some row is above the probes' largest there, the multiplier may not be the
        best for all rows and the search runs again on every row of that interval (the smaller
        ``r_k`` kept); ``needed (N,)``: only where ``r_k`` is not below it (an interval that
        holds keeps the first multiplier). Any multiplier is a certificate: the eigenvalues
        returned are all rows'."""
        a = self._scaled(bound)
        chosen = np.ones(len(self.M), dtype=bool) if intervals is None else intervals[self.owner]
        if not self.paired:
            rows = None if intervals is None else np.flatnonzero(chosen)
            alpha, _ = self._search(a, rows)
            return self._largest(alpha, a, rows), alpha
        alpha, probed = self._search(a, np.flatnonzero(chosen & self.probe))
        value = self._largest(alpha, a, np.flatnonzero(chosen))
        again = value > probed + 1e-9  # a pair off the diagonal binds: search on every row
        if needed is not None:
            again &= value >= needed
        if again.any():
            rows = np.flatnonzero(again[self.owner])
            other, _ = self._search(a, rows)
            other_value = self._largest(other, a, rows)
            better = again & (other_value < value)
            value, alpha = np.where(better, other_value, value), np.where(better, other, alpha)
        return value, alpha

    def _search(self, a: FloatArray, rows: np.ndarray | None) -> tuple[FloatArray, FloatArray]:
        """``(alpha (N,), r (N,))``: golden section on each interval's convex ``r_k(alpha)`` over
        ``rows`` (indices; None: all), and ``r_k`` over them at the ``alpha`` returned."""
        ratio = (np.sqrt(5.0) - 1) / 2
        # past this the eigenvalue of S grows with alpha (Mhat + alpha I dominates)
        top = 4 * (np.abs(self.M).max(initial=0.0) + np.abs(a).max(initial=0.0)) + 1.0
        low, high = np.zeros(self.N), np.full(self.N, top)
        c, d = high - ratio * (high - low), low + ratio * (high - low)
        largest = self._evaluator(a, rows)
        fc, fd = largest(c), largest(d)
        for _ in range(GOLDEN_STEPS):  # golden section on each interval's convex r_k(alpha)
            left = fc <= fd  # the minimum lies in [low, d]: drop (d, high]; else drop [low, c)
            high, low = np.where(left, d, high), np.where(left, low, c)
            probe = np.where(left, high - ratio * (high - low), low + ratio * (high - low))
            value = largest(probe)
            c, d, fc, fd = (
                np.where(left, probe, d), np.where(left, c, probe),
                np.where(left, value, fd), np.where(left, fc, value),
            )  # fmt: skip
        return np.where(fc <= fd, c, d), np.minimum(fc, fd)

    def holds_at(
        self,
        s: float,
        bound: FloatArray,
        lmi_term: FloatArray,
        hold: Callable[[float], FloatArray] | None = None,
    ) -> bool:
        """Whether ``2 r_k(s bound) + lmi_term_k < -LMI_MARGIN`` on every interval (with a held
        law's box ``hold(s)`` added, as ``multiple``): ``multiple`` is below ``s`` when not."""
        margins, _ = self.margins(_grown(s, np.asarray(bound, dtype=np.float64), hold))
        return bool(np.all(2 * margins + lmi_term < -LMI_MARGIN))

    def multiple(
        self,
        bound: FloatArray,
        lmi_term: FloatArray,
        hold: Callable[[float], FloatArray] | None = None,
        enough: float = math.inf,
    ) -> float:
        """The largest ``s`` with ``2 r_k(s bound) + lmi_term_k < -LMI_MARGIN`` on every interval,
        by bisection (``r_k`` is convex in ``s``: the set where it holds is an interval from 0),
        shrunk so that the bound itself is not on the edge; ``inf`` without a disturbance, or
        once ``2^19`` times it holds (not checked further). ``hold(s)``: a held law's box ``(N,
        n)`` (``funnel.law`` (I6)) under ``s`` times the disturbance, added to it (it grows with
        ``s``: the set is still an interval from 0). ``enough``: a caller that needs no more
        (certify, the smallest over its funnels): where it holds, it is returned unsearched."""
        bound = np.asarray(bound, dtype=np.float64)
        if not np.any(bound > 0):
            return float("inf")
        if math.isfinite(enough) and self.holds_at(enough, bound, lmi_term, hold):
            return enough

        last: FloatArray | None = None  # the multipliers of the last box that held

        def holds(s: float) -> bool:
            nonlocal last
            box = _grown(s, bound, hold)
            failing = np.ones(self.N, dtype=bool)
            if last is not None:  # any alpha >= 0 is a certificate (I5): the last ones first,
                # searching again only on the intervals they do not certify
                failing = 2 * self._largest(last, self._scaled(box)) + lmi_term >= -LMI_MARGIN
                if not failing.any():
                    return True
            margins, alpha = self.margins(box, failing)
            if np.all(2 * margins[failing] + lmi_term[failing] < -LMI_MARGIN):
                last = alpha if last is None else np.where(failing, alpha, last)
                return True
            return False

        if not holds(0.0):
            return 0.0
        low, high = 0.0, 1.0
        while holds(high):
            low, high = high, 2 * high
            if high > 1e6:
                return float("inf")
        for _ in range(MULTIPLE_STEPS):
            middle = (low + high) / 2
            low, high = (middle, high) if holds(middle) else (low, middle)
        return low * (1 - 1e-9)


def _grown(s: float, bound: FloatArray, hold: Callable[[float], FloatArray] | None) -> FloatArray:
    """``s`` times the disturbance box ``bound (n,)``, plus a held law's box ``hold(s) (N, n)``
    under it (``RobustCheck.multiple``)."""
    return s * bound if hold is None else s * bound + hold(s)
