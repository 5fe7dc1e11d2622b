"""Stage ``radius``: the robustness radius of a nominal trajectory.

The tube of P-norm radius ``r`` around ``x_ref`` is
``E(t) = {x : ||x - x_ref(t)||_P <= r e^{-lambda t}}``; the radius is the largest ``r`` for which
``E(t)`` avoids Unsafe, stays in the operating region, the ``state_bounds`` and the input bounds,
and ends in Goal, on the whole of ``[0, T]`` in continuous time. Each constraint's limit is
computed by ``pipeline.numerics.tube.radius`` (the maths is in its docstring), which the final
certificate check (stage ``certify``) uses as well.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.tube.radius import radius_limits
from pipeline.results.radius import RadiusResult as RadiusResult
from pipeline.results.stage import Stage, StageInputs


def robustness_radius(scenario: Scenario, tube: Tube, trajectory: Trajectory) -> RadiusResult:
    """The robustness radius of ``trajectory`` (one, unbatched: ``dense_xs (N s + 1, n)``,
    ``us (N, m)``) in the certified ``tube`` (``K (m, n)``, ``P (n, n)``, ``rate``,
    ``region``)."""
    found = radius_limits(scenario, tube, trajectory)
    limits = found.limits
    binding = min(limits, key=lambda key: limits[key][0])
    radius, when = limits[binding]
    position_clearance = tube.position_extent(radius)
    if radius > 0:
        message = (
            f"radius {radius:.4g} (position clearance {position_clearance:.3g}), "
            f"bound by {binding} at t = {when:.2f} s"
        )
    else:
        message = f"no tube: the nominal itself violates {binding} at t = {when:.2f} s"
    return RadiusResult(
        radius=radius,
        position_clearance=position_clearance,
        binding=binding,
        binding_time=when,
        limits={key: value[0] for key, value in limits.items()},
        nominal_clearance=found.nominal_clearance,
        success=radius > 0,
        message=message,
    )


@dataclass(frozen=True, kw_only=True)
class RadiusInputs(StageInputs):
    """What stage ``radius`` reads: the certified tube and the nominals (one radius each)."""

    scenario_fields: ClassVar = (
        "dynamics",
        "goal",
        "goal_bounds",
        "input_lower",
        "input_upper",
        "position_index",
        "state_bounds",
        "unsafe",
    )
    scenario: Scenario
    tube: Tube
    trajectories: tuple[Trajectory, ...]


def _radius_stage(inputs: RadiusInputs) -> tuple[RadiusResult, ...]:
    return tuple(
        robustness_radius(inputs.scenario, inputs.tube, trajectory)
        for trajectory in inputs.trajectories
    )


RADIUS = Stage("radius", _radius_stage, RadiusInputs, RadiusResult)
