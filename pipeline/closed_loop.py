"""Closed-loop simulation of the emitted controller: ``xdot = f(x, controller(t, x))``.

The feedback acts in continuous time, so the controller is evaluated at every RK4 stage. Its
reference input is piecewise constant, so each sample interval is integrated on its own and the
stage at an interval's right end uses the left limit of the input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.controller import Controller
from pipeline.dynamics import Dynamics, FloatArray

LEFT_LIMIT = 1e-9


@dataclass(frozen=True)
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


def simulate_closed_loop(
    dynamics: Dynamics,
    controller: Controller,
    x0: FloatArray,
    trajectory: int,
    substeps: int = 4,
    disturbance: FloatArray | None = None,
    noise: FloatArray | None = None,
) -> ClosedLoopRun:
    """Run the batch ``x0 (B, n)`` around trajectory number ``trajectory`` until its end ``T``.

    Stress tests only: ``disturbance (B, n)`` is added to ``xdot``; ``noise (B, K, n)`` is added
    to the state the controller measures on RK4 step ``j`` (``K = N * substeps``).
    """
    x = np.array(x0, dtype=np.float64)
    B = x.shape[0]
    controller.follow(np.full(B, trajectory))
    reference = controller.trajectories[trajectory]
    N = len(reference.u_ref)
    h = controller.Ts / substeps
    K = N * substeps
    xs = np.empty((B, K + 1, x.shape[1]))
    unclipped = np.empty((B, K, 4, len(controller.input_names)))
    xs[:, 0] = x
    extra = 0.0 if disturbance is None else disturbance

    def field(t: float, state: FloatArray, j: int, stage: int) -> FloatArray:
        raw = controller.unclipped(t, state if noise is None else state + noise[:, j])
        unclipped[:, j, stage] = raw
        return dynamics.f(state, np.clip(raw, controller.lower, controller.upper)) + extra

    for j in range(K):
        t = j * h
        t_end = (j + 1) * h - (LEFT_LIMIT if (j + 1) % substeps == 0 else 0.0)
        k1 = field(t, x, j, 0)
        k2 = field(t + h / 2, x + h / 2 * k1, j, 1)
        k3 = field(t + h / 2, x + h / 2 * k2, j, 2)
        k4 = field(t_end, x + h * k3, j, 3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        xs[:, j + 1] = x
    ts = h * np.arange(K + 1)
    x_ref = np.stack(
        [np.interp(ts, reference.t, reference.x_ref[:, i]) for i in range(x.shape[1])], axis=-1
    )
    return ClosedLoopRun(ts, xs, x_ref, unclipped)
