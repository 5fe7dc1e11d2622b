"""Copies of the session's finished ``double_integrator`` run for tests that change its files."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.runtime.cli import main

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = "300"  # the session run's (conftest.CI_SYNTHESIS_SAMPLES): a rerun reuses its stages


def finished_copy(session, base: Path) -> tuple[Path, Path]:
    """``(scenario folder, output folder)`` under ``base``: a copy of the shipped scenario and of
    the session's run ``session``, synthesized again there (every stage reused: the stage keys
    hash the parsed scenario, not where its file is)."""
    assert session.result.exit_code == 0 and session.samples == int(SAMPLES)
    scenario, out = base / "double_integrator", base / "out"
    shutil.copytree(ROOT / "scenarios" / "double_integrator", scenario)
    shutil.copytree(session.out, out)
    assert main(["synthesize", str(scenario), "--out", str(out), "--samples", SAMPLES, "-q"]) == 0
    return scenario, out


def private_copy(finished: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    """A private copy of ``finished`` (scenario and output folder) under ``tmp_path``."""
    scenario, out = tmp_path / "double_integrator", tmp_path / "out"
    shutil.copytree(finished[0], scenario)
    shutil.copytree(finished[1], out)
    return scenario, out
