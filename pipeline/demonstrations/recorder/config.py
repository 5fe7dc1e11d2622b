"""The recorder's stick and keyboard mapping: ``scenarios/NAME/recorder.yaml`` (optional).

Each input ``u_i`` is driven by one stick axis ``a`` in ``[-1, 1]`` and, as a fallback, two keys.
After the dead zone ``z`` the stick's deflection is ``d = sign(a) (|a| - z) / (1 - z)`` (0 when
``|a| <= z``; ``invert`` flips its sign); an ``increase`` key held adds ``key_deflection``, a
``decrease`` key subtracts it (stick and keys add, clipped to ``[-1, 1]``). The deflection
moves the input from ``centre`` towards the ends of ``range`` (default: the input bounds;
``centre`` defaults to 0 when it lies strictly inside the range, else to its middle), piecewise
linearly so both ends are reachable::

    u = centre + d (high - centre)   for d >= 0
    u = centre + d (centre - low)    for d <  0

The input sampled at ``k Ts`` is held on ``[k Ts, (k+1) Ts)``, as the pipeline assumes (§IV-A).
Without a ``recorder.yaml`` input ``i`` reads stick axis ``i``, the first input the keys
right/D (+) and left/A (-), the second up/W (+) and down/S (-).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydantic
import yaml
from pydantic import BaseModel, ConfigDict, Field

from pipeline.io.errors import ScenarioError
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

RECORDER_FILE = "recorder.yaml"
DEFAULT_DEAD_ZONE = 0.05
# (increase, decrease) keys of the first two inputs when no recorder.yaml maps them.
DEFAULT_KEYS = ((("right", "d"), ("left", "a")), (("up", "w"), ("down", "s")))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class KeysSpec(_Strict):
    increase: list[str] = Field(default_factory=list, description="pygame key names")
    decrease: list[str] = Field(default_factory=list, description="pygame key names")


class InputMappingSpec(_Strict):
    axis: int | None = Field(default=None, ge=0, description="joystick axis number")
    invert: bool = False
    centre: float | None = Field(default=None, description="input with the stick at rest")
    range: tuple[float, float] | None = Field(default=None, description="[low, high] at full")
    keys: KeysSpec = Field(default_factory=KeysSpec)
    key_deflection: float = Field(default=1.0, gt=0.0, le=1.0)


class RecorderSpec(_Strict):
    dead_zone: float = Field(default=DEFAULT_DEAD_ZONE, ge=0.0, lt=1.0)
    angle_state: str | None = Field(default=None, description="state drawn as orientation")
    goal_margin: float = Field(default=0.0, ge=0.0, description="end this far inside Goal")
    max_duration: float = Field(default=120.0, gt=0.0, description="(s) give up after this")
    countdown: float = Field(default=3.0, ge=0.0, description="(s) before the flight starts")
    inputs: dict[str, InputMappingSpec] = Field(default_factory=dict)


@dataclass(frozen=True)
class InputMapping:
    """How one input is flown: stick ``axis`` (or None), keys, and the deflection-to-input map."""

    name: str
    axis: int | None
    invert: bool
    centre: float
    low: float
    high: float
    increase_keys: tuple[str, ...]
    decrease_keys: tuple[str, ...]
    key_deflection: float

    def value(self, d: float) -> float:
        """The input for deflection ``d`` in ``[-1, 1]`` (after the dead zone and ``invert``)."""
        d = float(np.clip(d, -1.0, 1.0))
        if d >= 0.0:
            return self.centre + d * (self.high - self.centre)
        return self.centre + d * (self.centre - self.low)


@dataclass(frozen=True)
class RecorderConfig:
    """The recorder's settings for one scenario (see the module docstring)."""

    inputs: tuple[InputMapping, ...]  # (m,) in the scenario's input order
    dead_zone: float
    angle_index: int | None  # state drawn as the vehicle's orientation, if any
    goal_margin: float  # (m) the flight ends valid this far inside the Goal polygon
    max_duration: float  # (s)
    countdown: float  # (s)
    source: Path | None  # the recorder.yaml read, if any

    @property
    def keys(self) -> frozenset[str]:
        """Every key name the mapping uses."""
        return frozenset(
            k for mapping in self.inputs for k in (*mapping.increase_keys, *mapping.decrease_keys)
        )

    def deflections(self, axes: Mapping[int, float], pressed: Collection[str]) -> FloatArray:
        """Deflections ``(m,)`` in ``[-1, 1]`` from stick ``axes`` (number -> value) and keys."""
        z = self.dead_zone
        d = np.zeros(len(self.inputs))
        for i, mapping in enumerate(self.inputs):
            a = float(axes.get(mapping.axis, 0.0)) if mapping.axis is not None else 0.0
            stick = 0.0 if abs(a) <= z else np.sign(a) * (min(abs(a), 1.0) - z) / (1.0 - z)
            stick = -stick if mapping.invert else stick
            keys = any(k in pressed for k in mapping.increase_keys) - any(
                k in pressed for k in mapping.decrease_keys
            )
            d[i] = np.clip(stick + keys * mapping.key_deflection, -1.0, 1.0)
        return d

    def inputs_from(self, axes: Mapping[int, float], pressed: Collection[str]) -> FloatArray:
        """The input sample ``u (m,)`` for the current stick ``axes`` and ``pressed`` keys."""
        d = self.deflections(axes, pressed)
        return np.array([mapping.value(di) for mapping, di in zip(self.inputs, d, strict=True)])

    def axis_value(self, i: int, u: float) -> float:
        """The stick position of input ``i``'s axis that gives ``u`` (inverse of the mapping;
        for scripted sticks and tests). Inside the dead zone only ``centre`` is reachable."""
        mapping = self.inputs[i]
        if u >= mapping.centre:
            span = mapping.high - mapping.centre
            d = 0.0 if span == 0 else (u - mapping.centre) / span
        else:
            d = (u - mapping.centre) / (mapping.centre - mapping.low)
        d = -d if mapping.invert else d
        if d == 0.0:
            return 0.0
        return float(np.sign(d) * (self.dead_zone + abs(d) * (1.0 - self.dead_zone)))


def _default_centre(low: float, high: float) -> float:
    return 0.0 if low < 0.0 < high else 0.5 * (low + high)


def load_recorder_config(scenario: Scenario) -> RecorderConfig:
    """The mapping of ``scenario``: its folder's ``recorder.yaml`` if present, else the default."""
    path = scenario.path.parent / RECORDER_FILE
    spec = RecorderSpec()
    if path.is_file():
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
            spec = RecorderSpec.model_validate(data)
        except yaml.YAMLError as error:
            raise ScenarioError(f"YAML syntax error: {error}", file=path) from None
        except pydantic.ValidationError as error:
            first = error.errors()[0]
            raise ScenarioError(
                "invalid recorder setting",
                file=path,
                field=".".join(str(p) for p in first["loc"]) or "(top level)",
                found=first.get("input"),
                expected=first["msg"],
            ) from None
    return _build(scenario, spec, path if path.is_file() else None)


def _build(scenario: Scenario, spec: RecorderSpec, path: Path | None) -> RecorderConfig:
    where = path if path is not None else scenario.path.parent / RECORDER_FILE
    names: Sequence[str] = scenario.input_names
    unknown = [name for name in spec.inputs if name not in names]
    if unknown:
        raise ScenarioError(
            f"unknown input '{unknown[0]}'", file=where, field="inputs", expected=f"{list(names)}"
        )
    if spec.angle_state is not None and spec.angle_state not in scenario.state_names:
        raise ScenarioError(
            "unknown state",
            file=where,
            field="angle_state",
            found=spec.angle_state,
            expected=f"one of {list(scenario.state_names)}",
        )
    mappings = []
    for i, name in enumerate(names):
        lower, upper = float(scenario.input_lower[i]), float(scenario.input_upper[i])
        given = spec.inputs.get(name)
        if given is None:  # the default: axis i, arrows/WASD for the first two inputs
            keys = DEFAULT_KEYS[i] if i < len(DEFAULT_KEYS) else ((), ())
            given = InputMappingSpec(
                axis=i, keys=KeysSpec(increase=list(keys[0]), decrease=list(keys[1]))
            )
        low, high = given.range if given.range is not None else (lower, upper)
        centre = given.centre if given.centre is not None else _default_centre(low, high)
        if not lower <= low <= centre <= high <= upper:
            raise ScenarioError(
                "stick range outside the input bounds or centre outside the range",
                file=where,
                field=f"inputs.{name}",
                found={"range": [low, high], "centre": centre},
                expected=f"input_bounds.{name}[0] = {lower:g} <= range[0] <= centre <= range[1]"
                f" <= {upper:g}",
            )
        mappings.append(
            InputMapping(
                name=name,
                axis=given.axis,
                invert=given.invert,
                centre=centre,
                low=low,
                high=high,
                increase_keys=tuple(k.lower() for k in given.keys.increase),
                decrease_keys=tuple(k.lower() for k in given.keys.decrease),
                key_deflection=given.key_deflection,
            )
        )
    angle = None if spec.angle_state is None else scenario.state_names.index(spec.angle_state)
    return RecorderConfig(
        inputs=tuple(mappings),
        dead_zone=spec.dead_zone,
        angle_index=angle,
        goal_margin=spec.goal_margin,
        max_duration=spec.max_duration,
        countdown=spec.countdown,
        source=path,
    )
