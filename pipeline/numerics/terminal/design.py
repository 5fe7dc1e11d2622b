"""The terminal controller: an equilibrium in Goal, its LQR law and a certified invariant ellipsoid.

After the horizon ``T`` the law becomes ``u = u_eq + K_T e``, ``e = x - x_eq``
(``terminal.equilibrium``), and ``E_c = {e^T P_T e <= c}`` is certified invariant, inside Goal and
the input bounds, robust to the declared uncertainty, for the held law and a measurement error:
``terminal.check`` (T1), (T1'), (T1''), (T4), (T4'), (T5), (T7). This module chooses what is
checked: the equilibrium, the gain, the metric (the Riccati matrix, the disturbance-shaped (T3)
metric of ``terminal.robust``) and the largest level that certifies.

(T6) A larger set under a large bound (``hold_design``). The (T3) metric, certified at level ``c``,
holds ``sqrt(c)`` times the smallest set the disturbance leaves. Below ``ROOM`` times, the funnels'
ends (each at least its own smallest set, about the same size) find no room in it but at its
centre, so the largest set of ``terminal.robust`` (T6) is tried for the same gain and kept when
``largest_level`` certifies it with a larger volume. Where no metric of the LQR gain certifies
any level, (T6) designs the gain with its metric (``Y = K Q``) and the (T3) set of that gain
must certify too. Soundness is (T1')-(T5)'s: every set is checked from scratch like any other;
(T6) only chose its metric and gain. The nominals still end in the (T3) set
(``TerminalDesign.arrival``), and the funnels must end in the larger one (T2).

End tubes: ``pipeline.numerics.terminal.fit`` (the exact containment level, and the funnel's LMI).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import shapely

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.hull import HullError
from pipeline.numerics.terminal.check import TerminalCheck, largest_level, level_tube, mapped
from pipeline.numerics.terminal.equilibrium import (
    TerminalError,
    equilibrium,
    goal_centre,
    lqr_terminal,
)
from pipeline.numerics.terminal.fit import end_levels
from pipeline.numerics.terminal.robust import SHARES, largest_metric, robust_metric
from pipeline.numerics.uncertainty import additive_bound, equilibrium_bound

ROOM = 2.0  # a shaped terminal set this many times (T3)'s smallest one holds the funnels' ends


# where a terminal law's gain comes from: control.lqr at the equilibrium, the tube's (or first
# funnel's end) K, or designed with its metric (Y = K Q, (T6))
TerminalGain = Literal["lqr", "tube", "codesigned"]


@dataclass(frozen=True, kw_only=True)
class TerminalDesign:
    """The kept terminal controller and how well the end tubes fit its ellipsoid.

    Attributes:
      x_eq: (n,); u_eq: (m,); K: (m, n); P: (n, n); check: its certified level and decay.
      gain: where ``K`` comes from (``TerminalGain``): "lqr" (``control.lqr`` at the
        equilibrium), "tube" (the tube's ``K`` and ``P``) or "codesigned" (designed with its
        metric, (T6)).
      fit: ``sqrt(max_i c_i / level)``: the largest end tube's share of the ellipsoid (<= 1).
      shaped: ``P`` is (T3)'s metric for a declared disturbance (``terminal.robust``), designed
        at level 1: ``{e^T P e <= 1}`` is about the smallest set the disturbance leaves.
      arrival: the (T3)-shaped design the nominals end in and the funnels' room is sized from,
        when this one is (T6)'s larger set (``hold_design``); None: this one itself.
      disturbance: (n,) the additive box ``check`` held, with the parameter intervals in the
        hull (T7); None: the box the design was asked for, without them.
    """

    x_eq: FloatArray
    u_eq: FloatArray
    K: FloatArray
    P: FloatArray
    check: TerminalCheck
    gain: TerminalGain
    fit: float
    shaped: bool = False
    arrival: TerminalDesign | None = None
    disturbance: FloatArray | None = None

    @property
    def arrives_in(self) -> TerminalDesign:
        """The design whose set the nominals end in: ``arrival``, else this one."""
        return self if self.arrival is None else self.arrival

    @property
    def log_volume(self) -> float:
        """``log det(level P^-1)``: twice the log of the set's volume, up to a constant."""
        return float(np.linalg.slogdet(self.check.level * np.linalg.inv(self.P))[1])


def design_terminal(
    scenario: Scenario,
    K: FloatArray,
    P: FloatArray,
    ends: Sequence[FloatArray],
    end_radii: Sequence[float],
    period: float = 0.0,
    end_metrics: FloatArray | None = None,
    disturbance: FloatArray | None = None,
    held_period: float = 0.0,
    measurement: FloatArray | None = None,
) -> TerminalDesign:
    """The best-fitting certified terminal controller for end tubes ``||x - ends[i]||_P <=
    end_radii[i]`` (tube gain ``K (m, n)``, metric ``P (n, n)``; ``end_metrics (k, n, n)``: each
    end tube's own metric instead of ``P``, a funnel's).

    Candidates: equilibria at Goal's centre and at the mean end position (when in Goal), each
    with the LQR gain and Riccati matrix there and with the tube's own ``K`` and ``P``; the
    certified one with the smallest ``fit`` is kept (for the law held every ``period`` s when
    it is > 0, the constant certificate's held rate; every ``held_period`` s, (T4), a funnel
    file's), robust to the additive bound ``disturbance (n,)`` (T1') and the measurement box
    ``measurement (n,)`` (T5). ``TerminalError`` when none certifies.
    """
    positions = [goal_centre(scenario)]
    mean = np.mean([scenario.positions(a) for a in ends], axis=0)
    if shapely.intersects_xy(scenario.goal, *mean):
        positions.append(mean)
    best: TerminalDesign | None = None
    reasons = []
    for position in positions:
        try:
            x_eq, u_eq = equilibrium(scenario, position)
        except TerminalError as error:
            reasons.append(str(error))
            continue
        gains: list[tuple[TerminalGain, FloatArray, FloatArray]] = [
            ("tube", np.asarray(K), np.asarray(P))
        ]
        try:
            gains.insert(0, ("lqr", *lqr_terminal(scenario, x_eq, u_eq)))
        except TerminalError as error:
            reasons.append(str(error))
        for gain, K_T, P_T in gains:
            check = largest_level(
                scenario, x_eq, u_eq, K_T, P_T, period, disturbance, held_period, measurement
            )
            if not check.success:
                reasons.append(
                    f"{gain} gain at {np.round(position, 3).tolist()}: " + "; ".join(check.failures)
                )
                continue
            metrics = P if end_metrics is None else end_metrics
            needed = end_levels(P_T, x_eq, metrics, ends, end_radii)
            fit = float(np.sqrt(needed.max() / check.level))
            if best is None or fit < best.fit:
                best = TerminalDesign(
                    x_eq=x_eq, u_eq=u_eq, K=K_T, P=P_T, check=check, gain=gain, fit=fit
                )
    if best is None:
        raise TerminalError("; ".join(dict.fromkeys(reasons)))
    return best


def hover_box(scenario: Scenario, design: TerminalDesign) -> FloatArray | None:
    """(2, 2) ``[[lower_X, upper_X], [lower_Y, upper_Y]]``: the bounding box of the positions at
    which ``design``'s terminal set, moved there unchanged (same ``K``, ``P``, level), still lies
    inside Goal as ``terminal.check.check_level`` tests it: Goal eroded by the set's position
    ellipse (in the whitened coordinates ``W p`` a disk of radius ``sqrt(level)``), and inside
    Goal's extra bounds and ``state_bounds`` on the position states. The erosion is shapely's buffer
    (arcs as segments), so the box is a guide, not a guarantee: a design at any of its points is
    checked from scratch (``hold_design``). None when nothing is left."""
    tube, r = level_tube(scenario, design.K, design.P), float(np.sqrt(design.check.level))
    W = tube.position_whitening
    eroded = mapped(scenario.goal, W).buffer(-r)
    if eroded.is_empty:
        return None
    region = mapped(eroded, np.linalg.inv(W))
    box = np.array(region.bounds, dtype=np.float64).reshape(2, 2).T  # rows X, Y
    extent = tube.state_extent_per_radius * r
    for k, i in enumerate(scenario.position_index):
        name = scenario.state_names[i]
        for bound in (scenario.goal_bounds.get(name), scenario.state_bounds.get(name)):
            if bound is not None:
                box[k] = max(box[k, 0], bound[0] + extent[i]), min(box[k, 1], bound[1] - extent[i])
    return None if np.any(box[:, 0] > box[:, 1]) else box


@dataclass(frozen=True, kw_only=True)
class _Demands:
    """What ``hold_design``'s sets must hold: the additive box ``bound (n,)``, the law held
    every ``period`` s (T4; 0: continuous), the measurement box (T5; None: exact) and the
    parameter intervals in the hull (T7; None: none)."""

    bound: FloatArray
    period: float
    measurement: FloatArray | None
    parameters: Uncertainty | None

    def largest_level(
        self, scenario: Scenario, x_eq: FloatArray, u_eq: FloatArray, K: FloatArray, P: FloatArray
    ) -> TerminalCheck:
        """``largest_level`` of ``(K (m, n), P (n, n))`` under what is held."""
        return largest_level(
            scenario, x_eq, u_eq, K, P, disturbance=self.bound, held_period=self.period,
            measurement=self.measurement, parameters=self.parameters,
        )  # fmt: skip

    def design(
        self,
        x_eq: FloatArray,
        u_eq: FloatArray,
        K: FloatArray,
        P: FloatArray,
        check: TerminalCheck,
        gain: TerminalGain,
        *,
        shaped: bool = False,
        arrival: TerminalDesign | None = None,
    ) -> TerminalDesign:
        """The ``TerminalDesign`` (fit 0), stating the box it held under (T7)."""
        return TerminalDesign(
            x_eq=x_eq, u_eq=u_eq, K=K, P=P, check=check, gain=gain, fit=0.0, shaped=shaped,
            arrival=arrival, disturbance=None if self.parameters is None else self.bound,
        )  # fmt: skip


def hold_design(
    scenario: Scenario,
    disturbance: FloatArray | None = None,
    period: float = 0.0,
    measurement: FloatArray | None = None,
    position: FloatArray | None = None,
    parameters: Uncertainty | None = None,
) -> TerminalDesign:
    """The terminal controller a funnel run designs BEFORE its funnels, for them to end in: the
    equilibrium at Goal's centre, its LQR gain and, under ``disturbance (n,)``, the metric shaped
    for it (T3) when that certifies (the larger set (T6) in its place, ``_larger``, when it holds
    less than ``ROOM`` times its smallest set), else the Riccati matrix, else (T6) with a gain
    designed with its metric; the largest level certified robustly (T1', T1''), for the law
    held every ``period`` s when it is > 0 (T4: the funnel file's law), seeing the state within
    ``measurement (n,)`` (T5); ``fit`` 0 (no end tube yet). ``position (2,)``: the
    equilibrium's position instead of Goal's centre. ``parameters``: a declared uncertainty
    with parameter intervals, held as (T7) when ``disturbance`` leaves no set (in the hull, the
    box ``equilibrium_bound`` in its place; the design's ``disturbance``). (T7) is the fallback,
    not the rule: its hull has twice the vertices, and on quadrotor_hill its larger set made the
    funnels' rounds four times slower for no shorter ``T``.
    ``TerminalError`` when there is no equilibrium, no stabilising gain or no certified level
    (after a failed (T7), with the whole box's failures first)."""
    x_eq, u_eq = equilibrium(scenario, position)
    bound = np.zeros(scenario.n) if disturbance is None else np.asarray(disturbance, float)
    whole = _Demands(bound=bound, period=period, measurement=measurement, parameters=None)
    try:
        return _hold(scenario, x_eq, u_eq, whole)
    except TerminalError as error:
        if parameters is None or parameters.parametric is None:
            raise
        without = str(error)
    # (T7): the box at the equilibrium, plus whatever ``disturbance`` asks beyond the declaration
    try:
        beyond = np.maximum(bound - additive_bound(scenario, parameters), 0.0)
    except HullError:
        beyond = np.zeros(scenario.n)
    local = equilibrium_bound(parameters, scenario, x_eq, u_eq) + beyond
    held = _Demands(bound=local, period=period, measurement=measurement, parameters=parameters)
    try:
        return _hold(scenario, x_eq, u_eq, held)
    except TerminalError as error:  # both failed: say why each did
        raise TerminalError(f"under the whole box's bound: {without}; then {error}") from None


def _hold(
    scenario: Scenario, x_eq: FloatArray, u_eq: FloatArray, demands: _Demands
) -> TerminalDesign:
    """``hold_design`` at the equilibrium ``(x_eq (n,), u_eq (m,))`` under ``demands``."""
    K_T, P_T = lqr_terminal(scenario, x_eq, u_eq)
    robust = bool(np.any(demands.bound > 0))
    if robust:
        shaped = _shaped(scenario, x_eq, u_eq, K_T, demands, "lqr")  # (T3)
        if shaped is not None:  # shaped for the disturbance: kept whenever it certifies
            if shaped.check.level >= ROOM**2:
                return shaped
            larger = _larger(scenario, x_eq, u_eq, K_T, demands, shaped)
            return shaped if larger is None else larger
    check = demands.largest_level(scenario, x_eq, u_eq, K_T, P_T)
    if check.success:
        return demands.design(x_eq, u_eq, K_T, P_T, check, "lqr")
    if robust:  # no metric of the LQR gain holds: one designed with its metric (T6)
        codesigned = _larger(scenario, x_eq, u_eq, None, demands, None)
        if codesigned is not None:
            return codesigned
    where = np.round(x_eq, 3).tolist()
    kind = " with the parameters in the hull (T7)" if demands.parameters is not None else ""
    raise TerminalError(f"lqr gain at {where}{kind}: " + "; ".join(check.failures))


def _shaped(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray,
    demands: _Demands,
    gain: TerminalGain,
) -> TerminalDesign | None:
    """The design of the gain ``K (m, n)`` on (T3)'s metric at its largest certified level
    (``largest_level``), None when there is no such metric or no level certifies."""
    metric = robust_metric(scenario, x_eq, u_eq, K, demands.bound, parameters=demands.parameters)
    if metric is None:
        return None
    check = demands.largest_level(scenario, x_eq, u_eq, K, metric)
    if not check.success:
        return None
    return demands.design(x_eq, u_eq, K, metric, check, gain, shaped=True)


def _larger(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray | None,
    demands: _Demands,
    shaped: TerminalDesign | None,
) -> TerminalDesign | None:
    """(T6): the largest set that ``largest_level`` certifies (every check from scratch), of the
    gain ``K (m, n)`` with ``shaped`` (its (T3) design) as the set the nominals arrive in, or,
    ``K`` None, of a gain designed with it, whose own (T3) design must certify and arrive; over
    the boxes of ``robust.SHARES``, the one of the largest volume above its arrival set's (a
    designed gain's (T3) design alone where none is larger). None when nothing beats ``shaped``
    (for a designed gain: when nothing certifies)."""
    best = shaped
    for share in SHARES:
        found = largest_metric(
            scenario, x_eq, u_eq, K, demands.bound, share, parameters=demands.parameters
        )
        if found is None:
            continue
        gain, metric = found
        arrival = shaped
        if K is None:
            arrival = _shaped(scenario, x_eq, u_eq, gain, demands, "codesigned")
        if arrival is None:
            continue
        check = demands.largest_level(scenario, x_eq, u_eq, gain, metric)
        larger = demands.design(x_eq, u_eq, gain, metric, check, arrival.gain, arrival=arrival)
        candidate = larger if check.success and larger.log_volume > arrival.log_volume else arrival
        if best is None or candidate.log_volume > best.log_volume:
            best = candidate
    return None if best is shaped else best
