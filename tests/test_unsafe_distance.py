"""The rollout kernel's distance to Unsafe (``pipeline.numerics.kernels.shared``): the full
measurement against shapely, and the nearest-edge shortcut near a full measurement
(``cached_distance``), which must give the full measurement's float exactly whenever it answers."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.model import geometry
from pipeline.model.scenario import load_scenario
from pipeline.numerics.closed_loop.rollouts import SceneArrays
from pipeline.numerics.kernels.rollout import LIPSCHITZ_ROUNDING
from pipeline.numerics.kernels.shared import cached_distance, unsafe_distance


@pytest.mark.parametrize("name", ["quadrotor_hill", "unicycle_slalom"])
def test_the_nearest_edge_alone_gives_the_full_measurement_where_it_answers(name):
    """From random anchors (clear of Unsafe or not) to points moved up to 1.5 times the
    anchor's distance: where ``cached_distance`` answers, it is the full measurement bit for
    bit and the point is outside every set; it answers for some of the moves (the shortcut is
    used) and declines others (those near another edge, or as far as the anchor's distance)."""
    scene = SceneArrays.of(load_scenario(name, check_demos=False)).unsafe
    rng = np.random.default_rng(7)
    lo, hi = scene[0].min(axis=0) - 2.0, scene[0].max(axis=0) + 2.0
    edge, full_edge, anchor = np.empty(8), np.empty(8), np.empty(2)
    answered = asked = 0
    for _ in range(400):
        anchor[:] = rng.uniform(lo, hi)
        measured = unsafe_distance(anchor[0], anchor[1], np.inf, scene, edge)
        for _ in range(20):
            step = rng.normal(size=2)
            point = anchor + step / np.linalg.norm(step) * rng.uniform(0, 1.5) * measured
            found = cached_distance(point[0], point[1], edge, LIPSCHITZ_ROUNDING)
            full = unsafe_distance(point[0], point[1], np.inf, scene, full_edge)
            asked += 1
            if found >= 0.0:
                answered += 1
                assert found == full and full > 0, (anchor, point, found, full)
    assert asked / 10 < answered < asked, (answered, asked)


@pytest.mark.parametrize("name", ["quadrotor_hill", "unicycle_slalom"])
def test_the_full_measurement_is_shapely_s_distance_and_says_when_it_is_an_edge_s(name):
    """``unsafe_distance`` with no cap: shapely's distance to the nearest Unsafe set (0 inside
    one); its edge record is valid exactly when the point is outside, and then bounds every
    other edge from below by no more than their true distances (at least the nearest's)."""
    scenario = load_scenario(name, check_demos=False)
    scene = SceneArrays.of(scenario).unsafe
    regions = list(scenario.unsafe.values())
    rng = np.random.default_rng(3)
    lo, hi = scene[0].min(axis=0) - 2.0, scene[0].max(axis=0) + 2.0
    edge = np.empty(8)
    for point in rng.uniform(lo, hi, size=(300, 2)):
        found = unsafe_distance(point[0], point[1], np.inf, scene, edge)
        expected = min(float(geometry.distance(point[None], region)[0]) for region in regions)
        inside = any(bool(geometry.contains(region, point[None])[0]) for region in regions)
        assert found == pytest.approx(0.0 if inside else expected, rel=1e-12, abs=1e-12)
        assert (edge[4] >= 0) == (not inside)
        if not inside:
            assert edge[4] >= found - 1e-12
