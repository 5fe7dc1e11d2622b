"""The result types of stage ``report`` (``stages/report.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class ReportResult(Result):
    html: Path
    pdf: Path | None
    success: bool
    message: str
