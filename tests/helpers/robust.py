"""A double integrator's first demo with a small initial set, for the robust-funnel tests."""

from __future__ import annotations

import dataclasses

import numpy as np
from shapely.geometry import box

from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import Trajectory, simulate

DISTURBANCE = np.array([0.0, 0.0, 0.05, 0.05])  # m/s^2 on both speeds of the double integrator


def rk4_step(field, x: np.ndarray, dt: float) -> np.ndarray:
    """One classical RK4 step of ``x' = field(x)`` (states stacked in rows)."""
    k1 = field(x)
    k2 = field(x + dt / 2 * k1)
    k3 = field(x + dt / 2 * k2)
    k4 = field(x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def double_integrator_case() -> tuple[Scenario, Trajectory, np.ndarray]:
    """The double integrator's first demo over 3 s, Goal around where it ends, and a small
    initial set ``Q_init (4, 4)`` (as tests/conftest.py's ``funnel_artifact``)."""
    scenario = load_scenario("double_integrator", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us[:30], scenario.Ts)
    end = trajectory.xs[-1, :2]
    scenario = dataclasses.replace(scenario, goal=box(*(end - 1.0), *(end + 1.0)))
    return scenario, trajectory, 2 * np.diag([0.05, 0.05, 0.0, 0.0]) ** 2
