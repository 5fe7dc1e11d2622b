"""The funnel certificate as a run (``certificate="funnel"``, ``--certificate funnel``): on the
double integrator end to end through the API, the command line's flag on the same folder (every
stage reused), and bad combinations refused before any work."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil

import numpy as np
import pytest

import pipeline
from pipeline.controller import FUNNEL_FORMAT, load
from pipeline.io.artifacts import read_stored
from pipeline.numerics.cover import subdivide
from pipeline.runtime import orchestrator
from pipeline.runtime.cli import main
from pipeline.runtime.options import RunOptions
from pipeline.runtime.orchestrator import run_synthesis
from pipeline.runtime.registry import RESULT_TYPES

SAMPLES = 200


@pytest.fixture(scope="module")
def funnel_run(tmp_path_factory: pytest.TempPathFactory):
    """``pipeline.synthesize("double_integrator", certificate="funnel")`` -> ``(result, the
    pipeline logger's lines)``."""
    out = tmp_path_factory.mktemp("funnel") / "double_integrator"
    lines: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: lines.append(record.getMessage())  # type: ignore[method-assign]
    logger = logging.getLogger("pipeline")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        result = pipeline.synthesize(
            "double_integrator", out=out, certificate="funnel", samples=SAMPLES
        )
    finally:
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
    return result, lines


def test_funnel_run_ships_a_certified_safety_controller_2(funnel_run):
    result, lines = funnel_run
    assert result.verdict is pipeline.Verdict.CERTIFIED_AND_VALIDATED, result.message
    summary = result.summary
    assert summary is not None and summary.certificate == "funnel"
    document = json.loads(result.outputs.summary.read_text())
    assert document["certificate"] == "funnel" and document["verdict"]["certified"]
    controller = load(result.outputs.controller)
    assert controller.format == FUNNEL_FORMAT and controller.funnel
    # One funnel per shipped trajectory, each level the one the funnel stage found.
    levels = [d.funnel_level for d in summary.demos]
    assert all(level is not None and 0 < level <= 1 for level in levels)
    assert sorted(tr.radius for tr in controller.trajectories) == pytest.approx(sorted(levels))
    # The file's initial ellipsoids E_i(0) cover Init, each in its own metric P_i[0].
    cover = subdivide(
        np.stack([tr.P[0] for tr in controller.trajectories]),
        pipeline.load_scenario("double_integrator").init_lower,
        pipeline.load_scenario("double_integrator").init_upper,
        np.stack([tr.x0 for tr in controller.trajectories]),
        np.array([tr.radius for tr in controller.trajectories]),
    )
    assert cover.covered
    assert summary.headline.covered_after and summary.headline.coverage_after == 1.0
    stages = [line.split("]")[0][1:] for line in lines if line.startswith("[")]
    order = ["coverage_optimized", "funnel", "coverage_funnel", "controller"]
    assert [stage for stage in stages if stage in order] == order
    assert any(
        line.startswith("[funnel] ") and "funnels certified for 9 of 9" in line for line in lines
    )
    assert (result.outputs.artifacts / "funnel.json").is_file()


def test_the_nominals_are_optimized_again_against_the_funnels(funnel_run):
    """Issue 16 part 4: round 1 re-optimizes against the funnels' extents; a kept round shortens
    the total T, and the shipped nominals are the kept round's."""
    result, lines = funnel_run
    assert any(line.startswith("[reoptimize_1] ") for line in lines)
    assert any(line.startswith("[funnel_1] ") for line in lines)
    rounds = [line for line in lines if line.startswith("[round ")]
    assert rounds, "every round says whether it was kept"
    demos = result.summary.demos
    constant = sum(d.T_constant for d in demos)
    shipped = sum(d.T_optimized for d in demos)
    controller = load(result.outputs.controller)
    assert sorted(tr.t[-1] for tr in controller.trajectories) == pytest.approx(
        sorted(d.T_optimized for d in demos)
    )
    if any("kept: total T" in line for line in rounds):
        assert shipped < constant
    else:
        assert shipped == pytest.approx(constant)


def test_the_claims_say_which_certificate_and_what_certify_proved(funnel_run):
    result, _ = funnel_run
    claims = {claim.claim: claim.kind for claim in result.claims}
    funnel_claims = [c for c in claims if "funnel" in c]
    assert len(funnel_claims) == 2
    assert all(claims[c] is pipeline.ClaimKind.CERTIFIED for c in funnel_claims)
    assert not any("over the operating region" in c for c in claims)  # no constant claim
    summary = result.summary
    assert summary is not None and summary.certification.certified


def test_the_command_line_flag_selects_the_certificate(funnel_run, capsys):
    """``--certificate funnel`` on the API run's folder: every stage reused, the verdict line
    names the certificate; ``--certificate constant`` there ships ``safety-controller/1``."""
    result, _ = funnel_run
    folder = result.outputs.folder
    argv = ["synthesize", "double_integrator", "--out", str(folder), "--samples", str(SAMPLES)]
    assert main([*argv, "--certificate", "funnel"]) == 0
    printed = capsys.readouterr().out
    assert "[funnel] reused (inputs unchanged)" in printed
    assert "\nverdict (funnel certificate): certified and validated" in printed
    assert "\nfunnels (level rho: E_i(0) holds rho times the constant ball's slice" in printed
    assert load(folder / "controller.json").format == FUNNEL_FORMAT
    assert main([*argv, "--certificate", "constant"]) == 0
    printed = capsys.readouterr().out
    assert "[funnel]" not in printed and "[optimize] reused (inputs unchanged)" in printed
    assert "\nverdict (constant certificate): certified and validated" in printed
    assert not load(folder / "controller.json").funnel
    document = json.loads((folder / "summary.json").read_text())
    assert document["certificate"] == "constant"


def test_the_funnel_certificate_refuses_held_feedback(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["synthesize", "double_integrator", "--out", str(out), "--certificate", "funnel"]
    assert main([*argv, "--feedback-period", "0.01"]) == 2
    err = capsys.readouterr().err
    assert "--feedback-period: found 0.01 s with the funnel certificate" in err
    assert "Traceback" not in err and not out.exists()
    with pytest.raises(pipeline.UserError, match="expected 0 \\(or --certificate constant\\)"):
        run_synthesis(
            "double_integrator", out, RunOptions(certificate="funnel", feedback_period=0.01)
        )


def test_a_run_without_any_certified_funnel_fails_and_says_why(funnel_run, tmp_path, monkeypatch):
    """Every funnel rejected (the funnel stage run again on a copy of the run): the run fails at
    stage funnel naming the reason, and ships no controller."""
    result, _ = funnel_run
    folder = tmp_path / "double_integrator"
    shutil.copytree(result.outputs.folder, folder)
    stored = read_stored(folder / "artifacts" / "funnel", RESULT_TYPES)
    assert stored is not None
    for artifact in (folder / "artifacts").glob("funnel.*"):
        artifact.unlink()  # the stage runs again: every funnel of the last run, all rejected

    def none_certified(*_args, **_kwargs):
        return dataclasses.replace(
            stored.result,
            usable=(),
            rejected=("all dropped: test",),
            success=False,
            message="no funnel certified for any of the 9 trajectories; all dropped: test",
        )

    monkeypatch.setattr(orchestrator, "synthesize_funnels", none_certified)
    failed = run_synthesis(
        "double_integrator", folder, RunOptions(certificate="funnel", samples=20)
    )
    assert failed.verdict is pipeline.Verdict.FAILED and failed.controller is None
    assert failed.message.startswith("failed: stage funnel: no funnel certified: ")
    assert "all dropped: test" in failed.message
    assert not (folder / "controller.json").exists()
