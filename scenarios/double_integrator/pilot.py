"""How the synthetic pilot (``pipeline/demonstrations/pilot.py``) flies double_integrator.

Route: up and over the block, across, and down into Goal; flights 2 and 6 cross 0.6 m lower,
closer to the block. Steering law for a point mass whose inputs are its accelerations: push the
velocity towards the wanted one,

    (ux, uy) = k_v (v_des - (vx, vy)) + noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.demonstrations.pilot import PilotConfig
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

CONFIG = PilotConfig(
    waypoints=((2.5, 3.6), (7.5, 3.6), (10.0, 0.5)),
    waypoint_jitter=0.15,
    cruise_speed=1.4,
    capture_radius=0.8,
    k_position=0.6,
    variant_flights=(2, 6),
    variant_waypoint=1,
    variant_shift=(0.0, -0.6),
    variant_note="This flight passes close to the block, as a hurried pilot does.",
    delay=2,
    noise=(0.15, 0.15),  # (m/s^2) on each acceleration
    noise_memory=0.8,
    stick_step=(0.1, 0.1),
    stick_range=((-1.5, 1.5), (-1.5, 1.5)),
    goal_margin=0.4,
    stop_speed=0.25,
    max_duration=40.0,
    grid=(("y", 3), ("x", 3)),
)


@dataclass(frozen=True)
class PointMassSteering:
    """Velocity tracking with gain ``k_velocity`` (1/s)."""

    velocity: tuple[int, int]  # indices of vx, vy
    k_velocity: float = 1.2

    def speed(self, x: FloatArray) -> float:
        return float(np.hypot(*x[list(self.velocity)]))

    def __call__(self, x: FloatArray, v_des: FloatArray, noise: FloatArray) -> FloatArray:
        return self.k_velocity * (v_des - x[list(self.velocity)]) + noise  # (ux, uy)


def steering(scenario: Scenario) -> PointMassSteering:
    index = scenario.state_names.index
    return PointMassSteering(velocity=(index("vx"), index("vy")))
