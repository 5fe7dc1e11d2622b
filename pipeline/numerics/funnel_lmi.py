"""The funnel's semidefinite program (pipeline.numerics.funnel, (F3)), built for Clarabel directly.

Unknowns ``Q[0..N]`` (n, n symmetric), ``x = (q_0, .., q_N)``, ``q_k`` the upper triangle of
``Q[k]`` (``Q = sum_l q_l E_l``, ``E_l = e_i e_j^T + e_j e_i^T`` for ``i < j``). Problem:

    minimise sum_k tr(W[k] Q[k]) - w tau
    subject to  -(Q[k+1] - Q[k]) / Ts + G_kv(Q[k+e]) <= 0,  G(X) = Acl X + X Acl^T + c X,
                Acl = A_v + B_v K[k], every vertex v of interval k, e in {0, 1};           (F3)
                Q[0] >= tau Q_init, tau <= 1;  Q[k] >= floor I;  C Q[k] C^T <= bound (caps).

``tau`` is the fraction of the required initial set held (``w`` large: it is maximised first), so
a program that cannot hold all of it still returns the funnel that holds the most.

Why not cvxpy: on quadrotor_hill (150 intervals x 12 vertices x 2 ends = 3,600 6x6 LMIs) cvxpy's
canonicalisation took 20-40 s per trajectory and added a slack matrix per LMI, so Clarabel's
solve took 10-20 s more. Here each LMI is one ``PSDTriangleConeT`` row block ``s = b - A x``
(upper triangle in column-major order, off-diagonal entries times sqrt 2), assembled with numpy.
``solve_cvxpy`` states the same problem in cvxpy as the reference the tests compare against.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import clarabel
import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from pipeline.model.dynamics import FloatArray


@dataclass(frozen=True, kw_only=True)
class FunnelProgram:
    """The data of (F3).

    Attributes:
      Ts: sample time; K: (N, m, n) gains; vertices: N arrays (V_k, n, n+m) of ``[A_v B_v]``.
      c: ``2 lambda + eps`` in ``G``; Q_init: (n, n); floor: smallest eigenvalue of each Q[k].
      caps: ``(k, C (r, n), bound (r, r))``: ``C Q[k] C^T <= bound`` (a scalar if r = 1).
      W: (N+1, n, n) objective weights; initial_weight: ``w``.
    """

    Ts: float
    K: FloatArray
    vertices: tuple[FloatArray, ...] = field(repr=False)
    c: float
    Q_init: FloatArray
    floor: float
    caps: tuple[tuple[int, FloatArray, FloatArray], ...] = field(repr=False)
    W: FloatArray = field(repr=False)
    initial_weight: float


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


def solve_clarabel(program: FunnelProgram) -> tuple[FloatArray, float] | str:
    """``(Q (N+1, n, n), tau)`` solving (F3), or the solver's status."""
    K, Ts = program.K, program.Ts
    N, n = len(K), K.shape[2]
    p = n * (n + 1) // 2
    E = basis(n)
    sE = svec(E)  # (p, p): column l is svec(E_l)
    blocks_A, blocks_b, cones = [], [], []

    def columns(k: int, block: FloatArray) -> sp.coo_matrix:
        """``block (r, p)`` placed on the unknowns of Q[k]."""
        out = sp.coo_matrix(block)
        return sp.coo_matrix(
            (out.data, (out.row, out.col + k * p)), shape=(len(block), (N + 1) * p + 1)
        )

    # C Q[k] C^T <= bound: s = svec(bound) - svec(C Q[k] C^T) = b - A x.
    for k, C, bound in program.caps:
        blocks_A.append(columns(k, svec(C @ E @ C.T).T))
        blocks_b.append(svec(bound))
        r = len(C)
        cones.append(clarabel.NonnegativeConeT(1) if r == 1 else clarabel.PSDTriangleConeT(r))
    # tau <= 1; Q[0] - tau Q_init >= 0: s = svec(Q[0]) - tau svec(Q_init) = b - A x (tau last).
    tau = sp.coo_matrix(([1.0], ([0], [(N + 1) * p])), shape=(1, (N + 1) * p + 1))
    blocks_A.append(tau)
    blocks_b.append(np.ones(1))
    cones.append(clarabel.NonnegativeConeT(1))
    initial = sp.coo_matrix(svec(program.Q_init)[:, None])
    blocks_A.append(columns(0, -sE.T) + sp.hstack([sp.coo_matrix((p, (N + 1) * p)), initial]))
    blocks_b.append(np.zeros(p))
    cones.append(clarabel.PSDTriangleConeT(n))
    # Q[k] - floor I >= 0: s = svec(Q[k]) - svec(floor I) = b - A x.
    for k, lower in [(k, program.floor * np.eye(n)) for k in range(N + 1)]:
        blocks_A.append(columns(k, -sE.T))
        blocks_b.append(-svec(lower))
        cones.append(clarabel.PSDTriangleConeT(n))
    # (F3): s = -M(x), M(Q[k], Q[k+1]) = -(Q[k+1] - Q[k]) / Ts + G(Q[k+e]).
    for k in range(N):
        J = program.vertices[k]
        Acl = J[:, :, :n] + J[:, :, n:] @ K[k]  # (V, n, n)
        G = Acl[:, None] @ E[None] + E[None] @ np.swapaxes(Acl, 1, 2)[:, None] + program.c * E
        sG = np.swapaxes(svec(G), 1, 2)  # (V, p rows, p unknowns)
        V = len(J)
        for e in (0, 1):  # A = svec(M(E_l)) on the unknowns of Q[k] and Q[k+1], b = 0
            A_k = sE.T / Ts + (sG if e == 0 else 0.0)  # (V, p, p) after broadcasting
            A_next = -sE.T / Ts + (sG if e == 1 else 0.0)
            A_k = np.broadcast_to(A_k, (V, p, p)).reshape(V * p, p)
            A_next = np.broadcast_to(A_next, (V, p, p)).reshape(V * p, p)
            blocks_A.append(columns(k, A_k) + columns(k + 1, A_next))
            blocks_b.append(np.zeros(V * p))
            cones.extend(clarabel.PSDTriangleConeT(n) for _ in range(V))
    A = sp.vstack(blocks_A).tocsc()
    b = np.concatenate([np.asarray(v, dtype=np.float64) for v in blocks_b])
    q = np.concatenate(
        [np.einsum("ij,lij->l", W, E) for W in program.W] + [[-program.initial_weight]]
    )
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solution = clarabel.DefaultSolver(
        sp.csc_matrix(((N + 1) * p + 1,) * 2), q, A, b, cones, settings
    ).solve()
    status = str(solution.status)
    if status not in ("Solved", "AlmostSolved"):
        return f"Clarabel status {status}"
    x = np.asarray(solution.x)
    return unpack(x[:-1], n), float(x[-1])


def solve_cvxpy(program: FunnelProgram) -> tuple[FloatArray, float] | str:
    """The same program through cvxpy + Clarabel (reference for tests; slow on long horizons)."""
    K, Ts = program.K, program.Ts
    N, n = len(K), K.shape[2]
    Q = [cp.Variable((n, n), symmetric=True) for _ in range(N + 1)]
    tau = cp.Variable()
    constraints = [Q[0] - tau * program.Q_init >> 0, tau <= 1]
    constraints += [Qk >> program.floor * np.eye(n) for Qk in Q]
    constraints += [bound - C @ Q[k] @ C.T >> 0 for k, C, bound in program.caps]
    for k in range(N):
        D = (Q[k + 1] - Q[k]) / Ts  # eq. (F1)
        for J in program.vertices[k]:
            Acl = J[:, :n] + J[:, n:] @ K[k]
            for Qe in (Q[k], Q[k + 1]):
                M = -D + Acl @ Qe + Qe @ Acl.T + program.c * Qe  # eq. (F2)
                constraints.append((M + M.T) / 2 << 0)  # eq. (F3)
    cost = sum(cp.trace(W @ Qk) for W, Qk in zip(program.W, Q, strict=True))
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
    return (values + np.swapaxes(values, 1, 2)) / 2, float(tau.value)
