"""Gradient by the discrete adjoint of the RK4 map: one forward pass, one backward sweep.

One RK4 step of the grid (``h = Ts / s``, ``u`` held)::

    k1 = f(x, u), k2 = f(x + h/2 k1, u), k3 = f(x + h/2 k2, u), k4 = f(x + h k3, u)
    x+ = x + h/6 (k1 + 2 k2 + 2 k3 + k4)

Given ``lam = dJ/dx+`` (a row n-vector), reverse-mode differentiation of that step is::

    kap4 = h/6 lam                   -> lam_y4 = kap4 A4,  dJ/du += kap4 B4
    kap3 = h/3 lam + h   lam_y4      -> lam_y3 = kap3 A3,  dJ/du += kap3 B3
    kap2 = h/3 lam + h/2 lam_y3      -> lam_y2 = kap2 A2,  dJ/du += kap2 B2
    kap1 = h/6 lam + h/2 lam_y2      -> lam_y1 = kap1 A1,  dJ/du += kap1 B1
    dJ/dx = lam + lam_y1 + lam_y2 + lam_y3 + lam_y4 (+ the penalty's own dJ/dx at x)

with ``A_r = f_x``, ``B_r = f_u`` at the stage values ``y_r``. It is the exact derivative of the
cost as implemented (the integrator's, not the ODE's), using only vector-Jacobian products:
no ``n x n`` sensitivities are formed. This module is the NumPy reference; the compiled sweep is
in ``pipeline.numerics.kernels.loops``.
"""

from __future__ import annotations

from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.numerics.optimize.sensitivity import stage_jacobians


def adjoint_gradient(
    dynamics: Dynamics,
    dense_xs: FloatArray,
    us: FloatArray,
    Ts: float,
    substeps: int,
    J_x: FloatArray,
    J_u: FloatArray,
) -> FloatArray:
    """``dJ/du`` (N, m) by the discrete adjoint of RK4.

    Args:
      dense_xs: (N s + 1, n) grid states; us: (N, m) inputs; substeps: ``s``.
      J_x: (N s + 1, n), J_u: (N, m) partial derivatives of J (``penalties.Penalized``).
    """
    h = Ts / substeps
    A, B = stage_jacobians(dynamics, dense_xs, us, substeps, h)
    q = J_u.copy()
    lam = J_x[-1].copy()
    for i in range(dense_xs.shape[0] - 2, -1, -1):
        k = i // substeps
        kap4 = (h / 6.0) * lam
        lam4 = kap4 @ A[i, 3]
        kap3 = (h / 3.0) * lam + h * lam4
        lam3 = kap3 @ A[i, 2]
        kap2 = (h / 3.0) * lam + 0.5 * h * lam3
        lam2 = kap2 @ A[i, 1]
        kap1 = (h / 6.0) * lam + 0.5 * h * lam2
        lam1 = kap1 @ A[i, 0]
        q[k] += kap4 @ B[i, 3] + kap3 @ B[i, 2] + kap2 @ B[i, 1] + kap1 @ B[i, 0]
        lam = lam + lam1 + lam2 + lam3 + lam4 + J_x[i]
    return q
