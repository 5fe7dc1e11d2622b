"""Shortening the horizon of a feasible flight (paper Remark 4): the searches and their seeds.

``feasible(N)`` is one optimisation of the horizon ``N`` (``stages.optimize``); these functions
only decide which horizons to try and how to seed them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pipeline.model.dynamics import FloatArray

SEED_MODES = ("compress", "truncate")


def reseed(u: FloatArray, N: int, mode: str) -> FloatArray:
    """A seed of ``N`` samples from a feasible input ``u (N_u, m)``: its first ``N`` samples
    (``truncate``, the paper's Remark 4) or the same input played faster (``compress``)."""
    if mode == "truncate":
        return np.array(u[:N]) if N <= len(u) else np.vstack([u, np.repeat(u[-1:], N - len(u), 0)])
    if mode == "compress":
        source = (np.arange(len(u)) + 0.5) / len(u)
        target = (np.arange(N) + 0.5) / N
        return np.stack([np.interp(target, source, column) for column in u.T], axis=-1)
    raise ValueError(f"seed mode must be one of {SEED_MODES}, got {mode!r}")


def smallest_feasible(feasible: Callable[[int], bool], lo: int, hi: int) -> int:
    """Bisection on the horizon (Remark 4): the smallest ``N`` in ``(lo, hi]`` with
    ``feasible(N)``, given ``lo`` infeasible and ``hi`` feasible and feasibility monotone in
    ``N``. Each call of ``feasible`` is one optimisation; there are ``ceil(log2(hi - lo))``."""
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if feasible(mid):
            hi = mid
        else:
            lo = mid
    return hi


def shortest_by_continuation(feasible: Callable[[int], bool], N: int, fraction: float) -> int:
    """Shorten a feasible horizon ``N`` step by step: try ``N - step`` (``step`` a ``fraction``
    of ``N``), keep it when feasible, halve the step when not, stop below one sample.

    Each try is warm-started from the last feasible solution, which stays close to it; measured
    on quadrotor_hill this finds 13% shorter flights than the bisection's long jumps, whose
    seeds are far from any solution (see the README)."""
    step = max(1, int(fraction * N))
    while step >= 1:
        if N - step >= 1 and feasible(N - step):
            N -= step
            step = max(1, int(fraction * N))
        else:
            step //= 2
    return N
