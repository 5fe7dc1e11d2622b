"""Continuous-time verification of a nominal trajectory, independent of the optimisation cost.

The trajectory is re-simulated on a fine RK4 grid (spacing ``h``). Between grid points the
position moves at most ``v_max h / 2`` from the nearer grid point, and distance to a set is
1-Lipschitz, so ``min_grid(dist) - v_max h / 2`` is a lower bound on the clearance over the
whole of ``[0, T]``; the operating-region states are bounded the same way with their rates.
Margins may vary along the trajectory (``pipeline.numerics.optimize.margins``): a clearance, input
bound or region bound per sample interval ``(N,)`` is checked on that interval's fine grid points
(each fine step lies inside one interval, so the bound between grid points is the same).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import simulate

VERIFY_SUBSTEPS = 16


@dataclass(frozen=True, kw_only=True)
class Verification:
    """What was checked on ``[0, T]``, as continuous-time lower bounds on margins.

    Attributes:
      clearance: Unsafe name -> lower bound on the distance to that set over ``[0, T]``.
      required_clearance: the largest distance required from Unsafe over ``[0, T]``.
      goal_margin: distance of the final position inside Goal shrunk by ``d`` (< 0: outside).
      input_margin: smallest distance of an input to its (shrunk) bound (< 0: violated).
      region_margin: smallest distance of a state/input to its operating-region bound.
    """

    clearance: Mapping[str, float]
    goal_margin: float
    input_margin: float
    region_margin: float
    required_clearance: float
    failures: tuple[str, ...] = field(default=())

    @property
    def passed(self) -> bool:
        return not self.failures

    @property
    def message(self) -> str:
        return "verified in continuous time" if self.passed else "; ".join(self.failures)


def verify_nominal(
    scenario: Scenario,
    x0: FloatArray,
    us: FloatArray,
    *,
    input_lower: FloatArray,
    input_upper: FloatArray,
    region: Mapping[str, tuple[float | FloatArray, float | FloatArray]],
    clearance: float | FloatArray | None = None,
    goal_bounds: Mapping[str, tuple[float, float]] | None = None,
    goal_clearance: float | None = None,
    substeps: int = VERIFY_SUBSTEPS,
) -> Verification:
    """Check ``x0 (n,)``, ``us (N, m)``: clearance ``>= d`` from every Unsafe set, final position
    in Goal shrunk by ``d`` (and Goal's extra bounds), inputs in ``[input_lower, input_upper]``
    and states/inputs in the ``region`` box, all on ``[0, T]`` in continuous time. ``d`` is
    ``clearance``, by default the scenario's; ``goal_bounds`` replaces Goal's extra bounds (e.g.
    shrunk by the tube's extent).

    Margins along the trajectory: ``clearance`` may be ``(N,)``, one per sample interval (then
    ``goal_clearance``, Goal's shrink, is required), ``input_lower``/``input_upper`` ``(N, m)``
    and each region bound ``(N,)``."""
    N = len(us)
    d_k = np.broadcast_to(
        np.asarray(scenario.clearance if clearance is None else clearance, float), (N,)
    )
    if goal_clearance is None:
        if clearance is not None and np.ndim(clearance) != 0:
            raise ValueError("verify_nominal: a clearance per interval needs goal_clearance")
        goal_clearance = float(d_k[0])
    d = float(d_k.max())
    trajectory = simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=substeps)
    xs = trajectory.dense_xs
    h = scenario.Ts / substeps
    failures: list[str] = []
    if not np.all(np.isfinite(xs)):
        k = int(np.argmax(~np.all(np.isfinite(xs), axis=-1)))
        return Verification(
            clearance={},
            goal_margin=-np.inf,
            input_margin=-np.inf,
            region_margin=-np.inf,
            required_clearance=d,
            failures=(f"non-finite state at t = {trajectory.dense_ts[k]:.2f} s",),
        )
    xdot = scenario.dynamics.f(xs[:-1], np.repeat(us, substeps, axis=0))
    positions = scenario.positions(xs)
    speed = float(np.max(np.linalg.norm(scenario.positions(xdot), axis=-1)))
    clearances: dict[str, float] = {}
    for name, unsafe in scenario.unsafe.items():
        distances = geometry.distance(positions, unsafe)
        low = _per_interval(distances, substeps, np.minimum) - speed * h / 2  # (N,)
        clearances[name] = float(low.min())
        short = low - d_k
        if short.min() < 0:
            k = int(np.argmin(short))
            failures.append(
                f"clearance to '{name}' is {low[k]:.3f} < d = {d_k[k]:g} "
                f"on [{k * scenario.Ts:.2f}, {(k + 1) * scenario.Ts:.2f}] s"
            )
    mod_goal = geometry.shrink(scenario.goal, goal_clearance)
    final = positions[-1]
    inside = bool(geometry.contains(mod_goal, final))
    to_boundary = float(geometry.boundary_distance(final, mod_goal)) if not mod_goal.is_empty else 0
    goal_margin = to_boundary if inside else -to_boundary
    bounds = scenario.goal_bounds if goal_bounds is None else goal_bounds
    for name, (lower, upper) in bounds.items():
        value = xs[-1, scenario.state_names.index(name)]
        goal_margin = min(goal_margin, value - lower, upper - value)
    if goal_margin < 0:
        failures.append(
            f"final position ({final[0]:.3f}, {final[1]:.3f}) is not in Goal "
            f"shrunk by {goal_clearance:g} (margin {goal_margin:.3f})"
        )
    input_margin = float(np.min(np.minimum(us - input_lower, input_upper - us)))
    if input_margin < 0:
        failures.append(f"input outside its bounds by {-input_margin:.3g}")
    region_margin = float(np.inf)
    for name, (floor, ceiling) in region.items():  # numbers, or (N,) per interval
        if name in scenario.state_names:
            i = scenario.state_names.index(name)
            slack = float(np.max(np.abs(xdot[:, i]))) * h / 2
            low = _per_interval(xs[:, i], substeps, np.minimum)
            high = _per_interval(xs[:, i], substeps, np.maximum)
        else:
            low = high = us[:, scenario.input_names.index(name)]
            slack = 0.0
        room = np.minimum(low - floor, ceiling - high) - slack  # (N,)
        margin = float(np.min(room))
        region_margin = min(region_margin, margin)
        if margin < 0:
            k = int(np.argmin(room))
            lo, hi = (float(np.broadcast_to(bound, (N,))[k]) for bound in (floor, ceiling))
            failures.append(
                f"'{name}' leaves the region [{lo:.3g}, {hi:.3g}] near t = {k * scenario.Ts:.2f} s"
            )
    return Verification(
        clearance=clearances,
        goal_margin=goal_margin,
        input_margin=input_margin,
        region_margin=float(region_margin),
        required_clearance=d,
        failures=tuple(failures),
    )


def _per_interval(values: FloatArray, substeps: int, reduce: np.ufunc) -> FloatArray:
    """(N,) ``reduce`` (minimum or maximum) of fine-grid ``values (N s + 1,)`` over each sample
    interval's ``s + 1`` points (both ends)."""
    inner = values[:-1].reshape(-1, substeps)  # (N, s): the interval's first s points
    return reduce(reduce.reduce(inner, axis=1), values[substeps::substeps])
