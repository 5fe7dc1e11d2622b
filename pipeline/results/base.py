"""Deeply frozen stage results: ``Result`` is the base of every stage's result type.

``frozen=True`` forbids assigning a field, not writing into the array or mapping it holds.
A ``Result`` freezes its fields on construction (``__post_init__``), at any depth: arrays become
read-only copies, mappings ``types.MappingProxyType`` over copies, tuples element by element,
and a nested dataclass (a ``Funnel``, a ``Tube``, an ``IterationLog``) a copy with its fields
frozen the same way; a value frozen already is kept as it is (the same object), so a result
built from another's parts shares them. Pickled by its fields (``__reduce__``): unpickling
constructs, hence freezes, it again (NumPy unpickles arrays writable). Read-only mapping views
pickle as views over a copy (registered with ``copyreg`` here).
"""

from __future__ import annotations

import copy
import copyreg
import dataclasses
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np

from pipeline.model.frozen import frozen_array, reduce_fields


def read_only(items: dict[Any, Any]) -> MappingProxyType:
    """A read-only view of ``items`` (what an unpickled view is made by)."""
    return MappingProxyType(items)


def _reduce_view(mapping: MappingProxyType) -> tuple[Any, ...]:
    return read_only, (dict(mapping),)


copyreg.pickle(MappingProxyType, _reduce_view)


def _frozen_already(array: np.ndarray) -> bool:
    """Read-only and owning its data (no writable base to change it through)."""
    return not array.flags.writeable and array.base is None


def freeze_deep(value: Any) -> Any:
    """``value`` deeply frozen (module docstring); ``value`` itself when it is already."""
    if isinstance(value, np.ndarray):
        return value if _frozen_already(value) else frozen_array(value)
    if isinstance(value, Mapping):
        items = {k: freeze_deep(v) for k, v in value.items()}
        kept = isinstance(value, MappingProxyType) and all(items[k] is value[k] for k in items)
        return value if kept else MappingProxyType(items)
    if type(value) is tuple:
        elements = tuple(freeze_deep(v) for v in value)
        return value if all(a is b for a, b in zip(elements, value, strict=True)) else elements
    if isinstance(value, Result):  # froze itself when constructed
        return value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
        frozen = {name: freeze_deep(v) for name, v in fields.items()}
        if all(frozen[name] is fields[name] for name in fields):
            return value
        duplicate = copy.copy(value)
        for name, v in frozen.items():
            object.__setattr__(duplicate, name, v)
        return duplicate
    return value


class Result:
    """Base of a stage's result type (a frozen, keyword-only dataclass): deeply frozen."""

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):  # type: ignore[arg-type]
            value = getattr(self, field.name)
            frozen = freeze_deep(value)
            if frozen is not value:
                object.__setattr__(self, field.name, frozen)

    def __reduce__(self) -> tuple[Any, ...]:
        return reduce_fields(self)
