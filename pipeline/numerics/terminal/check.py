"""The certificate of one terminal ellipsoid: ``u = u_eq + K_T e`` keeps ``E_c`` invariant.

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

(T7) Parameters in the hull. Under declared parameter intervals, (T1')'s ``b`` from (U1) over the
whole certified box (``pipeline.numerics.uncertainty``) takes the parameters' term at the largest
thrust the box allows. Where that leaves no set, ``terminal.design.hold_design`` holds them as
(U1)'s (T7) split: the hull over ``Z_c`` and the parameter intervals
(``uncertainty.parametric_hull``), and ``b`` the declared disturbance plus the parameters' term
at ``(x_eq, u_eq)`` alone (``uncertainty.equilibrium_bound``). Then ``e' = (A + B K_T) e + r +
w`` holds with ``[A B]`` in that hull and ``|w| <= b`` for every parameter in its interval, so
(T1')-(T5) go through word for word (``check_level(parameters=...)``), the residual ``r`` still
the nominal model's, and so does (T6)'s choice of a set (``terminal.design``).

``terminal.design`` chooses the equilibrium, the gain, the metric and the level; everything it
ships is checked here from scratch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.affinity import affine_transform
from shapely.geometry.base import BaseGeometry

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.funnel.law import LMI_MARGIN, corners
from pipeline.numerics.funnel.robust import RobustCheck
from pipeline.numerics.funnel.sampled import remainder_box
from pipeline.numerics.hull import DEFAULT_SEGMENTS, HullError
from pipeline.numerics.tube.contraction import contraction_rate
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.tube.sampled import held_rate
from pipeline.numerics.uncertainty import parametric_hull

LEVEL_BISECTIONS = 24
DECAY_FRACTION = 0.5  # the level kept leaves V' <= -alpha V with half the linearisation's alpha


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


def mapped(geometry: BaseGeometry, M: np.ndarray) -> BaseGeometry:
    """``geometry`` under the linear map ``p -> M p``, ``M (2, 2)``."""
    return affine_transform(geometry, [M[0, 0], M[0, 1], M[1, 0], M[1, 1], 0.0, 0.0])


def level_tube(scenario: Scenario, K: FloatArray, P: FloatArray) -> Tube:
    """The ellipsoid ``{e^T P e <= r^2}`` of the law ``K (m, n)``, ``P (n, n)`` as a ``Tube``
    (its extents per unit radius; the rate is not used)."""
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
    tube, r = level_tube(scenario, K, P), float(np.sqrt(level))
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
    goal = mapped(scenario.goal, W)
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
    def room_in(field: str, name: str, lo: float, hi: float, where: str = "") -> float:
        """The room (P_T-norm radius) between ``x_eq`` and ``[lo, hi]`` in state ``name``; a
        failure named ``field.name`` when ``E_c`` leaves it."""
        i = scenario.state_names.index(name)
        room_i = min((x_eq[i] - lo) / extent[i], (hi - x_eq[i]) / extent[i])
        if not room_i - r >= 0:
            failures.append(
                f"E_c leaves {field}.{name} = [{lo:g}, {hi:g}]{where} (radius {r:.3g} > room "
                f"{room_i:.3g} in P_T-norm)"
            )
        return room_i

    envelope = np.inf
    for name, (lo, hi) in scenario.state_bounds.items():
        envelope = min(envelope, room_in("state_bounds", name, lo, hi))
    if np.any(b > 0):  # the additive bound holds over uncertainty.certified_box only
        for name, (lo, hi) in scenario.operating_region.items():
            if name not in scenario.state_names or name in scenario.state_bounds:
                continue
            where = ", where the disturbance bound holds"
            envelope = min(envelope, room_in("operating_region", name, lo, hi, where))
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
    tube = level_tube(scenario, K, P)
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
