"""The result types of stage ``funnel`` (``stages/funnel.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.numerics.funnel.check import Funnel
from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class FunnelStageResult(Result):
    """The funnels of the final trajectories, one per trajectory in order.

    Attributes:
      names: the trajectories' names (their demos).
      funnels: each trajectory's funnel (``Funnel``; a rejected one has ``success`` False).
      initial_radii: (k,) the constant certificate's radius ``r_i`` whose ball slice (I1) a
        funnel whose start owns no cell of Init was asked to hold.
      usable: indices of the trajectories whose funnel is certified (``success``, ``rho > 0``
        and the independent check passed); the others are dropped.
      rejected: one line per dropped trajectory: its name and why.
    """

    names: tuple[str, ...]
    funnels: tuple[Funnel, ...] = field(repr=False)
    initial_radii: FloatArray = field(repr=False)
    usable: tuple[int, ...]
    rejected: tuple[str, ...]
    success: bool
    message: str

    @property
    def starts(self) -> FloatArray:
        """(k, n, n) ``P_i[0]``, the metric of each funnel's initial ellipsoid ``E_i(0)``."""
        return np.stack([funnel.P[0] for funnel in self.funnels])

    @property
    def levels(self) -> FloatArray:
        """(k,) ``rho_i`` of the usable funnels, 0 for dropped ones (they cover nothing)."""
        return np.array(
            [f.rho if i in self.usable else 0.0 for i, f in enumerate(self.funnels)], dtype=float
        )

    def failure(self, i: int) -> str | None:
        """Why trajectory ``i``'s funnel was dropped (its ``rejected`` line without the name);
        None if it is usable."""
        if i in self.usable:
            return None
        prefix = f"{self.names[i]} dropped: "
        return next(line.removeprefix(prefix) for line in self.rejected if line.startswith(prefix))
