"""A time-varying funnel around one nominal trajectory: gains ``K[k]``, metrics ``P[k]``, level rho.

Problem. Nominal ``x_ref``, ``u_ref[k]`` held on ``[t_k, t_k+1)``, ``t_k = k Ts`` (eq. (1)).
Feedback ``u = u_ref[k] + K[k] e``, ``e = x - x_ref``; funnel
``E(t) = {x : e^T P(t) e <= rho^2}``. ``Q = P^-1`` is LINEAR in t on each sample interval,

    Q(t) = (1 - s) Q[k] + s Q[k+1],  s = (t - t_k) / Ts,  dQ/dt = (Q[k+1] - Q[k]) / Ts,      (F1)

so between samples ``P(t) = ((1 - s) P[k]^-1 + s P[k+1]^-1)^-1`` (not linear in P).

Error dynamics. ``de/dt = f(x_ref + e, u_ref + K e) - f(x_ref, u_ref) = (Abar + Bbar K) e`` with
``[Abar Bbar] = int_0^1 [f_x f_u](x_ref + r e, u_ref + r K e) dr``. While ``x`` is in the tube and
the input in its bounds (no clipping), the segment lies in the box ``Z_k`` holding the tube and the
inputs on the interval, so ``[Abar Bbar]`` lies in the hull ``conv{[A_v B_v]}`` of ``[f_x f_u]``
over ``Z_k`` (``pipeline.numerics.hull``; the hull is convex and holds every Jacobian on the
segment, hence their average).

Certificate. ``V = e^T P e`` has ``dV/dt = e^T (dP/dt + Acl^T P + P Acl) e``, ``Acl = A + B K``, so
``dV/dt <= -2 lambda V`` follows from ``dP/dt + Acl^T P + P Acl + 2 lambda P <= 0``. Multiply by
``Q`` on both sides; ``dP/dt = -P (dQ/dt) P`` gives ``Q (dP/dt) Q = -dQ/dt``:

    L(t, J) = -dQ/dt + Acl Q(t) + Q(t) Acl^T + 2 lambda Q(t) <= 0,  Acl = A + B K[k].        (F2)

With ``K[k]`` FIXED (from time-varying LQR) ``Y(t) = K[k] Q(t)`` is affine in t and (F2) is linear
in the unknowns ``Q[k], Q[k+1]``; no product of unknowns appears. We impose (F2) with margin,
``+ (2 lambda + eps) Q``, at ``s = 0`` and ``s = 1`` for every vertex ``J_v = [A_v B_v]``:

    L(0, J_v) <= 0,  L(1, J_v) <= 0  for all v.                                             (F3)

Why (F3) implies (F2) for all t in the interval and all J in the hull: for fixed ``s``, ``L`` is
affine in ``J`` (``Acl`` is linear in ``[A B]`` for fixed ``K``), so ``J = sum_v mu_v J_v`` with
``mu >= 0, sum mu = 1`` gives ``L(s, J) = sum_v mu_v L(s, J_v)``; for fixed ``J_v``, ``L`` is affine
in ``s`` by (F1), so ``L(s, J_v) = (1 - s) L(0, J_v) + s L(1, J_v)``. A nonnegative combination of
negative semidefinite matrices is negative semidefinite. (``L`` is bilinear, not jointly affine,
in ``(s, J)``; the two steps above need only affinity in each.) ``Q`` is continuous at ``t_k``
and ``K`` switches there, so ``V`` is continuous and the bound holds across samples.
Invariance: while ``V <= rho^2`` the state is in ``Z_k`` (the box holds the tube at level rho,
checked below), so ``V`` cannot grow and no solution starting in ``E(0)`` leaves the funnel.
That is for a law tracking the exact nominal. The shipped law tracks it interpolated on a grid;
the offset adds a bounded term (``funnel.law`` (I1)-(I3)) under which only the level set is
invariant (``V`` may grow deep inside the funnel, never across its boundary): the certify stage
and the funnel stage's re-check prove that, and the controller stage picks the grid.

Pieces (HOLD). The LMIs are imposed on pieces of ``HOLD`` sample intervals ``[t_a, t_b)``: ``K``
is held (``K[k] = K[a]``, the LQR gain at the piece's start), ``Q`` is linear in t over the whole
piece, and the hull is one polytope over a box ``Z_a`` holding every sample interval's box of the
piece. (F3) at the piece's two ends then implies (F2) on the whole piece by the argument above
(``s = (t - t_a) / (t_b - t_a)``), hence on each of its sample intervals; the funnel is stored
per sample interval (``Q[k]`` interpolated by (F1), the piece's ``K`` and hull repeated), and
``check_funnel`` re-checks (F3) at both ends of every SAMPLE interval: at a sample time inside a
piece ``L`` is the convex combination of the piece's end LMIs, so nothing it proves is weaker.
Every feasible point of the piecewise program is feasible for the per-sample program with the
same held gain (a tighter program); it has ``HOLD`` times fewer LMIs (the solver's time is
proportional to their number), at the price of a slightly wider funnel (``python -m bench
funnel``: position extent +5%, thrust extent +8% on quadrotor_hill_flythrough with ``HOLD = 2``).

Design. 1. Seed: discrete Riccati recursion on the zero-order-hold discretisation of the nominal's
linearisation, weights ``Ts diag(state_weights)``, ``Ts diag(input_weights)`` -> ``K[k]``,
``P_lqr[k]`` (F4). 2. Boxes: ``Q_seed = c P_lqr^-1`` scaled to contain the required initial
ellipsoid; the box of each variable the Jacobian depends on is the nominal's enclosure
(``funnel.bounds``, E1-E2) widened by ``allowance`` times the seed's extent, clipped to the state
and input bounds (sound: the level keeps the tube inside them). The seed over-estimates the
funnel (quadrotor_hill_flythrough: pitch 4-5x, thrust 1.7x), so ``allowance = 1``: with 2 the pitch
box was the whole envelope on every interval, the hull so wide that the program was nearly
infeasible (Clarabel stopped at 200 iterations, "AlmostSolved", with (F3) violated: demo 3 rejected,
demo 9 held 0.916 of its set after a second solve, ~60 s each). An angle's box is also capped to
whole arc segments of the hull (``funnel.pieces``: 6 hull vertices instead of 10 on
quadrotor_hill_flythrough, and a tighter hull); if the capped boxes cannot hold the whole initial
set, the uncapped ones are tried and the better funnel kept. 3. LMIs (F3) plus ``Q[0] >= tau
Q_init[j]`` for every required matrix (one ellipsoid, or ``v v^T`` per corner ``v`` of a polytope:
by the Schur complement, ``Q[0] >= tau v v^T`` iff ``v^T (Q[0] / tau)^-1 v <= 1``) and, at level 1,
the tube inside every box (``Q_ii <= s_i^2``, ``K_j Q K_j^T <= s_j^2`` at both ends), its position
disk clear of Unsafe (``C Q C^T <= d_k^2 I``, ``d_k`` the nominal's sound clearance on the interval)
and inside Goal at T; all linear in Q. Maximise ``tau <= 1`` first, then minimise
``sum_k tr(W Q[k])``, ``W`` weighting position by ``1/d^2`` and inputs by their inverse squared
half-ranges; Clarabel, the program assembled by ``funnel.lmi`` (cvxpy states the same program
for the tests). ``Q / tau`` holds the whole initial set at level 1 and meets every cap at level
``sqrt(tau)``. 4. Level: ``rho = min(sqrt(tau), funnel_limits)`` (``funnel.bounds``; Goal there
is the exact ellipse).
5. ``funnel.check.check_funnel``: numpy only; a funnel that fails it is rejected. Step 1 and (F5)
are ``funnel.seed``, step 3's program ``funnel.program``.

Co-designed gains (F6), under a disturbance. The LQR gains are designed for the nominal's
linearisation, not for the disturbance, and a funnel around them holds little of it. With
``Y = K Q`` as unknowns too (Boyd et al., LMIs in System and Control Theory, section 7.2.1)
(F2) is linear in ``(Q, Y)``: ``A_v Q + B_v Y + (.)^T``
replaces ``Acl Q + (.)^T``, the input caps become ``[[Q, Y_i^T], [Y_i, room^2]] >= 0`` (Schur)
and the inputs' spread at level 1, ``K Q K^T = Y Q^-1 Y^T <= Z``, is weighted in the objective
as the fixed-gain program weights ``K Q K^T``. With ``Y[j]`` held on a piece the law would be
``K(t) = Y[j] Q(t)^-1``, which is not what the controller ships, so (F6) only DESIGNS the gains:
``K[j] = Y[j] Qbar[j]^-1`` (``Qbar`` the piece's mean metric) is then held and the funnel solved
again by (F3) with it, exactly as with the LQR gains, and checked by ``check_funnel``. Nothing
proven depends on (F6). It is tried after the LQR gains, when none of their funnels holds the
whole design level (the LQR gains' funnels are the narrower ones where both hold: the
re-optimization has more room in them).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TypedDict, Unpack

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.bounds import (
    Enclosure,
    funnel_limits,
)
from pipeline.numerics.funnel.check import (
    LEVEL_SLACK,
    Funnel,
    certificate_margins,
    check_funnel,
)
from pipeline.numerics.funnel.law import LawOffset
from pipeline.numerics.funnel.lmi import FunnelProgram, codesign_gains, solve_clarabel
from pipeline.numerics.funnel.pieces import interpolate, piece_hulls, pieces
from pipeline.numerics.funnel.program import funnel_program
from pipeline.numerics.funnel.seed import disturbance_seed, lqr_seed
from pipeline.numerics.hull import HullError, arc_variables
from pipeline.numerics.terminal.fit import TerminalTarget, containing_level


class _Parts(TypedDict, total=False):
    """The ``Funnel`` fields a search has found so far (``_Search.result`` defaults the rest)."""

    K: FloatArray
    P: FloatArray
    rho: float
    margins: FloatArray
    boxes: FloatArray
    variables: tuple[str, ...]
    vertices: tuple[FloatArray, ...]
    enclosure: Enclosure | None
    limits: Mapping[str, float]
    binding: str
    multiplier: float
    codesigned: bool


class _Hulls(TypedDict):
    """The ``Funnel`` fields fixed once the hulls are built (``_Search.hulls``)."""

    boxes: FloatArray
    variables: tuple[str, ...]
    vertices: tuple[FloatArray, ...]
    enclosure: Enclosure


# The LMIs' margin eps in (2 lambda + eps) Q: a solution that fails the numpy check (the solver
# meets (F3) only to its tolerance, relative to the largest entries of Q) is solved again with a
# larger margin.
MARGINS = (1e-3, 1e-2)
# With a disturbance (funnel.robust (I5)): the S-procedure multipliers alpha tried (1/s), and the
# margin eps of each, as a share of alpha (room for the interpolated reference's term (I2)). Steps
# of at most 1.7x up to 3: a held law's funnels hold their cells whole at 0.5 or 0.7 where 0.3 and
# 1.0 held 76-96% of them.
ROBUST_MULTIPLIERS = (0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
ROBUST_MARGIN = 0.05
WHOLE_ROUNDING = 1e-6  # a level this close below the whole design level stops the search
# Sample intervals per LMI piece: K is held and Q = P^-1 linear in t over each piece (see HOLD in
# the module docstring).
HOLD = 2


@dataclass
class MultiplierSearch:
    """The robust program's multipliers ``alpha`` (``ROBUST_MULTIPLIERS``), searched upwards per
    gains family (LQR, (F6)) as a unimodal line search, as the invariant ellipsoid's ``alpha``
    is (Boyd et al., LMIs in System and Control Theory, section 6.1.3): a family is past its
    best at the first ``alpha`` after a feasible one that is infeasible or holds less (``tau``,
    capped at the whole design level 1). Only the search: every funnel kept is checked as any
    other, so nothing proven depends on it."""

    best: dict[bool, float] = field(default_factory=dict)  # family -> its last feasible tau
    stopped: set[bool] = field(default_factory=set)

    def record(self, codesign: bool, tau: float) -> None:
        """A solve of ``codesign``'s family with ``tau`` (<= 0: infeasible, no gains or no
        funnel)."""
        held = min(tau, 1.0)
        if codesign in self.best and held < self.best[codesign]:
            self.stopped.add(codesign)
        if held > 0:
            self.best[codesign] = held

    def past_best(self, codesign: bool) -> bool:
        """Whether ``codesign``'s family has stopped."""
        return codesign in self.stopped


def _outside(terminal: TerminalTarget, end: FloatArray, funnel: Funnel, T: float) -> str | None:
    """Why ``E(T)`` (around ``end (n,)``) is not inside ``terminal`` (exact level), or None."""
    radius = funnel.rho * float(np.exp(-funnel.rate * T))
    needed = containing_level(terminal.P, end - terminal.x_eq, funnel.P[-1], radius)
    if needed <= terminal.level:
        return None
    return (
        f"E(T) is not inside the terminal ellipsoid (it needs level {needed:.4g} > "
        f"{terminal.level:.4g})"
    )


def synthesize_funnel(
    scenario: Scenario,
    trajectory: Trajectory,
    *,
    state_bounds: Mapping[str, tuple[float, float]] | None = None,
    initial: FloatArray | None = None,
    rate: float = 0.0,
    allowance: float = 1.0,
    segments: int = 1,
    disturbance: FloatArray | None = None,
    terminal: TerminalTarget | None = None,
    period: float = 0.0,
    codesign: bool = True,
    widen: bool = True,
    from_multiplier: float = 0.0,
    codesign_first: bool = False,
    pushed: frozenset[int] | None = None,
) -> Funnel:
    """Synthesize and check the funnel around ``trajectory`` (one: ``xs (N+1, n)``, ``us (N, m)``,
    its dense grid); see the module docstring.

    Args:
      state_bounds: state name -> (lower, upper) the tube must respect (the physical envelope).
      initial: (n, n) ``Q_init`` (positive semidefinite): ``E(0)`` at level 1 must hold
        ``{Q_init^1/2 v : |v| <= 1}`` (degenerate for a slice, e.g. Init's free directions);
        or (p, n, n), every one of them (``Q_init[j] = v_j v_j^T``: the points ``x0 +- v_j``,
        the corners of the hull of the start's cells of Init, ``pipeline.numerics.funnel.cells``);
        default the seed's shape with position extent ``scenario.clearance``.
      rate: lambda of (F2). Default 0: the tube's level is constant and ``Q(t)`` itself shrinks
        where the closed loop contracts (``Q e^{-2 lambda t}`` would satisfy (F2) with rate 0
        too, so a positive rate only restricts the shape); the LMI margin stays (``MARGINS``).
      allowance: the hull boxes are the nominal's enclosure widened by this times the seed tube.
      segments: pieces per angle-like block of the local hulls.
      disturbance: (n,) ``d``: the funnel must hold for ``xdot = f(x, u) + w`` with any
        ``|w_i| <= d_i`` (``funnel.robust`` (I5)). (F3) is then joined with each corner ``w_c``
        by the S-procedure (``funnel.lmi``) for the multipliers ``alpha`` of
        ``ROBUST_MULTIPLIERS`` upwards (with margin ``eps = ROBUST_MARGIN alpha``), up to the
        first past a feasible one that is infeasible or holds less; the hull boxes hold the
        seed's disturbance extent (F5, ``disturbance_seed``); the LQR gains first, then gains
        co-designed with the metric (F6); the funnel with the highest checked level is kept
        (the first that holds the whole design level).
      terminal: the terminal ellipsoid ``E(T)`` must lie in (``terminal.fit.TerminalTarget``,
        e.g. from ``terminal.hold_design``): (T2) on ``Q`` at ``T`` in the program, and the exact
        containment level as a limit on rho (``terminal``; sound whatever the solver returned)
        and re-checked after ``check_funnel``. A nominal ending outside it has no funnel.
      period: ``h`` (s) of a held law to design for (0: continuous): with ``disturbance``, the
        program imposes (F3) also on each vertex's first-order push (``funnel.sampled``
        (I6') at ``tau = h``, ``paired_vertices``), so the disturbance need only hold (I6')'s
        remainder box (R) on top of the declared one. A design heuristic: the funnel returned
        is checked for the continuous law under ``disturbance`` here, and the held law's check
        is the caller's (``stages.funnel``).
      pushed: with ``period``, the sample intervals whose pieces get (I6')'s rows (None: every
        piece; ``stages.funnel`` first names those where the held law's check failed: a piece's
        rows double its LMIs, and the solve time grows faster). A design choice too.
      codesign: with ``disturbance``, try gains co-designed with the metric (F6) after the LQR
        gains' multipliers (False: the LQR gains only; ``stages.funnel`` for a held law, whose
        push (I6) the (F6) program cannot see: it is bilinear in the gains).
      widen: where the capped angle boxes do not hold the whole initial set, solve again on the
        seed's uncapped boxes and keep the better funnel (False: the capped boxes only, half the
        programs of a search that falls short; ``stages.funnel``'s redesign for a held or
        measured law, whose programs are the costliest). A design choice: nothing proven
        depends on it.
      from_multiplier: with ``disturbance``, the search starts at the first multiplier of
        ``ROBUST_MULTIPLIERS`` at least this large (``stages.funnel``'s redesign starts where
        the first design's program was feasible: the redesign's program adds the held law's
        rows and box to it). A design choice too.
      codesign_first: with ``disturbance`` and ``codesign``, search the (F6) gains' multipliers
        before the LQR gains' (a re-optimize round's funnel around a nominal whose last funnel
        needed (F6) gains, ``stages.certificates.rounds``), and the LQR gains' only where (F6)
        certified no funnel at all: the first funnel holding the whole design level is kept,
        else the highest. A design choice too.
    """
    start = time.perf_counter()
    setup = _search_setup(
        scenario, trajectory, state_bounds=state_bounds, initial=initial, rate=rate,
        disturbance=disturbance, terminal=terminal,
    )  # fmt: skip
    search = _Search(
        scenario=scenario, trajectory=trajectory, setup=setup, allowance=allowance,
        segments=segments, terminal=terminal, period=period, pushed=pushed, codesign=codesign,
        codesign_first=codesign_first, from_multiplier=from_multiplier, start=start,
    )  # fmt: skip
    funnel = search.attempt(tight=True)
    capped = bool(arc_variables(scenario.dynamics))  # without angles both attempts are the same
    if widen and capped and (not funnel.success or funnel.limits["design"] < 1.0):
        # The capped boxes could not hold the whole initial set: the seed's boxes, keep the better.
        wide = search.attempt(tight=False)
        funnel = max(funnel, wide, key=lambda f: (f.success, f.rho))
    return dataclasses.replace(funnel, seconds=time.perf_counter() - start)


@dataclass(frozen=True, kw_only=True)
class _Setup:
    """What every attempt of one ``synthesize_funnel`` call shares: its checked arguments and the
    seed (steps 1-2 of the module docstring); N sample intervals in S pieces of ``HOLD``.

    Attributes:
      state_bounds: state name -> (lower, upper), every name a state's.
      robust: (n,) the disturbance bound ``d``; None: the exact model (none, or every bound 0).
      rate: lambda of (F2).
      K: (N, m, n) the LQR gains (F4), each piece's first held over the piece.
      P_lqr: (N+1, n, n) the LQR cost-to-go (a rejected funnel's ``P``).
      bounds: (S+1,) each piece's first sample interval, then N (``funnel.pieces.pieces``).
      Q_seed: (N+1, n, n) ``P_lqr^-1`` scaled to hold every ``Q_init[j]`` at t = 0, plus the
        disturbance's extent (F5): the tube that sizes the hull boxes.
      Q_init: (p, n, n) the initial set's matrices (``synthesize_funnel``'s ``initial``).
    """

    state_bounds: Mapping[str, tuple[float, float]]
    robust: FloatArray | None
    rate: float
    K: FloatArray
    P_lqr: FloatArray
    bounds: np.ndarray
    Q_seed: FloatArray
    Q_init: FloatArray

    @property
    def N(self) -> int:
        """Sample intervals."""
        return len(self.K)

    @property
    def S(self) -> int:
        """Pieces."""
        return len(self.bounds) - 1


def _search_setup(
    scenario: Scenario,
    trajectory: Trajectory,
    *,
    state_bounds: Mapping[str, tuple[float, float]] | None,
    initial: FloatArray | None,
    rate: float,
    disturbance: FloatArray | None,
    terminal: TerminalTarget | None,
) -> _Setup:
    """``synthesize_funnel``'s arguments of these names checked (a ValueError names what is
    wrong) and the search's seed: LQR gains held on pieces, ``Q_seed``, ``Q_init``."""
    state_bounds = MappingProxyType(dict(state_bounds or {}))  # read-only, as _Setup is frozen
    robust = _disturbance_bound(scenario, disturbance)
    rate = float(rate)
    _check_nominal(scenario, trajectory, state_bounds, terminal)
    K, P_lqr = lqr_seed(
        scenario, trajectory, stationary_end=robust is not None and terminal is not None
    )
    bounds = pieces(len(K), HOLD)
    K = K[np.repeat(bounds[:-1], np.diff(bounds))]  # each piece holds its first gain
    Q_seed = np.linalg.inv(P_lqr)
    Q_init = _initial_sets(scenario, initial, Q_seed[0])
    L_inv = np.linalg.inv(np.linalg.cholesky(Q_seed[0]))
    # Q_seed[0] >= every Q_init[j]; under a disturbance, plus the extent that holds it (F5)
    seed_level = np.linalg.eigvalsh(L_inv @ Q_init @ L_inv.T)[:, -1].max()
    Q_seed = Q_seed * seed_level
    guess = None if robust is None else disturbance_seed(scenario, trajectory, K, robust)
    if guess is not None:
        Q_seed = Q_seed + guess  # holds both the initial set and the disturbance's extent
    return _Setup(
        state_bounds=state_bounds, robust=robust, rate=rate, K=K, P_lqr=P_lqr, bounds=bounds,
        Q_seed=Q_seed, Q_init=Q_init,
    )  # fmt: skip


def _disturbance_bound(scenario: Scenario, disturbance: FloatArray | None) -> FloatArray | None:
    """``disturbance`` (n,) checked (every bound >= 0); None if it is None or every bound is 0."""
    if disturbance is None:
        return None
    robust = np.asarray(disturbance, dtype=np.float64)
    if robust.shape != (scenario.n,) or not np.all(robust >= 0):
        raise ValueError(f"funnel: disturbance {disturbance!r}; expected {scenario.n} bounds >= 0")
    return robust if np.any(robust > 0) else None  # none: exactly the nominal design


def _check_nominal(
    scenario: Scenario,
    trajectory: Trajectory,
    state_bounds: Mapping[str, tuple[float, float]],
    terminal: TerminalTarget | None,
) -> None:
    """Raises a ValueError unless ``trajectory`` is one finite trajectory, ``state_bounds``
    names states only and the nominal ends inside ``terminal`` (if any)."""
    xs = trajectory.dense_xs
    if xs.ndim != 2 or trajectory.us.ndim != 2:
        raise ValueError(f"funnel: expected one trajectory, got dense_xs of shape {xs.shape}")
    bad = np.argwhere(~np.isfinite(xs))
    if len(bad):
        k, i = bad[0]
        raise ValueError(
            f"funnel: non-finite state '{scenario.state_names[i]}' at dense index {k} "
            f"(t = {trajectory.dense_ts[k]:.3f} s)"
        )
    for name in state_bounds:
        if name not in scenario.state_names:
            raise ValueError(
                f"funnel: state_bounds names '{name}', not one of {scenario.state_names}"
            )
    if terminal is not None and not terminal.share(xs[-1]) < 1:
        raise ValueError(
            f"funnel: the nominal ends at {np.round(xs[-1], 3).tolist()}, outside the terminal "
            f"ellipsoid ({terminal.share(xs[-1]):.3g} of its radius from its centre)"
        )


def _initial_sets(scenario: Scenario, initial: FloatArray | None, seed: FloatArray) -> FloatArray:
    """(p, n, n) ``Q_init`` of ``synthesize_funnel``'s ``initial`` (checked); None: the seed's
    ``Q_seed[0]`` shape ``seed (n, n)`` with position extent ``scenario.clearance``."""
    if initial is None:
        c = list(scenario.position_index)
        extent = np.linalg.eigvalsh(seed[np.ix_(c, c)])[-1]
        initial = seed * scenario.clearance**2 / extent
    Q_init = np.asarray(initial, dtype=np.float64)
    if Q_init.ndim == 2:
        Q_init = Q_init[None]
    if Q_init.ndim != 3 or Q_init.shape[1:] != (scenario.n, scenario.n) or not len(Q_init):
        raise ValueError(
            f"funnel: initial of shape {np.shape(initial)}; expected ({scenario.n}, "
            f"{scenario.n}) or (p, {scenario.n}, {scenario.n}) with p >= 1"
        )
    return Q_init


@dataclass(frozen=True, kw_only=True)
class _Try:
    """One program of an attempt: the LMI margin ``eps``, the S-procedure ``multiplier``
    ``alpha`` (0: no disturbance) and the gains: ``codesigned`` with the metric (F6), or the LQR
    gains."""

    margin: float
    multiplier: float
    codesigned: bool


@dataclass(frozen=True, kw_only=True)
class _Candidate:
    """A funnel one try certified (its message not yet written): ``margin`` the try's LMI
    margin, ``when`` (s) the time its binding limit binds."""

    funnel: Funnel
    margin: float
    when: float


@dataclass(frozen=True, kw_only=True)
class _Failed:
    """Why one try certified no funnel; ``final``: the exact model's program had no solution
    holding any of the initial set, which ends the attempt."""

    reason: str
    final: bool = False


@dataclass(frozen=True, kw_only=True)
class _Search:
    """One ``synthesize_funnel`` call's search for a funnel (steps 3-5 of the module docstring)
    from its ``setup``; ``start``, the call's ``time.perf_counter()``. The other fields are
    ``synthesize_funnel``'s arguments of the same names."""

    scenario: Scenario
    trajectory: Trajectory
    setup: _Setup
    allowance: float
    segments: int
    terminal: TerminalTarget | None
    period: float
    pushed: frozenset[int] | None
    codesign: bool
    codesign_first: bool
    from_multiplier: float
    start: float

    def attempt(self, tight: bool) -> Funnel:
        """Hulls (capped angle boxes if ``tight``), the program, its check (``MARGINS``)."""
        hulls = self.hulls(tight)
        if isinstance(hulls, str):
            return self.result(False, f"funnel: {hulls}")
        failures: list[str] = []
        best: _Candidate | None = None
        multipliers = MultiplierSearch()
        for one in self.tries():
            if self.setup.robust is not None and multipliers.past_best(one.codesigned):
                continue
            if self.codesign_first and not one.codesigned and best is not None:
                continue  # (F6) certified a funnel short of the whole level: not the LQR gains
            # a solution within the solver's tolerance may fail the check: the next margin
            tried = self.one_try(hulls, multipliers, one)
            if isinstance(tried, _Failed):
                if tried.final:
                    return self.result(False, f"funnel: {tried.reason}", **hulls)
                failures.append(f"margin {one.margin:g}: {tried.reason}")
                continue
            # robust: the highest checked level is kept; none beats the design's whole level
            # (to the solver's tolerance: a funnel whose caps held to it, level ~1 - 1.1e-7,
            # never stopped the search at rho >= 1 - LEVEL_SLACK)
            rho = tried.funnel.rho
            if self.setup.robust is None or rho >= (1 - LEVEL_SLACK) * (1 - WHOLE_ROUNDING):
                chosen = tried
                break
            if best is None or rho > best.funnel.rho:
                best = tried
        else:
            if best is None:
                return self.result(False, f"funnel rejected: {_grouped(failures)}", **hulls)
            chosen = best
        return self.described(chosen, tight)

    def tries(self) -> list[_Try]:
        """An attempt's programs in order: each of ``MARGINS``; with a disturbance each
        multiplier of ``ROBUST_MULTIPLIERS`` from ``from_multiplier`` up, per gains family."""
        if self.setup.robust is None:
            return [_Try(margin=margin, multiplier=0.0, codesigned=False) for margin in MARGINS]
        # robust: every multiplier with the LQR gains, then with co-designed gains (F6) (the
        # other way round with codesign_first)
        families = (
            ((True, False) if self.codesign_first else (False, True)) if self.codesign else (False,)
        )
        return [
            _Try(margin=ROBUST_MARGIN * alpha, multiplier=alpha, codesigned=family)
            for family in families
            for alpha in ROBUST_MULTIPLIERS
            if alpha >= min(self.from_multiplier, ROBUST_MULTIPLIERS[-1])
        ]

    def hulls(self, tight: bool) -> _Hulls | str:
        """The pieces' hulls and boxes (``funnel.pieces``; angle boxes capped if ``tight``), or
        why there are none."""
        setup = self.setup
        try:
            variables, boxes, vertices, enclosure = piece_hulls(
                self.scenario, self.trajectory, setup.Q_seed, setup.K, setup.state_bounds,
                self.allowance, self.segments, setup.bounds, tight,
            )  # fmt: skip
        except HullError as error:
            return str(error)
        return {
            "boxes": boxes, "variables": variables, "vertices": vertices, "enclosure": enclosure
        }  # fmt: skip

    def one_try(
        self, hulls: _Hulls, multipliers: MultiplierSearch, one: _Try
    ) -> _Candidate | _Failed:
        """The program of ``one`` (its gains designed first if ``codesigned``), solved and its
        funnel checked; under a disturbance, the program's ``tau`` recorded in ``multipliers``."""
        setup = self.setup
        gains = setup.K
        if one.codesigned:  # (F6): gains designed with the metric, then held ((F3))
            designed = codesign_gains(self.program(hulls, setup.K, one, codesign=True))
            if isinstance(designed, str):  # no gains to hold: nothing new to solve
                multipliers.record(one.codesigned, 0.0)
                return _Failed(reason=f"(F6) {designed} over {setup.N} intervals")
            gains = designed[0][np.repeat(np.arange(setup.S), np.diff(setup.bounds))]
        solution = solve_clarabel(self.program(hulls, gains, one))
        if isinstance(solution, str) or solution[1] <= 1e-6:
            failure = (
                f"{solution} over {setup.N} intervals"
                if isinstance(solution, str)
                else f"no funnel holds any of the initial set (tau {solution[1]:.2g})"
            )
            if setup.robust is None:
                return _Failed(reason=failure, final=True)
            multipliers.record(one.codesigned, 0.0)
            return _Failed(reason=failure)
        Q_ends, tau = solution
        multipliers.record(one.codesigned, tau)
        # eq. (P1) at every sample time; E(0) at level 1 holds the initial set, the caps
        # hold at level sqrt(tau)
        Q = interpolate(Q_ends, setup.bounds) / tau
        lowest = np.linalg.eigvalsh(Q)[:, 0]
        if not lowest.min() > 1e-12 * np.abs(Q).max():  # the solver's rounding: no metric
            return _Failed(
                reason=f"Q[{int(np.argmin(lowest))}] is not positive definite ({lowest.min():.3g})"
            )
        return self.checked(hulls, one, gains, Q, tau)

    def program(
        self, hulls: _Hulls, gains: FloatArray, one: _Try, codesign: bool = False
    ) -> FunnelProgram:
        """(F3)'s program (``funnel.program``) for ``gains (N, m, n)`` held on the pieces; with
        ``codesign`` the (F6) program, which the gains only seed."""
        setup = self.setup
        return funnel_program(
            self.scenario, self.trajectory, gains, hulls["vertices"], hulls["boxes"],
            hulls["variables"], hulls["enclosure"], setup.Q_init, setup.Q_seed,
            2 * setup.rate + one.margin, setup.bounds, setup.robust, one.multiplier, one.margin,
            self.terminal, setup.state_bounds, codesign=codesign, period=self.period,
            pushed=self.pushed,
        )  # fmt: skip

    def checked(
        self, hulls: _Hulls, one: _Try, gains: FloatArray, Q: FloatArray, tau: float
    ) -> _Candidate | _Failed:
        """The funnel of ``gains (N, m, n)`` and ``Q (N+1, n, n)`` (at level 1 its E(0) holds the
        initial set; the program's ``tau``): its level (step 4), then ``check_funnel`` and the
        terminal containment."""
        scenario, trajectory, setup = self.scenario, self.trajectory, self.setup
        end = trajectory.dense_xs[-1]
        limits = funnel_limits(
            scenario, trajectory, Q, gains, hulls["enclosure"], setup.state_bounds
        )
        limits["design"] = (float(np.sqrt(min(tau, 1.0))), 0.0)
        if self.terminal is not None:  # E(T) = {||x - x_ref(T)||_P[N] <= rho e^{-lambda T}}
            T = trajectory.dense_ts[-1]
            reach = self.terminal.end_radius(end, np.linalg.inv(Q[-1]))
            limits["terminal"] = (reach * float(np.exp(setup.rate * T)), float(T))
        binding = min(limits, key=lambda key: limits[key][0])
        level, when = limits[binding]
        rho = level * (1 - LEVEL_SLACK)
        funnel = self.result(
            True, "", K=gains, P=np.linalg.inv(Q).astype(np.float64, copy=False), rho=rho,
            binding=binding, multiplier=one.multiplier, codesigned=one.codesigned,
            margins=certificate_margins(Q, gains, hulls["vertices"], setup.rate, scenario.Ts),
            limits={key: value[0] for key, value in limits.items()}, **hulls,
        )  # fmt: skip
        law = LawOffset.none(setup.N, scenario.n, scenario.m, scenario.Ts)
        if setup.robust is not None:
            law = law.with_disturbance(setup.robust)
        failure = check_funnel(scenario, trajectory, funnel, setup.state_bounds, law)
        if self.terminal is not None and not failure:
            failure = _outside(self.terminal, end, funnel, trajectory.dense_ts[-1])
        if rho <= 0:
            failure = failure or f"the nominal itself violates {binding} at t = {when:.2f} s"
        if failure:
            return _Failed(reason=failure)
        return _Candidate(funnel=funnel, margin=one.margin, when=when)

    def described(self, chosen: _Candidate, tight: bool) -> Funnel:
        """``chosen``'s funnel with its message (level, the share of the initial set it holds,
        what binds it, how it was designed)."""
        funnel, setup = chosen.funnel, self.setup
        rho, origin = funnel.rho, "(F6) " if funnel.codesigned else ""
        message = (
            f"funnel level {rho:.4g} (E(0) holds {min(rho, 1.0):.3g} x the required initial "
            f"set) over {setup.N} intervals ({setup.S} pieces, {origin}K held over {HOLD}), "
            f"bound by {funnel.binding} at t = {chosen.when:.2f} s (largest eigenvalue "
            f"{funnel.margins.max():.2e}, LMI margin {chosen.margin:g}, "
            f"{'capped' if tight else 'uncapped'} angle boxes)"
        )
        return dataclasses.replace(funnel, message=message)

    def result(self, success: bool, message: str, **values: Unpack[_Parts]) -> Funnel:
        """A ``Funnel`` of ``values``; the fields not given: the seed's gains and metric, no
        level, no hulls."""
        setup = self.setup
        defaults: _Parts = {
            "K": setup.K, "P": setup.P_lqr, "rho": 0.0, "margins": np.full((setup.N, 2), np.nan),
            "boxes": np.zeros((setup.N, 2, 0)), "variables": (), "vertices": (),
            "enclosure": None, "limits": {}, "binding": "", "multiplier": 0.0,
            "codesigned": False,
        }  # fmt: skip
        defaults.update(values)
        return Funnel(
            rate=setup.rate, **defaults, seconds=time.perf_counter() - self.start,
            success=success, message=message,
        )  # fmt: skip


def _grouped(failures: list[str]) -> str:
    """``"margin 0.1: X"``-style lines with the same reason said once, with their margins:
    ``"margins 0.1, 1: Clarabel status PrimalInfeasible over 34 intervals; margin 0.3: ..."``."""
    reasons: dict[str, list[str]] = {}
    for line in failures:
        label, _, reason = line.partition(": ")
        reasons.setdefault(reason, []).append(label.removeprefix("margin "))
    return "; ".join(
        f"margin{'s' if len(margins) > 1 else ''} {', '.join(margins)}: {reason}"
        for reason, margins in reasons.items()
    )
