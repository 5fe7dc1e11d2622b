"""How much of issue 29's declared uncertainty can a quadratic certificate hold at hover?

Issue 29 asked quadrotor_hill_flythrough to certify wind ``wX`` in [-1, 0] m/s, mass +-5% and a gust
of 0.25 m/s^2, whose additive bound (``pipeline.numerics.uncertainty``) is ``|w_vX| <= 1.092``,
``|w_vY| <= 1.075`` m/s^2. Here the most favourable case for the certificates of this pipeline
is searched: the hover at Goal's centre (no trajectory), with the gain AND the metric both free
(``Y = K Q``, the LMI co-design of Boyd et al., section 7.2.1), the S-procedure's joint condition
of ``funnel.robust`` (I5) at every vertex of the sound Jacobian hull over a box about the hover
(pitch +-theta, thrust +-du) and every corner of the disturbance box, the ellipsoid inside the
box, Goal and the input bounds. Printed per box: the largest fraction ``s`` of the issue's bound
that any multiplier certifies (bisection), the same with the hull replaced by Jacobians sampled
on a grid of the box (not sound: a lower bound on what any hull could do), and with the gain
fixed to quadrotor_hill's LQR gain (the metric alone free, as in the funnels today). Run:
``python -m bench robust_ceiling`` (also part of ``make bench``).
"""

from __future__ import annotations

import itertools
import warnings

import cvxpy as cp
import numpy as np
import shapely

import pipeline
from pipeline.numerics.hull import jacobian_hull
from pipeline.numerics.terminal.equilibrium import equilibrium, lqr_terminal

# m/s^2, on the quadrotor's states
ISSUE_BOUND = np.array([0.0, 0.0, 0.0, 1.0922, 1.0755, 0.0])
BOXES = ((0.3, 2.5), (0.3, 4.0), (0.45, 4.0), (0.6, 4.8))  # (pitch +-rad, thrust +-N)
ALPHAS = (0.5, 1.0, 2.0, 3.0)
STEPS = 8


def _feasible(vertices, x_eq, u_eq, scenario, pitch, thrust, scale, gain=None) -> bool:
    """Whether some multiplier admits (Q, Y) for ``scale`` times the issue's bound (``Y = gain
    Q`` when a gain ``(m, n)`` is given: the metric alone is free)."""
    n = scenario.n
    w = scale * ISSUE_BOUND
    acting = np.flatnonzero(w > 0)
    corners = []
    for signs in itertools.product((-1.0, 1.0), repeat=len(acting) - 1):
        c = np.zeros(n)
        c[acting] = w[acting] * np.array([1.0, *signs])
        corners.append(c)
    position = list(scenario.position_index)
    room = float(shapely.distance(shapely.Point(x_eq[position]), scenario.goal.boundary))
    theta = scenario.state_names.index("theta")
    rooms = [
        thrust,
        float(min(scenario.input_upper[1] - u_eq[1], u_eq[1] - scenario.input_lower[1])),
    ]
    for alpha in ALPHAS:
        Q = cp.Variable((n, n), symmetric=True)
        Y = cp.Variable((scenario.m, n)) if gain is None else gain @ Q
        C = np.eye(n)[position]
        constraints = [Q >> 1e-6 * np.eye(n), C @ Q @ C.T << room**2 * np.eye(2)]
        constraints.append(Q[theta, theta] <= pitch**2)
        for j, r in enumerate(rooms):
            constraints.append(
                cp.bmat([[np.array([[r**2]]), Y[j : j + 1]], [Y[j : j + 1].T, Q]]) >> 0
            )
        for J in vertices:
            A, B = J[:, :n], J[:, n:]
            M = A @ Q + Q @ A.T + B @ Y + Y.T @ B.T + alpha * Q
            for c in corners:
                column = c[:, None]
                constraints.append(
                    cp.bmat([[(M + M.T) / 2, column], [column.T, np.array([[-alpha]])]]) << 0
                )
        problem = cp.Problem(cp.Minimize(0), constraints)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                problem.solve(solver=cp.CLARABEL)
        except cp.SolverError:
            continue
        if problem.status == cp.OPTIMAL:
            return True
    return False


def _largest(vertices, x_eq, u_eq, scenario, pitch, thrust, gain=None) -> float:
    low, high = 0.0, 1.0
    if _feasible(vertices, x_eq, u_eq, scenario, pitch, thrust, 1.0, gain):
        return 1.0
    for _ in range(STEPS):
        middle = (low + high) / 2
        ok = _feasible(vertices, x_eq, u_eq, scenario, pitch, thrust, middle, gain)
        low, high = (middle, high) if ok else (low, middle)
    return low


def run() -> None:
    scenario = pipeline.load_scenario("quadrotor_hill")
    x_eq, u_eq = equilibrium(scenario)
    lqr, _ = lqr_terminal(scenario, x_eq, u_eq)
    dynamics = scenario.dynamics
    print(
        f"issue 29's additive bound: |w_vX| <= {ISSUE_BOUND[3]}, |w_vY| <= {ISSUE_BOUND[4]} m/s^2"
    )
    print(
        f"{'pitch':>6} {'thrust':>6} {'hull: largest s':>16} {'grid: largest s':>16} "
        f"{'LQR gain: largest s':>20}"
    )
    for pitch, thrust in BOXES:
        region = {
            name: (float(x), float(x)) for name, x in zip(scenario.state_names, x_eq, strict=True)
        }
        region["theta"] = (x_eq[2] - pitch, x_eq[2] + pitch)
        region["u1"] = (u_eq[0] - thrust, u_eq[0] + thrust)
        region["u2"] = (float(u_eq[1]), float(u_eq[1]))
        hull = jacobian_hull(dynamics, region).vertices
        grid = []
        for t, u in itertools.product(
            np.linspace(-pitch, pitch, 7), np.linspace(-thrust, thrust, 3)
        ):
            x = x_eq.copy()
            x[2] += t
            v = u_eq + np.array([u, 0.0])
            grid.append(np.hstack([dynamics.f_x(x, v), dynamics.f_u(x, v)]))
        sound = _largest(hull, x_eq, u_eq, scenario, pitch, thrust)
        sampled = _largest(np.array(grid), x_eq, u_eq, scenario, pitch, thrust)
        fixed = _largest(hull, x_eq, u_eq, scenario, pitch, thrust, lqr)
        print(f"{pitch:>6.2f} {thrust:>6.1f} {sound:>16.3f} {sampled:>16.3f} {fixed:>20.3f}")
