"""A scenario as plain data, for the stages' cache keys: every value the stages can read.

``scenario_data(scenario)`` walks ``dataclasses.fields(Scenario)``, so a field added later is
keyed without further code, and turns each value into data that ``pipeline.io.artifacts``
encodes exactly (``inputs_key``):

- arrays, numbers, strings, tuples, mappings (in their order): as they are;
- ``Dynamics``: the ``sympy.srepr`` of its state and input symbols (names and assumptions) and
  of its expressions, exact to the last bit of every Float; its Jacobians, sparsity patterns
  and compiled functions are derived from these by ``Dynamics.from_expressions``;
- shapely geometries (Unsafe, Goal): their WKB, little-endian, hex (vertex coordinates as the
  float64 bits, rings and holes included);
- pydantic models (``spec``, ``feedback``): their type and declared fields, so ``spec.stress``
  and ``spec.description``, read through the spec, are keyed too;
- dataclasses (``Demo``): their type and fields;
- anything else: ``TypeError`` naming the field and the type (nothing is keyed by ``str()``).

Left out: ``LOCATIONS``, where the data was read from (the scenario and demo files' paths, the
hash of the YAML's bytes), since the parsed values are keyed and a copied scenario folder or a
comment added to the file must not recompute anything; and ``spec.demos`` (the ``demos`` field
holds each demo's parsed ``x0`` and inputs).

The key is of the ``Scenario`` object, not of its file: ``dataclasses.replace(scenario,
clearance=0.25)`` changes it, while ``spec`` (the file as parsed) still says the old clearance.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pydantic
import shapely
import sympy
from shapely.geometry.base import BaseGeometry

from pipeline.model.dynamics import Dynamics

if TYPE_CHECKING:
    from pipeline.model.scenario import Scenario

# fields naming where the data was read from, at any depth (Scenario.path, Demo.file)
LOCATIONS = frozenset({"path", "file", "source_hash"})


def scenario_data(scenario: Scenario, exclude: Collection[str] = ()) -> dict[str, Any]:
    """Field name -> plain data for every field of ``scenario`` but ``LOCATIONS`` and
    ``exclude``; a name in ``exclude`` is left out of the parsed file (``spec``) too (e.g.
    ``"description"``, ``"stress"``, ``"optimizer"``). Raises ``TypeError`` naming a field whose
    value has no exact encoding."""
    names = {f.name for f in dataclasses.fields(scenario)} | set(type(scenario.spec).model_fields)
    unknown = sorted(set(exclude) - names)
    if unknown:
        raise ValueError(f"exclude names no field of a scenario or its spec: {unknown}")
    skip = LOCATIONS | set(exclude)
    data = {}
    for field in dataclasses.fields(scenario):
        if field.name in skip:
            continue
        value = getattr(scenario, field.name)
        if field.name == "spec":
            value = _model(value, skip | {"demos"}, "spec")
        data[field.name] = plain(value, field.name)
    return data


def plain(value: Any, where: str = "value") -> Any:
    """``value`` as data that ``inputs_key`` encodes exactly (module docstring); ``where`` names
    it in the ``Unkeyable`` (a ``TypeError``) raised for a value of another type."""
    if isinstance(value, (np.ndarray, np.generic, str, int, float, Path)) or value is None:
        return value  # bool is an int
    if isinstance(value, Dynamics):
        return {
            "Dynamics": {
                "states": tuple(sympy.srepr(s) for s in value.state_symbols),
                "inputs": tuple(sympy.srepr(s) for s in value.input_symbols),
                "expressions": tuple(sympy.srepr(e) for e in value.expressions),
            }
        }
    if isinstance(value, BaseGeometry):
        return {"WKB": shapely.to_wkb(value, hex=True, byte_order=1)}
    if isinstance(value, pydantic.BaseModel):
        return _model(value, frozenset(), where)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {
            f.name: plain(getattr(value, f.name), f"{where}.{f.name}")
            for f in dataclasses.fields(value)
            if f.name not in LOCATIONS
        }
        return {f"{type(value).__module__}:{type(value).__qualname__}": fields}
    if isinstance(value, (tuple, list)):
        items = [plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if isinstance(value, tuple) else items
    if isinstance(value, Mapping):
        return {plain(k, where): plain(v, f"{where}.{k}") for k, v in value.items()}
    raise Unkeyable(where, value)


class Unkeyable(TypeError):
    """A value ``plain`` has no exact encoding for, at ``where`` (a field name and path)."""

    def __init__(self, where: str, value: Any) -> None:
        self.where, self.type_name = where, type(value).__qualname__
        super().__init__(
            f"scenario field {where}: cannot key a {self.type_name} (expected arrays, numbers, "
            "strings, geometries, Dynamics, pydantic models, dataclasses or containers of "
            "them; teach pipeline.model.scenario_data its exact encoding)"
        )


def _model(model: pydantic.BaseModel, exclude: Collection[str], where: str) -> Any:
    """A pydantic model's type and fields (its declared fields only, in order)."""
    fields = {
        name: plain(getattr(model, name), f"{where}.{name}")
        for name in type(model).model_fields
        if name not in exclude
    }
    return {f"{type(model).__module__}:{type(model).__qualname__}": fields}
