"""The held law's boxes as ``funnel.law`` (I6) bounded them before the support-function bound
(commit 9136737): the reference the tighter bound is compared with."""

from __future__ import annotations

import math

import numpy as np


def per_state_hold(vertices, K, P, rho, rate, Ts, offset, period, disturbance, measurement=None):
    """``(H (N, n), held_input (N, m), h Edot (N, n))`` of the law held every ``period`` s from
    the per-state box ``h Edot`` of ``e(t_j) - e(t)``: ``H[k] = max_v |B_v K| (h Edot + E)``,
    ``held_input = |K| (h Edot + E)``. ``offset (N, n)``: ``Delta`` (with ``E``),
    ``law_offset``'s ``deviation`` at period 0; ``disturbance (n,)`` ``d``, ``measurement (n,)``
    ``E`` or None."""
    N, m, n = K.shape
    Q = np.linalg.inv(P)
    Q_diagonal = np.diagonal(Q, axis1=1, axis2=2)
    E = np.zeros(n) if measurement is None else np.asarray(measurement, dtype=np.float64)
    hold, held_input, drift = np.zeros((N, n)), np.zeros((N, m)), np.zeros((N, n))
    for k in range(N):
        A, B = vertices[k][:, :, :n], vertices[k][:, :, n:]
        level = rho * math.exp(-rate * Ts * k)
        extent = level * np.sqrt(np.maximum(Q_diagonal[k], Q_diagonal[k + 1]))
        spread = np.maximum(
            np.einsum("ji,il,jl->j", K[k], Q[k], K[k]),
            np.einsum("ji,il,jl->j", K[k], Q[k + 1], K[k]),
        )
        reach = level * np.sqrt(np.maximum(spread, 0.0)) + np.abs(K[k]) @ offset[k]
        speed = (np.abs(A) @ extent + np.abs(B) @ reach).max(axis=0) + disturbance
        drift[k] = period * speed
        pushed = drift[k] + E
        hold[k] = (np.abs(B @ K[k]) @ pushed).max(axis=0)
        held_input[k] = np.abs(K[k]) @ pushed
    return hold, held_input, drift
