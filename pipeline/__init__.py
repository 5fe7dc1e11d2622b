"""Safety controller synthesis from human-generated trajectories (Winn & Julius).

The package is layered; a module imports only from its own layer or the ones below it
(``pyproject.toml``'s import-linter contracts enforce this)::

    pipeline.runtime          orchestration, stage cache, command line
    pipeline.demonstrations   pilot and recorder (write demo files)
    stages                    one module per stage, one function and one frozen result each
    pipeline.reporting        HTML/PDF report and figures (reads results)
    pipeline.numerics         penalties, gradients, descent, hull, verification, closed loop
    pipeline.model            scenario, dynamics, geometry, simulation, demos
    pipeline.io               errors, atomic files, hashing, executors, progress

``pipeline.controller`` stands apart: NumPy and the standard library only, so users can copy it.

The names below are imported lazily, so ``import pipeline.controller`` stays light.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipeline.io.errors import ScenarioError, UserError
    from pipeline.model.scenario import Scenario, available_scenarios, load_scenario

__all__ = ["Scenario", "ScenarioError", "UserError", "available_scenarios", "load_scenario"]

_WHERE = {
    "Scenario": "pipeline.model.scenario",
    "available_scenarios": "pipeline.model.scenario",
    "load_scenario": "pipeline.model.scenario",
    "ScenarioError": "pipeline.io.errors",
    "UserError": "pipeline.io.errors",
}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
