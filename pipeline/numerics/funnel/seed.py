"""Where a funnel's design starts (``funnel.synthesis``, Design step 1 and (F5)): the time-varying
LQR gains and cost-to-go along the nominal (F4), and a guess of the extent a declared disturbance
needs (F5). Both only size the hull boxes and seed the gains: the program and ``check_funnel``
decide what is certified.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm, solve_discrete_are

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.robust import invariant_ellipsoid

ROBUST_SEED = 2.0  # the hull boxes hold this multiple of the seed's disturbance extent (F5)


def lqr_seed(
    scenario: Scenario, trajectory: Trajectory, stationary_end: bool = False
) -> tuple[FloatArray, FloatArray]:
    """Time-varying LQR along the nominal: ``K (N, m, n)`` (sign of ``u = u_ref + K e``) and the
    cost-to-go ``P (N+1, n, n)``, terminal ``P[N] = Ts diag(state_weights)``; with
    ``stationary_end`` the stationary cost-to-go at the end (the discrete Riccati equation of the
    last sample's linearisation: a nominal ending at rest hands over to the terminal LQR law, and
    its gains do not fade towards T as they do with the small terminal cost, which under a
    disturbance left the end too wide for the terminal ellipsoid)."""
    dynamics, Ts = scenario.dynamics, scenario.Ts
    xs, us = trajectory.xs, trajectory.us
    n, m, N = scenario.n, scenario.m, us.shape[0]
    M = np.zeros((N, n + m, n + m))
    M[:, :n, :n] = dynamics.f_x(xs[:-1], us)
    M[:, :n, n:] = dynamics.f_u(xs[:-1], us)
    E = expm(M * Ts)  # zero-order hold: [Ad Bd; 0 I] = expm([A B; 0 0] Ts)
    Ad, Bd = E[:, :n, :n], E[:, :n, n:]
    Qw = Ts * np.diag(scenario.feedback.state_weights)
    Rw = Ts * np.diag(scenario.feedback.input_weights)
    P = np.empty((N + 1, n, n))
    K = np.empty((N, m, n))
    P[N] = Qw
    if stationary_end:
        try:
            P[N] = solve_discrete_are(Ad[-1], Bd[-1], Qw, Rw)
        except (ValueError, np.linalg.LinAlgError):
            pass  # not stabilisable at the end: the plain terminal cost
    for k in range(N - 1, -1, -1):  # eq. (F4): discrete Riccati recursion
        A, B, S = Ad[k], Bd[k], P[k + 1]
        K[k] = -np.linalg.solve(Rw + B.T @ S @ B, B.T @ S @ A)
        Pk = Qw + A.T @ S @ (A + B @ K[k])
        P[k] = (Pk + Pk.T) / 2
    return K, P


def disturbance_seed(
    scenario: Scenario, trajectory: Trajectory, K: FloatArray, bound: FloatArray
) -> FloatArray | None:
    """A guess ``(N+1, n, n)`` of the funnel that holds the disturbance ``|w| <= bound (n,)``
    (F5): per sample ``k`` the invariant ellipsoid of the frozen closed loop ``Acl = f_x + f_u
    K[k]`` at the nominal (``funnel.robust.invariant_ellipsoid``, least position extent), times
    ``ROBUST_SEED^2``. Only the hull boxes are sized by it, so nothing here needs to be sound:
    the LMIs and ``check_funnel`` decide. None where a frozen loop is not stable. ``K (N, m,
    n)``."""
    n, N = scenario.n, len(K)
    A = scenario.dynamics.f_x(trajectory.xs[:-1], trajectory.us)
    B = scenario.dynamics.f_u(trajectory.xs[:-1], trajectory.us)
    position = np.zeros((n, n))
    position[scenario.position_index, scenario.position_index] = 1.0
    Q = np.empty((N + 1, n, n))
    for k in range(N):
        guess = invariant_ellipsoid(A[k] + B[k] @ K[k], bound, position)
        if guess is None:
            return None
        Q[k] = guess
    Q[N] = Q[N - 1]
    return ROBUST_SEED**2 * Q
