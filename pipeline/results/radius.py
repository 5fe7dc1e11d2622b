"""The result types of stage ``radius`` (``stages/radius.py``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class RadiusResult(Result):
    """The robustness radius of one nominal trajectory.

    Attributes:
      radius: largest P-norm radius ``r`` of a safe tube (0 if the nominal itself fails).
      position_clearance: radius of the smallest disk holding the position projection of the
        radius-``r`` ball (the clearance ``d`` for which ``r = r_d``).
      binding: the constraint that sets ``r``, e.g. "unsafe 'NAME'", "goal", "input 'NAME' upper".
      binding_time: when it binds (s); the start of the grid interval.
      limits: constraint -> the largest radius it allows on its own.
      nominal_clearance: lower bound on the nominal position's distance to Unsafe over [0, T].
    """

    radius: float
    position_clearance: float
    binding: str
    binding_time: float
    limits: Mapping[str, float] = field(repr=False)
    nominal_clearance: float
    success: bool
    message: str
