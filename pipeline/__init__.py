"""Safety controller synthesis from human-generated trajectories (Winn & Julius).

Core objects: scenarios, dynamics, simulation, geometry, artifacts, orchestration and the CLI.
"""

from pipeline.errors import ScenarioError, UserError
from pipeline.scenario import Scenario, available_scenarios, load_scenario

__all__ = ["Scenario", "ScenarioError", "UserError", "available_scenarios", "load_scenario"]
