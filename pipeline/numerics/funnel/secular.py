"""Cheap brackets of (I5)'s eigenvalues, to skip the matrices that cannot hold the maximum.

``funnel.robust``'s search evaluates, for every row ``r`` and corner ``c``, the largest
eigenvalue of the arrow-like matrix ``S = [[Mhat_r + alpha I, a_rc], [a_rc^T, -alpha]]`` (n+1,
n+1) and keeps each interval's maximum. With ``Mhat_r = U diag(w) U^T`` (once per row: it does not
depend on ``alpha`` or the corner) and ``b = U^T a_rc``, ``S`` is similar to the arrow matrix
with diagonal ``mu_i = w_i + alpha``, ``d = -alpha`` and border ``b``, whose largest eigenvalue
is the largest root of the secular equation (Golub, SIAM Review 15 (1973); Bunch, Nielsen and
Sorensen, Numer. Math. 31 (1978))

    g(x) = x - d - sum_i b_i^2 / (x - mu_i) = 0,   x > max_i mu_i   (every b_i != 0).   (S1)

``g`` is increasing and concave there with ``g' >= 1``, so for any ``x > max mu`` the root is
within ``|g(x)|`` of ``x``:

    |x - lambda_max(S)| <= |g(x)|.                                                     (S2)

An index with ``b_i = 0`` (a block-diagonal ``Mhat`` has exact zeros in ``U``) splits off: ``mu_i``
is an eigenvalue and (S1) holds for the others, so

    lambda_max(S) = max(root of (S1) over the i with b_i != 0, mu_i with b_i = 0).          (S3)

``x`` starts at the largest eigenvalue of the border's matrix compressed to ``(u_j, 0)`` and
``(0, 1)``, ``j`` the largest ``mu`` with ``b_j != 0`` (a lower bound: Cauchy interlacing) and
takes Newton steps, which from the left of the root of a concave increasing function stay left
of it and converge. The bracket (S2) is widened by ``ROUNDING`` times the scale of ``S`` (the
eigen-decomposition's and LAPACK's backward errors are a few ``eps`` of it; ``ROUNDING`` is ~10^6
eps) and of ``g``'s terms. A non-finite value gets the bracket ``(-inf, inf)``: it is always
evaluated. Only ever used to skip matrices whose largest eigenvalue is below another's: the
values kept are numpy's eigenvalues of the same matrices.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.model.dynamics import FloatArray

ROUNDING = 2.0**-32  # relative to S's scale: the brackets' allowance for rounding
NEWTON_STEPS = 80  # at most: each halves the bracket at least (bisection), or Newton


@njit(cache=True, error_model="numpy")  # x / 0 is inf or nan (then the bracket is infinite)
def _brackets(
    w: FloatArray, U: FloatArray, norm: FloatArray, a: FloatArray, alpha: FloatArray,
    rounding: float, steps: int,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    R, C, n = a.shape
    lo = np.empty((R, C))
    hi = np.empty((R, C))
    b2 = np.empty(n)
    for r in range(R):
        al = alpha[r]
        d = -al
        for c in range(C):
            size = 0.0  # |a_rc|^2
            split = -np.inf  # the largest mu_i with b_i = 0: an eigenvalue (S3)
            pole = -np.inf  # the largest mu_i with b_i != 0, and its b_i^2
            weight, border = 0.0, 0.0  # that b_i^2, and the sum of all b_i^2
            for i in range(n):
                s = 0.0
                for j in range(n):
                    s += U[r, j, i] * a[r, c, j]
                b2[i] = s * s
                size += a[r, c, i] * a[r, c, i]
                border += b2[i]
                mu = w[r, i] + al
                if b2[i] == 0.0:
                    split = max(split, mu)
                elif mu >= pole:
                    pole, weight = mu, b2[i]
            terms = abs(d) + (abs(split) if split > -np.inf else 0.0)
            if pole == -np.inf:  # no border: the eigenvalues are the mu_i and d
                low = high = max(split, d)
            else:  # the root of (S1) between the compressions to (u_j, 0), (0, 1) and to
                # mu_j I on the whole first block (both with d in the corner)
                low = 0.5 * (pole + d) + math.sqrt((0.5 * (pole - d)) ** 2 + weight)
                high = 0.5 * (pole + d) + math.sqrt((0.5 * (pole - d)) ** 2 + border)
                x, last = low, np.inf
                for _ in range(steps):  # safeguarded Newton on (S1)
                    g, slope, size_g = x - d, 1.0, abs(x) + abs(d)
                    for i in range(n):
                        if b2[i] != 0.0:
                            t = b2[i] / (x - (w[r, i] + al))
                            g -= t
                            slope += t / (x - (w[r, i] + al))
                            size_g += abs(t)
                    if math.isfinite(size_g):  # the scale of g's rounding where it is used
                        terms = max(terms, size_g)
                    if g < 0.0:  # x is left of the root, x - g right of it (S2)
                        low, high = max(low, x), min(high, x - g)
                    else:
                        low, high = max(low, x - g), min(high, x)
                    if not high - low > rounding * (norm[r] + abs(al)):
                        break  # narrower than the rounding allowance added below
                    x = x - g / slope
                    if not (low < x < high) or high - low > 0.5 * last:
                        x = 0.5 * (low + high)  # Newton left the bracket or is slow: bisect
                    last = high - low
            scale = norm[r] + math.sqrt(n) * abs(al) + math.sqrt(2.0 * size) + terms + 1.0
            low, high = max(low, split), max(high, split)  # (S3)
            if not (math.isfinite(low) and math.isfinite(high) and low <= high):
                lo[r, c], hi[r, c] = -np.inf, np.inf
            else:
                lo[r, c], hi[r, c] = low - rounding * scale, high + rounding * scale
    return lo, hi


def brackets(
    w: FloatArray, U: FloatArray, norm: FloatArray, a: FloatArray, alpha: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``(lo (R, C), hi (R, C))`` around the largest eigenvalue of ``S`` for each row and corner:
    ``w (R, n)``, ``U (R, n, n)`` the eigen-decomposition of each ``Mhat_r`` (``np.linalg.eigh``),
    ``norm (R,)`` its Frobenius norm, ``a (R, C, n)`` the scaled corners, ``alpha (R,)`` each
    row's multiplier; ``(-inf, inf)`` where (S1) does not apply."""
    return _brackets(
        np.ascontiguousarray(w), np.ascontiguousarray(U), np.ascontiguousarray(norm),
        np.ascontiguousarray(a), np.ascontiguousarray(alpha), ROUNDING, NEWTON_STEPS,
    )  # fmt: skip
