"""The recorder's view and HUD: the part of the scene it fits, the clearance band and ModGoal it
draws, speed and attitude, inputs labelled with their units. The view and the HUD's text are
plain functions (``pipeline.demonstrations.recorder.view``); the drawing is checked pixel by
pixel on SDL's dummy (headless) video driver."""

from __future__ import annotations

import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # before pygame is imported anywhere
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import dataclasses  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from pipeline.demonstrations.recorder.config import load_recorder_config  # noqa: E402
from pipeline.demonstrations.recorder.view import (  # noqa: E402
    demo_paths,
    hud_lines,
    input_rows,
    view_box,
)
from pipeline.model import geometry  # noqa: E402
from pipeline.model.scenario import load_scenario  # noqa: E402


@pytest.fixture(scope="module")
def quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


def corners(shape) -> np.ndarray:  # type: ignore[no-untyped-def]
    return np.reshape(shape.bounds, (2, 2))


def test_the_view_fits_init_goal_and_the_flights_not_the_whole_polygons(quadrotor):
    paths = demo_paths(quadrotor)
    view = view_box(quadrotor, paths)
    i, j = quadrotor.position_index
    assert view.contains(quadrotor.init_lower[[i, j]]) and view.contains(
        quadrotor.init_upper[[i, j]]
    )
    assert view.contains(corners(quadrotor.goal)).all()
    assert all(view.contains(path).all() for path in paths)
    # the corridor: the ground (the hill's foot, y = 0) and the ceiling's underside (y = 8) with
    # a margin of Unsafe beyond, not the polygons' far sides (y = -5 and y = 13)
    assert -5 < view.lower[1] < 0 and 8 < view.upper[1] < 13
    # horizontally the flights, not the 40 m polygons (x from -5 to 35)
    assert -5 < view.lower[0] <= 1.0 - quadrotor.clearance
    assert 21.0 + quadrotor.clearance <= view.upper[0] < 35 - 5
    assert view.span[0] < 0.65 * 40
    # before any flight is recorded the corridor is found from Init and Goal alone
    bare = view_box(quadrotor)
    assert bare.upper[1] > 8 and bare.lower[1] < 0 and bare.span[0] <= view.span[0]


def test_an_obstacle_in_the_way_is_shown_whole():
    scenario = load_scenario("double_integrator", check_demos=False)
    view = view_box(scenario)  # Init and Goal only: the block lies between them
    assert view.contains(corners(scenario.unsafe["block"])).all()
    assert view.upper[0] < 11 + 2 and view.lower[0] > -2  # and no more than that


def test_the_hud_gives_speed_and_attitude_in_their_units(quadrotor):
    x = np.array([10.0, 5.0, 0.2, 3.0, 4.0, 0.0])  # vX = 3, vY = 4 m/s; theta = 0.2 rad
    assert hud_lines(quadrotor, x, np.array([9.81, 0.0]), 2) == [
        "speed 5.00 m/s",
        "theta (pitch) +0.20 rad (+11.5 deg)",
    ]
    assert hud_lines(quadrotor, x, None, None) == ["speed 5.00 m/s"]  # no angle state
    bare = dataclasses.replace(quadrotor, units={}, labels={})
    assert hud_lines(bare, x, None, 2) == ["speed 5.00 position units/s", "theta +0.20"]


def test_inputs_are_labelled_with_their_names_and_units(quadrotor):
    assert input_rows(quadrotor, np.array([9.81, -2.0])) == [
        ("u1 (thrust) [N]", "+9.81 N   in [0, 14.9]"),
        ("u2 (pitch acceleration) [rad/s^2]", "-2.00 rad/s^2   in [-10, 10]"),
    ]
    assert [value for _, value in input_rows(quadrotor, None)] == [
        "-   in [0, 14.9]",
        "-   in [-10, 10]",
    ]


@pytest.fixture(scope="module")
def scene(quadrotor):
    """The quadrotor's recorder scene on a dummy display."""
    pygame = pytest.importorskip("pygame")
    from pipeline.demonstrations.recorder import app
    from pipeline.demonstrations.recorder.draw import Scene

    app.start_pygame()
    yield Scene(quadrotor, load_recorder_config(quadrotor)), pygame
    pygame.quit()


def colour_at(surface, scene, point) -> tuple[int, int, int]:  # type: ignore[no-untyped-def]
    u, v = scene.to_screen(point)
    return tuple(surface.get_at((int(round(u)), int(round(v)))))[:3]


def test_the_map_draws_the_clearance_band_and_modgoal(scene, quadrotor):
    from pipeline.demonstrations.recorder import draw

    scene, pygame = scene
    assert np.array_equal(scene.view.lower, view_box(quadrotor, demo_paths(quadrotor)).lower)
    surface = pygame.Surface(scene.size)
    x0 = quadrotor.demos[0].x0
    scene.draw(surface, x0, np.array([9.81, 0.0]), x0[None, :], 0.0)
    hill, d = quadrotor.unsafe["hill"], quadrotor.clearance
    in_band, in_hill, free = (10.5, 5.2), (7.0, 1.0), (3.5, 5.5)
    assert 0 < float(geometry.distance(np.array(in_band), hill)) < d  # the cases are what
    assert bool(geometry.contains(hill, np.array(in_hill)))  # they say
    assert float(min(geometry.distance(np.array(free), u) for u in quadrotor.unsafe.values())) > d
    assert colour_at(surface, scene, in_band) == draw.BAND
    assert colour_at(surface, scene, in_hill) == draw.UNSAFE
    assert colour_at(surface, scene, free) == draw.BACKGROUND
    # ModGoal (Goal shrunk by d: [18, 20] x [2, 3]) is dashed along its edges
    modgoal = corners(geometry.shrink(quadrotor.goal, d))
    np.testing.assert_allclose(modgoal, [[18, 2], [20, 3]], atol=1e-9)
    top = [colour_at(surface, scene, (x, 3.0)) for x in np.linspace(18.1, 19.9, 40)]
    assert 0.3 < top.count(draw.MODGOAL) / len(top) < 0.9  # dashes and gaps
    assert colour_at(surface, scene, (18.5, 2.2)) == draw.GOAL  # inside: Goal's fill
    rows = [words for _, words in scene.legend_rows()]
    assert "clearance band: within d = 1 m of Unsafe" in rows
    assert "ModGoal: Goal shrunk by d (dashed)" in rows


def test_a_vehicle_off_the_map_is_marked_on_its_edge(scene, quadrotor):
    from pipeline.demonstrations.recorder import draw

    scene, pygame = scene
    surface = pygame.Surface(scene.size)
    away = np.array([60.0, 5.0, 0.0, 0.0, 0.0, 0.0])  # far right of the view
    scene.draw(surface, away, None, away[None, :], 0.0)
    right = int(scene.map_size[0]) - 1
    column = [
        tuple(surface.get_at((u, v)))[:3]
        for u in range(right - 25, right)
        for v in range(
            int(scene.to_screen((0.0, 5.0))[1]) - 12, int(scene.to_screen((0.0, 5.0))[1]) + 12
        )
    ]
    assert draw.WARN in column
