"""Penalty terms of the cost (paper §IV-A, eqs. (40)-(42)) and their exact derivatives.

With ``s`` RK4 substeps per sample interval (``x_i``, ``i = 0..N s``, the RK4 grid) and weight
``w = 1 / s`` on the states::

    J(u) = G(x_{N s}) + sum_k [g_in(u[k]) + g_reg(u[k])] + w sum_i [g_unsafe(x_i) + g_reg(x_i)]

so ``s = 1`` is the paper's sum over sample times (26), and every ``s`` puts the same weight on
an interval. The terms (``box(z) = sum_j dist(z_j, [lo_j, hi_j])^2``):

    g_in(u)      = box(u) on the input bounds shrunk by eps_i + input_margin       eq. (40)
    G(x)         = dist(p, ModGoal)^2 + box(x) on goal.bounds,                       eq. (41)
                   ModGoal = Goal shrunk by d + eps_g
    g_unsafe(x)  = sum_i b(r_i), r_i = dist(p, Unsafe_i), d' = d + eps_d:            eq. (42)
                   b = 0 for r > d', -log(r/d') + (r - d')/d' for 0 < r <= d', +inf at r = 0
    g_reg(x, u)  = box on the operating region shrunk by region_margin

with ``p`` the position of ``x``. Margins may vary along the trajectory
(``pipeline.numerics.optimize.margins``): on sample interval ``k`` the tube's extents
``clearance[k]``, ``input[k]``, ``state[k]`` are added to ``d'``, to the input shrink and to the
region's shrink (``Constraints.grid``: the bounds on one grid, a point on a sample boundary taking
the larger margin of its two intervals); with constant margins the arrays are constant. Every term
is zero exactly when its constraint holds with its margin, so ``J == 0`` is the feasibility test.
All terms are C^1 (away from the medial axis of the polygon distances); ``Constraints.evaluate``
returns ``J`` with its partial derivatives with respect to every grid state and input, which
the gradient methods chain through RK4.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from shapely.geometry.base import BaseGeometry

from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.numerics.optimize.margins import MarginProfile, per_point
from pipeline.numerics.settings import EPS_D, EPS_G, EPS_I

if TYPE_CHECKING:
    from pipeline.model.scenario import Scenario

IntArray = npt.NDArray[np.int64]

# Below this |z| the barrier uses its series, so that b > 0 for every representable r < d'.
_SERIES_BELOW = 1e-4


class MarginError(ValueError):
    """The margins leave a constraint set empty (inputs, operating region, Goal); the message
    names the set and the fix."""


def box_penalty(
    z: FloatArray, lower: FloatArray, upper: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Squared distance outside a box, summed over components (shape of eq. (40)).

    Args:
      z: (..., k) points; lower, upper: (k,) bounds.
    Returns:
      value (...), gradient (..., k).
    """
    excess = z - np.clip(z, lower, upper)
    return np.sum(excess**2, axis=-1), 2.0 * excess


def barrier(r: FloatArray, d: float | FloatArray) -> tuple[FloatArray, FloatArray]:
    """The Unsafe barrier of eq. (42), corrected, and its slope ``db/dr``.

    (42) as printed, ``-log(r - d) + (r - d)/d`` on ``r <= d``, takes the log of a non-positive
    number. We use ``b(r) = -log(r/d) + (r - d)/d`` on ``0 < r <= d`` (here ``d`` is the caller's
    ``d' = d + eps_d``): zero with zero slope at ``r = d``, growing without bound as ``r -> 0``;
    ``b = 0`` for ``r > d`` and ``+inf`` at ``r = 0`` (inside the set). With ``z = (r - d)/d``,
    ``b = z - log1p(z)``, evaluated by its series ``z^2/2 - z^3/3 + ...`` for small ``|z|`` so
    that it is positive for every ``r < d``.

    Args:
      r: (...) distances (>= 0); d: d', a number or (...) per distance. Returns value (...),
        slope (...) (0 where the value is inf).
    """
    r = np.asarray(r, dtype=np.float64)
    z = np.minimum(r - d, 0.0) / d
    with np.errstate(divide="ignore"):
        direct = z - np.log1p(z)
    series = z * z * (0.5 - z * (1.0 / 3.0 - z * (0.25 - z / 5.0)))
    value = np.where(z > -_SERIES_BELOW, series, direct)
    value = np.where(r <= 0.0, np.inf, value)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(r > 0.0, z / (1.0 + z) / d, 0.0)
    return value, slope


def polygon_distance(positions: FloatArray, region: BaseGeometry) -> tuple[FloatArray, FloatArray]:
    """Distance to ``region`` and its gradient ``(p - nearest) / r`` (0 inside).

    Exact away from the medial axis of the region's complement, where the nearest point jumps.

    Args:
      positions: (..., 2). Returns r (...), gradient (..., 2).
    """
    positions = np.asarray(positions, dtype=np.float64)
    r = geometry.distance(positions, region)
    nearest = geometry.nearest_points(positions, region)
    with np.errstate(divide="ignore", invalid="ignore"):
        gradient = np.where(r[..., None] > 0.0, (positions - nearest) / r[..., None], 0.0)
    return r, gradient


@dataclass(frozen=True, kw_only=True)
class Penalized:
    """``J`` and its partial derivatives with respect to each grid state and input.

    Attributes:
      cost: J (``+inf`` if a grid state is inside Unsafe).
      J_x: (N s + 1, n) ``dJ/dx_i`` holding the other variables fixed (final point includes G).
      J_u: (N, m) ``dJ/du[k]`` holding the states fixed.
    """

    cost: float
    J_x: FloatArray
    J_u: FloatArray


@dataclass(frozen=True, kw_only=True)
class GridBounds:
    """The bounds on one grid of ``N`` sample intervals and ``s`` RK4 substeps (base + profile).

    Attributes:
      unsafe_margin: (N s + 1,) ``d'`` at each grid state.
      input_lower, input_upper: (N, m) shrunk input bounds per sample.
      region_state_lower, region_state_upper: (N s + 1, a) the region's state part per point.
      region_input_lower, region_input_upper: (N, b) the region's input part per sample.
    """

    unsafe_margin: FloatArray
    input_lower: FloatArray
    input_upper: FloatArray
    region_state_lower: FloatArray
    region_state_upper: FloatArray
    region_input_lower: FloatArray
    region_input_upper: FloatArray


@dataclass(frozen=True, kw_only=True, eq=False)
class Constraints:
    """The modified constraints of §IV-A, as penalties. Index arrays select state/input entries.

    Attributes:
      input_lower, input_upper: (m,) input bounds shrunk by ``eps_i + input_margin``.
      region: name -> (lower, upper) box the nominal stays in (the operating region, or the
        box given to ``build_constraints``) shrunk by region_margin (states and inputs).
      region_state_index, region_state_lower, region_state_upper: (a,) the state part.
      region_input_index, region_input_lower, region_input_upper: (b,) the input part.
      goal_region: ModGoal (polygon over position); goal_index, goal_lower, goal_upper: (c,)
        goal.bounds on other states (not shrunk).
      unsafe: name -> Unsafe polygon (not bloated); unsafe_margin: ``d' = d + eps_d``.
      position_index: (2,) position states.
      profile: the margins that vary along the trajectory, on top of the bounds above
        (``MarginProfile.zero`` for constant margins); ``grid(N, s)`` combines the two.
    With ``MarginProfile.zero`` the bounds above hold at every time.
    """

    input_lower: FloatArray
    input_upper: FloatArray
    region: Mapping[str, tuple[float, float]]
    region_state_index: IntArray
    region_state_lower: FloatArray
    region_state_upper: FloatArray
    region_input_index: IntArray
    region_input_lower: FloatArray
    region_input_upper: FloatArray
    goal_region: BaseGeometry = field(repr=False)
    goal_index: IntArray
    goal_lower: FloatArray
    goal_upper: FloatArray
    unsafe: Mapping[str, BaseGeometry] = field(repr=False)
    unsafe_margin: float
    position_index: tuple[int, int]
    profile: MarginProfile = field(repr=False)
    _grids: dict[tuple[int, int], GridBounds] = field(default_factory=dict, repr=False)

    def grid(self, N: int, substeps: int) -> GridBounds:
        """The bounds on the RK4 grid of ``N`` intervals and ``substeps`` per interval: the base
        bounds plus ``profile.on_grid(N)`` (normalised time, maximum over the window)."""
        key = (int(N), int(substeps))
        if key not in self._grids:
            on = self.profile.on_grid(key[0])
            state = per_point(on.state, key[1])[:, self.region_state_index]  # (N s + 1, a)
            region_input = on.input[:, self.region_input_index]  # (N, b)
            self._grids[key] = GridBounds(
                unsafe_margin=self.unsafe_margin + per_point(on.clearance, key[1]),
                input_lower=self.input_lower + on.input,
                input_upper=self.input_upper - on.input,
                region_state_lower=self.region_state_lower + state,
                region_state_upper=self.region_state_upper - state,
                region_input_lower=self.region_input_lower + region_input,
                region_input_upper=self.region_input_upper - region_input,
            )
        return self._grids[key]

    def _constant(self, grid: GridBounds | None) -> GridBounds:
        """``grid``, or the bounds at every time when the margins do not vary (M = 1)."""
        if grid is not None:
            return grid
        if self.profile.M != 1:
            raise ValueError(
                f"the margins vary along the trajectory ({self.profile.M} intervals): pass the"
                " grid's bounds, constraints.grid(N, substeps)"
            )
        one = self.grid(1, 1)  # every row holds the same bounds: keep one, to broadcast
        return GridBounds(**{name: value[0] for name, value in vars(one).items()})

    def state_terms(
        self, xs: FloatArray, grid: GridBounds | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """``g_unsafe + g_reg`` at states ``xs (..., n)``: value (...), gradient (..., n).

        ``grid``: the bounds of the grid ``xs (N s + 1, n)`` is on; without it (constant margins
        only), any leading shape."""
        xs = np.asarray(xs, dtype=np.float64)
        bounds = self._constant(grid)
        value = np.zeros(xs.shape[:-1])
        gradient = np.zeros_like(xs)
        positions = xs[..., list(self.position_index)]
        for region in self.unsafe.values():
            r, r_p = polygon_distance(positions, region)
            b, b_r = barrier(r, bounds.unsafe_margin)  # eq. (42)
            value += b
            gradient[..., self.position_index] += b_r[..., None] * r_p
        box, box_x = box_penalty(
            xs[..., self.region_state_index], bounds.region_state_lower, bounds.region_state_upper
        )
        value += box
        gradient[..., self.region_state_index] += box_x
        return value, gradient

    def input_terms(
        self, us: FloatArray, grid: GridBounds | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """``g_in + g_reg`` at inputs ``us (..., m)``: value (...), gradient (..., m).

        ``grid``: the bounds of the horizon ``us (N, m)`` is on; without it (constant margins
        only), any leading shape."""
        us = np.asarray(us, dtype=np.float64)
        bounds = self._constant(grid)
        value, gradient = box_penalty(us, bounds.input_lower, bounds.input_upper)  # eq. (40)
        box, box_u = box_penalty(
            us[..., self.region_input_index], bounds.region_input_lower, bounds.region_input_upper
        )
        gradient[..., self.region_input_index] += box_u
        return value + box, gradient

    def final_terms(self, x: FloatArray) -> tuple[float, FloatArray]:
        """``G`` at the final state ``x (n,)``: value, gradient (n,)."""
        x = np.asarray(x, dtype=np.float64)
        p = x[list(self.position_index)]
        r, r_p = polygon_distance(p, self.goal_region)
        gradient = np.zeros_like(x)
        gradient[list(self.position_index)] = 2.0 * r * r_p  # eq. (41): d(r^2) = 2 (p - nearest)
        box, box_x = box_penalty(x[self.goal_index], self.goal_lower, self.goal_upper)
        gradient[self.goal_index] += box_x
        return float(r**2 + box), gradient

    def evaluate(self, dense_xs: FloatArray, us: FloatArray, substeps: int) -> Penalized:
        """``J`` with its partial derivatives on the RK4 grid.

        Args:
          dense_xs: (N s + 1, n) states on the grid; us: (N, m); substeps: ``s``.
        """
        w = 1.0 / substeps
        grid = self.grid(len(us), substeps)
        state_value, state_gradient = self.state_terms(dense_xs, grid)
        input_value, J_u = self.input_terms(us, grid)
        final_value, final_gradient = self.final_terms(dense_xs[-1])
        J_x = w * state_gradient
        J_x[-1] += final_gradient
        cost = final_value + float(np.sum(input_value)) + w * float(np.sum(state_value))
        return Penalized(cost=cost, J_x=J_x, J_u=J_u)


def build_constraints(
    scenario: Scenario,
    *,
    input_margin: FloatArray | float | None = None,
    region_margin: Mapping[str, float] | None = None,
    eps_d: float = EPS_D,
    eps_g: float = EPS_G,
    eps_i: float = EPS_I,
    clearance: float | None = None,
    goal_margin: Mapping[str, float] | None = None,
    region: Mapping[str, tuple[float, float]] | None = None,
    profile: MarginProfile | None = None,
) -> Constraints:
    """The §IV-A constraints of ``scenario`` with the given margins (each error says the fix);
    ``clearance`` replaces the scenario's ``d`` when the tube must be wider than ``d``'s, and
    ``goal_margin`` (state name -> the tube's extent) shrinks Goal's extra bounds. ``region``
    (name -> (lower, upper)) is the box the nominal stays in (default: the scenario's
    operating region); ``profile`` adds margins that vary along the trajectory."""
    n, m = scenario.n, scenario.m
    d = scenario.clearance if clearance is None else clearance
    for name, value in [("eps_d", eps_d), ("eps_g", eps_g), ("eps_i", eps_i), ("clearance", d)]:
        if not (np.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    profile = MarginProfile.zero(n, m) if profile is None else profile
    if profile.input.shape[1:] != (m,) or profile.state.shape[1:] != (n,):
        raise ValueError(
            f"margin profile has input {profile.input.shape} and state {profile.state.shape};"
            f" expected (M, {m}) and (M, {n}) for scenario '{scenario.name}'"
        )
    if d + eps_d + float(profile.clearance.min()) <= 0.0:
        raise ValueError(
            f"d + eps_d = {d + eps_d:g} with no position margin: the Unsafe margin must be > 0"
        )
    margin = np.zeros(m) if input_margin is None else np.asarray(input_margin, dtype=np.float64)
    if margin.shape not in [(), (m,)] or not np.all(np.isfinite(margin)) or np.any(margin < 0):
        raise ValueError(
            f"input_margin must be a number or {m} numbers >= 0 ({', '.join(scenario.input_names)})"
            f", got {input_margin!r}"
        )
    input_lower = scenario.input_lower + eps_i + margin
    input_upper = scenario.input_upper - eps_i - margin
    widest = profile.input.max(axis=0)  # (m,) the profile's largest input extent
    for j in np.flatnonzero(input_lower + widest > input_upper - widest):
        name = scenario.input_names[j]
        raise MarginError(
            f"input bounds of '{name}' are empty after shrinking by eps_i +"
            f" input_margin = {eps_i + np.broadcast_to(margin, (m,))[j]:g} plus the tube's"
            f" extent {widest[j]:g}: [{input_lower[j] + widest[j]:g},"
            f" {input_upper[j] - widest[j]:g}]; the feedback's gain on '{name}' is too large"
            f" for the radius kept: widen input_bounds.{name}, or lower feedback.rate"
        )

    box = dict(scenario.operating_region if region is None else region)
    label = "scenario's operating_region" if region is None else "region"
    region_margin = dict(region_margin or {})
    unknown = sorted(set(region_margin) - set(box))
    if unknown:
        raise ValueError(
            f"region_margin names '{unknown[0]}', which is not in the {label}"
            f" (names: {sorted(box)})"
        )
    states, inputs = scenario.state_names, scenario.input_names
    extent = dict(zip(states, profile.state.max(axis=0), strict=True))
    extent |= dict(zip(inputs, profile.input.max(axis=0), strict=True))
    shrunk: dict[str, tuple[float, float]] = {}
    for name, (lower, upper) in box.items():
        if name not in extent:
            raise ValueError(f"{label} names '{name}', which is not a state or input")
        shrink = float(region_margin.get(name, 0.0))
        if not (np.isfinite(shrink) and shrink >= 0.0):
            raise ValueError(f"region_margin['{name}'] must be a finite number >= 0, got {shrink}")
        widest_shrink = shrink + float(extent[name])
        if lower + widest_shrink > upper - widest_shrink:
            raise MarginError(
                f"{'operating region' if region is None else 'region'} of '{name}'"
                f" [{lower:g}, {upper:g}] is empty after"
                f" shrinking by region_margin = {shrink:g} plus the tube's extent"
                f" {float(extent[name]):g}; the tube at the radius kept is wider than it:"
                f" widen operating_region.{name}, or lower feedback.rate"
            )
        shrunk[name] = (lower + shrink, upper - shrink)
    state_part = [(states.index(k), lo, hi) for k, (lo, hi) in shrunk.items() if k in states]
    input_part = [(inputs.index(k), lo, hi) for k, (lo, hi) in shrunk.items() if k in inputs]
    goal_part = []
    for name, (lower, upper) in scenario.goal_bounds.items():
        i = states.index(name)
        shrink = float((goal_margin or {}).get(name, 0.0)) + float(profile.final_state[i])
        if lower + shrink > upper - shrink:
            raise MarginError(
                f"Goal's bound on '{name}' [{lower:g}, {upper:g}] is empty after shrinking by the"
                f" tube's extent {shrink:g}; widen goal.bounds.{name} or use a smaller clearance"
            )
        goal_part.append((i, lower + shrink, upper - shrink))

    goal_shrink = d + eps_g + profile.final_clearance
    goal_region = geometry.shrink(scenario.goal, goal_shrink)
    if goal_region.is_empty:
        raise MarginError(
            f"Goal shrunk by d + eps_g = {goal_shrink:g} (d = {d:g} plus the tube's position"
            f" extent at T {profile.final_clearance:g}) is empty; use a smaller clearance or a"
            " larger goal.polygon"
        )

    def columns(part: list[tuple[int, float, float]]) -> tuple[IntArray, FloatArray, FloatArray]:
        index, lower, upper = zip(*part, strict=True) if part else ((), (), ())
        return (
            np.array(index, dtype=np.int64),
            np.array(lower, dtype=np.float64),
            np.array(upper, dtype=np.float64),
        )

    rs_index, rs_lower, rs_upper = columns(state_part)
    ri_index, ri_lower, ri_upper = columns(input_part)
    g_index, g_lower, g_upper = columns(goal_part)
    return Constraints(
        input_lower=input_lower,
        input_upper=input_upper,
        region=shrunk,
        region_state_index=rs_index,
        region_state_lower=rs_lower,
        region_state_upper=rs_upper,
        region_input_index=ri_index,
        region_input_lower=ri_lower,
        region_input_upper=ri_upper,
        goal_region=goal_region,
        goal_index=g_index,
        goal_lower=g_lower,
        goal_upper=g_upper,
        unsafe=dict(scenario.unsafe),
        unsafe_margin=d + eps_d,
        position_index=scenario.position_index,
        profile=profile,
    )
