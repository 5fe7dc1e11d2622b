"""The result types of stage ``stress`` (``stages/stress.py``)."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class StressRun(Result):
    """One stress campaign: with the feedback (``gain_scale = 1``) or without (``0``)."""

    gain_scale: float
    samples: int
    failures: dict[str, int]
    failed_fraction: float
    min_clearance: float
    min_goal_margin: float


@dataclass(frozen=True, kw_only=True)
class StressResult(Result):
    with_feedback: StressRun
    without_feedback: StressRun
    success: bool
    message: str
    # the declared uncertainty's multiple drawn (BEYOND); None: the scenario's 'stress' block
    beyond_declared: float | None = None
