"""Numba loops of the cost and its gradients: a template, compiled per scenario.

Not imported directly: ``pipeline.numerics.kernels.compiled`` appends to this source the scenario's
``f_eval``, ``f_jac_eval`` and ``vjp_eval`` (generated from its sympy expressions, replacing the
stubs below) and imports the result with ``numba.njit(cache=True)``. The maths is that of the NumPy
references: ``pipeline.numerics.penalties`` (eqs. (40)-(42)), ``pipeline.numerics.adjoint``
(discrete adjoint of RK4) and ``pipeline.numerics.sensitivity`` (eqs. (29), (33)-(37), pruned).
Shapes: ``n`` states, ``m`` inputs, ``N`` samples, ``s`` substeps, ``h = Ts / s``;
``X (N s + 1, n)``
the RK4 grid.

``P`` is a ``pipeline.numerics.kernels.compiled.PenaltyData`` tuple: its margins are per RK4
grid point (``unsafe_margin (N s + 1,)``, ``region_state_* (N s + 1, a)``) and per sample
(``input_* (N, m)``, ``region_input_* (N, b)``), constant arrays for constant margins. Polygons
are vertex arrays ``V (v, 2)`` with rings ``ring_start[r]:ring_start[r+1]`` (not closed); Unsafe
set ``S`` owns rings ``set_rings[S]:set_rings[S+1]``.
"""

import math

import numpy as np
from numba import njit

_SERIES_BELOW = 1e-4  # as pipeline.numerics.penalties


def f_eval(x, u, out):  # generated: out (n,) = f(x, u)
    raise NotImplementedError


def f_jac_eval(x, u, out, A, B):  # generated: f, A (n*n,) = f_x, B (n*m,) = f_u (nonzeros)
    raise NotImplementedError


def vjp_eval(x, u, lam, out_x, out_u):  # generated: out_x = lam f_x, out_u = lam f_u
    raise NotImplementedError


@njit(cache=True, inline="always")
def _copy(source, target):
    """``target[:] = source`` for 1-D arrays, as a loop: numba compiles an array-to-array slice
    assignment with a shape-mismatch message built from strings, ~1.6 s once per process."""
    for i in range(source.size):
        target[i] = source[i]


@njit(cache=True)
def polygon_query(px, py, V, ring_start, r0, r1):
    """Inside (even-odd rule), distance and nearest point of rings ``r0..r1-1``."""
    inside = False
    best = np.inf
    cx = px
    cy = py
    for r in range(r0, r1):
        a = ring_start[r]
        b = ring_start[r + 1]
        j = b - 1
        for i in range(a, b):
            x1 = V[j, 0]
            y1 = V[j, 1]
            x2 = V[i, 0]
            y2 = V[i, 1]
            if (y2 > py) != (y1 > py):
                if px < x2 + (py - y2) * (x1 - x2) / (y1 - y2):
                    inside = not inside
            dx = x2 - x1
            dy = y2 - y1
            L = dx * dx + dy * dy
            t = 0.0
            if L > 0.0:
                t = min(max(((px - x1) * dx + (py - y1) * dy) / L, 0.0), 1.0)
            qx = x1 + t * dx
            qy = y1 + t * dy
            dd = (px - qx) * (px - qx) + (py - qy) * (py - qy)
            if dd < best:
                best = dd
                cx = qx
                cy = qy
            j = i
    return inside, math.sqrt(best), cx, cy


@njit(cache=True)
def state_penalty(x, w, grad, P, i_grid):
    """``w (g_unsafe + g_reg)(x)`` at RK4 grid point ``i_grid`` (its margins); sets ``grad (n,)``
    to its derivative."""
    grad[:] = 0.0
    value = 0.0
    p0 = P.position[0]
    p1 = P.position[1]
    px = x[p0]
    py = x[p1]
    d = P.unsafe_margin[i_grid]
    for S in range(P.unsafe_set_rings.size - 1):
        # distance to the bounding box <= r: the barrier is zero when it exceeds d'
        ex = max(P.unsafe_box[S, 0] - px, 0.0, px - P.unsafe_box[S, 2])
        ey = max(P.unsafe_box[S, 1] - py, 0.0, py - P.unsafe_box[S, 3])
        if ex * ex + ey * ey > d * d:
            continue
        inside, r, cx, cy = polygon_query(
            px,
            py,
            P.unsafe_vertices,
            P.unsafe_ring_start,
            P.unsafe_set_rings[S],
            P.unsafe_set_rings[S + 1],
        )
        if inside or r <= 0.0:
            value = np.inf
        elif r < d:
            z = (r - d) / d  # eq. (42), corrected: b = -log(r/d') + (r - d')/d' = z - log1p(z)
            if z > -_SERIES_BELOW:
                value += z * z * (0.5 - z * (1.0 / 3.0 - z * (0.25 - z / 5.0)))
            else:
                value += z - math.log1p(z)
            slope = w * z / (1.0 + z) / d / r
            grad[p0] += slope * (px - cx)
            grad[p1] += slope * (py - cy)
    for j in range(P.region_state_index.size):
        i = P.region_state_index[j]
        lo = P.region_state_lower[i_grid, j]
        e = x[i] - min(max(x[i], lo), P.region_state_upper[i_grid, j])
        value += e * e
        grad[i] += w * 2.0 * e
    return w * value


@njit(cache=True)
def input_penalty(u, grad, P, k):
    """``(g_in + g_reg)(u)`` (eq. (40)) for sample ``k`` (its margins); sets ``grad (m,)``."""
    value = 0.0
    for i in range(u.size):
        e = u[i] - min(max(u[i], P.input_lower[k, i]), P.input_upper[k, i])
        value += e * e
        grad[i] = 2.0 * e
    for j in range(P.region_input_index.size):
        i = P.region_input_index[j]
        e = u[i] - min(max(u[i], P.region_input_lower[k, j]), P.region_input_upper[k, j])
        value += e * e
        grad[i] += 2.0 * e
    return value


@njit(cache=True)
def final_penalty(x, grad, P):
    """``G(x)`` (eq. (41)); adds its derivative to ``grad (n,)``."""
    p0 = P.position[0]
    p1 = P.position[1]
    inside, r, cx, cy = polygon_query(
        x[p0], x[p1], P.goal_vertices, P.goal_ring_start, 0, P.goal_ring_start.size - 1
    )
    value = 0.0
    if not inside:
        value += r * r
        grad[p0] += 2.0 * (x[p0] - cx)
        grad[p1] += 2.0 * (x[p1] - cy)
    for j in range(P.goal_index.size):
        i = P.goal_index[j]
        e = x[i] - min(max(x[i], P.goal_lower[j]), P.goal_upper[j])
        value += e * e
        grad[i] += 2.0 * e
    return value


@njit(cache=True)
def all_finite(x):
    for i in range(x.size):
        if not math.isfinite(x[i]):
            return False
    return True


@njit(cache=True)
def rk4_step(x, u, h, K, Y, out):
    """One RK4 step; stage values into ``Y (4, n)``, slopes into ``K (4, n)``, ``x+`` into out."""
    n = x.size
    for i in range(n):  # element loops, not slice copies: see the note on _copy
        Y[0, i] = x[i]
    f_eval(Y[0], u, K[0])
    for i in range(n):
        Y[1, i] = x[i] + 0.5 * h * K[0, i]
    f_eval(Y[1], u, K[1])
    for i in range(n):
        Y[2, i] = x[i] + 0.5 * h * K[1, i]
    f_eval(Y[2], u, K[2])
    for i in range(n):
        Y[3, i] = x[i] + h * K[2, i]
    f_eval(Y[3], u, K[3])
    for i in range(n):
        out[i] = x[i] + (h / 6.0) * (K[0, i] + 2.0 * K[1, i] + 2.0 * K[2, i] + K[3, i])


@njit(cache=True)
def simulate_kernel(x0, U, h, s, X):
    """The RK4 grid ``X (N s + 1, n)`` (as ``pipeline.model.simulate.simulate``)."""
    n = x0.size
    K = np.empty((4, n))
    Y = np.empty((4, n))
    _copy(x0, X[0])
    for i in range(U.shape[0] * s):
        rk4_step(X[i], U[i // s], h, K, Y, X[i + 1])


@njit(cache=True)
def cost_kernel(x0, U, h, s, P):
    """``J(u)``; ``+inf`` as soon as a grid state is inside Unsafe or not finite."""
    n = x0.size
    N = U.shape[0]
    w = 1.0 / s
    K = np.empty((4, n))
    Y = np.empty((4, n))
    gx = np.empty(n)
    gu = np.empty(U.shape[1])
    J = 0.0
    for k in range(N):
        J += input_penalty(U[k], gu, P, k)
    x = x0.copy()
    x_next = np.empty(n)
    J += state_penalty(x, w, gx, P, 0)
    for i in range(N * s):
        rk4_step(x, U[i // s], h, K, Y, x_next)
        x, x_next = x_next, x
        if not all_finite(x):
            return np.inf
        J += state_penalty(x, w, gx, P, i + 1)
        if J == np.inf:
            return J
    return J + final_penalty(x, gx, P)


@njit(cache=True)
def forward_kernel(x0, U, h, s, P, X, Y, J_x, J_u):
    """Forward pass for the adjoint: grid ``X``, stages ``Y (N s, 4, n)``, partials ``J_x``,
    ``J_u``. Returns J (``nan`` if a state is not finite)."""
    n = x0.size
    N = U.shape[0]
    w = 1.0 / s
    K = np.empty((4, n))
    J = 0.0
    for k in range(N):
        J += input_penalty(U[k], J_u[k], P, k)
    _copy(x0, X[0])
    J += state_penalty(X[0], w, J_x[0], P, 0)
    for i in range(N * s):
        rk4_step(X[i], U[i // s], h, K, Y[i], X[i + 1])
        if not all_finite(X[i + 1]):
            return np.nan
        J += state_penalty(X[i + 1], w, J_x[i + 1], P, i + 1)
    return J + final_penalty(X[N * s], J_x[N * s], P)


@njit(cache=True)
def adjoint_sweep(U, h, s, Y, J_x, q, G):
    """Backward sweep of the discrete RK4 adjoint (see ``pipeline.numerics.adjoint``); adds into q.

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
    for i in range(J_x.shape[0] - 2, -1, -1):
        k = i // s
        u = U[k]
        for j in range(n):
            lam_next[j] = lam[j] + J_x[i, j]
        for j in range(n):  # stage 4: kap4 = h/6 lam
            kap[j] = (h / 6.0) * lam[j]
        vjp_eval(Y[i, 3], u, kap, lam_y, gu)
        for j in range(m):
            q[k, j] += gu[j]
        for j in range(n):  # stage 3: kap3 = h/3 lam + h lam_y4
            lam_next[j] += lam_y[j]
            kap[j] = (h / 3.0) * lam[j] + h * lam_y[j]
        vjp_eval(Y[i, 2], u, kap, lam_y, gu)
        for j in range(m):
            q[k, j] += gu[j]
        for j in range(n):  # stage 2: kap2 = h/3 lam + h/2 lam_y3
            lam_next[j] += lam_y[j]
            kap[j] = (h / 3.0) * lam[j] + 0.5 * h * lam_y[j]
        vjp_eval(Y[i, 1], u, kap, lam_y, gu)
        for j in range(m):
            q[k, j] += gu[j]
        for j in range(n):  # stage 1: kap1 = h/6 lam + h/2 lam_y2
            lam_next[j] += lam_y[j]
            kap[j] = (h / 6.0) * lam[j] + 0.5 * h * lam_y[j]
        vjp_eval(Y[i, 0], u, kap, lam_y, gu)
        for j in range(m):
            q[k, j] += gu[j]
        for j in range(n):
            lam[j] = lam_next[j] + lam_y[j]
        if i % s == 0:  # u[k] = v[k] + G (x_i - z[k]): chain dJ/du[k] into dJ/dx_i
            for j in range(n):
                for r in range(m):
                    lam[j] += G[r, j] * q[k, r]


@njit(cache=True)
def adjoint_kernel(x0, U, h, s, P, q):
    """``J`` and ``q = dJ/du`` into ``q (N, m)`` by one forward pass and one backward sweep."""
    n = x0.size
    Ns = U.shape[0] * s
    X = np.empty((Ns + 1, n))
    Y = np.empty((Ns, 4, n))
    J_x = np.empty((Ns + 1, n))
    J = forward_kernel(x0, U, h, s, P, X, Y, J_x, q)
    if math.isnan(J):
        q[:] = np.nan
        return np.inf
    adjoint_sweep(U, h, s, Y, J_x, q, np.zeros((U.shape[1], n)))
    return J


@njit(cache=True)
def feedback_inputs(x0, V, Z, G, h, s, U):
    """Held inputs of the sampled feedback ``U[k] = V[k] + G (x(k Ts) - Z[k])`` into ``U (N, m)``;
    returns False if a state is not finite."""
    n = x0.size
    K = np.empty((4, n))
    Y = np.empty((4, n))
    x = x0.copy()
    x_next = np.empty(n)
    for k in range(V.shape[0]):
        for r in range(V.shape[1]):
            U[k, r] = V[k, r]
            for j in range(n):
                U[k, r] += G[r, j] * (x[j] - Z[k, j])
        for _ in range(s):
            rk4_step(x, U[k], h, K, Y, x_next)
            x, x_next = x_next, x
        if not all_finite(x):
            return False
    return True


@njit(cache=True)
def feedback_adjoint_kernel(x0, V, Z, G, h, s, P, U, q):
    """``J(U(V))`` and ``q = dJ/dV`` under the sampled feedback (``U`` receives the inputs)."""
    n = x0.size
    if not feedback_inputs(x0, V, Z, G, h, s, U):
        q[:] = np.nan
        return np.inf
    Ns = U.shape[0] * s
    X = np.empty((Ns + 1, n))
    Y = np.empty((Ns, 4, n))
    J_x = np.empty((Ns + 1, n))
    J = forward_kernel(x0, U, h, s, P, X, Y, J_x, q)
    if math.isnan(J):
        q[:] = np.nan
        return np.inf
    adjoint_sweep(U, h, s, Y, J_x, q, G)
    return J


@njit(cache=True)
def _variational_slope(A, B, zP, zQ, S, KP, KQ):
    """Right-hand sides of (33)-(34) on the pruned entries: ``KP = (A Phi)_P``,
    ``KQ = (A Gamma + B)_Q``; ``S`` = (phi_ptr, phi_a, phi_src, gamma_ptr, gamma_a, gamma_src,
    gamma_b) term lists of the sparse products."""
    phi_ptr, phi_a, phi_src, gamma_ptr, gamma_a, gamma_src, gamma_b = S
    for e in range(KP.size):
        acc = 0.0
        for t in range(phi_ptr[e], phi_ptr[e + 1]):
            acc += A[phi_a[t]] * zP[phi_src[t]]
        KP[e] = acc
    for e in range(KQ.size):
        acc = B[gamma_b[e]]
        for t in range(gamma_ptr[e], gamma_ptr[e + 1]):
            acc += A[gamma_a[t]] * zQ[gamma_src[t]]
        KQ[e] = acc


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
                    _copy(x, y)
                    _copy(Phi, zP)
                    _copy(Gamma, zQ)
                else:
                    c_r = stage[r] * h
                    for i in range(n):
                        y[i] = x[i] + c_r * Kx[r - 1, i]
                    for e in range(nP):
                        zP[e] = Phi[e] + c_r * KP[r - 1, e]
                    for e in range(nQ):
                        zQ[e] = Gamma[e] + c_r * KQ[r - 1, e]
                f_jac_eval(y, u, Kx[r], A, B)
                _variational_slope(A, B, zP, zQ, S, KP[r], KQ[r])  # eqs. (33)-(34)
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
        _copy(Phi, Phi_k[k])
        _copy(Gamma, Gamma_k[k])
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
