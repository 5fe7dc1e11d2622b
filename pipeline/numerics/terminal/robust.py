"""A terminal metric shaped for a declared disturbance (T3): the invariant ellipsoid by an LMI.

The Riccati matrix of the LQR gain (``terminal.design.lqr_terminal``) is a Lyapunov function for
the exact model, but its ellipsoids are not shaped for a disturbance: on quadrotor_hill_flythrough
the slow horizontal mode makes the disturbance's push dominate the decay on part of every level set.
Here the gain ``K_T`` is kept and the metric is chosen for it (Boyd et al., LMIs in System and
Control Theory, section 6.1.3, with the S-procedure of ``funnel.robust`` (I5)): for a multiplier
``alpha > 0``,

    [[Acl_v Q + Q Acl_v^T + (alpha + eps) Q, w_c], [w_c^T, -(alpha - eps)]] <= 0     (T3)

at every vertex ``v`` of a hull of the Jacobian over a box ``Z`` about the equilibrium and every
corner ``w_c`` of the disturbance box, with ``E = {e^T Q^-1 e <= 1}`` inside ``Z`` (``Q_ii <=
half_i^2``, ``K_j Q K_j^T <= input room^2``) and its position disk inside Goal; the smallest
position extent is kept over ``ALPHAS``. ``Z`` is guessed first (the frozen loop's invariant
ellipsoid at ``SEED`` times its extents, as ``funnel.synthesis`` (F5)). Nothing here is trusted:
the metric returned is certified, or not, by ``terminal.design.check_level`` ((T1'') among the
checks), at the level it finds.
"""

from __future__ import annotations

import warnings

import cvxpy as cp
import numpy as np
import shapely

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.funnel.law import corners
from pipeline.numerics.funnel.robust import invariant_ellipsoid
from pipeline.numerics.hull import DEFAULT_SEGMENTS, HullError, jacobian_hull

ALPHAS = (0.3, 0.6, 1.0, 1.5, 2.5, 4.0)  # the multipliers tried (1/s)
MARGIN = 0.05  # eps, as a share of alpha
SEED = 2.0  # the hull's box holds this multiple of the guessed ellipsoid's extents


def robust_metric(
    scenario: Scenario,
    x_eq: FloatArray,
    u_eq: FloatArray,
    K: FloatArray,
    bound: FloatArray,
    segments: int = DEFAULT_SEGMENTS,
) -> FloatArray | None:
    """``P_T (n, n)`` from (T3) for the gain ``K (m, n)`` at the equilibrium ``(x_eq (n,), u_eq
    (m,))`` and the additive bound ``bound (n,)``; None when no multiplier gives one."""
    dynamics = scenario.dynamics
    A0, B0 = dynamics.f_x(x_eq, u_eq), dynamics.f_u(x_eq, u_eq)
    guess = invariant_ellipsoid(
        A0 + B0 @ K, np.asarray(bound, dtype=np.float64), np.eye(scenario.n)
    )
    if guess is None:
        return None
    n = scenario.n
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
    try:
        hull = jacobian_hull(dynamics, region, segments)
    except HullError:
        return None
    w = corners(np.asarray(bound, dtype=np.float64))
    position = list(scenario.position_index)
    C = np.eye(n)[position]
    inside = shapely.intersects_xy(scenario.goal, *x_eq[position])
    goal_room = float(shapely.distance(shapely.Point(x_eq[position]), scenario.goal.boundary))
    if not inside or not len(w):
        return None
    best: tuple[float, FloatArray] | None = None
    for alpha in ALPHAS:
        Q = cp.Variable((n, n), symmetric=True)
        eps = MARGIN * alpha
        constraints = [Q >> 1e-9 * np.eye(n), C @ Q @ C.T << goal_room**2 * np.eye(2)]
        for i, name in enumerate(scenario.state_names):
            room = min(x_eq[i] - region[name][0], region[name][1] - x_eq[i])
            constraints.append(Q[i, i] <= room**2)
        for j, name in enumerate(scenario.input_names):
            room = min(u_eq[j] - region[name][0], region[name][1] - u_eq[j])
            constraints.append(K[j] @ Q @ K[j] <= room**2)
        for J in hull.vertices:
            Acl = J[:, :n] + J[:, n:] @ K
            M = Acl @ Q + Q @ Acl.T + (alpha + eps) * Q
            for corner in w:
                column = corner[:, None]
                constraints.append(
                    cp.bmat([[(M + M.T) / 2, column], [column.T, np.array([[eps - alpha]])]]) << 0
                )  # (T3)
        problem = cp.Problem(cp.Minimize(cp.trace(C @ Q @ C.T)), constraints)
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
        if best is None or float(problem.value) < best[0]:
            best = (float(problem.value), value)
    if best is None:
        return None
    P = np.linalg.inv(best[1])
    return ((P + P.T) / 2).astype(np.float64)
