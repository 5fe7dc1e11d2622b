"""The static type check is clean: mypy over ``pipeline/`` and ``stages/`` with the settings in
``pyproject.toml`` (only the numba template modules, which numba compiles, are left out)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEMPLATES = ("pipeline/numerics/kernels/loops.py", "pipeline/numerics/kernels/rollout.py")


def test_mypy_settings_cover_the_code():
    """Every module of ``pipeline/`` and ``stages/`` is checked except the numba templates."""
    settings = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    assert set(settings["files"]) == {"pipeline", "stages"}
    assert not settings.get("ignore_errors", False)
    for override in settings.get("overrides", []):
        if override.get("ignore_errors"):
            modules = {m.replace(".", "/") + ".py" for m in override["module"]}
            assert modules <= set(TEMPLATES), f"errors ignored in {sorted(modules)}"


@pytest.mark.slow
def test_mypy_is_clean():
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    run = subprocess.run(
        [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml")],
        cwd=ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    checked = re.search(r"Success: no issues found in (\d+) source files", run.stdout)
    assert checked is not None, run.stdout + run.stderr
    modules = [p for folder in ("pipeline", "stages") for p in (ROOT / folder).rglob("*.py")]
    expected = len([p for p in modules if p.relative_to(ROOT).as_posix() not in TEMPLATES])
    assert int(checked.group(1)) == expected, run.stdout
