"""A double integrator's first demo with a small initial set, for the robust-funnel tests."""

from __future__ import annotations

import dataclasses

import numpy as np
from shapely.geometry import box

from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import Trajectory, simulate

DISTURBANCE = np.array([0.0, 0.0, 0.05, 0.05])  # m/s^2 on both speeds of the double integrator


def double_integrator_case() -> tuple[Scenario, Trajectory, np.ndarray]:
    """The double integrator's first demo over 3 s, Goal around where it ends, and a small
    initial set ``Q_init (4, 4)`` (as tests/conftest.py's ``funnel_artifact``)."""
    scenario = load_scenario("double_integrator", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us[:30], scenario.Ts)
    end = trajectory.xs[-1, :2]
    scenario = dataclasses.replace(scenario, goal=box(*(end - 1.0), *(end + 1.0)))
    return scenario, trajectory, 2 * np.diag([0.05, 0.05, 0.0, 0.0]) ** 2
