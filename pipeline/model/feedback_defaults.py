"""The feedback block as the stages read it: the file's fields, the rest filled in.

A field the file's ``feedback`` sets is used as given. The others: ``reference_state`` is the
centre of Init clipped into the operating region, ``reference_input`` the centre of the input
bounds clipped into it, the weights all 1, the rate ``DEFAULT_RATE``. ``tune`` is the file's, or
true unless all five design fields are set (``feedback: auto`` and an absent block set none);
with it the feedback stage searches over the fields left out and narrows the operating region
(``pipeline.numerics.tube.feedback_search``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pipeline.model.schema import DEFAULT_RATE, FEEDBACK_DESIGN, FeedbackSpec, ScenarioSpec


def resolve_feedback(
    spec: ScenarioSpec, states: Sequence[str], inputs: Sequence[str]
) -> FeedbackSpec:
    """The resolved ``FeedbackSpec`` of the scenario file ``spec`` (module docstring)."""
    block, region = spec.feedback, spec.operating_region

    def centre(name: str, lower: float, upper: float) -> float:
        if name in region:
            lower, upper = max(lower, region[name][0]), min(upper, region[name][1])
            if lower > upper:  # disjoint: the region's nearest edge
                return float(region[name][0] if upper < region[name][0] else region[name][1])
        return (lower + upper) / 2

    given = tuple(name for name in FEEDBACK_DESIGN if getattr(block, name) is not None)
    defaults: dict[str, Any] = {
        "reference_state": [centre(s, *spec.init[s]) for s in states],
        "reference_input": [centre(u, *spec.input_bounds[u]) for u in inputs],
        "state_weights": [1.0] * len(states),
        "input_weights": [1.0] * len(inputs),
        "rate": DEFAULT_RATE,
    }
    values = {name: getattr(block, name) if name in given else defaults[name] for name in defaults}
    tune = block.tune if block.tune is not None else len(given) < len(FEEDBACK_DESIGN)
    return FeedbackSpec(**values, tune=tune, given=given)
