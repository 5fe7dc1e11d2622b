"""A certificate's footprint on the constraints: the margins the nominal keeps, and their check.

``ConstraintMargins`` says how far the tube around a nominal reaches (paper §IV-A: the
constraints the optimizer meets are the real ones shrunk by it): a constant certificate's tube of
radius ``r`` (``of_tube``: constant extents) or a funnel's (``of_funnel``: extents per sample
interval, ``pipeline.numerics.optimize.margins``). ``verify_within`` checks an optimized nominal
against them in continuous time (``pipeline.numerics.verify.nominal``), independently of the cost.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.funnel.check import Funnel
from pipeline.numerics.optimize.margins import MarginProfile, funnel_margins
from pipeline.numerics.optimize.problem import Problem
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.verify.nominal import Verification, verify_nominal


@dataclass(frozen=True, kw_only=True)
class ConstraintMargins:
    """The tube's footprint at the required radius, from the feedback stage.

    Attributes:
      input_margin: (m,) how much the tube's feedback may add to ``u_ref``, per input.
      region_margin: state/input name -> how far the tube extends along it.
      gain: (m, n) the feedback gain, which also stabilises the shooting
        (``pipeline.numerics.optimize.shooting``).
      clearance: the tube's position extent, kept from Unsafe and Goal's boundary (default: the
        scenario's ``d``; larger when coverage of Init needs a radius above ``r_d``).
      goal_margin: state name -> how far the tube extends along it (shrinks Goal's extra bounds).
      profile: margins that vary along the trajectory (a funnel's extents per sample interval,
        ``pipeline.numerics.optimize.margins``), added to the constant ones above; None: none.
      region: name -> (lower, upper), the box the nominal stays in (None: the scenario's
        operating region and ``state_bounds``, ``nominal_box``; a funnel's: the scenario's
        ``state_bounds``).
      state_extent: state name -> how far the tube extends along it (a constant tube's: shrinks
        the scenario's ``state_bounds`` when ``region`` is None).
    """

    input_margin: FloatArray
    region_margin: Mapping[str, float]
    gain: FloatArray
    clearance: float | None = None
    goal_margin: Mapping[str, float] = field(default_factory=dict)
    profile: MarginProfile | None = None
    region: Mapping[str, tuple[float, float]] | None = None
    state_extent: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def of_tube(cls, tube: Tube, radius: float) -> ConstraintMargins:
        """The footprint of the feedback's tube of P-norm radius ``radius``."""
        extent = dict(zip(tube.state_names, map(float, tube.state_extent(radius)), strict=True))
        return cls(
            input_margin=tube.input_margin(radius),
            region_margin=tube.region_extent(radius),
            gain=tube.K,
            clearance=tube.position_extent(radius),
            goal_margin=extent,
            state_extent=dict(extent),
        )

    def nominal_box(
        self, scenario: Scenario
    ) -> tuple[Mapping[str, tuple[float, float]] | None, dict[str, float]]:
        """``(region, shrink)``: the box the nominal stays in (None: the operating region) and
        the tube's extent along each of its names. ``region`` when set (a funnel's); else the
        operating region intersected with the scenario's ``state_bounds``, each state bound
        shrunk by ``state_extent``: a nominal kept that far inside holds its constant tube in
        the physical envelope (None, ``region_margin``, when there are no state bounds)."""
        if self.region is not None or not scenario.state_bounds:
            return self.region, dict(self.region_margin)
        box, shrink = dict(scenario.operating_region), dict(self.region_margin)
        for name, (lower, upper) in scenario.state_bounds.items():
            low, high = box.get(name, (lower, upper))
            box[name] = (max(low, lower), min(high, upper))
            shrink[name] = max(shrink.get(name, 0.0), self.state_extent.get(name, 0.0))
        return box, shrink

    @classmethod
    def of_funnel(
        cls,
        scenario: Scenario,
        funnel: Funnel,
        *,
        clearance: float = 0.0,
        level: float | None = None,
        at_least: float = 0.0,
    ) -> ConstraintMargins:
        """The footprint of ``funnel``'s tube at ``level`` (default its rho): its extents per
        sample interval (``funnel_margins``), no operating region (the nominal stays in the
        scenario's ``state_bounds`` shrunk by the tube), Unsafe kept ``clearance`` beyond the
        tube and at least ``at_least`` from the nominal (the scenario's d: the nominal keeps the
        required clearance even where the funnel is thinner); the shooting is stabilised by the
        mean of the funnel's gains ``K[k]``."""
        for name, value in (("clearance", clearance), ("at_least", at_least)):
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        profile = funnel_margins(scenario, funnel, level=level)
        profile = dataclasses.replace(
            profile, clearance=np.maximum(profile.clearance, at_least - clearance)
        )
        return cls(
            input_margin=np.zeros(scenario.m),
            region_margin={},
            gain=funnel.K.mean(axis=0),
            clearance=clearance,
            profile=profile,
            region=dict(scenario.state_bounds),
        )


def verify_within(
    scenario: Scenario, problem: Problem, u: FloatArray, margins: ConstraintMargins
) -> Verification:
    """``pipeline.numerics.verify.nominal`` of ``u (N, m)`` against ``problem``'s margins on its
    horizon (without the descent's eps_r: the region shrunk by the tube's extents only)."""
    region, region_margin = margins.nominal_box(scenario)
    box = scenario.operating_region if region is None else region
    on = margins.profile.on_grid(problem.N) if margins.profile is not None else None
    extents: dict[str, FloatArray | float] = {key: 0.0 for key in box}
    final = np.zeros(scenario.n)
    if on is not None:
        extents |= {k: on.state[:, i] for i, k in enumerate(scenario.state_names) if k in box}
        extents |= {k: on.input[:, j] for j, k in enumerate(scenario.input_names) if k in box}
        final = on.final_state
    d = scenario.clearance if margins.clearance is None else margins.clearance
    shrink = {key: region_margin.get(key, 0.0) + extents[key] for key in box}
    goal_shrink = {
        key: margins.goal_margin.get(key, 0.0) + final[scenario.state_names.index(key)]
        for key in scenario.goal_bounds
    }
    return verify_nominal(
        scenario,
        problem.x0,
        u,
        input_lower=problem.input_lower,
        input_upper=problem.input_upper,
        region={k: (lo + shrink[k], hi - shrink[k]) for k, (lo, hi) in box.items()},
        clearance=d + (on.clearance if on is not None else 0.0),
        goal_clearance=d + (on.final_clearance if on is not None else 0.0),
        goal_bounds={
            k: (lo + goal_shrink[k], hi - goal_shrink[k])
            for k, (lo, hi) in scenario.goal_bounds.items()
        },
    )
