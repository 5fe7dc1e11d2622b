"""``pipeline.numerics.funnel.cells``: Init cut into cells, each given to the nearest start (C1);
the hulls of the cells' corners together hold Init, and each start is asked for its own cells
only."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

from pipeline.numerics.funnel.cells import PAD, init_cells


def test_two_starts_split_a_square_in_halves():
    """Starts at the centres of the square's halves, g = 2: each owns the two cells of its half,
    so it is asked for the four corners of that half (pushed ``PAD`` away from it)."""
    starts = np.array([[0.25, 0.5], [0.75, 0.5]])
    left, right = init_cells(np.zeros(2), np.ones(2), starts, np.eye(2), divisions=2)
    expected = np.array([[-0.25, -0.5], [-0.25, 0.5], [0.25, -0.5], [0.25, 0.5]]) * (1 + PAD)
    for offsets in (left, right):
        order = np.lexsort(offsets.T[::-1])
        np.testing.assert_allclose(offsets[order], expected, rtol=1e-12)


def test_the_hulls_hold_init_and_a_fixed_state_stays_fixed():
    """Random starts in a box with one fixed state: every random point of Init lies in the hull
    of the corners its owner was asked for; the fixed state has zero offset."""
    rng = np.random.default_rng(3)
    lower, upper = np.array([0.0, -1.0, 2.0, 0.5]), np.array([2.0, 1.0, 2.0, 1.0])
    starts = rng.uniform(lower, upper, size=(5, 4))
    starts[:, 2] = 2.0
    M = np.diag([1.0, 4.0, 1.0, 9.0])
    cells = init_cells(lower, upper, starts, M)
    assert all(np.all(v[:, 2] == 0.0) for v in cells if len(v))
    free = [0, 1, 3]
    hulls = [Delaunay((starts[i] + v / (1 + PAD))[:, free]) if len(v) > 3 else None
             for i, v in enumerate(cells)]  # fmt: skip
    points = rng.uniform(lower, upper, size=(2000, 4))
    inside = np.zeros(len(points), dtype=bool)
    for hull in hulls:
        if hull is not None:
            inside |= hull.find_simplex(points[:, free], tol=1e-9) >= 0
    assert inside.all()


def test_a_grid_of_starts_is_asked_for_its_voronoi_boxes():
    """Three by three starts at the centres of a box's thirds (Init 2 x 1): by default each is
    asked for its own third of every side to within one cell, the middle ones too; with
    g = 4 the middle column owns two of the four cells, half of the 2 m side (1.5x a third)."""
    lower, upper = np.array([1.0, 2.0]), np.array([3.0, 3.0])
    centres = [
        lower + (np.array([i, j]) + 0.5) * (upper - lower) / 3 for j in range(3) for i in range(3)
    ]
    starts = np.array(centres)
    side = upper - lower
    for offsets in init_cells(lower, upper, starts, np.eye(2)):
        span = offsets.max(axis=0) - offsets.min(axis=0)
        assert np.all(span / (1 + PAD) <= side / 3 + side / 64 + 1e-12)
        assert np.all(span / (1 + PAD) >= side / 3 - side / 64 - 1e-12)
    coarse = init_cells(lower, upper, starts, np.eye(2), divisions=4)
    middle = coarse[1]  # the bottom row's middle start
    np.testing.assert_allclose((middle.max(axis=0) - middle.min(axis=0))[0] / (1 + PAD), 1.0)


def test_a_start_far_away_owns_nothing():
    starts = np.array([[0.5, 0.5], [10.0, 10.0]])
    near, far = init_cells(np.zeros(2), np.ones(2), starts, np.eye(2))
    assert len(near) == 4 and far.shape == (0, 2)  # the whole square: its four corners


def test_bad_shapes_and_divisions():
    with pytest.raises(ValueError, match=r"expected \(k, 2\) and \(2, 2\)"):
        init_cells(np.zeros(2), np.ones(2), np.zeros((1, 3)), np.eye(2))
    with pytest.raises(ValueError, match="divisions must be a whole number >= 1, got 0"):
        init_cells(np.zeros(2), np.ones(2), np.zeros((1, 2)), np.eye(2), divisions=0)


def test_one_free_state_asks_for_the_ends_of_the_owned_interval():
    """Init with one free state: each start is asked for the two ends of its cells' interval
    (Qhull needs two dimensions; this used to raise)."""
    cells = init_cells([0.0, 0.0], [1.0, 0.0], [[0.5, 0.0]], np.eye(2))
    np.testing.assert_allclose(np.sort(cells[0][:, 0]), np.array([-0.5, 0.5]) * (1 + PAD))
    assert np.all(cells[0][:, 1] == 0.0)


def test_a_start_at_a_single_point_init_asks_for_nothing():
    """Init is the start itself: no offset to hold (the funnel then holds the ball slice)."""
    cells = init_cells([1.0, 2.0], [1.0, 2.0], [[1.0, 2.0], [3.0, 2.0]], np.eye(2))
    assert [len(c) for c in cells] == [0, 0]


def test_many_hull_corners_fall_back_to_the_bounding_box():
    """A start owning a region whose hull has more than MAX_CORNERS vertices is asked for the
    2^D corners of its cells' bounding box, which hold the hull."""
    from pipeline.numerics.funnel.cells import MAX_CORNERS, _hull_corners

    angles = np.linspace(0, 2 * np.pi, 4 * MAX_CORNERS, endpoint=False)
    circle = np.c_[np.cos(angles), np.sin(angles)]  # every point a hull vertex
    corners = _hull_corners(circle)
    assert len(corners) == 4
    np.testing.assert_allclose(np.sort(corners, axis=0)[[0, -1]], [[-1, -1], [1, 1]], atol=1e-12)


def test_the_padding_covers_the_level_slack():
    """A funnel at level ``1 - LEVEL_SLACK`` holds a corner pushed ``PAD`` out when
    ``1 / (1 + PAD) <= 1 - LEVEL_SLACK``."""
    from pipeline.numerics.funnel.check import LEVEL_SLACK

    assert 1 / (1 + PAD) <= 1 - LEVEL_SLACK


def test_the_bisector_polytope_of_a_circle_is_the_octagon_around_it():
    """(C2) on points of the unit circle with the eight normals ``(cos, sin)(k pi / 4)``: each
    cut touches the circle, so the polytope is the regular octagon around it, vertices at radius
    ``1 / cos(pi / 8)`` half-way between the normals."""
    from pipeline.numerics.funnel.cells import MAX_CORNERS, _hull_corners

    angles = np.linspace(0, 2 * np.pi, 4 * MAX_CORNERS, endpoint=False)
    circle = np.c_[np.cos(angles), np.sin(angles)]
    k = np.arange(8) * np.pi / 4
    corners = _hull_corners(circle, np.c_[np.cos(k), np.sin(k)])
    assert len(corners) == 8
    np.testing.assert_allclose(np.hypot(*corners.T), 1 / np.cos(np.pi / 8), rtol=1e-12)
    phase = np.sort(np.mod(np.arctan2(corners[:, 1], corners[:, 0]), 2 * np.pi))
    np.testing.assert_allclose(phase, np.pi / 8 + k, atol=1e-12)


def test_five_free_states_ask_for_polytopes_that_hold_their_cells_and_reach_less_than_boxes():
    """Nine starts in a five-dimensional Init (the centre and eight corners with pitch and
    speeds coupled, as quadrotor_hill_gusty's demos): the fine cells' hulls have more than
    ``MAX_CORNERS`` vertices, so the starts are asked for (C2)'s polytopes. Every corner of every
    cell (C1) gives a start lies in that start's own request, and the eight corner starts'
    requests reach at most 0.8 as far in ``M`` as their bounding boxes."""
    from pipeline.numerics.funnel.cells import MAX_CORNERS

    lower = np.array([1.0, 2.0, -0.05, -0.2, -0.2, 0.0])
    upper = np.array([3.0, 3.0, 0.05, 0.2, 0.2, 0.0])
    middle, half = (lower + upper) / 2, (upper - lower) / 2
    signs = [(sx, sy, st, sx, sy, 0) for sx in (-1, 1) for sy in (-1, 1) for st in (-1, 1)]
    starts = np.array([middle] + [middle + np.array(s) * half * 2 / 3 for s in signs])
    starts[1:, 2:5] = middle[2:5] + np.array(signs)[:, 2:5] * half[2:5]  # pitch, speeds at ends
    M = np.diag([1.0, 2.0, 400.0, 10.0, 10.0, 1.0])
    g = 8  # the default for five free states: 8^5 = MAX_CELLS
    requests = init_cells(lower, upper, starts, M)
    np.testing.assert_array_equal(
        [len(v) for v in init_cells(lower, upper, starts, M, divisions=g)],
        [len(v) for v in requests],
    )
    assert all(len(v) <= MAX_CORNERS for v in requests)
    assert any(len(v) != 2**5 for v in requests)  # some polytopes, not only boxes
    free = [0, 1, 2, 3, 4]
    index = np.array(list(itertools.product(range(g), repeat=5)))  # (C1) on the cells again
    steps = (upper - lower)[free] / g
    centres = np.repeat(lower[None], len(index), axis=0)
    centres[:, free] = lower[free] + (index + 0.5) * steps
    e = centres[:, None, :] - starts[None]
    owner = np.argmin(np.einsum("cki,ij,ckj->ck", e, M, e), axis=1)
    unit = np.array(list(itertools.product((0, 1), repeat=5)))
    ratio = []
    for i, v in enumerate(requests):
        hull = ConvexHull(v[:, free] / (1 + PAD))  # facets a^T z + b <= 0 inside
        # each grid corner of the owned cells once (a corner shared by several cells is the
        # same point: checking it again cannot change the maximum below)
        grid = np.unique((index[owner == i][:, None, :] + unit[None]).reshape(-1, 5), axis=0)
        offsets = grid * steps + lower[free] - starts[i, free]
        assert (
            len(offsets)
            and np.max(offsets @ hull.equations[:, :-1].T + hull.equations[:, -1]) <= 1e-9
        )
        low, high = v.min(axis=0), v.max(axis=0)
        box = low + np.array(list(itertools.product((0, 1), repeat=6))) * (high - low)
        reach = np.sqrt(np.einsum("pi,ij,pj->p", v, M, v)).max()
        ratio.append(reach / np.sqrt(np.einsum("pi,ij,pj->p", box, M, box)).max())
    assert np.all(np.array(ratio[1:]) <= 0.8)  # each corner start: 0.71 of its box


def test_the_same_question_is_answered_once_and_the_answer_cannot_be_changed():
    """The funnel stages of a run ask for the same cells every round: the answer is kept, read
    only, and any change of Init, the starts or the metric asks again."""
    lower, upper = np.zeros(2), np.ones(2)
    starts = np.array([[0.25, 0.5], [0.75, 0.5]])
    first = init_cells(lower, upper, starts, np.eye(2))
    assert init_cells(lower.copy(), upper.copy(), starts.copy(), np.eye(2)) is first
    with pytest.raises(ValueError, match="read-only"):
        first[0][0, 0] = 1.0
    skewed = init_cells(lower, upper, starts, np.diag([1.0, 1e-3]))
    assert skewed is not first
    moved = init_cells(lower, upper, starts + [[0.1, 0.0], [0.0, 0.0]], np.eye(2))
    assert not np.array_equal(moved[0], first[0])
