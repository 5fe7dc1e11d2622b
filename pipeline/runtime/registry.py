"""The declared stages, and the result types a stage artifact may hold: the only classes
decoding ever constructs.

``STAGES`` is every ``Stage`` declared at module level in the ``stages`` package (found by
importing its modules: a new stage module is registered by being there). ``RESULT_TYPES`` maps
each stored name (``module:qualname``) to its class. It is built from the stages' result
classes and, through their field annotations, every dataclass nested inside them (e.g.
``IterationLog`` and ``Verification`` of ``pipeline.numerics`` inside an optimization). An
artifact naming anything else is refused by ``pipeline.io.artifacts.read_stored``.
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import typing
from collections.abc import Iterable, Mapping
from types import MappingProxyType
from typing import Any

import stages
from pipeline.io.artifacts import type_name
from pipeline.results.stage import Stage


def declared_stages() -> tuple[Stage[Any, Any], ...]:
    """Every ``Stage`` value declared in a module of the ``stages`` package (beside its
    function), in module order."""
    found: list[Stage[Any, Any]] = []
    for info in sorted(pkgutil.iter_modules(stages.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"stages.{info.name}")
        found.extend(
            value
            for value in vars(module).values()
            if isinstance(value, Stage) and value.function.__module__ == module.__name__
        )
    return tuple(found)


STAGES = declared_stages()


def _nested(hint: object) -> Iterable[type]:
    """Every class named in a type hint (``X | None``, ``tuple[X, ...]``, ``dict[str, X]``)."""
    if isinstance(hint, type):
        yield hint
    for argument in typing.get_args(hint):
        yield from _nested(argument)


def result_types(roots: Iterable[type]) -> Mapping[str, type]:
    """``module:qualname`` -> class for ``roots`` and every dataclass in their fields' types."""
    found: dict[str, type] = {}
    pending = list(roots)
    while pending:
        cls = pending.pop()
        if not dataclasses.is_dataclass(cls) or type_name(cls) in found:
            continue
        found[type_name(cls)] = cls
        for hint in typing.get_type_hints(cls).values():
            pending.extend(_nested(hint))
    return MappingProxyType(found)


RESULT_TYPES = result_types(stage.result for stage in STAGES)
