"""Geometry: distances, nearest points, containment, bloat and shrink on shapes with known answers.

All queries take positions ``(..., 2)`` and keep the leading shape.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.model import geometry

SQUARE = geometry.polygon([[0, 0], [1, 0], [1, 1], [0, 1]])  # the unit square
# An L-shape: the square [0, 2] x [0, 2] without [1, 2] x [1, 2] (non-convex).
L_SHAPE = geometry.polygon([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]])

# (position, distance to SQUARE, nearest point of SQUARE)
KNOWN = [
    ((0.5, 0.5), 0.0, (0.5, 0.5)),  # inside
    ((1.0, 0.5), 0.0, (1.0, 0.5)),  # on the boundary
    ((2.0, 0.5), 1.0, (1.0, 0.5)),  # beside an edge
    ((0.5, -3.0), 3.0, (0.5, 0.0)),
    ((2.0, 2.0), np.sqrt(2.0), (1.0, 1.0)),  # beyond a corner
    ((-3.0, 5.0), 5.0, (0.0, 1.0)),  # 3-4-5 from the corner (0, 1)
]
POSITIONS = np.array([p for p, _, _ in KNOWN])  # (6, 2)
DISTANCES = np.array([d for _, d, _ in KNOWN])
NEAREST = np.array([q for _, _, q in KNOWN])


def test_polygon_from_open_vertex_list() -> None:
    assert SQUARE.is_valid and SQUARE.area == 1.0
    assert L_SHAPE.is_valid and L_SHAPE.area == 3.0


def test_distance_known_answers_and_shapes() -> None:
    np.testing.assert_allclose(geometry.distance(POSITIONS, SQUARE), DISTANCES, atol=1e-15)
    grid = POSITIONS.reshape(2, 3, 2)
    assert geometry.distance(grid, SQUARE).shape == (2, 3)
    np.testing.assert_allclose(geometry.distance(grid, SQUARE), DISTANCES.reshape(2, 3))
    assert geometry.distance(np.array([2.0, 0.5]), SQUARE).shape == ()
    assert float(geometry.distance(np.array([2.0, 0.5]), SQUARE)) == 1.0


def test_distance_to_a_non_convex_set() -> None:
    # (1.5, 1.5) sits in the L's notch: 0.5 from both inner edges; (3, 3) is sqrt(5) from (2, 1)
    # and (1, 2), equally.
    positions = np.array([[1.5, 1.5], [3.0, 3.0], [0.5, 1.5], [1.5, 0.5]])
    np.testing.assert_allclose(
        geometry.distance(positions, L_SHAPE), [0.5, np.sqrt(5.0), 0.0, 0.0], atol=1e-15
    )


def test_nearest_points_known_answers_and_shapes() -> None:
    np.testing.assert_allclose(geometry.nearest_points(POSITIONS, SQUARE), NEAREST, atol=1e-15)
    grid = POSITIONS.reshape(3, 2, 2)
    np.testing.assert_allclose(
        geometry.nearest_points(grid, SQUARE), NEAREST.reshape(3, 2, 2), atol=1e-15
    )


def test_nearest_points_give_the_distance_gradient() -> None:
    """Outside a set, ``(p - nearest) / distance`` has unit length and points away from it."""
    outside = POSITIONS[DISTANCES > 0]
    direction = (outside - geometry.nearest_points(outside, SQUARE)) / geometry.distance(
        outside, SQUARE
    )[:, None]
    np.testing.assert_allclose(np.linalg.norm(direction, axis=-1), 1.0)
    h = 1e-6
    step = geometry.distance(outside + h * direction, SQUARE) - geometry.distance(outside, SQUARE)
    np.testing.assert_allclose(step / h, 1.0, rtol=1e-6)


def test_boundary_distance() -> None:
    positions = np.array([[0.5, 0.5], [0.25, 0.5], [2.0, 0.5]])
    np.testing.assert_allclose(geometry.boundary_distance(positions, SQUARE), [0.5, 0.25, 1.0])


def test_contains_includes_the_boundary_and_keeps_shape() -> None:
    inside = geometry.contains(SQUARE, POSITIONS)
    np.testing.assert_array_equal(inside, DISTANCES == 0)
    assert inside.dtype == np.bool_
    grid = geometry.contains(SQUARE, POSITIONS.reshape(2, 3, 2))
    np.testing.assert_array_equal(grid, (DISTANCES == 0).reshape(2, 3))
    np.testing.assert_array_equal(
        geometry.contains(L_SHAPE, np.array([[1.5, 1.5], [0.5, 1.5], [1.0, 1.0], [1.01, 1.01]])),
        [False, True, True, False],
    )


def test_bloat_square() -> None:
    d = 0.5
    bloated = geometry.bloat(SQUARE, d)
    # Area of a unit square bloated by d: 1 + 4 d + pi d^2 (the corner arcs are polygonal).
    np.testing.assert_allclose(bloated.area, 1 + 4 * d + np.pi * d**2, rtol=1e-3)
    # Exactly d away along an edge: on the boundary; the corner (1 + d/sqrt2)^2 likewise.
    on_boundary = np.array([[1.0 + d, 0.5], [0.5, -d], [1 + d / np.sqrt(2), 1 + d / np.sqrt(2)]])
    np.testing.assert_allclose(geometry.boundary_distance(on_boundary, bloated), 0.0, atol=1e-3)
    np.testing.assert_array_equal(
        geometry.contains(bloated, np.array([[1.0 + 0.99 * d, 0.5], [1.0 + 1.01 * d, 0.5]])),
        [True, False],
    )


def test_shrink_square() -> None:
    shrunk = geometry.shrink(SQUARE, 0.25)
    np.testing.assert_allclose(shrunk.bounds, [0.25, 0.25, 0.75, 0.75])
    np.testing.assert_allclose(shrunk.area, 0.25)
    assert geometry.shrink(SQUARE, 0.6).is_empty
    assert geometry.shrink(L_SHAPE, 0.25).area < L_SHAPE.area


# Rounded to 1e-6 so that a point outside is at least 1e-6 away (no distance underflowing to 0).
coordinate = st.floats(min_value=-4.0, max_value=5.0).map(lambda value: round(value, 6))


@settings(max_examples=200, deadline=None)
@given(x=coordinate, y=coordinate, d=st.floats(min_value=0.05, max_value=2.0))
def test_bloat_distance_property(x: float, y: float, d: float) -> None:
    """dist(p, bloat(R, d)) = max(dist(p, R) - d, 0) up to the polygonal arcs (32 per quarter)."""
    p = np.array([[x, y]])
    for region in (SQUARE, L_SHAPE):
        expected = np.maximum(geometry.distance(p, region) - d, 0.0)
        tolerance = d * (1 - np.cos(np.pi / 64)) + 1e-12
        np.testing.assert_allclose(
            geometry.distance(p, geometry.bloat(region, d)), expected, atol=tolerance
        )
        assert bool(geometry.contains(region, p)[0]) == (geometry.distance(p, region)[0] == 0.0)
