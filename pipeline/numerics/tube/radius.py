"""How large a tube a nominal trajectory allows: each constraint's largest P-norm radius.

The tube of P-norm radius ``r`` around ``x_ref`` is
``E(t) = {x : ||x - x_ref(t)||_P <= r e^{-lambda t}}`` (the feedback's contraction certificate
keeps every closed-loop solution started in ``E(0)`` inside it while the tube stays in the
operating region). The radius is the largest ``r`` such that for all ``t`` in ``[0, T]``:

1. the position projection of ``E(t)`` avoids every Unsafe polygon ``U``. With
   ``Sigma = C P^-1 C^T`` and ``W = Sigma^-1/2`` the projection is the disk of radius
   ``rho(t) = r e^{-lambda t}`` about ``W p_ref(t)`` in the coordinates ``W p``, so the exact
   test is ``dist(W p_ref(t), W U) >= rho(t)``;
2. ``E(t)`` stays in the operating region and in the scenario's ``state_bounds`` (the physical
   envelope): ``|e_i| <= rho sqrt((P^-1)_ii)`` along each state (the support function of the
   ball in direction ``c`` is ``rho sqrt(c^T P^-1 c)``, here ``c = e_i``), and the tube's input
   ``u_ref + K e`` (``|K_j e| <= rho ||K_j P^-1/2||``) stays in the region and in the input
   bounds;
3. at ``T``, ``E(T)`` lies in Goal: the disk inside ``W Goal`` and Goal's extra state bounds.

Continuous time: the constraints are evaluated on the trajectory's dense grid; on a grid
interval ``[t_k, t_k + h]`` a quantity ``q`` with ``|dq/dt| <= L_k`` is at least
``(q_k + q_{k+1} - L_k h) / 2``, and ``e^{-lambda t} <= e^{-lambda t_k}``. ``L_k`` is the larger
of the rates at the interval's ends plus their difference (a first-order allowance for the
rate's change inside the interval). The reference input is held on each sample interval, so
the input constraints are exact.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.affinity import affine_transform

from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.tube.geometry import Tube


@dataclass(frozen=True, kw_only=True)
class RadiusLimits:
    """Each constraint's largest tube radius around one nominal trajectory.

    Attributes:
      limits: constraint name (e.g. "unsafe 'NAME'", "goal", "input 'NAME' upper", "state
        'NAME' lower" for state_bounds) -> (largest radius it allows on its own, when it binds
        in s).
      nominal_clearance: lower bound on the nominal position's distance to Unsafe over [0, T].
      position_scale: ``sqrt(lambda_max(C P^-1 C^T))``, the position extent per unit radius.
    """

    limits: Mapping[str, tuple[float, float]] = field(repr=False)
    nominal_clearance: float
    position_scale: float

    @property
    def radius(self) -> float:
        """The largest radius every constraint allows."""
        return min(value[0] for value in self.limits.values())


def _interval_lower_bound(q: FloatArray, rate: FloatArray, h: float) -> FloatArray:
    """Lower bound (K,) of ``q`` on each grid interval from ``q (K+1,)`` at the grid points and
    the rate of change at both ends ``rate (K, 2)``."""
    L = np.abs(rate).max(axis=1) + np.abs(rate[:, 1] - rate[:, 0])
    return np.minimum(np.minimum(q[:-1], q[1:]), (q[:-1] + q[1:] - L * h) / 2)


def radius_limits(scenario: Scenario, tube: Tube, trajectory: Trajectory) -> RadiusLimits:
    """Each constraint's largest radius for ``trajectory`` (one, unbatched: ``dense_xs (N s + 1,
    n)``, ``us (N, m)``) in ``tube`` (feedback ``K (m, n)``, metric ``P (n, n)``, ``rate`` (1/s),
    certified over its operating ``region``)."""
    lam, region = float(tube.rate), tube.region
    ts, xs, us = trajectory.dense_ts, trajectory.dense_xs, trajectory.us
    if xs.ndim != 2:
        raise ValueError(f"radius: expected one trajectory, got dense_xs of shape {xs.shape}")
    bad = ~np.isfinite(xs)
    if bad.any():
        k, i = np.argwhere(bad)[0]
        raise ValueError(
            f"radius: non-finite state '{scenario.state_names[i]}' at time index {k} "
            f"(t = {ts[k]:.3f} s)"
        )
    N = us.shape[0]
    s = (len(ts) - 1) // N
    if N == 0 or N * s != len(ts) - 1:
        raise ValueError(f"radius: {len(ts)} dense times do not split into {N} sample intervals")
    h = float(ts[1] - ts[0])
    u_grid = np.repeat(us, s, axis=0)  # (N s, m) the input held on each dense interval
    rates = np.stack(
        [scenario.dynamics.f(xs[:-1], u_grid), scenario.dynamics.f(xs[1:], u_grid)], axis=1
    )  # (N s, 2, n): dx/dt at both ends of each dense interval
    growth = np.exp(lam * ts[:-1])  # (N s,) e^{lambda t_k}
    extent = tube.state_extent_per_radius  # (n,) sqrt((P^-1)_ii)
    gain = tube.input_margin_per_radius  # (m,) ||K_j P^-1/2||
    limits: dict[str, tuple[float, float]] = {}  # name -> (radius, time)

    def record(name: str, per_interval: FloatArray, times: FloatArray) -> None:
        k = int(np.argmin(per_interval))
        limits[name] = (max(float(per_interval[k]), 0.0), float(times[k]))

    # 1. Unsafe, in the coordinates where the position ellipse is a disk.
    W = tube.position_whitening  # Sigma^-1/2, Sigma = C P^-1 C^T (2, 2)
    positions = scenario.positions(xs)
    Wp = positions @ W.T
    Wv = scenario.positions(rates) @ W.T  # (N s, 2, 2)
    speed = np.linalg.norm(Wv, axis=-1)  # (N s, 2)
    raw_speed = np.linalg.norm(scenario.positions(rates), axis=-1)
    nominal_clearance = np.inf
    for name, polygon in scenario.unsafe.items():
        transformed = affine_transform(polygon, [W[0, 0], W[0, 1], W[1, 0], W[1, 1], 0.0, 0.0])
        distance = shapely.distance(shapely.points(Wp), transformed)
        record(f"unsafe '{name}'", _interval_lower_bound(distance, speed, h) * growth, ts)
        plain = geometry.distance(positions, polygon)
        nominal_clearance = min(
            nominal_clearance, float(_interval_lower_bound(plain, raw_speed, h).min())
        )

    # 2. Operating region (states with their rates; held inputs exactly), state and input bounds.
    t_N = trajectory.ts[:-1]  # (N,) sample times
    growth_N = np.exp(lam * t_N)
    for name, (lower, upper) in region.items():
        if name in scenario.state_names:
            i = scenario.state_names.index(name)
            for side, q in (("lower", xs[:, i] - lower), ("upper", upper - xs[:, i])):
                bound = _interval_lower_bound(q, rates[:, :, i], h) * growth / extent[i]
                record(f"region '{name}' {side}", bound, ts)
        elif name in scenario.input_names:
            j = scenario.input_names.index(name)
            for side, q in (("lower", us[:, j] - lower), ("upper", upper - us[:, j])):
                record(f"region '{name}' {side}", _input_limit(q, gain[j], growth_N), t_N)
        else:
            raise ValueError(f"radius: operating region names unknown variable '{name}'")
    for name, (lower, upper) in scenario.state_bounds.items():  # as the region's states
        i = scenario.state_names.index(name)
        for side, q in (("lower", xs[:, i] - lower), ("upper", upper - xs[:, i])):
            bound = _interval_lower_bound(q, rates[:, :, i], h) * growth / extent[i]
            record(f"state '{name}' {side}", bound, ts)
    for j, name in enumerate(scenario.input_names):
        lower, upper = scenario.input_lower[j], scenario.input_upper[j]
        for side, q in (("lower", us[:, j] - lower), ("upper", upper - us[:, j])):
            record(f"input '{name}' {side}", _input_limit(q, gain[j], growth_N), t_N)

    # 3. Goal at T.
    T, final = float(ts[-1]), xs[-1]
    goal = affine_transform(scenario.goal, [W[0, 0], W[0, 1], W[1, 0], W[1, 1], 0.0, 0.0])
    inside = shapely.intersects_xy(goal, *Wp[-1])
    to_boundary = float(shapely.distance(shapely.points(Wp[-1]), goal.boundary))
    limits["goal"] = ((to_boundary if inside else 0.0) * float(np.exp(lam * T)), T)
    for name, (lower, upper) in scenario.goal_bounds.items():
        i = scenario.state_names.index(name)
        room = min(final[i] - lower, upper - final[i])
        limits[f"goal bound '{name}'"] = (float(max(room, 0.0) * np.exp(lam * T) / extent[i]), T)

    return RadiusLimits(
        limits=limits,
        nominal_clearance=float(nominal_clearance),
        position_scale=tube.position_scale,
    )


def _input_limit(room: FloatArray, gain: float, growth: FloatArray) -> FloatArray:
    """Largest radius per sample interval keeping ``u_ref + K_j e`` within ``room (N,)`` of its
    bound: ``|K_j e| <= gain r e^{-lambda t_k}`` on ``[t_k, t_{k+1})``."""
    if gain <= 0:
        return np.where(room >= 0, np.inf, 0.0)
    return np.maximum(room, 0.0) * growth / gain
