"""The feedback design that tunes itself (issue 31, item 3): ``feedback: auto`` (or no block)
searches over the operating region, the rate and the LQR weights; fields the file sets are used
as given; a car written from the ``new`` template with speed and turn-rate inputs certifies and
validates on the first run, and its constant-speed variant is refused in one line."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.demonstrations.pilot import regenerate_demos
from pipeline.model.demos import write_demo_csv
from pipeline.model.feedback_defaults import resolve_feedback
from pipeline.model.scenario import load_scenario
from pipeline.numerics.tube.feedback_search import fix_for
from pipeline.runtime.cli import main
from pipeline.runtime.scaffold import new_scenario
from stages.feedback import design_feedback
from tests.helpers.scenario_files import write_scenario, yaml_replace

REPO = Path(__file__).resolve().parents[1]
FEEDBACK_BLOCK = (
    "feedback:\n  reference_state: [0, 0, 0, 0]\n  reference_input: [0, 0]\n"
    "  state_weights: [1, 1, 1, 1]\n  input_weights: [1, 1]\n  rate: 0.5\n"
)


def _with_feedback(tmp_path: Path, block: str) -> Path:
    path = write_scenario(tmp_path / "scenario")
    return Path(yaml_replace(FEEDBACK_BLOCK, block)(path))


@pytest.mark.parametrize(
    ("block", "tune", "given"),
    [
        ("feedback: auto\n", True, ()),
        ("", True, ()),  # no block: auto
        ("feedback:\n  rate: 0.3\n", True, ("rate",)),
        ("feedback: {tune: false}\n", False, ()),
        (FEEDBACK_BLOCK, False, ("reference_state", "reference_input", "state_weights",
                                 "input_weights", "rate")),
        (FEEDBACK_BLOCK + "  tune: true\n", True, ("reference_state", "reference_input",
                                                   "state_weights", "input_weights", "rate")),
    ],
)  # fmt: skip
def test_the_feedback_block_says_what_is_tuned(tmp_path, block, tune, given):
    scenario = load_scenario(_with_feedback(tmp_path, block))
    assert scenario.feedback.tune is tune
    assert scenario.feedback.given == given
    if "rate" not in given:
        assert scenario.feedback.rate == 0.5  # the default, the search's start
    assert len(scenario.feedback.reference_state) == scenario.n
    assert resolve_feedback(scenario.spec, scenario.state_names, scenario.input_names) == (
        scenario.feedback
    )


def test_explicit_feedback_is_used_as_given():
    scenario = load_scenario("double_integrator")
    result = design_feedback(scenario)
    assert result.tuning is None and result.applied_to(scenario) is scenario
    assert result.rate == scenario.feedback.rate and result.region == scenario.operating_region


def test_a_given_rate_is_kept_while_the_region_is_tuned(tmp_path):
    scenario = load_scenario(_with_feedback(tmp_path, "feedback:\n  rate: 0.3\n"))
    result = design_feedback(scenario)
    print(result.message)
    assert result.success and result.tuning is not None
    assert result.rate == 0.3 and result.tuning.rate == 0.3
    assert "tuned over" in result.message and "radius limited by" in result.message
    for name, (lower, upper) in result.region.items():  # only ever narrowed
        assert scenario.operating_region[name][0] <= lower < upper
        assert upper <= scenario.operating_region[name][1]
    tuned = result.applied_to(scenario)
    assert tuned.operating_region == result.region and tuned.feedback.rate == 0.3


def test_the_advice_names_only_fields_of_the_scenario_file():
    car = load_scenario("unicycle_slalom")
    assert fix_for(car, "input 'turn_rate' upper") == (
        "widen input_bounds.turn_rate or narrow operating_region (psi, v) (a smaller feedback gain)"
    )
    assert fix_for(car, "region 'v' lower").startswith("widen operating_region.v")


# --- the car of the issue, from the template --------------------------------------------------

CAR = """\
name: car
description: A car with speed and turn-rate inputs passing one block into a goal box.
states: [x, y, psi]
inputs: [v, turn_rate]
dynamics:
  x: v*cos(psi)
  y: v*sin(psi)
  psi: turn_rate
position: [x, y]
sampling_time: 0.1
input_bounds:
  v: [0.5, 3.0]
  turn_rate: [-1.5, 1.5]
unsafe:
  block: [[6.0, -1.0], [7.0, -1.0], [7.0, 0.8], [6.0, 0.8]]
goal:
  polygon: [[12.0, -1.0], [16.0, -1.0], [16.0, 3.0], [12.0, 3.0]]
init:
  x: [0.0, 0.4]
  y: [1.6, 2.0]
  psi: [-0.1, 0.1]
clearance: 0.3
operating_region:
  psi: [-0.8, 0.8]
  v: [0.5, 3.0]
demos: []
"""

CAR_PILOT = '''\
CONFIG = PilotConfig(
    waypoints=((6.5, 2.0), (14.0, 1.0)),
    cruise_speed=2.0,
    noise=(0.05, 0.03),
    stick_step=(0.05, 0.05),
    stick_range=((1.0, 2.5), (-1.0, 1.0)),
    grid=(("y", 2), ("psi", 2)),
    k_position=1.0,
    goal_margin=1.0,
    stop_speed=100.0,
)


@dataclass(frozen=True)
class CarSteering:
    """Aim the heading along the wanted velocity; the speed is the first input."""

    heading: int
    k_heading: float = 1.5
    max_heading: float = 0.45
    min_speed: float = 1.5
    max_speed: float = 2.2

    def speed(self, x: FloatArray) -> float:
        return 0.0  # stop_speed is above it: the pilot stops inside Goal

    def __call__(self, x: FloatArray, v_des: FloatArray, noise: FloatArray) -> FloatArray:
        psi_des = np.clip(np.arctan2(v_des[1], v_des[0]), -self.max_heading, self.max_heading)
        speed = np.clip(np.hypot(*v_des), self.min_speed, self.max_speed)
        error = (psi_des - x[self.heading] + np.pi) % (2 * np.pi) - np.pi
        return np.array([speed + noise[0], self.k_heading * error + noise[1]])


def steering(scenario: Scenario) -> CarSteering:
    return CarSteering(heading=scenario.state_names.index("psi"))
'''


def _car_from_template(root: Path, name: str = "car") -> Path:
    """``new car --like unicycle_slalom``, then the user's edits: the car's scenario (no
    feedback block: auto) under the template's guide, the pilot's CONFIG and steering law."""
    folder = new_scenario(name, "unicycle_slalom", where=root)
    text = (folder / "scenario.yaml").read_text()
    assert "feedback: auto" in text  # the template says so
    guide = text[: text.index(f"name: {name}")]
    (folder / "scenario.yaml").write_text(guide + CAR.replace("name: car", f"name: {name}"))
    pilot = (folder / "pilot.py").read_text()
    (folder / "pilot.py").write_text(pilot[: pilot.index("CONFIG = PilotConfig(")] + CAR_PILOT)
    return folder


@pytest.mark.slow
def test_a_car_from_the_template_with_auto_feedback_certifies_on_the_first_run(tmp_path, capsys):
    folder = _car_from_template(tmp_path)
    demos = regenerate_demos(folder / "scenario.yaml")
    assert len(demos) == 4
    scenario = load_scenario(folder / "scenario.yaml")
    assert scenario.feedback.tune and scenario.feedback.given == ()
    out = tmp_path / "out"
    code = main(["synthesize", str(folder), "--samples", "2000", "--out", str(out)])
    printed = capsys.readouterr().out
    print(printed)
    assert code == 0
    assert "verdict (constant certificate): certified and validated" in printed
    assert "[feedback search]" in printed and "tuned over" in printed
    # the report is rebuilt from the run's files with the tuned region (pipeline.runtime.stored)
    rebuilt = tmp_path / "rebuilt"
    assert main(["report", str(folder), "--from", str(out), "--out", str(rebuilt)]) == 0
    assert (rebuilt / "report.html").is_file()


def test_the_constant_speed_car_is_refused_in_one_line(tmp_path, capsys):
    folder = _car_from_template(tmp_path, "car_constant_speed")
    text = (folder / "scenario.yaml").read_text()
    for old, new in [
        ("inputs: [v, turn_rate]", "inputs: [turn_rate]\nparameters: {v: 2.0}"),
        ("  v: [0.5, 3.0]\n  turn_rate", "  turn_rate"),
        ("  psi: [-0.8, 0.8]\n  v: [0.5, 3.0]\n", "  psi: [-0.8, 0.8]\n"),
    ]:
        assert old in text, old
        text = text.replace(old, new)
    text = text.replace(
        "demos: []\n", "demos:\n  - {file: demos/demo_01.csv, x0: [0.2, 1.8, 0.0]}\n"
    )
    (folder / "scenario.yaml").write_text(text)
    straight = np.zeros((60, 1))  # 12 m at 2 m/s: past the block into Goal
    write_demo_csv(folder / "demos" / "demo_01.csv", straight, ["turn_rate"], 0.1, "straight")
    code = main(["synthesize", str(folder), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    print(err)
    assert code == 2 and err.count("\n") == 1
    assert "not stabilisable at the reference: no input moves the direction x (" in err


@pytest.mark.slow  # about 5 designs of the quadrotor's 11-vertex hull
def test_a_search_that_certifies_nothing_says_what_is_left(tmp_path):
    """The quadrotor at a given rate of 20 1/s: no region narrowing certifies it, and the
    message does not repeat the advice the search has already followed."""
    folder = tmp_path / "quadrotor"
    shutil.copytree(REPO / "scenarios" / "quadrotor_hill_flythrough", folder)
    text = (folder / "scenario.yaml").read_text()
    block = re.search(r"^feedback:\n(?:  .*\n)+", text, flags=re.MULTILINE)
    assert block is not None
    (folder / "scenario.yaml").write_text(
        text[: block.start()] + "feedback: {rate: 20.0}\n" + text[block.end() :]
    )
    scenario = load_scenario(folder / "scenario.yaml")
    result = design_feedback(scenario)
    print(result.message)
    assert not result.success and result.tuning is None
    assert "try a feedback.rate" not in result.message
    assert result.message.endswith(
        "; nor with the operating region narrowed around the demos: lower feedback.rate (the "
        "search keeps a rate the file gives), or fly the demos over a smaller range of (theta, u1)"
    )
