"""Funnels built by hand, for the tests of what reads a funnel's gains and metrics."""

from __future__ import annotations

import numpy as np

from pipeline.numerics.funnel.check import Funnel


def make_funnel(
    K: np.ndarray, P: np.ndarray, rho: float, success: bool = True, enclosure=None
) -> Funnel:
    """A funnel with gains ``K (N, m, n)`` and metrics ``P (N+1, n, n)`` (no hull data: the
    margins read only K, P, rho and the enclosure)."""
    N = len(K)
    return Funnel(
        K=K, P=P, rho=rho, rate=0.0, margins=np.full((N, 2), -1.0), boxes=np.zeros((N, 2, 0)),
        variables=(), vertices=(), enclosure=enclosure, limits={}, binding="", seconds=0.0,
        success=success, message="" if success else "rejected for the test",
    )  # fmt: skip
