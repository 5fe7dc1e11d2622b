"""The brackets of (I5)'s eigenvalues (``pipeline.numerics.funnel.secular``) and the search that
skips the matrices they place below another's (``funnel.robust``): every bracket holds numpy's
largest eigenvalue of its matrix, and the skipping evaluation returns exactly (bit for bit) the
full one's values, on random matrices, block-diagonal ones (exact zeros in the border, (S3)),
tiny borders (a pole the root sits on) and a held law's pairs."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.numerics.funnel.robust import RobustCheck
from pipeline.numerics.funnel.secular import brackets


def _arrow_cases(rng: np.random.Generator, R: int, C: int, n: int, kind: str):
    """``(M (R, n, n), a (R, C, n), alpha (R,))`` of the kind named."""
    X = rng.normal(size=(R, n, n))
    M = -(X @ np.swapaxes(X, 1, 2)) + rng.normal(size=(R, 1, 1))
    a = rng.normal(size=(R, C, n))
    if kind == "block":  # two uncoupled blocks, the corner acting on one of them
        M[:, : n // 2, n // 2 :] = M[:, n // 2 :, : n // 2] = 0.0
        a[:, :, : n // 2] = 0.0
    elif kind == "tiny":  # a border nearly orthogonal to the top eigenvector
        a *= 10.0 ** rng.uniform(-9, 0, size=(R, C, 1))
    elif kind == "scaled":  # a large multiplier over a small matrix, as early in the search
        M *= 1e-3
    alpha = np.abs(rng.normal(size=R)) * (1e4 if kind == "scaled" else 1.0)
    return M, a, alpha


@pytest.mark.parametrize("kind", ["random", "block", "tiny", "scaled"])
def test_each_bracket_holds_numpys_largest_eigenvalue_and_is_narrow(kind):
    rng = np.random.default_rng(11)
    R, C, n = 300, 4, 6
    M, a, alpha = _arrow_cases(rng, R, C, n, kind)
    w, U = np.linalg.eigh(M)
    lo, hi = brackets(w, U, np.sqrt((M * M).sum(axis=(1, 2))), a, alpha)
    S = np.zeros((R, C, n + 1, n + 1))
    S[:, :, :n, :n] = M[:, None] + alpha[:, None, None, None] * np.eye(n)
    S[:, :, :n, n] = S[:, :, n, :n] = a
    S[:, :, n, n] = -alpha[:, None]
    top = np.linalg.eigvalsh(S)[..., -1]
    assert np.all((lo <= top) & (top <= hi))
    scale = 1 + np.abs(M).max() + alpha.max() + np.abs(a).max()
    assert np.median(hi - lo) < 1e-6 * scale  # narrow enough to skip most matrices


def _random_check(rng: np.random.Generator, period: float = 0.0) -> RobustCheck:
    N, n, m, V = 6, 4, 2, 3
    root = rng.normal(size=(n, n)) * 0.3 + np.eye(n) + 0.002 * rng.normal(size=(N + 1, n, n))
    Q = root @ np.swapaxes(root, 1, 2)
    K = -np.abs(rng.normal(size=(N, m, n)))
    vertices = tuple(
        np.concatenate(
            [-2 * np.eye(n) + 0.3 * rng.normal(size=(V, n, n)), 0.2 * rng.normal(size=(V, n, m))],
            axis=2,
        )
        for _ in range(N)
    )
    return RobustCheck(Q, K, vertices, 0.1, 0.05, 1.0, period)


@pytest.mark.parametrize("period", [0.0, 0.01])
def test_the_skipping_evaluation_returns_the_full_ones_values_bit_for_bit(period):
    """Over a golden-section-like sweep of multipliers (from far above the minimum to near it),
    on every row and on a subset, the skipping evaluation equals ``_largest`` exactly."""
    rng = np.random.default_rng(3)
    for _ in range(4):
        check = _random_check(rng, period)
        a = check._scaled(np.abs(rng.normal(size=4)) * 0.3)
        subset = np.flatnonzero(rng.random(len(check.M)) < 0.5)
        for rows in (None, subset):
            largest = check._evaluator(a, rows)
            for alpha in np.geomspace(1e-3, 1e3, 40)[:, None] * rng.uniform(0.5, 1, check.N):
                np.testing.assert_array_equal(largest(alpha), check._largest(alpha, a, rows))


def test_margins_are_unchanged_by_the_skipping_search():
    """``margins`` (whose search skips) against the same golden section on ``_largest``."""
    rng = np.random.default_rng(8)
    check = _random_check(rng)
    bound = np.abs(rng.normal(size=4)) * 0.2
    value, alpha = check.margins(bound)
    full = RobustCheck.__new__(RobustCheck)
    full.__dict__.update(check.__dict__)
    full._evaluator = lambda a, rows: lambda al: check._largest(al, a, rows)  # type: ignore[method-assign]
    reference_value, reference_alpha = full.margins(bound)
    np.testing.assert_array_equal(alpha, reference_alpha)
    np.testing.assert_array_equal(value, reference_value)
