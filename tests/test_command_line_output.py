"""What the command line prints, without a run: each "radius limited by" constraint explained
with its bound and unit, and the outputs listing (the run-based checks are in test_api.py)."""

from __future__ import annotations

import dataclasses
import logging
import sys
from pathlib import Path

import pytest
from tqdm import tqdm

from pipeline.model.scenario import load_scenario
from pipeline.reporting.summary import Verdict
from pipeline.runtime.synthesis import Outputs, Synthesis
from pipeline.runtime.terminal import (
    explain_binding,
    format_done,
    format_outputs,
    length_unit,
    show_progress,
)


@pytest.fixture(scope="module")
def quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


@pytest.mark.parametrize(
    ("binding", "expected"),
    [
        ("unsafe 'hill'", "unsafe 'hill': the tube touches this Unsafe set"),
        ("goal", "goal: at the final time the tube reaches the edge of Goal"),
        (
            "input 'u2' lower",
            "input 'u2' lower: u2 (pitch acceleration) >= -10 rad/s^2, the input bound: the "
            "feedback's input would be clipped beyond it",
        ),
        (
            "region 'u1' upper",
            "region 'u1' upper: u1 (thrust) <= 14.9 N, the operating region's edge (where the "
            "contraction certificate holds)",
        ),
        ("region 'theta' lower", "region 'theta' lower: theta (pitch) >= -0.6 rad, the"),
        ("state 'theta' upper", "state 'theta' upper: theta (pitch) <= 0.8 rad, the physical"),
        ("goal bound 'vX' upper", "goal bound 'vX' upper: at the final time the tube reaches"),
        ("a new kind", "a new kind: a constraint of the radius (see the report)"),
    ],
)
def test_each_radius_limit_is_explained_with_its_bound_and_unit(quadrotor, binding, expected):
    assert explain_binding(binding, quadrotor).startswith(expected)


def test_the_operating_region_used_is_the_feedbacks_and_bare_without_a_scenario(quadrotor):
    used = {"u1": (4.0, 12.5)}  # the feedback stage's region wins over the scenario's
    assert explain_binding("region 'u1' upper", quadrotor, used).startswith(
        "region 'u1' upper: u1 (thrust) <= 12.5 N,"
    )
    assert explain_binding("region 'u1' upper", None, used).startswith(
        "region 'u1' upper: u1 <= 12.5, the operating region's edge"
    )
    assert explain_binding("input 'u2' lower") == (
        "input 'u2' lower: the input bound: the feedback's input would be clipped beyond it"
    )


def test_the_length_unit_is_the_position_states_common_unit(quadrotor):
    assert length_unit(quadrotor) == "m"
    assert length_unit(None) == ""
    mixed = dataclasses.replace(quadrotor, units={**quadrotor.units, "Y": "ft"})
    assert length_unit(mixed) == ""  # no single unit to print
    assert length_unit(dataclasses.replace(quadrotor, units={})) == ""


def _synthesis(folder: Path) -> Synthesis:
    return Synthesis(
        scenario="quadrotor_hill_flythrough",
        verdict=Verdict.NOT_CERTIFIED,
        success=False,
        message="not certified",
        claims=(),
        controller=None,
        demos=(),
        summary=None,
        outputs=Outputs.of(folder),
    )


def test_the_outputs_name_the_folder_and_each_main_file(tmp_path):
    for name in ("report.html", "report.pdf", "summary.json", "scenario.png"):
        (tmp_path / name).write_text("x")
    (tmp_path / "artifacts").mkdir()
    lines = format_outputs(_synthesis(tmp_path)).splitlines()
    assert lines[0] == f"outputs in {tmp_path}:"
    names = [line.split()[0] for line in lines[1:]]
    assert names == [
        "report.html",
        "report.pdf",
        "controller.json",
        "summary.json",
        "scenario.png",
        "artifacts/",
    ]
    assert "not written: the run did not certify it" in lines[3]
    (tmp_path / "controller.stale.json").write_text("{}")  # a run that did not certify it
    stale = format_outputs(_synthesis(tmp_path)).splitlines()[3]
    assert stale.split()[0] == "controller.stale.json" and "NOT certified" in stale


def test_the_last_line_gives_the_wall_time_and_the_verdict_alone(tmp_path):
    passed = dataclasses.replace(
        _synthesis(tmp_path), verdict=Verdict.CERTIFIED_AND_VALIDATED, message="ok"
    )
    assert format_done(passed, 48.6) == "done in 49 s: certified and validated"
    failed = dataclasses.replace(passed, verdict=Verdict.NOT_CERTIFIED, message="not: a; b")
    assert format_done(failed, 3.04) == "done in 3.0 s: not certified"  # reasons above it


def test_a_stage_line_starts_its_own_line_while_a_progress_bar_is_open(capsys):
    """On a terminal the stage's bar (stderr) and its line (stdout) share the screen: the bar is
    cleared for the line, not followed by it."""
    with show_progress():
        bar = tqdm(total=3, file=sys.stdout, ncols=60, mininterval=0)  # stdout: one capture
        bar.update(1)
        logging.getLogger("pipeline.runtime.test").info("[stage] 1.0 s: done")
        bar.close()
    out = capsys.readouterr().out
    before, after = out.split("[stage] 1.0 s: done\n")
    assert "1/3" in before and before.endswith("\r")  # the bar was wiped, the cursor at column 0
    assert "1/3" in after  # and drawn again under the line
