"""A planar double integrator scenario (its YAML, with goal, region and rate to fill in) and a
controller for it emitted from four starts held at rest, for the stage tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pipeline.model.scenario import Scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS
from stages.controller import ControllerResult, emit_controller
from stages.feedback import design_feedback
from stages.radius import robustness_radius

# Four starts in Init, each held at rest for ten samples (the double integrator's references).
AT_REST_STARTS = [np.array([x, y, 0.0, 0.0]) for x in (0.25, 0.75) for y in (2.25, 2.75)]

# States [X, Y, vX, vY], inputs [aX, aY]. Unsafe "wall" is the half-plane Y <= 0 (as a large
# rectangle), Goal a large box above it, Init [0, 1] x [2, 3] at rest.
DOUBLE_INTEGRATOR = """\
name: double_integrator
states: [X, Y, vX, vY]
inputs: [aX, aY]
dynamics: {X: vX, Y: vY, vX: aX, vY: aY}
position: [X, Y]
sampling_time: 0.1
input_bounds: {aX: [-100.0, 100.0], aY: [-100.0, 100.0]}
unsafe:
  wall: [[-1000, -1000], [1000, -1000], [1000, 0], [-1000, 0]]
goal:
  polygon: %(goal)s
init: {X: [0.0, 1.0], Y: [2.0, 3.0], vX: [0.0, 0.0], vY: [0.0, 0.0]}
clearance: 0.5
operating_region: %(region)s
feedback:
  reference_state: [0, 0, 0, 0]
  reference_input: [0, 0]
  state_weights: [1, 1, 1, 1]
  input_weights: [1, 1]
  rate: %(rate)s
"""


def emit_at_rest(scenario: Scenario, path: Path, **options: Any) -> ControllerResult:
    """``controller.json`` at ``path`` for ``AT_REST_STARTS`` held at rest, each with its largest
    certified radius; ``options`` go to ``emit_controller`` (e.g. ``radius_floor``)."""
    feedback = design_feedback(scenario)
    us = np.zeros((10, 2))
    radii = [
        robustness_radius(
            scenario,
            feedback.certified_tube,
            simulate(scenario.dynamics, x0, us, scenario.Ts, VERIFY_SUBSTEPS),
        ).radius
        for x0 in AT_REST_STARTS
    ]
    K, P, rate = feedback.K, feedback.P, feedback.rate
    starts, inputs = AT_REST_STARTS, [us] * len(AT_REST_STARTS)
    return emit_controller(scenario, K, P, rate, starts, inputs, radii, path, **options)
