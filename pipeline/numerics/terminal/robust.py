"""A terminal metric shaped for a declared disturbance (T3): the invariant ellipsoid by an LMI.

The Riccati matrix of the LQR gain (``terminal.equilibrium.lqr_terminal``) is a Lyapunov function
for the exact model, but its ellipsoids are not shaped for a disturbance: on
quadrotor_hill_flythrough the slow horizontal mode makes the disturbance's push dominate the decay
on part of every level set. Here the gain ``K_T`` is kept and the metric is chosen for it (Boyd et
al., LMIs in System and Control Theory, section 6.1.3, with the S-procedure of ``funnel.robust``
(I5)): for a multiplier ``alpha > 0``,

    [[Acl_v Q + Q Acl_v^T + (alpha + eps) Q, w_c], [w_c^T, -(alpha - eps)]] <= 0     (T3)

at every vertex ``v`` of a hull of the Jacobian over a box ``Z`` about the equilibrium and every
corner ``w_c`` of the disturbance box, with ``E = {e^T Q^-1 e <= 1}`` inside ``Z`` (``Q_ii <=
half_i^2``, ``K_j Q K_j^T <= input room^2``) and its position disk inside Goal; the smallest
position extent is kept over ``ALPHAS``. ``Z`` is guessed first (the frozen loop's invariant
ellipsoid at ``SEED`` times its extents, as ``funnel.synthesis`` (F5)). Nothing here is trusted:
the metric returned is certified, or not, by ``terminal.check.check_level`` ((T1'') among the
checks), at the level it finds.

(T6) The largest set instead. (T3) at level 1 is about the smallest set the disturbance leaves, and
the terminal level then scales it up to what the inputs, Goal and the hull allow. Under a large
bound that is little: a funnel ends in its own smallest set around its nominal's end, and a terminal
set only ``sqrt(level)`` times (T3)'s holds no such end but near its centre
(bench/notes/arrive-and-stay.md). ``largest_metric`` keeps (T3)'s invariance rows and maximises
``log det Q`` instead, over a fixed box: each bounded variable within a share of its room about the
equilibrium (``Q_ii <= half_i^2``, ``K_j Q K_j^T <= half_j^2``), the position disk in Goal and the
states in Goal's extra bounds. Without a gain, ``Y = K Q`` is an unknown too (Boyd et al. section
7.2.1: ``A_v Q + B_v Y`` in the rows, the input caps ``[[Q, Y_j^T], [Y_j, half_j^2]] >= 0`` by the
Schur complement) and ``K = Y Q^-1``. The largest set is not shaped for the ends' offsets (its
inscribed box is no larger than (T3)'s scaled one), so the nominals still end in a (T3) set
(``terminal.design.hold_design``)."""

from __future__ import annotations

import warnings

import cvxpy as cp
import numpy as np
import shapely

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.funnel.law import corners
from pipeline.numerics.funnel.robust import invariant_ellipsoid
from pipeline.numerics.hull import DEFAULT_SEGMENTS, HullError
from pipeline.numerics.uncertainty import parametric_hull

ALPHAS = (0.3, 0.6, 1.0, 1.5, 2.5, 4.0)  # the multipliers tried (1/s)
MARGIN = 0.05  # eps, as a share of alpha
SEED = 2.0  # the hull's box holds this multiple of the guessed ellipsoid's extents
# (T6)'s boxes: (states', inputs') shares of each variable's room about the equilibrium
SHARES = ((1 / 3, 2 / 3), (1 / 3, 1 / 3), (1 / 4, 2 / 3))


def robust_metric(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray,
    bound: FloatArray,
    segments: int = DEFAULT_SEGMENTS,
    parameters: Uncertainty | None = None,
) -> FloatArray | None:
    """``P_T (n, n)`` from (T3) for the gain ``K (m, n)`` at the equilibrium ``(x_eq (n,), u_eq
    (m,))`` and the additive bound ``bound (n,)``, the parameter intervals of ``parameters`` in
    the hull (``terminal.check`` (T7)); None when no multiplier gives one."""
    dynamics = scenario.dynamics
    A0, B0 = dynamics.f_x(x_eq, u_eq), dynamics.f_u(x_eq, u_eq)
    guess = invariant_ellipsoid(
        A0 + B0 @ K, np.asarray(bound, dtype=np.float64), np.eye(scenario.n)
    )
    if guess is None:
        return None
    state_half = SEED * np.sqrt(np.diag(guess))
    input_half = SEED * np.sqrt(np.diag(K @ guess @ K.T))
    region = {}
    limits = {**scenario.operating_region, **scenario.state_bounds}
    for i, name in enumerate(scenario.state_names):
        lower, upper = limits.get(name, (-np.inf, np.inf))
        region[name] = (max(x_eq[i] - state_half[i], lower), min(x_eq[i] + state_half[i], upper))
    for j, name in enumerate(scenario.input_names):
        lower, upper = scenario.input_lower[j], scenario.input_upper[j]
        region[name] = (max(u_eq[j] - input_half[j], lower), min(u_eq[j] + input_half[j], upper))
    caps = {name: min(x_eq[i] - region[name][0], region[name][1] - x_eq[i])
            for i, name in enumerate(scenario.state_names)}  # fmt: skip
    solved = _invariant_metric(
        scenario, x_eq, u_eq, K, bound, region, caps, largest=False, segments=segments,
        parameters=parameters,
    )  # fmt: skip
    return None if solved is None else solved[1]


def largest_metric(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray | None,
    bound: FloatArray,
    share: tuple[float, float],
    segments: int = DEFAULT_SEGMENTS,
    parameters: Uncertainty | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """``(K_T (m, n), P_T (n, n))`` of (T6): the largest ``{e^T P_T e <= 1}`` (``log det``) that
    (T3) holds for the gain ``K (m, n)`` (None: designed with it, ``Y = K Q``) and the additive
    bound ``bound (n,)``, within ``share`` (the states', the inputs', each in (0, 1)) of each
    bounded variable's room about ``(x_eq (n,), u_eq (m,))``; None when no multiplier gives one,
    the Jacobian depends on a state without bounds or the equilibrium lies on a bound.
    ``parameters``: as ``robust_metric``'s."""
    limits = {**scenario.operating_region, **scenario.state_bounds}
    region: dict[str, tuple[float, float]] = {}
    caps: dict[str, float] = {}
    for i, name in enumerate(scenario.state_names):
        if name in limits:
            lower, upper = limits[name]
            caps[name] = share[0] * max(min(x_eq[i] - lower, upper - x_eq[i]), 0.0)
            region[name] = (x_eq[i] - caps[name], x_eq[i] + caps[name])
        if name in scenario.goal_bounds:  # the terminal set lies in Goal's extra bounds
            lower, upper = scenario.goal_bounds[name]
            caps[name] = min(caps.get(name, np.inf), x_eq[i] - lower, upper - x_eq[i])
    for j, name in enumerate(scenario.input_names):
        lower, upper = limits.get(name, (-np.inf, np.inf))
        lower, upper = max(lower, scenario.input_lower[j]), min(upper, scenario.input_upper[j])
        half = share[1] * max(min(u_eq[j] - lower, upper - u_eq[j]), 0.0)
        region[name] = (u_eq[j] - half, u_eq[j] + half)
    if not all(h > 0 for h in caps.values()):  # an equilibrium on a bound: no room
        return None
    return _invariant_metric(
        scenario, x_eq, u_eq, K, bound, region, caps, largest=True, segments=segments,
        parameters=parameters,
    )  # fmt: skip


def _invariant_metric(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray | None,
    bound: FloatArray,
    region: dict[str, tuple[float, float]],
    caps: dict[str, float],
    *,
    largest: bool,
    segments: int = DEFAULT_SEGMENTS,
    parameters: Uncertainty | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """(T3)'s rows at every vertex of the hull over ``region`` (variable name -> interval) and
    every corner of the box ``bound (n,)``, with ``Q_ii <= caps[name]^2``, the inputs ``K_j Q
    K_j^T`` inside the region's input intervals and the position disk in Goal: ``(K, P =
    Q^-1)`` of the smallest position extent (``tr C Q C^T``) or, ``largest``, the largest ``log
    det Q``, over ``ALPHAS``; ``K`` None: ``Y = K Q`` an unknown too (Boyd et al. section 7.2.1;
    the input rows in Schur form) and ``K = Y Q^-1``; the hull over ``parameters``' intervals too
    (T7). None when no multiplier gives one."""
    n, m = scenario.n, scenario.m
    try:
        hull = parametric_hull(scenario, region, segments, parameters)
    except HullError:
        return None
    w = corners(np.asarray(bound, dtype=np.float64))
    position = list(scenario.position_index)
    C = np.eye(n)[position]
    inside = shapely.intersects_xy(scenario.goal, *x_eq[position])
    goal_room = float(shapely.distance(shapely.Point(x_eq[position]), scenario.goal.boundary))
    if not inside or not len(w):
        return None
    # one program for every multiplier: alpha a parameter (cvxpy's DPP), so the program is
    # compiled once and re-solved for each value of ALPHAS
    alpha = cp.Parameter(nonneg=True)
    Q = cp.Variable((n, n), symmetric=True)
    Y = K @ Q if K is not None else cp.Variable((m, n))  # Y = K Q, an unknown without K
    constraints = [Q >> 1e-9 * np.eye(n), C @ Q @ C.T << goal_room**2 * np.eye(2)]
    for i, name in enumerate(scenario.state_names):
        if name in caps:
            constraints.append(Q[i, i] <= caps[name] ** 2)
    for j, name in enumerate(scenario.input_names):
        room = min(u_eq[j] - region[name][0], region[name][1] - u_eq[j])
        if K is not None:
            constraints.append(K[j] @ Q @ K[j] <= room**2)
        else:  # K_j Q K_j^T = Y_j Q^-1 Y_j^T <= room^2 (Schur)
            row = Y[j : j + 1]
            constraints.append(cp.bmat([[Q, row.T], [row, np.array([[room**2]])]]) >> 0)
    corner_entry = cp.reshape((MARGIN - 1) * alpha, (1, 1), order="C")  # eps - alpha
    for J in hull.vertices:
        A, B = J[:, :n], J[:, n:]
        AQ = (A + B @ K) @ Q if K is not None else A @ Q + B @ Y
        M = AQ + AQ.T + (1 + MARGIN) * alpha * Q  # ... + (alpha + eps) Q
        for corner in w:
            column = corner[:, None]
            constraints.append(
                cp.bmat([[(M + M.T) / 2, column], [column.T, corner_entry]]) << 0
            )  # (T3)
    objective = cp.Maximize(cp.log_det(Q)) if largest else cp.Minimize(cp.trace(C @ Q @ C.T))
    problem = cp.Problem(objective, constraints)
    best: tuple[float, FloatArray, FloatArray] | None = None
    for value_of_alpha in ALPHAS:
        alpha.value = value_of_alpha
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                problem.solve(solver=cp.CLARABEL)
        except cp.SolverError:
            continue
        if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or Q.value is None:
            continue
        value = (Q.value + Q.value.T) / 2
        if np.linalg.eigvalsh(value)[0] <= 0:
            continue
        gain = K if K is not None else np.linalg.solve(value, np.asarray(Y.value).T).T
        score = -float(problem.value) if largest else float(problem.value)
        if best is None or score < best[0]:
            best = (score, value, np.asarray(gain, dtype=np.float64))
    if best is None:
        return None
    P = np.linalg.inv(best[1])
    return best[2], ((P + P.T) / 2).astype(np.float64)
