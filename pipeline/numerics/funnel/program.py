"""The funnel's LMI program for one design (``funnel.synthesis``, Design step 3): (F3) on the
pieces, the initial set, and the tube at level 1 inside every hull box and cap, as a
``funnel.lmi.FunnelProgram`` for Clarabel.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping

import numpy as np
import shapely

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.funnel.bounds import interval_clearance
from pipeline.numerics.funnel.law import corners
from pipeline.numerics.funnel.lmi import FunnelProgram
from pipeline.numerics.funnel.sampled import paired_vertices


def objective_weights(scenario: Scenario, state_bounds: Mapping[str, tuple[float, float]], K):
    """(N, n, n) ``W[k]`` of the objective ``sum_k tr(W[k] Q[k])``: position by ``1 / d^2``, each
    input by its inverse squared half-range through ``K (N, m, n)``, each of ``state_bounds`` by
    ``4 / width^2``."""
    n = scenario.n
    C = np.zeros((2, n))
    C[0, scenario.position_index[0]] = C[1, scenario.position_index[1]] = 1.0
    W = np.broadcast_to(C.T @ C / scenario.clearance**2, (len(K), n, n)).copy()
    for j in range(scenario.m):
        half = (scenario.input_upper[j] - scenario.input_lower[j]) / 2
        W += np.einsum("ki,kl->kil", K[:, j], K[:, j]) / half**2
    for name, (lower, upper) in state_bounds.items():
        i = scenario.state_names.index(name)
        W[:, i, i] += 4 / (upper - lower) ** 2
    return W


def funnel_program(
    scenario, trajectory, K, vertices, boxes, variables, enclosure, Q_init, Q_seed, c, bounds,
    disturbance=None, multiplier=0.0, margin=0.0, terminal=None, state_bounds=None,
    codesign=False, period=0.0, pushed=None,
):  # fmt: skip
    """(F3) on the LMI pieces ``bounds`` (unknowns: ``Q`` at the piece ends), with the initial set
    and the tube at level 1 inside every hull box, clear of Unsafe (a disk bound) and inside Goal
    (``funnel.lmi``). On a piece ``Q`` is linear and ``K`` held, so the tube's extents are largest
    at its ends (E3): the caps there hold on every sample interval of the piece. Under a
    ``disturbance`` every input bound and ``state_bounds`` entry is capped too: the level of a
    robust funnel cannot shrink below the design's to fit a bound the program did not see
    ((I5)'s disturbance term grows as the level shrinks). ``period > 0``: (F3) on the pairs of
    ``funnel.sampled.paired_vertices`` too (a held law's push to first order, (I6'), at the
    piece's first gain ``K``; with ``codesign`` the seed's), on the pieces holding an interval of
    ``pushed`` (None: every piece)."""
    n, us, final_state = scenario.n, trajectory.us, trajectory.dense_xs[-1]
    S = len(bounds) - 1
    clearance = interval_clearance(scenario, trajectory, enclosure)
    C_pos = np.eye(n)[list(scenario.position_index)]
    caps: list[tuple[int, FloatArray, FloatArray]] = []
    gain_caps: list[tuple[int, int, int, float]] = []

    def cap_input(j: int, a: int, i: int, room: float) -> None:
        """Input ``i``'s tube at level 1 within ``room`` of u_ref on piece ``j`` (from ``a``),
        at both ends: ``K_i Q K_i^T <= room^2``, or with ``codesign`` its Schur form in ``Y``."""
        for e in (j, j + 1):
            if codesign:
                gain_caps.append((e, j, i, max(room, 0.0) ** 2))
            else:
                caps.append((e, K[a, i : i + 1], np.full((1, 1), max(room, 0.0) ** 2)))

    for j, (a, b) in enumerate(itertools.pairwise(bounds)):
        for d, name in enumerate(variables):
            lo, hi = boxes[a, :, d]
            if name in scenario.input_names:  # K_j Q K_j^T <= room^2 at both ends
                i = scenario.input_names.index(name)
                cap_input(j, a, i, min((us[a:b, i] - lo).min(), (hi - us[a:b, i]).min()))
                continue
            i = scenario.state_names.index(name)  # Q_ii <= room^2 at both ends
            room = min(
                (enclosure.range[a:b, 0, i] - lo).min(), (hi - enclosure.range[a:b, 1, i]).min()
            )
            caps += [
                (e, np.eye(n)[i : i + 1], np.full((1, 1), max(room, 0.0) ** 2)) for e in (j, j + 1)
            ]
        if disturbance is not None:  # under a disturbance the level cannot shrink to fit
            for i, name in enumerate(scenario.input_names):  # the input bounds, every input
                if name in variables:
                    continue  # capped by its hull box above
                lower, upper = scenario.input_lower[i], scenario.input_upper[i]
                room = min((us[a:b, i] - lower).min(), (upper - us[a:b, i]).min())
                cap_input(j, a, i, room)
            for name, (lower, upper) in (state_bounds or {}).items():  # and the state bounds
                if name in variables:
                    continue
                i = scenario.state_names.index(name)
                room = min(
                    (enclosure.range[a:b, 0, i] - lower).min(),
                    (upper - enclosure.range[a:b, 1, i]).min(),
                )
                C = np.eye(n)[i : i + 1]
                caps += [(e, C, np.full((1, 1), max(room, 0.0) ** 2)) for e in (j, j + 1)]
        # The position disk of the tube at level 1 clear of Unsafe (funnel.bounds (a)).
        d = clearance[a:b].min()
        if np.isfinite(d):
            caps += [(e, C_pos, max(d, 0.0) ** 2 * np.eye(2)) for e in (j, j + 1)]
    final = scenario.positions(trajectory.dense_xs[-1])
    inside = shapely.intersects_xy(scenario.goal, *final)
    g = float(shapely.distance(shapely.Point(final), scenario.goal.boundary)) * inside
    caps.append((S, C_pos, g**2 * np.eye(2)))
    for name, (lower, upper) in scenario.goal_bounds.items():
        i = scenario.state_names.index(name)
        room = max(min(final_state[i] - lower, upper - final_state[i]), 0.0)
        caps.append((S, np.eye(n)[i : i + 1], np.full((1, 1), room**2)))
    if terminal is not None:  # E(T) inside the terminal ellipsoid (terminal.fit (T2))
        caps.append((S, *terminal.end_cap(final_state)))
    # with codesign the inputs' spread is weighted through Z >= K Q K^T (funnel.lmi's gain_weight)
    W = objective_weights(scenario, {}, np.zeros_like(K) if codesign else K)
    W = np.concatenate([W, W[-1:]])[bounds]  # (S+1, n, n) at the piece ends
    halves = (scenario.input_upper - scenario.input_lower) / 2
    return FunnelProgram(
        Ts=scenario.Ts * np.diff(bounds).astype(np.float64),
        K=K[bounds[:-1]],
        vertices=tuple(
            paired_vertices(vertices[a], K[a], period)
            if period > 0 and (pushed is None or any(a <= k < b for k in pushed))
            else vertices[a]
            for a, b in itertools.pairwise(bounds)
        ),
        c=c,
        Q_init=Q_init,
        floor=1e-4 * float(np.linalg.eigvalsh(Q_init)[:, -1].max()),
        caps=tuple(caps),
        W=W,
        initial_weight=100 * float(np.einsum("kij,kji->", W, Q_seed[bounds])),
        disturbance=None if disturbance is None else corners(disturbance),
        multiplier=multiplier,
        margin=margin,
        codesign=codesign,
        gain_caps=tuple(gain_caps),
        gain_weight=np.diag(1 / halves**2) if codesign else None,
    )
