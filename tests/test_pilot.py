"""The synthetic pilot and the demonstrations it ships for quadrotor_hill."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline import geometry
from pipeline.cli import main
from pipeline.errors import UserError
from pipeline.pilot import fly, regenerate_demos
from pipeline.scenario import SCENARIOS_ROOT, Scenario, load_scenario
from pipeline.simulate import simulate

SHIPPED = SCENARIOS_ROOT / "quadrotor_hill"


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    """The shipped scenario; loading it simulates every demo (avoids Unsafe, ends in Goal)."""
    return load_scenario("quadrotor_hill", check_demos=True)


def test_shipped_demos_start_spread_over_init(scenario: Scenario) -> None:
    assert len(scenario.demos) >= 6
    starts = np.array([demo.x0 for demo in scenario.demos])
    assert np.all(starts >= scenario.init_lower) and np.all(starts <= scenario.init_upper)
    positions = scenario.positions(starts)
    assert len({tuple(p) for p in positions.tolist()}) == len(scenario.demos)
    width = scenario.positions(scenario.init_upper - scenario.init_lower)
    assert np.all(np.ptp(positions, axis=0) >= 0.5 * width)


def test_shipped_demos_are_synthetic_and_say_so(scenario: Scenario) -> None:
    for demo in scenario.demos:
        header = demo.file.read_text().split("\nt,")[0]
        assert "SYNTHETIC" in header and "NOT by a human" in header
        assert "make demos" in header


def test_shipped_demos_are_suboptimal_and_one_passes_close(scenario: Scenario) -> None:
    closest = []
    for demo in scenario.demos:
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


def test_regenerate_reproduces_shipped_files_and_keeps_the_yaml(tmp_path: Path) -> None:
    copy = tmp_path / "quadrotor_hill"
    shutil.copytree(SHIPPED, copy)
    for csv in (copy / "demos").glob("*.csv"):
        csv.unlink()
    yaml_path = copy / "scenario.yaml"
    shipped_yaml = (SHIPPED / "scenario.yaml").read_text()
    block = re.search(r"^demos:", shipped_yaml, flags=re.MULTILINE)
    assert block is not None
    yaml_path.write_text(shipped_yaml[: block.start()] + "demos: []  # to be flown\n")

    demos = regenerate_demos(yaml_path)

    assert yaml_path.read_bytes() == (SHIPPED / "scenario.yaml").read_bytes()
    assert [demo.file.name for demo in demos] == [f"demo_{i:02d}.csv" for i in range(1, 10)]
    for demo in demos:
        assert demo.file.read_bytes() == (SHIPPED / "demos" / demo.file.name).read_bytes()


def test_pilot_refuses_a_scenario_without_configuration(tmp_path: Path) -> None:
    copy = tmp_path / "other"
    shutil.copytree(SHIPPED, copy)
    yaml_path = copy / "scenario.yaml"
    yaml_path.write_text(
        yaml_path.read_text().replace("name: quadrotor_hill", "name: other_hill", 1)
    )
    with pytest.raises(UserError, match="no configuration for scenario 'other_hill'"):
        regenerate_demos(yaml_path)


def test_cli_demos_unknown_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demos", "nope"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: unknown scenario 'nope'")
    assert error.count("\n") == 1
