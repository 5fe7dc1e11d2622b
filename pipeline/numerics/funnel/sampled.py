"""A held law's push taken to first order into the (I5) matrix, not into its box (I6').

Problem. ``funnel.law`` (I6) bounds the hold's push ``Bbar(t) K (e(t_j) - e(t))`` by a per-state
box ``H[k]`` and joins it to (I5)'s disturbance. To first order the push is linear in ``e(t)``
(``e(t_j) ~ e(t) - tau Acl e(t)``) and the box throws that away: on a stiff loop it is
``h |B K| |B K| rho``, far above what the loop's own decay leaves. Here the linear part goes into
(I5)'s matrix and only a remainder (second order in ``h`` in the state, first order in the law's
offset and the disturbance) into the box.

Setting. On ``[t_j, t_j + h)`` inside sample interval ``k``, ``tau = t - t_j`` in ``[0, h]``;
``u - u_ref = K (e(t_j) + c)``, ``|c| <= C`` (the law's offset at ``t_j``: (I1)'s ``Delta`` plus
(I7)'s ``E``); ``w`` with ``|w| <= d``; ``[Abar(s) Bbar(s)]`` the Jacobian averaged on the
segment at time ``s``, in the hull ``conv{[A_v B_v]}`` of interval ``k`` while the state is in
the funnel on ``[t_j, t]`` and the input in (I3)'s widened box (as (I6) argues: up to the first
exit, which is all the invariance argument needs). The error obeys

    e'(s) = Abar(s) e(s) + Bbar(s) K (e(t_j) + c) + w(s),    |e'(s)| <= Edot   (I6's bound).

Split. With ``Acl(s) = Abar(s) + Bbar(s) K``, add and subtract ``Acl(s) e(t)``:

    e'(s) = Acl(s) e(t) + Abar(s) (e(s) - e(t)) + Bbar(s) K (e(t_j) - e(t)) + Bbar(s) K c + w(s),

and ``e(t_j) - e(t) = -int_{t_j}^t e'(s) ds``, so the push is

    Bbar(t) K (e(t_j) - e(t)) = -tau Bbar(t) K Mbar e(t) + R,   Mbar = (1/tau) int Acl(s) ds,
    R = -Bbar(t) K int_{t_j}^t [Abar(s) (e(s) - e(t)) + Bbar(s) K (e(t_j) - e(t))
                                 + Bbar(s) K c + w(s)] ds.

``Mbar`` is the mean of ``Acl(s)``, each in the closed convex set ``conv{A_v' + B_v' K}``: so is
``Mbar`` (for ``tau = 0`` the term is zero, any ``Mbar`` will do).

(R) The remainder. ``|e(s) - e(t)| <= (t - s) Edot`` and ``|e(t_j) - e(t)| <= tau Edot``
componentwise; ``|Abar(s) y| <= max_v' |A_v'| |y|`` (a convex combination of the vertices), so the
first two terms of the integral are at most ``Y = h^2 (max_v' |A_v'| Edot / 2 + max_v' |B_v' K|
Edot)`` (``int (t - s) ds = tau^2 / 2``). With ``Bbar(t) = sum_v a_v B_v`` and the pair terms
bilinear in the two hulls' weights (as (I6)):

    |R_i| <= max_v [ (|B_v K| Y)_i + h max_v' (|B_v K B_v' K| C)_i + h (|B_v K| d)_i ]     (R)

and a measurement error adds ``|B_v K| E`` at the same ``v`` ((I7): ``Bbar(t) K eta(t_j)``). The
box ``R[k]`` (N, n) joins (I5)'s disturbance ``d``.

(I6') The linear part. The error equation is ``e' = (Acl(t) - tau Bbar(t) K Mbar) e + Bbar K
delta + R + w`` (``delta``: (I2)'s offset, through ``lmi_term`` as before), so (I5)'s operator
gains ``-tau (Bbar K Mbar Q + Q Mbar^T K^T Bbar^T)``:

    N = [[L(t, v) - tau (Bbar K Mbar Q(t) + Q(t) Mbar^T K^T Bbar^T) + alpha Q(t), w],
         [w^T, -alpha rho^2]].

Take ``t``, ``tau`` as independent (the pair ``(t, tau)`` lies in ``[t_k, t_k+1] x [0, h]``; not
using ``tau <= t - t_k`` only enlarges the set). For fixed ``z``, ``alpha``, ``[z; 1]^T (N + mu
diag(Q, rho^2)) [z; 1]`` is affine in each of: ``t`` (``Q`` linear in t, ``Q'`` constant on the
interval, eq. (F1)), ``tau``, the weights ``a`` of ``[Abar(t) Bbar(t)]`` (in ``L`` and in the
push: one set), the weights ``b`` of ``Mbar`` and ``w``; a function affine in each of several
variables over a product of polytopes attains its maximum at a vertex of the product. So
``lambda_max(S) <= -mu`` at every ``(end, v, v', tau in {0, h}, corner of d + R)`` gives it
everywhere: (I5)'s argument with ``V (V + 1)`` rows per end instead of ``V`` (``tau = 0``: the
plain rows; ``tau = h``: one per pair). With ``h = 0``, ``R = 0`` (plus ``E``'s box) and the rows
are (I5)'s: every number is the continuous law's.

What it does not change: (I2)'s ``lmi_term``, (I3)'s input offset (``held_input``: the hold's
input part stays (I6)'s bound), ``Edot`` and the per-state ``Delta_h``.
"""

from __future__ import annotations

import numpy as np

from pipeline.model.dynamics import FloatArray


def remainder_box(
    A: FloatArray,
    B: FloatArray,
    K: FloatArray,
    speed: FloatArray,
    offset: FloatArray,
    disturbance: FloatArray,
    measurement: FloatArray,
    period: float,
) -> FloatArray:
    """(n,) the box (R) of one interval, with (I7)'s ``|B_v K| E`` at the same vertex: ``A (V, n,
    n)``, ``B (V, n, m)`` the hull's vertices, ``K (m, n)``, ``speed (n,)`` ``Edot``, ``offset
    (n,)`` ``C``, ``disturbance (n,)`` ``d``, ``measurement (n,)`` ``E``, ``period`` ``h``."""
    BK = np.abs(B @ K)  # (V, n, n) |B_v K|
    Y = period**2 * ((np.abs(A) @ speed).max(axis=0) / 2 + (BK @ speed).max(axis=0))  # (n,)
    pairs = np.abs(np.einsum("vij,wjm->vwim", B @ K, B @ K)) @ offset  # (V, V, n)
    per_vertex = BK @ Y + period * pairs.max(axis=1) + period * BK @ disturbance  # eq. (R)
    return np.asarray((per_vertex + BK @ measurement).max(axis=0), dtype=np.float64)


def pushed_rows(
    A: FloatArray, B: FloatArray, K: FloatArray, Q: FloatArray, period: float
) -> FloatArray:
    """(V, V, n, n) the push's term ``-h (B_v K M_v' Q + Q M_v'^T K^T B_v^T)`` of (I6') at
    ``tau = h`` for every pair ``(v, v')``, ``M_v' = A_v' + B_v' K``; ``Q (n, n)`` at one end."""
    BK = B @ K  # (V, n, n)
    M = A + BK  # (V, n, n)
    T = np.einsum("vij,wjl,lp->vwip", BK, M, Q)  # B_v K M_v' Q
    return np.asarray(-period * (T + np.swapaxes(T, 2, 3)), dtype=np.float64)


def paired_vertices(J: FloatArray, K: FloatArray, period: float) -> FloatArray:
    """(2 V, n, n + m) the hull's vertices ``J (V, n, n + m)`` followed by one per diagonal pair
    ``(v, v)``, ``[A_v - h B_v K A_v, B_v - h B_v K B_v]``, ``K (m, n)``: its closed loop is
    ``A_v + B_v K - h B_v K M_v`` (``M_v = A_v + B_v K``), so its (F2) operator is the plain
    row's plus ``pushed_rows``' ``(v, v)`` term, (I6') at ``tau = h``. A design aid: the funnel
    program (``synthesis``, ``period``) imposes (F3) on these as on vertices (linear in ``Q`` for
    the fixed ``K``); nothing proven uses them as a hull (``funnel.robust`` checks (I6') on every
    pair). Only the diagonal: the other pairs moved quadrotor_hill's 5 ms margins by under 0.002
    (``bench.bench_sampled``) and took 7x the LMIs of the plain program instead of 2x."""
    n = J.shape[1]
    A, B = J[:, :, :n], J[:, :, n:]
    BK = B @ K  # (V, n, n)
    pairs = np.concatenate([A - period * BK @ A, B - period * BK @ B], axis=2)  # (V, n, n + m)
    return np.concatenate([J, pairs]).astype(np.float64)
