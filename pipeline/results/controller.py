"""The result types of stage ``controller`` (``stages/controller.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class ControllerResult(Result):
    path: Path
    trajectories: int
    interpolation_error: float
    success: bool
    message: str
    terminal: bool = False  # a certified terminal controller was written
    terminal_message: str = ""  # what it is, or why there is none
