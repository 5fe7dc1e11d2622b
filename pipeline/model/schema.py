"""The scenario file's schema (pydantic); ``python -m pipeline schema`` prints it as JSON Schema.

Field names here are the YAML keys. Cross-field rules (names that must match, polygons that
must be valid, sets that must not overlap) are checked in ``pipeline.model.scenario``.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Sequence
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    WithJsonSchema,
)

# A number as YAML writes one: an int or a float, never a boolean or quoted text (pydantic's lax
# mode would read `clearance: true` as 1.0 and `rate: "0.5"` as 0.5).
Number = Annotated[float, Strict()]
PositiveNumber = Annotated[float, Strict(), Field(gt=0)]
NonNegativeNumber = Annotated[float, Strict(), Field(ge=0)]


def _ordered(interval: tuple[float, float]) -> tuple[float, float]:
    lower, upper = interval
    if lower > upper:
        raise ValueError(f"lower bound {lower} is above upper bound {upper}")
    return interval


def _proper(interval: tuple[float, float]) -> tuple[float, float]:
    lower, upper = interval
    if not lower < upper:
        raise ValueError("an interval [lower, upper] with lower < upper (room for the state)")
    return interval


def _number_as_text(value: object) -> object:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return str(value)
    return value


def _auto_or_mapping(schema: dict[str, Any]) -> None:
    """The JSON Schema of ``feedback``: ``"auto"`` or the block."""
    schema["anyOf"] = [{"const": "auto"}, {"$ref": schema.pop("$ref")}]


Interval = Annotated[tuple[Number, Number], AfterValidator(_ordered)]
# A bound on a physical quantity: a proper interval, with room inside (lower < upper).
ProperInterval = Annotated[tuple[Number, Number], AfterValidator(_proper)]
Vertex = tuple[Number, Number]
Name = Annotated[str, Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$")]
# A dynamics expression: text in the grammar of ``pipeline.model.expressions``; a bare number is
# accepted.
Expression = Annotated[
    str,
    BeforeValidator(_number_as_text),
    WithJsonSchema({"anyOf": [{"type": "string"}, {"type": "number"}]}),
]


# What certifies the controller: a strategy for each in ``stages.certificates``.
CertificateName = Literal["constant", "funnel"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class GoalSpec(_Strict):
    """Goal: a polygon over the position coordinates, optionally with bounds on other states."""

    polygon: list[Vertex] = Field(min_length=3, description="vertices [[x, y], ...] in order")
    bounds: dict[str, Interval] = Field(
        default_factory=dict, description="extra bounds on named states at the final time"
    )


DEFAULT_RATE = 0.5  # 1/s: an unset feedback.rate is tuned from here down
FEEDBACK_DESIGN = ("reference_state", "reference_input", "state_weights", "input_weights", "rate")


class FeedbackSpec(_Strict):
    """The robustness feedback ``u = u_ref + K (x - x_ref)``'s design data, resolved: every field
    set (``pipeline.model.scenario`` fills in what the file's ``feedback`` leaves out).

    ``tune``: the feedback stage searches (``pipeline.numerics.tube.feedback_search``) over the
    operating region (narrowed inside the file's, around what the demos use) and over the
    fields not in ``given``; ``given``: the fields the file sets, used as given."""

    reference_state: list[Number] = Field(description="operating point x* for the LQR design (n)")
    reference_input: list[Number] = Field(description="operating point u* for the LQR design (m)")
    state_weights: list[PositiveNumber] = Field(description="diagonal of the LQR Q (n)")
    input_weights: list[PositiveNumber] = Field(description="diagonal of the LQR R (m)")
    rate: PositiveNumber = Field(description="contraction rate lambda to certify (1/s)")
    tune: bool = False
    given: tuple[str, ...] = FEEDBACK_DESIGN


class FeedbackFileSpec(_Strict):
    """The file's ``feedback`` block: each field set is used as given; with ``tune`` (the
    default unless all five design fields are set) the feedback stage searches over the ones
    left out and narrows the operating region around the demos; ``feedback: auto`` (or no
    ``feedback``) sets none."""

    reference_state: list[Number] | None = Field(
        default=None,
        description="operating point x* for the LQR design (n); default: the centre of Init, "
        "the operating region's centre for the states it bounds",
    )
    reference_input: list[Number] | None = Field(
        default=None,
        description="operating point u* for the LQR design (m); default: the centre of the "
        "input bounds within the operating region",
    )
    state_weights: list[PositiveNumber] | None = Field(
        default=None, description="diagonal of the LQR Q (n); default: all 1 (tuned)"
    )
    input_weights: list[PositiveNumber] | None = Field(
        default=None, description="diagonal of the LQR R (m); default: all 1 (tuned)"
    )
    rate: PositiveNumber | None = Field(
        default=None,
        description="contraction rate lambda to certify (1/s); default: tuned (from "
        f"{DEFAULT_RATE:g} 1/s down)",
    )
    tune: bool | None = Field(
        default=None,
        description="search over the operating region and the fields left out, keeping the "
        "certified design whose tubes best cover Init (default: true unless all five design "
        "fields are set); false: use the defaults of the fields left out, as given",
    )


def _feedback_auto(value: object) -> object:
    if value is None or value == "auto":
        return {}
    if isinstance(value, str):
        raise ValueError(f"'auto' or a mapping of ({', '.join(FeedbackFileSpec.model_fields)})")
    return value


class StressSpec(_Strict):
    """Perturbations for the stress test (``--stress``), never part of the certificate."""

    disturbance: dict[str, PositiveNumber] = Field(
        default_factory=dict,
        description="bound on a constant term added to the named state's derivative, drawn "
        "uniformly per run (e.g. wind)",
    )
    measurement_noise: dict[str, PositiveNumber] = Field(
        default_factory=dict, description="standard deviation of noise on the measured state"
    )


class UncertaintySpec(_Strict):
    """What every certificate must hold against (``pipeline.model.uncertainty``)."""

    disturbance: dict[str, NonNegativeNumber] = Field(
        default_factory=dict,
        description="bound on an additive term in the named state's derivative, |w| <= bound, "
        "at every instant (any signal inside the box, e.g. gusts, in the state's unit per s)",
    )
    disturbance_ellipsoid: dict[str, PositiveNumber] = Field(
        default_factory=dict,
        description="semi-axes a of an ellipsoid bounding an additive term in the named states' "
        "derivatives, sum (w_i / a_i)^2 <= 1, at every instant (e.g. a gust of any direction), "
        "added to disturbance's box; the certificates hold its bounding box |w_i| <= a_i",
    )
    parameters: dict[str, Interval] = Field(
        default_factory=dict,
        description="interval [lower, upper] of a parameter whose true value is unknown (held "
        "constant during a flight); it must contain the value under parameters:",
    )
    measurement: dict[str, NonNegativeNumber] = Field(
        default_factory=dict,
        description="bound on the error of the named state as the feedback measures it, "
        "|x_meas - x| <= bound, at every instant (any signal inside the box, in the state's unit)",
    )


class DemoSpec(_Strict):
    """One demonstration: a CSV of held inputs and the initial state it was flown from."""

    file: str = Field(description="CSV path relative to the scenario folder")
    x0: list[Number] = Field(description="initial state (n), inside Init")


class ScenarioSpec(_Strict):
    """A scenario file, ``scenarios/NAME/scenario.yaml``."""

    name: str = Field(pattern=r"^[A-Za-z0-9_\-]+$")
    description: str = ""
    states: list[Name] = Field(min_length=1, description="state names, in order")
    inputs: list[Name] = Field(min_length=1, description="input names, in order")
    parameters: dict[Name, Number] = Field(default_factory=dict)
    dynamics: dict[str, Expression] = Field(description="time derivative of every state, as text")
    position: tuple[str, str] = Field(description="the two states that Unsafe and Goal are over")
    sampling_time: PositiveNumber = Field(description="Ts: inputs are held for Ts seconds")
    input_bounds: dict[str, Interval]
    unsafe: dict[str, Annotated[list[Vertex], Field(min_length=3)]] = Field(
        description="named Unsafe polygons over position"
    )
    goal: GoalSpec
    init: dict[str, Interval] = Field(description="Init box over every state")
    clearance: PositiveNumber = Field(description="required distance d from Unsafe (m)")
    operating_region: dict[str, Interval] = Field(
        description="box over the states and inputs the Jacobian depends on"
    )
    feedback: Annotated[FeedbackFileSpec, BeforeValidator(_feedback_auto)] = Field(
        default_factory=FeedbackFileSpec,
        description="the robustness feedback: 'auto' (the default) designs and tunes it; a "
        "mapping sets some or all of its fields (each set field is used as given)",
        json_schema_extra=_auto_or_mapping,
    )
    terminal: Literal["reach", "hold"] = Field(
        default="reach",
        description="after T: 'reach' (the paper's Goal; a terminal controller is emitted when "
        "the end tubes fit, else the law stops at T) or 'hold' (the run certifies only with a "
        "terminal controller holding it in Goal for all time; bound the speeds at T in "
        "goal.bounds so that it can)",
    )
    certificate: CertificateName = Field(
        default="constant",
        description="'constant' (one metric P and gain K over operating_region, the paper's "
        "certificate) or 'funnel' (per-trajectory time-varying K[k], P[k] over each tube)",
    )
    feedback_period: NonNegativeNumber = Field(
        default=0.0,
        description="h (s): the vehicle's control period, the feedback law is evaluated every h "
        "seconds and held in between (zero-order hold), and every certificate, the controller "
        "file and the Monte Carlo are for that law; 0 (the default): continuous feedback. h "
        "must divide sampling_time and be at least 1e-4 s (MIN_FEEDBACK_PERIOD); "
        "--feedback-period overrides it",
    )
    optimizer: Literal["gd", "lbfgs"] = Field(
        default="gd",
        description="how the nominal trajectories are optimized: 'gd' (the paper's gradient "
        "descent, §III-B) or 'lbfgs' (L-BFGS-B on the same cost); --method overrides it",
    )
    state_bounds: dict[str, ProperInterval] = Field(
        default_factory=dict,
        description="the physical envelope of the states (e.g. a small-angle limit), apart from "
        "any certificate region, each [lower, upper] with lower < upper and holding Init: every "
        "certificate keeps its tubes inside it, and the uncertified comparison uses it",
    )
    units: dict[str, str] = Field(
        default_factory=dict,
        description="optional unit of a state or input (e.g. force: N), for reports and the HUD",
    )
    labels: dict[str, str] = Field(
        default_factory=dict,
        description="optional human name of a state or input (e.g. force: thrust)",
    )
    uncertainty: UncertaintySpec = Field(
        default_factory=UncertaintySpec,
        description="declared disturbance, parameter and measurement bounds: every certificate "
        "holds for all of them (omitted: the exact model)",
    )
    stress: StressSpec | None = Field(default=None, description="optional stress-test settings")
    demos: list[DemoSpec] = Field(default_factory=list)


def json_schema() -> dict[str, object]:
    """The JSON Schema of the scenario file."""
    return ScenarioSpec.model_json_schema()


def field_names(location: Sequence[str | int]) -> list[str]:
    """The YAML keys allowed in the mapping at ``location`` (a pydantic error location such as
    ``("feedback",)`` or ``("demos", 0)``); empty where any key is allowed."""
    model: object = ScenarioSpec
    for part in location:
        model = _item_type(model, part)
    if typing.get_origin(model) in (typing.Union, types.UnionType):
        model = next((a for a in typing.get_args(model) if a is not type(None)), None)
    if isinstance(model, type) and issubclass(model, BaseModel):
        return list(model.model_fields)
    return []


def _item_type(annotation: object, part: str | int) -> object:
    """The type found at ``part`` (a field name, list index or dict key) inside ``annotation``."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        field = annotation.model_fields.get(str(part))
        return None if field is None else field.annotation
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Annotated:
        return _item_type(args[0], part)
    if origin in (typing.Union, types.UnionType):
        models = [a for a in args if isinstance(a, type) and issubclass(a, BaseModel)]
        return _item_type(models[0], part) if models else None
    if origin in (list, tuple, dict) and args:
        return args[-1]
    return None
