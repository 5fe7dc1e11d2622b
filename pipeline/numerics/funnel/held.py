"""The rates of a held law's push, ``funnel.law`` (I6), on one sample interval.

Problem. On ``[t_j, t)`` inside sample interval ``k`` the law is held at ``t_j``, and the push
``Bbar(t) K (e(t_j) - e(t)) = -int_{t_j}^t Bbar(t) K e'(s) ds`` with

    e'(s) = Abar(s) e(s) + Bbar(s) K (e(t_j) + c) + w(s),   |c| <= C,  |w| <= d,

``[Abar Bbar]`` in the hull ``conv{[A_v B_v]}``, ``e(s)``, ``e(t_j)`` in the funnel (``e^T P e <=
rho_k^2``, ``Q = P^-1`` linear in t on the interval). ``|(Bbar(t) K e'(s))_i|`` is at most the
largest over vertex pairs ``(v, v')`` of

    rho_k sqrt(max_ends r Q r^T) + rho_k sqrt(max_ends s Q s^T) + (|B_v K B_v' K| C)_i
        + (|B_v K| d)_i,       r = (B_v K A_v')[i, :],  s = (B_v K B_v' K)[i, :],        (I6)

and ``|(K e'(s))_j|`` the largest over ``v'`` of the same with ``K_j`` for ``(B_v K)[i, :]``.
``r Q r^T = B_v[i] (K A_v' Q A_v'^T K^T) B_v[i]^T``: the (m, m) middle is formed once per
vertex, so every pair costs ``O(n m^2)``.
"""

from __future__ import annotations

import numpy as np

from pipeline.model.dynamics import FloatArray


def held_rates(
    A: FloatArray,
    B: FloatArray,
    K: FloatArray,
    Q_ends: FloatArray,
    level: float,
    offset: FloatArray,
    disturbance: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """(I6)'s bounds on one interval: ``push (V, n)``, for each vertex ``v`` of ``Bbar(t)`` the
    largest over ``v'`` of the bound on ``|(B_v K e'(s))_i|``; ``swing (m,)`` the bound on
    ``|(K e'(s))_j|``. ``A (V, n, n)``, ``B (V, n, m)`` the hull's vertices, ``K (m, n)``,
    ``Q_ends (2, n, n)`` the inverse metric at the interval's ends, ``level`` ``rho_k`` (the
    level at its start), ``offset (n,)`` the box ``C`` of the law's offset at ``t_j``,
    ``disturbance (n,)`` the box ``d``."""
    KA = np.einsum("jl,wlm->wjm", K, A)  # (V, m, n) K A_v'
    KBK = np.einsum("jl,wlp,pm->wjm", K, B, K)  # (V, m, n) K B_v' K
    # (2, V, m, m) the middles K A_v' Q K A_v'^T and K B_v' K Q (K B_v' K)^T at both ends
    G_A = np.einsum("wjl,elp,wqp->ewjq", KA, Q_ends, KA)
    G_B = np.einsum("wjl,elp,wqp->ewjq", KBK, Q_ends, KBK)
    # (V, V, n) max_ends r Q r^T, max_ends s Q s^T over the pairs (v, v')
    r = np.einsum("vij,ewjq,viq->evwi", B, G_A, B).max(axis=0)
    s = np.einsum("vij,ewjq,viq->evwi", B, G_B, B).max(axis=0)
    boxed = np.abs(np.einsum("vij,wjm->vwim", B, KBK)) @ offset  # (V, V, n) |B_v K B_v' K| C
    acted = np.abs(B @ K) @ disturbance  # (V, n) |B_v K| d
    pairs = level * (np.sqrt(np.maximum(r, 0.0)) + np.sqrt(np.maximum(s, 0.0))) + boxed
    push = pairs.max(axis=1) + acted  # (V, n): the largest over v'
    r_K = np.diagonal(G_A, axis1=2, axis2=3).max(axis=0)  # (V, m) with K_j for (B_v K)[i]
    s_K = np.diagonal(G_B, axis1=2, axis2=3).max(axis=0)
    spread = np.sqrt(np.maximum(r_K, 0.0)) + np.sqrt(np.maximum(s_K, 0.0))
    swing = (level * spread + np.abs(KBK) @ offset).max(axis=0) + np.abs(K) @ disturbance
    return push, swing
