"""The paper's gradient (§IV-A): forward sensitivities Phi, Gamma and the O(N) sum of eq. (29).

Over each sample interval ``[k Ts, (k+1) Ts)`` the state is integrated together with

    dPhi/dt   = f_x Phi,          Phi(k Ts) = I                       eqs. (33), (35)
    dGamma/dt = f_x Gamma + f_u,  Gamma(k Ts) = 0                     eqs. (34), (35)

by the same RK4 steps as the state, with the Jacobians at the RK4 stage values: that is exactly
the chain rule through the RK4 map, so ``Phi_k = dx_{k+1}/dx_k`` and ``Gamma_k = dx_{k+1}/du[k]``
of the integrator the cost uses. Only the structurally nonzero entries are integrated: ``Phi``'s
pattern is the reflexive-transitive closure of ``f_x``'s sparsity graph (state ``j`` reaches state
``i``), ``Gamma``'s the states that each input reaches (the paper's Remark 3).

With ``rho_{j+1}[j] = Gamma_j`` (36) and ``rho_k[j] = Phi_{k-1} rho_{k-1}[j]`` (37; the printed
``Phi((k+1)Ts, kTs)`` is an index slip), the sum (29) is evaluated backwards in O(N):

    mu_N = dJ/dx_N,   q[k] = dJ/du[k] + mu_{k+1} Gamma_k,   mu_k = dJ/dx_k + mu_{k+1} Phi_k

where ``dJ/dx_k`` also carries the penalties at the intermediate RK4 grid points of interval
``k``, through the partial-interval ``Phi`` and ``Gamma``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.model.dynamics import BoolArray, Dynamics, FloatArray


@dataclass(frozen=True, kw_only=True)
class SensitivityPattern:
    """Structurally nonzero entries of ``Phi`` (n, n) and ``Gamma`` (n, m) (Remark 3)."""

    phi: BoolArray
    gamma: BoolArray

    @property
    def equations(self) -> int:
        """ODEs integrated per interval: ``n`` states + nonzeros of ``Phi`` and ``Gamma``."""
        return int(self.phi.shape[0] + self.phi.sum() + self.gamma.sum())

    @property
    def dense_equations(self) -> int:
        """Without pruning: ``n + n n + n m``."""
        n, m = self.gamma.shape
        return n + n * n + n * m


def sensitivity_pattern(dynamics: Dynamics) -> SensitivityPattern:
    """Reachability on the sparsity graph of ``f_x`` (edge ``j -> i`` if ``df_i/dx_j != 0``)."""
    S_x = dynamics.sparsity_x.astype(np.int64)
    reach = np.eye(dynamics.n, dtype=np.int64)
    while True:  # closure: Phi's pattern is sum_k S_x^k
        grown = ((reach + S_x @ reach) > 0).astype(np.int64)
        if np.array_equal(grown, reach):
            break
        reach = grown
    gamma = (reach @ dynamics.sparsity_u.astype(np.int64)) > 0
    return SensitivityPattern(phi=reach > 0, gamma=gamma)


def stage_jacobians(
    dynamics: Dynamics, dense_xs: FloatArray, us: FloatArray, substeps: int, h: float
) -> tuple[FloatArray, FloatArray]:
    """``f_x``, ``f_u`` at the four RK4 stage values of every step of the grid.

    Args:
      dense_xs: (N s + 1, n) grid states; us: (N, m); h: step ``Ts / s``.
    Returns:
      A: (N s, 4, n, n), B: (N s, 4, n, m).
    """
    x = dense_xs[:-1]
    u = np.repeat(us, substeps, axis=0)
    k1 = dynamics.f(x, u)
    y2 = x + 0.5 * h * k1
    k2 = dynamics.f(y2, u)
    y3 = x + 0.5 * h * k2
    k3 = dynamics.f(y3, u)
    y4 = x + h * k3
    y = np.stack([x, y2, y3, y4], axis=1)
    u4 = np.broadcast_to(u[:, None, :], (*y.shape[:2], u.shape[-1]))
    return dynamics.f_x(y, u4), dynamics.f_u(y, u4)


def _rk4_variational(
    A: FloatArray, B: FloatArray, Phi: FloatArray, Gamma: FloatArray, h: float
) -> tuple[FloatArray, FloatArray]:
    """One RK4 step of (33)-(34) with stage Jacobians ``A (4, n, n)``, ``B (4, n, m)``."""
    K1, L1 = A[0] @ Phi, A[0] @ Gamma + B[0]
    K2, L2 = A[1] @ (Phi + 0.5 * h * K1), A[1] @ (Gamma + 0.5 * h * L1) + B[1]
    K3, L3 = A[2] @ (Phi + 0.5 * h * K2), A[2] @ (Gamma + 0.5 * h * L2) + B[2]
    K4, L4 = A[3] @ (Phi + h * K3), A[3] @ (Gamma + h * L3) + B[3]
    return (
        Phi + (h / 6.0) * (K1 + 2.0 * K2 + 2.0 * K3 + K4),
        Gamma + (h / 6.0) * (L1 + 2.0 * L2 + 2.0 * L3 + L4),
    )


@dataclass(frozen=True, kw_only=True)
class IntervalSensitivities:
    """Per-interval sensitivities (dense; the NumPy reference).

    Attributes:
      Phi: (N, n, n) ``dx_{k+1}/dx_k``; Gamma: (N, n, m) ``dx_{k+1}/du[k]``.
      a: (N, n) ``sum_i J_x[i] Phi_(k,i)`` over the intermediate grid points ``i`` of interval k;
      c: (N, m) the same with ``Gamma_(k,i)``.
    """

    Phi: FloatArray
    Gamma: FloatArray
    a: FloatArray
    c: FloatArray


def interval_sensitivities(
    dynamics: Dynamics,
    dense_xs: FloatArray,
    us: FloatArray,
    Ts: float,
    substeps: int,
    J_x: FloatArray,
) -> IntervalSensitivities:
    """Integrate (33)-(35) over every interval by RK4 (dense, unpruned: the reference).

    Args:
      dense_xs: (N s + 1, n) grid states; us: (N, m); J_x: (N s + 1, n) penalty derivatives.
    """
    N, m = us.shape
    n = dense_xs.shape[-1]
    h = Ts / substeps
    A, B = stage_jacobians(dynamics, dense_xs, us, substeps, h)
    Phi_k, Gamma_k = np.empty((N, n, n)), np.empty((N, n, m))
    a, c = np.zeros((N, n)), np.zeros((N, m))
    for k in range(N):
        Phi, Gamma = np.eye(n), np.zeros((n, m))  # eq. (35)
        for j in range(substeps):
            i = k * substeps + j
            Phi, Gamma = _rk4_variational(A[i], B[i], Phi, Gamma, h)  # eqs. (33)-(34)
            if j < substeps - 1:
                a[k] += J_x[i + 1] @ Phi
                c[k] += J_x[i + 1] @ Gamma
        Phi_k[k], Gamma_k[k] = Phi, Gamma
    return IntervalSensitivities(Phi=Phi_k, Gamma=Gamma_k, a=a, c=c)


def backward_sum(
    sensitivities: IntervalSensitivities, J_x: FloatArray, J_u: FloatArray, substeps: int
) -> FloatArray:
    """Eq. (29) by the backward recursion over ``k``: O(N). Returns q (N, m).

    Args:
      J_x: (N s + 1, n) and J_u: (N, m) partial derivatives of J (``Penalized``).
    """
    N = J_u.shape[0]
    q = np.empty_like(J_u)
    mu = J_x[N * substeps].copy()  # dG/dx + dg/dx at the final sample
    for k in range(N - 1, -1, -1):
        q[k] = J_u[k] + sensitivities.c[k] + mu @ sensitivities.Gamma[k]  # eqs. (29), (36)
        mu = J_x[k * substeps] + sensitivities.a[k] + mu @ sensitivities.Phi[k]  # eq. (37)
    return q


def sensitivity_gradient(
    dynamics: Dynamics,
    dense_xs: FloatArray,
    us: FloatArray,
    Ts: float,
    substeps: int,
    J_x: FloatArray,
    J_u: FloatArray,
) -> FloatArray:
    """``dJ/du`` (N, m) by the paper's method (NumPy reference; see the module docstring)."""
    sensitivities = interval_sensitivities(dynamics, dense_xs, us, Ts, substeps, J_x)
    return backward_sum(sensitivities, J_x, J_u, substeps)
