"""Shared fixtures for the stage tests: a planar double integrator scenario in ``tmp_path``."""

from __future__ import annotations

import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.model.scenario import Scenario, load_scenario
from tests.helpers.double_integrator import DOUBLE_INTEGRATOR


@pytest.fixture
def double_integrator(tmp_path: Path) -> Callable[..., Scenario]:
    """Factory: ``double_integrator(goal=..., region=..., rate=...)`` -> a loaded Scenario."""

    def make(
        goal: str = "[[-900, 1], [900, 1], [900, 900], [-900, 900]]",
        region: str = "{aX: [-100.0, 100.0]}",
        rate: float = 0.5,
    ) -> Scenario:
        path = tmp_path / "double_integrator" / "scenario.yaml"
        path.parent.mkdir(exist_ok=True)
        text = DOUBLE_INTEGRATOR % {"goal": goal, "region": region, "rate": rate}
        path.write_text(textwrap.dedent(text))
        return load_scenario(path, check_demos=False)

    return make
