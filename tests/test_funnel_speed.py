"""What makes the funnel fast keeps it sound (pipeline.numerics.funnel.pieces, funnel.lmi, hull).

1. Pieces: ``Q`` interpolated linearly over each piece (P1), the gain held over it.
2. The angle cap fills whole arc segments and never goes below a quarter segment.
3. The hull's symbolic structure is cached per ``Dynamics`` object: two dynamics that differ
   only in a coefficient get their own hulls, each containing its own Jacobians.
4. quadrotor_hill_flythrough demo 3 (rejected before: the hull boxes spanned the whole pitch
envelope and
   the program was nearly infeasible) is certified, with the gain held over each piece.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy

from pipeline.model.dynamics import Dynamics
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.check import LEVEL_SLACK
from pipeline.numerics.funnel.pieces import ARC, arc_cap, interpolate, pieces
from pipeline.numerics.funnel.synthesis import HOLD, check_funnel, synthesize_funnel
from pipeline.numerics.hull import (
    MAX_SEGMENT_ANGLE,
    arc_polygon,
    arc_variables,
    jacobian_hull,
    unique_rows,
)

THETA_BOUNDS = {"theta": (-0.8, 0.8)}


def test_pieces_and_interpolation() -> None:
    np.testing.assert_array_equal(pieces(7, 2), [0, 2, 4, 6, 7])
    np.testing.assert_array_equal(pieces(6, 3), [0, 3, 6])
    rng = np.random.default_rng(0)
    Q_ends = rng.normal(size=(5, 3, 3))
    Q = interpolate(Q_ends, pieces(7, 2))
    assert Q.shape == (8, 3, 3)
    np.testing.assert_array_equal(Q[[0, 2, 4, 6, 7]], Q_ends)
    np.testing.assert_allclose(Q[1], (Q_ends[0] + Q_ends[1]) / 2)
    np.testing.assert_allclose(Q[5], (Q_ends[2] + Q_ends[3]) / 2)


@pytest.mark.parametrize("spread", [0.0, 0.1, 0.3, 0.5, 0.7, 0.77, 1.0, 2.0])
def test_arc_cap_fills_whole_segments(spread: float) -> None:
    w = arc_cap(spread)
    assert w >= ARC / 4 - 1e-12
    width = spread + 2 * w
    segments = round(width / ARC)
    assert width == pytest.approx(segments * ARC)
    # The arc polygon of the capped box has exactly that many segments (none added by rounding).
    assert len(arc_polygon(0.0, width, 1, compact=True)) == segments + 2
    assert math.ceil(width / MAX_SEGMENT_ANGLE) == segments


def test_the_hulls_unique_rows_are_numpys() -> None:
    """``unique_rows`` (the hull's vertices deduplicated by a lexsort) gives ``np.unique(...,
    axis=0)``'s array, byte for byte, on random rows with repeats, ties in leading columns and
    shapes of 1-3 dimensions; a hull's vertices are numpy's unique rows of themselves."""
    rng = np.random.default_rng(3)
    for trial in range(2000):
        k = int(rng.integers(1, 30))
        shape = (k, *rng.integers(1, 4, size=int(rng.integers(0, 3))).tolist())
        values = [0.0, 1.0, -1.0, 0.5, 2.0, 1e-300, -3.5]  # ties, in every column
        rows = rng.choice(values, size=shape) if trial % 2 else rng.normal(size=shape)
        rows = np.concatenate([rows, rows[rng.integers(0, k, size=int(rng.integers(0, k)))]])
        rng.shuffle(rows)
        expected = np.unique(rows, axis=0)
        found = unique_rows(rows)
        assert found.shape == expected.shape and found.tobytes() == expected.tobytes()
    quadrotor = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    region = dict(quadrotor.operating_region)
    vertices = jacobian_hull(quadrotor.dynamics, region).vertices
    assert vertices.tobytes() == np.unique(vertices, axis=0).tobytes()


def test_hull_structure_is_cached_per_dynamics() -> None:
    x, theta = sympy.symbols("x theta")
    u = sympy.Symbol("u")
    made = [
        Dynamics.from_expressions([x, theta], [u], [c * u * sympy.sin(theta), u])
        for c in (1.0, -3.0)
    ]
    assert arc_variables(made[0]) == ("theta",)  # f_theta has cos, f_u has sin
    region = {"theta": (0.2, 0.5), "u": (1.0, 2.0)}
    hulls = [jacobian_hull(D, region, 1, compact=True) for D in made]
    again = jacobian_hull(made[0], region, 1, compact=True)
    np.testing.assert_array_equal(again.vertices, hulls[0].vertices)
    for D, hull in zip(made, hulls, strict=True):  # each holds its own Jacobians
        for t in np.linspace(0.2, 0.5, 7):
            for v in (1.0, 1.5, 2.0):
                J = np.hstack([D.f_x(np.array([0.0, t]), np.array([v])),
                               D.f_u(np.array([0.0, t]), np.array([v]))])  # fmt: skip
                low = hull.vertices.min(axis=0)
                high = hull.vertices.max(axis=0)
                assert np.all(J >= low - 1e-12) and np.all(J <= high + 1e-12)
    assert np.sign(hulls[0].vertices[:, 0, 1].max()) != np.sign(hulls[1].vertices[:, 0, 1].max())
    quadrotor = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    assert arc_variables(quadrotor.dynamics) == ("theta",)


def test_demo_3_is_certified_with_held_gains() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    demo = scenario.demos[2]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    funnel = synthesize_funnel(scenario, trajectory, state_bounds=THETA_BOUNDS)
    assert funnel.success, funnel.message
    # holds the whole required initial set (the level sits LEVEL_SLACK below its cap)
    assert funnel.rho == pytest.approx(1.0 - LEVEL_SLACK, abs=1e-9)
    assert check_funnel(scenario, trajectory, funnel, THETA_BOUNDS) is None
    held = funnel.K[0::HOLD]
    for offset in range(1, HOLD):  # the gain is held over each piece
        np.testing.assert_array_equal(funnel.K[offset::HOLD], held[: len(funnel.K[offset::HOLD])])
    assert max(len(v) for v in funnel.vertices) == 6  # pitch boxes within one arc segment
