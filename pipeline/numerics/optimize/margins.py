"""Margins that vary along the trajectory: how far a certificate's tube reaches from the nominal.

On sample interval ``k`` of its grid (``M`` intervals, ``t`` in ``[t_k, t_k+1]``) the tube around
``x_ref`` reaches at most ``clearance[k]`` in position, ``input[k, j]`` along input ``j``
(``|K_j e|``) and ``state[k, i]`` along state ``i``; at ``T`` at most ``final_clearance`` in
position and ``final_state[i]`` along state ``i``. The optimizer keeps the nominal that much
further inside every constraint (``pipeline.numerics.optimize.penalties``): Unsafe bloated by
``d + eps_d + clearance[k]``, the inputs' bounds shrunk by ``eps_i + input[k]``, the state boxes
by ``state[k]``, Goal by ``d + eps_g + final_clearance``.

The constant certificate is the case ``M = 1``. A funnel (``pipeline.numerics.funnel.synthesis``:
level ``rho``, ``Q[k] = P[k]^-1`` at ``t_k``, linear in t between samples (F1), ``K[k]`` held on the
interval) reaches, by (E3) of ``funnel.bounds`` (the extents are square roots of functions
convex in t, so their maxima over an interval are at its ends, ``e = k, k+1``)::

    clearance[k] = rho max_e lambda_max(C Q[e] C^T)^1/2      (C selects the position)
    input[k, j]  = rho max_e (K_j[k] Q[e] K_j[k]^T)^1/2
    state[k, i]  = rho max_e (Q[e]_ii)^1/2
    final_clearance = rho lambda_max(C Q[N] C^T)^1/2,  final_state[i] = rho (Q[N]_ii)^1/2

Another horizon (``on_grid``). The optimizer shortens the flight, so the margins of a nominal of
``N`` intervals are read off the source grid of ``M`` by NORMALISED TIME WITH THE MAXIMUM OVER
THE WINDOW: new interval ``k`` covers the fraction ``[k/N, (k+1)/N]`` of the flight, and gets the
largest extent over the source intervals ``j`` whose ``[j/M, (j+1)/M]`` overlap it,
``j = floor(k M / N) .. ceil((k+1) M / N) - 1`` (integer arithmetic, exact). The optimizer's seeds
replay the previous nominal faster (``stages.optimize.reseed``, time compression), so new
interval ``k`` flies the part of the path that the window covered, and every one of its points is
held to the largest extent the tube had anywhere on that part: never less than the source at the
same fraction of the flight. This is a rule for the guide, not a certificate: the funnel is
synthesized again around the new nominal and checked before anything is emitted.

On the RK4 grid of ``s`` substeps per interval (``N s + 1`` points, ``per_point``), a point on a
sample boundary belongs to both intervals and takes the larger margin.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pipeline.model.dynamics import FloatArray

if TYPE_CHECKING:
    from pipeline.model.scenario import Scenario
    from pipeline.numerics.funnel.check import Funnel


@dataclass(frozen=True, kw_only=True, eq=False)
class MarginProfile:
    """A tube's extents per sample interval of a source grid of ``M`` intervals.

    Attributes:
      clearance: (M,) position extent on interval k (added to the Unsafe margin ``d'``).
      input: (M, m) extent along each input (shrinks its bounds and any region box on it).
      state: (M, n) extent along each state (shrinks the region box on it).
      final_clearance: position extent at ``T`` (Goal shrunk further by it).
      final_state: (n,) extent along each state at ``T`` (Goal's extra bounds shrunk by it).
    """

    clearance: FloatArray
    input: FloatArray
    state: FloatArray
    final_clearance: float
    final_state: FloatArray

    def __post_init__(self) -> None:
        for name in ("clearance", "input", "state", "final_state"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        object.__setattr__(self, "final_clearance", float(self.final_clearance))
        M = np.shape(self.clearance)[0] if np.ndim(self.clearance) == 1 else -1
        arrays = {"clearance": self.clearance, "input": self.input, "state": self.state}
        shapes = {name: np.shape(value) for name, value in arrays.items()}
        if M < 1 or shapes["input"][:1] != (M,) or shapes["state"][:1] != (M,):
            raise ValueError(
                f"margin profile: clearance (M,), input (M, m), state (M, n) with M >= 1; got"
                f" {shapes}"
            )
        if np.shape(self.final_state) != (shapes["state"][1],):
            raise ValueError(
                f"margin profile: final_state must have {shapes['state'][1]} entries (one per"
                f" state), got shape {np.shape(self.final_state)}"
            )
        values = {**arrays, "final_clearance": self.final_clearance}
        values["final_state"] = self.final_state
        for name, value in values.items():
            array = np.asarray(value, dtype=np.float64)
            if not (np.all(np.isfinite(array)) and np.all(array >= 0.0)):
                bad = array[~(np.isfinite(array) & (array >= 0.0))].ravel()[0]
                raise ValueError(f"margin profile: {name} must be finite and >= 0, got {bad}")

    @property
    def M(self) -> int:
        """Intervals of the source grid."""
        return int(self.clearance.shape[0])

    @classmethod
    def zero(cls, n: int, m: int) -> MarginProfile:
        """No extra margin anywhere (the constant case: its extents are in the base bounds)."""
        return cls(
            clearance=np.zeros(1),
            input=np.zeros((1, m)),
            state=np.zeros((1, n)),
            final_clearance=0.0,
            final_state=np.zeros(n),
        )

    def on_grid(self, N: int) -> MarginProfile:
        """The profile for a nominal of ``N`` intervals: normalised time, maximum over the window
        (module docstring)."""
        if int(N) != N or N < 1:
            raise ValueError(f"horizon N must be a whole number >= 1, got {N!r}")
        N, M = int(N), self.M
        if N == M:
            return self
        k = np.arange(N)
        first = (k * M) // N
        last = -((-(k + 1) * M) // N)  # ceil((k + 1) M / N), exclusive
        span = int(np.max(last - first))
        window = np.minimum(first[:, None] + np.arange(span), (last - 1)[:, None])  # (N, span)
        return MarginProfile(
            clearance=self.clearance[window].max(axis=1),
            input=self.input[window].max(axis=1),
            state=self.state[window].max(axis=1),
            final_clearance=self.final_clearance,
            final_state=self.final_state,
        )


def per_point(values: FloatArray, substeps: int) -> FloatArray:
    """Per-interval ``values (N, ...)`` on the RK4 grid of ``substeps`` per interval:
    ``(N s + 1, ...)``; a point on a sample boundary takes the larger of its two intervals."""
    values = np.asarray(values, dtype=np.float64)
    s = int(substeps)
    dense = np.repeat(values, s, axis=0)  # point i in interval i // s
    dense = np.concatenate([dense, values[-1:]])  # the final point: last interval
    dense[s:-1:s] = np.maximum(values[:-1], values[1:])  # boundary i = k s, 0 < k < N
    return dense


def funnel_margins(
    scenario: Scenario, funnel: Funnel, *, level: float | None = None, enclosure: bool = True
) -> MarginProfile:
    """The extents of ``funnel``'s tube at ``level`` (default its certified ``rho``) per sample
    interval of its nominal (module docstring, from (E3)); raises if the funnel was rejected.

    ``enclosure``: the state extents also hold the nominal's a priori enclosure, which the
    funnel's check requires inside the hull boxes, themselves clipped to the state bounds
    (``funnel.bounds`` (E1)-(E2): on interval ``k`` the box ``grid +- pad`` and the range
    ``grid +- F h / 2`` widened by the tube): ``state[k, i] = max(pad, F h / 2 + rho s)``,
    measured from the nominal's grid points, so that a nominal kept that far inside the state
    bounds leaves the next funnel the room its enclosure needs; likewise the clearance gains the
    position's motion between grid points, ``|F_XY| h / 2`` ((a) of ``funnel.bounds``)."""
    if not funnel.success:
        raise ValueError(f"funnel_margins: the funnel was not certified ({funnel.message})")
    rho = funnel.rho if level is None else float(level)
    if not (np.isfinite(rho) and rho >= 0.0):
        raise ValueError(f"funnel_margins: level must be a finite number >= 0, got {level!r}")
    Q, K = funnel.Q, funnel.K  # (N+1, n, n), (N, m, n)
    Q = (Q + np.swapaxes(Q, 1, 2)) / 2
    c = list(scenario.position_index)
    diagonal = np.diagonal(Q, axis1=1, axis2=2)  # (N+1, n)
    position = np.linalg.eigvalsh(Q[:, c][:, :, c])[:, -1]  # (N+1,) lambda_max(C Q C^T)
    gains = [np.einsum("kji,kil,kjl->kj", K, Q[e : len(Q) - 1 + e], K) for e in (0, 1)]
    state = rho * np.sqrt(np.maximum(diagonal[:-1], diagonal[1:]))  # (N, n)
    clearance = rho * np.sqrt(np.maximum(position[:-1], position[1:]))  # (E3)
    if enclosure and funnel.enclosure is not None:
        box, grid, reach = funnel.enclosure.box, funnel.enclosure.grid_range, funnel.enclosure.range
        pad = np.maximum(grid[:, 0] - box[:, 0], box[:, 1] - grid[:, 1])  # (E1)
        drift = np.maximum(grid[:, 0] - reach[:, 0], reach[:, 1] - grid[:, 1])  # (E2): F h / 2
        state = np.maximum(np.maximum(pad, drift + state), 0.0)
        # (a) of funnel.bounds: between grid points the position moves V h / 2, V = |F_XY|
        clearance = clearance + np.hypot(*drift[:, list(scenario.position_index)].T)
    return MarginProfile(
        clearance=clearance,
        input=rho * np.sqrt(np.maximum(np.maximum(*gains), 0.0)),
        state=state,
        final_clearance=float(rho * np.sqrt(position[-1])),
        final_state=rho * np.sqrt(diagonal[-1]),
    )
