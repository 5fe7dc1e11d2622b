"""Re-verify a ``safety-controller`` file's reference trajectories from the file's data alone.

``check_reference`` (either format): ``x_ref`` is the dynamics from ``x0`` under ``u_ref`` on the
file's RK4 grid (equal steps on each sample interval, their number may differ between intervals),
and its linear interpolation (what the law tracks) is measured against a finer simulation, both
in the tube's metric at the time, ``P(t)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.controller import ReferenceTrajectory
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate, simulate_graded
from pipeline.numerics.funnel.law import BASE_SUBSTEPS, grid_substeps


@dataclass(frozen=True, kw_only=True)
class ReferenceCheck:
    """One trajectory's reference as the file states it.

    Attributes:
      trajectory: ``x0``, ``u_ref`` simulated on the file's grid (None: ``t`` is not an RK4
        grid of the samples, and nothing else was measured).
      substeps: (N,) the grid's steps on each sample interval (None with ``trajectory``).
      error: ``max ||x_ref - simulated||_P(t) / radius`` on that grid.
      interpolation: ``max ||x_ref interpolated - the dynamics||_P(t)`` on the finer grid.
      integration: the RK4 error at the sample times, estimated against a grid twice as fine
        (Richardson, order 4: ``16/15 |x_s - x_2s|``), in ``P(t_k)`` per unit radius: the larger
        of the file's grid and the proof's (``BASE_SUBSTEPS``).
      nominal: the proof's nominal, ``x0`` and ``u_ref`` on a uniform grid of ``BASE_SUBSTEPS``
        (None with ``trajectory``).
    """

    trajectory: Trajectory | None
    substeps: np.ndarray | None = None
    nominal: Trajectory | None = None
    error: float
    interpolation: float
    integration: float = np.inf


def check_reference(
    scenario: Scenario, reference: ReferenceTrajectory, Ts: float, least_substeps: int
) -> ReferenceCheck:
    """``reference``'s ``x_ref`` against the dynamics, in ``P(t)``; the interpolation measured
    on a grid of ``2 max(file's substeps, least_substeps)`` RK4 steps on each sample interval
    (finer than the file's, midpoints included)."""
    tr, N = reference, len(reference.u_ref)
    substeps = grid_substeps(tr.t, N, Ts)
    if substeps is None:
        return ReferenceCheck(trajectory=None, error=np.inf, interpolation=np.inf)
    fine = simulate_graded(scenario.dynamics, tr.x0, tr.u_ref, Ts, substeps)
    e = tr.x_ref - fine.dense_xs
    metric = tr.metric(tr.t, Ts)  # (r, n, n)
    error = float(np.sqrt(np.einsum("ki,kij,kj->k", e, metric, e)).max()) / tr.radius
    finer = simulate_graded(
        scenario.dynamics, tr.x0, tr.u_ref, Ts, 2 * np.maximum(substeps, least_substeps)
    )
    tracked = np.stack(
        [np.interp(finer.dense_ts, tr.t, tr.x_ref[:, j]) for j in range(tr.x_ref.shape[1])], -1
    )
    gap = tracked - finer.dense_xs
    metric = tr.metric(finer.dense_ts, Ts)
    interpolation = float(np.sqrt(np.einsum("ki,kij,kj->k", gap, metric, gap)).max())
    metric = tr.metric(fine.ts, Ts)  # (N+1, n, n)
    proof = simulate(scenario.dynamics, tr.x0, tr.u_ref, Ts, BASE_SUBSTEPS)  # the proof's nominal
    twice = simulate(scenario.dynamics, tr.x0, tr.u_ref, Ts, 2 * BASE_SUBSTEPS)
    richardson = [  # order 4: the error of the coarser grid is 16/15 of the difference
        16 / 15 * np.sqrt(np.einsum("ki,kij,kj->k", d, metric, d)).max()
        for d in (fine.xs - finer.xs, proof.xs - twice.xs)
    ]
    integration = max(richardson)
    return ReferenceCheck(
        trajectory=fine,
        substeps=substeps,
        nominal=proof,
        error=error,
        interpolation=interpolation,
        integration=float(integration) / tr.radius,
    )
