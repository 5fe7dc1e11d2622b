"""Closed-loop simulation of the emitted controller: ``xdot = f(x, controller(t, x))``.

The feedback acts in continuous time, so the controller is evaluated at every RK4 stage. Its
reference input is piecewise constant, so each sample interval is integrated on its own and the
stage at an interval's right end uses the left limit of the input. A file with
``feedback_period h > 0`` is flown with the law it certifies: ``u`` computed from the state at
``t_k = k h`` and held on ``[t_k, t_k + h)`` (``held_steps``: RK4 steps aligned with the windows).

``check_runs`` measures each run's margins in continuous time (dense grid plus the motion bound
between grid points): clearance to Unsafe, Goal at ``T``, input slack before clipping, and the
error against the predicted tube ``||e(t)||_P(t) <= e^{-lambda t} ||e(0)||_P(0) + 2 delta``
(``P(t) = P`` for a ``/1`` file; a funnel's time-varying metric, its own ``lambda``, for ``/2``),
and the margin to the scenario's ``state_bounds`` on the grid less half the longest step of a
bounded state. ``draws`` (``pipeline.numerics.closed_loop.gusts``) fly each run with its own
uncertain parameters and gusts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.controller import Controller
from pipeline.model import geometry
from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.closed_loop.gusts import Draws, flown_dynamics

LEFT_LIMIT = 1e-9
TUBE_TOLERANCE = 1e-6
INTERPOLATION_SLACK = 2.0  # the reference is interpolated: allow twice its stated error


@dataclass(frozen=True, kw_only=True)
class ClosedLoopRun:
    """Closed-loop runs of one batch around one reference trajectory.

    Attributes:
      ts: (K+1,) dense times; xs: (B, K+1, n) states; x_ref: (K+1, n) the reference there.
      unclipped: (B, K, 4, m) the controller's output before clipping at every RK4 stage.
    """

    ts: FloatArray
    xs: FloatArray
    x_ref: FloatArray
    unclipped: FloatArray


def held_steps(controller: Controller, substeps: int) -> tuple[int, int]:
    """``(RK4 steps per sample interval, steps per held window)`` for at least ``substeps``
    steps per sample; the window is 0 for continuous feedback (``feedback_period == 0``)."""
    if controller.feedback_period == 0:
        return substeps, 0
    windows = round(controller.Ts / controller.feedback_period)
    per_window = max(1, -(-substeps // windows))
    return windows * per_window, per_window


def simulate_closed_loop(
    dynamics: Dynamics,
    controller: Controller,
    x0: FloatArray,
    trajectory: int,
    substeps: int = 4,
    disturbance: FloatArray | None = None,
    noise: FloatArray | None = None,
    hold: int = 0,
    draws: Draws | None = None,
) -> ClosedLoopRun:
    """Run the batch ``x0 (B, n)`` around trajectory number ``trajectory`` until its end ``T``.

    ``hold > 0``: the input is computed every ``hold`` RK4 steps (at the window's first stage)
    and held in between (zero-order-hold feedback); 0: at every stage.

    Stress tests only: ``disturbance (B, n)`` is added to ``xdot``; ``noise (B, K, n)`` is added
    to the state the controller measures on RK4 step ``j`` (``K = N * substeps``).

    ``draws``: each run's parameters (appended to the input: ``dynamics`` is then the
    parametric ``f(x, (u, p))``) and the gust in force at each RK4 step's start, added to
    ``xdot``.
    """
    x = np.array(x0, dtype=np.float64)
    B = x.shape[0]
    index = np.full(B, trajectory)
    reference = controller.trajectories[trajectory]
    N = len(reference.u_ref)
    h = controller.Ts / substeps
    K = N * substeps
    xs = np.empty((B, K + 1, x.shape[1]))
    unclipped = np.empty((B, K, 4, len(controller.input_names)))
    xs[:, 0] = x
    extra = 0.0 if disturbance is None else disturbance

    held = np.empty((B, len(controller.input_names)))

    def field(t: float, state: FloatArray, j: int, stage: int) -> FloatArray:
        if hold and (stage > 0 or j % hold):
            raw = held
        else:
            seen = state if noise is None else state + noise[:, j]
            if draws is not None:  # the measurement error in force at the step's start
                seen = seen + draws.error(j * h)
            raw = controller.unclipped(t, seen, index)
            held[:] = raw
        unclipped[:, j, stage] = raw
        u = np.clip(raw, controller.lower, controller.upper)
        if draws is not None and draws.parameters.shape[1]:
            u = np.concatenate([u, draws.parameters], axis=1)
        return dynamics.f(state, u) + extra

    for j in range(K):
        t = j * h
        if draws is not None:
            extra = draws.gust(t) + (0.0 if disturbance is None else disturbance)
        t_end = (j + 1) * h - (LEFT_LIMIT if (j + 1) % substeps == 0 else 0.0)
        k1 = field(t, x, j, 0)
        k2 = field(t + h / 2, x + h / 2 * k1, j, 1)
        k3 = field(t + h / 2, x + h / 2 * k2, j, 2)
        k4 = field(t_end, x + h * k3, j, 3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        xs[:, j + 1] = x
    ts = h * np.arange(K + 1, dtype=np.float64)
    x_ref = np.stack(
        [np.interp(ts, reference.t, reference.x_ref[:, i]) for i in range(x.shape[1])], axis=-1
    )
    return ClosedLoopRun(ts=ts, xs=xs, x_ref=x_ref, unclipped=unclipped)


@dataclass(frozen=True, kw_only=True)
class RunChecks:
    """Per-run margins for a batch ``(B,)``; a run fails when any margin is negative."""

    clearance: FloatArray
    goal_margin: FloatArray
    input_slack: FloatArray
    tube_tightness: FloatArray
    tube_final: FloatArray
    finite: np.ndarray
    covered: np.ndarray
    bounds_margin: FloatArray | None = None  # to the state bounds (inf without them)
    final_state: FloatArray  # (B, n): each run's state at its T

    def margin(self) -> FloatArray:
        """The smallest safety margin of each run (negative: unsafe, misses Goal or clips the
        input), for falsification. The tube check is a failure kind but not a margin: its
        ratio is 1 at ``t = 0`` by definition."""
        worst = np.minimum.reduce([self.clearance, self.goal_margin, self.input_slack])
        return np.where(self.finite & self.covered, worst, -np.inf)

    def binding(self) -> list[str]:
        """Which margin is the smallest in each run, with its unit."""
        parts = np.stack([self.clearance, self.goal_margin, self.input_slack])
        names = ("clearance to Unsafe, m", "Goal margin, m", "input slack, input units")
        return [
            names[k] if f and c else ("not covered" if not c else "non-finite state")
            for k, f, c in zip(np.argmin(parts, axis=0), self.finite, self.covered, strict=True)
        ]

    def _bounds(self) -> FloatArray:
        return (
            np.full(len(self.finite), np.inf) if self.bounds_margin is None else self.bounds_margin
        )

    def failures(self) -> dict[str, np.ndarray]:
        """Failure masks ``(B,)`` by kind."""
        ok = self.finite
        return {
            "unsafe": ok & (self.clearance <= 0),
            "goal": ok & (self.goal_margin < 0),
            "clipping": ok & (self.input_slack < 0),
            "tube": ok & (self.tube_tightness > 1 + TUBE_TOLERANCE),
            "non_finite": ~ok,
            "uncovered": ~self.covered,
            "bounds": ok & (self._bounds() < 0),
        }


def check_runs(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    substeps: int = 4,
    disturbance: FloatArray | None = None,
    noise_std: FloatArray | None = None,
    rng: np.random.Generator | None = None,
    draws: Draws | None = None,
) -> tuple[RunChecks, list[FloatArray]]:
    """Simulate the closed loop from ``x0 (B, n)`` and measure every run's margins.

    ``disturbance (B, n)`` and measurement noise of standard deviation ``noise_std (n,)`` (drawn
    from ``rng``) are for stress tests only. Returns the checks and, per reference trajectory
    used, the runs' positions ``(b, K+1, 2)``.
    """
    B = len(x0)
    substeps, hold = held_steps(controller, substeps)
    names = ("clearance", "goal_margin", "input_slack", "tube", "tube_final", "bounds")
    checks = {name: np.empty(B) for name in names}
    final_state = np.empty((B, len(x0[0])))
    finite = np.ones(B, dtype=bool)
    index, ratio = controller.select(x0)
    covered = ratio < 1.0
    paths = []
    for i in np.unique(index):
        rows = np.flatnonzero(index == i)
        steps = len(controller.trajectories[int(i)].u_ref) * substeps
        noise = None
        if noise_std is not None:
            generator = rng if rng is not None else np.random.default_rng(0)
            noise = generator.normal(size=(len(rows), steps, len(x0[0]))) * noise_std
        run = simulate_closed_loop(
            flown_dynamics(scenario, draws),
            controller,
            x0[rows],
            int(i),
            substeps,
            disturbance=None if disturbance is None else disturbance[rows],
            noise=noise,
            hold=hold,
            draws=None if draws is None else draws.rows(rows),
        )
        xs = run.xs
        final_state[rows] = xs[:, -1]
        checks["bounds"][rows] = _bounds_margin(scenario, xs)
        finite[rows] = np.all(np.isfinite(xs), axis=(1, 2))
        positions = scenario.positions(np.nan_to_num(xs, nan=1e9, posinf=1e9, neginf=-1e9))
        step = np.linalg.norm(np.diff(positions, axis=1), axis=-1).max(axis=1)  # (b,)
        # between grid points a run is within (step / 2) of a grid point (RK4 substeps are short)
        distances = np.min(
            [geometry.distance(positions, u) for u in scenario.unsafe.values()], axis=0
        )
        checks["clearance"][rows] = distances.min(axis=1) - step / 2
        inside = scenario.in_goal(xs[:, -1])
        to_edge = geometry.boundary_distance(positions[:, -1], scenario.goal)
        checks["goal_margin"][rows] = np.where(inside, to_edge, -to_edge)
        raw = run.unclipped
        slack = np.minimum(raw - controller.lower, controller.upper - raw)
        checks["input_slack"][rows] = slack.min(axis=(1, 2, 3))
        e = xs - run.x_ref
        reference = controller.trajectories[int(i)]
        P = reference.metric(run.ts, controller.Ts)  # (K+1, n, n): P(t) on the grid
        norm = np.sqrt(np.einsum("btj,tjk,btk->bt", e, P, e))
        # the reference is interpolated: allow twice its stated error (P-norm) on top of the tube
        slack = INTERPOLATION_SLACK * controller.interpolation_error + 1e-9
        decayed = np.maximum(norm - slack, 0.0) * np.exp(reference.rate * run.ts)
        ratio = decayed / np.maximum(norm[:, :1], 1e-12)
        checks["tube"][rows] = np.max(ratio, axis=1)
        checks["tube_final"][rows] = ratio[:, -1]
        paths.append(positions)
    result = RunChecks(
        clearance=checks["clearance"],
        goal_margin=checks["goal_margin"],
        input_slack=checks["input_slack"],
        tube_tightness=checks["tube"],
        tube_final=checks["tube_final"],
        finite=finite,
        covered=covered,
        bounds_margin=checks["bounds"],
        final_state=final_state,
    )
    return result, paths


def _bounds_margin(scenario: Scenario, xs: FloatArray) -> FloatArray:
    """(B,) the smallest margin of ``xs (B, K+1, n)`` to the state bounds on the grid, less half
    the longest step of a bounded state (inf without state bounds)."""
    if not scenario.state_bounds:
        return np.full(len(xs), np.inf)
    index = [scenario.state_names.index(name) for name in scenario.state_bounds]
    lower = np.array([lo for lo, _ in scenario.state_bounds.values()])
    upper = np.array([hi for _, hi in scenario.state_bounds.values()])
    bounded = xs[..., index]
    margin = np.minimum(bounded - lower, upper - bounded).min(axis=(1, 2))
    return margin - np.abs(np.diff(bounded, axis=1)).max(axis=(1, 2), initial=0.0) / 2


@dataclass(frozen=True, kw_only=True)
class HoldChecks:
    """Runs continued past ``T`` under the terminal law, per run ``(B,)``.

    Attributes:
      final_goal_margin: signed distance of the final position to Goal's boundary (negative:
        outside Goal or its extra bounds); level_ratio: ``max_t V(x(t)) / level`` (<= 1: stayed
        in the certified ellipsoid, which lies in Goal); input_slack: as in ``RunChecks``;
        clearance: to Unsafe over the continuation, less half the longest step; final_state:
        ``(B, n)``; path_goal_margin: the smallest signed Goal margin over the grid less half
        the longest step; bounds_margin: to the state bounds as in ``RunChecks``.
    """

    final_goal_margin: FloatArray
    level_ratio: FloatArray
    input_slack: FloatArray
    clearance: FloatArray
    final_state: FloatArray
    path_goal_margin: FloatArray
    bounds_margin: FloatArray

    def failures(self, ellipsoid: bool = True) -> np.ndarray:
        """``(B,)`` True where a continued run left Goal (at any time), clipped, came near
        Unsafe or left the state bounds, or (``ellipsoid``) left the terminal ellipsoid."""
        return (
            (self.final_goal_margin < 0)
            | (self.path_goal_margin < 0)
            | (ellipsoid & (self.level_ratio > 1 + TUBE_TOLERANCE))
            | (self.input_slack < 0)
            | (self.clearance <= 0)
            | (self.bounds_margin < 0)
        )


def continue_runs(
    scenario: Scenario,
    controller: Controller,
    x_end: FloatArray,
    index: np.ndarray,
    duration: float = 10.0,
    substeps: int = 4,
    draws: Draws | None = None,
) -> HoldChecks:
    """Continue runs that reached their ``T_i`` in ``x_end (B, n)`` (trajectories ``index
    (B,)``) for ``duration`` seconds under the law after ``T`` (``controller(t, x, index)``,
    the terminal controller), by RK4 with about ``substeps`` steps per ``Ts`` (held every
    ``feedback_period`` when the file says so); with ``draws`` (their times from 0 at the
    runs' start), each run's parameters and its gusts from ``T_i`` on."""
    terminal = controller.terminal
    if terminal is None:
        raise ValueError("continue_runs: the controller has no terminal law to continue with")
    x = np.array(x_end, dtype=np.float64)
    T = controller.horizons(index)  # (B,)
    substeps, hold = held_steps(controller, substeps)
    h = controller.Ts / substeps
    steps = int(np.ceil(duration / h))
    level = np.asarray(terminal.value(x)) / terminal.level
    slack = np.full(len(x), np.inf)
    states = [x]
    dynamics = flown_dynamics(scenario, draws)
    later = None if draws is None else draws.started(T)
    gust: FloatArray | float = 0.0
    eta: FloatArray | float = 0.0

    u = np.empty((len(x), len(controller.input_names)))

    def field(t: float, state: FloatArray, fresh: bool) -> FloatArray:
        nonlocal slack
        if fresh:
            seen = state + eta  # the state the law sees
            raw = terminal.unclipped(seen)
            slack = np.minimum(
                slack, np.min(np.minimum(raw - controller.lower, controller.upper - raw), axis=-1)
            )
            u[:] = controller(float(T.max()) + t + h, seen, index)
        if later is None or not later.parameters.shape[1]:
            return dynamics.f(state, u) + gust
        return dynamics.f(state, np.concatenate([u, later.parameters], axis=1)) + gust

    for j in range(steps):
        t = j * h
        if later is not None:
            gust, eta = later.gust(t), later.error(t)
        k1 = field(t, x, not hold or j % hold == 0)
        k2 = field(t + h / 2, x + h / 2 * k1, not hold)
        k3 = field(t + h / 2, x + h / 2 * k2, not hold)
        k4 = field(t + h, x + h * k3, not hold)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        states.append(x)
        level = np.maximum(level, terminal.value(x) / terminal.level)
    xs = np.stack(states, axis=1)  # (B, steps + 1, n)
    positions = scenario.positions(xs)
    step = np.linalg.norm(np.diff(positions, axis=1), axis=-1).max(axis=1)
    inside = scenario.in_goal(xs)  # (B, steps + 1), with Goal's extra bounds
    to_edge = geometry.boundary_distance(positions, scenario.goal)
    signed = np.where(inside, to_edge, -to_edge)
    distances = np.min([geometry.distance(positions, u) for u in scenario.unsafe.values()], axis=0)
    return HoldChecks(
        final_goal_margin=signed[:, -1],
        level_ratio=level,
        input_slack=slack,
        clearance=distances.min(axis=1) - step / 2,
        final_state=xs[:, -1],
        path_goal_margin=signed.min(axis=1) - step / 2,
        bounds_margin=_bounds_margin(scenario, xs),
    )


def hold_runs(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    duration: float = 10.0,
    draws: Draws | None = None,
) -> HoldChecks:
    """Fly ``x0 (B, n)`` to their ``T`` with the oracle, then ``duration`` s more past it (with
    ``draws``: their parameters and gusts throughout)."""
    index, _ = controller.select(x0)
    x_end = np.empty_like(np.asarray(x0, dtype=np.float64))
    for i in np.unique(index):
        rows = np.flatnonzero(index == i)
        substeps, hold = held_steps(controller, 4)
        run = simulate_closed_loop(
            flown_dynamics(scenario, draws),
            controller,
            x0[rows],
            int(i),
            substeps,
            hold=hold,
            draws=None if draws is None else draws.rows(rows),
        )
        x_end[rows] = run.xs[:, -1]
    return continue_runs(scenario, controller, x_end, index, duration, draws=draws)
