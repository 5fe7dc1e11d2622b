"""The result types of stage ``coverage`` (``stages/coverage.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class CoverageResult(Result):
    """Coverage of Init by the balls ``||x - centers[i]||_P_i <= radii[i]`` (one metric per ball).

    Attributes:
      covered: every part of Init is certified covered.
      covered_fraction: covered volume / Init volume over the free states (1 if Init is a point
        and covered); a lower bound on the true fraction.
      boxes: (B, 2, n) covered boxes ``[lower, upper]`` (full state vectors).
      assignment: (B,) the ball that covers each box (the controller's lookup table).
      uncovered_boxes: (U, 2, n) boxes not certified covered.
      free: indices of Init's non-degenerate states.
      depth: halvings per side reached.
    """

    covered: bool
    covered_fraction: float
    boxes: FloatArray = field(repr=False)
    assignment: np.ndarray = field(repr=False)
    uncovered_boxes: FloatArray = field(repr=False)
    free: tuple[int, ...]
    depth: int
    success: bool
    message: str

    def lookup(self, x: FloatArray) -> np.ndarray:
        """Index of the ball assigned to the box holding each state ``x (..., n)``; -1 outside
        every covered box. -> ``(...)``."""
        x = np.asarray(x, dtype=np.float64)
        flat = x.reshape(-1, x.shape[-1])
        lower, upper = self.boxes[:, 0], self.boxes[:, 1]
        inside = np.all(
            (flat[:, None, :] >= lower - 1e-12) & (flat[:, None, :] <= upper + 1e-12), axis=-1
        )
        first = np.where(inside.any(axis=1), inside.argmax(axis=1), -1)
        return np.where(first >= 0, self.assignment[first], -1).reshape(x.shape[:-1])

    def largest_gap(self) -> FloatArray | None:
        """(n,) centre of the largest uncovered box (where a new demonstration could start)."""
        if len(self.uncovered_boxes) == 0:
            return None
        widths = self.uncovered_boxes[:, 1] - self.uncovered_boxes[:, 0]
        volume = np.prod(widths[:, list(self.free)], axis=1)
        return self.uncovered_boxes[int(np.argmax(volume))].mean(axis=0)


@dataclass(frozen=True, kw_only=True)
class CoveringRadius(Result):
    """The smallest common radius (within ``tolerance``) at which the balls around the demo
    starts cover Init: the radius every optimized trajectory must keep so that coverage
    survives the optimization. ``radius`` is ``inf`` when even ``upper`` does not cover."""

    radius: float
    covered: bool
    tries: int
    success: bool
    message: str

    def kept_radius(self, r_d: float) -> float:
        """The radius the optimizer keeps: ``max(r_d, radius)``, or ``r_d`` alone when no
        common radius covers Init (the coverage stage then reports the gap)."""
        return max(r_d, self.radius) if self.covered else r_d
