"""The output folder of a run: checked before computing, locked while running, published as a
whole, and marked when a run fails so that nothing it did not certify looks current.

- ``check_output_folder``: ``--out`` must be a folder we can write (``check_report_folder``),
  whose own folders (``OWN_FOLDERS``) are folders, not links or files, with no folder where the
  run writes a file (``check_layout``), and must not hold another scenario's
  ``controller.json``; each mistake is a ``UserError`` (exit 2) before any work.
- ``staging_folder`` and ``publish``: a run writes its ``controller.json``, ``summary.json``,
  input manifest and reports into ``OUT/.staging`` and moves them into place only after certify
  and the report, so that the folder's files always describe one run (below). The stage cache
  ``OUT/artifacts`` is written in place: it is keyed by content, and the manifest names the
  results the published run used.
- ``check_complete``: a reader's check that no publish was cut short (``INCOMPLETE``).
- ``mark_failed``: a run that fails writes ``summary.json`` saying so (stage and reason) and
  renames the previous ``controller.json`` and reports to ``*.stale.*``.

Publishing is a sequence of renames, each atomic, not one: ``publish`` first writes the marker
``OUT/INCOMPLETE``, then removes the previous ``summary.json`` and reports (the verdict), then
renames the manifest, ``controller.json`` and the reports into place, ``summary.json`` last, and
removes the marker. A run killed at any instant leaves either the previous run's files, all of
them, or the marker; and at no instant does a ``summary.json`` or report sit beside a
``controller.json`` other than the one it describes.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import stat
import tempfile
from pathlib import Path

from pipeline.controller import MAX_BYTES as CONTROLLER_MAX_BYTES
from pipeline.io import files
from pipeline.io.artifacts import atomic_write_json, atomic_write_text
from pipeline.io.errors import UserError
from pipeline.io.files import FileRefused, PathRefused, open_folder, output_root, read_bytes

STALE_FILES = ("controller.json", "report.html", "report.pdf", "scenario.png")
REPORTS = ("report.html", "report.pdf", "scenario.png")
MANIFEST = "inputs.json"  # published as OUT/artifacts/inputs.json
STAGING = ".staging"
INCOMPLETE = "INCOMPLETE"
INCOMPLETE_TEXT = (
    "A run was moving its outputs into this folder and stopped before it finished: the files\n"
    "here may belong to two runs. Run `python -m pipeline synthesize` on this folder again.\n"
)
OWN_FOLDERS = ("artifacts", "artifacts/figures", STAGING)  # the folders a run writes into
log = logging.getLogger(__name__)


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
    written = (
        "summary.json", INCOMPLETE, *STALE_FILES,
        *(stale_name(Path(n)).name for n in STALE_FILES),
    )  # fmt: skip
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


def _remove(path: Path) -> None:
    """Delete ``path``, a folder with its files (a link or file: itself), if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def staging_folder(out: Path) -> Path:
    """``out/.staging``, empty (what a killed run left there is removed): where a run writes
    ``controller.json``, ``summary.json``, ``inputs.json`` and the reports until ``publish``."""
    staging = out / STAGING
    _remove(staging)
    staging.mkdir()
    return staging


def check_complete(out: Path, scenario_name: str) -> None:
    """Raise ``UserError`` when a run stopped while publishing into ``out`` (the marker is
    there): its files may belong to two runs."""
    marker = out / INCOMPLETE
    if marker.exists() or marker.is_symlink():
        raise UserError(
            "the output folder is incomplete: a run stopped while moving its outputs into place",
            file=marker,
            expected=f"a finished run; run `python -m pipeline synthesize {scenario_name} "
            f"--out {out}` again",
        )


def publish(out: Path, staging: Path, certified: bool) -> None:
    """Move the run in ``staging`` into ``out`` as a whole (the order is in the module
    docstring): ``inputs.json`` to ``out/artifacts``, ``controller.json`` (renamed
    ``controller.stale.json`` when the run did not certify it), the reports when the run wrote
    them (else the published ones are this run's already: same report key), ``summary.json``
    last; ``*.stale.*`` files of an earlier failed run are removed."""
    marker = out / INCOMPLETE
    atomic_write_text(marker, INCOMPLETE_TEXT)
    fresh_reports = files.is_regular(staging / "report.html")
    # the previous verdict goes first; every move and deletion goes through the folders'
    # descriptors (pipeline.io.files): a folder swapped for a link cannot redirect it
    files.unlink(out / "summary.json")
    if fresh_reports:
        for name in REPORTS:
            files.unlink(out / name)
    clear_stale(out)
    files.replace(staging / MANIFEST, out / "artifacts" / MANIFEST)
    controller = out / "controller.json"
    if certified:
        files.replace(staging / "controller.json", controller)
    else:  # this run did not certify it: no current-looking controller.json
        files.unlink(controller)
        files.replace(staging / "controller.json", stale_name(controller))
        log.info(f"controller.json renamed to {stale_name(controller).name}: not certified")
    for name in REPORTS:
        if files.is_regular(staging / name):
            files.replace(staging / name, out / name)
    files.replace(staging / "summary.json", out / "summary.json")
    files.unlink(marker)
    _remove(staging)


def mark_failed(
    out: Path, scenario_name: str, stage: str, reason: str, traceback: list[str] | None = None
) -> list[Path]:
    """Write ``out/summary.json`` for a failed run (with the ``traceback`` lines of a crash) and
    rename the previous run's controller and reports to ``*.stale.*``; returns the renamed files
    (their new names). What the run staged is removed, and so is the ``INCOMPLETE`` marker: the
    failed summary says what the folder holds."""
    _remove(out / STAGING)
    files.unlink(out / "summary.json")  # the previous verdict goes first (as in publish)
    renamed = []
    for name in STALE_FILES:
        path = out / name
        if files.is_regular(path):
            files.replace(path, stale_name(path))
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
            **({"traceback": traceback} if traceback else {}),
        },
    )
    files.unlink(out / INCOMPLETE)
    return renamed


def clear_stale(out: Path) -> None:
    """Remove ``*.stale.*`` files once a run has written fresh ones."""
    for name in STALE_FILES:
        files.unlink(stale_name(out / name))
