"""The funnel's semidefinite program (``synthesis``, (F3)), built for Clarabel directly.

Unknowns ``Q[0..N]`` (n, n symmetric), ``x = (q_0, .., q_N)``, ``q_k`` the upper triangle of
``Q[k]`` (``Q = sum_l q_l E_l``, ``E_l = e_i e_j^T + e_j e_i^T`` for ``i < j``). Problem:

    minimise sum_k tr(W[k] Q[k]) - w tau
    subject to  -(Q[k+1] - Q[k]) / Ts_k + G_kv(Q[k+e]) <= 0,  G(X) = Acl X + X Acl^T + c X,
                Acl = A_v + B_v K[k], every vertex v of interval k, e in {0, 1};           (F3)
                Q[0] >= tau Q_init[j] (every j), tau <= 1;  Q[k] >= floor I;
                C Q[k] C^T <= bound (caps);
    and under a disturbance box, (F3) joined with it by the S-procedure (funnel.robust (I5)):
                [[-(Q[k+1] - Q[k]) / Ts_k + G_kv(Q[k+e]) + alpha Q[k+e], w_c],
                 [w_c^T, -(alpha - eps)]] <= 0   (every vertex, end and corner w_c),
    ``alpha`` a fixed multiplier and ``eps`` the margin in ``c = 2 lambda + eps``, so that at
    level 1 (I5)'s ``S(alpha) <= -eps I``.

With ``codesign`` (``synthesis`` (F6)) the gains are unknowns too, ``Y[j] = K[j] Q`` (m, n) per
piece: ``Acl Q[k+e]`` becomes ``A_v Q[k+e] + B_v Y[j]``, input ``i``'s cap ``[[Q[k], Y[j]_i^T],
[Y[j]_i, bound]] >= 0`` and the spread ``[[Q[j], Y[j]^T], [Y[j], Z[j]]] >= 0`` with ``tr(R
Z[j])`` in the objective; all still linear in the unknowns.

``tau`` is the fraction of the required initial set held (``w`` large: it is maximised first), so
a program that cannot hold all of it still returns the funnel that holds the most.

Why not cvxpy: on quadrotor_hill_flythrough (150 intervals x 12 vertices x 2 ends = 3,600 6x6 LMIs)
cvxpy's canonicalisation took 20-40 s per trajectory and added a slack matrix per LMI, so Clarabel's
solve took 10-20 s more. Here each LMI is one ``PSDTriangleConeT`` row block ``s = b - A x``
(upper triangle in column-major order, off-diagonal entries times sqrt 2); all of them are
assembled at once as COO triplets with numpy. Clarabel's time grows with the number of LMIs (about
50 us per 6x6 LMI per interior-point iteration on this machine), which is why
``pipeline.numerics.funnel.synthesis`` imposes them per piece of ``HOLD`` samples on few-vertex
hulls. ``solve_cvxpy`` states the same problem in cvxpy as the reference the tests compare against.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

import clarabel
import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from pipeline.model.dynamics import FloatArray

# Clarabel's settings. Stopping tolerances (defaults 1e-8): the solution is re-checked with numpy
# eigenvalues against the LMI margin eps >= 1e-3 (pipeline.numerics.funnel.synthesis), three
# orders above these or more, so a looser stop saves interior-point iterations without weakening
# anything that is proven; tol_feas is 1e-6 because a held law's pushed program floors its primal
# residual just above 1e-7 and would run to the iteration cap. No chordal decomposition: it splits
# the small dense 6x6 and 7x7 LMIs into overlapping cliques joined by consensus rows, more cones
# for the same iterations (measurements: commit cf2f459).
SETTINGS = {
    "tol_gap_abs": 1e-7,
    "tol_gap_rel": 1e-7,
    "tol_feas": 1e-6,
    "chordal_decomposition_enable": False,
}


@dataclass(frozen=True, kw_only=True)
class FunnelProgram:
    """The data of (F3).

    Attributes:
      Ts: the intervals' durations, one for all or (N,); K: (N, m, n) gains held on each;
        vertices: N arrays (V_k, n, n+m) of ``[A_v B_v]``.
      c: ``2 lambda + eps`` in ``G``; Q_init: (n, n) or (p, n, n), each held by ``Q[0] / tau``;
        floor: smallest eigenvalue of each Q[k].
      caps: ``(k, C (r, n), bound (r, r))``: ``C Q[k] C^T <= bound`` (a scalar if r = 1).
      W: (N+1, n, n) objective weights; initial_weight: ``w``.
      disturbance: (C, n) corners ``w_c`` of a disturbance box (None: none); multiplier: the
        S-procedure's ``alpha``; margin: ``eps`` (both only with a disturbance).
      codesign: the gains are unknowns too (``codesign_gains``, (F6)): ``Y[j] = K[j] Q`` (m, n)
        per piece, ``K`` only seeds the objective; gain_caps: ``(k, j, i, bound)``, input ``i``'s
        cap ``Y[j]_i Q[k]^-1 Y[j]_i^T <= bound`` at piece end ``k`` of piece ``j`` (with
        ``codesign`` only: otherwise input caps are ``caps`` with ``C = K[j]_i``);
        gain_weight: (m, m) ``R``, with ``codesign`` the objective gains ``sum_j tr(R Z[j])``,
        ``Z[j] >= Y[j] Q[j]^-1 Y[j]^T = K Q K^T`` (the inputs' spread at level 1; Schur).
    """

    Ts: float | FloatArray
    K: FloatArray
    vertices: tuple[FloatArray, ...] = field(repr=False)
    c: float
    Q_init: FloatArray
    floor: float
    caps: tuple[tuple[int, FloatArray, FloatArray], ...] = field(repr=False)
    W: FloatArray = field(repr=False)
    initial_weight: float
    disturbance: FloatArray | None = field(default=None, repr=False)
    multiplier: float = 0.0
    margin: float = 0.0
    codesign: bool = False
    gain_caps: tuple[tuple[int, int, int, float], ...] = field(default=(), repr=False)
    gain_weight: FloatArray | None = field(default=None, repr=False)


def _triangle(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices (n (n+1) / 2,) of the upper triangle in column-major order."""
    pairs = [(i, j) for j in range(n) for i in range(j + 1)]
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])


def svec(M: FloatArray) -> FloatArray:
    """Clarabel's vectorisation of symmetric ``M (..., n, n)`` -> ``(..., n (n+1) / 2)``."""
    rows, cols = _triangle(M.shape[-1])
    return M[..., rows, cols] * np.where(rows == cols, 1.0, np.sqrt(2.0))


def basis(n: int) -> FloatArray:
    """(p, n, n) the matrices ``E_l`` of the unknowns ``q_l``."""
    rows, cols = _triangle(n)
    E = np.zeros((len(rows), n, n))
    E[np.arange(len(rows)), rows, cols] = 1.0
    E[np.arange(len(rows)), cols, rows] = 1.0
    return E


def unpack(x: FloatArray, n: int) -> FloatArray:
    """``x ((N+1) p,)`` -> ``Q (N+1, n, n)``."""
    return np.einsum("kl,lij->kij", x.reshape(-1, n * (n + 1) // 2), basis(n))


def _block(rows: np.ndarray, columns: np.ndarray, values: FloatArray) -> tuple[np.ndarray, ...]:
    """COO triplets of dense ``values (B, r, c)`` at ``rows (B, r)`` x ``columns (B, c)``."""
    B, r, c = values.shape
    return (
        np.broadcast_to(rows[:, :, None], (B, r, c)).ravel(),
        np.broadcast_to(columns[:, None, :], (B, r, c)).ravel(),
        values.ravel(),
    )


def solve_clarabel(program: FunnelProgram) -> tuple[FloatArray, float] | str:
    """``(Q (N+1, n, n), tau)`` solving (F3), or the solver's status."""
    x = _solve(program)
    if isinstance(x, str):
        return x
    n = program.K.shape[2]
    tau_index = (len(program.K) + 1) * (n * (n + 1) // 2)
    return unpack(x[:tau_index], n), float(x[tau_index])


def codesign_gains(program: FunnelProgram) -> tuple[FloatArray, FloatArray, float] | str:
    """``(K (N, m, n), Q (N+1, n, n), tau)`` of (F6), or the solver's status: ``program`` with
    ``codesign``, each piece's gain read back as ``K[j] = Y[j] Qbar[j]^-1``, ``Qbar[j]`` the
    mean of the piece's end metrics. Only a seed: (F6) holds for the law ``Y Q(t)^-1``, not
    for a held ``K``; the funnel is solved again with these gains held ((F3)) and checked."""
    x = _solve(dataclasses.replace(program, codesign=True))
    if isinstance(x, str):
        return x
    N, m, n = program.K.shape
    tau_index = (N + 1) * (n * (n + 1) // 2)
    Q = unpack(x[:tau_index], n)
    Y = x[tau_index + 1 : tau_index + 1 + N * m * n].reshape(N, m, n)
    K = np.linalg.solve((Q[:-1] + Q[1:]) / 2, np.swapaxes(Y, 1, 2))  # Qbar^-1 Y^T (Q symmetric)
    return np.swapaxes(K, 1, 2), Q, float(x[tau_index])


def _solve(program: FunnelProgram) -> FloatArray | str:
    """The solution vector ``(q_0 .. q_N, tau[, y_0 .. y_N-1])`` of (F3) (or (F6) with
    ``codesign``), or the solver's status.

    The constraint matrix is assembled as one set of COO triplets (every LMI at once); rows are
    ``s = b - A x`` in the cone order of ``cones``."""
    K = program.K
    N, m, n = K.shape
    Ts = np.broadcast_to(np.asarray(program.Ts, dtype=np.float64), (N,))
    p = n * (n + 1) // 2
    tau_index = (N + 1) * p  # q_0 .. q_N, tau, then y_0 .. y_N-1 and z_0 .. z_N-1 (codesign)
    pm = m * (m + 1) // 2
    spread = program.codesign and program.gain_weight is not None
    unknowns = tau_index + 1 + (N * m * n if program.codesign else 0) + (N * pm if spread else 0)
    E = basis(n)
    sE = svec(E)  # (p, p): column l is svec(E_l)
    triplets: list[tuple[np.ndarray, ...]] = []
    b_parts: list[FloatArray] = []
    cones: list = []
    row = 0

    def rows(count: int, size: int) -> np.ndarray:
        """(count, size) row indices of the next ``count`` cones of ``size`` rows each."""
        nonlocal row
        out = row + np.arange(count * size).reshape(count, size)
        row += count * size
        return out

    def of(k: np.ndarray) -> np.ndarray:
        """(len(k), p) columns of the unknowns of ``Q[k]``."""
        return np.asarray(k)[:, None] * p + np.arange(p)

    # C Q[k] C^T <= bound: s = svec(bound) - svec(C Q[k] C^T) = b - A x.
    for k, C, bound in program.caps:
        r = len(C)
        block = svec(C @ E @ C.T).T  # (r (r+1) / 2, p)
        triplets.append(_block(rows(1, len(block)), of(np.array([k])), block[None]))
        b_parts.append(svec(np.asarray(bound, dtype=np.float64)))
        cones.append(clarabel.NonnegativeConeT(1) if r == 1 else clarabel.PSDTriangleConeT(r))
    # tau <= 1: s = 1 - tau.
    triplets.append((rows(1, 1).ravel(), np.array([tau_index]), np.ones(1)))
    b_parts.append(np.ones(1))
    cones.append(clarabel.NonnegativeConeT(1))
    # Q[0] - tau Q_init[j] >= 0: s = svec(Q[0]) - tau svec(Q_init[j]) = b - A x.
    Q_init = np.asarray(program.Q_init, dtype=np.float64).reshape(-1, n, n)
    r0 = rows(len(Q_init), p)
    triplets.append(
        _block(
            r0, of(np.zeros(len(Q_init), dtype=int)), np.broadcast_to(-sE.T, (len(Q_init), p, p))
        )
    )
    triplets.append((r0.ravel(), np.full(r0.size, tau_index), svec(Q_init).ravel()))
    b_parts.append(np.zeros(r0.size))
    cones.extend(clarabel.PSDTriangleConeT(n) for _ in range(len(Q_init)))
    # Q[k] - floor I >= 0: s = svec(Q[k]) - svec(floor I) = b - A x.
    everyone = np.arange(N + 1)
    triplets.append(_block(rows(N + 1, p), of(everyone), np.broadcast_to(-sE.T, (N + 1, p, p))))
    b_parts.append(np.tile(-svec(program.floor * np.eye(n)), N + 1))
    cones.extend(clarabel.PSDTriangleConeT(n) for _ in range(N + 1))

    def gains(j: np.ndarray) -> np.ndarray:
        """(len(j), m n) columns of the unknowns ``Y[j]`` (row-major)."""
        return tau_index + 1 + np.asarray(j)[:, None] * (m * n) + np.arange(m * n)

    F = np.zeros((m * n, m, n))  # the unit matrices of Y's entries, row-major
    F[np.arange(m * n), np.arange(m * n) // n, np.arange(m * n) % n] = 1.0
    if spread and program.gain_weight is not None:
        # [[Q[j], Y[j]^T], [Y[j], Z[j]]] >= 0: s = svec of it = b - A x, b = 0
        size = (n + m) * (n + m + 1) // 2
        spread_rows = rows(N, size)
        Yunit = np.zeros((m * n, n + m, n + m))
        Yunit[:, n:, :n] = F
        Yunit[:, :n, n:] = np.swapaxes(F, 1, 2)
        Zunit = np.zeros((pm, n + m, n + m))
        Zunit[:, n:, n:] = basis(m)
        every = np.arange(N)
        z_columns = tau_index + 1 + N * m * n + every[:, None] * pm + np.arange(pm)
        for columns, values in (
            (of(every), np.broadcast_to(-sE.T, (N, p, p))),
            (gains(every), np.broadcast_to(-svec(Yunit).T, (N, size, m * n))),
            (z_columns, np.broadcast_to(-svec(Zunit).T, (N, size, pm))),
        ):
            triplets.append(_block(spread_rows[:, : values.shape[1]], columns, values))
        b_parts.append(np.zeros(spread_rows.size))
        cones.extend(clarabel.PSDTriangleConeT(n + m) for _ in range(N))
        spread_weight = np.einsum("ij,lij->l", program.gain_weight, basis(m))
    # with codesign, (F6)'s input caps: [[Q[k], Y[j]_i^T], [Y[j]_i, bound]] >= 0 (Schur), i.e.
    # s = svec of it = b - A x (the leading n-block's svec comes first, as for (I5))
    for k, j, i, room_squared in program.gain_caps:
        cap_rows = rows(1, (n + 1) * (n + 2) // 2)
        unit = np.zeros((n, n + 1, n + 1))
        unit[np.arange(n), np.arange(n), n] = unit[np.arange(n), n, np.arange(n)] = 1.0
        triplets.append(_block(cap_rows[:, :p], of(np.array([k])), -sE.T[None]))
        triplets.append(_block(cap_rows, gains(np.array([j]))[:, i * n : (i + 1) * n],
                               -svec(unit).T[None]))  # fmt: skip
        constant = np.zeros((n + 1, n + 1))
        constant[n, n] = room_squared
        b_parts.append(svec(constant))
        cones.append(clarabel.PSDTriangleConeT(n + 1))
    # (F3): s = -M(x), M(Q[k], Q[k+1]) = -(Q[k+1] - Q[k]) / Ts[k] + G(Q[k+e]), every vertex;
    # with a disturbance, (I5): s = -[[M(x) + alpha Q[k+e], w_c], [w_c^T, -(alpha - eps)]].
    J = np.concatenate(program.vertices)  # (T, n, n+m), T = sum_k V_k
    k_of = np.repeat(np.arange(N), [len(v) for v in program.vertices])  # (T,)
    # (T, n, n); with codesign the gain's term is B_v Y[k] below
    Acl = J[:, :, :n] if program.codesign else J[:, :, :n] + J[:, :, n:] @ K[k_of]
    G = Acl[:, None] @ E[None] + E[None] @ np.swapaxes(Acl, 1, 2)[:, None] + program.c * E
    disturbance = program.disturbance if program.disturbance is not None else np.zeros((0, n))
    if len(disturbance):
        G = G + program.multiplier * E
    sG = np.swapaxes(svec(G), 1, 2)  # (T, p rows, p unknowns)
    if program.codesign:  # (F6): B_v Y + Y^T B_v^T in G, on the unknowns of Y[k]
        BF = J[:, None, :, n:] @ F[None]  # (T, m n, n, n)
        sBF = np.swapaxes(svec(BF + np.swapaxes(BF, 2, 3)), 1, 2)  # (T, p, m n)
    D = sE.T / Ts[k_of][:, None, None]  # (T, p, p): the unknowns of Q[k] in -dQ/dt
    # the constant part: none for (F3); the corner's column and entry for (I5) (the svec of an
    # (n+1)-matrix starts with its leading n-block's, in the same order)
    constants = [np.zeros(p)]
    if len(disturbance):
        corner = np.zeros((len(disturbance), n + 1, n + 1))
        corner[:, :n, n] = corner[:, n, :n] = -disturbance
        corner[:, n, n] = program.multiplier - program.margin
        constants = list(svec(corner))
    size, dim = len(constants[0]), n + 1 if len(disturbance) else n
    for e in (0, 1):  # A = svec(M(E_l)) on the unknowns of Q[k] and Q[k+1]
        for constant in constants:
            lmi_rows = rows(len(J), size)[:, :p]
            triplets.append(_block(lmi_rows, of(k_of), D + (sG if e == 0 else 0.0)))
            triplets.append(_block(lmi_rows, of(k_of + 1), -D + (sG if e == 1 else 0.0)))
            if program.codesign:
                triplets.append(_block(lmi_rows, gains(k_of), sBF))
            cones.extend(clarabel.PSDTriangleConeT(dim) for _ in J)
            b_parts.append(np.tile(constant, len(J)))
    rows_, cols_, vals_ = (np.concatenate(part) for part in zip(*triplets, strict=True))
    keep = vals_ != 0.0
    A = sp.csc_matrix((vals_[keep], (rows_[keep], cols_[keep])), shape=(row, unknowns))
    b = np.concatenate(b_parts)
    q = np.concatenate(
        [
            np.einsum("kij,lij->kl", program.W, E).ravel(),
            [-program.initial_weight],
            np.zeros(N * m * n if program.codesign else 0),
            np.tile(spread_weight, N) if spread else [],
        ]
    )
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    for name, value in SETTINGS.items():
        setattr(settings, name, value)
    solution = clarabel.DefaultSolver(
        sp.csc_matrix((unknowns,) * 2), q, A, b, cones, settings
    ).solve()
    status = str(solution.status)
    if status not in ("Solved", "AlmostSolved"):
        return f"Clarabel status {status}"
    return np.asarray(solution.x)


def solve_cvxpy(
    program: FunnelProgram,
) -> tuple[FloatArray, float] | tuple[FloatArray, float, FloatArray] | str:
    """The same program through cvxpy + Clarabel (reference for tests; slow on long horizons):
    ``(Q (N+1, n, n), tau)``; with ``codesign``, ``(Q, tau, Y (N, m, n))``."""
    K = program.K
    N, m, n = K.shape
    Ts = np.broadcast_to(np.asarray(program.Ts, dtype=np.float64), (N,))
    Q = [cp.Variable((n, n), symmetric=True) for _ in range(N + 1)]
    tau = cp.Variable()
    Y = [cp.Variable((m, n)) for _ in range(N)] if program.codesign else []
    Q_init = np.asarray(program.Q_init, dtype=np.float64).reshape(-1, n, n)
    constraints = [Q[0] - tau * Q_j >> 0 for Q_j in Q_init] + [tau <= 1]
    constraints += [Qk >> program.floor * np.eye(n) for Qk in Q]
    constraints += [bound - C @ Q[k] @ C.T >> 0 for k, C, bound in program.caps]
    disturbance = program.disturbance if program.disturbance is not None else np.zeros((0, n))
    for k, j, i, room_squared in program.gain_caps:  # (F6)'s input caps (Schur)
        Yi = Y[j][i : i + 1]
        constraints.append(cp.bmat([[Q[k], Yi.T], [Yi, np.array([[room_squared]])]]) >> 0)
    cost = sum(cp.trace(W @ Qk) for W, Qk in zip(program.W, Q, strict=True))
    if program.codesign and program.gain_weight is not None:  # (F6)'s spread Z >= Y Q^-1 Y^T
        Z = [cp.Variable((m, m), symmetric=True) for _ in range(N)]
        constraints += [cp.bmat([[Q[k], Y[k].T], [Y[k], Z[k]]]) >> 0 for k in range(N)]
        cost = cost + sum(cp.trace(program.gain_weight @ Zk) for Zk in Z)
    for k in range(N):
        D = (Q[k + 1] - Q[k]) / Ts[k]  # eq. (F1)
        for J in program.vertices[k]:
            A, B = J[:, :n], J[:, n:]
            for Qe in (Q[k], Q[k + 1]):
                # eq. (F2); (F6): B K Q = B Y
                AQ = A @ Qe + B @ Y[k] if program.codesign else (A + B @ K[k]) @ Qe
                M = -D + AQ + AQ.T + program.c * Qe
                if not len(disturbance):
                    constraints.append((M + M.T) / 2 << 0)  # eq. (F3)
                for w in disturbance:  # funnel.robust (I5)
                    corner = np.array([[program.multiplier - program.margin]])
                    S = cp.bmat([[(M + M.T) / 2 + program.multiplier * Qe, -w[:, None]],
                                 [-w[None, :], -corner]])  # fmt: skip
                    constraints.append(S << 0)
    objective = cp.Minimize(cost - program.initial_weight * tau)
    problem = cp.Problem(objective, constraints)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            problem.solve(solver=cp.CLARABEL)
    except cp.SolverError as error:
        return f"solver error ({error})"
    if (
        problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
        or Q[0].value is None
        or tau.value is None
    ):
        return f"cvxpy status {problem.status}"
    values = np.array([Qk.value for Qk in Q])
    Q_values = (values + np.swapaxes(values, 1, 2)) / 2
    if program.codesign:
        return Q_values, float(tau.value), np.array([Yk.value for Yk in Y])
    return Q_values, float(tau.value)
