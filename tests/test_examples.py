"""``examples/fly_controller.py`` runs as a user would run it, on the controller the pipeline
emitted, and says what it saw."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.model.scenario import available_scenarios, load_scenario

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "fly_controller.py"


def _fly(controller: Path, tmp_path: Path, *extra: str) -> str:
    run = subprocess.run(
        [sys.executable, str(EXAMPLE), str(controller), *extra],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    return run.stdout


def test_example_flies_a_covered_start_into_goal_at_100_hz(synthesized, tmp_path):
    _, out = synthesized
    figure = tmp_path / "flight.png"
    start = ("--start", "1.5", "2.5", "0", "0", "0", "0")
    text = _fly(
        out / "controller.json", tmp_path, *start, "--period", "0.01", "--plot", str(figure)
    )
    assert "covered, coverage ratio" in text and "NOT covered" not in text
    assert re.search(r"trajectory \d+: demo_\d\d ", text), text  # the index and its demo
    hill = float(re.search(r"closest to Unsafe 'hill' ([\d.]+) m", text).group(1))
    assert hill > 0.5  # the tube keeps d = 1 m; a held 100 Hz feedback stays well clear
    assert " in Goal" in text
    assert figure.stat().st_size > 10_000


def test_example_flags_a_start_outside_the_certificate(synthesized, tmp_path):
    _, out = synthesized
    text = _fly(out / "controller.json", tmp_path, "--start", "6", "6", "0", "0", "0", "0")
    ratio = float(re.search(r"coverage ratio ([\d.]+)", text).group(1))
    assert "NOT covered" in text and ratio > 1


def test_example_refuses_a_bad_controller_file_with_exit_2(tmp_path):
    bad = tmp_path / "controller.json"
    bad.write_text('{"format": "safety-controller/1"}')
    run = subprocess.run(
        [sys.executable, str(EXAMPLE), str(bad)], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 2 and "Traceback" not in run.stderr


def test_example_flies_a_funnel_file_into_goal(quadrotor_funnel_artifact, tmp_path):
    """safety-controller/2 (one quadrotor funnel): a covered start near the funnel's centre
    flies clear of the hill into Goal, and the figure draws the time-varying tube."""
    _, path = quadrotor_funnel_artifact
    figure = tmp_path / "flight.png"
    start = ("--start", "1.4", "2.2", "0", "0", "0", "0")
    text = _fly(path, tmp_path, *start, "--period", "0.01", "--plot", str(figure))
    assert "covered, coverage ratio" in text and "(funnel certificate)" in text
    assert "NOT covered" not in text
    hill = float(re.search(r"closest to Unsafe 'hill' ([\d.]+) m", text).group(1))
    assert hill > 0.5 and " in Goal" in text
    assert figure.stat().st_size > 10_000


# the example's ``main`` called once per argument list in one interpreter, as ``python EXAMPLE
# ARGS`` calls it (the module loaded by path, not as ``__main__``): the imports the example
# pulls in (SciPy, SymPy, shapely, matplotlib; ~1.5 s of CPU per interpreter) are paid once
_FLY_ALL = """
import contextlib, io, json, runpy, sys
main = runpy.run_path(sys.argv[1], run_name="fly_controller")["main"]
results = []
for argv in json.loads(sys.argv[2]):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    results.append([code, out.getvalue(), err.getvalue()])
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def every_shipped_flight(tmp_path_factory) -> dict[str, tuple[str, Path]]:
    """name -> (the example's output, its figure) for a controller.json of each shipped
    scenario (emitted cheaply: the scenario's feedback around its first demo, which ends in
    Goal), flown from that demo's start; the example's ``main`` ran with exit code 0 and wrote
    nothing on stderr for each."""
    from stages.controller import emit_controller
    from stages.feedback import design_feedback

    cases, argvs = {}, []
    for name in available_scenarios():
        scenario = load_scenario(name)
        feedback = design_feedback(scenario)
        demo = scenario.demos[0]
        folder = tmp_path_factory.mktemp(f"example_{name}")
        path = folder / "controller.json"
        emit_controller(
            scenario, feedback.K, feedback.P, feedback.rate, [demo.x0], [demo.us], [0.01], path,
            names=[demo.name],
        )  # fmt: skip
        figure = folder / "flight.png"
        argvs.append(
            [str(path), "--start", *(repr(float(v)) for v in demo.x0), "--plot", str(figure)]
        )
        cases[name] = figure
    run = subprocess.run(
        [sys.executable, "-c", _FLY_ALL, str(EXAMPLE), json.dumps(argvs)],
        cwd=tmp_path_factory.mktemp("examples"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    results = json.loads(run.stdout)
    flights = {}
    for (name, figure), (code, out, err) in zip(cases.items(), results, strict=True):
        assert code == 0 and not err, (name, code, err)
        flights[name] = (out, figure)
    return flights


@pytest.mark.xdist_group("examples")  # one worker makes the module fixture
@pytest.mark.parametrize("name", available_scenarios())
def test_example_flies_every_shipped_scenario(name, every_shipped_flight):
    """Nothing in the example is any one scenario's: a controller.json for each shipped scenario
    flies from its first demo's start along it into Goal, naming the trajectory by index and demo
    and every Unsafe region of the scenario, and draws the figure."""
    scenario = load_scenario(name)
    demo = scenario.demos[0]
    text, figure = every_shipped_flight[name]
    assert f"covered, coverage ratio 0.000, trajectory 0: {demo.name} (constant" in text, text
    for region in scenario.unsafe:
        assert f"'{region}' " in text
    T = len(demo.us) * scenario.Ts
    assert f"at T = {T:g} s in Goal" in text, text
    assert figure.stat().st_size > 10_000
    assert float(re.search(r"flight of ([\d.]+) s", text).group(1)) >= round(T, 2)
