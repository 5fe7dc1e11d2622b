"""Sound enclosures along one nominal trajectory, and the funnel level they allow.

Nominal. ``x_ref`` solves ``xdot = f(x, u_ref[k])`` (eq. (1)) on ``[t_k, t_k+1)``, known at the
dense grid ``x_j = x_ref(t_j)``, ``t_{j+1} - t_j = h`` (the RK4 values are taken as exact, as the
radius stage does). On sample interval ``k`` let ``B_k = [lo - pad, hi + pad]`` with ``lo, hi``
the extremes of the dense points, ``J_v`` the vertices of a sound hull of ``[f_x f_u]`` over a box
holding ``B_k x {u_ref[k]}``, and

    F_i = max_j |f_i(x_j, u_ref[k])| + max_v sum_l |A_v[i, l]| (B_k upper_l - B_k lower_l).   (E1)

Mean value theorem: ``|f_i(x) - f_i(x_j)| <= sum_l |Abar[i, l]| |x_l - x_j,l|`` with ``Abar`` in
the hull (the segment from ``x_j`` to ``x`` lies in the convex ``B_k``), so ``|xdot_i| <= F_i``
while ``x`` is in ``B_k``. If ``F h < pad`` the solution cannot leave ``B_k``: before the first
exit it moves less than ``F h < pad`` from a grid point. Then, between grid points ``j, j+1``,
``x_i(t) <= min(x_j,i + F_i (t - t_j), x_{j+1},i + F_i (t_{j+1} - t)) <= max(x_j,i, x_{j+1},i)
+ F_i h / 2``, and likewise below:

    x_ref(t) in [lo - F h / 2, hi + F h / 2] on [t_k, t_k+1].                              (E2)

Levels. With ``Q = P^-1`` linear in t on each sample interval and ``K[k]`` held there, the tube
``E(t) = {x : (x - x_ref)^T P (x - x_ref) <= rho^2}`` reaches ``|e_i| <= rho sqrt(Q_ii(t))``,
``|K_j e| <= rho sqrt(K_j Q(t) K_j^T)`` and, in position, the disk of radius
``rho sqrt(lambda_max(C Q(t) C^T))``. All three are the square roots of functions convex in t
(linear, linear, lambda_max of a linear matrix), so their maxima over the interval are at its ends:

    s_i[k] = max(Q_ii[k], Q_ii[k+1])^1/2,  g_j[k] = max over both ends of (K_j[k] Q K_j[k]^T)^1/2,
    sigma[k] = max over both ends of lambda_max(C Q C^T)^1/2.                               (E3)

The level is the largest ``rho`` with: (a) ``dist(p_ref(t), Unsafe) >= rho sigma[k]``, the distance
bounded between dense points by ``(d_j + d_{j+1} - V h) / 2`` with ``V = |(F_X, F_Y)|`` (distance
is 1-Lipschitz in position); (b) ``u_ref[k] +- rho g[k]`` within the input bounds (exact, the
reference input is held); (c) the range (E2) widened by ``rho s[k]`` within the state bounds;
(d) ``E(T)`` in Goal: the ellipse ``C E(T)`` is a disk in the coordinates ``W = (C Q_N C^T)^-1/2``,
inside ``W Goal`` iff its centre is at least ``rho`` from the boundary, plus Goal's state bounds.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.affinity import affine_transform

from pipeline.model import geometry
from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory


@dataclass(frozen=True, kw_only=True)
class Enclosure:
    """The nominal on each sample interval ``k`` (N intervals, n states).

    Attributes:
      box: (N, 2, n) ``B_k`` (lower, upper), where ``|xdot| <= rate_bound`` holds (E1).
      rate_bound: (N, n) ``F``; ``grid_range``: (N, 2, n) extremes of the dense points.
      range: (N, 2, n) the sound range (E2) of ``x_ref`` on the interval.
    """

    box: FloatArray
    rate_bound: FloatArray
    grid_range: FloatArray
    range: FloatArray


def substeps(trajectory: Trajectory) -> int:
    """Dense steps per sample interval; raises if the dense grid does not split evenly."""
    N, dense = trajectory.us.shape[0], len(trajectory.dense_ts) - 1
    if N == 0 or dense % N:
        raise ValueError(f"funnel: {dense + 1} dense times do not split into {N} intervals")
    return dense // N


def grid_range(trajectory: Trajectory) -> FloatArray:
    """(N, 2, n) min and max of the dense states on each sample interval."""
    s, xs = substeps(trajectory), trajectory.dense_xs
    N = trajectory.us.shape[0]
    windows = np.stack([xs[k * s : (k + 1) * s + 1] for k in range(N)])  # (N, s+1, n)
    return np.stack([windows.min(axis=1), windows.max(axis=1)], axis=1)


def rate_bound(
    dynamics: Dynamics, trajectory: Trajectory, k: int, box: FloatArray, A: FloatArray
) -> FloatArray:
    """(n,) ``F`` of (E1) on interval ``k`` over ``box (2, n)``, hull vertices ``A (V, n, n)``."""
    s = substeps(trajectory)
    points = trajectory.dense_xs[k * s : (k + 1) * s + 1]
    grid = np.abs(dynamics.f(points, trajectory.us[k])).max(axis=0)
    return grid + (np.abs(A) @ (box[1] - box[0])).max(axis=0)  # eq. (E1)


def enclosure_range(grid: FloatArray, F: FloatArray, h: float) -> FloatArray:
    """(N, 2, n) the range (E2) from ``grid (N, 2, n)`` and ``F (N, n)``."""
    return grid + np.stack([-F, F], axis=1) * h / 2  # eq. (E2)


def tube_extents(
    Q: FloatArray, K: FloatArray, position: Sequence[int]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(E3) from ``Q (N+1, n, n)``, ``K (N, m, n)``: ``s (N, n)``, ``g (N, m)``, ``sigma (N,)``."""
    diag = np.diagonal(Q, axis1=1, axis2=2)
    s = np.sqrt(np.maximum(diag[:-1], diag[1:]))
    KQK = [np.einsum("kji,kil,kjl->kj", K, Q[e : len(Q) - 1 + e], K) for e in (0, 1)]
    g = np.sqrt(np.maximum(*KQK))
    c = list(position)
    CQC = np.linalg.eigvalsh(Q[:, c][:, :, c])[:, -1]
    sigma = np.sqrt(np.maximum(CQC[:-1], CQC[1:]))
    return s, g, sigma


def _interval_distance(d: FloatArray, speed: FloatArray, s: int, h: float) -> FloatArray:
    """(N,) lower bound of a 1-Lipschitz distance on each sample interval from ``d (N s + 1,)`` on
    the dense grid and the speed bound ``speed (N,)``."""
    V = np.repeat(speed, s)
    low = (d[:-1] + d[1:] - V * h) / 2
    return low.reshape(-1, s).min(axis=1)


def interval_clearance(
    scenario: Scenario, trajectory: Trajectory, enclosure: Enclosure
) -> FloatArray:
    """(N,) lower bound of the nominal position's distance to Unsafe on each sample interval,
    (a) of the docstring (``inf`` without Unsafe)."""
    s, h = substeps(trajectory), float(trajectory.dense_ts[1] - trajectory.dense_ts[0])
    speed = np.linalg.norm(enclosure.rate_bound[:, list(scenario.position_index)], axis=1)
    positions = scenario.positions(trajectory.dense_xs)
    clearance = np.full(trajectory.us.shape[0], np.inf)
    for polygon in scenario.unsafe.values():
        distance = _interval_distance(geometry.distance(positions, polygon), speed, s, h)
        clearance = np.minimum(clearance, distance)
    return clearance


def funnel_limits(
    scenario: Scenario,
    trajectory: Trajectory,
    Q: FloatArray,
    K: FloatArray,
    enclosure: Enclosure,
    state_bounds: Mapping[str, tuple[float, float]],
    input_offset: FloatArray | None = None,
) -> dict[str, tuple[float, float]]:
    """Constraint -> (largest level ``rho`` it allows, time it binds), (a)-(d) of the docstring.

    ``Q (N+1, n, n)`` the inverse metrics at ``t_k``, ``K (N, m, n)`` the gains, ``input_offset
    (N, m)`` the shipped law's input offset (``funnel.law`` (I3); none by default)."""
    ts, us = trajectory.ts, trajectory.us
    s, h = substeps(trajectory), float(trajectory.dense_ts[1] - trajectory.dense_ts[0])
    s_ext, g, sigma = tube_extents(Q, K, scenario.position_index)
    limits: dict[str, tuple[float, float]] = {}

    def record(name: str, per_interval: FloatArray) -> None:
        k = int(np.argmin(per_interval))
        limits[name] = (max(float(per_interval[k]), 0.0), float(ts[k]))

    def ratio(room: FloatArray, extent: FloatArray) -> FloatArray:
        return np.where(extent > 0, np.maximum(room, 0.0) / np.maximum(extent, 1e-300), np.inf)

    # (a) Unsafe: the position disk of radius rho sigma[k] around the nominal.
    c = list(scenario.position_index)
    speed = np.linalg.norm(enclosure.rate_bound[:, c], axis=1)
    positions = scenario.positions(trajectory.dense_xs)
    for name, polygon in scenario.unsafe.items():
        distance = _interval_distance(geometry.distance(positions, polygon), speed, s, h)
        record(f"unsafe '{name}'", np.where(distance > 0, distance, 0.0) / sigma)
    # (b) inputs (held reference: exact), less the law's offset (funnel.law (I3)).
    offset = np.zeros(us.shape) if input_offset is None else input_offset
    for j, name in enumerate(scenario.input_names):
        lower, upper = scenario.input_lower[j], scenario.input_upper[j]
        record(f"input '{name}' lower", ratio(us[:, j] - offset[:, j] - lower, g[:, j]))
        record(f"input '{name}' upper", ratio(upper - offset[:, j] - us[:, j], g[:, j]))
    # (c) state bounds on the sound range (E2).
    for name, (lower, upper) in state_bounds.items():
        i = scenario.state_names.index(name)
        record(f"state '{name}' lower", ratio(enclosure.range[:, 0, i] - lower, s_ext[:, i]))
        record(f"state '{name}' upper", ratio(upper - enclosure.range[:, 1, i], s_ext[:, i]))
    # (d) Goal at T.
    T, final = float(ts[-1]), trajectory.dense_xs[-1]
    values, vectors = np.linalg.eigh(Q[-1][np.ix_(c, c)])
    W = vectors @ np.diag(values**-0.5) @ vectors.T
    goal = affine_transform(scenario.goal, [W[0, 0], W[0, 1], W[1, 0], W[1, 1], 0.0, 0.0])
    Wp = W @ scenario.positions(final)
    inside = shapely.intersects_xy(goal, *Wp)
    limits["goal"] = (float(shapely.distance(shapely.points(Wp), goal.boundary)) * inside, T)
    for name, (lower, upper) in scenario.goal_bounds.items():
        i = scenario.state_names.index(name)
        room = max(min(final[i] - lower, upper - final[i]), 0.0)
        limits[f"goal bound '{name}'"] = (room / float(np.sqrt(Q[-1][i, i])), T)
    return limits
