"""Scenario validation: a table of bad inputs and the message each must produce.

Every case copies a tiny valid scenario (a planar double integrator with one hand-made demo) into
``tmp_path``, breaks one thing, and checks (1) the ``ScenarioError`` names the file, the field
path or CSV row, the value found and what was expected, and (2) the CLI turns it into one line on
stderr and exit code 2, without a traceback.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import sympy

from pipeline import ScenarioError, available_scenarios, load_scenario
from pipeline.model.expressions import ExpressionError, parse_expression
from pipeline.model.schema import json_schema
from pipeline.runtime.cli import main
from tests.helpers.scenario_files import (
    SCENARIO_YAML,
    STRAIGHT,
    Mutation,
    chain,
    demo_csv,
    write_scenario,
    yaml_replace,
)

REPO = Path(__file__).resolve().parents[1]

# STRAIGHT's bang-bang in X and Y: passes through the block (X = Y = 2 at t = sqrt(3) s).
DIAGONAL = demo_csv([1.0] * 20 + [-1.0] * 20, [1.0] * 20 + [-1.0] * 20)
# Half the acceleration: stops at (2.5, 0.5), short of Goal, after 4 s.
SHORT = demo_csv([0.5] * 20 + [-0.5] * 20, [0.0] * 40)


def csv_write(text: str | bytes) -> Mutation:
    def mutate(path: Path) -> str:
        target = path.parent / "demos" / "straight.csv"
        if isinstance(text, bytes):
            target.write_bytes(text)
        else:
            target.write_text(text)
        return str(path)

    return mutate


def csv_replace(old: str, new: str) -> Mutation:
    return csv_write(STRAIGHT.replace(old, new, 1))


def unknown_name(_path: Path) -> str:
    return "no_such_scenario"


YAML = "scenario.yaml"
CSV = "straight.csv"
BLOCK = "block: [[2, 2], [3, 2], [3, 3], [2, 3]]"

# (id, mutation, file the message must name (or None), parts the message must contain)
BAD_INPUTS: list[tuple[str, Mutation, str | None, list[str]]] = [
    (
        "unknown scenario name",
        unknown_name,
        None,
        ["unknown scenario 'no_such_scenario'", "expected one of:", *available_scenarios()],
    ),
    (
        "YAML syntax error",
        yaml_replace("states: [X, Y, vX, vY]", "states: [X, Y, vX, vY"),
        YAML,
        ["YAML syntax error at line 4, column 7", "expected ',' or ']'"],
    ),
    (
        "duplicate YAML key",
        yaml_replace("sampling_time: 0.1\n", "sampling_time: 0.1\nsampling_time: 0.2\n"),
        YAML,
        ["line 13, column 1", "duplicate key 'sampling_time' (first at line 12)"],
    ),
    (
        "empty file",
        yaml_replace(SCENARIO_YAML, ""),
        YAML,
        ["not a mapping", "found 'NoneType'", "expected a YAML mapping"],
    ),
    (
        "unknown name in state_bounds",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nstate_bounds: {aX: [-1, 1]}\n"),
        YAML,
        ["state_bounds", "unknown name 'aX'", "names from ['X', 'Y', 'vX', 'vY']"],
    ),
    (
        "unknown certificate kind",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\ncertificate: tube\n"),
        YAML,
        ["certificate", "'constant' or 'funnel'"],
    ),
    (
        "unknown optimizer",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\noptimizer: newton\n"),
        YAML,
        ["optimizer", "'gd' or 'lbfgs'"],
    ),
    (
        "feedback period that does not divide the sampling time",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nfeedback_period: 0.03\n"),
        YAML,
        [
            "feedback_period: is not a control period this scenario can be certified for",
            "found 0.03",
            "a period of at least 0.0001 s that divides sampling_time 0.1 s (e.g. 0.01)",
        ],
    ),
    (
        "feedback period below the shortest",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nfeedback_period: 0.00001\n"),
        YAML,
        ["feedback_period", "found 1e-05", "at least 0.0001 s"],
    ),
    (
        "negative feedback period",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nfeedback_period: -0.01\n"),
        YAML,
        ["feedback_period", "found -0.01", "greater than or equal to 0"],
    ),
    (
        "boolean where a number belongs",
        yaml_replace("clearance: 0.25\n", "clearance: true\n"),
        YAML,
        ["clearance", "found True", "a valid number"],
    ),
    (
        "quoted number",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nfeedback_period: '0.01'\n"),
        YAML,
        ["feedback_period", "found '0.01'", "a valid number"],
    ),
    (
        "boolean in an interval",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nstate_bounds: {vX: [false, 3]}\n"),
        YAML,
        ["state_bounds.vX.0", "found False", "a valid number"],
    ),
    (
        "negative disturbance bound",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {disturbance: {vX: -0.1}}\n"
        ),
        YAML,
        ["uncertainty.disturbance.vX", "greater than or equal to 0"],
    ),
    (
        "disturbance on an unknown state",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {disturbance: {vZ: 0.1}}\n"
        ),
        YAML,
        ["uncertainty.disturbance", "unknown name 'vZ'", "names from ['X', 'Y', 'vX', 'vY']"],
    ),
    (
        "zero ellipsoid semi-axis",
        yaml_replace(
            "clearance: 0.25\n",
            "clearance: 0.25\nuncertainty: {disturbance_ellipsoid: {vX: 0.1, vY: 0}}\n",
        ),
        YAML,
        ["uncertainty.disturbance_ellipsoid.vY", "greater than 0"],
    ),
    (
        "ellipsoid on an unknown state",
        yaml_replace(
            "clearance: 0.25\n",
            "clearance: 0.25\nuncertainty: {disturbance_ellipsoid: {vZ: 0.1}}\n",
        ),
        YAML,
        [
            "uncertainty.disturbance_ellipsoid",
            "unknown name 'vZ'",
            "names from ['X', 'Y', 'vX', 'vY']",
        ],
    ),
    (
        "negative measurement bound",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {measurement: {X: -0.02}}\n"
        ),
        YAML,
        ["uncertainty.measurement.X", "greater than or equal to 0"],
    ),
    (
        "measurement bound on an unknown state",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {measurement: {Z: 0.02}}\n"
        ),
        YAML,
        ["uncertainty.measurement", "unknown name 'Z'", "names from ['X', 'Y', 'vX', 'vY']"],
    ),
    (
        "measurement bound not a number",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {measurement: {X: small}}\n"
        ),
        YAML,
        ["uncertainty.measurement.X", "small"],
    ),
    (
        "interval of an unknown parameter",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {parameters: {mass: [0.9, 1.1]}}\n"
        ),
        YAML,
        ["uncertainty.parameters", "unknown name 'mass'", "names from ['k']"],
    ),
    (
        "parameter interval excluding the nominal value",
        yaml_replace(
            "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {parameters: {k: [1.1, 1.2]}}\n"
        ),
        YAML,
        ["uncertainty.parameters.k", "excludes the nominal value 1", "an interval holding 1"],
    ),
    (
        "unit of an unknown name",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\nunits: {speed: m/s}\n"),
        YAML,
        ["units", "unknown name 'speed'"],
    ),
    (
        "missing field",
        yaml_replace("sampling_time: 0.1\n", ""),
        YAML,
        ["sampling_time: missing field", "expected this field"],
    ),
    (
        "feedback neither auto nor a mapping",
        yaml_replace(
            "feedback:\n  reference_state: [0, 0, 0, 0]\n  reference_input: [0, 0]\n"
            "  state_weights: [1, 1, 1, 1]\n  input_weights: [1, 1]\n  rate: 0.5\n",
            "feedback: automatic\n",
        ),
        YAML,
        ["feedback: invalid value; found 'automatic'; expected 'auto' or a mapping of (ref"],
    ),
    (
        "feedback tune not a boolean",
        yaml_replace("  rate: 0.5\n", "  rate: 0.5\n  tune: sometimes\n"),
        YAML,
        ["feedback.tune"],
    ),
    (
        "extra field",
        yaml_replace("clearance: 0.25\n", "clearance: 0.25\ncolour: red\n"),
        YAML,
        ["colour: unknown field 'colour';", "expected one of the fields of the scenario: name,"],
    ),
    (
        "misspelled field",
        yaml_replace("clearance: 0.25\n", "clearence: 0.25\n"),
        YAML,
        ["clearence: unknown field 'clearence' (did you mean 'clearance'?) (and 1 more error)"],
    ),
    (
        "misspelled nested field",
        yaml_replace("  rate: 0.5\n", "  rat: 0.5\n"),
        YAML,
        ["feedback.rat: unknown field 'rat' (did you mean 'rate'?)", "input_weights, rate"],
    ),
    (
        "no Unsafe set",
        yaml_replace("unsafe:\n  " + BLOCK, "unsafe: {}"),
        YAML,
        ["unsafe: no Unsafe set; found {}", "at least one named polygon"],
    ),
    (
        "clearance larger than Goal allows",
        yaml_replace("clearance: 0.25", "clearance: 0.6"),
        YAML,
        ["clearance: does not fit in Goal", "radius 0.5", "found 0.6", "below 0.5"],
    ),
    (
        "absolute demo path",
        yaml_replace("file: demos/straight.csv", "file: /etc/hostname"),
        YAML,
        ["demos.0.file: demo file outside the scenario folder", "found '/etc/hostname'"],
    ),
    (
        "demo path out of the folder",
        yaml_replace("file: demos/straight.csv", "file: ../scenario/demos/../../x.csv"),
        YAML,
        ["demos.0.file: demo file outside the scenario folder"],
    ),
    (
        "underscore digits in a CSV",
        csv_replace("0.1,1.0,0.0", "0.1,0_5,0.0"),
        CSV,
        ["row 4: not a number: '0_5'", "expected decimal numbers"],
    ),
    (
        "non-ASCII digits in a CSV",
        csv_replace("0.1,1.0,0.0", "0.1,\u0661,0.0"),
        CSV,
        ["row 4: not a number: '\u0661'"],
    ),
    (
        "demo too long for the tube's decay",
        csv_write(demo_csv([1.0] * 20 + [-1.0] * 20 + [0.0] * 12000, [0.0] * 12040)),
        CSV,
        ["demo lasts 1204 s", "at most 1200 s at feedback.rate = 0.5 1/s"],
    ),
    (
        "extra nested field",
        yaml_replace("    x0: [", "    speed: 3\n    x0: ["),
        YAML,
        ["demos.0.speed: unknown field"],
    ),
    (
        "wrong type",
        yaml_replace("sampling_time: 0.1", "sampling_time: fast"),
        YAML,
        ["sampling_time: invalid value", "found 'fast'", "expected a valid number"],
    ),
    (
        "wrong type in a list",
        yaml_replace("states: [X, Y, vX, vY]", "states: X"),
        YAML,
        ["states: invalid value", "found 'X'", "expected a valid list"],
    ),
    (
        "several errors",
        yaml_replace("sampling_time: 0.1", "sampling_time: fast\ncolour: red"),
        YAML,
        ["(and 1 more error)"],
    ),
    (
        "state name not an identifier",
        yaml_replace("states: [X, Y, vX, vY]", "states: [X, Y, vX, 'v Y']"),
        YAML,
        ["states.3: invalid value", "found 'v Y'", "pattern"],
    ),
    (
        "reserved name",
        yaml_replace("parameters: {k: 1.0}", "parameters: {k: 1.0, sin: 2.0}"),
        YAML,
        ["states/inputs/parameters", "name 'sin' is reserved"],
    ),
    (
        "name declared twice",
        yaml_replace("parameters: {k: 1.0}", "parameters: {k: 1.0, aX: 2.0}"),
        YAML,
        ["states/inputs/parameters", "name 'aX' declared twice", "expected distinct names"],
    ),
    (
        "dynamics missing a state",
        yaml_replace("  vY: k*aY\n", ""),
        YAML,
        ["dynamics: missing entry 'vY'"],
    ),
    (
        "unknown symbol in dynamics",
        yaml_replace("vX: k*aX", "vX: k*aX + z"),
        YAML,
        ["dynamics.vX", "unknown symbol 'z'", "known: X, Y, aX, aY, k, vX, vY, pi", "'k*aX + z'"],
    ),
    (
        "unknown function in dynamics",
        yaml_replace("vX: k*aX", "vX: cosh(aX)"),
        YAML,
        ["dynamics.vX", "unknown function 'cosh'", "allowed: sin, cos"],
    ),
    (
        "__import__ in dynamics",
        yaml_replace("vX: k*aX", "vX: __import__('os')"),
        YAML,
        ["dynamics.vX", "unknown function '__import__'", "found \"__import__('os')\""],
    ),
    (
        "attribute access in dynamics",
        yaml_replace("vX: k*aX", "vX: aX.real"),
        YAML,
        ["dynamics.vX", "'aX.real' is not allowed", "found 'aX.real'"],
    ),
    (
        "wrong argument count in dynamics",
        yaml_replace("vX: k*aX", "vX: sin(aX, aY)"),
        YAML,
        ["dynamics.vX", "sin takes 1 argument, got 2"],
    ),
    (
        "huge power in dynamics",
        yaml_replace("vX: k*aX", "vX: 10**10**10"),
        YAML,
        ["dynamics.vX", "is not a finite real number", "found '10**10**10'"],
    ),
    (
        "division by zero in dynamics",
        chain(
            yaml_replace("parameters: {k: 1.0}", "parameters: {k: 0.0}"),
            yaml_replace("vX: k*aX", "vX: aX/k"),
        ),
        YAML,
        ["dynamics.vX", "not a finite real expression", "found 'aX/k'"],
    ),
    (
        "complex value in dynamics",
        yaml_replace("vX: k*aX", "vX: sqrt(-1)*aX"),
        YAML,
        ["dynamics.vX", "not a finite real expression", "no division by zero and no complex"],
    ),
    (
        "lower bound above upper bound",
        yaml_replace("aX: [-2.0, 2.0]", "aX: [2.0, -2.0]"),
        YAML,
        ["input_bounds.aX: invalid value", "found [2.0, -2.0]", "lower bound 2.0 is above upper"],
    ),
    (
        "Init interval reversed",
        yaml_replace("Y: [0.0, 1.0]", "Y: [1.0, 0.0]"),
        YAML,
        ["init.Y: invalid value", "found [1.0, 0.0]", "lower bound 1.0 is above upper bound 0.0"],
    ),
    (
        "Ts = 0",
        yaml_replace("sampling_time: 0.1", "sampling_time: 0"),
        YAML,
        ["sampling_time: invalid value", "found 0", "expected greater than 0"],
    ),
    (
        "Ts < 0",
        yaml_replace("sampling_time: 0.1", "sampling_time: -0.1"),
        YAML,
        ["sampling_time: invalid value", "found -0.1", "expected greater than 0"],
    ),
    (
        "NaN in the YAML",
        yaml_replace("clearance: 0.25", "clearance: .nan"),
        YAML,
        ["clearance: invalid value", "found nan", "expected a finite number"],
    ),
    (
        "inf in the YAML",
        yaml_replace("[[2, 2], [3, 2],", "[[2, .inf], [3, 2],"),
        YAML,
        ["unsafe.block.0.1: invalid value", "found inf", "expected a finite number"],
    ),
    (
        "self-intersecting polygon",
        yaml_replace(BLOCK, "block: [[2, 2], [3, 3], [3, 2], [2, 3]]"),
        YAML,
        ["unsafe.block: invalid polygon (Self-intersection[2.5 2.5])", "expected a simple polygon"],
    ),
    (
        "degenerate (collinear) polygon",
        yaml_replace(
            "polygon: [[4, 0], [5, 0], [5, 1], [4, 1]]", "polygon: [[4, 0], [5, 0], [6, 0]]"
        ),
        YAML,
        ["goal.polygon: invalid polygon (", "expected a simple polygon"],
    ),
    (
        "polygon with two vertices",
        yaml_replace(BLOCK, "block: [[2, 2], [3, 2]]"),
        YAML,
        ["unsafe.block: invalid value", "found [[2, 2], [3, 2]]", "at least 3 items"],
    ),
    (
        "Init overlaps Unsafe",
        yaml_replace(BLOCK, "block: [[0.5, 0.5], [3, 2], [3, 3], [2, 3]]"),
        YAML,
        ["init: overlaps Unsafe set 'block'", "POLYGON ((0 0, 1 0, 1 1, 0 1, 0 0))", "disjoint"],
    ),
    (
        "Init point inside Unsafe",
        yaml_replace("X: [0.0, 1.0]\n  Y: [0.0, 1.0]", "X: [2.5, 2.5]\n  Y: [2.5, 2.5]"),
        YAML,
        ["init: overlaps Unsafe set 'block' (for example at position (2.5, 2.5))", "POINT (2.5"],
    ),
    (
        "Goal overlaps Unsafe",
        yaml_replace(BLOCK, "block: [[2, 2], [4.5, 0.5], [3, 3], [2, 3]]"),
        YAML,
        ["goal.polygon: overlaps Unsafe set 'block'", "POLYGON ((4 0, 5 0, 5 1, 4 1, 4 0))"],
    ),
    (
        "position names one state twice",
        yaml_replace("position: [X, Y]", "position: [X, X]"),
        YAML,
        ["position: the same state twice", "found ['X', 'X']", "two different states"],
    ),
    (
        "feedback weights of the wrong length",
        yaml_replace("state_weights: [1, 1, 1, 1]", "state_weights: [1, 1, 1]"),
        YAML,
        ["feedback.state_weights: wrong length 3", "expected 4 values"],
    ),
    (
        "demo x0 of the wrong length",
        yaml_replace("x0: [0.5, 0.5, 0.0, 0.0]", "x0: [0.5, 0.5, 0.0]"),
        YAML,
        ["demos.0.x0: wrong length 3", "expected 4 values (X, Y, vX, vY)"],
    ),
    (
        "demo x0 outside Init",
        yaml_replace("x0: [0.5, 0.5, 0.0, 0.0]", "x0: [1.5, 0.5, 0.0, 0.0]"),
        YAML,
        ["demos.0.x0: initial state outside Init in 'X'", "found 1.5", "a value in [0, 1]"],
    ),
    (
        "demo file missing",
        yaml_replace("demos/straight.csv", "demos/missing.csv"),
        "missing.csv",
        ["cannot read demo file (No such file or directory)"],
    ),
    (
        "demo file not text",
        csv_write(b"\xff\xfe\x00\x01"),
        CSV,
        ["cannot read demo file (not UTF-8 text)"],
    ),
    (
        "demo CSV wrong header",
        csv_replace("t,aX,aY", "t,aY,aX"),
        CSV,
        ["row 2: wrong header", "found 't,aY,aX'", "expected t,aX,aY"],
    ),
    (
        "demo CSV wrong column count",
        csv_replace("0.2,1.0,0.0", "0.2,1.0"),
        CSV,
        ["row 5: wrong column count 2", "found '0.2,1.0'", "expected 3 columns (t,aX,aY)"],
    ),
    (
        "demo CSV not a number",
        csv_replace("0.2,1.0,0.0", "0.2,one,0.0"),
        CSV,
        ["row 5: not a number", "found '0.2,one,0.0'"],
    ),
    (
        "demo CSV NaN",
        csv_replace("0.2,1.0,0.0", "0.2,nan,0.0"),
        CSV,
        ["row 5: non-finite value in column 'aX'", "found nan", "expected a finite number"],
    ),
    (
        "demo CSV inf",
        csv_replace("0.2,1.0,0.0", "0.2,1.0,-inf"),
        CSV,
        ["row 5: non-finite value in column 'aY'", "found -inf", "expected a finite number"],
    ),
    (
        "demo time not a whole number of samples",
        csv_replace("0.2,1.0,0.0", "0.25,1.0,0.0"),
        CSV,
        ["row 5: t is not a whole number of samples (sample 2, Ts = 0.1)", "found 0.25", "t = 0.2"],
    ),
    (
        "demo with no samples",
        csv_write("# nothing\nt,aX,aY\n"),
        CSV,
        ["no samples"],
    ),
    (
        "demo input outside its bounds",
        csv_replace("0.2,1.0,0.0", "0.2,5.0,0.0"),
        CSV,
        ["row 5: input 'aX' outside its bounds", "found 5.0", "[-2, 2] (input_bounds.aX)"],
    ),
    (
        "demo enters Unsafe",
        csv_write(DIAGONAL),
        CSV,
        ["demo 'straight' enters Unsafe set 'block' at t = 1.75 s", "position (2.031, 2.031)"],
    ),
    (
        "demo does not end in Goal",
        csv_write(SHORT),
        CSV,
        ["demo 'straight' does not end in Goal: at t = 4.00 s", "position (2.500, 0.500)"],
    ),
]


def _apply(case: Mutation, tmp_path: Path) -> str:
    return case(write_scenario(tmp_path / "scenario"))


@pytest.mark.parametrize("fast", [True, False], ids=["libyaml", "pure Python"])
def test_a_number_in_exponent_form_is_a_number_and_yaml_s_own_loader_is_untouched(
    tmp_path: Path, fast: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``25e-2`` is 0.25 (YAML 1.2; PyYAML's YAML 1.1 reads text, which the schema refuses where
    a number belongs), with either of the scenario loader's parsers; ``yaml.safe_load`` still
    reads text."""
    import yaml

    from pipeline.model import safe_yaml

    if not fast:
        monkeypatch.setattr(safe_yaml, "_FAST_LOADER", None)
    path = yaml_replace("clearance: 0.25\n", "clearance: 25e-2\nfeedback_period: 1E-2\n")(
        write_scenario(tmp_path / "scenario")
    )
    scenario = load_scenario(path)
    assert scenario.clearance == 0.25 and scenario.feedback_period == 0.01
    assert yaml.safe_load("a: 1e6") == {"a": "1e6"}


def test_fixture_is_valid(tmp_path: Path) -> None:
    scenario = load_scenario(write_scenario(tmp_path / "scenario"))
    assert scenario.n == 4 and scenario.m == 2 and scenario.demos[0].N == 40
    assert scenario.in_goal(scenario.demos[0].x0 + [4.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    ("mutation", "file", "parts"),
    [pytest.param(m, f, p, id=i) for i, m, f, p in BAD_INPUTS],
)
def test_bad_input_message(mutation: Mutation, file: str | None, parts: list[str], tmp_path: Path):
    target = _apply(mutation, tmp_path)
    with pytest.raises(ScenarioError) as raised:
        load_scenario(target)
    message = str(raised.value)
    assert "\n" not in message
    if file is not None:
        assert message.startswith(str(tmp_path / "scenario")) and f"{file}: " in message
    for part in parts:
        assert part in message


@pytest.mark.parametrize("mutation", [pytest.param(m, id=i) for i, m, _f, _p in BAD_INPUTS])
def test_bad_input_exits_2_in_one_line(
    mutation: Mutation, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = _apply(mutation, tmp_path)
    code = main(["synthesize", target, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "mutation",
    [yaml_replace("vX: k*aX", "vX: __import__('os')"), unknown_name],
    ids=["forbidden expression", "unknown scenario"],
)
def test_subprocess_exit_code_2_without_traceback(mutation: Mutation, tmp_path: Path) -> None:
    target = _apply(mutation, tmp_path)
    result = subprocess.run(
        [sys.executable, "-m", "pipeline", "synthesize", target],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1


def test_forbidden_expression_is_never_evaluated(tmp_path: Path) -> None:
    marker = tmp_path / "evaluated"
    text = f"__import__('os').system('touch {marker}')"
    target = _apply(yaml_replace("vX: k*aX", f'vX: "{text}"'), tmp_path)
    with pytest.raises(ScenarioError, match="is not allowed"):
        load_scenario(target)
    assert not marker.exists()


def test_numeric_dynamics_entry_is_accepted(tmp_path: Path) -> None:
    """A fifth state ``Z`` with ``dZ/dt = 0`` written as the YAML number 0, not the text "0"."""
    add_state = chain(
        yaml_replace("X: vX\n", "X: vX\n  Z: 0\n"),
        yaml_replace("states: [X, Y, vX, vY]", "states: [X, Y, vX, vY, Z]"),
        yaml_replace("  vY: [0.0, 0.0]\n", "  vY: [0.0, 0.0]\n  Z: [0.0, 0.0]\n"),
        yaml_replace("reference_state: [0, 0, 0, 0]", "reference_state: [0, 0, 0, 0, 0]"),
        yaml_replace("state_weights: [1, 1, 1, 1]", "state_weights: [1, 1, 1, 1, 1]"),
        yaml_replace("x0: [0.5, 0.5, 0.0, 0.0]", "x0: [0.5, 0.5, 0.0, 0.0, 0.0]"),
    )
    target = _apply(add_state, tmp_path)
    scenario = load_scenario(target)
    assert scenario.dynamics.expressions[4] == 0


# --- the expression grammar on its own --------------------------------------------------------

SYMBOLS = {name: sympy.Symbol(name, real=True) for name in ["x", "y"]}
x, y = SYMBOLS["x"], SYMBOLS["y"]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("x + 2*y - 3", x + 2 * y - 3),
        ("-x**2 / y", -(x**2) / y),
        ("+x", x),
        ("sin(x) * cos(y) + tan(x)", sympy.sin(x) * sympy.cos(y) + sympy.tan(x)),
        ("exp(x) + log(y) + sqrt(x)", sympy.exp(x) + sympy.log(y) + sympy.sqrt(x)),
        ("tanh(x) + atan(y) + atan2(y, x)", sympy.tanh(x) + sympy.atan(y) + sympy.atan2(y, x)),
        ("abs(x) * pi", sympy.Abs(x) * sympy.pi),
        ("2**-1 * x", 0.5 * x),
        ("1.5e-3", sympy.Float(1.5e-3)),
    ],
)
def test_allowed_expressions(text: str, expected: sympy.Expr) -> None:
    assert sympy.simplify(parse_expression(text, SYMBOLS) - expected) == 0


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os')",
        "x.real",
        "().__class__",
        "x[0]",
        "lambda: 1",
        "'text'",
        "True",
        "x if y else 1",
        "x < y",
        "x and y",
        "[x for x in y]",
        "sin(x=1)",
        "sin(*x)",
        "(x := 1)",
        "x % y",
        "x // y",
        "open('f')",
        "eval('1')",
        "1e400",
        "10**10**10",
        "atan2(x)",
        "x +",
        "(" * 500 + "x" + ")" * 500,
        "x + " * 5000 + "x",
    ],
)
def test_forbidden_expressions(text: str) -> None:
    with pytest.raises(ExpressionError):
        parse_expression(text, SYMBOLS)


# --- the published schema ---------------------------------------------------------------------


def test_committed_json_schema_is_current() -> None:
    committed = json.loads((REPO / "scenarios" / "scenario.schema.json").read_text())
    assert committed == json.loads(json.dumps(json_schema())), (
        "scenarios/scenario.schema.json is stale; regenerate it with "
        "`python -m pipeline schema > scenarios/scenario.schema.json`"
    )


def test_schema_command_prints_the_schema(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(json_schema()))


@pytest.mark.parametrize("name", available_scenarios())
def test_shipped_scenarios_load_without_demos(name: str) -> None:
    scenario = load_scenario(name, check_demos=False)
    assert scenario.name == name


def test_labels_and_units_name_quantities_for_people() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    assert scenario.label("u1") == "u1 (thrust) [N]"
    assert scenario.label("theta", unit=False) == "theta (pitch)"
    assert scenario.unit("u2") == "rad/s^2"
    assert scenario.state_bounds["theta"] == (-0.8, 0.8)
    plain = load_scenario("double_integrator", check_demos=False)
    assert plain.label("vx") == "vx [m/s]"
    assert plain.certificate == "constant" and plain.optimizer == "gd"
    assert scenario.certificate == "funnel" and scenario.optimizer == "lbfgs"
