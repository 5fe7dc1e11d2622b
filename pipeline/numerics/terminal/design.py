"""The terminal controller: an equilibrium in Goal, its LQR law and a certified invariant ellipsoid.

After the horizon ``T`` the law becomes ``u = u_eq + K_T e``, ``e = x - x_eq``, with
``f(x_eq, u_eq) = 0`` and the position of ``x_eq`` inside Goal. With ``V(e) = e^T P_T e`` the
candidate set is ``E_c = {e : V(e) <= c}``. Along a solution in ``E_c`` (mean value theorem on the
segment from ``x_eq`` to ``x``, which lies in ``E_c``'s bounding box ``Z_c``):

    e' = f(x, u_eq + K_T e) - f(x_eq, u_eq) + f(x_eq, u_eq)
       = (A + B K_T) e + r,      [A B] in conv{[A_v B_v]} = a sound hull over Z_c,
                                   r = f(x_eq, u_eq) (the equilibrium's residual)

so with ``M_v = (A_v + B_v K_T)^T P_T + P_T (A_v + B_v K_T) <= -alpha P_T`` at every vertex,

    V' <= -alpha V + 2 sqrt(V) ||r||_{P_T}                                          (T1)

which is negative on the boundary ``V = c`` when ``alpha sqrt(c) > 2 ||r||_{P_T}``: ``E_c`` is
invariant. It is certified when, in addition, ``E_c`` keeps ``u_eq + K_T e`` inside the input
bounds (no clipping, so the law is the linear one), its position projection lies in Goal (the
disk test of ``pipeline.numerics.tube.geometry``) and its states in Goal's extra bounds and in the
scenario's ``state_bounds``. ``Z_c`` holds the states ``x_eq +- sqrt(c (P_T^-1)_ii)`` and inputs
``u_eq +- sqrt(c) ||K_j P_T^-1/2||``.

Robust (T1'). With the declared uncertainty as one additive term (``pipeline.numerics.
uncertainty``), ``x' = f(x, u) + w``, ``|w_i| <= b_i`` for every measurable ``w``, the error gains
``+ w``: ``e' = (A + B K_T) e + r + w`` and, by Cauchy-Schwarz in the ``P_T`` inner product,

    V' <= -alpha V + 2 sqrt(V) (||r||_{P_T} + w_max),   w_max = max_{|w| <= b} ||w||_{P_T}.   (T1')

``||w||_{P_T}`` is convex in ``w``, so its maximum over the box is at a corner
(``funnel.law.corners``). ``E_c`` is invariant for every such ``w`` when ``alpha sqrt(c) > 2
(||r||_{P_T} + w_max)``: the level is bounded BELOW by ``floor = (2 (||r|| + w_max) / alpha)^2``
as well as above (inputs, Goal, the hull's decay). ``b`` holds only where ``(x, u)`` lies in
``uncertainty.certified_box``, so with ``b > 0`` ``Z_c`` must lie in the operating region too
for the states without ``state_bounds``. With ``b = 0`` (T1') is (T1), and every check and level
is exactly the exact model's.

(T1''). (T1') bounds the decay and the disturbance's push at their own worst boundary points.
Where it fails, the S-procedure of ``pipeline.numerics.funnel.robust`` (I5) bounds them together:
``E_c`` with constant ``Q = P_T^-1`` is a funnel of one interval (``Q' = 0``), the hull's vertices
held, the residual added to the box (``|r + w| <= |r| + b`` entrywise); ``V' < 0`` on its boundary
when (I5)'s eigenvalue is below ``-LMI_MARGIN`` (not with the constant certificate's held rate,
``period``; a funnel file's held law (T4) is an additive term, and keeps (T1'')).

(T4) A held law in a funnel file. With ``--feedback-period h`` the law after ``T`` is ``u = u_eq +
K_T e(t_j)`` on ``[t_j, t_j + h)``, ``t_j = j h`` (``T`` is a multiple of ``h``, so the first
window starts at ``T``). As in ``funnel.law`` (I6), ``f(x, u) - f(x_eq, u_eq) = Abar e + Bbar K_T
e(t_j)`` with ``[Abar Bbar]`` in the hull over ``Z_c`` (``u`` is ``u_eq + K_T e(t_j)``, ``e(t_j)``
in ``E_c`` up to the first exit: inside ``Z_c``'s input box), so

    e' = (Abar + Bbar K_T) e + r + w + Bbar K_T (e(t_j) - e(t)),

the continuous law's error equation with one more additive term. While ``e`` stays in ``E_c``,
``|e(t_j) - e(t)| <= h Edot`` with ``Edot_i = max_v [sum_l |A_v[i, l]| ext_l + sum_j |B_v[i, j]|
reach_j] + |r_i| + b_i`` (``ext``, ``reach``: ``E_c``'s state and input extents about
``(x_eq, u_eq)``; a convex combination of the vertices' terms, as in (I6)), and ``|(Bbar K_T
v)_i| <= max_v sum_l |(B_v K_T)[i, l]| |v_l|``. So the hold is an additive term in the box
``b_h = h max_v |B_v K_T| Edot``, and (T1'), (T1'') with ``b + b_h`` in place of ``b`` certify
``E_c`` for the held law (both hold for every hull point and every ``w`` in the box, so the term
sharing ``Bbar`` with the loop is covered). ``b_h`` grows with the level (``ext``, ``reach``), so
(T1')'s floor does too, linearly in ``sqrt(c)``: a larger level is still the better chance for it
(``largest_level``). ``check_level(held_period=h)``; ``period`` is the constant certificate's
held rate (``pipeline.numerics.tube.sampled``), for files without a disturbance.

(T4') The hold's push to first order. ``b_h`` is ``h |B K_T| Edot`` over the whole ellipsoid,
about ``e`` itself; on a stiff hover loop (quadrotor_hill at 5 ms) it is far above what
the decay leaves. ``funnel.sampled`` (I6') splits it for a funnel's interval; ``E_c`` is that
argument's case with ``Q = P_T^-1`` constant (``Q' = 0``, rate 0, no interval end: every ``t``
gives the same rows), the offset at ``t_j`` the measurement's ``c = eta(t_j)`` (``|c| <= E``,
(T5); zero without it) and the additive term ``r + w`` with ``|r + w| <= |r| + b``. On ``[t_j,
t]``, ``tau = t - t_j`` in ``[0, h]``, while ``e`` is in ``E_c`` (up to the first exit, which is
all the invariance argument needs), ``|e'| <= Edot`` of (T4) (``held_speed``), ``Acl(s) = Abar(s)
+ Bbar(s) K_T`` and ``Mbar = (1/tau) int_{t_j}^t Acl(s) ds`` in ``conv{A_v' + B_v' K_T}``:

    e' = (Acl(t) - tau Bbar(t) K_T Mbar) e + R + r + w,
    R = Bbar(t) K_T (e(t_j) - e(t) + tau Mbar e(t)) + Bbar(t) K_T eta(t_j),

and (I6')'s (R) with ``C = E``, ``d = |r| + b`` and ``E`` bounds ``|R_i|`` componentwise
(``funnel.sampled.remainder_box``). (T1'')'s S-procedure with (I6')'s rows (the plain ones,
``tau = 0``, and one per vertex pair ``(v, v')`` at ``tau = h``: ``funnel.robust.RobustCheck``
with ``period``) and the box ``b + |r| + R``: for fixed ``z`` and ``alpha`` the quadratic form is
affine in ``tau``, in the weights of ``[Abar(t) Bbar(t)]``, in those of ``Mbar`` and in the
signal, so its largest value over their product of polytopes is at a vertex; the eigenvalue
below ``-LMI_MARGIN`` there gives ``V' < 0`` on ``V = c`` for the held law. ``E_c`` is certified
for it when (T1') or (T1'') holds with (T4)'s box, or (T4') holds (each is a proof of the same
boundary inequality; ``check_level`` tries them in that order). With ``h = 0`` none of this is
used.

(T5) A measurement error. The law sees ``x + eta``, ``|eta_i| <= E_i`` for every measurable
``eta`` (the scenario's ``uncertainty.measurement``): ``u = u_eq + K_T (e + eta)`` (held: ``u =
u_eq + K_T (e(t_j) + eta(t_j))``). ``E_c`` stays a set of the true state. The applied input is
``u_eq + K_T e + K_T eta`` with ``|(K_T eta)_j| <= (|K_T| E)_j``: the no-clipping check and
``Z_c``'s input box take ``reach + |K_T| E`` (so the hull covers the segment to the applied
``(x, u)``), and (T4)'s ``Edot`` its input term with it. As in (T4), ``f(x, u) - f(x_eq, u_eq)
= Abar e + Bbar K_T e + Bbar K_T eta`` with ``[Abar Bbar]`` in that hull, and ``|(Bbar K_T
eta)_i| <= max_v sum_l |(B_v K_T)[i, l]| E_l =: b_e,i``: one more additive term in a box, so
(T1'), (T1'') with ``b + b_h + b_e`` in place of ``b`` certify ``E_c`` for every ``eta`` (both
hold for every hull point and every signal in the box). ``b_e`` does not depend on the level:
it raises (T1')'s floor, as the disturbance does. With ``E = 0`` every number is (T1)-(T4)'s.

(T6) A larger set under a large bound (``hold_design``). The (T3) metric, certified at level ``c``,
holds ``sqrt(c)`` times the smallest set the disturbance leaves. Below ``ROOM`` times, the funnels'
ends (each at least its own smallest set, about the same size) find no room in it but at its
centre, so the largest set of ``terminal.robust`` (T6) is tried for the same gain and kept when
``largest_level`` certifies it with a larger volume. Where no metric of the LQR gain certifies
any level, (T6) designs the gain with its metric (``Y = K Q``) and the (T3) set of that gain
must certify too. Soundness is (T1')-(T5)'s: every set is checked from scratch like any other;
(T6) only chose its metric and gain. The nominals still end in the (T3) set
(``TerminalDesign.arrival``), and the funnels must end in the larger one (T2).

(T7) Parameters in the hull. Under declared parameter intervals, (T1')'s ``b`` from (U1) over the
whole certified box (``pipeline.numerics.uncertainty``) takes the parameters' term at the largest
thrust the box allows. Where that leaves no set, ``hold_design`` holds them as (U1)'s (T7) split:
the hull over ``Z_c`` and the parameter intervals (``uncertainty.parametric_hull``), and ``b`` the
declared disturbance plus the parameters' term at ``(x_eq, u_eq)`` alone
(``uncertainty.equilibrium_bound``). Then ``e' = (A + B K_T) e + r + w`` holds with ``[A B]`` in
that hull and ``|w| <= b`` for every parameter in its interval, so (T1')-(T6) go through word for
word (``check_level(parameters=...)``), the residual ``r`` still the nominal model's.

End tubes: ``pipeline.numerics.terminal.fit`` (the exact containment level, and the funnel's LMI).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import control
import numpy as np
import shapely
from scipy.optimize import least_squares
from shapely.affinity import affine_transform
from shapely.geometry.base import BaseGeometry
from shapely.ops import polylabel

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.funnel.law import LMI_MARGIN, corners
from pipeline.numerics.funnel.robust import RobustCheck
from pipeline.numerics.funnel.sampled import remainder_box
from pipeline.numerics.hull import DEFAULT_SEGMENTS, HullError
from pipeline.numerics.terminal.fit import containing_level as containing_level
from pipeline.numerics.terminal.fit import end_levels
from pipeline.numerics.terminal.robust import SHARES, largest_metric, robust_metric
from pipeline.numerics.tube.contraction import contraction_rate
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.tube.sampled import held_rate
from pipeline.numerics.uncertainty import additive_bound, equilibrium_bound, parametric_hull

EQUILIBRIUM_TOLERANCE = 1e-9  # ||f(x_eq, u_eq)|| accepted as an equilibrium
LEVEL_BISECTIONS = 24
DECAY_FRACTION = 0.5  # the level kept leaves V' <= -alpha V with half the linearisation's alpha
ROOM = 2.0  # a shaped terminal set this many times (T3)'s smallest one holds the funnels' ends


# where a terminal law's gain comes from: control.lqr at the equilibrium, the tube's (or first
# funnel's end) K, or designed with its metric (Y = K Q, (T6))
TerminalGain = Literal["lqr", "tube", "codesigned"]


class TerminalError(ValueError):
    """No terminal controller: no equilibrium in Goal, or its linearisation not stabilisable."""


@dataclass(frozen=True, kw_only=True)
class TerminalCheck:
    """What the certificate (T1') of one terminal ellipsoid found.

    Attributes:
      level: ``c``; decay: ``alpha`` (1/s, > 0 for a certificate, ``-inf`` without a hull);
      residual: ``||f(x_eq, u_eq)||_{P_T}``; input_slack: smallest room (input units) between
      ``u_eq + K_T e`` over ``E_c`` and the bounds; goal_margin: smallest room (P_T-norm radius)
      between ``E_c`` and Goal's boundary, its extra bounds and the scenario's ``state_bounds``;
      failures: one line per failed check; disturbance: ``w_max = max ||w||_{P_T}`` over the
      additive bound's box (0: the exact model); below_floor: the only failures are (T1')'s
      lower bound on the level (a larger level may hold, a smaller one cannot).
    """

    level: float
    decay: float
    residual: float
    input_slack: float
    goal_margin: float
    vertices: int
    failures: tuple[str, ...]
    disturbance: float = 0.0
    below_floor: bool = False

    @property
    def floor(self) -> float:
        """``(2 (||r||_{P_T} + w_max) / alpha)^2``: the smallest level (T1') certifies at this
        decay (``inf`` without a positive decay)."""
        if not self.decay > 0:
            return float("inf")
        return (2 * (self.residual + self.disturbance) / self.decay) ** 2

    @property
    def success(self) -> bool:
        return not self.failures


def goal_centre(scenario: Scenario) -> FloatArray:
    """(2,) the point of Goal farthest from its boundary (the pole of inaccessibility)."""
    point = polylabel(scenario.goal, tolerance=1e-6)
    return np.array([point.x, point.y])


def equilibrium(
    scenario: Scenario, position: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """``(x_eq (n,), u_eq (m,))`` with ``f = 0``, the position at ``position (2,)`` (default
    ``goal_centre``), the other states in Goal's bounds, the operating region and the state
    bounds and the inputs within their bounds; ``TerminalError`` when the least-squares search
    finds none."""
    dynamics, spec = scenario.dynamics, scenario.feedback
    n, m = len(scenario.state_names), len(scenario.input_names)
    position_index = list(scenario.position_index)
    free = [i for i in range(n) if i not in position_index]
    lower = np.concatenate([np.full(n, -np.inf), scenario.input_lower])
    upper = np.concatenate([np.full(n, np.inf), scenario.input_upper])
    boxes = {**scenario.operating_region, **scenario.goal_bounds}
    for name, (lo, hi) in [*boxes.items(), *scenario.state_bounds.items()]:
        k = (scenario.state_names + scenario.input_names).index(name)
        lower[k], upper[k] = max(lower[k], lo), min(upper[k], hi)
    z0 = np.concatenate([np.array(spec.reference_state, float), np.array(spec.reference_input)])
    z0[position_index] = goal_centre(scenario) if position is None else position
    keep = np.array(free + list(range(n, n + m)))
    lo, hi = lower[keep], upper[keep]
    if np.any(lo > hi):
        raise TerminalError("Goal's bounds and the operating region leave no state to hold")
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    start = np.clip(z0[keep], lo + 1e-6 * span, hi - 1e-6 * span)

    def residual(z: FloatArray) -> FloatArray:
        full = z0.copy()
        full[keep] = z
        return dynamics.f(full[:n], full[n:])

    found = least_squares(residual, start, bounds=(lo, hi), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    z = z0.copy()
    z[keep] = found.x
    error = float(np.linalg.norm(residual(found.x)))
    if not error <= EQUILIBRIUM_TOLERANCE:
        raise TerminalError(
            f"no equilibrium with the position at {np.round(z0[position_index], 3).tolist()}: "
            f"smallest |f(x, u)| found {error:.2g} within the bounds"
        )
    return z[:n], z[n:]


def lqr_terminal(
    scenario: Scenario, x_eq: FloatArray, u_eq: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``(K_T (m, n), P_T (n, n))``: ``control.lqr`` at the equilibrium with the scenario's
    feedback weights, ``K_T = -K_lqr`` (sign of ``u = u_eq + K_T e``), ``P_T`` the Riccati
    solution (``A_cl^T P_T + P_T A_cl = -(Q + K^T R K)`` at the equilibrium)."""
    spec = scenario.feedback
    A, B = scenario.dynamics.f_x(x_eq, u_eq), scenario.dynamics.f_u(x_eq, u_eq)
    try:
        K, S, _ = control.lqr(A, B, np.diag(spec.state_weights), np.diag(spec.input_weights))
    except (ValueError, np.linalg.LinAlgError, control.ControlArgument) as error:
        raise TerminalError(
            f"the linearisation at the equilibrium is not stabilisable ({error})"
        ) from None
    S = np.asarray(S, dtype=np.float64)
    return -np.asarray(K, dtype=np.float64), (S + S.T) / 2


def _mapped(geometry: BaseGeometry, M: np.ndarray) -> BaseGeometry:
    """``geometry`` under the linear map ``p -> M p``, ``M (2, 2)``."""
    return affine_transform(geometry, [M[0, 0], M[0, 1], M[1, 0], M[1, 1], 0.0, 0.0])


def _tube(scenario: Scenario, K: FloatArray, P: FloatArray) -> Tube:
    return Tube(
        K=K,
        P=P,
        rate=1.0,
        region={},
        state_names=scenario.state_names,
        input_names=scenario.input_names,
        position_index=scenario.position_index,
    )


def check_level(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray,
    P: FloatArray,
    level: float,
    segments: int = DEFAULT_SEGMENTS,
    min_decay: float = 0.0,
    period: float = 0.0,
    disturbance: FloatArray | None = None,
    held_period: float = 0.0,
    measurement: FloatArray | None = None,
    parameters: Uncertainty | None = None,
) -> TerminalCheck:
    """Check (T1') and the bounds for ``E_c``, ``c = level`` (module docstring), from scratch:
    hull over ``Z_c``, decay by ``numpy.linalg.eigvalsh``, no clipping, inside Goal. With a
    feedback ``period > 0`` (the law held) the decay is that of the held law: ``2 lambda_h`` of
    ``pipeline.numerics.tube.sampled`` at the continuous rate ``alpha / 2``. ``disturbance (n,)``:
    the additive bound ``b`` of (T1') (None or zeros: the exact model, (T1)). ``held_period >
    0``: the law held every ``held_period`` s, its hold an additive term (T4) joined to ``b``,
    or its push to first order (T4') (a funnel file's terminal law). ``measurement (n,)``: the
    box ``E`` of the error on the state the law sees (T5) (None or zeros: the exact state).
    ``parameters``: its parameter intervals join the hull's box (T7); ``disturbance`` must then
    hold its term at the equilibrium (``uncertainty.equilibrium_bound``)."""
    tube, r = _tube(scenario, K, P), float(np.sqrt(level))
    b = np.zeros(len(x_eq)) if disturbance is None else np.asarray(disturbance, dtype=np.float64)
    E = None if measurement is None else np.asarray(measurement, dtype=np.float64)
    measured = E is not None and bool(np.any(E > 0))
    failures = []
    # no clipping: u_eq +- r ||K_j P^-1/2|| (+ |K| E, (T5)) inside the bounds
    reach = tube.input_margin(r)
    if measured:
        reach = reach + np.abs(K) @ E
    slack = float(
        np.min(np.minimum(u_eq - reach - scenario.input_lower, scenario.input_upper - u_eq - reach))
    )
    if not slack >= 0:
        failures.append(f"the terminal law clips its inputs on E_c (slack {slack:.3g})")
    # inside Goal: the position disk in the whitened coordinates, and the extra bounds
    W = tube.position_whitening
    goal = _mapped(scenario.goal, W)
    centre = W @ x_eq[list(scenario.position_index)]
    inside = shapely.intersects_xy(goal, *centre)
    room = float(shapely.distance(shapely.points(centre), goal.boundary)) if inside else 0.0
    extent = tube.state_extent_per_radius
    for name, (lo, hi) in scenario.goal_bounds.items():
        i = scenario.state_names.index(name)
        room = min(room, (x_eq[i] - lo) / extent[i], (hi - x_eq[i]) / extent[i])
    if not room - r >= 0:
        failures.append(f"E_c leaves Goal (radius {r:.3g} > room {room:.3g} in P_T-norm)")
    # inside the physical envelope (state_bounds), which holds after T too
    envelope = np.inf
    for name, (lo, hi) in scenario.state_bounds.items():
        i = scenario.state_names.index(name)
        inside = min((x_eq[i] - lo) / extent[i], (hi - x_eq[i]) / extent[i])
        if not inside - r >= 0:
            failures.append(
                f"E_c leaves state_bounds.{name} = [{lo:g}, {hi:g}] (radius {r:.3g} > room "
                f"{inside:.3g} in P_T-norm)"
            )
        envelope = min(envelope, inside)
    if np.any(b > 0):  # the additive bound holds over uncertainty.certified_box only
        for name, (lo, hi) in scenario.operating_region.items():
            if name not in scenario.state_names or name in scenario.state_bounds:
                continue
            i = scenario.state_names.index(name)
            inside = min((x_eq[i] - lo) / extent[i], (hi - x_eq[i]) / extent[i])
            if not inside - r >= 0:
                failures.append(
                    f"E_c leaves operating_region.{name} = [{lo:g}, {hi:g}], where the "
                    f"disturbance bound holds (radius {r:.3g} > room {inside:.3g} in P_T-norm)"
                )
            envelope = min(envelope, inside)
    margin = min(room, envelope) - r
    # decay (T1) at every vertex of a sound hull over the bounding box Z_c
    centre_z = np.concatenate([x_eq, u_eq])  # (n + m,)
    half = np.concatenate([r * extent, reach])  # (n + m,)
    names = scenario.state_names + scenario.input_names
    box = {k: (float(c - w), float(c + w)) for k, c, w in zip(names, centre_z, half, strict=True)}
    residual = scenario.dynamics.f(x_eq, u_eq)
    residual_norm = float(np.sqrt(residual @ P @ residual))
    pushed = b  # (T4')'s box, set with the hull
    try:
        hull = parametric_hull(scenario, box, segments, parameters)
        decay, vertices = decay_rate(P, K, hull.A, hull.B), len(hull.vertices)
        if period > 0:
            decay = 2 * held_rate(P, K, hull.A, hull.B, decay / 2, period).held_rate
        if held_period > 0:  # (T4'): the push to first order, its remainder (R) as a box;
            # (T4): the hold as an additive term; both from one bound on |e'|
            E_0 = np.zeros(len(x_eq)) if E is None else E
            speed = held_speed(hull.A, hull.B, extent * r, reach, residual, b)
            pushed = b + np.abs(residual) + remainder_box(
                hull.A, hull.B, K, speed, E_0, np.abs(residual) + b, E_0, held_period
            )  # fmt: skip
            b = b + _held_box(hull.B, K, speed, held_period)
        if measured:  # (T5): the measurement's push as an additive term
            b = b + (np.abs(hull.B @ K) @ E).max(axis=0)
    except HullError as error:
        decay, vertices = -np.inf, 0
        failures.append(f"no Jacobian hull over E_c's bounding box: {error}")
    w = corners(b)  # (C, n)
    w_max = float(np.sqrt(np.einsum("ci,ij,cj->c", w, P, w).max())) if len(w) else 0.0  # (T1')
    if vertices and not (decay > 0 and decay >= min_decay):
        failures.append(
            f"V does not decrease on the boundary of E_c (decay {decay:.3g}/s, required "
            f"{min_decay:.3g}/s; residual {residual_norm:.2g})"
        )
    others = len(failures)
    floor = bool(vertices) and decay > 0 and not decay * r > 2 * (residual_norm + w_max)  # (T1')
    if floor and len(w) and period == 0:  # (T1''): the S-procedure may hold where (T1') does not
        floor = not joint_margin(P, K, hull.A, hull.B, r, b + np.abs(residual)) < -LMI_MARGIN
    if floor and held_period > 0:  # (T4'): or the held law's push to first order
        floor = not joint_margin(P, K, hull.A, hull.B, r, pushed, held_period) < -LMI_MARGIN
    if floor:
        failures.append(
            f"V does not decrease on the boundary of E_c (decay {decay:.3g}/s x radius {r:.3g} "
            f"<= 2 (residual {residual_norm:.2g} + disturbance {w_max:.3g}) in P_T-norm, and "
            "the S-procedure (T1'') does not hold either"
            + (", nor the held law's push to first order (T4'))" if held_period > 0 else ")")
        )
    return TerminalCheck(
        level=float(level),
        decay=float(decay),
        residual=residual_norm,
        input_slack=slack,
        goal_margin=float(margin),
        vertices=vertices,
        failures=tuple(failures),
        disturbance=w_max,
        below_floor=floor and not others,
    )


def hold_bound(
    A: FloatArray,
    B: FloatArray,
    K: FloatArray,
    extent: FloatArray,
    reach: FloatArray,
    residual: FloatArray,
    bound: FloatArray,
    period: float,
) -> FloatArray:
    """(n,) (T4)'s ``b_h = h max_v |B_v K| Edot``: the box of ``Bbar K (e(t_j) - e(t))`` for the
    law held every ``period`` s, with ``Edot`` of ``held_speed``; hull ``A (V, n, n)``, ``B (V,
    n, m)``, gain ``K (m, n)``, the ellipsoid's state and input extents ``extent (n,)``, ``reach
    (m,)``, the equilibrium's residual and the additive bound ``(n,)``."""
    return _held_box(B, K, held_speed(A, B, extent, reach, residual, bound), period)


def _held_box(B: FloatArray, K: FloatArray, speed: FloatArray, period: float) -> FloatArray:
    """(n,) ``h max_v |B_v K| Edot`` for ``B (V, n, m)``, ``K (m, n)``, ``speed`` = ``Edot
    (n,)``."""
    return np.asarray(period * (np.abs(B @ K) @ speed).max(axis=0), dtype=np.float64)


def held_speed(
    A: FloatArray,
    B: FloatArray,
    extent: FloatArray,
    reach: FloatArray,
    residual: FloatArray,
    bound: FloatArray,
) -> FloatArray:
    """(n,) (T4)'s ``Edot = max_v (|A_v| extent + |B_v| reach) + |residual| + bound``, a bound
    on ``|e'|`` while ``e`` and ``e(t_j)`` are in ``E_c`` (arguments as ``hold_bound``'s)."""
    speed = (np.abs(A) @ extent + np.abs(B) @ reach).max(axis=0) + np.abs(residual) + bound
    return np.asarray(speed, dtype=np.float64)


def joint_margin(
    P: FloatArray,
    K: FloatArray,
    A: FloatArray,
    B: FloatArray,
    radius: float,
    bound: FloatArray,
    period: float = 0.0,
) -> float:
    """Twice (T1'')'s eigenvalue: ``funnel.robust`` (I5) for the constant metric ``P (n, n)``,
    gain ``K (m, n)``, hull ``A (V, n, n)``, ``B (V, n, m)``, at ``radius`` and the box ``|w| <=
    bound (n,)``. Negative: ``V' < 0`` on ``V = radius^2`` for every hull point and ``w``.
    ``period > 0``: (T4')'s, with the held law's pushed rows (``funnel.sampled`` (I6')) and
    ``bound`` the box with its remainder."""
    inverse = np.linalg.inv(P)
    Q: FloatArray = np.stack([(inverse + inverse.T) / 2] * 2)  # one interval, Q' = 0
    hull = (np.concatenate([A, B], axis=2),)
    check = RobustCheck(Q, K[None], hull, 0.0, 1.0, radius, period)
    return 2 * float(check.margins(bound)[0][0])


def decay_rate(P: FloatArray, K: FloatArray, A: FloatArray, B: FloatArray) -> float:
    """``alpha = min_v -lambda_max(P^-1/2 M_v P^-1/2)``, ``M_v = A_cl^T P + P A_cl``,
    ``A_cl = A_v + B_v K``, over ``A (V, n, n)``, ``B (V, n, m)``: ``V' <= -alpha V`` (twice the
    contraction rate of ``pipeline.numerics.tube.contraction.contraction_rate``)."""
    return 2.0 * contraction_rate(P, K, A, B)


def largest_level(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray,
    P: FloatArray,
    period: float = 0.0,
    disturbance: FloatArray | None = None,
    held_period: float = 0.0,
    measurement: FloatArray | None = None,
    parameters: Uncertainty | None = None,
) -> TerminalCheck:
    """The largest level ``c`` certified with at least ``DECAY_FRACTION`` of the linearisation's
    decay (bisection on ``sqrt(c)``; the input and Goal bounds give the top), robust to the
    additive bound ``disturbance (n,)`` (T1'), for the law held every ``held_period`` s when it
    is > 0 (T4), the parameter intervals of ``parameters`` in the hull (T7). Every check but
    (T1')'s floor only gets harder as ``c`` grows, so the bisection finds the largest level
    passing those, and (T1') is checked there (it is the best
    chance: the floor is a lower bound, (T4)'s term growing with ``sqrt(c)`` too); the returned
    check fails when that level is below the floor."""
    robust = disturbance is not None and bool(np.any(np.asarray(disturbance) > 0))
    robust = robust or held_period > 0 or (measurement is not None and bool(np.any(measurement)))
    A0, B0 = scenario.dynamics.f_x(x_eq, u_eq), scenario.dynamics.f_u(x_eq, u_eq)
    linear = decay_rate(P, K, A0[None], B0[None])
    if period > 0:
        linear = 2 * held_rate(P, K, A0[None], B0[None], linear / 2, period).held_rate
    need = DECAY_FRACTION * linear
    tube = _tube(scenario, K, P)
    room = np.minimum(u_eq - scenario.input_lower, scenario.input_upper - u_eq)  # (m,)
    gain = tube.input_margin_per_radius  # (m,)
    by_input = np.where(gain > 0, np.maximum(room, 0.0) / np.where(gain > 0, gain, 1.0), np.inf)
    by_goal = check_level(scenario, x_eq, u_eq, K, P, 1.0).goal_margin + 1.0  # room in Goal
    hi = float(min(np.min(by_input), max(by_goal, 0.0)))

    def at(radius: float) -> TerminalCheck:
        return check_level(
            scenario, x_eq, u_eq, K, P, radius**2, min_decay=need, period=period,
            disturbance=disturbance, held_period=held_period, measurement=measurement,
            parameters=parameters,
        )  # fmt: skip

    best = at(hi)
    if best.success or (robust and best.below_floor):
        return best
    lo = 0.0
    for _ in range(LEVEL_BISECTIONS):
        mid = 0.5 * (lo + hi)
        trial = at(mid)
        if trial.success or (robust and trial.below_floor):
            lo, best = mid, trial
        else:
            hi = mid
    return best


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
    which ``design``'s terminal set, moved there unchanged (same ``K``, ``P``, level), still
    lies inside Goal as ``check_level`` tests it: Goal eroded by the set's position ellipse (in
    the whitened coordinates ``W p`` a disk of radius ``sqrt(level)``), and inside Goal's extra
    bounds and ``state_bounds`` on the position states. The erosion is shapely's buffer (arcs
    as segments), so the box is a guide, not a guarantee: a design at any of its points is
    checked from scratch (``hold_design``). None when nothing is left."""
    tube, r = _tube(scenario, design.K, design.P), float(np.sqrt(design.check.level))
    W = tube.position_whitening
    eroded = _mapped(scenario.goal, W).buffer(-r)
    if eroded.is_empty:
        return None
    region = _mapped(eroded, np.linalg.inv(W))
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
