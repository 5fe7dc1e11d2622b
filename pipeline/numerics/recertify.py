"""Re-verify a ``safety-controller`` file's trajectories from the file's data alone.

``check_reference`` (either format): ``x_ref`` is the dynamics from ``x0`` under ``u_ref`` on the
file's RK4 grid, and its linear interpolation (what the law tracks) is measured against a finer
simulation, both in the tube's metric at the time, ``P(t)``.

``recheck_funnel`` (``/2``). The file carries, per trajectory, ``x_ref`` (re-simulated by
``check_reference`` from ``x0`` and ``u_ref``), ``K (N, m, n)``, ``P (N+1, n, n)`` (``Q =
P^-1`` linear in t between samples, eq. (F1) of ``pipeline.numerics.funnel``), the level ``rho``
and the rate ``lambda``; not the hulls the synthesis used. Rebuilt here, independently of the
synthesis's boxes and its solver:

1. per sample interval ``k``, the nominal's a priori box ``B_k = grid_k +- pad`` (E1 of
   ``funnel_bounds``: ``F h < pad`` with ``F`` from the hull below, ``pad`` grown until it holds);
2. the box ``Z_k`` of the variables the Jacobian depends on: a state's ``B_k`` widened by the
   tube's extent ``rho s_i[k]``, an input's ``u_ref[k] +- rho g_j[k]`` (E3), clipped to the
   scenario's state and input bounds (sound: the limits re-checked below keep the tube inside
   them), and a sound hull of ``[f_x f_u]`` over ``Z_k`` (``pipeline.numerics.hull``, outward
   rounded);
3. ``funnel_check.check_funnel`` on the funnel so rebuilt: ``P[k]`` positive definite, (F3) at
   every vertex at both ends of every interval (numpy eigenvalues), the enclosure (E1) and the
   tube inside every hull box, ``rho`` within the limits of Unsafe, the inputs, the state bounds
   and Goal at ``T`` (``funnel_bounds.funnel_limits``).

A hull over a box is sound for any number of segments, so ``SEGMENTS`` are tried in turn and the
funnel is accepted when one of them certifies it (a finer hull is tighter, not always a subset).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pipeline.controller import ReferenceTrajectory
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.funnel_bounds import funnel_limits
from pipeline.numerics.funnel_check import Funnel, certificate_margins, check_funnel
from pipeline.numerics.funnel_pieces import piece_hulls
from pipeline.numerics.hull import HullError

SEGMENTS = (1, 4)
WIDEN = 1e-9  # relative widening of the tube's extent in the hull boxes (rounding of E3)
PAD_ROUNDS = 8


@dataclass(frozen=True, kw_only=True)
class ReferenceCheck:
    """One trajectory's reference as the file states it.

    Attributes:
      trajectory: ``x0``, ``u_ref`` simulated on the file's grid (None: ``t`` is not a uniform
        RK4 grid of the samples, and nothing else was measured).
      error: ``max ||x_ref - simulated||_P(t) / radius`` on that grid.
      interpolation: ``max ||x_ref interpolated - the dynamics||_P(t)`` on the finer grid.
    """

    trajectory: Trajectory | None
    error: float
    interpolation: float


def check_reference(
    scenario: Scenario, reference: ReferenceTrajectory, Ts: float, least_substeps: int
) -> ReferenceCheck:
    """``reference``'s ``x_ref`` against the dynamics, in ``P(t)``; the interpolation measured
    on a grid of ``2 max(file's substeps, least_substeps)`` RK4 steps per sample (finer than the
    file's, midpoints included)."""
    tr, N = reference, len(reference.u_ref)
    substeps = (len(tr.t) - 1) // N
    fine = simulate(scenario.dynamics, tr.x0, tr.u_ref, Ts, substeps=max(substeps, 1))
    if substeps * N + 1 != len(tr.t) or not np.allclose(fine.dense_ts, tr.t, rtol=0, atol=1e-9):
        return ReferenceCheck(trajectory=None, error=np.inf, interpolation=np.inf)
    e = tr.x_ref - fine.dense_xs
    metric = tr.metric(tr.t, Ts)  # (r, n, n)
    error = float(np.sqrt(np.einsum("ki,kij,kj->k", e, metric, e)).max()) / tr.radius
    finer = simulate(scenario.dynamics, tr.x0, tr.u_ref, Ts, 2 * max(substeps, least_substeps))
    tracked = np.stack(
        [np.interp(finer.dense_ts, tr.t, tr.x_ref[:, j]) for j in range(tr.x_ref.shape[1])], -1
    )
    gap = tracked - finer.dense_xs
    metric = tr.metric(finer.dense_ts, Ts)
    interpolation = float(np.sqrt(np.einsum("ki,kij,kj->k", gap, metric, gap)).max())
    return ReferenceCheck(trajectory=fine, error=error, interpolation=interpolation)


@dataclass(frozen=True, kw_only=True)
class FunnelRecheck:
    """The re-verification of one funnel.

    Attributes:
      failure: what fails (None: certified); margin: the largest eigenvalue of (F2) over the
        vertices at both ends of every interval (< 0 for a certificate); vertices: hull vertices
        over all intervals; radius: the largest level the constraints allow (>= rho to pass);
        binding: the constraint that sets it.
    """

    failure: str | None
    margin: float
    vertices: int
    radius: float
    binding: str


def rebuild_funnel(
    scenario: Scenario,
    trajectory: Trajectory,
    K: FloatArray,
    P: FloatArray,
    Q: FloatArray,
    rho: float,
    rate: float,
    state_bounds: Mapping[str, tuple[float, float]],
    segments: int,
) -> Funnel:
    """The funnel ``K (N, m, n)``, ``P (N+1, n, n)``, ``rho``, ``rate`` around ``trajectory``
    with hulls and enclosure rebuilt by steps 1-2 of the module docstring
    (``funnel_pieces.piece_hulls`` on pieces of one sample interval, with the file's ``Q (N+1,
    n, n) = P^-1`` (symmetrized) at level ``rho (1 + WIDEN)`` as the extents and no arc caps).

    Raises:
      HullError: no hull over a box, or no a priori enclosure within ``PAD_ROUNDS``.
    """
    N = len(K)
    variables, boxes, vertices, enclosure = piece_hulls(
        scenario, trajectory, Q, K, state_bounds,
        rho * (1 + WIDEN), segments, np.arange(N + 1), tight=False, pad_rounds=PAD_ROUNDS,
    )  # fmt: skip
    return Funnel(
        K=K, P=P, rho=rho, rate=rate, margins=np.full((N, 2), np.nan), boxes=boxes,
        variables=variables, vertices=vertices, enclosure=enclosure, limits={},
        binding="", seconds=0.0, success=True, message="rebuilt from controller.json",
    )  # fmt: skip


def recheck_funnel(
    scenario: Scenario,
    trajectory: Trajectory,
    K: FloatArray,
    P: FloatArray,
    rho: float,
    rate: float,
    state_bounds: Mapping[str, tuple[float, float]],
) -> FunnelRecheck:
    """Steps 1-3 of the module docstring for one funnel (``K (N, m, n)``, ``P (N+1, n, n)``)."""
    Q = np.linalg.inv(P)
    Q = (Q + np.swapaxes(Q, 1, 2)) / 2
    failures: list[str] = []
    last = FunnelRecheck(failure="", margin=float("nan"), vertices=0, radius=0.0, binding="")
    for segments in SEGMENTS:
        try:
            funnel = rebuild_funnel(
                scenario, trajectory, K, P, Q, rho, rate, state_bounds, segments
            )
        except (HullError, np.linalg.LinAlgError) as error:
            failures.append(f"{segments} segment(s): {error}")
            continue
        failure = check_funnel(scenario, trajectory, funnel, state_bounds)
        margin = float(certificate_margins(Q, K, funnel.vertices, rate, scenario.Ts).max())
        assert funnel.enclosure is not None
        limits = funnel_limits(scenario, trajectory, Q, K, funnel.enclosure, state_bounds)
        binding = min(limits, key=lambda key: limits[key][0])
        last = FunnelRecheck(
            failure=failure,
            margin=margin,
            vertices=sum(len(v) for v in funnel.vertices),
            radius=limits[binding][0],
            binding=binding,
        )
        if failure is None:
            return last
        failures.append(f"{segments} segment(s): {failure}")
    return dataclasses.replace(last, failure="; ".join(failures))
