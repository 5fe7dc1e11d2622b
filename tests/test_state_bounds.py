"""``state_bounds`` under the constant certificate (issue 27 item 2): enforced, or refused.

The issue's case, double_integrator with ``certificate: constant`` and ``state_bounds: {vx: [-0.1,
0.1]}`` (every demo flies at up to 1.6 m/s), was "certified and validated"; so were an empty
interval and bounds that exclude Init. Now: an empty interval, Init outside the bounds and a demo
leaving them are exit 2 at load; the radius of a constant tube is limited by the bounds (a known
answer: the support function of the ball), certify refuses a file whose tube or terminal ellipsoid
leaves them, and the optimizer keeps the nominal inside them shrunk by the tube.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.optimize.footprint import ConstraintMargins
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.tube.radius import radius_limits
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS
from pipeline.runtime.cli import main
from stages.certify import certify_controller
from stages.feedback import design_feedback
from stages.optimize import OptimizeOptions, optimize_demo
from stages.radius import robustness_radius
from tests.helpers.double_integrator import DOUBLE_INTEGRATOR, emit_at_rest

REPO = Path(__file__).resolve().parents[1]


def _shipped_with(tmp_path: Path, name: str, extra: str) -> Path:
    """A copy of the shipped scenario ``name`` in ``tmp_path`` with ``extra`` YAML appended."""
    folder = tmp_path / name
    shutil.copytree(REPO / "scenarios" / name, folder)
    path = folder / "scenario.yaml"
    path.write_text(path.read_text() + extra)
    return folder


def _refused(folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``synthesize`` on ``folder`` (constant certificate): exit 2, one line, nothing
    written. Returns the line."""
    out = tmp_path / "out"
    code = main(["synthesize", str(folder), "--out", str(out), "--certificate", "constant"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert not (out / "controller.json").exists()
    return err


def test_the_issues_case_is_refused_at_load(tmp_path, capsys):
    folder = _shipped_with(
        tmp_path, "double_integrator", "certificate: constant\nstate_bounds: {vx: [-0.1, 0.1]}\n"
    )
    err = _refused(folder, tmp_path, capsys)
    assert "demo_01.csv: demo 'demo_01' leaves state_bounds.vx = [-0.1, 0.1] at t = " in err
    assert "expected a flight inside the state bounds" in err


@pytest.mark.parametrize(
    ("bounds", "parts"),
    [
        ("{vx: [1, 1]}", ["state_bounds.vx", "found [1, 1]", "lower < upper"]),
        ("{vx: [1.0, 0.5]}", ["state_bounds.vx", "found [1.0, 0.5]", "lower < upper"]),
        (
            "{x: [2.0, 3.0]}",  # Init has x in [0, 1]
            ["init.x: Init leaves state_bounds.x = [2, 3]", "found [0.0, 1.0]", "inside [2, 3]"],
        ),
        (
            "{y: [0.5, 3.0]}",  # Init only partly inside
            ["init.y: Init leaves state_bounds.y = [0.5, 3]", "found [0.0, 1.0]"],
        ),
    ],
    ids=["empty interval", "inverted interval", "Init outside", "Init partly outside"],
)
def test_bad_state_bounds_are_exit_2_at_load(bounds, parts, tmp_path, capsys):
    folder = _shipped_with(tmp_path, "double_integrator", f"state_bounds: {bounds}\n")
    err = _refused(folder, tmp_path, capsys)
    assert f"{folder / 'scenario.yaml'}: " in err
    for part in parts:
        assert part in err, err


@pytest.mark.parametrize("name", ["quadrotor_hill_flythrough", "quadrotor_hill_gusty_flythrough"])
def test_shipped_scenarios_with_state_bounds_load_with_their_demos(name):
    scenario = load_scenario(name)  # Init and every demo inside theta in [-0.8, 0.8]
    assert scenario.state_bounds == {"theta": (-0.8, 0.8)}


def _scenario(tmp_path: Path, bounds: str = "") -> Scenario:
    """The stage tests' double integrator (states X, Y, vX, vY; Unsafe Y <= 0, Goal Y >= 1,
    Init [0, 1] x [2, 3] at rest) with ``state_bounds: bounds`` (YAML; none when empty)."""
    path = tmp_path / ("bounded" if bounds else "free") / "scenario.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = DOUBLE_INTEGRATOR % {
        "goal": "[[-900, 1], [900, 1], [900, 900], [-900, 900]]",
        "region": "{aX: [-100.0, 100.0]}",
        "rate": 0.5,
    }
    path.write_text(text + (f"state_bounds: {bounds}\n" if bounds else ""))
    return load_scenario(path, check_demos=False)


def test_the_radius_is_the_support_function_of_the_bound(tmp_path):
    """Coasting at vX = 0.5 under vX <= 1: the largest ball ``||e||_P <= r`` with ``e_vX <= 0.5``
    has ``r sqrt((P^-1)_vXvX) = 0.5``; with ``P`` coupling position and speed, ``(P^-1)_vXvX = 4/3``
    and ``r = 0.5 / sqrt(4/3) = sqrt(3) / 4``, binding at t = 0 (the tube only shrinks)."""
    scenario = _scenario(tmp_path, "{vX: [-1.0, 1.0]}")
    P = np.array([[4.0, 0, 1, 0], [0, 4, 0, 1], [1, 0, 1, 0], [0, 1, 0, 1]])
    tube = Tube(
        K=-np.array([[1.0, 0, 2, 0], [0, 1, 0, 2]]),
        P=P,
        rate=0.5,
        region={},
        state_names=scenario.state_names,
        input_names=scenario.input_names,
        position_index=scenario.position_index,
    )
    assert tube.state_extent_per_radius[2] == pytest.approx(np.sqrt(4 / 3), rel=1e-14)
    trajectory = simulate(
        scenario.dynamics, np.array([0.0, 2.5, 0.5, 0.0]), np.zeros((20, 2)), 0.1, VERIFY_SUBSTEPS
    )
    found = radius_limits(scenario, tube, trajectory)
    assert found.limits["state 'vX' upper"] == (pytest.approx(np.sqrt(3) / 4, rel=1e-12), 0.0)
    assert found.limits["state 'vX' lower"][0] == pytest.approx(1.5 / np.sqrt(4 / 3), rel=1e-12)
    result = robustness_radius(scenario, tube, trajectory)
    assert result.radius == pytest.approx(np.sqrt(3) / 4, rel=1e-12)
    assert result.binding == "state 'vX' upper" and result.binding_time == 0.0
    # without the bound the same tube is far wider (here Goal's edge binds)
    free = robustness_radius(_scenario(tmp_path), tube, trajectory)
    assert free.radius > 2 * result.radius and "state" not in free.binding


@pytest.fixture
def emitted(tmp_path):
    """``(scenario without bounds, path, extent)``: a certified file of four references at rest
    (``tests.stages.conftest.emit_at_rest``) and its tube's vX extent per unit radius."""
    scenario = _scenario(tmp_path)
    path = tmp_path / "controller.json"
    emit_at_rest(scenario, path)
    assert certify_controller(scenario, path).success
    P = np.array(json.loads(path.read_text())["feedback"]["P"])
    return scenario, path, float(np.sqrt(np.linalg.inv(P)[2, 2]))


def test_certify_refuses_a_tube_wider_than_the_bounds_allow(emitted, tmp_path):
    scenario, path, extent = emitted
    radii = certify_controller(scenario, path).radii
    # half of what the file's smallest tube needs along vX (the references are at rest)
    bound = 0.5 * min(radii) * extent
    bounded = _scenario(tmp_path, f"{{vX: [{-bound!r}, {bound!r}]}}")
    result = certify_controller(bounded, path)
    assert not result.success
    for i, radius in enumerate(radii):
        assert (
            f"trajectories[{i}]: radius {radius:.6g} > {bound / extent:.6g}, the largest the tube "
            "allows (state 'vX' lower binds at t = 0.00 s)"
        ) in result.message
    assert result.verified_radii == pytest.approx([bound / extent] * len(radii), rel=1e-12)


def test_certify_refuses_a_terminal_ellipsoid_leaving_the_bounds(emitted, tmp_path):
    scenario, path, extent = emitted
    emit_at_rest(scenario, path, radius_floor=1.0)  # radii lowered to 1: a terminal block fits
    terminal = json.loads(path.read_text())["terminal"]
    reach = float(np.sqrt(terminal["level"] * np.linalg.inv(np.array(terminal["P"]))[2, 2]))
    assert terminal["x_eq"][2] == 0.0 and extent < reach  # E_c reaches further than the tubes
    bound = (extent + reach) / 2  # holds every tube of radius 1, not E_c
    bounded = _scenario(tmp_path, f"{{vX: [{-bound!r}, {bound!r}]}}")
    result = certify_controller(bounded, path)
    assert not result.success and len(result.failures) == 1, result.message
    assert result.failures[0].startswith(
        f"terminal: E_c leaves state_bounds.vX = [{-bound:g}, {bound:g}]"
    )
    # the controller stage sizes E_c to the bounds
    emit_at_rest(bounded, path, radius_floor=1.0)
    assert certify_controller(bounded, path).success
    terminal = json.loads(path.read_text())["terminal"]
    reach = float(np.sqrt(terminal["level"] * np.linalg.inv(np.array(terminal["P"]))[2, 2]))
    assert reach <= bound * (1 + 1e-12)


def test_the_optimizer_keeps_the_nominal_inside_the_bounds_shrunk_by_the_tube(tmp_path):
    """double_integrator's optimized flights reach vx ~ 3.7 m/s; with vx <= 2 (its demos stay
    below 1.7) the nominal keeps its tube of radius r_d inside the bound."""
    free = load_scenario("double_integrator", check_demos=False)
    bounded = load_scenario(
        _shipped_with(tmp_path, "double_integrator", "state_bounds: {vx: [-1.0, 2.0]}\n")
    )
    feedback = design_feedback(free)
    tube = feedback.certified_tube
    r_d = feedback.required_radius(free.clearance)
    margins = ConstraintMargins.of_tube(tube, r_d)
    reach = float(tube.state_extent(r_d)[2])

    def fastest(scenario: Scenario) -> float:
        result = optimize_demo(scenario, 0, margins, OptimizeOptions())
        assert result.success, result.message
        flight = simulate(scenario.dynamics, result.x0, result.u, scenario.Ts, VERIFY_SUBSTEPS)
        return float(flight.dense_xs[:, 2].max())

    assert fastest(free) + reach > 2.5  # the bound binds
    assert fastest(bounded) + reach <= 2.0
