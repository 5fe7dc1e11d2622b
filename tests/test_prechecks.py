"""Pre-checks before any stage (issue 31, item 2): each mistake is one line and exit code 2,
naming the cause, before the feedback stage would fail on it; a YAML error appears before the
numerics are imported.

The car of the issue: states ``X, Y, theta``, turn rate ``omega`` the only input, a constant speed
``v``. At the reference no input moves the along-track position, so no feedback exists.
"""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import pipeline
from pipeline import ScenarioError, available_scenarios, load_scenario
from pipeline.model.demos import write_demo_csv
from pipeline.numerics.prechecks import check_scenario, direction, uncontrollable_modes
from pipeline.runtime.cli import main
from stages.feedback import design_feedback

REPO = Path(__file__).resolve().parents[1]


def _car(tmp_path: Path, *, speed_input: bool = False, heading: float = 0.0, **replace) -> Path:
    """A Dubins-type car driving 5 m along ``heading`` into a goal box; with ``speed_input`` its
    speed ``v`` is a state driven by the input ``accel`` instead of a parameter. ``replace``:
    YAML text to swap (old -> new)."""
    states = "[X, Y, theta, v]" if speed_input else "[X, Y, theta]"
    inputs = "[omega, accel]" if speed_input else "[omega]"
    c, s = math.cos(heading), math.sin(heading)
    text = textwrap.dedent(
        f"""\
        name: car
        states: {states}
        inputs: {inputs}
        parameters: {{{"" if speed_input else "v: 1.0"}}}
        dynamics:
          X: v*cos(theta)
          Y: v*sin(theta)
          theta: omega
        {"  v: accel" if speed_input else ""}
        position: [X, Y]
        sampling_time: 0.1
        input_bounds:
          omega: [-1.0, 1.0]
        {"  accel: [-1.0, 1.0]" if speed_input else ""}
        unsafe:
          block: [[-3.0, 3.0], [-2.0, 3.0], [-2.0, 4.0], [-3.0, 4.0]]
        goal:
          polygon: [[{5 * c - 1}, {5 * s - 1}], [{5 * c + 1}, {5 * s - 1}],
                    [{5 * c + 1}, {5 * s + 1}], [{5 * c - 1}, {5 * s + 1}]]
        init:
          X: [0.0, 0.0]
          Y: [0.0, 0.0]
          theta: [{heading}, {heading}]
        {"  v: [1.0, 1.0]" if speed_input else ""}
        clearance: 0.1
        operating_region:
          theta: [{heading - 0.5}, {heading + 0.5}]
          omega: [-1.0, 1.0]
        {"  v: [0.5, 1.5]" if speed_input else ""}
        feedback:
          reference_state: [0, 0, {heading}{", 1" if speed_input else ""}]
          reference_input: [0{", 0" if speed_input else ""}]
          state_weights: [1, 1, 1{", 1" if speed_input else ""}]
          input_weights: [1{", 1" if speed_input else ""}]
          rate: 0.1
        demos:
          - {{file: demo_01.csv, x0: [0, 0, {heading}{", 1" if speed_input else ""}]}}
        """
    )
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    folder = tmp_path / "car"
    folder.mkdir()
    (folder / "scenario.yaml").write_text(text)
    names = ["omega", "accel"] if speed_input else ["omega"]
    write_demo_csv(folder / "demo_01.csv", np.zeros((50, len(names))), names, 0.1, "test")
    return folder


def test_a_constant_speed_car_is_refused_naming_the_along_track_direction(tmp_path, capsys):
    folder = _car(tmp_path)
    code = main(["synthesize", str(folder), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    print(err)
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "feedback.reference_state: not stabilisable at the reference" in err
    assert "no input moves the direction X (an uncontrollable mode, eigenvalue 0" in err
    assert not (tmp_path / "out" / "artifacts").exists()  # before any stage


def test_the_direction_is_along_track_at_any_heading(tmp_path):
    folder = _car(tmp_path, heading=math.pi / 4)
    with pytest.raises(ScenarioError, match=r"direction 0\.71 X \+ 0\.71 Y \(") as error:
        check_scenario(load_scenario(folder))
    print(error.value)


def test_the_car_with_speed_as_an_input_passes(tmp_path):
    check_scenario(load_scenario(_car(tmp_path, speed_input=True)))


@pytest.mark.parametrize(
    ("A", "B", "modes"),
    [
        ([[0, 1], [0, 0]], [[0], [1]], []),  # double integrator: controllable
        ([[-1, 0], [0, 2]], [[1], [0]], [(2, [0, 1])]),  # an unstable mode no input reaches
        ([[0, 0, 0], [0, 0, 1], [0, 0, 0]], [[0], [0], [1]], [(0, [1, 0, 0])]),  # the car
    ],
)
def test_the_pbh_modes_and_their_left_eigenvectors(A, B, modes):
    A, B = np.array(A, dtype=float), np.array(B, dtype=float)
    found = uncontrollable_modes(A, B)
    assert len(found) == len(modes)
    for (mu, w), (mu_expected, w_expected) in zip(found, modes, strict=True):
        assert mu == pytest.approx(mu_expected)
        assert w == pytest.approx(np.array(w_expected, dtype=float))
        assert w @ B == pytest.approx(np.zeros(B.shape[1]))
        assert w @ A == pytest.approx(mu.real * w)


def test_direction_text():
    assert direction(np.array([0.6, -0.8, 0.0]), ["X", "Y", "theta"]) == "0.6 X - 0.8 Y"
    assert direction(np.array([0.0, 1.0]), ["a", "b"]) == "b"


def test_demo_inputs_outside_the_operating_region_are_refused(tmp_path):
    folder = _car(tmp_path, speed_input=True)
    write_demo_csv(  # +-0.5 m/s^2 from t = 1 s: within input_bounds, outside the region's accel
        folder / "demo_01.csv",
        np.array([[0.0, 0.0]] * 10 + [[0.0, 0.5]] * 3 + [[0.0, -0.5]] * 3 + [[0.0, 0.0]] * 34),
        ["omega", "accel"],
        0.1,
        "test",
    )
    text = (folder / "scenario.yaml").read_text()
    region = "  v: [0.5, 1.5]"
    (folder / "scenario.yaml").write_text(text.replace(region, f"{region}\n  accel: [-0.2, 0.2]"))
    load_scenario(folder)  # valid: inputs within input_bounds, flight ends in Goal
    with pytest.raises(ScenarioError) as error:
        pipeline.synthesize(folder, out=tmp_path / "out")
    assert not (tmp_path / "out" / "artifacts").exists()  # before any stage
    message = str(error.value)
    print(message)
    assert "operating_region.accel: demo 'demo_01' leaves the operating region" in message
    assert "input 'accel' = 0.5 at t = 1.00 s" in message
    assert "found [-0.2, 0.2]" in message and "the demos use [-0.5, 0.5]" in message


@pytest.mark.parametrize(
    ("replace", "expected"),
    [
        (  # theta's range missing: the Jacobian depends on it
            {"  theta: [-0.5, 0.5]\n": ""},
            "the Jacobian depends on ['theta'] but the operating region does not bound them",
        ),
        (  # a Jacobian entry unbounded over the region (e^v up to v = 1e6)
            {
                "X: v*cos(theta)": "X: v*cos(theta) + 1e-300*exp(v)",
                "v: [0.5, 1.5]": "v: [0.5, 1e6]",
            },
            "is unbounded over",
        ),
    ],
    ids=["missing-range", "unbounded-entry"],
)
def test_an_operating_region_with_an_unbounded_hull_is_refused(tmp_path, replace, expected):
    folder = _car(tmp_path, speed_input=True, **replace)
    with pytest.raises(ScenarioError) as error:
        pipeline.synthesize(folder, out=tmp_path / "out")
    message = str(error.value)
    print(message)
    assert "operating_region: the feedback's Jacobian hull is unbounded" in message
    assert expected in message
    assert not (tmp_path / "out" / "artifacts").exists()


@pytest.mark.parametrize("name", available_scenarios())
def test_the_shipped_scenarios_pass_the_prechecks(name):
    check_scenario(load_scenario(name))


def test_a_yaml_error_comes_before_the_numerics_are_imported(tmp_path):
    bad = tmp_path / "scenario.yaml"
    bad.write_text("name: bad\nstates: [x\n")
    started = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-m", "pipeline", "synthesize", str(bad)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    seconds = time.perf_counter() - started
    print(f"time to a YAML error: {seconds:.2f} s")
    assert run.returncode == 2 and "YAML syntax error at line 3" in run.stderr
    assert run.stderr.count("\n") == 1
    code = (
        "import sys; from pipeline.runtime.cli import main\n"
        f"assert main(['synthesize', {str(bad)!r}]) == 2\n"
        "heavy = {'sympy', 'scipy', 'shapely', 'cvxpy', 'clarabel', 'numba', 'matplotlib'}\n"
        "assert not heavy & set(sys.modules), sorted(heavy & set(sys.modules))\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)
    assert seconds < 2.0


def test_the_feedback_failure_names_only_what_the_scenario_file_has():
    quadrotor = load_scenario("quadrotor_hill_flythrough")
    result = design_feedback(quadrotor, rate=20.0)
    assert not result.success
    print(result.message)
    assert result.message.endswith(
        "; try a feedback.rate below 20 or narrow operating_region (theta, u1)"
    )
    assert set(quadrotor.dynamics.depends_on()) <= set(quadrotor.operating_region)
