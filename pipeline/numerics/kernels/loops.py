"""Numba loops of the cost and its gradients: a template, compiled per scenario.

Not imported directly: ``pipeline.numerics.kernels.compiled`` appends to this source the scenario's
``f_eval``, ``f_jac_eval`` and ``vjp_eval`` (generated from its sympy expressions, replacing the
stubs below) and imports the result with ``numba.njit(cache=True)``. The maths is that of the NumPy
references: ``pipeline.numerics.optimize.penalties`` (eqs. (40)-(42)),
``pipeline.numerics.optimize.adjoint`` (discrete adjoint of RK4) and
``pipeline.numerics.optimize.sensitivity`` (eqs. (29), (33)-(37), pruned). Shapes: ``n`` states,
``m`` inputs, ``N`` samples, ``s`` substeps, ``h = Ts / s``; ``X (N s + 1, n)`` the RK4 grid. ``P``
is a ``pipeline.numerics.kernels.compiled.PenaltyData`` tuple. The penalties and other functions
that do not depend on the dynamics live in ``pipeline.numerics.kernels.shared`` (compiled once per
machine, not once per scenario).
"""

import numpy as np
from numba import njit

from pipeline.numerics.kernels.shared import (
    all_finite,
    copy_vector,
    final_penalty,
    input_penalty,
    state_penalty,
    variational_slope,
)


def f_eval(x, u, out):  # generated: out (n,) = f(x, u)
    raise NotImplementedError


def f_jac_eval(x, u, out, A, B):  # generated: f, A (n*n,) = f_x, B (n*m,) = f_u (nonzeros)
    raise NotImplementedError


def vjp_eval(x, u, lam, out_x, out_u):  # generated: out_x = lam f_x, out_u = lam f_u
    raise NotImplementedError


@njit(cache=True)
def rk4_step(x, u, h, K, Y, out):
    """One RK4 step; stage values into ``Y (4, n)``, slopes into ``K (4, n)``, ``x+`` into out."""
    n = x.size
    step = (0.0, 0.5 * h, 0.5 * h, h)  # stage r at x + step[r] K[r - 1]
    for r in range(4):
        if r == 0:
            copy_vector(x, Y[0])
        else:
            for i in range(n):
                Y[r, i] = x[i] + step[r] * K[r - 1, i]
        f_eval(Y[r], u, K[r])
    for i in range(n):
        out[i] = x[i] + (h / 6.0) * (K[0, i] + 2.0 * K[1, i] + 2.0 * K[2, i] + K[3, i])


@njit(cache=True)
def simulate_kernel(x0, U, h, s, X):
    """The RK4 grid ``X (N s + 1, n)`` (as ``pipeline.model.simulate.simulate``)."""
    n = x0.size
    K = np.empty((4, n))
    Y = np.empty((4, n))
    copy_vector(x0, X[0])
    for i in range(U.shape[0] * s):
        rk4_step(X[i], U[i // s], h, K, Y, X[i + 1])


@njit(cache=True)
def rollout_grid(x0, V, Z, G, feedback, h, s, U, X, Y):
    """The RK4 grid ``X (N s + 1, n)``, its stages ``Y (N s, 4, n)`` and the held inputs
    ``U (N, m)``: with ``feedback`` those of the sampled feedback ``U[k] = V[k] + G (X[k s] -
    Z[k])``, set as the grid reaches each sample; without, ``U = V`` (``U`` may be ``V``).
    Returns False if a state is not finite."""
    n = x0.size
    K = np.empty((4, n))
    copy_vector(x0, X[0])
    for k in range(V.shape[0]):
        for r in range(V.shape[1]):
            U[k, r] = V[k, r]
            if feedback:
                for j in range(n):
                    U[k, r] += G[r, j] * (X[k * s, j] - Z[k, j])
        for j in range(s):
            i = k * s + j
            rk4_step(X[i], U[k], h, K, Y[i], X[i + 1])
            if not all_finite(X[i + 1]):
                return False
    return True


@njit(cache=True)
def grid_penalty(U, s, P, X, J_x, J_u):
    """``J`` of the inputs ``U (N, m)`` and the grid ``X (N s + 1, n)``, with its partials
    ``J_x`` (per grid point) and ``J_u`` (per sample)."""
    N = U.shape[0]
    w = 1.0 / s
    J = 0.0
    for k in range(N):
        J += input_penalty(U[k], J_u[k], P, k)
    for i in range(N * s + 1):
        J += state_penalty(X[i], w, J_x[i], P, i)
    return J + final_penalty(X[N * s], J_x[N * s], P)


@njit(cache=True)
def adjoint_sweep(U, h, s, Y, J_x, q, G):
    """Backward sweep of the discrete RK4 adjoint (see ``pipeline.numerics.optimize.adjoint``); adds
    into q.

    ``G (m, n)``: sampled feedback ``u[k] = v[k] + G (x(k Ts) - z[k])`` (zeros: open loop). Once
    ``q[k] = dJ/du[k]`` is complete, ``dJ/dx(k Ts)`` gains ``G^T q[k]``; ``q`` is then
    ``dJ/dv``."""
    n = J_x.shape[1]
    m = U.shape[1]
    lam = J_x[J_x.shape[0] - 1].copy()
    kap = np.empty(n)
    lam_y = np.empty(n)
    lam_next = np.empty(n)
    gu = np.empty(m)
    a = (h / 6.0, h / 3.0, h / 3.0, h / 6.0)  # RK4 weights h b_r
    b = (0.5 * h, 0.5 * h, h, 0.0)  # stage r + 1's coupling to stage r + 2 (none: r = 3)
    for i in range(J_x.shape[0] - 2, -1, -1):
        k = i // s
        u = U[k]
        for j in range(n):
            lam_next[j] = lam[j] + J_x[i, j]
        for r in range(3, -1, -1):  # stage r + 1, last first: kap = a[r] lam + b[r] lam_y
            if r == 3:
                for j in range(n):  # kap4 = h/6 lam
                    kap[j] = a[r] * lam[j]
            else:
                for j in range(n):  # kap3 = h/3 lam + h lam_y4, kap2 = h/3 lam + h/2 lam_y3, ...
                    lam_next[j] += lam_y[j]
                    kap[j] = a[r] * lam[j] + b[r] * lam_y[j]
            vjp_eval(Y[i, r], u, kap, lam_y, gu)
            for j in range(m):
                q[k, j] += gu[j]
        for j in range(n):
            lam[j] = lam_next[j] + lam_y[j]
        if i % s == 0:  # u[k] = v[k] + G (x_i - z[k]): chain dJ/du[k] into dJ/dx_i
            for j in range(n):
                for r in range(m):
                    lam[j] += G[r, j] * q[k, r]


@njit(cache=True)
def adjoint_kernel(x0, V, Z, G, feedback, h, s, P, U, q, sweep):
    """``J(U)`` and ``q = dJ/dV`` into ``q (N, m)`` by one forward pass and one backward sweep
    (one kernel for both cases: numba compiles it once per scenario, not twice). Without
    ``sweep``, ``J`` alone (``q`` then holds the input penalties' partials): the cost, with no
    kernel of its own to compile.

    With ``feedback``, ``U (N, m)`` receives the inputs of the sampled feedback
    ``U[k] = V[k] + G (x(k Ts) - Z[k])`` (``Z (N, n)``, ``G (m, n)``); without, the open loop:
    ``U = V`` (``U`` may be ``V``), ``G`` must be zeros and ``Z`` is not read."""
    n = x0.size
    Ns = V.shape[0] * s
    X = np.empty((Ns + 1, n))
    Y = np.empty((Ns, 4, n))
    J_x = np.empty((Ns + 1, n))
    if not rollout_grid(x0, V, Z, G, feedback, h, s, U, X, Y):
        q[:] = np.nan
        return np.inf
    J = grid_penalty(U, s, P, X, J_x, q)
    if sweep:
        adjoint_sweep(U, h, s, Y, J_x, q, G)
    return J


@njit(cache=True)
def sensitivity_kernel(x0, U, h, s, P, S, phi_rows, phi_cols, gamma_rows, gamma_cols, q):
    """``J`` and ``q`` by the paper's method: state, pruned Phi and Gamma integrated together
    over each interval (eqs. (33)-(35)), then the backward recursion of eq. (29)."""
    n = x0.size
    N = U.shape[0]
    m = U.shape[1]
    nP = phi_rows.size
    nQ = gamma_rows.size
    w = 1.0 / s
    Phi_k = np.empty((N, nP))
    Gamma_k = np.empty((N, nQ))
    a = np.zeros((N, n))
    c = np.zeros((N, m))
    J_samples = np.empty((N + 1, n))
    A = np.zeros(n * n)
    B = np.zeros(n * m)
    Kx = np.empty((4, n))
    KP = np.empty((4, nP))
    KQ = np.empty((4, nQ))
    y = np.empty(n)
    zP = np.empty(nP)
    zQ = np.empty(nQ)
    Phi = np.empty(nP)
    Gamma = np.empty(nQ)
    gx = np.empty(n)
    J = 0.0
    for k in range(N):
        J += input_penalty(U[k], q[k], P, k)
    x = x0.copy()
    J += state_penalty(x, w, J_samples[0], P, 0)
    stage = (0.0, 0.5, 0.5, 1.0)
    for k in range(N):
        u = U[k]
        for e in range(nP):  # eq. (35): Phi = I, Gamma = 0
            Phi[e] = 1.0 if phi_rows[e] == phi_cols[e] else 0.0
        Gamma[:] = 0.0
        for j in range(s):
            for r in range(4):  # RK4 on (x, Phi_P, Gamma_Q): the pruned 33-equation system
                if r == 0:
                    copy_vector(x, y)
                    copy_vector(Phi, zP)
                    copy_vector(Gamma, zQ)
                else:
                    c_r = stage[r] * h
                    for i in range(n):
                        y[i] = x[i] + c_r * Kx[r - 1, i]
                    for e in range(nP):
                        zP[e] = Phi[e] + c_r * KP[r - 1, e]
                    for e in range(nQ):
                        zQ[e] = Gamma[e] + c_r * KQ[r - 1, e]
                f_jac_eval(y, u, Kx[r], A, B)
                variational_slope(A, B, zP, zQ, S, KP[r], KQ[r])  # eqs. (33)-(34)
            for i in range(n):
                x[i] += (h / 6.0) * (Kx[0, i] + 2.0 * Kx[1, i] + 2.0 * Kx[2, i] + Kx[3, i])
            for e in range(nP):
                Phi[e] += (h / 6.0) * (KP[0, e] + 2.0 * KP[1, e] + 2.0 * KP[2, e] + KP[3, e])
            for e in range(nQ):
                Gamma[e] += (h / 6.0) * (KQ[0, e] + 2.0 * KQ[1, e] + 2.0 * KQ[2, e] + KQ[3, e])
            if not all_finite(x):
                q[:] = np.nan
                return np.inf
            if j < s - 1:  # an intermediate grid point: chain its penalty to x_k and u[k]
                J += state_penalty(x, w, gx, P, k * s + j + 1)
                for e in range(nP):
                    a[k, phi_cols[e]] += gx[phi_rows[e]] * Phi[e]
                for e in range(nQ):
                    c[k, gamma_cols[e]] += gx[gamma_rows[e]] * Gamma[e]
        J += state_penalty(x, w, J_samples[k + 1], P, (k + 1) * s)
        copy_vector(Phi, Phi_k[k])
        copy_vector(Gamma, Gamma_k[k])
    J += final_penalty(x, J_samples[N], P)
    mu = J_samples[N].copy()  # backward recursion of eq. (29)
    mu_next = np.empty(n)
    for k in range(N - 1, -1, -1):
        for j in range(m):
            q[k, j] += c[k, j]
        for e in range(nQ):  # eq. (36): rho_{k+1}[k] = Gamma_k
            q[k, gamma_cols[e]] += mu[gamma_rows[e]] * Gamma_k[k, e]
        for i in range(n):
            mu_next[i] = J_samples[k, i] + a[k, i]
        for e in range(nP):  # eq. (37): rho_{k+1}[j] = Phi_k rho_k[j]
            mu_next[phi_cols[e]] += mu[phi_rows[e]] * Phi_k[k, e]
        mu, mu_next = mu_next, mu
    return J
