"""How the synthetic pilot (``pipeline/demonstrations/pilot.py``) flies quadrotor_hill:
quadrotor_hill_flythrough's pilot, the same demos.

Route: climb, cross high above the hill, fly past Goal, come back down into it; flights 4 and 8
cross the hill 1.7 m lower, the way a hurried pilot does.

Steering law, a cascade for a planar quadrotor (thrust along the body axis, pitch driven by an
angular acceleration), on the registered state:

    F = (k_v (v_des,X - vX), hover + k_v (v_des,Y - vY))      desired force, stick units (N)
    u1 = |F| + noise_0,  theta_des = atan2(-F_X, F_Y) + noise_1 (clipped to max_tilt)
    u2 = k_theta (theta_des - theta) - k_omega omega          pitch stick
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.demonstrations.pilot import PilotConfig
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

CONFIG = PilotConfig(
    waypoints=((4.5, 5.8), (10.0, 6.6), (16.0, 6.0), (21.2, 4.8), (19.2, 2.6)),
    waypoint_jitter=0.25,
    cruise_speed=3.4,
    capture_radius=1.0,
    k_position=0.5,
    variant_flights=(4, 8),
    variant_waypoint=1,
    variant_shift=(0.0, -1.7),
    variant_note="This flight crosses the hill low, as a hurried pilot does.",
    delay=2,
    noise=(0.4, 0.05),  # thrust (N), aimed pitch (rad)
    noise_memory=0.8,
    stick_step=(0.5, 0.5),
    stick_range=((5.0, 14.9), (-10.0, 10.0)),
    goal_margin=0.3,
    stop_speed=0.6,
    max_duration=40.0,
    grid=(("Y", 3), ("X", 3)),
)


@dataclass(frozen=True)
class QuadrotorSteering:
    """The cascade above; gains in N s/m (k_velocity), 1/s^2 (k_theta), 1/s (k_omega)."""

    velocity: tuple[int, int]  # indices of vX, vY
    pitch: int
    pitch_rate: int
    k_velocity: float = 1.0
    k_theta: float = 4.0
    k_omega: float = 3.5
    hover_thrust: float = 9.8  # the thrust the pilot knows holds altitude
    max_tilt: float = 0.45  # (rad) the steepest pitch the pilot asks for

    def speed(self, x: FloatArray) -> float:
        return float(np.hypot(*x[list(self.velocity)]))

    def __call__(self, x: FloatArray, v_des: FloatArray, noise: FloatArray) -> FloatArray:
        v = x[list(self.velocity)]
        F = self.k_velocity * (v_des - v) + np.array([0.0, self.hover_thrust])
        theta_des = np.clip(np.arctan2(-F[0], F[1]) + noise[1], -self.max_tilt, self.max_tilt)
        thrust = np.hypot(*F) + noise[0]
        pitch = self.k_theta * (theta_des - x[self.pitch]) - self.k_omega * x[self.pitch_rate]
        return np.array([thrust, pitch])


def steering(scenario: Scenario) -> QuadrotorSteering:
    index = scenario.state_names.index
    return QuadrotorSteering(
        velocity=(index("vX"), index("vY")), pitch=index("theta"), pitch_rate=index("omega")
    )
