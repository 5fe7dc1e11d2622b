"""Deep immutability for frozen dataclasses: ``frozen=True`` forbids assigning a field, not
writing into the array or mapping it holds (``scenario.init_lower[0] = 99.0``).

``freeze(value)`` returns a copy that cannot be changed in place: arrays read-only, mappings
``types.MappingProxyType`` over a fresh dict, tuples element by element; anything else as it is
(str, numbers, shapely geometries and frozen dataclasses are immutable already). A dataclass
calls it on its fields in ``__post_init__`` (``freeze_fields``), as ``pipeline.controller`` does
with its arrays. The copy is what makes it safe: a caller keeps no writable handle on the data
the object holds.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np


def frozen_array(array: np.ndarray) -> np.ndarray:
    """A read-only copy of ``array`` (same dtype and shape)."""
    copy = np.array(array, copy=True)
    copy.flags.writeable = False
    return copy


def freeze(value: Any) -> Any:
    """``value`` with its arrays read-only and mappings read-only views (copies of both)."""
    if isinstance(value, np.ndarray):
        return frozen_array(value)
    if isinstance(value, Mapping):
        return MappingProxyType({k: freeze(v) for k, v in value.items()})
    if type(value) is tuple:
        return tuple(freeze(v) for v in value)
    return value


def thaw(value: Any) -> Any:
    """``value`` with its read-only mapping views as dicts (``MappingProxyType`` cannot be
    pickled); the constructor that ``reduce_fields`` calls freezes them again."""
    if isinstance(value, MappingProxyType):
        return {k: thaw(v) for k, v in value.items()}
    if type(value) is tuple:
        return tuple(thaw(v) for v in value)
    return value


def freeze_fields(instance: Any) -> None:
    """Replace every field of the frozen dataclass ``instance`` by ``freeze(field)`` (call it in
    ``__post_init__``)."""
    for field in dataclasses.fields(instance):
        value = getattr(instance, field.name)
        frozen = freeze(value)
        if frozen is not value:
            object.__setattr__(instance, field.name, frozen)


def reduce_fields(instance: Any) -> tuple[Any, ...]:
    """``__reduce__`` of a frozen dataclass: unpickled by calling its class with its fields, so
    that ``__post_init__`` freezes the copy (NumPy unpickles arrays writable)."""
    fields = {f.name: thaw(getattr(instance, f.name)) for f in dataclasses.fields(instance)}
    return _construct, (type(instance), fields)


def _construct(cls: type, fields: dict[str, Any]) -> Any:
    return cls(**fields)
