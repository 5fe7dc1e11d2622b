"""The funnel's LMI pieces and the hull boxes over them (pipeline.numerics.funnel.synthesis, HOLD).

Pieces. The sample intervals ``[t_k, t_k+1)``, k = 0..N-1, are grouped into pieces
``[t_a, t_b)`` of ``hold`` intervals; on a piece ``K`` is held and ``Q`` linear in t (F1), so the
stored ``Q[k]`` at the sample times inside a piece are interpolated:

    Q[k] = (1 - s) Q[a] + s Q[b],  s = (k - a) / (b - a).                                    (P1)

Boxes. Each piece gets one box ``Z`` over the variables the Jacobian depends on, holding every
sample interval's a priori box ``B_k`` (E1 of ``funnel.bounds``) widened by ``w``, and one sound
hull over it (``pipeline.numerics.hull``). ``w`` is ``allowance`` times the seed tube's extent
on the piece (a state's ``sqrt(Q_ii)``, an input's ``sqrt(K_j Q K_j^T)``, at the piece's sample
times), clipped to the state and input bounds. For an angle ``z`` that enters through
``(cos z, sin z)`` the hull's arc polygon needs ``ceil(width / MAX_SEGMENT_ANGLE)`` segments, each
a vertex more, and a wider arc loosens every vertex; when ``tight``, its ``w`` is also capped so
that the box fills whole segments, ``w <= (c ARC - spread) / 2`` with ``c`` the fewest segments
leaving ``w >= ARC / 4`` (``ARC`` just under ``MAX_SEGMENT_ANGLE``, ``spread`` the nominal's range
on the piece). Any box is sound (the certificate checks that the tube stays inside it); the cap
only chooses a smaller one, and ``funnel.synthesize_funnel`` falls back to the uncapped boxes
when the capped ones cannot hold the whole initial set.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.bounds import (
    Enclosure,
    enclosure_range,
    grid_range,
    rate_bound,
    substeps,
)
from pipeline.numerics.hull import MAX_SEGMENT_ANGLE, HullError, arc_variables, jacobian_hull

ARC = 0.99 * MAX_SEGMENT_ANGLE  # below the segment width, so that rounding adds no segment
PAD_ROUNDS = 6


def pieces(N: int, hold: int) -> np.ndarray:
    """(S+1,) sample indices bounding the pieces: ``hold`` sample intervals each, the last one
    shorter if ``hold`` does not divide ``N``."""
    return np.append(np.arange(0, N, hold), N)


def interpolate(Q_ends: FloatArray, bounds: np.ndarray) -> FloatArray:
    """(N+1, n, n) ``Q`` at the sample times from ``Q_ends (S+1, n, n)`` at the piece ends
    ``bounds (S+1,)``, eq. (P1)."""
    k = np.arange(bounds[-1] + 1)
    j = np.minimum(np.searchsorted(bounds, k, side="right") - 1, len(bounds) - 2)
    s = ((k - bounds[j]) / (bounds[j + 1] - bounds[j]))[:, None, None]
    return (1 - s) * Q_ends[j] + s * Q_ends[j + 1]  # eq. (P1)


def _limits_of(scenario: Scenario, state_bounds: Mapping[str, tuple[float, float]], name: str):
    if name in scenario.input_names:
        j = scenario.input_names.index(name)
        return float(scenario.input_lower[j]), float(scenario.input_upper[j])
    lower, upper = state_bounds.get(name, (-np.inf, np.inf))
    return float(lower), float(upper)


def arc_cap(spread: float) -> float:
    """The largest ``w`` with ``spread + 2 w`` filling whole arc segments, at least ``ARC / 4``."""
    count = math.ceil((spread + ARC / 2) / ARC)
    return (count * ARC - spread) / 2


def piece_hulls(
    scenario: Scenario,
    trajectory: Trajectory,
    Q_seed: FloatArray,
    K: FloatArray,
    state_bounds: Mapping[str, tuple[float, float]],
    allowance: float,
    segments: int,
    bounds: np.ndarray,
    tight: bool,
    pad_rounds: int = PAD_ROUNDS,
    input_offset: FloatArray | None = None,
) -> tuple[tuple[str, ...], FloatArray, tuple[FloatArray, ...], Enclosure]:
    """The boxes and hulls of the module docstring for seed ``Q_seed (N+1, n, n)``, held gains
    ``K (N, m, n)`` and pieces ``bounds (S+1,)``: ``(variables (d names), boxes (N, 2, d),
    vertices (N arrays (V, n, n+m)), enclosure)``, per sample interval (its piece's box and hull).
    ``pipeline.numerics.verify.recertify`` rebuilds a shipped funnel's hulls with it too: pieces of
    one interval, the file's ``Q`` as the seed, ``allowance`` its level, and ``input_offset (N, m)``
    the shipped law's input offset (``funnel.law`` (I3)) added to the inputs' widths.

    Raises:
      HullError: no hull over a box, or no a priori enclosure (E1) in ``pad_rounds`` rounds.
    """
    dynamics, n = scenario.dynamics, scenario.n
    variables = dynamics.depends_on()
    arcs = arc_variables(dynamics) if tight else ()
    h = scenario.Ts / substeps(trajectory)
    grid = grid_range(trajectory)  # (N, 2, n)
    N = len(grid)
    s_seed = np.sqrt(np.diagonal(Q_seed, axis1=1, axis2=2))  # (N+1, n)
    g_seed = np.sqrt(
        np.maximum(*(np.einsum("kji,kil,kjl->kj", K, Q_seed[e : N + e], K) for e in (0, 1)))
    )  # (N, m)
    boxes, vertices = np.empty((N, 2, len(variables))), []
    pads = 2 * h * np.abs(dynamics.f(grid, trajectory.us[:, None])).max(axis=1) + 1e-9  # (N, n)
    F = np.empty((N, n))
    for a, b in itertools.pairwise(bounds):
        for _ in range(pad_rounds):
            B = grid[a:b] + np.stack([-pads[a:b], pads[a:b]], axis=1)  # a priori boxes (E1)
            box = np.empty((2, len(variables)))
            for d, name in enumerate(variables):
                if name in scenario.input_names:
                    j = scenario.input_names.index(name)
                    w = allowance * g_seed[a:b, j].max()
                    if input_offset is not None:
                        w += input_offset[a:b, j].max()  # funnel.law (I3)
                    centre = trajectory.us[a:b, j].min(), trajectory.us[a:b, j].max()
                else:
                    i = scenario.state_names.index(name)
                    w = allowance * s_seed[a : b + 1, i].max()
                    centre = B[:, 0, i].min(), B[:, 1, i].max()
                if name in arcs:
                    w = min(w, arc_cap(centre[1] - centre[0]))
                lower, upper = _limits_of(scenario, state_bounds, name)
                box[:, d] = max(centre[0] - w, lower), min(centre[1] + w, upper)
            region = {
                name: (float(box[0, d]), float(box[1, d])) for d, name in enumerate(variables)
            }
            hull = jacobian_hull(dynamics, region, segments, compact=True)
            for k in range(a, b):
                F[k] = rate_bound(dynamics, trajectory, k, B[k - a], hull.A)  # eq. (E1)
            if np.all(F[a:b] * h < pads[a:b]):
                break
            pads[a:b] = np.maximum(pads[a:b], 2 * F[a:b] * h)
        else:
            raise HullError(f"no a priori enclosure of the nominal on intervals {a}-{b - 1}")
        boxes[a:b] = box
        vertices.extend([hull.vertices] * (b - a))
    enclosure = Enclosure(
        box=grid + np.stack([-pads, pads], axis=1),
        rate_bound=F,
        grid_range=grid,
        range=enclosure_range(grid, F, h),
    )
    return variables, boxes, tuple(vertices), enclosure
