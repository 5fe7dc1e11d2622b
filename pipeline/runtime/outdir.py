"""The output folder of a run: checked before computing, locked while running, and marked when a
run fails so that nothing it did not certify looks current.

- ``check_output_folder``: ``--out`` must be a folder we can write (``check_report_folder``),
  whose own folders (``OWN_FOLDERS``) are folders, not links or files, with no folder where the
  run writes a file (``check_layout``), and must not hold another scenario's
  ``controller.json``; each mistake is a ``UserError`` (exit 2) before any work.
- ``mark_failed``: a run that fails writes ``summary.json`` saying so (stage and reason) and
  renames the previous ``controller.json`` and reports to ``*.stale.*``.
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from pathlib import Path

from pipeline.controller import MAX_BYTES as CONTROLLER_MAX_BYTES
from pipeline.io.artifacts import atomic_write_json
from pipeline.io.errors import UserError
from pipeline.io.files import FileRefused, PathRefused, open_folder, output_root, read_bytes

STALE_FILES = ("controller.json", "report.html", "report.pdf", "scenario.png")
OWN_FOLDERS = ("artifacts", "artifacts/figures")  # the folders a run writes into, inside OUT


def stale_name(path: Path) -> Path:
    """``controller.json`` -> ``controller.stale.json``."""
    return path.with_name(f"{path.stem}.stale{path.suffix}")


def _owner(controller: Path) -> object:
    """The scenario named by an existing ``controller.json`` (``None`` if it names none)."""
    try:
        document = json.loads(read_bytes(controller, CONTROLLER_MAX_BYTES))
    except (OSError, FileRefused, ValueError, RecursionError):
        return None  # unreadable (or not a regular file): ours to regenerate
    return document.get("scenario") if isinstance(document, dict) else None


def check_output_folder(out: Path, scenario_name: str) -> None:
    """Create ``out`` if needed and check, before any computing, that a run can use it."""
    check_report_folder(out)
    check_layout(out)
    check_report_folder(out / "artifacts", named=out)
    owner = _owner(out / "controller.json")
    if owner is not None and owner != scenario_name:
        raise UserError(
            "output folder holds another scenario's controller.json",
            file=out / "controller.json",
            found=owner,
            expected=f"'{scenario_name}'; choose another --out or remove that folder",
        )


def check_layout(out: Path) -> None:
    """``out``'s own folders (``OWN_FOLDERS``, where present) are folders, not links or files,
    and no folder stands where the run writes a file; else ``PathRefused`` in one line."""
    written = ("summary.json", *STALE_FILES, *(stale_name(Path(n)).name for n in STALE_FILES))
    with output_root(out):
        for name in OWN_FOLDERS:
            try:
                os.close(open_folder(out / name))
            except FileNotFoundError:
                pass
        for name in written:
            try:
                mode = os.lstat(out / name).st_mode
            except FileNotFoundError:
                continue
            if stat.S_ISDIR(mode):
                raise PathRefused(
                    "is a folder where the run writes a file",
                    file=out / name,
                    expected="a file: remove or rename that folder",
                )


def check_report_folder(out: Path, named: Path | None = None) -> None:
    """Create ``out`` if needed and check that this user can write there (``named``: the folder
    the user gave, when ``out`` is inside it)."""
    named = out if named is None else named
    if named.exists() and not named.is_dir():
        raise UserError("--out names a file", file=named, expected="a folder (or a new path)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as error:
        raise UserError(
            f"output folder is not writable ({error.strerror})",
            file=named,
            expected="a folder this user can write; choose another --out",
        ) from None


def mark_failed(out: Path, scenario_name: str, stage: str, reason: str) -> list[Path]:
    """Write ``out/summary.json`` for a failed run and rename the previous run's controller and
    reports to ``*.stale.*``; returns the renamed files (their new names)."""
    renamed = []
    for name in STALE_FILES:
        path = out / name
        if path.is_file():
            os.replace(path, stale_name(path))
            renamed.append(stale_name(path))
    atomic_write_json(
        out / "summary.json",
        {
            "status": "failed",
            "scenario": scenario_name,
            "stage": stage,
            "reason": reason,
            "verdict": {"text": f"failed at stage {stage}", "certified": False},
            "stale": [p.name for p in renamed],
        },
    )
    return renamed


def clear_stale(out: Path) -> None:
    """Remove ``*.stale.*`` files once a run has written fresh ones."""
    for name in STALE_FILES:
        stale_name(out / name).unlink(missing_ok=True)
