"""Inputs that once hung or crashed: each case runs under a time limit, so a hang fails the test.

Hangs: a YAML alias bomb ("billion laughs"), a self-referencing alias, a nesting too deep, and
the covering-radius bisection on a single-point Init. Crashes: ``demos: []``, ``abs()`` in the
dynamics (now bounded soundly by the Jacobian hull), a Goal too small for the tubes the
coverage needs. Every case ends in exit 2 with one line, or in a finished run.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import sympy

from pipeline import ScenarioError, load_scenario
from pipeline.model import safe_yaml
from pipeline.model.dynamics import Dynamics
from pipeline.model.scenario import Scenario
from pipeline.numerics.hull import jacobian_hull
from pipeline.runtime.cli import main
from stages.coverage import MAX_BISECTIONS, cover_init, covering_radius
from tests.helpers.scenario_files import chain, write_scenario, yaml_replace
from tests.helpers.timing import time_limit

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "scenarios"
CLI_TIME_LIMIT = 300  # s, a whole small synthesis
LOAD_TIME_LIMIT = 10  # s, loading one scenario


def run_cli(*args: str, timeout: float = CLI_TIME_LIMIT) -> subprocess.CompletedProcess[str]:
    """``python -m pipeline ARGS`` from the repository; ``TimeoutExpired`` fails the test."""
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def synthesize_in_process(
    capsys: pytest.CaptureFixture[str], *args: str
) -> subprocess.CompletedProcess[str]:
    """``python -m pipeline synthesize ARGS`` run in this process under ``CLI_TIME_LIMIT`` (a
    hang fails the test): the same exit code and output as ``run_cli`` without starting Python
    and importing the pipeline again; an exception that ``main`` does not turn into exit 2
    fails the test with its traceback."""
    capsys.readouterr()
    with time_limit(CLI_TIME_LIMIT):
        code = main(["synthesize", *args])
    printed = capsys.readouterr()
    return subprocess.CompletedProcess(["synthesize", *args], code, printed.out, printed.err)


def assert_one_line_exit_2(result: subprocess.CompletedProcess[str], *parts: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("error: ") and result.stderr.count("\n") == 1
    for part in parts:
        assert part in result.stderr


def billion_laughs(levels: int = 9, width: int = 9) -> str:
    """``levels`` anchors each listing ``width`` aliases of the one before: width^levels
    strings from a file of about a kilobyte."""
    lines = [f"a0: &a0 [{', '.join(['lol'] * width)}]"]
    for level in range(1, levels):
        lines.append(f"a{level}: &a{level} [{', '.join([f'*a{level - 1}'] * width)}]")
    return "\n".join([*lines, f"name: *a{levels - 1}"]) + "\n"


# --- YAML limits -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "parts"),
    [
        pytest.param(
            billion_laughs(), ["aliases expand to more than 100,000 YAML nodes"], id="bomb"
        ),
        pytest.param(
            "name: &x [1, *x]\n", ["self-referencing alias", "line 1 contains itself"], id="cycle"
        ),
        pytest.param(
            "a: &a 1\nb: [" + ", ".join(["*a"] * (safe_yaml.MAX_ALIASES + 1)) + "]\n",
            ["more than 100 aliases"],
            id="many aliases",
        ),
        pytest.param("[" * 100_000 + "]" * 100_000, ["YAML is nested too deeply"], id="deep"),
        pytest.param(
            "description: " + "x" * safe_yaml.MAX_BYTES + "\n",
            ["file is larger than 1,000,000 bytes"],
            id="huge",
        ),
    ],
)
def test_hostile_yaml_is_refused_quickly(text: str, parts: list[str], tmp_path: Path) -> None:
    path = tmp_path / "scenario.yaml"
    path.write_text(text)
    started = time.perf_counter()
    with time_limit(LOAD_TIME_LIMIT), pytest.raises(ScenarioError) as raised:
        load_scenario(path)
    assert time.perf_counter() - started < LOAD_TIME_LIMIT
    message = str(raised.value)
    assert message.startswith(str(path)) and "\n" not in message
    for part in parts:
        assert part in message


def test_alias_bomb_exits_2_from_the_command_line(tmp_path: Path) -> None:
    path = tmp_path / "scenario.yaml"
    path.write_text(billion_laughs())
    assert len(path.read_bytes()) < 1600
    result = run_cli("synthesize", str(path), "--out", str(tmp_path / "out"), timeout=60)
    assert_one_line_exit_2(result, "aliases expand to more than")


def test_a_few_plain_aliases_are_still_accepted(tmp_path: Path) -> None:
    """Anchors and aliases are YAML; only their unbounded expansion is refused."""
    path = write_scenario(tmp_path / "scenario")
    text = path.read_text()
    text = text.replace("  aX: [-2.0, 2.0]\n  aY", "  aX: &bounds [-2.0, 2.0]\n  aY", 1)
    text = text.replace("operating_region:\n  aX: [-2.0, 2.0]", "operating_region:\n  aX: *bounds")
    path.write_text(text)
    with time_limit(LOAD_TIME_LIMIT):
        scenario = load_scenario(path)
    assert scenario.operating_region["aX"] == (-2.0, 2.0)


def test_expanded_size_counts_shared_nodes_once_per_use() -> None:
    node = safe_yaml._ScenarioLoader("a: &a [1, 2]\nb: [*a, *a, *a]\n").get_single_node()
    # mapping 1 + keys 2 + a (1 + 2) + b (1 + 3 * 3) = 16
    assert safe_yaml.expanded_size(node) == 16


# --- single-point Init ---------------------------------------------------------------------------


def point_init_scenario(tmp_path: Path) -> Scenario:
    """The test fixture with Init shrunk to the point (0.5, 0.5) at rest."""
    point = chain(
        yaml_replace("X: [0.0, 1.0]", "X: [0.5, 0.5]"),
        yaml_replace("Y: [0.0, 1.0]", "Y: [0.5, 0.5]"),
    )
    return load_scenario(point(write_scenario(tmp_path / "scenario")), check_demos=False)


def test_covering_radius_of_a_point_is_the_distance_to_the_nearest_start(tmp_path: Path) -> None:
    scenario = point_init_scenario(tmp_path)
    metric = SimpleNamespace(P=np.diag([4.0, 1.0, 1.0, 1.0]))
    centers = np.array([[0.5, 0.5, 0, 0], [0.0, 0.5, 0, 0], [0.5, 0.0, 0, 0]], dtype=float)
    with time_limit(LOAD_TIME_LIMIT):
        at_start = covering_radius(scenario, metric, centers, upper=1.0)
        away = covering_radius(scenario, metric, centers[1:], upper=1.0)
    assert at_start.covered and at_start.radius == 0.0 and at_start.kept_radius(0.3) == 0.3
    # ||(0.5, 0)||_P = 2 * 0.5 = 1 to the second start, 0.5 to the third.
    assert away.covered and away.radius == pytest.approx(0.5, rel=1e-9)
    assert cover_init(scenario, metric, centers[1:], [0.0, away.radius]).covered
    assert not cover_init(scenario, metric, centers[1:], [0.0, 0.999 * away.radius]).covered


def test_covering_radius_bisection_is_bounded(tmp_path: Path) -> None:
    """``tolerance=0`` cannot be met in floating point; the bisection still stops."""
    scenario = load_scenario(write_scenario(tmp_path / "scenario"), check_demos=False)
    metric = SimpleNamespace(P=np.eye(4))
    with time_limit(120):
        result = covering_radius(scenario, metric, [[0.5, 0.5, 0, 0]], upper=1.0, tolerance=0.0)
    assert result.covered and result.tries == MAX_BISECTIONS + 1
    assert result.radius == pytest.approx(np.hypot(0.5, 0.5), rel=1e-6)
    assert "stopped after" in result.message


@pytest.mark.slow
def test_single_point_init_synthesizes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The shipped double integrator with Init shrunk to its first demo's start."""
    folder = tmp_path / "point"
    shutil.copytree(SHIPPED / "double_integrator", folder)
    path = folder / "scenario.yaml"
    text = path.read_text()
    text = text.replace("x: [0.0, 1.0]", "x: [0.167, 0.167]")
    text = text.replace("y: [0.0, 1.0]", "y: [0.167, 0.167]")
    path.write_text(
        "".join(line for line in text.splitlines(True) if "demo_0" not in line or "demo_01" in line)
    )
    out = tmp_path / "out"
    result = synthesize_in_process(capsys, str(path), "--out", str(out), "--samples", "20", "-q")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "certified and validated" in result.stdout


# --- crashes on plausible inputs ---------------------------------------------------------------


def test_no_demos_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_scenario(tmp_path / "scenario")
    yaml_replace("demos:\n  - file: demos/straight.csv\n    x0: [0.5, 0.5, 0.0, 0.0]", "demos: []")(
        path
    )
    load_scenario(path)  # valid to load (the recorder adds demos to such a file)
    code = main(["synthesize", str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "demos: no demonstrations to synthesize from; found []" in err
    assert "python -m pipeline record double_integrator" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_goal_too_small_for_the_covering_tubes_finishes_with_a_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Clearance 0.45 fits Goal (a 1 m square), but the tube that covers Init from one start
    is wider: the optimizer keeps the demo as flown and says why; no traceback."""
    path = write_scenario(tmp_path / "scenario")
    yaml_replace("clearance: 0.25", "clearance: 0.45")(path)
    out = tmp_path / "out"
    result = synthesize_in_process(capsys, str(path), "--out", str(out), "--samples", "20", "-q")
    assert result.returncode in (0, 1) and "Traceback" not in result.stderr, result.stderr
    summary = (out / "summary.json").read_text()
    assert "was not optimized: Goal shrunk by d + eps_g" in summary


# --- abs() in the dynamics ---------------------------------------------------------------------


def test_hull_of_abs_holds_every_jacobian_including_the_kink() -> None:
    v, w, u = sympy.symbols("v w u", real=True)
    f = [u - 0.3 * sympy.Abs(v) * v + sympy.Abs(w - 1), -sympy.Abs(v)]
    dynamics = Dynamics.from_expressions([v, w], [u], f)
    region = {"v": (-2.0, 3.0), "w": (0.5, 4.0), "u": (-1.0, 1.0)}
    hull = jacobian_hull(dynamics, region)
    lower, upper = hull.vertices.min(axis=0), hull.vertices.max(axis=0)
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(-2, 3, 2000), rng.uniform(0.5, 4, 2000)])
    x[:10, 0] = 0.0  # on the kinks
    x[10:20, 1] = 1.0
    us = rng.uniform(-1, 1, (2000, 1))
    J = np.concatenate([dynamics.f_x(x, us), dynamics.f_u(x, us)], axis=-1)
    assert np.all(J >= lower - 1e-9) and np.all(J <= upper + 1e-9)
    # d|v|/dv = sign(v): its range holds the generalised derivative [-1, 1] at the kink.
    assert lower[1, 0] == pytest.approx(-1.0) and upper[1, 0] == pytest.approx(1.0)
    assert lower[0, 1] == pytest.approx(-1.0) and upper[0, 1] == pytest.approx(1.0)
    # d(-0.3 |v| v)/dv = -0.6 |v| in [-1.8, 0], enclosed by boxes over pieces of [-2, 3] (the
    # binary constant 0.3 is 0.29999999999999998890: the exact bound is -1.7999999999999998)
    assert lower[0, 0] <= -1.8 + 1e-12 and 0.0 <= upper[0, 0] <= 0.2


@pytest.mark.slow
def test_abs_in_the_dynamics_is_certified(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A drag ``-0.1 |vY|`` (the demo flies at vY = 0, on the kink)."""
    path = write_scenario(tmp_path / "scenario")
    yaml_replace("vY: k*aY", "vY: k*aY - 0.1*abs(vY)")(path)
    yaml_replace(
        "operating_region:\n  aX: [-2.0, 2.0]",
        "operating_region:\n  aX: [-2.0, 2.0]\n  vY: [-3.0, 3.0]",
    )(path)
    out = tmp_path / "out"
    result = synthesize_in_process(capsys, str(path), "--out", str(out), "--samples", "20", "-q")
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == 0 and "certified and validated" in result.stdout, result.stdout
    summary = (out / "summary.json").read_text()
    assert "hull vertices" in summary


@pytest.mark.skipif(safe_yaml._LIBYAML is None, reason="PyYAML without libyaml")
@pytest.mark.parametrize(
    "name", ["quadrotor_hill_flythrough", "unicycle_slalom", "double_integrator"]
)
def test_libyaml_composes_what_the_reference_loader_does(name: str, tmp_path: Path) -> None:
    """The fast path (libyaml composes, the same constructor builds) gives the reference
    loader's data, also with anchors and aliases; its alias count is the reference's."""
    text = load_scenario(name, check_demos=False).path.read_text()
    text += "\nx_anchor: &a {p: [1, 2.5, null, yes]}\nx_uses: [*a, *a, {q: *a}]\n"
    reference = safe_yaml._ScenarioLoader(text)
    expected = reference.get_data()
    fast = safe_yaml._compose_with_libyaml(text)
    assert fast is not None
    node, loader = fast
    assert loader.construct_document(node) == expected
    assert safe_yaml._aliases(node) == reference.aliases == 3
    path = tmp_path / "scenario.yaml"
    path.write_text(text)
    assert safe_yaml.load_yaml(path) == expected


@pytest.mark.skipif(safe_yaml._LIBYAML is None, reason="PyYAML without libyaml")
def test_what_libyaml_refuses_the_reference_loader_reports(tmp_path: Path) -> None:
    """A syntax error, too many aliases, nesting past libyaml's limit, a tab (which libyaml
    would accept): the fast path steps aside and the message is the reference loader's
    (PyYAML's words and place)."""
    many = "a: &a 1\nb: [" + ", ".join(["*a"] * (safe_yaml.MAX_ALIASES + 1)) + "]\n"
    cases = {
        "a: [1, 2\nb: 3\n": "line 2, column 2: expected ',' or ']', but got ':'",
        many: f"more than {safe_yaml.MAX_ALIASES} aliases",
        "a: " + "[" * 2000 + "]" * 2000 + "\n": "nested too deeply",
        "a:\t1\n": "line 1, column 3: found character '\\t' that cannot start any token",
    }
    for text, message in cases.items():
        assert safe_yaml._compose_with_libyaml(text) is None
        path = tmp_path / "scenario.yaml"
        path.write_text(text)
        with pytest.raises(ScenarioError, match=re.escape(message)):
            safe_yaml.load_yaml(path)
