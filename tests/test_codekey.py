"""Cache keys follow the code: editing a module changes the key of every stage that imports it,
transitively, and of no other stage (checked on a temporary copy of the project)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from pipeline.runtime.codekey import LIBRARIES, code_key, library_versions, modules_of

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("stages.feedback", "stages.radius", "stages.report")


def _keys(project: Path) -> dict[str, str]:
    code = (
        "import json; from pipeline.runtime.codekey import code_key; "
        f"print(json.dumps({{m: code_key(m) for m in {STAGES!r}}}))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=project,
        env={**os.environ, "PYTHONPATH": str(project)},
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout)


def _append(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text)


def test_an_edit_changes_exactly_the_keys_of_the_stages_that_use_it(tmp_path):
    for package in ("pipeline", "stages"):
        shutil.copytree(ROOT / package, tmp_path / package)
    keys = [_keys(tmp_path)]
    _append(tmp_path / "stages" / "radius.py", "\n# edited\n")
    keys.append(_keys(tmp_path))
    # feedback only (the hull is the report's too: its section Declared uncertainty derives (U1))
    _append(tmp_path / "pipeline" / "numerics" / "tube" / "contraction.py", "\n# edited\n")
    keys.append(_keys(tmp_path))
    _append(tmp_path / "pipeline" / "reporting" / "templates" / "report.html.j2", "\n")
    keys.append(_keys(tmp_path))
    changed = [{m for m in STAGES if a[m] != b[m]} for a, b in zip(keys, keys[1:], strict=False)]
    assert changed == [{"stages.radius"}, {"stages.feedback"}, {"stages.report"}]


def test_the_key_covers_imported_modules_and_library_versions():
    assert "pipeline.numerics.hull" in modules_of("stages.feedback")
    assert "pipeline.numerics.hull" not in modules_of("stages.radius")
    assert [name for name, _ in library_versions()] == list(LIBRARIES)
    assert code_key("stages.radius") != code_key(
        "stages.radius", "pipeline.numerics.verify.nominal"
    )
