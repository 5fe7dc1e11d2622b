"""The contraction inequality (C), evaluated in this one place for the designer and the certifier.

At every vertex ``[A_v B_v]`` of a sound Jacobian hull (``pipeline.numerics.hull``), with
``A_cl = A_v + B_v K``::

    M_v = A_cl^T P + P A_cl + 2 lambda P < 0                                              (C)

gives ``d/dt ||e||_P <= -lambda ||e||_P`` while the error stays in the hull's region (``P`` is
symmetric positive definite). ``contraction_margin`` is the largest eigenvalue of ``M_v`` over the
vertices, negative when (C) holds: the certifier reads it as it is (``stages.certify``), the
designer (``stages.feedback``) in the metric's own scale, ``L^-1 M_v L^-T`` with ``P = L L^T``
(the same sign by Sylvester's law of inertia; ``lambda`` enters it as ``+ 2 lambda``).
``contraction_rate`` is the largest ``lambda`` that (C) allows.
"""

from __future__ import annotations

import numpy as np

from pipeline.model.dynamics import FloatArray


def contraction_margin(
    P: FloatArray,
    K: FloatArray,
    A: FloatArray,
    B: FloatArray,
    rate: float,
    *,
    normalised: bool = False,
) -> float:
    """Largest eigenvalue of (C)'s left side ``M_v`` over the vertices ``A (V, n, n)``, ``B (V, n,
    m)`` for ``P (n, n)``, ``K (m, n)``; with ``normalised``, of ``L^-1 M_v L^-T`` (raises
    ``numpy.linalg.LinAlgError`` when ``P`` is not positive definite). The symmetric part is
    taken last, so that rounding cannot make ``M_v`` look symmetric when it is not."""
    A_cl = A + B @ K  # (V, n, n)
    M = np.swapaxes(A_cl, 1, 2) @ P + P @ A_cl + 2.0 * rate * P
    if normalised:
        L_inv = np.linalg.inv(np.linalg.cholesky(P))
        M = L_inv @ M @ L_inv.T
    return float(np.linalg.eigvalsh((M + np.swapaxes(M, 1, 2)) / 2).max())


def contraction_rate(P: FloatArray, K: FloatArray, A: FloatArray, B: FloatArray) -> float:
    """The largest ``lambda`` of (C) at every vertex: ``min_v -lambda_max(L^-1 (A_cl^T P + P
    A_cl) L^-T) / 2`` for ``A (V, n, n)``, ``B (V, n, m)``, ``A_cl = A + B K``."""
    return -contraction_margin(P, K, A, B, 0.0, normalised=True) / 2
