"""Where runs are written by default (``pipeline.io.folders``) and the progress bars
(``pipeline.io.progress``), silent unless stderr is a terminal."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from pipeline.io import progress
from pipeline.io.folders import default_output_folder


def test_runs_go_under_reports_in_the_current_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert default_output_folder("slalom") == tmp_path / "reports" / "slalom"
    assert default_output_folder("slalom").is_absolute()


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("quiet", [False, True])
def test_a_progress_bar_draws_only_on_a_terminal_and_not_when_quiet(
    quiet: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    terminal = Terminal()
    monkeypatch.setattr(progress.sys, "stderr", terminal)
    with progress.progress_bar(4, "demos", quiet=quiet) as advance:
        for _ in range(4):
            advance(1)
    assert ("demos" in terminal.getvalue()) == (not quiet)


def test_no_progress_bar_when_stderr_is_not_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    redirected = io.StringIO()  # isatty() is False, as for a file or a pipe
    monkeypatch.setattr(progress.sys, "stderr", redirected)
    with progress.progress_bar(4, "demos") as advance:
        advance(4)
    assert redirected.getvalue() == ""
