"""Fault injection on the stage cache and the output folder (issue 14: 1, 2, 5, 6, 7, 8, 9).

The session's run of ``double_integrator`` (conftest; 300 Monte Carlo samples) is copied for
each test, with a copy of the scenario folder, which then tampers with, corrupts, locks or kills
it and checks the next run's behaviour: nothing read from disk chooses code to run, an edited or
damaged artifact is refused in one line and recomputed, a failed run says so and leaves no
controller it did not certify, and the cache keys follow the code and the parsed inputs.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import stages.feedback
import stages.montecarlo
from pipeline.io import lock
from pipeline.io.artifacts import content_hash, read_stored
from pipeline.runtime import orchestrator
from pipeline.runtime.cli import main
from pipeline.runtime.registry import RESULT_TYPES
from tests.helpers.runs import SAMPLES, finished_copy, private_copy

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run


@pytest.fixture(scope="module")
def finished(synthesis_run, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """``(scenario folder, output folder)`` of one finished run on a copy of the scenario."""
    return finished_copy(synthesis_run("double_integrator"), tmp_path_factory.mktemp("faults"))


@pytest.fixture
def run(finished: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    """A private copy of the finished run (scenario and output folder)."""
    return private_copy(finished, tmp_path)


def synthesize(run: tuple[Path, Path], *extra: str) -> int:
    return main(["synthesize", str(run[0]), "--out", str(run[1]), "--samples", SAMPLES, *extra])


def computed(printed: str) -> set[str]:
    """The stages a run computed: their line shows the time (``[optimize] 6.6 s: ...``); a
    reused stage says ``[optimize] reused (inputs unchanged)``."""
    return set(re.findall(r"^\[(\w+)\] \d+\.\d s", printed, flags=re.MULTILINE))


def mtimes(out: Path) -> dict[str, int]:
    """Modification times of the stage artifacts (the input manifest is rewritten every run)."""
    stems = (out / "artifacts").glob("*.json")
    return {p.name: p.stat().st_mtime_ns for p in stems if p.name != "inputs.json"}


def radii(out: Path) -> list[float]:
    document = json.loads((out / "controller.json").read_text())
    return [float(t["radius"]) for t in document["trajectories"]]


# --- 1. nothing read from disk chooses code ---------------------------------------------------


def test_artifact_naming_a_callable_is_refused_and_recomputed(run, capsys):
    scenario, out = run
    marker = out.parent / "PWNED"
    path = out / "artifacts" / "feedback.json"
    document = json.loads(path.read_text())
    document["result"] = {
        "__dataclass__": "subprocess:call",
        "fields": {"args": f"touch {marker}", "shell": True},
    }
    with np.load(out / "artifacts" / "feedback.npz") as stored:  # re-signed: only the registry
        arrays = {k: stored[k] for k in stored.files if k != "__key__"}  # stands in the way
    document["sha256"] = content_hash(document["key"], document["result"], arrays)
    path.write_text(json.dumps(document))

    assert main(["report", str(scenario), "--from", str(out)]) == 2
    error = capsys.readouterr().err
    assert "'subprocess:call', which is not a registered result type" in error
    assert error.count("\n") == 1 and str(path) in error

    assert synthesize(run, "-q") == 0
    assert "not a registered result type" in capsys.readouterr().err
    assert not marker.exists()
    assert type(read_stored(out / "artifacts" / "feedback", RESULT_TYPES).result).__name__ == (
        "FeedbackResult"
    )


def test_unknown_field_of_a_registered_type_is_refused(run, capsys):
    _, out = run
    path = out / "artifacts" / "covering_radius.json"
    document = json.loads(path.read_text())
    document["result"]["fields"]["extra"] = 1
    document["sha256"] = content_hash(document["key"], document["result"], {})
    path.write_text(json.dumps(document))
    assert synthesize(run, "-q") == 0
    refused = "fields of pipeline.results.coverage:CoveringRadius do not match"
    assert refused in capsys.readouterr().err


# --- 2. an edited artifact is refused; a failed run certifies nothing -----------------------


def test_edited_radius_is_recomputed_and_never_shipped(run, capsys):
    _, out = run
    shipped = radii(out)
    path = out / "artifacts" / "radius_optimized.json"
    text = path.read_text()
    field = f'"radius": {shipped[0]!r}'
    assert field in text
    path.write_text(text.replace(field, f'"radius": {shipped[0] * 10!r}', 1))
    assert synthesize(run, "-q") == 0
    printed = capsys.readouterr()
    assert "radius_optimized.json: content does not match its stored sha256" in printed.err
    assert printed.err.count("refused") == 1
    assert radii(out) == shipped


def nudge_demo(scenario: Path, name: str, delta: float) -> Path:
    """Add ``delta`` to the first input value of demo ``name``'s first data row."""
    demo = scenario / "demos" / f"{name}.csv"
    lines = demo.read_text().splitlines()
    row = next(i for i, line in enumerate(lines) if line[:1].isdigit())
    cells = lines[row].split(",")
    cells[1] = repr(float(cells[1]) + delta)
    lines[row] = ",".join(cells)
    demo.write_text("\n".join(lines) + "\n")
    return demo


def test_failed_stage_writes_a_failed_summary_and_stales_old_outputs(run, capsys, monkeypatch):
    scenario, out = run

    def broken(*args, **kwargs):
        raise RuntimeError("worker lost")

    nudge_demo(scenario, "demo_01", 1e-10)  # reruns the demo stages, not the feedback
    monkeypatch.setattr(stages.feedback, "design_feedback", pytest.fail)
    monkeypatch.setattr(stages.montecarlo, "validate_closed_loop", broken)
    assert synthesize(run, "-q") == 1
    assert "failed: stage montecarlo: RuntimeError: worker lost" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["stage"] == "montecarlo"
    assert "worker lost" in summary["reason"] and summary["verdict"]["certified"] is False
    assert "in broken" in "\n".join(summary["traceback"])
    assert not (out / "controller.json").exists() and (out / "controller.stale.json").is_file()
    assert not (out / "report.html").exists() and (out / "report.stale.html").is_file()

    assert main(["report", str(scenario), "--from", str(out)]) == 2
    assert "the last run failed at stage 'montecarlo'" in capsys.readouterr().err

    monkeypatch.undo()  # the next good run clears the stale files
    assert synthesize(run, "-q") == 0
    assert (out / "controller.json").is_file() and not list(out.glob("*.stale.*"))


def _type_error_in_a_worker(folder: str) -> None:
    """A deterministic bug in a Monte Carlo chunk; each call appends a line to ``folder/calls``.
    Module level: a worker process imports this module to find it."""
    with open(Path(folder) / "calls", "a") as calls:
        calls.write("called\n")
    return folder + 1  # type: ignore[operator]  # TypeError, raised here


def test_a_crash_in_a_worker_is_run_once_and_its_traceback_saved(
    run, tmp_path, capsys, monkeypatch
):
    scenario, out = run

    def montecarlo(*args, executor, **kwargs):
        return executor.map(_type_error_in_a_worker, [str(tmp_path)])

    monkeypatch.setattr(stages.montecarlo, "validate_closed_loop", montecarlo)
    rerun = ["synthesize", str(scenario), "--out", str(out), "--samples", "200"]  # a new key
    assert main([*rerun, "--jobs", "2", "-q"]) == 1
    printed = capsys.readouterr()
    assert (tmp_path / "calls").read_text() == "called\n"  # not retried
    # one line, saying where the traceback is; no traceback on the terminal
    assert (
        printed.out.startswith("failed: stage montecarlo: ChunkFailed: chunk 0 failed: TypeError: ")
        and printed.out.count("\n") == 1
    ), printed.out
    assert f"({out / 'summary.json'}, with the traceback;" in printed.out
    assert printed.err == ""
    summary = json.loads((out / "summary.json").read_text())
    saved = "\n".join(summary["traceback"])
    assert "in _type_error_in_a_worker" in saved and "return folder + 1" in saved  # the worker's

    assert main([*rerun, "-v"]) == 1  # in this process (one job); -v prints the traceback
    printed = capsys.readouterr()
    assert (tmp_path / "calls").read_text() == "called\n" * 2
    assert "stage montecarlo raised\nTraceback (most recent call last):" in printed.err
    assert "in _type_error_in_a_worker" in printed.err


def test_uncertifiable_feedback_is_exit_1_with_a_failed_summary(run, capsys, monkeypatch):
    _, out = run
    stored = read_stored(out / "artifacts" / "feedback", RESULT_TYPES).result
    failed = dataclasses.replace(stored, success=False, message="LMI infeasible at rate 0.5")
    monkeypatch.setattr(stages.feedback, "design_feedback", lambda scenario: failed)
    assert synthesize(run, "--force", "-q") == 1
    assert "failed: stage feedback: the feedback could not be certified" in (
        capsys.readouterr().out
    )
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["status"], summary["stage"]) == ("failed", "feedback")
    assert "LMI infeasible" in summary["reason"]
    assert not (out / "controller.json").exists()


# --- 5. corrupt caches -------------------------------------------------------------------------

DAMAGE = {
    "truncated npz": ("coverage_optimized.npz", lambda b: b[: len(b) // 2]),
    "bit-flipped npz": ("montecarlo.npz", lambda b: b[:-9999] + bytes([b[-9999] ^ 4]) + b[-9998:]),
    "empty npz": ("radius_demos.npz", lambda b: b""),
    "truncated json": ("coverage_demos.json", lambda b: b[: len(b) // 3]),
    "empty json": ("feedback.json", lambda b: b""),
}


def test_corrupt_artifacts_are_recomputed_in_one_line_each(run, capsys):
    _, out = run
    for name, damage in DAMAGE.values():
        path = out / "artifacts" / name
        path.write_bytes(damage(path.read_bytes()))
    shipped = radii(out)
    assert synthesize(run, "-q") == 0
    refused = [line for line in capsys.readouterr().err.splitlines() if "refused" in line]
    assert len(refused) == len(DAMAGE)
    assert radii(out) == shipped


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_report_on_a_corrupt_artifact_is_exit_2_naming_it(run, capsys, case):
    scenario, out = run
    name, damage = DAMAGE[case]
    path = out / "artifacts" / name
    path.write_bytes(damage(path.read_bytes()))
    assert main(["report", str(scenario), "--from", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("error: ") and error.count("\n") == 1
    assert str(path.with_suffix(".json")) in error and "synthesize" in error


# --- 6. output folder mistakes: exit 2 before computing ---------------------------------------


def test_out_naming_a_file_is_exit_2(run, capsys, tmp_path):
    target = tmp_path / "a_file"
    target.write_text("x")
    assert main(["synthesize", str(run[0]), "--out", str(target)]) == 2
    assert "--out names a file" in capsys.readouterr().err
    assert target.read_text() == "x"


def test_unwritable_out_is_exit_2_before_computing(run, capsys, tmp_path, monkeypatch):
    if os.geteuid() == 0:  # root writes through permissions; sysfs refuses everyone
        target = Path("/sys/safety-synthesis-out")
        if not Path("/sys/kernel").is_dir():
            pytest.skip("no read-only file system to write to")
    else:
        tmp_path.chmod(0o555)
        target = tmp_path / "out"
    monkeypatch.setattr(stages.feedback, "design_feedback", pytest.fail)  # nothing computed
    try:
        assert main(["synthesize", str(run[0]), "--out", str(target)]) == 2
    finally:
        tmp_path.chmod(0o755)
    assert "output folder is not writable" in capsys.readouterr().err


def test_another_scenarios_controller_is_refused(run, capsys, tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    (other / "controller.json").write_text(json.dumps({"scenario": "quadrotor_hill_flythrough"}))
    assert main(["synthesize", str(run[0]), "--out", str(other)]) == 2
    error = capsys.readouterr().err
    assert "holds another scenario's controller.json; found 'quadrotor_hill_flythrough'" in error


# --- 7. leaks and races ------------------------------------------------------------------------


def test_second_run_on_a_locked_folder_exits_2_naming_the_holder(run, capsys, monkeypatch):
    monkeypatch.setattr(lock, "WAIT_SECONDS", 0.3)
    with lock.folder_lock(run[1]):
        started = time.monotonic()
        assert synthesize(run) == 2
        assert time.monotonic() - started < 5
    assert f"another run (pid {os.getpid()}) is using this output folder" in (
        capsys.readouterr().err
    )


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, pending = set(), [pid]
    while pending:
        for child in children.get(pending.pop(), []):
            found.add(child)
            pending.append(child)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
def test_kill_9_with_workers_leaves_no_worker_and_no_temporary(run):
    scenario, out = run
    command = [sys.executable, "-m", "pipeline", "synthesize", str(scenario), "--out", str(out)]
    process = subprocess.Popen(
        [*command, "--samples", SAMPLES, "--jobs", "2", "--force", "-q"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        while len(workers) < 2 and time.monotonic() < deadline and process.poll() is None:
            time.sleep(0.2)
            workers = _descendants(process.pid)
        assert len(workers) >= 2, "the run never started its workers"
        time.sleep(0.5)
        process.send_signal(signal.SIGKILL)
        process.wait()
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [p for p in workers if _alive(p)], "workers outlived the killed run"
    finally:  # whatever happened, leave nothing of this test running
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        for pid in _descendants(process.pid) | {p for p in workers if _alive(p)}:
            os.kill(pid, signal.SIGKILL)
    assert synthesize(run, "-q") == 0  # resumes; the lock died with its holder
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


# --- 8. cache granularity: keyed on the code and on what each stage reads ---------------------


def test_fully_cached_rerun_and_csv_comment_edit_recompute_nothing(run, capsys):
    scenario, out = run
    before = mtimes(out)
    report = (out / "report.html").stat().st_mtime_ns
    demo = scenario / "demos" / "demo_01.csv"
    demo.write_text("# a comment added by hand\n" + demo.read_text().replace(",", ", "))
    assert synthesize(run) == 0
    printed = capsys.readouterr().out
    assert computed(printed) == {"controller", "certify"}  # both always run: the file itself
    assert mtimes(out) == {**before, "controller.json": mtimes(out)["controller.json"]}
    assert (out / "report.html").stat().st_mtime_ns == report  # timings are not in its key


def test_report_checks_the_demo_values_not_only_the_yaml(run, capsys):
    scenario, out = run
    demo = nudge_demo(scenario, "demo_02", 1e-3)
    assert main(["report", str(scenario), "--from", str(out)]) == 2
    assert f"demos changed since the run: {demo}" in capsys.readouterr().err


def _negative_radius(text: str) -> str:
    document = json.loads(text)
    document["trajectories"][0]["radius"] = -1.0  # every state would look covered
    return json.dumps(document)


@pytest.mark.parametrize("edit", [_negative_radius, lambda text: text[: len(text) // 2]])
def test_an_edited_or_truncated_controller_is_rewritten_from_the_certified_results(
    run, capsys, edit
):
    _, out = run
    shipped = radii(out)
    path = out / "controller.json"
    path.write_text(edit(path.read_text()))
    assert synthesize(run) == 0
    assert "controller" in computed(capsys.readouterr().out)
    assert radii(out) == shipped


def test_report_refuses_a_controller_the_run_did_not_write(run, capsys):
    scenario, out = run
    path = out / "controller.json"
    path.write_text(_negative_radius(path.read_text()))
    assert main(["report", str(scenario), "--from", str(out)]) == 2
    assert f"{path}: controller.json is not the file the run wrote" in capsys.readouterr().err


def _copy_project(destination: Path) -> Path:
    for package in ("pipeline", "stages"):
        shutil.copytree(
            ROOT / package, destination / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    return destination


def _stages_run(project: Path, scenario: Path, out: Path) -> set[str]:
    done = subprocess.run(
        [sys.executable, "-m", "pipeline", "synthesize", str(scenario), "--out", str(out)]
        + ["--samples", SAMPLES],
        cwd=project,
        env={**os.environ, "PYTHONPATH": str(project)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return computed(done.stdout)


@pytest.mark.slow
def test_editing_a_stage_recomputes_that_stage_and_nothing_unrelated(run, tmp_path):
    scenario, out = run
    project = _copy_project(tmp_path / "project")
    for stage in ("radius", "montecarlo"):
        source = project / "stages" / f"{stage}.py"
        source.write_text(source.read_text() + f"\n# an edit: stage {stage} must recompute\n")
    ran = _stages_run(project, scenario, out)
    assert {"radius_demos", "radius_optimized", "montecarlo"} <= ran
    assert not {"feedback", "covering_radius", "optimize"} & ran


def test_a_full_disk_is_one_line_and_exit_2(monkeypatch, capsys, tmp_path):
    """ENOSPC while writing (simulated where the output folder is prepared): no traceback."""
    import errno

    from pipeline.runtime import cli

    def full(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "summary.json"))

    monkeypatch.setattr(orchestrator, "check_output_folder", full)
    code = cli.main(["synthesize", "double_integrator", "--out", str(tmp_path), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert "No space left on device" in err and "summary.json" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
