"""Issue 27 items 4, 5 and 9: no write, delete or read through a link planted in the output
folder, bounded reads of regular files only, and any valid path (bytes that are not UTF-8).

Most cases work on a copy of the session's ``double_integrator`` run (conftest; its stages are
reused, so a re-run takes seconds); a case that could hang or exhaust memory on a regression
runs in a subprocess with a timeout and a memory limit.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.io.artifacts import atomic_save, atomic_write_text
from pipeline.io.errors import UserError
from pipeline.io.files import output_root, replace
from pipeline.io.lock import folder_lock
from pipeline.runtime.cli import main
from pipeline.runtime.runner import StageRunner
from tests.helpers.runs import SAMPLES

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run


@pytest.fixture
def out(synthesis_run, tmp_path: Path) -> Path:
    """A private copy of the session's finished ``double_integrator`` run."""
    session = synthesis_run("double_integrator")
    assert session.result.exit_code == 0 and session.samples == int(SAMPLES)
    copy = tmp_path / "out"
    shutil.copytree(session.out, copy)
    return copy


def synthesize(out: Path, *extra: str) -> int:
    return main(
        ["synthesize", "double_integrator", "--out", str(out), "--samples", SAMPLES, "-q", *extra]
    )


def one_line(printed: str) -> str:
    """The single line printed (no traceback)."""
    assert "Traceback" not in printed
    lines = printed.strip().splitlines()
    assert len(lines) == 1, printed
    return lines[0]


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder``: (size, mtime)."""
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _limited() -> None:  # a subprocess that would read /dev/zero fails instead of swapping
    resource.setrlimit(resource.RLIMIT_AS, (4 * 2**30, 4 * 2**30))


def run_python(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """``python *args`` from the repository, with a memory limit; fails the test on a hang."""
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=environment,
        preexec_fn=_limited,
    )


# --- item 4: no writes through links ----------------------------------------------------------


def test_a_lock_file_that_is_a_link_is_refused_and_its_target_kept(tmp_path, capsys):
    """Issue 27 item 4: ``OUT/.lock`` linked to a file outside overwrote it with a pid."""
    precious = tmp_path / "precious.txt"
    precious.write_text("keep me\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / ".lock").symlink_to(precious)
    with pytest.raises(UserError, match="is a symbolic link"), folder_lock(out):
        pass
    assert synthesize(out) == 2
    line = one_line(capsys.readouterr().err)
    assert f"{out / '.lock'}: is a symbolic link" in line and "remove it" in line
    assert precious.read_text() == "keep me\n"
    assert not (out / "artifacts" / "feedback.json").exists()  # refused before any work


@pytest.mark.parametrize("fifo", [False, True], ids=["folder", "fifo"])
def test_a_lock_that_is_not_a_regular_file_is_refused(tmp_path, fifo):
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / ".lock") if fifo else (out / ".lock").mkdir()
    with pytest.raises(UserError, match="is a (FIFO|folder)"), folder_lock(out):
        pass


@pytest.mark.parametrize(
    "planted",
    ["artifacts link", "figures link", "artifacts file"],
)
def test_an_own_folder_that_is_a_link_or_a_file_is_refused(out, tmp_path, capsys, planted):
    """Issue 27 item 4: ``artifacts/`` or ``artifacts/figures/`` as links made the run replace or
    delete files in the target folder (the figure cache deletes files it did not use)."""
    elsewhere = tmp_path / "elsewhere"
    name = "artifacts" if planted.startswith("artifacts") else "artifacts/figures"
    if planted.endswith("link"):
        shutil.move(out / name, elsewhere)
        (elsewhere / "precious.txt").write_text("keep me\n")
        (out / name).symlink_to(elsewhere, target_is_directory=True)
        (out / "report.html").unlink()  # the report is written again: figures kept, others pruned
    else:
        elsewhere.mkdir()
        shutil.rmtree(out / name)
        (out / name).write_text("a file\n")
    before = snapshot(elsewhere)
    assert synthesize(out) == 2
    line = one_line(capsys.readouterr().err)
    kind = "a symbolic link" if planted.endswith("link") else "a regular file"
    assert f"{out / name}: is {kind} inside the output folder" in line
    assert snapshot(elsewhere) == before


def test_artifacts_swapped_for_a_link_mid_run_are_not_followed(out, tmp_path, capsys, monkeypatch):
    """Issue 27 item 4: a swap of ``artifacts/`` for a link mid-run wrote 12 files into the
    target. Swapped here before the Monte Carlo stage: the run refuses in one line and writes
    nothing there."""
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(out / "artifacts", elsewhere)
    before = snapshot(elsewhere)
    original = StageRunner.run_keyed

    def swap_then_run(self, name, *args, **kwargs):
        if name == "montecarlo" and not (out / "artifacts").is_symlink():
            (out / "artifacts").rename(out / "artifacts.moved")
            (out / "artifacts").symlink_to(elsewhere, target_is_directory=True)
        return original(self, name, *args, **kwargs)

    monkeypatch.setattr(StageRunner, "run_keyed", swap_then_run)
    assert synthesize(out) == 2
    line = one_line(capsys.readouterr().err)
    assert f"{out / 'artifacts'}: is a symbolic link inside the output folder" in line
    assert snapshot(elsewhere) == before


def test_a_write_keeps_the_folder_it_opened_when_that_is_swapped_mid_write(tmp_path):
    """The atomic writer creates, renames and cleans up through the folder's descriptor: a swap
    of the folder for a link while the file is written cannot redirect it; the next write is
    refused."""
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    (out / "artifacts").mkdir(parents=True)
    elsewhere.mkdir()

    def swap_while_writing(stream):
        stream.write(b"first half, ")
        (out / "artifacts").rename(out / "artifacts.moved")
        (out / "artifacts").symlink_to(elsewhere, target_is_directory=True)
        stream.write(b"second half")

    with output_root(out):
        atomic_save(out / "artifacts" / "stage.npz", swap_while_writing)
        assert (out / "artifacts.moved" / "stage.npz").read_bytes() == b"first half, second half"
        assert list(elsewhere.iterdir()) == []
        with pytest.raises(UserError, match="is a symbolic link inside the output folder"):
            atomic_write_text(out / "artifacts" / "next.json", "{}")
        runner = StageRunner(out)
        with pytest.raises(UserError, match="is a symbolic link inside the output folder"):
            runner.run_keyed("feedback", "key", lambda: 1.0)
    assert list(elsewhere.iterdir()) == []


def test_a_move_inside_the_output_folder_follows_no_link(tmp_path):
    """``replace`` (for publishing staged files) refuses a folder on either way that is a link."""
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    (out / ".staging").mkdir(parents=True)
    elsewhere.mkdir()
    (out / ".staging" / "summary.json").write_text("{}")
    (out / "artifacts").symlink_to(elsewhere, target_is_directory=True)
    with output_root(out):
        with pytest.raises(UserError, match="artifacts: is a symbolic link inside the output"):
            replace(out / ".staging" / "summary.json", out / "artifacts" / "inputs.json")
        replace(out / ".staging" / "summary.json", out / "summary.json")
    assert list(elsewhere.iterdir()) == [] and (out / "summary.json").read_text() == "{}"


# --- a folder where a file belongs --------------------------------------------------------------


def test_a_folder_where_a_cache_file_belongs_is_replaced(out, capsys):
    """Issue 27 note: a folder in place of a cache file made every re-run fail until removed by
    hand. The stage is computed again and its file replaces the folder."""
    (out / "artifacts" / "montecarlo.json").unlink()
    (out / "artifacts" / "montecarlo.json").mkdir()
    (out / "artifacts" / "montecarlo.json" / "inside.txt").write_text("x")
    assert synthesize(out) == 0, capsys.readouterr().err
    assert (out / "artifacts" / "montecarlo.json").is_file()
    assert (out / "controller.json").is_file()


def test_a_folder_where_a_cached_figure_belongs_is_replaced(out, capsys):
    figure = next((out / "artifacts" / "figures").glob("coverage-*.svg"))
    figure.unlink()
    figure.mkdir()
    assert main(["report", "double_integrator", "--from", str(out)]) == 0, capsys.readouterr()
    assert figure.is_file() and figure.read_text().startswith("<svg")


def test_a_folder_where_an_output_file_belongs_is_one_line_before_any_work(out, capsys):
    (out / "summary.json").unlink()
    (out / "summary.json").mkdir()
    started = time.perf_counter()
    assert synthesize(out) == 2
    assert time.perf_counter() - started < 30
    line = one_line(capsys.readouterr().err)
    assert f"{out / 'summary.json'}: is a folder where the run writes a file" in line


# --- item 5: bounded reads of regular files ------------------------------------------------------


@pytest.mark.parametrize("kind", ["/dev/zero", "fifo", "loop", "folder", "oversized"])
def test_load_controller_refuses_what_is_not_a_bounded_regular_file(tmp_path, kind):
    """Issue 27 item 5: ``/dev/zero`` as ``controller.json`` was read without limit (16 GB, a
    MemoryError under a memory cap) and a FIFO hung; each is one line, at once. Run in a
    subprocess, so that a regression fails on its timeout or memory limit."""
    path = tmp_path / "controller.json"
    if kind == "/dev/zero":
        path.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "loop":
        path.symlink_to(path)
    elif kind == "folder":
        path.mkdir()
    else:
        with open(path, "wb") as stream:  # sparse: 257 MiB of size, no disk
            stream.truncate(257 * 2**20)
    code = (
        "import sys, time; from pipeline.controller import load, ControllerFormatError\n"
        "started = time.perf_counter()\n"
        "try:\n    load(sys.argv[1])\n"
        "except ControllerFormatError as error:\n"
        "    print(error); print(f'{time.perf_counter() - started:.3f}')\n"
    )
    run = run_python("-c", code, str(path), timeout=60)
    assert run.returncode == 0, run.stderr[-2000:]
    message, seconds = run.stdout.strip().splitlines()
    expected = {
        "/dev/zero": "is a character device; expected a controller.json file",
        "fifo": "is a FIFO (named pipe); expected a controller.json file",
        "loop": "cannot read (Too many levels of symbolic links)",
        "folder": "is a folder; expected a controller.json file",
        "oversized": "larger than 256 MiB",
    }[kind]
    assert message.startswith(f"{path}: {expected}")
    assert float(seconds) < 1.0


@pytest.mark.parametrize(
    "file, command, code, said",
    [
        ("controller.json", "synthesize", 0, None),  # not ours to read: replaced by the run
        ("artifacts/montecarlo.npz", "synthesize", 0, None),  # a cache miss, recomputed
        ("summary.json", "report", 2, "summary.json is a FIFO (named pipe); expected a regular"),
        ("artifacts/inputs.json", "report", 2, "manifest is a FIFO (named pipe); expected a"),
    ],
)
def test_a_fifo_in_the_output_folder_never_hangs_a_command(out, file, command, code, said):
    """Issue 27 item 5: a FIFO as ``controller.json`` hung the run forever."""
    (out / file).unlink()
    os.mkfifo(out / file)
    if command == "synthesize":
        args = ["synthesize", "double_integrator", "--out", str(out), "--samples", SAMPLES, "-q"]
    else:
        args = ["report", "double_integrator", "--from", str(out)]
    run = run_python("-m", "pipeline", *args, timeout=240)
    assert run.returncode == code, run.stderr[-2000:]
    if said is None:
        assert (out / file).is_file()  # replaced by a regular file
    else:
        assert said in one_line(run.stderr)


def test_an_oversized_summary_is_refused_with_its_cap(out, capsys):
    with open(out / "summary.json", "r+b") as stream:  # sparse: 65 MiB of size
        stream.truncate(65 * 2**20)
    assert main(["report", "double_integrator", "--from", str(out)]) == 2
    assert "expected at most 64 MiB" in one_line(capsys.readouterr().err)


@pytest.mark.parametrize("kind", ["fifo", "loop"])
def test_a_demo_that_is_a_fifo_or_a_link_loop_is_one_line(tmp_path, kind):
    """Issue 27 item 5: a FIFO demo CSV hung, a symbolic-link loop gave a traceback."""
    scenario = tmp_path / "scenario"
    shutil.copytree(ROOT / "scenarios" / "double_integrator", scenario)
    demo = scenario / "demos" / "demo_01.csv"
    demo.unlink()
    os.mkfifo(demo) if kind == "fifo" else demo.symlink_to(demo.name)
    run = run_python("-m", "pipeline", "synthesize", str(scenario), "--out", str(tmp_path / "o"))
    assert run.returncode == 2
    line = one_line(run.stderr)
    said = "is a FIFO (named pipe); expected a regular file" if kind == "fifo" else "link loop"
    assert "demo_01.csv" in line and said in line


@pytest.mark.parametrize("kind", ["fifo", "/dev/zero", "loop"])
def test_a_scenario_file_that_is_not_a_regular_file_is_one_line(tmp_path, kind):
    """A scenario file that is a FIFO, a device or a link loop is named as such (it was an
    "unknown scenario"), at once."""
    scenario = tmp_path / "scenario"
    shutil.copytree(ROOT / "scenarios" / "double_integrator", scenario)
    path = scenario / "scenario.yaml"
    path.unlink()
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.symlink_to("/dev/zero" if kind == "/dev/zero" else path)
    run = run_python("-m", "pipeline", "synthesize", str(scenario), "--out", str(tmp_path / "o"))
    assert run.returncode == 2
    said = {
        "fifo": "is a FIFO (named pipe)",
        "/dev/zero": "is a character device",
        "loop": "is a symbolic-link loop",
    }[kind]
    assert f"{path}: cannot read scenario file ({said}" in one_line(run.stderr)


# --- item 9: any valid path ----------------------------------------------------------------------


def test_folders_whose_names_are_not_utf8_run_through_the_report(out, tmp_path, capsys):
    """Issue 27 item 9: a valid ``--out`` or scenario folder with byte 0xff certified, then the
    report stage failed (UnicodeEncodeError) and the controller was renamed stale."""
    odd = tmp_path / os.fsdecode(b"out\xff")
    out.rename(odd)
    (odd / "report.html").unlink()  # the report is written again, naming this folder
    scenario = tmp_path / os.fsdecode(b"scenario\xff")
    shutil.copytree(ROOT / "scenarios" / "double_integrator", scenario)
    args = ["--out", str(odd), "--samples", SAMPLES, "-q"]
    assert main(["synthesize", str(scenario), *args]) == 0, capsys.readouterr().err
    assert (odd / "controller.json").is_file() and not (odd / "controller.stale.json").exists()
    page = (odd / "report.html").read_bytes().decode("utf-8")  # valid UTF-8
    assert f"{tmp_path}/out\\xff" in page  # the byte shown as \xff
    assert main(["report", str(scenario), "--from", str(odd)]) == 0
    assert f"{tmp_path}/out\\xff/report.html" in capsys.readouterr().out
