"""How the synthetic pilot (``pipeline/demonstrations/pilot.py``) drives unicycle_slalom.

Route: over bar 1, under bar 2, over bar 3, into Goal; flights 3 and 7 take bar 2 tighter.
Steering law for a car-like vehicle, on the registered state: aim the heading along the wanted
velocity and the speed at its length (kept within a comfortable speed band),

    psi_des = clip(atan2(v_des), +-max_heading),  s_des = clip(|v_des|, min_speed, max_speed)
    accel = k_v (s_des - v) + noise_0,  turn_rate = k_psi wrap(psi_des - psi) + noise_1.

The vehicle never stops (the certificate needs it rolling), so the pilot stops recording once
inside Goal shrunk by ``goal_margin`` (``stop_speed`` is above any speed it drives).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.demonstrations.pilot import PilotConfig
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

CONFIG = PilotConfig(
    waypoints=((6.3, 1.3), (13.3, -1.3), (20.3, 1.3), (27.0, 0.0)),
    waypoint_jitter=0.1,
    cruise_speed=2.5,
    capture_radius=1.0,
    k_position=1.0,
    variant_flights=(3, 7),
    variant_waypoint=1,
    variant_shift=(0.0, 0.3),
    variant_note="This run takes bar 2 tighter, as a hurried driver does.",
    delay=2,
    noise=(0.1, 0.05),  # accel (m/s^2), turn rate (rad/s)
    noise_memory=0.8,
    stick_step=(0.1, 0.05),
    stick_range=((-1.0, 1.0), (-1.0, 1.0)),
    goal_margin=1.0,
    stop_speed=100.0,
    max_duration=40.0,
    grid=(("psi", 2), ("y", 2), ("x", 2)),
)


@dataclass(frozen=True)
class CarSteering:
    """Heading and speed tracking; gains in 1/s."""

    heading: int  # index of psi
    speed_index: int  # index of v
    k_speed: float = 1.0
    k_heading: float = 1.5
    max_heading: float = 0.45  # (rad) the steepest heading the driver aims for
    min_speed: float = 2.2
    max_speed: float = 2.8

    def speed(self, x: FloatArray) -> float:
        return float(abs(x[self.speed_index]))

    def __call__(self, x: FloatArray, v_des: FloatArray, noise: FloatArray) -> FloatArray:
        psi_des = np.clip(np.arctan2(v_des[1], v_des[0]), -self.max_heading, self.max_heading)
        s_des = np.clip(np.hypot(*v_des), self.min_speed, self.max_speed)
        error = (psi_des - x[self.heading] + np.pi) % (2 * np.pi) - np.pi
        accel = self.k_speed * (s_des - x[self.speed_index]) + noise[0]
        return np.array([accel, self.k_heading * error + noise[1]])  # (accel, turn_rate)


def steering(scenario: Scenario) -> CarSteering:
    index = scenario.state_names.index
    return CarSteering(heading=index("psi"), speed_index=index("v"))
