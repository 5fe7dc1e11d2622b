"""The result types of stage ``montecarlo`` (``stages/montecarlo.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.closed_loop.gusts import Draws
from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class Falsification(Result):
    """The worst initial state found by search and its margin (evidence, not a bound)."""

    worst_x0: FloatArray
    worst_margin: float
    evaluations: int
    binding: str = ""  # which margin is the smallest there, with its unit
    # under a declared uncertainty: the worst bang-bang realisation found (one run), else None
    worst_draws: Draws | None = field(default=None, repr=False)


@dataclass(frozen=True, kw_only=True)
class MonteCarloResult(Result):
    samples: int
    seed: int
    failures: dict[str, int]
    failed_x0: FloatArray = field(repr=False)
    min_clearance: float
    min_goal_margin: float
    max_tube_tightness: float
    failure_bound: float
    clearance: FloatArray = field(repr=False)
    tube_tightness: FloatArray = field(repr=False)
    paths: tuple[FloatArray, ...] = field(repr=False)
    falsification: Falsification
    success: bool
    message: str
    # ||e(T)||_P e^(lambda T) / ||e(0)||_P per run: how much of the certified decay is used
    tube_final: FloatArray = field(default_factory=lambda: np.zeros(0), repr=False)
    hold_runs: int = 0  # runs continued to T + HOLD_SECONDS under the terminal law
    hold_max_level_ratio: float = float("nan")  # their largest V(x) / level after T
