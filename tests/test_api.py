"""The Python API (``pipeline.synthesize``, ``load_scenario``, ``load_controller``): a frozen
result, no printing, outputs under the current directory, and its options kept in step with the
command line's."""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pipeline
from pipeline.runtime.cli import main
from pipeline.runtime.options import RunOptions
from pipeline.runtime.terminal import format_outputs, format_summary

ROOT = Path(__file__).resolve().parents[1]
# the tests read the session's run of double_integrator (conftest): one worker runs it once
pytestmark = pytest.mark.xdist_group("synthesis-double_integrator")


@pytest.fixture(scope="module")
def synthesized(synthesis_run):
    """``pipeline.synthesize("double_integrator")`` run from an empty directory (the session's
    run, ``conftest.synthesis_run``) -> ``(result, that directory, the pipeline logger's
    records, what it printed)``."""
    run = synthesis_run("double_integrator")
    return run.result, run.cwd, list(run.records), run.printed


def test_public_names_are_listed_and_resolve():
    assert sorted(pipeline.__all__) == pipeline.__all__
    for name in pipeline.__all__:
        assert getattr(pipeline, name) is not None, name
    assert {"synthesize", "load_scenario", "load_controller", "Synthesis"} <= set(pipeline.__all__)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        pipeline.nothing  # noqa: B018


def test_importing_the_api_loads_no_numerics():
    code = (
        "import sys; from pipeline import synthesize, Synthesis, load_controller, Verdict; "
        "heavy = {'sympy', 'scipy', 'cvxpy', 'numba', 'shapely', 'pydantic', 'stages'}; "
        "print(sorted(heavy & set(sys.modules)))"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert run.stdout.strip() == "[]"


def test_synthesize_takes_every_computing_option_with_its_default():
    """Each ``RunOptions`` field (the command line's source) is a keyword of ``synthesize``
    with the same default, except how much the command line prints."""
    parameters = inspect.signature(pipeline.synthesize).parameters
    for field in dataclasses.fields(RunOptions):
        if field.name in ("verbose", "quiet"):
            assert field.name not in parameters
            continue
        assert parameters[field.name].kind is inspect.Parameter.KEYWORD_ONLY, field.name
        assert parameters[field.name].default == field.default, field.name


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"certificate": "tube"}, "certificate='tube'; expected one of ('constant', 'funnel')"),
        ({"samples": 0}, "samples=0; expected a whole number from 1 to 1,000,000,000"),
        ({"jobs": 1.5}, "jobs=1.5; expected a whole number from 1 to 1,024"),
        ({"method": "newton"}, "method='newton'; expected one of ('gd', 'lbfgs')"),
    ],
)
def test_bad_arguments_raise_before_any_work(keywords, message, tmp_path):
    with pytest.raises(ValueError, match=re.escape(message)):
        pipeline.synthesize("double_integrator", out=tmp_path / "out", **keywords)
    assert not (tmp_path / "out").exists()


def test_synthesis_is_a_frozen_result_with_the_run_in_it(synthesized, synthesis_run):
    result, where, _, printed = synthesized
    assert isinstance(result, pipeline.Synthesis)
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.verdict = None  # type: ignore[misc]
    assert result.verdict is pipeline.Verdict.CERTIFIED_AND_VALIDATED and result.success
    assert result.exit_code == 0 and result.message == "certified and validated"
    kinds = {claim.kind for claim in result.claims}
    assert pipeline.ClaimKind.CERTIFIED in kinds
    assert pipeline.ClaimKind.STATISTICALLY_VALIDATED in kinds
    assert pipeline.ClaimKind.FALSIFICATION_SEARCHED in kinds
    scenario = pipeline.load_scenario("double_integrator")
    assert [d.demo for d in result.demos] == [d.name for d in scenario.demos]
    assert all(d.T_optimized < d.T_demo for d in result.demos)
    samples = synthesis_run("double_integrator").samples
    assert result.summary is not None and result.summary.montecarlo.samples == samples

    files = result.outputs
    assert files.folder == where / "reports" / "double_integrator"  # under the cwd
    for path in (files.summary, files.controller, files.report_html, files.report_pdf):
        assert path is not None and path.is_file() and path.parent == files.folder
    assert files.artifacts.is_dir()
    assert json.loads(files.summary.read_text())["verdict"]["kind"] == result.verdict.value

    controller = pipeline.load_controller(files.controller)
    assert isinstance(result.controller, pipeline.Controller)
    np.testing.assert_array_equal(result.controller.K, controller.K)
    index, ratio = result.controller.select(scenario.demos[0].x0)
    assert int(index) == 0 and float(ratio) < 1  # the demo's own start is covered
    assert printed == ""  # the library prints nothing (it logs)


def test_the_library_logs_one_line_per_stage(synthesized):
    _, where, records, _ = synthesized
    lines = [r.getMessage() for r in records]
    assert lines[0] == f"outputs: {where / 'reports' / 'double_integrator'}"
    stages = [m.group(1) for line in lines if (m := re.match(r"\[(\w+)\] ", line))]
    assert len(stages) == len(set(stages))  # one line each, no running/done pairs
    assert {"feedback", "optimize", "certify", "montecarlo", "report"} <= set(stages)
    assert all(r.name.startswith("pipeline.") for r in records)


def test_the_terminal_explains_its_terms_in_the_scenarios_units(synthesized):
    result, _, _, _ = synthesized
    summary, scenario = result.summary, pipeline.load_scenario("double_integrator")
    text = format_summary(summary, scenario, verbose=True)  # the tables: -v
    assert "radius limited by (the constraint the tube touches first;" in text
    assert "tube ratio at the final time (closed-loop error / its certified bound;" in text
    # clearances in the position unit, radii in the P-norm
    assert "(clear: the nominal path's smallest distance to Unsafe, m; r: robustness radius" in text
    assert "the largest tube that stays safe, in the P-norm (no unit)" in text
    h, mc = summary.headline, summary.montecarlo
    assert (
        f"min nominal clearance {h.min_clearance_before:.2f} m -> {h.min_clearance_after:.2f} m "
        f"(required d = {h.required_clearance:g} m); closed loop {mc.min_clearance:.2f} m"
    ) in text
    # each constraint that limits a radius is explained once, with its bound and unit
    bindings = {b for d in summary.demos for b in (d.binding_before, d.binding_after)}
    explained = [line for line in text.splitlines() if line.startswith("  (") and ": " in line]
    assert sorted(line[3:].split(":")[0] for line in explained) == sorted(bindings)
    for line in explained:
        if line.startswith("  (region '"):  # double_integrator: the region is the input box
            name, side = line.split("'")[1], line.split("'")[2].split(":")[0].strip()
            bound = summary.feedback.region[name][0 if side == "lower" else 1]
            relation = ">=" if side == "lower" else "<="
            assert f": {name} {relation} {bound:g} m/s^2, the operating region's edge" in line
    if "input slack" in text:
        assert "(input slack: how far the feedback's input stays from its bounds" in text
        assert "(ux: m/s^2, uy: m/s^2)" in text
    bare = format_summary(summary, verbose=True)  # no scenario: numbers bare, said so
    assert "smallest distance to Unsafe, position units;" in bare
    assert f"closed loop {mc.min_clearance:.2f}\n" in bare
    outputs = format_outputs(result)
    assert outputs.startswith(f"outputs in {result.outputs.folder}:")
    assert "report.html" in outputs and "controller.json" in outputs


def test_the_command_line_is_quiet_with_q_and_says_where_outputs_went(
    synthesized, tmp_path, capsys
):
    out = tmp_path / "out"
    shutil.copytree(synthesized[0].outputs.folder, out)  # the session's run, at other samples
    argv = ["synthesize", "double_integrator", "--out", str(out), "--samples", "20"]
    assert main([*argv, "-q"]) in (0, 1)
    quiet = capsys.readouterr().out
    assert quiet.startswith("verdict (constant certificate): ") and "done in" not in quiet
    assert main(argv) in (0, 1)  # every stage reused
    printed = capsys.readouterr().out
    assert printed.startswith(f"outputs: {out}\n")
    assert "[optimize] reused (inputs unchanged)" in printed
    *_, files, blank, done = printed.rstrip().splitlines()
    assert files.strip().startswith("artifacts/") and blank == ""
    verdict = json.loads((out / "summary.json").read_text())["verdict"]["kind"]
    assert re.fullmatch(rf"done in \d+(\.\d)? s: {verdict}", done), done
    assert re.search(r"closed loop \d+\.\d\d m\n", printed)  # the summary in the units
    # compact by default (issue 30, item 6): stages and verdict; the tables under -v
    assert "(distances in m)" not in printed and "radius limited by" not in printed
    assert "(the tables per demonstration: -v, or report.html)" in printed
    assert main([*argv, "-v"]) in (0, 1)
    verbose = capsys.readouterr().out
    assert "ends in Goal   (distances in m)" in verbose  # the demo table, in the units
    assert "radius limited by (the constraint the tube touches first;" in verbose


def test_a_scenario_name_is_looked_up_in_the_current_directory_first(tmp_path, monkeypatch):
    shipped = pipeline.load_scenario("double_integrator").path.parent
    own = tmp_path / "scenarios" / "double_integrator"
    shutil.copytree(shipped, own)
    monkeypatch.chdir(tmp_path)
    assert pipeline.load_scenario("double_integrator").path == own / "scenario.yaml"
    shutil.rmtree(own)
    assert pipeline.load_scenario("double_integrator").path == shipped / "scenario.yaml"
    with pytest.raises(pipeline.ScenarioError, match="unknown scenario 'nope'; expected one of"):
        pipeline.load_scenario("nope")
