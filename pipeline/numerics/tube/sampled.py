"""Zero-order-hold feedback: the tube's rate when ``u`` is recomputed only every ``h`` seconds.

The held law is ``u(t) = u_ref(t) + K e_k`` on ``[t_k, t_k + h)``, ``t_k = k h``, ``e_k = e(t_k)``,
``e = x - x_ref`` (``h`` divides ``Ts``, so ``u_ref`` switches at sample times). Write it as the
continuous law plus a disturbance:

    e' = f(x, u_ref + K e) - f(x_ref, u_ref) + w,   w = f(x, u_ref + K e_k) - f(x, u_ref + K e)

The contraction certificate (C) (``pipeline.numerics.tube.contraction``) of the hull's vertices at
rate ``lambda`` gives ``d/dt ||e||_P <= -lambda ||e||_P + ||w||_P`` while the tube stays in the
operating region.

Bound on ``w`` in one window, ``s = t - t_k in [0, h]``, ``rho_k = ||e_k||_P``. By the mean value
theorem on segments inside the region, with ``[A B]``, ``[A' B']``, ``B''`` points of the hull
``conv{[A_v B_v]}`` (A_cl = A + B K):

    e' = A e + B K e_k = A_cl e_k + A (e - e_k),     w = B'' K (e_k - e)

so ``delta(s) = ||e - e_k||_P`` obeys ``delta' <= beta rho_k + alpha delta``, hence ``delta(s) <=
beta rho_k (e^{alpha s} - 1) / alpha``, and

    ||w(s)||_P <= rho_k [C1 s + C3 (e^{alpha s} - 1 - alpha s) / alpha^2]
    alpha = max_v ||A_v||_P,  beta = max_v ||A_cl,v||_P,
    C1 = max_{v,u} ||B_v K A_cl,u||_P,  C3 = beta max_{v,u} ||B_v K A_u||_P

(``||M||_P = ||P^1/2 M P^-1/2||_2``; a product of points of two hulls is a convex combination
of the vertex products, so its norm is at most their largest). Integrating the comparison
inequality (``e^{-lambda (s - tau)} <= 1`` on the disturbance):

    ||e(t_k + s)||_P <= rho_k q(s),
    q(s) = e^{-lambda s} + C1 s^2 / 2 + C3 (e^{alpha s} - 1 - alpha s - alpha^2 s^2 / 2) / alpha^3

Since ``-ln q >= 1 - q`` and ``e^{-lambda s} <= 1 - lambda s + (lambda s)^2 / 2``,

    -ln q(s) / s >= lambda - (lambda^2 + C1) s / 2 - C3 tail(s) / s,
    tail(s) = (e^{alpha s} - 1 - alpha s - alpha^2 s^2 / 2) / alpha^3,

which decreases in ``s``; so with ``lambda_h = lambda - (lambda^2 + C1) h / 2 - C3 tail(h) / h``,
``||e(t_k + s)||_P <= e^{-lambda_h s} rho_k`` in every window, and by induction over windows
``||e(t)||_P <= e^{-lambda_h t} ||e(0)||_P`` for all ``t``: the held law has the tube of
the continuous one at the lower rate ``lambda_h`` (certified when ``lambda_h > 0``). The radius
stage, the optimizer and the certify stage then use ``lambda_h``; the cost of holding is the
lower rate, ``lambda - lambda_h ~ C1 h / 2`` for small ``h``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.model.dynamics import FloatArray


@dataclass(frozen=True, kw_only=True)
class HeldRate:
    """The held law's tube rate and the constants of its bound (module docstring).

    Attributes:
      period: ``h`` (s); rate: the continuous certificate's ``lambda``; held_rate: ``lambda_h``
      (> 0 for a certificate); alpha, beta, C1, C3: the bound's constants.
    """

    period: float
    rate: float
    held_rate: float
    alpha: float
    beta: float
    C1: float
    C3: float

    @property
    def success(self) -> bool:
        return self.held_rate > 0


def held_rate(
    P: FloatArray, K: FloatArray, A: FloatArray, B: FloatArray, rate: float, period: float
) -> HeldRate:
    """``lambda_h`` for the held law with period ``h = period`` (module docstring).

    Args:
      P: (n, n) metric; K: (m, n) gain; A: (V, n, n), B: (V, n, m) hull vertices; rate: the
        continuous certificate's ``lambda`` at those vertices (1/s).
    """
    if not period > 0:
        raise ValueError(f"held_rate: the feedback period must be > 0 s, found {period!r}")
    values, vectors = np.linalg.eigh(P)
    root = vectors @ np.diag(np.sqrt(values)) @ vectors.T  # P^1/2
    inverse_root = vectors @ np.diag(values**-0.5) @ vectors.T  # P^-1/2

    def norm(M: FloatArray) -> float:
        """Largest ``||M_i||_P`` over a stack ``M (k, n, n)``."""
        return float(np.linalg.norm(root @ M @ inverse_root, ord=2, axis=(-2, -1)).max())

    A_cl = A + B @ K  # (V, n, n)
    BK = B @ K  # (V, n, n)
    alpha, beta = norm(A), norm(A_cl)
    C1 = norm((BK[:, None] @ A_cl[None]).reshape(-1, *P.shape))
    C3 = beta * norm((BK[:, None] @ A[None]).reshape(-1, *P.shape))
    h, a = float(period), max(alpha, 1e-12)
    # tail(h) / h, by its series where the closed form cancels
    if a * h > 1e-3:
        tail = (np.expm1(a * h) - a * h - (a * h) ** 2 / 2) / a**3 / h
    else:
        tail = h**2 / 6 * (1 + a * h / 4 + (a * h) ** 2 / 20 + (a * h) ** 3 / 100)
    lam = float(rate - (rate**2 + C1) * h / 2 - C3 * tail)
    return HeldRate(
        period=float(period), rate=float(rate), held_rate=lam, alpha=alpha, beta=beta, C1=C1, C3=C3
    )
