"""The synthetic pilot and the demonstrations it ships (quadrotor_hill_flythrough, and every
scenario
with a ``pilot.py``)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.demonstrations.pilot import SYNTHETIC_FILE, fly, regenerate_demos
from pipeline.demonstrations.recorder.save import append_demo_entry
from pipeline.io.errors import UserError
from pipeline.model import geometry
from pipeline.model.scenario import SCENARIOS_ROOT, Scenario, available_scenarios, load_scenario
from pipeline.model.simulate import simulate
from pipeline.runtime.cli import main

SHIPPED = SCENARIOS_ROOT / "quadrotor_hill_flythrough"
FLOWN = [name for name in available_scenarios() if (SCENARIOS_ROOT / name / "pilot.py").is_file()]


def _flown_by_pilot(scenario: Scenario) -> list:
    """The pilot's demos (``demos/demo_NN.csv``); a user may have recorded more."""
    return [d for d in scenario.demos if SYNTHETIC_FILE.search(d.file.as_posix())]


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    """The shipped scenario; loading it simulates every demo (avoids Unsafe, ends in Goal)."""
    return load_scenario("quadrotor_hill_flythrough", check_demos=True)


def test_shipped_demos_start_spread_over_init(scenario: Scenario) -> None:
    demos = _flown_by_pilot(scenario)
    assert len(demos) >= 6
    starts = np.array([demo.x0 for demo in demos])
    assert np.all(starts >= scenario.init_lower) and np.all(starts <= scenario.init_upper)
    positions = scenario.positions(starts)
    assert len({tuple(p) for p in positions.tolist()}) == len(demos)
    width = scenario.positions(scenario.init_upper - scenario.init_lower)
    assert np.all(np.ptp(positions, axis=0) >= 0.5 * width)


def test_shipped_demos_are_synthetic_and_say_so(scenario: Scenario) -> None:
    for demo in _flown_by_pilot(scenario):
        header = demo.file.read_text().split("\nt,")[0]
        assert "SYNTHETIC" in header and "NOT by a human" in header
        assert "make demos" in header


def test_shipped_demos_are_suboptimal_and_one_passes_close(scenario: Scenario) -> None:
    closest = []
    for demo in _flown_by_pilot(scenario):
        assert np.all(demo.us >= scenario.input_lower) and np.all(demo.us <= scenario.input_upper)
        trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
        positions = scenario.positions(trajectory.dense_xs)
        closest.append(
            min(geometry.distance(positions, region).min() for region in scenario.unsafe.values())
        )
        assert trajectory.duration > 10.0  # a good flight takes 7-9 s
    closest = np.array(closest)
    assert np.all(closest > 0.0)
    assert np.any(closest < scenario.clearance)


def test_pilot_is_deterministic_for_a_seed(scenario: Scenario) -> None:
    x0 = scenario.demos[0].x0
    first, second = fly(scenario, x0, seed=1), fly(scenario, x0, seed=1)
    np.testing.assert_array_equal(first, second)
    np.testing.assert_array_equal(first, scenario.demos[0].us)
    assert not np.array_equal(first, fly(scenario, x0, seed=2))


@pytest.mark.parametrize("name", FLOWN)
def test_regenerate_reproduces_shipped_files_and_keeps_the_yaml(tmp_path: Path, name: str) -> None:
    shipped = SCENARIOS_ROOT / name
    copy = tmp_path / name
    shutil.copytree(shipped, copy)
    for csv in (copy / "demos").glob("demo_*.csv"):
        csv.unlink()
    yaml_path = copy / "scenario.yaml"
    shipped_yaml = (shipped / "scenario.yaml").read_text()
    block = re.search(r"^demos:", shipped_yaml, flags=re.MULTILINE)
    assert block is not None
    recorded = [  # flights a user recorded into the shipped scenario stay listed
        line
        for line in shipped_yaml[block.start() :].splitlines(keepends=True)
        if line.lstrip().startswith("- {") and not SYNTHETIC_FILE.search(line)
    ]
    demos_block = "demos:\n" + "".join(recorded) if recorded else "demos: []  # to be flown\n"
    yaml_path.write_text(shipped_yaml[: block.start()] + demos_block)

    demos = regenerate_demos(yaml_path)

    assert yaml_path.read_bytes() == (shipped / "scenario.yaml").read_bytes()
    count = len(_flown_by_pilot(load_scenario(name, check_demos=False)))
    assert [demo.file.name for demo in demos] == [f"demo_{i:02d}.csv" for i in range(1, count + 1)]
    for demo in demos:
        assert demo.file.read_bytes() == (shipped / "demos" / demo.file.name).read_bytes()


@pytest.mark.parametrize("name", FLOWN)
def test_demos_start_on_every_free_direction_of_init(name: str) -> None:
    """The pilot's starts spread over each non-degenerate Init interval (x, y and heading for
    unicycle_slalom), so that coverage has a chance in every dimension."""
    scenario = load_scenario(name, check_demos=False)
    starts = np.array([demo.x0 for demo in scenario.demos])
    width = scenario.init_upper - scenario.init_lower
    free = width > 0
    assert np.all(np.ptp(starts, axis=0)[free] >= 0.4 * width[free])


def test_pilot_refuses_a_scenario_without_configuration(tmp_path: Path) -> None:
    copy = tmp_path / "other"
    shutil.copytree(SHIPPED, copy)
    (copy / "pilot.py").unlink()
    yaml_path = copy / "scenario.yaml"
    yaml_path.write_text(
        yaml_path.read_text().replace("name: quadrotor_hill_flythrough", "name: other_hill", 1)
    )
    with pytest.raises(UserError, match="no configuration for scenario 'other_hill'"):
        regenerate_demos(yaml_path)


def test_a_field_after_the_demos_block_is_not_dropped(tmp_path: Path) -> None:
    """make demos rewrites ``demos:`` to the end of the file: a field after it would be lost,
    so the run stops first (exit 2 through the CLI), naming the line, and changes nothing."""
    copy = tmp_path / "quadrotor_hill_flythrough"
    shutil.copytree(SHIPPED, copy)
    yaml_path = copy / "scenario.yaml"
    text = yaml_path.read_text() + "uncertainty:\n  disturbance: {vX: 0.05}\n"
    yaml_path.write_text(text)
    line = text.count("\n") - 1
    with pytest.raises(UserError, match=f"line {line} follows the 'demos:' block.*'uncertainty:'"):
        regenerate_demos(yaml_path)
    assert yaml_path.read_text() == text


def test_cli_demos_unknown_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demos", "nope"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: unknown scenario 'nope'")
    assert error.count("\n") == 1


@pytest.mark.parametrize(
    ("pilot_text", "message"),
    [
        ("X = 1\n", "pilot file does not define CONFIG and steering"),
        (
            "CONFIG = {'waypoints': ()}\ndef steering(scenario):\n    return None\n",
            "found 'CONFIG: dict, steering: function'",
        ),
    ],
)
def test_a_pilot_file_without_config_is_refused(tmp_path: Path, pilot_text, message) -> None:
    copy = tmp_path / "quadrotor_hill_flythrough"
    shutil.copytree(SHIPPED, copy)
    (copy / "pilot.py").write_text(pilot_text)
    with pytest.raises(UserError, match=message):
        regenerate_demos(copy / "scenario.yaml")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("stick_step=(0.5, 0.5)", "stick_step has 1 entries, expected 2 (one per input)"),
        ('grid=(("Y", 3), ("X", 3))', "grid names unknown state 'Z'"),
        ("variant_waypoint=1", "variant_waypoint 9 is not a waypoint index"),
    ],
)
def test_a_pilot_config_that_does_not_fit_is_refused(tmp_path: Path, change, message) -> None:
    copy = tmp_path / "quadrotor_hill_flythrough"
    shutil.copytree(SHIPPED, copy)
    broken = {
        "stick_step=(0.5, 0.5)": "stick_step=(0.5,)",
        'grid=(("Y", 3), ("X", 3))': 'grid=(("Z", 3), ("X", 3))',
        "variant_waypoint=1": "variant_waypoint=9",
    }[change]
    text = (copy / "pilot.py").read_text()
    assert change in text
    (copy / "pilot.py").write_text(text.replace(change, broken))
    with pytest.raises(UserError, match=re.escape(message)):
        fly(load_scenario(copy / "scenario.yaml", check_demos=False), np.zeros(6), seed=1)


def test_regenerating_keeps_the_flights_the_pilot_did_not_fly(tmp_path: Path) -> None:
    copy = tmp_path / "double_integrator"
    shutil.copytree(SCENARIOS_ROOT / "double_integrator", copy)
    yaml_path = copy / "scenario.yaml"
    first = load_scenario(yaml_path, check_demos=False).demos[0]
    for name in ("recorded_01.csv", "recorded_02.csv"):
        shutil.copyfile(first.file, copy / "demos" / name)
    append_demo_entry(yaml_path, "demos/recorded_01.csv", first.x0, comment="flown by Ada")
    values = ", ".join(str(float(v)) for v in first.x0)
    with yaml_path.open("a") as text:  # a block-style entry, as someone may write by hand
        text.write(f"  - file: demos/recorded_02.csv\n    x0: [{values}]\n")
    before = load_scenario(yaml_path, check_demos=False).demos

    regenerate_demos(yaml_path)

    after = load_scenario(yaml_path, check_demos=True).demos
    assert [d.name for d in after] == [d.name for d in before]
    for old, new in zip(before, after, strict=True):
        np.testing.assert_array_equal(old.x0, new.x0)
    assert "recorded_01.csv" in yaml_path.read_text().split("# flown by Ada")[0].splitlines()[-1]
