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

with ``p`` the position of ``x``. Every term is zero exactly when its constraint holds with its
margin, so ``J == 0`` is the feasibility test. All terms are C^1 (away from the medial axis of
the polygon distances); ``Constraints.evaluate`` returns ``J`` with its partial derivatives with
respect to every grid state and input, which the gradient methods chain through RK4.
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


def barrier(r: FloatArray, d: float) -> tuple[FloatArray, FloatArray]:
    """The Unsafe barrier of eq. (42), corrected, and its slope ``db/dr``.

    (42) as printed, ``-log(r - d) + (r - d)/d`` on ``r <= d``, takes the log of a non-positive
    number. We use ``b(r) = -log(r/d) + (r - d)/d`` on ``0 < r <= d`` (here ``d`` is the caller's
    ``d' = d + eps_d``): zero with zero slope at ``r = d``, growing without bound as ``r -> 0``;
    ``b = 0`` for ``r > d`` and ``+inf`` at ``r = 0`` (inside the set). With ``z = (r - d)/d``,
    ``b = z - log1p(z)``, evaluated by its series ``z^2/2 - z^3/3 + ...`` for small ``|z|`` so
    that it is positive for every ``r < d``.

    Args:
      r: (...) distances (>= 0). Returns value (...), slope (...) (0 where the value is inf).
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


@dataclass(frozen=True, kw_only=True, eq=False)
class Constraints:
    """The modified constraints of §IV-A, as penalties. Index arrays select state/input entries.

    Attributes:
      input_lower, input_upper: (m,) input bounds shrunk by ``eps_i + input_margin``.
      region: name -> shrunk (lower, upper) operating-region box (states and inputs).
      region_state_index, region_state_lower, region_state_upper: (a,) the state part.
      region_input_index, region_input_lower, region_input_upper: (b,) the input part.
      goal_region: ModGoal (polygon over position); goal_index, goal_lower, goal_upper: (c,)
        goal.bounds on other states (not shrunk).
      unsafe: name -> Unsafe polygon (not bloated); unsafe_margin: ``d' = d + eps_d``.
      position_index: (2,) position states.
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

    def state_terms(self, xs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``g_unsafe + g_reg`` at states ``xs (..., n)``: value (...), gradient (..., n)."""
        xs = np.asarray(xs, dtype=np.float64)
        value = np.zeros(xs.shape[:-1])
        gradient = np.zeros_like(xs)
        positions = xs[..., list(self.position_index)]
        for region in self.unsafe.values():
            r, r_p = polygon_distance(positions, region)
            b, b_r = barrier(r, self.unsafe_margin)  # eq. (42)
            value += b
            gradient[..., self.position_index] += b_r[..., None] * r_p
        box, box_x = box_penalty(
            xs[..., self.region_state_index], self.region_state_lower, self.region_state_upper
        )
        value += box
        gradient[..., self.region_state_index] += box_x
        return value, gradient

    def input_terms(self, us: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``g_in + g_reg`` at inputs ``us (..., m)``: value (...), gradient (..., m)."""
        us = np.asarray(us, dtype=np.float64)
        value, gradient = box_penalty(us, self.input_lower, self.input_upper)  # eq. (40)
        box, box_u = box_penalty(
            us[..., self.region_input_index], self.region_input_lower, self.region_input_upper
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
        state_value, state_gradient = self.state_terms(dense_xs)
        input_value, J_u = self.input_terms(us)
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
) -> Constraints:
    """The §IV-A constraints of ``scenario`` with the given margins (each error says the fix);
    ``clearance`` replaces the scenario's ``d`` when the tube must be wider than ``d``'s, and
    ``goal_margin`` (state name -> the tube's extent) shrinks Goal's extra bounds."""
    m = scenario.m
    d = scenario.clearance if clearance is None else clearance
    for name, value in [("eps_d", eps_d), ("eps_g", eps_g), ("eps_i", eps_i), ("clearance", d)]:
        if not (np.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    margin = np.zeros(m) if input_margin is None else np.asarray(input_margin, dtype=np.float64)
    if margin.shape not in [(), (m,)] or not np.all(np.isfinite(margin)) or np.any(margin < 0):
        raise ValueError(
            f"input_margin must be a number or {m} numbers >= 0 ({', '.join(scenario.input_names)})"
            f", got {input_margin!r}"
        )
    input_lower = scenario.input_lower + eps_i + margin
    input_upper = scenario.input_upper - eps_i - margin
    for j in np.flatnonzero(input_lower > input_upper):
        raise MarginError(
            f"input bounds of '{scenario.input_names[j]}' are empty after shrinking by eps_i +"
            f" input_margin = {eps_i + np.broadcast_to(margin, (m,))[j]:g}: "
            f"[{input_lower[j]:g}, {input_upper[j]:g}]; use smaller margins"
        )

    region_margin = dict(region_margin or {})
    unknown = sorted(set(region_margin) - set(scenario.operating_region))
    if unknown:
        raise ValueError(
            f"region_margin names '{unknown[0]}', which is not in the scenario's operating_region"
            f" (names: {sorted(scenario.operating_region)})"
        )
    region: dict[str, tuple[float, float]] = {}
    for name, (lower, upper) in scenario.operating_region.items():
        shrink = float(region_margin.get(name, 0.0))
        if not (np.isfinite(shrink) and shrink >= 0.0):
            raise ValueError(f"region_margin['{name}'] must be a finite number >= 0, got {shrink}")
        if lower + shrink > upper - shrink:
            raise MarginError(
                f"operating region of '{name}' [{lower:g}, {upper:g}] is empty after shrinking by"
                f" region_margin = {shrink:g}; use a smaller margin"
            )
        region[name] = (lower + shrink, upper - shrink)
    states, inputs = scenario.state_names, scenario.input_names
    state_part = [(states.index(k), lo, hi) for k, (lo, hi) in region.items() if k in states]
    input_part = [(inputs.index(k), lo, hi) for k, (lo, hi) in region.items() if k in inputs]
    goal_part = []
    for name, (lower, upper) in scenario.goal_bounds.items():
        shrink = float((goal_margin or {}).get(name, 0.0))
        if lower + shrink > upper - shrink:
            raise MarginError(
                f"Goal's bound on '{name}' [{lower:g}, {upper:g}] is empty after shrinking by the"
                f" tube's extent {shrink:g}; widen the bound or use a smaller clearance"
            )
        goal_part.append((states.index(name), lower + shrink, upper - shrink))

    goal_shrink = d + eps_g
    goal_region = geometry.shrink(scenario.goal, goal_shrink)
    if goal_region.is_empty:
        raise MarginError(
            f"Goal shrunk by d + eps_g = {goal_shrink:g} (d = {d:g}, the tube's position extent)"
            " is empty; use a smaller clearance or eps_g, or a larger Goal"
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
        region=region,
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
    )
