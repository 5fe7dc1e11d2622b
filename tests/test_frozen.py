"""Deep immutability (``pipeline.model.frozen``): frozen copies cannot be written through, the
caller's data stays its own, and a frozen dataclass pickles back frozen."""

from __future__ import annotations

import dataclasses
import pickle
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np
import pytest

from pipeline.model.frozen import freeze, freeze_fields, frozen_array, reduce_fields, thaw


@dataclasses.dataclass(frozen=True)
class Held:
    """A frozen dataclass holding an array, a mapping and a tuple, frozen deeply."""

    array: np.ndarray
    table: Mapping[str, Any]
    pair: tuple[Any, ...]

    def __post_init__(self) -> None:
        freeze_fields(self)

    def __reduce__(self) -> tuple[Any, ...]:
        return reduce_fields(self)


def test_a_frozen_array_is_a_read_only_copy_of_the_same_shape_and_dtype() -> None:
    original = np.arange(6, dtype=np.int32).reshape(2, 3)
    frozen = frozen_array(original)
    assert frozen.shape == (2, 3) and frozen.dtype == np.int32
    with pytest.raises(ValueError, match="read-only"):
        frozen[0, 0] = 99
    original[0, 0] = 99  # the caller's array stays writable and is not the frozen one
    assert frozen[0, 0] == 0


def test_freeze_reaches_into_mappings_and_tuples_and_thaw_undoes_the_mappings() -> None:
    value: dict[str, Any] = {"a": np.zeros(2), "b": ({"c": 1.0}, "text")}
    frozen = freeze(value)
    assert isinstance(frozen, MappingProxyType) and isinstance(frozen["b"][0], MappingProxyType)
    with pytest.raises(TypeError):
        frozen["a"] = 1  # type: ignore[index]
    with pytest.raises(ValueError, match="read-only"):
        frozen["a"][0] = 1.0
    value["b"][0]["c"] = 2.0  # a copy: the caller's dict does not reach the frozen one
    assert frozen["b"][0]["c"] == 1.0
    thawed = thaw(frozen)
    assert type(thawed) is dict and type(thawed["b"][0]) is dict
    assert freeze("text") == "text" and freeze(3) == 3  # immutable values as they are


def test_a_frozen_dataclass_pickles_back_frozen() -> None:
    held = Held(array=np.ones(3), table={"k": np.zeros(2)}, pair=(np.ones(1), 2))
    with pytest.raises(ValueError, match="read-only"):
        held.array[0] = 5.0
    copy = pickle.loads(pickle.dumps(held))
    np.testing.assert_array_equal(copy.array, held.array)
    assert isinstance(copy.table, MappingProxyType)
    for array in (copy.array, copy.table["k"], copy.pair[0]):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 5.0
