"""Stage ``coverage``: known covered and uncovered configurations, 2-D and 3-D Init inside a
higher-dimensional state, one metric per ball (the funnel's initial ellipsoids), and the lookup
table's soundness."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Point, box
from shapely.ops import unary_union

from stages.coverage import cover_balls, cover_init, covering_radius


def init(lower, upper, names=None):
    names = names or tuple(f"x{i}" for i in range(len(lower)))
    return SimpleNamespace(
        init_lower=np.array(lower, float), init_upper=np.array(upper, float), state_names=names
    )


METRIC = SimpleNamespace(P=np.eye(2))


def test_one_ball_covers_a_rectangle():
    result = cover_init(init([0, 0], [2, 1]), METRIC, [[1.0, 0.5]], [np.hypot(1, 0.5)])
    assert result.covered and result.success and result.covered_fraction == 1.0
    assert result.assignment.tolist() == [0] and result.depth == 0
    assert len(result.uncovered_boxes) == 0 and result.largest_gap() is None


def test_two_balls_with_corners_missing():
    """Balls of radius 0.6 about (0.5, 0.5) and (1.5, 0.5) miss the rectangle's corners."""
    centers, radii = np.array([[0.5, 0.5], [1.5, 0.5]]), np.array([0.6, 0.6])
    result = cover_init(init([0, 0], [2, 1]), METRIC, centers, radii, max_depth=7)
    assert not result.covered and not result.success
    exact = unary_union([Point(c).buffer(0.6, 256) for c in centers]).intersection(box(0, 0, 2, 1))
    assert result.covered_fraction <= exact.area / 2 + 1e-9
    assert result.covered_fraction >= exact.area / 2 - 0.02
    gaps = result.uncovered_boxes
    corner_in_gap = (gaps[:, 0] <= 0).all(axis=1) & (gaps[:, 1] >= 0).all(axis=1)
    assert corner_in_gap.any()  # the corner (0, 0) is reported uncovered
    assert "not covered" in result.message


def test_ellipsoidal_balls_enough_and_too_small():
    """Two P-balls whose vertex test passes once split into halves, then one ball shrunk."""
    P = np.array([[1.0, 0.2], [0.2, 2.0]])
    centers = np.array([[0.5, 0.5], [1.5, 0.5]])
    half_square = np.array([[dx, dy] for dx in (-0.5, 0.5) for dy in (-0.5, 0.5)])
    needed = np.sqrt(np.einsum("vi,ij,vj->v", half_square, P, half_square).max()) * (1 + 1e-9)
    covered = cover_init(init([0, 0], [2, 1]), SimpleNamespace(P=P), centers, [needed] * 2)
    assert covered.covered and covered.depth == 1
    assert sorted(set(covered.assignment.tolist())) == [0, 1]
    short = cover_init(init([0, 0], [2, 1]), SimpleNamespace(P=P), centers, [needed, 0.9 * needed])
    assert not short.covered
    assert np.all(short.uncovered_boxes[:, 0, 0] >= 1.0 - 1e-12)  # gaps only on ball 1's side


HALF_SQUARE = np.array([[dx, dy] for dx in (-0.5, 0.5) for dy in (-0.5, 0.5)])
METRICS = np.array([[[1.0, 0.2], [0.2, 2.0]], [[3.0, -0.8], [-0.8, 0.5]]])  # (2, 2, 2) P_0, P_1


def _exact_radii(metrics):
    """(2,) the smallest radius at which each ball, about (0.5, 0.5) and (1.5, 0.5) in its own
    metric, holds its half of [0, 2] x [0, 1]: the largest P_i-norm of a half-square corner."""
    return np.sqrt(np.einsum("vi,kij,vj->kv", HALF_SQUARE, metrics, HALF_SQUARE).max(axis=1))


def test_two_balls_with_their_own_metrics_cover_exactly():
    """Each ball holds exactly its half at its own metric's radius: covered at depth 1, each half
    by its own ball; the same radii fail when the metrics are swapped, and ball 1 a thousandth
    short leaves gaps on its side only."""
    centers = np.array([[0.5, 0.5], [1.5, 0.5]])
    needed = _exact_radii(METRICS) * (1 + 1e-12)
    exact = cover_balls(init([0, 0], [2, 1]), METRICS, centers, needed)
    assert exact.covered and exact.depth == 1 and exact.covered_fraction == 1.0
    left = exact.boxes[:, 1, 0] <= 1.0  # the boxes of x0 in [0, 1]
    assert exact.assignment[left].tolist() == [0, 0]  # [0, 1] x [0, 0.5] and [0, 1] x [0.5, 1]
    assert exact.assignment[~left].tolist() == [1, 1]
    assert "covered by 2 balls" in exact.message
    swapped = cover_balls(init([0, 0], [2, 1]), METRICS[::-1], centers, needed, max_depth=4)
    assert not swapped.covered  # the metrics are read per ball, not one for all
    short = cover_balls(
        init([0, 0], [2, 1]), METRICS, centers, needed * [1, 1 - 1e-3], max_depth=6, noun="start"
    )
    assert not short.covered and 0.99 < short.covered_fraction < 1.0
    assert np.all(short.uncovered_boxes[:, 0, 0] >= 1.0 - 1e-12)  # gaps only on ball 1's side
    assert "not covered" in short.message


def test_constant_metric_is_the_same_code_with_p_repeated():
    P = METRICS[0]
    centers, radii = np.array([[0.5, 0.5], [1.5, 0.5]]), np.array([0.9, 0.7])
    constant = cover_init(init([0, 0], [2, 1]), SimpleNamespace(P=P), centers, radii)
    repeated = cover_balls(init([0, 0], [2, 1]), np.stack([P, P]), centers, radii)
    np.testing.assert_array_equal(constant.boxes, repeated.boxes)
    np.testing.assert_array_equal(constant.uncovered_boxes, repeated.uncovered_boxes)
    assert constant.covered_fraction == repeated.covered_fraction


def test_metrics_of_the_wrong_shape():
    with pytest.raises(ValueError, match=r"metrics of shape \(3, 2, 2\) for 2 balls"):
        cover_balls(init([0, 0], [1, 1]), np.stack([np.eye(2)] * 3), [[0, 0], [1, 1]], [1, 1])


def three_d_case():
    """Init [0,1]^3 in (x0, x2, x4) of a 5-state system; x1 = 0.3 and x3 = -1 fixed."""
    lower, upper = [0, 0.3, 0, -1, 0], [1, 0.3, 1, -1, 1]
    rng = np.random.default_rng(0)
    M = rng.normal(size=(5, 5))
    P = M @ M.T + 5 * np.eye(5)
    octants = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    centers = np.zeros((8, 5))
    centers[:, [0, 2, 4]] = 0.25 + 0.5 * octants
    centers[:, 1], centers[:, 3] = 0.3, -1.0
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) * 0.25
    e = np.zeros((8, 5))
    e[:, [0, 2, 4]] = corners
    needed = np.sqrt(np.einsum("vi,ij,vj->v", e, P, e).max())
    return init(lower, upper), SimpleNamespace(P=P), centers, np.full(8, needed * (1 + 1e-9))


def test_three_d_init_covered_by_eight_octant_balls():
    scenario, metric, centers, radii = three_d_case()
    result = cover_init(scenario, metric, centers, radii)
    assert result.covered and result.free == (0, 2, 4) and result.covered_fraction == 1.0
    assert len(set(result.assignment.tolist())) == 8
    np.testing.assert_array_equal(result.boxes[:, :, 1], 0.3)  # fixed states stay fixed


def test_three_d_init_with_one_ball_too_small():
    scenario, metric, centers, radii = three_d_case()
    radii[7] *= 0.8  # the octant at (1, 1, 1)
    result = cover_init(scenario, metric, centers, radii, max_depth=5)
    assert not result.covered and 0.8 < result.covered_fraction < 1.0
    gap = result.largest_gap()
    assert np.all(gap[[0, 2, 4]] > 0.5)  # the gap is in that octant
    assert "x0 in [" in result.message


def test_point_init():
    scenario = init([1.0, 2.0], [1.0, 2.0])
    assert cover_init(scenario, METRIC, [[1.0, 2.5]], [0.6]).covered
    assert not cover_init(scenario, METRIC, [[1.0, 2.5]], [0.4]).covered


def test_bad_shapes():
    with pytest.raises(ValueError, match="2 centers but 1 radii"):
        cover_init(init([0, 0], [1, 1]), METRIC, [[0, 0], [1, 1]], [1.0])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_lookup_table_is_sound(seed):
    """Every point of a covered box lies in the ball the table assigns to it."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(2, 2))
    P = M @ M.T + 0.5 * np.eye(2)
    centers = rng.uniform(0, 1, size=(5, 2))
    radii = rng.uniform(0.2, 1.0, size=5)
    result = cover_init(init([0, 0], [1, 1]), SimpleNamespace(P=P), centers, radii, max_depth=5)
    x = rng.uniform(0, 1, size=(500, 2))
    ball = result.lookup(x)
    hit = ball >= 0
    e = x[hit] - centers[ball[hit]]
    assert np.all(np.einsum("bi,ij,bj->b", e, P, e) <= radii[ball[hit]] ** 2 + 1e-12)
    # The covered boxes' volume is the reported fraction; uncovered points are not in a box.
    volume = np.prod(result.boxes[:, 1] - result.boxes[:, 0], axis=1).sum()
    assert volume == pytest.approx(result.covered_fraction)
    assert abs(hit.mean() - result.covered_fraction) < 0.1  # 500 samples


def test_covering_radius_of_two_balls_is_the_half_square_diagonal():
    """Balls about (0.5, 0.5) and (1.5, 0.5) cover [0, 2] x [0, 1] from radius sqrt(0.5) on."""
    centers, exact = np.array([[0.5, 0.5], [1.5, 0.5]]), np.sqrt(0.5)
    found = covering_radius(init([0, 0], [2, 1]), METRIC, centers, upper=2.0, tolerance=0.01)
    assert found.covered and exact <= found.radius <= exact * 1.01
    assert cover_init(init([0, 0], [2, 1]), METRIC, centers, [found.radius] * 2).covered
    assert found.kept_radius(0.5) == found.radius and found.kept_radius(1.0) == 1.0
    too_small = covering_radius(init([0, 0], [2, 1]), METRIC, centers, upper=0.6)
    assert not too_small.covered and too_small.radius == np.inf
    assert too_small.kept_radius(0.5) == 0.5 and "do not cover" in too_small.message


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_lookup_table_is_sound_with_one_metric_per_ball(seed):
    """Every point of a covered box lies in the ball the table assigns to it, in that ball's
    own metric."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(5, 2, 2))
    P = M @ np.swapaxes(M, 1, 2) + 0.3 * np.eye(2)  # (5, 2, 2)
    centers = rng.uniform(0, 1, size=(5, 2))
    radii = rng.uniform(0.2, 1.0, size=5)
    result = cover_balls(init([0, 0], [1, 1]), P, centers, radii, max_depth=5)
    x = rng.uniform(0, 1, size=(500, 2))
    ball = result.lookup(x)
    hit = ball >= 0
    e = x[hit] - centers[ball[hit]]
    assert np.all(np.einsum("bi,bij,bj->b", e, P[ball[hit]], e) <= radii[ball[hit]] ** 2 + 1e-12)
    assert abs(hit.mean() - result.covered_fraction) < 0.1  # 500 samples


def test_one_metric_per_ball():
    """A funnel's balls each have their own ``P_i[0]`` (``subdivide`` with ``P (k, n, n)``).
    The box [-1, 3] x [-0.1, 0.1]: a ball at (0, 0) long in x (``diag(1, 100)``, radius 1.5:
    its corner (1, 0.1) at norm sqrt 2) and one at (2, 0) in ``diag(1, 100)`` cover it; the
    same two balls in one metric ``diag(100, 1)`` (long in y) do not. ``P`` repeated is the
    constant case: the same answer as ``P (n, n)``."""
    from pipeline.numerics.verify.cover import subdivide

    lower, upper = np.array([-1.0, -0.1]), np.array([3.0, 0.1])
    centres, radii = np.array([[0.0, 0.0], [2.0, 0.0]]), np.array([1.5, 1.5])
    long_x, long_y = np.diag([1.0, 100.0]), np.diag([100.0, 1.0])
    assert subdivide(np.stack([long_x, long_x]), lower, upper, centres, radii).covered
    mixed = subdivide(np.stack([long_x, long_y]), lower, upper, centres, radii)
    assert not mixed.covered and 0.25 < mixed.fraction < 0.75  # the second ball is thin in x
    for P in (long_x, long_y):
        one, repeated = (subdivide(M, lower, upper, centres, radii) for M in (P, np.stack([P, P])))
        assert one.covered == repeated.covered and one.fraction == repeated.fraction
