"""A synthetic pilot: the stand-in for the paper's human with a joystick (§IV-A).

No human is available to this project, so the shipped demonstrations are flown by this model of
one. The pilot flies the same simulator the pipeline uses (``pipeline.model.simulate.simulate``) and
moves the stick once per sample, so the input is piecewise constant, ``u(t) = u[k]`` on
``[k Ts, (k+1) Ts)``. What makes it human-like, and suboptimal:

- **Waypoints.** It steers for a route of waypoints in the position plane at a cruise speed,
  switching to the next waypoint once within ``capture_radius`` of it or past it; at the last one
  it slows down (``k_position``). Some flights (``variant_flights``) move one waypoint by
  ``variant_shift``, the way a hurried pilot cuts a corner.
- **Late reactions.** It acts on the state it saw ``delay`` samples ago.
- **A coarse stick.** Every input is rounded to ``stick_step`` and kept in a comfortable range
  (``stick_range``, clipped to the input bounds).
- **An unsteady hand.** Seeded, slowly varying noise (AR(1), ``numpy.random.default_rng(seed)``)
  with one channel per entry of ``noise``, and per-flight jitter of the waypoints.

Everything vehicle-specific lives with the scenario, in ``scenarios/NAME/pilot.py`` (loaded by
path, so this module never names a scenario's states). That file defines

    CONFIG: PilotConfig                       the route, the hand and where flights start
    steering(scenario) -> Steering            the vehicle's steering law

where a ``Steering`` turns the wanted position velocity ``v_des (2,)`` into raw stick commands
``(m,)`` from the state the pilot has registered, and says how fast the vehicle moves. The
recording stops at the first sample where the vehicle is inside Goal (shrunk by
``goal_margin``) and slower than ``stop_speed``, so the demo's final state is in Goal.
"""

from __future__ import annotations

import importlib.util
import itertools
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import yaml

from pipeline.io.artifacts import atomic_write_text
from pipeline.io.errors import UserError
from pipeline.model import geometry
from pipeline.model.demos import Demo, demo_entry, write_demo_csv
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import (
    Scenario,
    check_demo_flight,
    load_scenario,
    resolve_scenario_path,
)
from pipeline.model.simulate import simulate

PILOT_FILE = "pilot.py"
SYNTHETIC_FILE = re.compile(r"demos/demo_\d+\.csv")  # what the pilot writes


@dataclass(frozen=True, kw_only=True)
class PilotConfig:
    """How the synthetic pilot flies one scenario (positions in m, speeds in m/s, time in s).

    Attributes:
      waypoints: the route in the position plane; the last one is the landing aim.
      stick_step: (m,) stick resolution per input; stick_range: (m,) comfortable
        ``(lower, upper)`` per input, clipped to the input bounds.
      noise: std of the hand's noise per channel (the steering law says what each perturbs).
      grid: ``(state name, cells)`` pairs, slowest first: flights start on the cell centres of
        this grid over Init, other states at Init's midpoint; ``extra_starts`` (n,) follow.

    Fields with a default need not be set (``python -m pipeline new`` writes a pilot with only
    the others and lists these, with their meaning, in a comment).
    """

    waypoints: tuple[tuple[float, float], ...]
    waypoint_jitter: float = 0.1  # std of the per-flight waypoint deviation
    cruise_speed: float
    capture_radius: float = 1.0
    k_position: float = 0.5  # (1/s) approach gain at the last waypoint
    variant_flights: tuple[int, ...] = ()  # flight numbers (1-based) that move one waypoint
    variant_waypoint: int = 0
    variant_shift: tuple[float, float] = (0.0, 0.0)
    variant_note: str = ""  # a line for the CSV header of those flights
    delay: int = 2  # reaction delay (samples)
    noise: tuple[float, ...]
    noise_memory: float = 0.8  # AR(1) coefficient of the noise, in [0, 1)
    stick_step: tuple[float, ...]
    stick_range: tuple[tuple[float, float], ...]
    goal_margin: float = 0.3  # stop only this far inside Goal
    stop_speed: float = 0.5
    max_duration: float = 40.0  # give up after this long
    grid: tuple[tuple[str, int], ...]
    extra_starts: tuple[tuple[float, ...], ...] = ()


class Steering(Protocol):
    """A vehicle's steering law, built by ``scenarios/NAME/pilot.py`` for its scenario."""

    def speed(self, x: FloatArray) -> float:
        """How fast the vehicle at state ``x (n,)`` moves (for the stop rule)."""
        ...

    def __call__(self, x: FloatArray, v_des: FloatArray, noise: FloatArray) -> FloatArray:
        """Raw stick commands ``(m,)`` towards the position velocity ``v_des (2,)`` from the
        registered state ``x (n,)``, perturbed by the hand's ``noise`` (one value per channel)."""
        ...


@dataclass(frozen=True)
class Pilot:
    """A scenario's pilot: its configuration, its steering law and the file they came from."""

    config: PilotConfig
    steering: Callable[[Scenario], Steering]
    source: Path


def load_pilot(scenario: Scenario) -> Pilot:
    """The pilot of ``scenario`` from ``scenarios/NAME/pilot.py``, checked against the scenario;
    a UserError says what is missing."""
    path = scenario.path.parent / PILOT_FILE
    if not path.is_file():
        raise UserError(
            f"the synthetic pilot has no configuration for scenario '{scenario.name}'",
            file=path,
            expected="a file defining CONFIG (pipeline.demonstrations.pilot.PilotConfig) and "
            "steering(scenario) (see scenarios/double_integrator/pilot.py), or write the demo CSVs "
            "by hand",
        )
    name = f"_scenario_pilot_{abs(hash(path.resolve()))}"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses in the file look their module up here
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[name]
    config, steering = getattr(module, "CONFIG", None), getattr(module, "steering", None)
    if not isinstance(config, PilotConfig) or not callable(steering):
        raise UserError(
            "pilot file does not define CONFIG and steering",
            file=path,
            found=f"CONFIG: {type(config).__name__}, steering: {type(steering).__name__}",
            expected="CONFIG = pipeline.demonstrations.pilot.PilotConfig(...) and "
            "def steering(scenario)",
        )
    m, states = scenario.m, scenario.state_names
    problems = [
        f"{field} has {len(value)} entries, expected {m} (one per input)"
        for field, value in (("stick_step", config.stick_step), ("stick_range", config.stick_range))
        if len(value) != m
    ]
    problems += [f"grid names unknown state '{s}'" for s, _ in config.grid if s not in states]
    problems += [
        f"extra start {list(x0)} has {len(x0)} values, expected {scenario.n}"
        for x0 in config.extra_starts
        if len(x0) != scenario.n
    ]
    if config.variant_flights and not 0 <= config.variant_waypoint < len(config.waypoints):
        problems.append(f"variant_waypoint {config.variant_waypoint} is not a waypoint index")
    if problems:
        raise UserError(
            f"CONFIG does not fit scenario '{scenario.name}': {'; '.join(problems)}",
            file=path,
            expected=f"states {list(states)}, inputs {list(scenario.input_names)}",
        )
    return Pilot(config, steering, path)


def start_states(scenario: Scenario, config: PilotConfig) -> FloatArray:
    """Starts on the cell centres of ``config.grid`` over Init (first name slowest), other
    states at Init's midpoint, rounded to 1e-3, then ``config.extra_starts``. -> ``(flights, n)``.
    """
    lo, hi = scenario.init_lower, scenario.init_upper
    index = [scenario.state_names.index(name) for name, _ in config.grid]
    starts = []
    for cells in itertools.product(*(range(count) for _, count in config.grid)):
        x0 = 0.5 * (lo + hi)
        for i, c, (_, count) in zip(index, cells, config.grid, strict=True):
            x0[i] = lo[i] + (hi[i] - lo[i]) * (c + 0.5) / count
        starts.append(np.round(x0, 3))
    starts.extend(np.array(x0, dtype=np.float64) for x0 in config.extra_starts)
    return np.array(starts).reshape(-1, scenario.n)


def _stick(command: float, step: float, lower: float, upper: float) -> float:
    """The stick position nearest ``command`` on a grid of ``step``, within [lower, upper]."""
    return float(np.clip(step * np.round(command / step), lower, upper)) + 0.0  # no -0.0


def fly(
    scenario: Scenario,
    x0: FloatArray,
    seed: int,
    variant: bool = False,
    pilot: Pilot | None = None,
) -> FloatArray:
    """Fly from ``x0 (n,)`` until slower than ``stop_speed`` inside Goal; returns the held inputs
    ``u (N, m)``.

    ``variant``: move waypoint ``variant_waypoint`` by ``variant_shift``; ``pilot``: default
    ``load_pilot(scenario)``. Raises UserError if the pilot crashes into Unsafe or has not
    landed in Goal after ``max_duration``.
    """
    pilot = load_pilot(scenario) if pilot is None else pilot
    config, steer = pilot.config, pilot.steering(scenario)
    ip = list(scenario.position_index)
    Ts = scenario.Ts
    comfortable = np.array(config.stick_range, dtype=np.float64)
    stick_lo = np.maximum(comfortable[:, 0], scenario.input_lower)
    stick_hi = np.minimum(comfortable[:, 1], scenario.input_upper)
    landing = geometry.shrink(scenario.goal, config.goal_margin)

    rng = np.random.default_rng(seed)
    W = np.array(config.waypoints) + rng.normal(
        0.0, config.waypoint_jitter, (len(config.waypoints), 2)
    )
    if variant:
        W[config.variant_waypoint] += config.variant_shift
    a = config.noise_memory
    noise = np.zeros(len(config.noise))
    scale = np.array(config.noise) * np.sqrt(1.0 - a * a)

    seen = [np.asarray(x0, dtype=np.float64)]  # states at the sample times
    us: list[FloatArray] = []
    target = 0
    for k in range(int(round(config.max_duration / Ts))):
        x = seen[-1]
        if k > 0 and scenario.in_goal(x) and geometry.contains(landing, x[ip]):
            if steer.speed(x) < config.stop_speed:
                return np.array(us)
        xo = seen[max(0, k - config.delay)]  # what the pilot has registered so far
        p = xo[ip]
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
        noise = a * noise + scale * rng.normal(size=noise.size)
        command = steer(xo, v_des, noise)
        u = np.array(
            [
                _stick(c, step, lower, upper)
                for c, step, lower, upper in zip(
                    command, config.stick_step, stick_lo, stick_hi, strict=True
                )
            ]
        )
        step = simulate(scenario.dynamics, x, u[None, :], Ts)
        for name, region in scenario.unsafe.items():
            if geometry.contains(region, scenario.positions(step.dense_xs)).any():
                raise UserError(
                    f"synthetic pilot (seed {seed}) crashed into Unsafe set '{name}' at"
                    f" t = {(k + 1) * Ts:.1f} s, position {np.round(step.final_state[ip], 2)}",
                    expected=f"a safe flight; retune {pilot.source}",
                )
        us.append(u)
        seen.append(step.final_state)
    raise UserError(
        f"synthetic pilot (seed {seed}) did not come to rest in Goal within"
        f" {config.max_duration:g} s; it is at {np.round(seen[-1][ip], 2)} moving at"
        f" {steer.speed(seen[-1]):.2f}",
        expected=f"a landing; retune {pilot.source}",
    )


def demo_header(scenario: Scenario, seed: int, x0: FloatArray, note: str) -> str:
    """The CSV comment header: says plainly that the flight is synthetic and how to regenerate."""
    return (
        f"SYNTHETIC demonstration of scenario '{scenario.name}': flown by the synthetic pilot\n"
        f"in pipeline/demonstrations/pilot.py (seed {seed}), NOT by a human.\n"
        f"start x0 = {np.asarray(x0).tolist()} ({', '.join(scenario.state_names)})\n"
        + (f"{note}\n" if note else "")
        + f"Regenerate all demos with `make demos` (python -m pipeline demos {scenario.name}).\n"
        + f"Row k holds u[k] on [k Ts, (k+1) Ts), Ts = {scenario.Ts:g} s."
    )


def _other_demo_entries(block: str) -> list[str]:
    """The entries of a ``demos:`` block that the pilot did not fly (recorded flights), one line
    each: kept verbatim when already one line (with its comment), else re-written in flow style."""
    listed = (yaml.safe_load(block) or {}).get("demos") or []
    lines = block.splitlines(keepends=True)
    kept = []
    for entry in listed:
        file = str(entry["file"])
        if SYNTHETIC_FILE.fullmatch(Path(file).as_posix()):
            continue
        same = [
            line for line in lines if line.lstrip().startswith("- {") and f"file: {file}," in line
        ]
        kept.append(same[0] if len(same) == 1 else f"  - {demo_entry(file, entry['x0'])}\n")
    return [line if line.endswith("\n") else line + "\n" for line in kept]


def regenerate_demos(scenario_name: str | Path) -> list[Demo]:
    """Fly the pilot from every start, write ``demos/demo_NN.csv`` and the YAML's ``demos:``.

    Only the ``demos:`` block at the end of ``scenario.yaml`` is rewritten; everything above it is
    kept byte for byte, and so is every entry of the old block that is not one of the pilot's
    ``demos/demo_NN.csv`` (a recorded flight is never dropped). Seeds are the flight numbers, so
    the files are reproducible.
    """
    path = resolve_scenario_path(scenario_name)
    scenario = load_scenario(path, check_demos=False)
    pilot = load_pilot(scenario)
    config = pilot.config
    text = path.read_text()
    block = re.search(r"^demos:", text, flags=re.MULTILINE)
    if block is None:
        raise UserError(
            "no 'demos:' block to rewrite",
            file=path,
            expected="a line starting with 'demos:' (the last field of the file)",
        )
    after = re.search(r"^[^\s#-]", text[block.end() :], flags=re.MULTILINE)
    if after is not None:  # rewriting the block would drop it
        line = text[: block.end() + after.start()].count("\n") + 1
        found = text[block.end() + after.start() :].split("\n", 1)[0]
        raise UserError(
            f"line {line} follows the 'demos:' block, which make demos rewrites to the end",
            file=path,
            found=found,
            expected="'demos:' as the last field of the file (move the field above it)",
        )
    kept = _other_demo_entries(text[block.start() :])
    demos, entries = [], []
    for seed, x0 in enumerate(start_states(scenario, config), start=1):
        variant = seed in config.variant_flights
        us = fly(scenario, x0, seed, variant=variant, pilot=pilot)
        file = Path("demos") / f"demo_{seed:02d}.csv"
        demo = Demo(name=file.stem, file=path.parent / file, x0=x0, us=us)
        check_demo_flight(scenario, demo)
        header = demo_header(scenario, seed, x0, config.variant_note if variant else "")
        write_demo_csv(demo.file, us, scenario.input_names, scenario.Ts, header)
        demos.append(demo)
        entries.append(f"  - {demo_entry(file.as_posix(), x0)}\n")
    atomic_write_text(
        path,
        text[: block.start()]
        + "demos:  # SYNTHETIC flights from pipeline/demonstrations/pilot.py, not human; "
        "regenerate: make demos\n" + "".join(entries + kept),
    )
    load_scenario(path, check_demos=True)
    return demos


def describe_demos(demos: list[Demo], Ts: float, path: Path) -> str:
    """One line for ``regenerate_demos``'s result, e.g. ``wrote demo_01..04 (T 10.3-10.8 s, all
    valid); updated scenario.yaml demos: in scenarios/NAME`` (``path``: the scenario's YAML)."""
    updated = f"updated {path.name} demos: in {_shown(path.parent)}"
    if not demos:
        return f"wrote no demos (the pilot's grid has no cells); {updated}"
    last = demos[-1].name.removeprefix("demo_")
    names = demos[0].name if len(demos) == 1 else f"{demos[0].name}..{last}"
    T = [len(demo.us) * Ts for demo in demos]
    span = f"{min(T):.1f}" if len(demos) == 1 else f"{min(T):.1f}-{max(T):.1f}"
    return f"wrote {names} (T {span} s, all valid); {updated}"


def _shown(folder: Path) -> str:
    """``folder`` relative to the current directory when inside it, else absolute."""
    folder = folder.resolve()
    try:
        return str(folder.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(folder)
