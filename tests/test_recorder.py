"""The demonstration recorder (issue 8), headless: scripted keys and a fake joystick.

The window runs on SDL's dummy video driver; tests post pygame events (key presses, joystick
axis motion) and advance the recorder with a scripted clock. The pure parts (mapping, Recorder,
saving) need no pygame. To refresh the README's screenshot:
``RECORDER_SCREENSHOT=docs/recorder.png .venv/bin/pytest tests/test_recorder.py -k screenshot``.
"""

from __future__ import annotations

import dataclasses
import os

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # before pygame is imported anywhere
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import yaml  # noqa: E402

from pipeline.demonstrations.recorder.config import load_recorder_config  # noqa: E402
from pipeline.demonstrations.recorder.flight import FlightStatus, Recorder, suggested_start  # noqa: E402
from pipeline.demonstrations.recorder.save import save_flight, with_demo_entry  # noqa: E402
from pipeline.io.artifacts import save_result  # noqa: E402
from pipeline.io.errors import ScenarioError, UserError  # noqa: E402
from pipeline.model.scenario import SCENARIOS_ROOT, load_scenario  # noqa: E402
from pipeline.model.simulate import simulate  # noqa: E402
from pipeline.runtime.cli import main  # noqa: E402
from pipeline.runtime.registry import RESULT_TYPES  # noqa: E402

QUADROTOR = SCENARIOS_ROOT / "quadrotor_hill_flythrough"

# A point flown by its velocity: right/D = +2 m/s in X, up/W = +2 m/s in Y (default mapping).
SLIDER_YAML = """\
# A point that moves at the commanded velocity: the recorder's test scenario.
name: slider
states: [X, Y]
inputs: [vX, vY]
dynamics:
  X: vX
  Y: vY
position: [X, Y]
sampling_time: 0.1
input_bounds:
  vX: [-2.0, 2.0]
  vY: [-2.0, 2.0]
unsafe:
  wall: [[0, 2], [10, 2], [10, 3], [0, 3]]
goal:
  polygon: [[6, -1], [8, -1], [8, 1], [6, 1]]
init:
  X: [0.0, 1.0]
  Y: [-0.5, 0.5]
clearance: 0.5
operating_region: {}
feedback:
  reference_state: [0, 0]
  reference_input: [0, 0]
  state_weights: [1, 1]
  input_weights: [1, 1]
  rate: 0.5

demos: []  # recorded flights are listed here
"""
SLIDER_X0 = np.array([0.5, 0.0])


@pytest.fixture
def slider(tmp_path: Path) -> Path:
    folder = tmp_path / "slider"
    (folder / "demos").mkdir(parents=True)
    (folder / "scenario.yaml").write_text(SLIDER_YAML)
    return folder / "scenario.yaml"


@pytest.fixture
def quadrotor(tmp_path: Path) -> Path:
    """A copy of the shipped quadrotor_hill_flythrough folder (saving writes into it)."""
    shutil.copytree(QUADROTOR, tmp_path / "quadrotor_hill_flythrough")
    return tmp_path / "quadrotor_hill_flythrough" / "scenario.yaml"


@pytest.fixture(scope="module")
def pg():
    """pygame with a (dummy) display; the window tests skip cleanly without pygame."""
    pygame = pytest.importorskip("pygame")
    from pipeline.demonstrations.recorder import app

    app.start_pygame()
    yield pygame
    pygame.quit()


def recorded_files(scenario_path: Path) -> list[Path]:
    return sorted((scenario_path.parent / "demos").glob("recorded_*.csv"))


# --- the mapping -----------------------------------------------------------------------------


def test_quadrotor_mapping_centre_dead_zone_ends_and_keys() -> None:
    config = load_recorder_config(load_scenario(QUADROTOR, check_demos=False))
    assert config.angle_index == 2  # theta
    np.testing.assert_allclose(config.inputs_from({}, ()), [9.81, 0.0])  # hover at rest
    np.testing.assert_allclose(config.inputs_from({1: -0.07, 3: 0.07}, ()), [9.81, 0.0])
    np.testing.assert_allclose(config.inputs_from({1: -1.0, 3: 1.0}, ()), [14.9, -5.0])
    np.testing.assert_allclose(config.inputs_from({1: 1.0, 3: -1.0}, ()), [0.0, 5.0])
    np.testing.assert_allclose(config.inputs_from({}, {"w", "left"}), [12.355, 2.0])
    np.testing.assert_allclose(config.inputs_from({}, {"s", "d"}), [4.905, -2.0])
    for u1, u2 in np.random.default_rng(0).uniform([0.0, -5.0], [14.9, 5.0], (50, 2)):
        axes = {1: config.axis_value(0, u1), 3: config.axis_value(1, u2)}
        np.testing.assert_allclose(config.inputs_from(axes, ()), [u1, u2], atol=1e-12)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("inputs: {thrust: {axis: 1}}\n", "unknown input 'thrust'"),
        ("inputs: {u1: {range: [-1, 14.9]}}\n", "stick range outside the input bounds"),
        ("angle_state: phi\n", "angle_state: unknown state; found 'phi'"),
        ("dead_zone: 1.5\n", "dead_zone: invalid recorder setting; found 1.5"),
    ],
)
def test_bad_recorder_file_names_file_field_and_value(
    quadrotor: Path, text: str, message: str
) -> None:
    (quadrotor.parent / "recorder.yaml").write_text(text)
    with pytest.raises(ScenarioError, match="recorder.yaml") as error:
        load_recorder_config(load_scenario(quadrotor, check_demos=False))
    assert message in str(error.value)


# --- the flight, without a window ------------------------------------------------------------


def test_recorder_ends_on_unsafe_and_goal_and_matches_simulate(slider: Path) -> None:
    scenario = load_scenario(slider)
    crash = Recorder(scenario, SLIDER_X0)
    while crash.step(np.array([0.0, 2.0])) is FlightStatus.FLYING:
        pass
    assert crash.status is FlightStatus.HIT_UNSAFE and "'wall'" in crash.message
    assert crash.end_time <= crash.t
    with pytest.raises(RuntimeError, match="has ended"):
        crash.step(np.zeros(2))
    flight = Recorder(scenario, SLIDER_X0)
    while flight.step(np.array([2.0, 0.1234567])) is FlightStatus.FLYING:
        pass
    assert flight.status.valid and flight.N == 28  # X: 0.5 + 0.2 k >= 6
    result = flight.flight()
    np.testing.assert_array_equal(result.us[:, 1], 0.123457)  # the CSV's 6 decimals
    replay = simulate(scenario.dynamics, result.x0, result.us, scenario.Ts)
    np.testing.assert_array_equal(replay.xs, result.xs)
    np.testing.assert_array_equal(replay.dense_xs, result.dense_xs)


def test_recorder_clips_to_bounds_and_times_out(slider: Path) -> None:
    scenario = load_scenario(slider)
    recorder = Recorder(scenario, SLIDER_X0, max_duration=0.5)
    recorder.step(np.array([-7.0, 0.0]))
    np.testing.assert_array_equal(recorder.us[0], [-2.0, 0.0])
    while recorder.step(np.zeros(2)) is FlightStatus.FLYING:
        pass
    assert recorder.status is FlightStatus.TIMED_OUT and recorder.N == 5


@pytest.mark.parametrize(
    ("x0", "message"),
    [
        ([0.5], "start state has 1 values; expected 2 values (X, Y)"),
        ([0.5, 0.9], "start state outside Init in 'Y'; found 0.9; expected a value in [-0.5, 0.5]"),
        ([np.nan, 0.0], "start state outside Init in 'X'"),
    ],
)
def test_bad_start_state(slider: Path, x0: list[float], message: str) -> None:
    with pytest.raises(UserError) as error:
        Recorder(load_scenario(slider), np.array(x0))
    assert message in str(error.value)


def test_suggested_start_is_the_largest_uncovered_box(slider: Path, tmp_path: Path) -> None:
    from stages.coverage import CoverageResult

    scenario = load_scenario(slider)
    x0, reason = suggested_start(scenario, tmp_path / "reports", RESULT_TYPES)
    np.testing.assert_array_equal(x0, [0.5, 0.0])
    assert "no coverage result" in reason
    boxes = np.array([[[0.0, -0.5], [0.25, -0.25]], [[0.5, 0.0], [1.0, 0.5]]])
    coverage = CoverageResult(
        covered=False,
        covered_fraction=0.6,
        boxes=np.zeros((0, 2, 2)),
        assignment=np.zeros(0, dtype=int),
        uncovered_boxes=boxes,
        free=(0, 1),
        depth=2,
        success=True,
        message="2 boxes uncovered",
    )
    save_result(tmp_path / "reports" / "artifacts" / "coverage_optimized", "k", coverage)
    x0, reason = suggested_start(scenario, tmp_path / "reports", RESULT_TYPES)
    np.testing.assert_array_equal(x0, [0.75, 0.25])
    assert "uncovered" in reason


# --- saving ----------------------------------------------------------------------------------

ENTRY = {"file": "demos/recorded_01.csv", "x0": [1.0, 2.0]}


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "name: a  # kept\ndemos:  # the list\n  - {file: d1.csv, x0: [0.0]}\n# tail\n",
            "name: a  # kept\ndemos:  # the list\n  - {file: d1.csv, x0: [0.0]}\n"
            "  - {file: demos/recorded_01.csv, x0: [1.0, 2.0]}  # c\n# tail\n",
        ),
        (
            "demos:\n- file: d1.csv\n  x0: [0.0]\n\nstates: [X]\n",
            "demos:\n- file: d1.csv\n  x0: [0.0]\n"
            "- {file: demos/recorded_01.csv, x0: [1.0, 2.0]}  # c\n\nstates: [X]\n",
        ),
        (
            "demos: []  # none yet\n",
            "demos:   # none yet\n  - {file: demos/recorded_01.csv, x0: [1.0, 2.0]}  # c\n",
        ),
        ("name: a", "name: a\ndemos:\n  - {file: demos/recorded_01.csv, x0: [1.0, 2.0]}  # c\n"),
    ],
)
def test_demo_entry_is_added_keeping_comments(text: str, expected: str) -> None:
    new = with_demo_entry(text, ENTRY["file"], ENTRY["x0"], "c")
    assert new == expected
    assert yaml.safe_load(new)["demos"][-1] == ENTRY


def test_flow_style_demo_list_is_refused() -> None:
    with pytest.raises(UserError, match="flow style"):
        with_demo_entry("demos: [{file: a.csv, x0: [0]}]\n", ENTRY["file"], ENTRY["x0"])


def test_failed_validation_restores_the_scenario_and_removes_the_csv(slider: Path) -> None:
    scenario = load_scenario(slider)
    recorder = Recorder(scenario, SLIDER_X0)
    recorder.step(np.array([2.0, 0.0]))
    fake = dataclasses.replace(recorder.flight(), status=FlightStatus.REACHED_GOAL)
    before = slider.read_bytes()
    with pytest.raises(ScenarioError, match="does not end in Goal"):
        save_flight(scenario, fake, "keyboard")
    assert slider.read_bytes() == before
    assert recorded_files(slider) == []
    with pytest.raises(ValueError, match="only flights that reached Goal"):
        save_flight(scenario, recorder.flight(), "keyboard")


# --- the window: scripted keyboard and a fake joystick ---------------------------------------


def post_key(pygame, name: str, down: bool = True) -> None:
    kind = pygame.KEYDOWN if down else pygame.KEYUP
    code = pygame.key.key_code(name)
    pygame.event.post(pygame.event.Event(kind, key=code, mod=0, unicode="", scancode=0))


def post_axis(pygame, axis: int, value: float) -> None:
    event = pygame.event.Event(pygame.JOYAXISMOTION, instance_id=0, joy=0, axis=axis, value=value)
    pygame.event.post(event)


def make_app(pygame, path: Path, x0=None):  # type: ignore[no-untyped-def]
    from pipeline.demonstrations.recorder.app import RecorderApp

    scenario = load_scenario(path, check_demos=False)
    config = load_recorder_config(scenario)
    pygame.event.clear()
    start = x0 if x0 is not None else scenario.demos[0].x0
    return RecorderApp(scenario, config, start, "test")


def fly(pygame, app, before_sample=lambda k: None, start: float = 0.0) -> int:  # type: ignore[no-untyped-def]
    """Start the countdown at ``start``, then call ``before_sample(k)`` and update at the
    middle of every sample interval until the flight ends. Returns the samples flown."""
    from pipeline.demonstrations.recorder.app import Phase

    post_key(pygame, "space")
    app.update(start)
    assert app.phase is Phase.COUNTDOWN
    t0, Ts = start + app.config.countdown, app.scenario.Ts
    k = 0
    while app.phase is not Phase.ENDED:
        before_sample(k)
        app.update(t0 + (k + 0.5) * Ts)
        k += 1
        assert k < 2000, "the scripted flight did not end"
    return app.recorder.N


def test_keyboard_crash_is_not_saved_then_retry_reaches_goal_and_validates(
    pg, slider: Path
) -> None:
    app = make_app(pg, slider, SLIDER_X0)
    before = slider.read_text()
    fly(pg, app, lambda k: post_key(pg, "w") if k == 0 else None)  # straight up into the wall
    assert app.recorder.status is FlightStatus.HIT_UNSAFE
    assert app.saved == [] and recorded_files(slider) == [] and slider.read_text() == before
    post_key(pg, "w", down=False)
    n = fly(pg, app, lambda k: post_key(pg, "right") if k == 0 else None, start=100.0)  # retry
    assert app.recorder.status is FlightStatus.REACHED_GOAL and n == 28
    assert app.saved == [slider.parent / "demos" / "recorded_01.csv"]
    scenario = load_scenario(slider, check_demos=True)
    (demo,) = scenario.demos
    assert demo.name == "recorded_01" and demo.N == 28
    np.testing.assert_array_equal(demo.x0, SLIDER_X0)
    header = demo.file.read_text().split("\nt,")[0]
    assert "HUMAN demonstration" in header and "input device: keyboard" in header
    assert slider.read_text().startswith(before.split("demos:")[0])  # everything above kept
    np.testing.assert_array_equal(
        simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts).final_state, app.recorder.x
    )


def test_quadrotor_keyboard_sample_is_held(pg, quadrotor: Path) -> None:
    app = make_app(pg, quadrotor)
    post_key(pg, "space")
    app.update(0.0)
    post_key(pg, "w")
    post_key(pg, "left")
    app.update(3.05)  # the countdown ends: u[0] is read now, held on [0, Ts)
    post_key(pg, "w", down=False)
    app.update(3.09)  # within the same sample: nothing new is read
    assert app.recorder.N == 1
    np.testing.assert_allclose(app.recorder.us[0], [12.355, 2.0])
    app.update(3.11)
    np.testing.assert_allclose(app.recorder.us[1], [9.81, 2.0])
    assert app.stick.device() == "keyboard"
    post_key(pg, "escape")
    app.update(3.2)
    assert not app.running and app.saved == []


def test_fake_joystick_flies_a_shipped_demo_into_goal_and_it_is_saved(
    pg, quadrotor: Path, tmp_path: Path
) -> None:
    """The stick replays demo_01's inputs: the recorder's sampling, hold, RK4 and Goal test are
    the pipeline's, so the saved demo is demo_01 up to where the recorder saw Goal."""
    app = make_app(pg, quadrotor)
    config, us = app.config, app.scenario.demos[0].us
    screenshot = Path(os.environ.get("RECORDER_SCREENSHOT", tmp_path / "recorder.png"))

    def stick(k: int) -> None:
        for i, mapping in enumerate(config.inputs):
            post_axis(pg, mapping.axis, config.axis_value(i, us[k, i]))
        if k == 76:  # the window still shows the frame drawn over the hill, at t = 7.55 s
            pg.image.save(app.surface, screenshot)

    N = fly(pg, app, stick)
    assert app.recorder.status is FlightStatus.REACHED_GOAL and N == 136 < len(us)
    (saved,) = app.saved
    assert saved.name == "recorded_01.csv"
    scenario = load_scenario(quadrotor, check_demos=True)
    demo = scenario.demos[-1]
    assert demo.file == saved and len(scenario.demos) == 10
    np.testing.assert_array_equal(demo.us, us[:N])
    end = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts).final_state
    np.testing.assert_array_equal(end, app.recorder.x)
    assert "input device: joystick 0" in saved.read_text()
    lines = quadrotor.read_text().splitlines()
    # comments kept
    assert "# SYNTHETIC flights from pipeline/demonstrations/pilot.py" in lines[-11]
    assert lines[-1].startswith("  - {file: demos/recorded_01.csv, x0: [")
    assert "# HUMAN, recorded" in lines[-1] and lines[-1].endswith("with joystick 0")
    image = pg.image.load(str(screenshot))
    assert image.get_size() == app.scene.size


def test_click_inside_init_moves_the_start(pg, slider: Path) -> None:
    app = make_app(pg, slider, SLIDER_X0)
    pixel = app.scene.to_screen([0.2, -0.3])
    pg.event.post(pg.event.Event(pg.MOUSEBUTTONDOWN, button=1, pos=tuple(pixel.round())))
    app.update(0.0)
    np.testing.assert_allclose(app.x0, [0.2, -0.3], atol=0.5 / app.scene.scale + 1e-3)
    app.click(tuple(app.scene.to_screen([5.0, 0.0])))  # outside Init: ignored
    np.testing.assert_allclose(app.x0, [0.2, -0.3], atol=0.5 / app.scene.scale + 1e-3)


def test_replay_shows_a_demo_to_its_end(pg) -> None:
    from pipeline.demonstrations.recorder.app import ReplayApp

    scenario = load_scenario(QUADROTOR, check_demos=False)
    pg.event.clear()
    app = ReplayApp(scenario, load_recorder_config(scenario), scenario.demos[1])
    app.update(0.0)
    app.update(1e3)
    assert app.running and app.origin.startswith("SYNTHETIC demonstration")
    post_key(pg, "escape")
    app.update(1e3 + 0.1)
    assert not app.running


def test_cli_errors_exit_2(pg, quadrotor: Path, capsys) -> None:
    assert main(["record", str(quadrotor), "--x0", "1", "2"]) == 2
    assert "start state has 2 values" in capsys.readouterr().err
    assert main(["replay", str(quadrotor), "demo_99"]) == 2
    assert "no demo 'demo_99'" in capsys.readouterr().err
