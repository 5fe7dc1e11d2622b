"""mypy's settings in ``pyproject.toml`` cover the code: every module of ``pipeline/`` and
``stages/`` except the numba template modules (which numba compiles), untyped functions
included. mypy itself runs in ``make lint`` (which CI runs beside ``make test``), not here."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEMPLATES = ("pipeline/numerics/kernels/loops.py", "pipeline/numerics/kernels/rollout.py")


def test_mypy_settings_cover_the_code():
    """Every module of ``pipeline/`` and ``stages/`` is checked except the numba templates."""
    settings = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    assert set(settings["files"]) == {"pipeline", "stages"}
    assert settings["check_untyped_defs"] is True
    assert not settings.get("ignore_errors", False)
    modules = [
        p.relative_to(ROOT).as_posix()
        for folder in ("pipeline", "stages")
        for p in (ROOT / folder).rglob("*.py")
    ]
    excluded = {m for m in modules if any(re.search(x, m) for x in settings.get("exclude", []))}
    assert excluded <= set(TEMPLATES), f"excluded from mypy: {sorted(excluded)}"
    for override in settings.get("overrides", []):
        if override.get("ignore_errors"):
            modules = {m.replace(".", "/") + ".py" for m in override["module"]}
            assert modules <= set(TEMPLATES), f"errors ignored in {sorted(modules)}"
