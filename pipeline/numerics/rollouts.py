"""Closed-loop checks on the compiled kernel: the same margins as ``check_runs``, nothing stored.

``check_runs_compiled`` gives, for a batch of initial states, exactly the ``RunChecks`` of the
NumPy oracle ``pipeline.numerics.closed_loop.check_runs`` (same integration, same law, same
continuous-time checks; see ``pipeline.numerics.kernels.rollout``), without materialising the
``(runs, steps, n)`` paths: memory stays ``O(runs)`` and a rollout costs one pass of scalar code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.controller import Controller
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.closed_loop import INTERPOLATION_SLACK, RunChecks
from pipeline.numerics.kernels.compiled import load_kernels, ring_arrays, rings
from pipeline.numerics.penalties import IntArray


@dataclass(frozen=True, kw_only=True)
class SceneArrays:
    """Unsafe and Goal as vertex rings for the kernel (see ``pipeline.numerics.kernels.loops``).

    Attributes:
      position: (2,) position state indices.
      unsafe_vertices: (v, 2); unsafe_ring_start: (rings + 1,); unsafe_set_rings: (sets + 1,);
        unsafe_boxes: (sets, 4) bounding boxes (xmin, ymin, xmax, ymax).
      goal_vertices: (w, 2); goal_ring_start: (goal rings + 1,).
      goal_index, goal_lower, goal_upper: (g,) Goal's extra bounds on states at ``T``.
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

    @classmethod
    def of(cls, scenario: Scenario) -> SceneArrays:
        unsafe: list[FloatArray] = []
        set_rings = [0]
        for region in scenario.unsafe.values():
            unsafe += rings(region)
            set_rings.append(set_rings[-1] + len(rings(region)))
        vertices, start = ring_arrays(unsafe) if unsafe else (np.zeros((0, 2)), np.zeros(1))
        goal_vertices, goal_start = ring_arrays(rings(scenario.goal))
        names = list(scenario.goal_bounds)
        return cls(
            position=np.array(scenario.position_index, dtype=np.int64),
            unsafe_vertices=vertices,
            unsafe_ring_start=start.astype(np.int64),
            unsafe_set_rings=np.array(set_rings, dtype=np.int64),
            unsafe_boxes=np.array(
                [region.bounds for region in scenario.unsafe.values()], dtype=np.float64
            ).reshape(-1, 4),
            goal_vertices=goal_vertices,
            goal_ring_start=goal_start,
            goal_index=np.array([scenario.state_names.index(k) for k in names], dtype=np.int64),
            goal_lower=np.array([scenario.goal_bounds[k][0] for k in names], dtype=np.float64),
            goal_upper=np.array([scenario.goal_bounds[k][1] for k in names], dtype=np.float64),
        )


def check_runs_compiled(
    scenario: Scenario, controller: Controller, x0: FloatArray, substeps: int = 4
) -> RunChecks:
    """The margins of every closed-loop run from ``x0 (B, n)``, as ``check_runs`` computes them."""
    x0 = np.ascontiguousarray(x0, dtype=np.float64)
    kernels = load_kernels(scenario.dynamics)
    scene = SceneArrays.of(scenario)
    out = np.empty((len(x0), kernels.CHECKS))
    index, ratio = controller.select(x0)
    covered = ratio < 1.0
    slack = INTERPOLATION_SLACK * controller.interpolation_error
    for i in np.unique(index):
        rows = np.flatnonzero(index == i)
        reference = controller.trajectories[int(i)]
        N = len(reference.u_ref)
        gains = np.ascontiguousarray(np.broadcast_to(controller.K, (N, *controller.K.shape)))
        checks = np.empty((len(rows), kernels.CHECKS))
        law = (
            controller.Ts,
            np.ascontiguousarray(reference.u_ref),
            gains,
            controller.lower,
            controller.upper,
        )
        kernels.rollout_kernel(
            np.ascontiguousarray(x0[rows]),
            substeps,
            law,
            np.ascontiguousarray(reference.t),
            np.ascontiguousarray(reference.x_ref),
            np.ascontiguousarray(controller.P),
            controller.rate,
            slack + 1e-9,
            scene.position,
            (
                scene.unsafe_vertices,
                scene.unsafe_ring_start,
                scene.unsafe_set_rings,
                scene.unsafe_boxes,
            ),
            (
                scene.goal_vertices,
                scene.goal_ring_start,
                scene.goal_index,
                scene.goal_lower,
                scene.goal_upper,
            ),
            checks,
        )
        out[rows] = checks
    return RunChecks(
        clearance=out[:, kernels.CLEARANCE],
        goal_margin=out[:, kernels.GOAL],
        input_slack=out[:, kernels.SLACK],
        tube_tightness=out[:, kernels.TUBE],
        tube_final=out[:, kernels.TUBE_FINAL],
        finite=out[:, kernels.FINITE] > 0.5,
        covered=covered,
    )
