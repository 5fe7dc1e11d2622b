"""Closed-loop checks on the compiled kernel: the same margins as ``check_runs``, nothing stored.

``check_runs_compiled`` gives, for a batch of initial states, exactly the ``RunChecks`` of the
NumPy oracle ``pipeline.numerics.closed_loop.simulate.check_runs`` (same integration, same law, same
continuous-time checks; see ``pipeline.numerics.kernels.rollout``), without materialising the
``(runs, steps, n)`` paths: memory stays ``O(runs)`` and a rollout costs one pass of scalar code.
``hold_runs_compiled`` continues the runs past ``T`` under the terminal law, as ``hold_runs``;
``run_paths_compiled`` gives the position paths of a few runs (the report draws them), as the
oracle's ``check_runs`` does. Each takes optional ``draws``
(``pipeline.numerics.closed_loop.gusts``): every run flown with its own uncertain parameters and
gusts, as the oracle does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.controller import Controller
from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.closed_loop.gusts import Draws, flown_dynamics
from pipeline.numerics.closed_loop.simulate import (
    INTERPOLATION_SLACK,
    HoldChecks,
    RunChecks,
    held_steps,
)
from pipeline.numerics.kernels.compiled import (
    load_kernels,
    ring_arrays,
    rings,
    unsafe_ring_arrays,
)
from pipeline.numerics.optimize.penalties import IntArray

HOLD_SECONDS = 10.0  # a run with a law past T is flown to T + this


@dataclass(frozen=True, kw_only=True)
class SceneArrays:
    """Unsafe and Goal as vertex rings for the kernel (see ``pipeline.numerics.kernels.loops``).

    Attributes:
      position: (2,) position state indices.
      unsafe_vertices: (v, 2); unsafe_ring_start: (rings + 1,); unsafe_set_rings: (sets + 1,);
        unsafe_boxes: (sets, 4) bounding boxes (xmin, ymin, xmax, ymax).
      goal_vertices: (w, 2); goal_ring_start: (goal rings + 1,).
      goal_index, goal_lower, goal_upper: (g,) Goal's extra bounds on states at ``T``.
      bound_index, bound_lower, bound_upper: (c,) the state bounds.
    """

    position: IntArray
    unsafe_vertices: FloatArray
    unsafe_ring_start: IntArray
    unsafe_set_rings: IntArray
    unsafe_boxes: FloatArray
    goal_vertices: FloatArray
    goal_ring_start: IntArray
    goal_index: IntArray
    goal_lower: FloatArray
    goal_upper: FloatArray
    bound_index: IntArray
    bound_lower: FloatArray
    bound_upper: FloatArray

    @classmethod
    def of(cls, scenario: Scenario) -> SceneArrays:
        vertices, start, set_rings, boxes = unsafe_ring_arrays(list(scenario.unsafe.values()))
        goal_vertices, goal_start = ring_arrays(rings(scenario.goal))
        names = list(scenario.goal_bounds)
        return cls(
            position=np.array(scenario.position_index, dtype=np.int64),
            unsafe_vertices=vertices,
            unsafe_ring_start=start,
            unsafe_set_rings=set_rings,
            unsafe_boxes=boxes,
            goal_vertices=goal_vertices,
            goal_ring_start=goal_start,
            goal_index=np.array([scenario.state_names.index(k) for k in names], dtype=np.int64),
            goal_lower=np.array([scenario.goal_bounds[k][0] for k in names], dtype=np.float64),
            goal_upper=np.array([scenario.goal_bounds[k][1] for k in names], dtype=np.float64),
            bound_index=np.array(
                [scenario.state_names.index(k) for k in scenario.state_bounds], dtype=np.int64
            ),
            bound_lower=np.array([lo for lo, _ in scenario.state_bounds.values()], dtype=float),
            bound_upper=np.array([hi for _, hi in scenario.state_bounds.values()], dtype=float),
        )

    @property
    def unsafe(self) -> tuple[FloatArray, IntArray, IntArray, FloatArray]:
        """``(vertices, ring_start, set_rings, boxes)``: the kernels' ``scene`` of Unsafe
        (``pipeline.numerics.kernels.shared.unsafe_distance``)."""
        return (
            self.unsafe_vertices,
            self.unsafe_ring_start,
            self.unsafe_set_rings,
            self.unsafe_boxes,
        )


def check_runs_compiled(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    substeps: int = 4,
    draws: Draws | None = None,
) -> RunChecks:
    """The margins of every closed-loop run from ``x0 (B, n)``, as ``check_runs`` computes them."""
    kernels, out, _ = _rollouts(scenario, controller, x0, substeps, draws=draws)
    return _checks(kernels, out, controller.select(x0)[1] < 1.0)


def run_paths_compiled(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    substeps: int = 4,
    draws: Draws | None = None,
) -> list[FloatArray]:
    """The position path ``(K + 1, 2)`` of each run from ``x0 (B, n)`` on the RK4 grid (``K``
    steps of its trajectory), in the order of ``x0``; as in ``check_runs``, a state that is not
    finite is drawn at +-1e9."""
    _, _, paths = _rollouts(scenario, controller, x0, substeps, record=True, draws=draws)
    return [np.nan_to_num(path, nan=1e9, posinf=1e9, neginf=-1e9) for path in paths]


def hold_runs_compiled(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    duration: float = 10.0,
    substeps: int = 4,
    draws: Draws | None = None,
    ends: FloatArray | None = None,
) -> HoldChecks:
    """``hold_runs`` on the kernel: fly ``x0 (B, n)`` to their ``T``, then ``duration`` s more
    under the terminal law ``u_eq + K_T (x - x_eq)``, which is the kernel's law around the
    constant reference ``x_eq`` with inputs ``u_eq`` (metric ``P_T / level``, rate 0: the tube
    ratio times the start's norm is ``max_t sqrt(V / level)``); the Goal margin is the smallest
    over the continuation (``every_goal``); ``draws`` continue from each run's ``T_i``.

    ``ends (B, n)``: the runs' states at their ``T`` when they were flown there already
    (``RunChecks.final_state`` of ``check_runs_compiled`` with the same ``substeps`` and
    ``draws``); the flight to ``T`` is then not repeated."""
    terminal = controller.terminal
    if terminal is None:
        raise ValueError("hold_runs_compiled: the controller has no terminal law")
    kernels = load_kernels(flown_dynamics(scenario, draws))
    if ends is None:
        ends = _rollouts(scenario, controller, x0, substeps, draws=draws)[1][:, kernels.CHECKS :]
    if np.shape(ends) != np.shape(x0):
        raise ValueError(f"hold_runs_compiled: ends {np.shape(ends)} for x0 {np.shape(x0)}")
    x_end = np.ascontiguousarray(ends, dtype=np.float64)
    T = controller.horizons(controller.select(x0)[0])
    later = Draws.none(len(x0), x_end.shape[1]) if draws is None else draws

    N = int(round(duration / controller.Ts))
    law = (
        controller.Ts,
        _read_only(np.tile(terminal.u_eq, (N, 1))),
        _read_only(np.broadcast_to(terminal.K, (N, *terminal.K.shape))),
        _read_only(controller.lower),
        _read_only(controller.upper),
    )
    steps, hold = held_steps(controller, substeps)
    metric = np.broadcast_to(terminal.P / terminal.level, (N * steps + 1, *terminal.P.shape))
    after = np.empty((len(x_end), kernels.CHECKS + x_end.shape[1]))
    kernels.rollout_kernel(
        x_end,
        steps,
        hold,
        law,
        _read_only(np.array([0.0, N * controller.Ts])),
        _read_only(np.stack([terminal.x_eq, terminal.x_eq])),
        np.ascontiguousarray(metric),
        0.0,
        0.0,
        *_scene(scenario),
        _draws(later.started(T)),
        True,
        after,
        np.empty((0, 1, 2)),
    )
    start = np.maximum(np.sqrt(terminal.value(x_end) / terminal.level), 1e-12)
    final = after[:, kernels.CHECKS :]
    to_edge = geometry.boundary_distance(scenario.positions(final), scenario.goal)
    return HoldChecks(
        final_goal_margin=np.where(scenario.in_goal(final), to_edge, -to_edge),
        level_ratio=(after[:, kernels.TUBE] * start) ** 2,
        input_slack=after[:, kernels.SLACK],
        clearance=after[:, kernels.CLEARANCE],
        final_state=final,
        path_goal_margin=after[:, kernels.GOAL],
        bounds_margin=after[:, kernels.BOUNDS],
    )


def _read_only(a: np.ndarray) -> FloatArray:
    """``a`` as a C-contiguous read-only float64 view (copied only when it is not contiguous
    float64). numba compiles a kernel apart for read-only and writable arrays: the controller's
    arrays are one or the other by file format, and each mix compiled the rollout kernel again
    (~3.6 s each); the kernel only reads them."""
    view = np.ascontiguousarray(a, dtype=np.float64).view()
    view.flags.writeable = False
    return view


def _draws(draws: Draws) -> tuple:
    """The ``draws`` argument of the kernel."""
    return (
        _read_only(draws.parameters),
        _read_only(draws.gusts),
        _read_only(draws.start),
        float(draws.period),
        _read_only(
            np.zeros((len(draws.start), 0, draws.gusts.shape[2]))
            if draws.errors is None
            else draws.errors
        ),
    )


def _scene(scenario: Scenario) -> tuple:
    """``(position, unsafe, goal, bounds)`` arguments of the kernel."""
    scene = SceneArrays.of(scenario)
    return (
        scene.position,
        scene.unsafe,
        (
            scene.goal_vertices,
            scene.goal_ring_start,
            scene.goal_index,
            scene.goal_lower,
            scene.goal_upper,
        ),
        (scene.bound_index, scene.bound_lower, scene.bound_upper),
    )


def _rollouts(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    substeps: int,
    record: bool = False,
    draws: Draws | None = None,
) -> tuple[Any, FloatArray, list[FloatArray]]:
    """``(kernels, out (B, CHECKS + n), paths)``: each run's checks and final state, and with
    ``record`` each run's positions ``(K + 1, 2)`` on the RK4 grid (else no paths)."""
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    substeps, hold = held_steps(controller, substeps)
    kernels = load_kernels(flown_dynamics(scenario, draws))
    out = np.empty((len(x0), kernels.CHECKS + x0.shape[1]))
    slack = INTERPOLATION_SLACK * controller.interpolation_error
    index, _ = controller.select(x0)
    paths: list[FloatArray] = [np.empty((0, 2))] * (len(x0) if record else 0)
    for i in np.unique(index):
        rows = np.flatnonzero(index == i)
        reference = controller.trajectories[int(i)]
        grid = controller.Ts / substeps * np.arange(len(reference.u_ref) * substeps + 1)
        checks = np.empty((len(rows), out.shape[1]))
        recorded = np.empty((len(rows) if record else 0, len(grid), 2))
        law = (
            controller.Ts,
            _read_only(reference.u_ref),
            _read_only(reference.K),  # (N, m, n): K[k] on sample interval k
            _read_only(controller.lower),
            _read_only(controller.upper),
        )
        kernels.rollout_kernel(
            np.ascontiguousarray(x0[rows]),
            substeps,
            hold,
            law,
            _read_only(reference.t),
            _read_only(reference.x_ref),
            np.ascontiguousarray(reference.metric(grid, controller.Ts)),  # P(t) on the RK4 grid
            reference.rate,
            slack + 1e-9,
            *_scene(scenario),
            _draws(Draws.none(len(rows), x0.shape[1]) if draws is None else draws.rows(rows)),
            False,
            checks,
            recorded,
        )
        out[rows] = checks
        for row, path in zip(rows[: len(recorded)], recorded, strict=True):
            paths[row] = path
    return kernels, out, paths


def _checks(kernels: Any, out: FloatArray, covered: np.ndarray) -> RunChecks:
    return RunChecks(
        clearance=out[:, kernels.CLEARANCE],
        goal_margin=out[:, kernels.GOAL],
        input_slack=out[:, kernels.SLACK],
        tube_tightness=out[:, kernels.TUBE],
        tube_final=out[:, kernels.TUBE_FINAL],
        finite=out[:, kernels.FINITE] > 0.5,
        covered=covered,
        bounds_margin=out[:, kernels.BOUNDS],
        final_state=out[:, kernels.CHECKS :],
    )
