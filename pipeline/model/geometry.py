"""Planar sets over the position coordinates: Unsafe polygons, Goal, distances, bloat and shrink.

All point queries are vectorised with shapely 2 (``shapely.points``, ``shapely.distance``,
``shapely.contains_xy``); positions have shape ``(..., 2)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from pipeline.model.dynamics import BoolArray, FloatArray


def polygon(vertices: Sequence[Sequence[float]]) -> Polygon:
    """A shapely polygon from ``(k, 2)`` vertices (not repeated at the end)."""
    return Polygon(np.asarray(vertices, dtype=np.float64))


def distance(positions: FloatArray, region: BaseGeometry) -> FloatArray:
    """Euclidean distance from each position ``(..., 2)`` to ``region``; 0 inside. -> ``(...)``."""
    positions = np.asarray(positions, dtype=np.float64)
    points = shapely.points(positions.reshape(-1, 2))
    return shapely.distance(points, region).reshape(positions.shape[:-1])


def nearest_points(positions: FloatArray, region: BaseGeometry) -> FloatArray:
    """The point of ``region`` nearest to each position: ``(..., 2)`` -> ``(..., 2)``.

    For positions outside the region, ``(p - nearest) / distance`` is the gradient of the
    distance function.
    """
    positions = np.asarray(positions, dtype=np.float64)
    points = shapely.points(positions.reshape(-1, 2))
    lines = shapely.shortest_line(points, region)
    coords = shapely.get_coordinates(lines).reshape(-1, 2, 2)
    return coords[:, 1, :].reshape(positions.shape)


def boundary_distance(positions: FloatArray, region: BaseGeometry) -> FloatArray:
    """Distance from each position ``(..., 2)`` to the boundary of ``region``. -> ``(...)``."""
    return distance(positions, region.boundary)


def contains(region: BaseGeometry, positions: FloatArray) -> BoolArray:
    """True where a position ``(..., 2)`` lies in ``region`` (boundary included). -> ``(...)``."""
    positions = np.asarray(positions, dtype=np.float64)
    return shapely.intersects_xy(region, positions[..., 0], positions[..., 1])


def bloat(region: BaseGeometry, margin: float) -> BaseGeometry:
    """The set of points within ``margin`` of ``region`` (Unsafe bloated by ``d``)."""
    return region.buffer(margin, quad_segs=32)


def shrink(region: BaseGeometry, margin: float) -> BaseGeometry:
    """The points of ``region`` at least ``margin`` from its boundary (ModGoal); may be empty."""
    return region.buffer(-margin, quad_segs=32)


def inscribed_radius(region: BaseGeometry) -> float:
    """Radius of the largest disk inside ``region`` (the largest margin ``shrink`` can take)."""
    tolerance = 1e-6 * max(region.length, 1e-12)
    return float(shapely.maximum_inscribed_circle(region, tolerance).length)
