"""The result types a stage artifact may hold: the only classes decoding ever constructs.

``RESULT_TYPES`` maps each stored name (``module:qualname``) to its class. It is built from the
stage result classes and, through their field annotations, every dataclass nested inside them
(e.g. ``IterationLog`` and ``Verification`` of ``pipeline.numerics`` inside an optimization).
An artifact naming anything else is refused by ``pipeline.io.artifacts.read_stored``.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Iterable, Mapping
from types import MappingProxyType

from pipeline.io.artifacts import type_name
from stages.controller import ControllerResult
from stages.coverage import CoverageResult, CoveringRadius
from stages.feedback import FeedbackResult
from stages.funnel import FunnelStageResult
from stages.montecarlo import MonteCarloResult
from stages.optimize import OptimizeResult
from stages.radius import RadiusResult
from stages.report import ReportResult
from stages.stress import StressResult

STAGE_RESULTS: tuple[type, ...] = (
    FeedbackResult,
    RadiusResult,
    CoverageResult,
    CoveringRadius,
    OptimizeResult,
    FunnelStageResult,
    ControllerResult,
    MonteCarloResult,
    StressResult,
    ReportResult,
)


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


RESULT_TYPES = result_types(STAGE_RESULTS)
