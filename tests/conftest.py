"""Shared fixtures: one full synthesis of quadrotor_hill per test session."""

from __future__ import annotations

import pytest

from pipeline.orchestrator import RunOptions, synthesize

E2E_SAMPLES = 1000


@pytest.fixture(scope="session")
def synthesized(tmp_path_factory):
    """``(exit_code, out)`` of ``synthesize quadrotor_hill`` with 1,000 Monte Carlo samples."""
    out = tmp_path_factory.mktemp("quadrotor_hill")
    code = synthesize(
        "quadrotor_hill", out=out, options=RunOptions(samples=E2E_SAMPLES, quiet=True)
    )
    return code, out
