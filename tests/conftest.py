"""Shared fixtures: one full synthesis per shipped scenario per test session."""

from __future__ import annotations

import pytest

from pipeline.runtime.api import synthesize

E2E_SAMPLES = 1000  # quadrotor_hill: the end-to-end tests reuse its run
CI_SYNTHESIS_SAMPLES = 300  # every other shipped scenario: the CI safety check only
SAMPLES = {"quadrotor_hill": E2E_SAMPLES}


@pytest.fixture(scope="session")
def synthesis(tmp_path_factory):
    """Factory: ``synthesis(name)`` -> ``(exit_code, out)`` of ``synthesize name`` with
    ``SAMPLES.get(name, CI_SYNTHESIS_SAMPLES)`` Monte Carlo samples, run once per session."""
    runs: dict[str, tuple[int, object]] = {}

    def run(name: str):
        if name not in runs:
            out = tmp_path_factory.mktemp(name)
            result = synthesize(name, out=out, samples=SAMPLES.get(name, CI_SYNTHESIS_SAMPLES))
            runs[name] = (result.exit_code, out)
        return runs[name]

    return run


@pytest.fixture(scope="session")
def synthesized(synthesis):
    """``(exit_code, out)`` of ``synthesize quadrotor_hill`` with 1,000 Monte Carlo samples."""
    return synthesis("quadrotor_hill")
