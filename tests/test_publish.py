"""The output folder is published as a whole, and ``report`` derives the verdict it prints
(issue 27, items 1 and 3).

1. A run stages ``controller.json``, ``summary.json``, its manifest and the reports in
   ``OUT/.staging`` and moves them into place after certify and the report: a kill at any instant
   leaves the previous run's files, all of them, or the marker ``OUT/INCOMPLETE``, which
   ``report`` refuses in one line.
3. ``report`` certifies ``controller.json`` again and reads the Monte Carlo result of that file:
   a ``summary.json`` edited to say "certified", edited Monte Carlo counts and a forged controller
   hash in ``inputs.json`` give the re-derived verdict or a one-line refusal.

The session's run of ``double_integrator`` (conftest; 300 Monte Carlo samples) is copied for
each test that runs the pipeline.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import signal
import subprocess
import sys
from html import unescape
from pathlib import Path

import pytest

import stages.controller
from pipeline.io.errors import UserError
from pipeline.model.scenario import load_scenario
from pipeline.reporting.summary import Summary
from pipeline.runtime import outdir
from pipeline.runtime.cli import main
from pipeline.runtime.options import RunOptions
from pipeline.runtime.orchestrator import run_synthesis
from pipeline.runtime.stored import load_report_data
from tests.helpers.runs import SAMPLES, finished_copy, private_copy

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run


@pytest.fixture(scope="module")
def finished(synthesis_run, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """``(scenario folder, output folder)`` of one finished run on a copy of the scenario."""
    return finished_copy(synthesis_run("double_integrator"), tmp_path_factory.mktemp("publish"))


@pytest.fixture
def run(finished: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    """A private copy of the finished run (scenario and output folder)."""
    return private_copy(finished, tmp_path)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def published(out: Path) -> dict[str, bytes]:
    """The files a run publishes, as they are now."""
    names = ("controller.json", "summary.json", "report.html", "scenario.png")
    return {name: (out / name).read_bytes() for name in (*names, "artifacts/inputs.json")}


def describes_its_controller(out: Path) -> bool:
    """summary.json, the manifest and report.html all name the controller.json beside them."""
    shipped = sha256(out / "controller.json")
    summary = json.loads((out / "summary.json").read_text())
    manifest = json.loads((out / "artifacts" / "inputs.json").read_text())
    report = (out / "report.html").read_text()
    return (
        summary["certification"]["sha256"] == manifest["controller_sha256"] == shipped
        and shipped in report
    )


def report_verdict(out: Path) -> str:
    """The verdict report.html opens with."""
    match = re.search(r"Verdict: (.*?)\. Method: ", (out / "report.html").read_text(), re.S)
    assert match is not None
    return unescape(match.group(1))


# --- 1. publish as a whole ---------------------------------------------------------------------


def _old_and_new(tmp_path: Path, *, staged_reports: bool = True) -> tuple[Path, Path]:
    """An output folder holding a previous run ("old", with a report.pdf and a stale report of
    an earlier failed run) and a staged run ("new"; its reports only with ``staged_reports``,
    and no PDF). Each file's text names the controller.json it describes."""
    out = tmp_path / "out"
    (out / "artifacts").mkdir(parents=True)
    for name in ("controller.json", "summary.json", "report.html", "report.pdf", "scenario.png"):
        (out / name).write_text("old")
    (out / "artifacts" / "inputs.json").write_text("old")
    (out / "report.stale.html").write_text("older")
    staging = outdir.staging_folder(out)
    new = ("controller.json", "summary.json", "inputs.json")
    for name in (*new, *(("report.html", "scenario.png") if staged_reports else ())):
        (staging / name).write_text("new")
    return out, staging


def _state(out: Path) -> dict[str, str]:
    """Every file in ``out`` (the staging folder aside) -> its text."""
    return {
        str(path.relative_to(out)): path.read_text()
        for path in sorted(out.rglob("*"))
        if path.is_file() and outdir.STAGING not in path.parts
    }


@pytest.mark.parametrize("certified", [True, False])
def test_every_instant_of_a_publish_shows_one_run_or_the_marker(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, certified: bool
) -> None:
    """The folder after each rename and deletion of ``publish`` (what a kill -9 then leaves):
    without the marker, one run's files, all of them; with it, a one-line refusal."""
    out, staging = _old_and_new(tmp_path)
    states = [_state(out)]
    for name in ("replace", "unlink", "rmdir"):
        original = getattr(os, name)

        def recorded(*args, _original=original, **kwargs):
            _original(*args, **kwargs)
            states.append(_state(out))

        monkeypatch.setattr(os, name, recorded)
    outdir.publish(out, staging, certified=certified)
    monkeypatch.undo()

    carriers = ("summary.json", "artifacts/inputs.json", "report.html", "scenario.png")
    for state in states:
        if outdir.INCOMPLETE in state:
            continue  # readers refuse it (below)
        generations = {state.get(name) for name in carriers}
        assert generations in ({"old"}, {"new"}), state  # one run's, none missing
        shipped = state.get("controller.json", state.get("controller.stale.json"))
        assert shipped == generations.pop(), state
    controller = "controller.json" if certified else "controller.stale.json"
    assert states[-1] == {controller: "new", **{name: "new" for name in carriers}}
    assert not staging.exists() and len(states) > 4
    assert all(outdir.INCOMPLETE in state for state in states[2:-2])  # the instants between
    (out / outdir.INCOMPLETE).write_text(outdir.INCOMPLETE_TEXT)
    with pytest.raises(UserError, match=r"INCOMPLETE: the output folder is incomplete"):
        outdir.check_complete(out, "double_integrator")


def test_published_reports_stay_when_the_run_did_not_write_them(tmp_path: Path) -> None:
    """No reports staged: the run's report key is the published one, they are this run's."""
    out, staging = _old_and_new(tmp_path, staged_reports=False)
    outdir.publish(out, staging, certified=True)
    reports = {name: "old" for name in ("report.html", "report.pdf", "scenario.png")}
    assert _state(out) == {
        "controller.json": "new",
        "summary.json": "new",
        "artifacts/inputs.json": "new",
        **reports,
    }


@pytest.mark.slow
def test_a_run_killed_after_its_controller_stage_leaves_the_previous_run_whole(run):
    """kill -9 when the log shows [controller], in a re-run that writes another controller:
    the folder still holds the previous run, every file of it, and nothing says "certified"
    for a controller.json it does not describe."""
    scenario, out = run
    before = published(out)
    demo = scenario / "demos" / "demo_01.csv"  # another optimized trajectory, another file
    lines = demo.read_text().splitlines()
    row = next(i for i, line in enumerate(lines) if line[:1].isdigit())
    cells = lines[row].split(",")
    cells[1] = repr(float(cells[1]) + 1e-3)
    lines[row] = ",".join(cells)
    demo.write_text("\n".join(lines) + "\n")
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "synthesize", str(scenario), "--out", str(out)]
        + ["--samples", SAMPLES],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    try:
        assert process.stdout is not None
        for line in process.stdout:
            if line.startswith("[controller]"):
                process.send_signal(signal.SIGKILL)
                break
        process.wait(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == -signal.SIGKILL, "killed before or after its controller stage"
    assert describes_its_controller(out)
    assert published(out) == before  # the previous run's files, every one
    assert not (out / outdir.INCOMPLETE).exists()
    staged = out / outdir.STAGING / "controller.json"  # the killed run had written its own
    assert staged.is_file() and staged.read_bytes() != before["controller.json"]
    killed = staged.read_bytes()
    assert main(["synthesize", str(scenario), "--out", str(out), "--samples", SAMPLES, "-q"]) == 0
    assert describes_its_controller(out) and not (out / outdir.STAGING).exists()
    assert (out / "controller.json").read_bytes() == killed  # resumed: the same file


def test_report_refuses_a_publish_cut_short_and_the_next_run_completes_it(run, capsys, monkeypatch):
    """Interrupted between renaming controller.json and summary.json into place: ``report``
    refuses in one line naming the marker and the fix; the next run publishes a whole run."""
    scenario, out = run
    (out / "report.html").unlink()  # the run writes its reports too
    original = outdir.files.replace  # publish moves through the folders' descriptors

    def interrupted(source, target):
        original(source, target)
        if Path(target) == out / "controller.json":
            raise KeyboardInterrupt

    monkeypatch.setattr(outdir.files, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_synthesis(scenario, out, RunOptions(samples=int(SAMPLES)))
    monkeypatch.undo()
    assert (out / outdir.INCOMPLETE).is_file() and not (out / "summary.json").exists()

    assert main(["report", str(scenario), "--from", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1, error
    assert error.startswith(f"error: {out / outdir.INCOMPLETE}: the output folder is incomplete")
    assert f"python -m pipeline synthesize double_integrator --out {out}" in error

    result = run_synthesis(scenario, out, RunOptions(samples=int(SAMPLES)))
    assert result.exit_code == 0 and not (out / outdir.INCOMPLETE).exists()
    assert describes_its_controller(out)
    assert main(["report", str(scenario), "--from", str(out)]) == 0


# --- 3. the report's verdict is derived, never read ------------------------------------------


def _edit_json(path: Path, edit) -> None:
    document = json.loads(path.read_text())
    edit(document)
    path.write_text(json.dumps(document, indent=2))


def _claim_certified(summary: dict) -> None:
    summary["verdict"] = {
        "kind": "certified and validated",
        "certified": True,
        "validated": True,
        "text": "certified and validated",
        "reasons": [],
    }
    for claim in summary["claims"][:2]:
        claim["kind"] = "certified"


def test_an_uncertified_run_edited_to_say_certified_is_reported_not_certified(
    run, capsys, monkeypatch
):
    """The issue's case: a not-certified run, its summary's verdict edited and
    controller.stale.json renamed back; the report certifies the file again."""
    scenario, out = run
    emit = stages.controller.emit_controller

    def shrunk(*args, **kwargs):  # balls too small to cover Init: certify refuses the file
        result = emit(*args, **kwargs)
        _edit_json(
            result.path,
            lambda document: [t.update(radius=t["radius"] / 5) for t in document["trajectories"]],
        )
        return result

    monkeypatch.setattr(stages.controller, "emit_controller", shrunk)
    assert main(["synthesize", str(scenario), "--out", str(out), "--samples", SAMPLES, "-q"]) == 1
    monkeypatch.undo()
    assert json.loads((out / "summary.json").read_text())["verdict"]["certified"] is False
    (out / "controller.stale.json").rename(out / "controller.json")
    _edit_json(out / "summary.json", _claim_certified)
    capsys.readouterr()

    assert main(["report", str(scenario), "--from", str(out)]) == 0
    verdict = report_verdict(out)
    assert verdict.startswith("not certified: controller.json is not certified: "), verdict
    assert "Init is not covered by the file's balls" in verdict


def test_edited_monte_carlo_counts_are_not_what_the_report_shows(run, capsys):
    scenario, out = run

    def edit(summary: dict) -> None:
        summary["montecarlo"].update(samples=99999, failures={"unsafe": 17})
        summary["headline"].update(montecarlo_samples=99999, montecarlo_failures=17)
        summary["claims"][3]["claim"] = "failure probability <= 1.23e-09"

    _edit_json(out / "summary.json", edit)
    assert main(["report", str(scenario), "--from", str(out)]) == 0
    html = (out / "report.html").read_text()
    assert "99999" not in html and "1.23e-09" not in html
    assert (
        f"0 of {SAMPLES} runs failed" in html and report_verdict(out) == "certified and validated"
    )


def test_a_forged_controller_hash_in_the_manifest_is_refused_in_one_line(run, capsys):
    scenario, out = run
    path = out / "controller.json"
    _edit_json(path, lambda document: document["trajectories"][0].update(radius=1e-3))
    _edit_json(
        out / "artifacts" / "inputs.json",
        lambda manifest: manifest.update(controller_sha256=sha256(path)),
    )
    assert main(["report", str(scenario), "--from", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1, error
    assert f"{out / 'artifacts' / 'montecarlo.json'}: the Monte Carlo result is not of this " in (
        error
    )
    assert "synthesize" in error


@pytest.mark.parametrize(
    "options", [(), pytest.param(("--feedback-period", "0.01"), marks=pytest.mark.slow)]
)
def test_an_untampered_run_is_reported_as_it_summarised_itself(run, options):
    """Derived again from the folder, the summary is the run's own, field for field (with a
    feedback period: the feedback block at the held law's rate, as the run had it)."""
    scenario, out = run
    if options:
        command = ["synthesize", str(scenario), "--out", str(out), "--samples", SAMPLES, "-q"]
        assert main([*command, *options]) == 0
    data = load_report_data(load_scenario(scenario), out)
    stored = Summary.from_json(json.loads((out / "summary.json").read_text()))
    assert data.summary.to_json() == stored.to_json()
