"""A synthetic pilot: the stand-in for the paper's human with a joystick (§IV-A).

No human is available to this project, so the shipped demonstrations are flown by this model of
one. The pilot flies the same simulator the pipeline uses (``pipeline.simulate.simulate``) and
moves the stick once per sample, so the input is piecewise constant, ``u(t) = u[k]`` on
``[k Ts, (k+1) Ts)``. What makes it human-like, and suboptimal:

- **Waypoints.** It steers for a route of waypoints in the position plane (climb, cross high
  above the hill, fly past Goal, come back down into it) at a cruise speed, switching to the next
  waypoint once within ``capture_radius`` of it or past it; at the last one it slows to a stop.
  Some flights (``low_flights``) cut the hill crossing lower, the way a hurried pilot does.
- **Late reactions.** It acts on the state it saw ``delay`` samples ago.
- **A coarse stick.** Thrust and pitch commands are rounded to ``thrust_step`` and
  ``pitch_step``, and kept in a comfortable range (``thrust_range``, inside the input bounds).
- **An unsteady hand.** Seeded, slowly varying noise (AR(1), ``numpy.random.default_rng(seed)``)
  on both commands, and per-flight jitter of the waypoints.

Its steering law is a cascade written for a planar quadrotor (thrust along the body axis, pitch
driven by an angular acceleration), parameterised by the gains in ``PILOT_CONFIGS``:

    F = (k_v (v_des,X - vX), hover + k_v (v_des,Y - vY))      desired force, stick units (N)
    u1 = |F|,  theta_des = atan2(-F_X, F_Y)                   thrust and pitch that would give F
    u2 = k_theta (theta_des - theta) - k_omega omega          pitch stick

The recording stops at the first sample where the vehicle is inside Goal (shrunk by
``goal_margin``) and slower than ``stop_speed``, so the demo's final state is in Goal.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import geometry
from pipeline.artifacts import atomic_write_text
from pipeline.demos import Demo, write_demo_csv
from pipeline.dynamics import FloatArray
from pipeline.errors import UserError
from pipeline.scenario import Scenario, check_demo_flight, load_scenario, resolve_scenario_path
from pipeline.simulate import simulate


@dataclass(frozen=True)
class PilotConfig:
    """How the synthetic pilot flies one scenario (positions in m, speeds in m/s, forces in N)."""

    waypoints: tuple[tuple[float, float], ...]  # route; the last one is the landing aim
    low_flights: tuple[int, ...]  # flight numbers (1-based) that cross the hill low
    low_drop: float  # how much lower those flights put waypoint ``crossing`` (m)
    crossing: int  # index of the waypoint above the hill
    waypoint_jitter: float  # std of the per-flight waypoint deviation (m)
    cruise_speed: float
    capture_radius: float
    k_position: float  # (1/s) approach gain at the last waypoint
    k_velocity: float  # (N s/m) velocity error -> force
    k_theta: float  # (1/s^2) pitch error -> pitch acceleration
    k_omega: float  # (1/s) pitch rate -> pitch acceleration
    hover_thrust: float  # the thrust the pilot knows holds altitude
    max_tilt: float  # (rad) the steepest pitch the pilot asks for
    thrust_range: tuple[float, float]  # comfortable stick range (clipped to the input bounds)
    thrust_step: float  # stick resolution
    pitch_step: float
    delay: int  # reaction delay (samples)
    thrust_noise: float  # std of the hand's noise (stick units)
    pitch_noise: float  # (rad) on the pitch the pilot aims for
    noise_memory: float  # AR(1) coefficient of the noise, in [0, 1)
    goal_margin: float  # stop only this far inside Goal (m)
    stop_speed: float
    max_duration: float  # (s) give up after this long
    grid: tuple[int, int]  # flights start on this grid of cell centres over Init's position box
    roles: tuple[tuple[str, str], ...]  # (steering role, state or input name), one per ROLES


ROLES = ("pitch", "velocity_X", "velocity_Y", "pitch_rate", "thrust", "pitch_acceleration")


PILOT_CONFIGS: dict[str, PilotConfig] = {
    "quadrotor_hill": PilotConfig(
        waypoints=((4.5, 5.8), (10.0, 6.6), (16.0, 6.0), (21.2, 4.8), (19.2, 2.6)),
        low_flights=(4, 8),
        low_drop=1.7,
        crossing=1,
        waypoint_jitter=0.25,
        cruise_speed=3.4,
        capture_radius=1.0,
        k_position=0.5,
        k_velocity=1.0,
        k_theta=4.0,
        k_omega=3.5,
        hover_thrust=9.8,
        max_tilt=0.45,
        thrust_range=(5.0, 14.9),
        thrust_step=0.5,
        pitch_step=0.5,
        delay=2,
        thrust_noise=0.4,
        pitch_noise=0.05,
        noise_memory=0.8,
        goal_margin=0.3,
        stop_speed=0.6,
        max_duration=40.0,
        grid=(3, 3),
        roles=(
            ("pitch", "theta"),
            ("velocity_X", "vX"),
            ("velocity_Y", "vY"),
            ("pitch_rate", "omega"),
            ("thrust", "u1"),
            ("pitch_acceleration", "u2"),
        ),
    ),
}


def pilot_config(scenario: Scenario) -> PilotConfig:
    """The pilot's configuration for ``scenario``, or a UserError naming the configured ones."""
    try:
        return PILOT_CONFIGS[scenario.name]
    except KeyError:
        raise UserError(
            f"the synthetic pilot has no configuration for scenario '{scenario.name}'",
            expected=f"one of {sorted(PILOT_CONFIGS)}; add an entry to "
            "pipeline.pilot.PILOT_CONFIGS or write the demo CSVs by hand",
        ) from None


def start_states(scenario: Scenario, config: PilotConfig) -> FloatArray:
    """Starts on the centres of a ``grid`` over Init's position box, other states at Init's
    midpoint, rounded to mm. -> ``(flights, n)``, row-major over (Y, X)."""
    i, j = scenario.position_index
    lo, hi = scenario.init_lower, scenario.init_upper
    columns, rows = config.grid
    starts = []
    for r in range(rows):
        for c in range(columns):
            x0 = 0.5 * (lo + hi)
            x0[i] = lo[i] + (hi[i] - lo[i]) * (c + 0.5) / columns
            x0[j] = lo[j] + (hi[j] - lo[j]) * (r + 0.5) / rows
            starts.append(np.round(x0, 3))
    return np.array(starts)


def _stick(command: float, step: float, lower: float, upper: float) -> float:
    """The stick position nearest ``command`` on a grid of ``step``, within [lower, upper]."""
    return float(np.clip(step * np.round(command / step), lower, upper)) + 0.0  # no -0.0


def fly(scenario: Scenario, x0: FloatArray, seed: int, low: bool = False) -> FloatArray:
    """Fly from ``x0 (n,)`` until at rest in Goal; returns the held inputs ``u (N, m)``.

    ``low``: cross the hill ``low_drop`` lower than the route says. Raises UserError if the pilot
    crashes into Unsafe or has not landed in Goal after ``max_duration``.
    """
    config = pilot_config(scenario)
    names = (*scenario.state_names, *scenario.input_names)
    roles = dict(config.roles)
    if sorted(roles) != sorted(ROLES) or not set(roles.values()) <= set(names):
        raise UserError(
            f"PILOT_CONFIGS['{scenario.name}'].roles does not fit the scenario",
            found=config.roles,
            expected=f"one name from {list(names)} for each role of {ROLES}",
        )
    index = {role: names.index(name) for role, name in roles.items()}
    ip = list(scenario.position_index)
    iv = [index["velocity_X"], index["velocity_Y"]]
    i_theta, i_omega = index["pitch"], index["pitch_rate"]
    i_thrust = index["thrust"] - scenario.n
    i_pitch = index["pitch_acceleration"] - scenario.n
    m, Ts = scenario.m, scenario.Ts
    lower, upper = scenario.input_lower, scenario.input_upper
    thrust_lo = max(config.thrust_range[0], lower[i_thrust])
    thrust_hi = min(config.thrust_range[1], upper[i_thrust])
    landing = geometry.shrink(scenario.goal, config.goal_margin)

    rng = np.random.default_rng(seed)
    W = np.array(config.waypoints) + rng.normal(
        0.0, config.waypoint_jitter, (len(config.waypoints), 2)
    )
    if low:
        W[config.crossing, 1] -= config.low_drop
    a = config.noise_memory
    noise = np.zeros(2)
    scale = np.array([config.thrust_noise, config.pitch_noise]) * np.sqrt(1.0 - a * a)

    seen = [np.asarray(x0, dtype=np.float64)]  # states at the sample times
    us: list[FloatArray] = []
    target = 0
    for k in range(int(round(config.max_duration / Ts))):
        x = seen[-1]
        if k > 0 and scenario.in_goal(x) and geometry.contains(landing, x[ip]):
            if np.hypot(*x[iv]) < config.stop_speed:
                return np.array(us)
        xo = seen[max(0, k - config.delay)]  # what the pilot has registered so far
        p, v = xo[ip], xo[iv]
        previous = W[target - 1] if target > 0 else seen[0][ip]
        if target < len(W) - 1 and (
            np.hypot(*(W[target] - p)) < config.capture_radius
            or np.dot(p - W[target], W[target] - previous) > 0.0  # flown past it
        ):
            target += 1
        to_target = W[target] - p
        if target == len(W) - 1:
            v_des = config.k_position * to_target  # arrive: slow down near the aim
        else:
            v_des = config.cruise_speed * to_target / max(np.hypot(*to_target), 1e-9)
        speed = np.hypot(*v_des)
        if speed > config.cruise_speed:
            v_des *= config.cruise_speed / speed
        F = config.k_velocity * (v_des - v) + np.array([0.0, config.hover_thrust])
        noise = a * noise + scale * rng.normal(size=2)
        theta_des = np.clip(np.arctan2(-F[0], F[1]) + noise[1], -config.max_tilt, config.max_tilt)
        thrust = np.hypot(*F) + noise[0]
        pitch = config.k_theta * (theta_des - xo[i_theta]) - config.k_omega * xo[i_omega]
        u = np.zeros(m)
        u[i_thrust] = _stick(thrust, config.thrust_step, thrust_lo, thrust_hi)
        u[i_pitch] = _stick(pitch, config.pitch_step, lower[i_pitch], upper[i_pitch])
        step = simulate(scenario.dynamics, x, u[None, :], Ts)
        for name, region in scenario.unsafe.items():
            if geometry.contains(region, scenario.positions(step.dense_xs)).any():
                raise UserError(
                    f"synthetic pilot (seed {seed}) crashed into Unsafe set '{name}' at"
                    f" t = {(k + 1) * Ts:.1f} s, position {np.round(step.final_state[ip], 2)}",
                    expected=f"a safe flight; retune PILOT_CONFIGS['{scenario.name}']",
                )
        us.append(u)
        seen.append(step.final_state)
    raise UserError(
        f"synthetic pilot (seed {seed}) did not come to rest in Goal within"
        f" {config.max_duration:g} s; it is at {np.round(seen[-1][ip], 2)} with velocity"
        f" {np.round(seen[-1][iv], 2)}",
        expected=f"a landing; retune PILOT_CONFIGS['{scenario.name}']",
    )


def demo_header(scenario: Scenario, seed: int, x0: FloatArray, low: bool) -> str:
    """The CSV comment header: says plainly that the flight is synthetic and how to regenerate."""
    return (
        f"SYNTHETIC demonstration of scenario '{scenario.name}': flown by the synthetic pilot\n"
        f"in pipeline/pilot.py (seed {seed}), NOT by a human.\n"
        f"start x0 = {np.asarray(x0).tolist()} ({', '.join(scenario.state_names)})\n"
        + ("This flight crosses the hill low, as a hurried pilot does.\n" if low else "")
        + f"Regenerate all demos with `make demos` (python -m pipeline demos {scenario.name}).\n"
        + f"Row k holds u[k] on [k Ts, (k+1) Ts), Ts = {scenario.Ts:g} s."
    )


def regenerate_demos(scenario_name: str | Path) -> list[Demo]:
    """Fly the pilot from every start, write ``demos/demo_NN.csv`` and the YAML's ``demos:``.

    Only the ``demos:`` block at the end of ``scenario.yaml`` is rewritten; everything above it is
    kept byte for byte. Seeds are the flight numbers, so the files are reproducible.
    """
    path = resolve_scenario_path(scenario_name)
    scenario = load_scenario(path, check_demos=False)
    config = pilot_config(scenario)
    text = path.read_text()
    block = re.search(r"^demos:", text, flags=re.MULTILINE)
    if block is None:
        raise UserError(
            "no 'demos:' block to rewrite",
            file=path,
            expected="a line starting with 'demos:' (the last field of the file)",
        )
    demos, entries = [], []
    for seed, x0 in enumerate(start_states(scenario, config), start=1):
        low = seed in config.low_flights
        us = fly(scenario, x0, seed, low=low)
        file = Path("demos") / f"demo_{seed:02d}.csv"
        demo = Demo(name=file.stem, file=path.parent / file, x0=x0, us=us)
        check_demo_flight(scenario, demo)
        write_demo_csv(
            demo.file, us, scenario.input_names, scenario.Ts, demo_header(scenario, seed, x0, low)
        )
        demos.append(demo)
        values = ", ".join(repr(float(value)) for value in x0)
        entries.append(f"  - {{file: {file.as_posix()}, x0: [{values}]}}\n")
    atomic_write_text(
        path,
        text[: block.start()]
        + "demos:  # SYNTHETIC flights from pipeline/pilot.py, not human; regenerate: make demos\n"
        + "".join(entries),
    )
    load_scenario(path, check_demos=True)
    return demos
