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

The public API (documented in docs/api.md)::

    import pipeline
    result = pipeline.synthesize("double_integrator")    # -> pipeline.Synthesis
    scenario = pipeline.load_scenario("quadrotor_hill")  # name or path
    controller = pipeline.load_controller("reports/double_integrator/controller.json")
    flight = pipeline.fly(controller, "double_integrator", x0)  # -> pipeline.Flight

The names are imported lazily: ``import pipeline`` loads none of the numerics, and
``import pipeline.controller`` stays light. The library prints nothing; it logs on the
``pipeline`` logger (``logging``).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pipeline.controller import Controller, ControllerFormatError
    from pipeline.controller import load as load_controller
    from pipeline.io.errors import ScenarioError, UserError
    from pipeline.model.scenario import Scenario, available_scenarios, load_scenario
    from pipeline.numerics.closed_loop.flight import Flight, fly
    from pipeline.reporting.summary import Claim, ClaimKind, DemoSummary, Summary, Verdict
    from pipeline.runtime.api import synthesize
    from pipeline.runtime.synthesis import Outputs, Synthesis

__all__ = [
    "Claim",
    "ClaimKind",
    "Controller",
    "ControllerFormatError",
    "DemoSummary",
    "Flight",
    "Outputs",
    "Scenario",
    "ScenarioError",
    "Summary",
    "Synthesis",
    "UserError",
    "Verdict",
    "available_scenarios",
    "fly",
    "load_controller",
    "load_scenario",
    "synthesize",
]

# name -> (module, attribute)
_WHERE = {
    "synthesize": ("pipeline.runtime.api", "synthesize"),
    "Synthesis": ("pipeline.runtime.synthesis", "Synthesis"),
    "Outputs": ("pipeline.runtime.synthesis", "Outputs"),
    "Summary": ("pipeline.reporting.summary", "Summary"),
    "Verdict": ("pipeline.reporting.summary", "Verdict"),
    "Claim": ("pipeline.reporting.summary", "Claim"),
    "ClaimKind": ("pipeline.reporting.summary", "ClaimKind"),
    "DemoSummary": ("pipeline.reporting.summary", "DemoSummary"),
    "load_controller": ("pipeline.controller", "load"),
    "Controller": ("pipeline.controller", "Controller"),
    "ControllerFormatError": ("pipeline.controller", "ControllerFormatError"),
    "Scenario": ("pipeline.model.scenario", "Scenario"),
    "available_scenarios": ("pipeline.model.scenario", "available_scenarios"),
    "load_scenario": ("pipeline.model.scenario", "load_scenario"),
    "fly": ("pipeline.numerics.closed_loop.flight", "fly"),
    "Flight": ("pipeline.numerics.closed_loop.flight", "Flight"),
    "ScenarioError": ("pipeline.io.errors", "ScenarioError"),
    "UserError": ("pipeline.io.errors", "UserError"),
}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        module, attribute = _WHERE[name]
        return getattr(importlib.import_module(module), attribute)
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
