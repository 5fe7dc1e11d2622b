"""A recorded flight, one held input sample at a time: the recorder's logic, without a window.

The person's stick is sampled at ``t = k Ts`` and the sample held on ``[k Ts, (k+1) Ts)``; the
interval is integrated with the pipeline's RK4 (``pipeline.model.simulate.simulate``, same
substeps), so the flight recorded is exactly the flight the pipeline will simulate from the saved
CSV::

    x((k+1) Ts) = RK4(f, x(k Ts), u[k], Ts)

Each sample is first clipped to the input bounds and rounded to the CSV's 6 decimals. A flight
ends as invalid when a substep's position touches Unsafe (the check ``check_demo_flight`` makes),
and as valid at the first sample ``k >= 1`` whose state is in Goal with the position at least
``goal_margin`` inside the Goal polygon.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.io.artifacts import ArtifactError, read_stored
from pipeline.io.errors import UserError
from pipeline.io.folders import default_output_folder
from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import DEFAULT_SUBSTEPS, simulate


class FlightStatus(enum.Enum):
    """Where a flight stands; the value is what the pilot is told."""

    FLYING = "flying"
    REACHED_GOAL = "reached Goal: a valid demonstration"
    HIT_UNSAFE = "touched Unsafe: not saved, try again"
    TIMED_OUT = "did not reach Goal in time: not saved, try again"
    DIVERGED = "the simulation diverged (non-finite state): not saved, try again"

    @property
    def valid(self) -> bool:
        return self is FlightStatus.REACHED_GOAL


def quantize(scenario: Scenario, u: FloatArray) -> FloatArray:
    """``u (m,)`` clipped to the input bounds and rounded as ``write_demo_csv`` writes it."""
    u = np.clip(np.asarray(u, dtype=np.float64), scenario.input_lower, scenario.input_upper)
    return np.array([float(f"{value:.6f}") + 0.0 for value in u])  # + 0.0: no -0.0


@dataclass(frozen=True)
class Flight:
    """A finished (or current) flight.

    Attributes:
      x0: (n,) start; us: (N, m) held inputs; xs: (N+1, n) states at ``k Ts``.
      dense_ts: (N s + 1,) RK4 grid times; dense_xs: (N s + 1, n) states on it.
      end_time: when the flight ended (the first substep in Unsafe when it hit Unsafe).
    """

    x0: FloatArray
    us: FloatArray
    xs: FloatArray
    dense_ts: FloatArray
    dense_xs: FloatArray
    status: FlightStatus
    message: str
    end_time: float


class Recorder:
    """Simulates a flight from ``x0 (n,)`` one input sample at a time: ``step(u) -> status``."""

    def __init__(
        self,
        scenario: Scenario,
        x0: FloatArray,
        goal_margin: float = 0.0,
        max_duration: float = 120.0,
        substeps: int = DEFAULT_SUBSTEPS,
    ) -> None:
        self.scenario = scenario
        self.x0 = check_start(scenario, x0)
        self.landing = geometry.shrink(scenario.goal, goal_margin)
        self.max_samples = int(np.ceil(max_duration / scenario.Ts - 1e-9))
        self.substeps = substeps
        self.us: list[FloatArray] = []
        self.xs: list[FloatArray] = [self.x0]
        self.dense: list[FloatArray] = [self.x0[None, :]]
        self.status = FlightStatus.FLYING
        self.message = "flying"
        self.end_time = 0.0

    @property
    def N(self) -> int:
        """Samples taken so far."""
        return len(self.us)

    @property
    def t(self) -> float:
        """Simulated time: ``N Ts``."""
        return self.N * self.scenario.Ts

    @property
    def x(self) -> FloatArray:
        """(n,) the latest state at a sample time."""
        return self.xs[-1]

    def step(self, u: FloatArray) -> FlightStatus:
        """Hold the sample ``u (m,)`` for one ``Ts``; returns the status after the interval."""
        if self.status is not FlightStatus.FLYING:
            raise RuntimeError(f"the flight has ended ({self.status.name}); start a new Recorder")
        scenario, Ts = self.scenario, self.scenario.Ts
        u = quantize(scenario, u)
        with np.errstate(over="ignore", invalid="ignore"):
            interval = simulate(scenario.dynamics, self.x, u[None, :], Ts, self.substeps)
        k = self.N
        self.us.append(u)
        self.xs.append(interval.final_state)
        self.dense.append(interval.dense_xs[1:])
        self.end_time = (k + 1) * Ts
        h = Ts / self.substeps
        if not np.all(np.isfinite(interval.dense_xs)):
            return self._end(FlightStatus.DIVERGED, f"non-finite state after t = {k * Ts:.2f} s")
        positions = scenario.positions(interval.dense_xs[1:])
        for name, region in scenario.unsafe.items():
            hits = np.flatnonzero(geometry.contains(region, positions))
            if hits.size:
                self.end_time = k * Ts + (hits[0] + 1) * h
                X, Y = positions[hits[0]]
                return self._end(
                    FlightStatus.HIT_UNSAFE,
                    f"touched Unsafe set '{name}' at t = {self.end_time:.2f} s,"
                    f" position ({X:.2f}, {Y:.2f})",
                )
        if self.landed(self.x):
            X, Y = scenario.positions(self.x)
            return self._end(
                FlightStatus.REACHED_GOAL,
                f"reached Goal at t = {self.t:.1f} s, position ({X:.2f}, {Y:.2f})",
            )
        if self.N >= self.max_samples:
            return self._end(FlightStatus.TIMED_OUT, f"still flying after {self.t:.0f} s")
        return self.status

    def landed(self, x: FloatArray) -> bool:
        """Whether state ``x (n,)`` ends a flight as valid (in Goal, ``goal_margin`` inside)."""
        inside = geometry.contains(self.landing, self.scenario.positions(x))
        return bool(self.scenario.in_goal(x) and inside)

    def _end(self, status: FlightStatus, detail: str) -> FlightStatus:
        self.status = status
        self.message = f"{status.value} ({detail})"
        return status

    def state_at(self, t: float) -> FloatArray:
        """(n,) the state at time ``t`` (clipped to the flight so far); for drawing only."""
        return interpolate(self.dense_xs, self.scenario.Ts / self.substeps, min(t, self.end_time))

    @property
    def dense_xs(self) -> FloatArray:
        """(N s + 1, n) the states on the RK4 grid so far."""
        if len(self.dense) > 1:
            self.dense = [np.concatenate(self.dense, axis=0)]
        return self.dense[0]

    def flight(self) -> Flight:
        """The flight so far as a frozen record."""
        m = self.scenario.m
        h = self.scenario.Ts / self.substeps
        dense = self.dense_xs
        return Flight(
            x0=self.x0,
            us=np.array(self.us).reshape(-1, m),
            xs=np.array(self.xs),
            dense_ts=h * np.arange(dense.shape[0], dtype=np.float64),
            dense_xs=dense,
            status=self.status,
            message=self.message,
            end_time=self.end_time,
        )


def interpolate(dense_xs: FloatArray, h: float, t: float) -> FloatArray:
    """(n,) the state at time ``t`` from states ``dense_xs (M, n)`` on a grid of step ``h``,
    linear between grid points and clipped to the grid; for drawing only."""
    s = float(np.clip(t / h, 0.0, dense_xs.shape[0] - 1))
    i = min(int(s), dense_xs.shape[0] - 1)
    j = min(i + 1, dense_xs.shape[0] - 1)
    return dense_xs[i] + (s - i) * (dense_xs[j] - dense_xs[i])


def check_start(scenario: Scenario, x0: FloatArray) -> FloatArray:
    """``x0`` as an ``(n,)`` array, or a UserError if it has the wrong length or is outside Init."""
    x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
    names = scenario.state_names
    if x0.shape != (scenario.n,):
        raise UserError(
            f"start state has {x0.size} values",
            field="--x0",
            expected=f"{scenario.n} values ({', '.join(names)})",
        )
    outside = np.flatnonzero(
        ~np.isfinite(x0) | (x0 < scenario.init_lower - 1e-12) | (x0 > scenario.init_upper + 1e-12)
    )
    if outside.size:
        i = outside[0]
        raise UserError(
            f"start state outside Init in '{names[i]}'",
            field="--x0",
            found=float(x0[i]),
            expected=f"a value in [{scenario.init_lower[i]:g}, {scenario.init_upper[i]:g}]",
        )
    return x0


def suggested_start(
    scenario: Scenario, reports: Path | None = None, registry: Mapping[str, type] | None = None
) -> tuple[FloatArray, str]:
    """Where to start the next flight, and why: the centre of the largest box of Init that the
    last ``synthesize`` run left uncovered (``./reports/NAME/artifacts/coverage_optimized``, read
    with the stage cache's ``registry`` of result types), else the middle of Init.
    -> ``(x0 (n,), reason)``."""
    folder = reports or default_output_folder(scenario.name)
    stem = folder / "artifacts" / "coverage_optimized"
    middle = 0.5 * (scenario.init_lower + scenario.init_upper)
    try:
        stored = read_stored(stem, registry or {})
        gap = None if stored is None else stored.result.largest_gap()
    except (ArtifactError, AttributeError):  # from another version or damaged: only a hint
        stored = None
    if stored is None:
        return middle, "the middle of Init (no coverage result yet)"
    if gap is None:
        return middle, "the middle of Init (the last run covered all of Init)"
    gap = np.asarray(gap, dtype=np.float64)
    if gap.shape != (scenario.n,):
        return middle, "the middle of Init (coverage result does not fit the scenario)"
    start = np.clip(np.round(gap, 3), scenario.init_lower, scenario.init_upper)
    return start, "the largest part of Init the last run left uncovered"
