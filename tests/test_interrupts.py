"""Ctrl-C on a run with worker processes (issue 27, item 6).

A terminal's Ctrl-C sends SIGINT to the whole foreground process group: the run, the fork server
and the workers. Only the run may act on it: one "interrupted" line on stderr, exit code 130, no
traceback from any process, the folder's lock released and no process left behind, also when a
second Ctrl-C follows 0.3 s later, while the first is being handled.

The run is a re-run in a copy of double_integrator's session run (300 Monte Carlo samples):
every stage before the Monte Carlo is reused, and the Monte Carlo's default 100,000 runs start
the fork server and the workers (a run from an empty folder computed the stages before, ~3-4 s
of CPU each time, for the same interruption).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.io.lock import LOCK_NAME

ROOT = Path(__file__).resolve().parents[1]
INTERRUPTED = "interrupted: finished artifacts are kept; re-run to resume"


def _group(pgid: int) -> list[int]:
    """The live (not zombie) processes of process group ``pgid``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            found.append(int(stat.parent.name))
    return found


def _fork_server_started(pgid: int) -> bool:
    return any(
        b"multiprocessing.forkserver" in Path(f"/proc/{pid}/cmdline").read_bytes()
        for pid in _group(pgid)
    )


def _as_from_a_shell() -> None:
    """In the child before it runs: SIGINT default and unblocked, as a shell starts a command.
    A child inherits both from this test's worker, which earlier tests in the same worker may
    leave ignored or blocked (measured: the whole suite's workers did, each file alone not)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _read(path: str) -> bytes:
    """A /proc file's bytes; empty if the process is gone."""
    try:
        return Path(path).read_bytes()
    except OSError:
        return b""


def _workers(pgid: int) -> int:
    """How many processes the fork server of process group ``pgid`` has forked (the pool's)."""
    group = _group(pgid)
    servers = {
        str(pid).encode()
        for pid in group
        if b"multiprocessing.forkserver" in _read(f"/proc/{pid}/cmdline")
    }
    parents = [_read(f"/proc/{pid}/stat").rsplit(b")", 1)[-1].split()[1:2] for pid in group]
    return sum(1 for parent in parents if parent and parent[0] in servers)


@pytest.mark.slow
@pytest.mark.xdist_group("synthesis-double_integrator")  # with the session run it copies
@pytest.mark.parametrize("signals", [1, 2], ids=["one Ctrl-C", "two Ctrl-C 0.3 s apart"])
@pytest.mark.parametrize("when", ["fork server importing", "workers computing"])
def test_ctrl_c_with_workers_prints_one_line_and_exits_130(
    synthesis_run, tmp_path: Path, when: str, signals: int
) -> None:
    out = tmp_path / "out"
    shutil.copytree(synthesis_run("double_integrator").out, out)
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "synthesize", "double_integrator"]
        + ["--jobs", "2", "--out", str(out)],  # the default 100,000 Monte Carlo runs: long
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
        preexec_fn=_as_from_a_shell,
    )
    try:
        assert process.stdout is not None
        printed = []
        for line in process.stdout:  # each stage's line is flushed as it is logged
            printed.append(line)
            if line.startswith("[certify]"):  # the Monte Carlo next: it starts the fork server
                break
        assert printed and printed[-1].startswith("[certify]"), "".join(printed)
        assert "[optimize] reused (inputs unchanged)" in "".join(printed)  # no pool before
        deadline = time.monotonic() + 30
        while not _fork_server_started(process.pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert _fork_server_started(process.pid)  # its imports take seconds (cvxpy, scipy)
        if when == "workers computing":  # the server forked both workers: give them work
            while _workers(process.pid) < 2 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert _workers(process.pid) == 2
            time.sleep(0.5)
        for index in range(signals):
            if index:
                time.sleep(0.3)
            os.killpg(process.pid, signal.SIGINT)
        rest, error = process.communicate(timeout=120)
        assert process.returncode == 130, error
        assert error.splitlines() == [INTERRUPTED]
        assert "Traceback" not in rest
        handle = os.open(out / LOCK_NAME, os.O_RDONLY)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released: free at once
        finally:
            os.close(handle)
        deadline = time.monotonic() + 30  # the fork server ends after its imports (seconds)
        while _group(process.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _group(process.pid), "processes of the interrupted run remain"
    finally:  # whatever happened, leave nothing of this test running
        if process.poll() is None:
            process.kill()
        for pid in _group(process.pid):
            os.kill(pid, signal.SIGKILL)
        process.communicate()


def test_a_run_that_hangs_after_ctrl_c_still_ends_with_130() -> None:
    """If unwinding hangs after the first Ctrl-C (a lock left held by the interrupted code), the
    watchdog ends the process ``INTERRUPT_GRACE`` seconds later: the one line, exit 130."""
    code = (
        "import os, signal, time\n"
        "import pipeline.runtime.cli as cli\n"
        "cli.INTERRUPT_GRACE = 0.5\n"
        "with cli._one_interrupt():\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        time.sleep(5)\n"
        "    except KeyboardInterrupt:\n"
        "        time.sleep(60)  # the unwinding that never ends\n"
    )
    started = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=30,
        env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=_as_from_a_shell,
    )  # fmt: skip
    assert done.returncode == 130 and done.stderr.splitlines() == [INTERRUPTED], done.stderr
    assert time.monotonic() - started < 20
