"""The horizon searches of Remark 4 (``pipeline.numerics.optimize.horizon``) on feasibility oracles
with a known answer: ``feasible(N)`` is ``N >= 37``, so the shortest feasible horizon is 37."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from pipeline.numerics.optimize.horizon import reseed, shortest_by_continuation, smallest_feasible

SHORTEST = 37


def counting_oracle() -> tuple[list[int], Callable[[int], bool]]:
    """``feasible(N) = N >= SHORTEST``, and the horizons it was asked about, in order."""
    asked: list[int] = []

    def feasible(N: int) -> bool:
        asked.append(N)
        return N >= SHORTEST

    return asked, feasible


def test_bisection_finds_the_shortest_feasible_horizon_in_log2_calls() -> None:
    asked, feasible = counting_oracle()
    assert smallest_feasible(feasible, 0, 100) == SHORTEST
    assert len(asked) == math.ceil(math.log2(100))  # 7 optimisations
    assert all(0 < N < 100 for N in asked)


def test_continuation_shortens_to_the_shortest_feasible_horizon() -> None:
    asked, feasible = counting_oracle()
    assert shortest_by_continuation(feasible, 100, 0.25) == SHORTEST
    # the last try is one sample shorter than the answer, and refused
    assert asked[-1] == SHORTEST - 1
    assert shortest_by_continuation(lambda N: False, 100, 0.25) == 100  # nothing shorter


def test_truncate_keeps_the_first_samples_and_holds_the_last_to_extend() -> None:
    u = np.arange(8.0).reshape(4, 2)  # (N_u, m) = (4, 2)
    np.testing.assert_array_equal(reseed(u, 2, "truncate"), u[:2])
    np.testing.assert_array_equal(reseed(u, 6, "truncate"), np.vstack([u, u[-1], u[-1]]))


def test_compress_plays_the_same_input_faster() -> None:
    """Samples at the interval midpoints, linear between them: u = 0, 1, 2, 3 at 1/8, 3/8, 5/8,
    7/8 read at 1/4 and 3/4 gives 0.5 and 2.5; a constant input stays constant."""
    u = np.stack([np.arange(4.0), np.full(4, 7.0)], axis=-1)  # (4, 2)
    np.testing.assert_allclose(reseed(u, 2, "compress"), [[0.5, 7.0], [2.5, 7.0]])
    assert reseed(u, 9, "compress").shape == (9, 2)


def test_an_unknown_seed_mode_is_a_value_error_naming_it() -> None:
    with pytest.raises(ValueError, match="seed mode must be one of .* got 'stretch'"):
        reseed(np.zeros((3, 1)), 2, "stretch")
