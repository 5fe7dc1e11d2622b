"""The time-varying funnel (``funnel/``): known answers and the certificate's argument.

1. Double integrator (linear: one hull vertex, the exact ``[A B]``): the time-varying LQR
   converges to the stationary discrete LQR on a long horizon, and the funnel holds exactly:
   ``e(t) = expm((A + B K[k]) (t - t_k)) e(t_k)`` stays in ``E(t)`` on a fine time grid.
2. Quadrotor (nonlinear, local hulls): the end-point LMIs imply (F2) on a 10x finer time grid
   and for random Jacobians sampled from each interval's box; the local hull contains the
   Jacobians sampled from its box (LP membership); the nominal stays in its enclosure (E2)
   between grid points (solve_ivp at tight tolerance).
3. The independent check rejects a funnel whose ``P`` is perturbed.
4. The hand-built Clarabel program (funnel.lmi) has the optimum of the same program in cvxpy,
   also with intervals of different durations (the LMI pieces of funnel.HOLD samples).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm, solve_discrete_are
from scipy.optimize import linprog
from shapely.geometry import box as shapely_box

from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.check import check_funnel
from pipeline.numerics.funnel.lmi import FunnelProgram, basis, solve_clarabel, solve_cvxpy, svec
from pipeline.numerics.funnel.pieces import pieces
from pipeline.numerics.funnel.seed import lqr_seed
from pipeline.numerics.funnel.synthesis import synthesize_funnel

THETA_BOUNDS = {"theta": (-0.8, 0.8)}


def _q_at(funnel, k: int, s: float) -> np.ndarray:
    """``Q(t)`` (n, n) at fraction ``s`` of interval ``k``, eq. (F1)."""
    Q = funnel.Q
    return (1 - s) * Q[k] + s * Q[k + 1]


def _worst_eigenvalue(funnel, Ts: float, k: int, s: float, J: np.ndarray) -> float:
    """Largest eigenvalue of ``Q^-1/2 L(s, J) Q^-1/2`` of (F2) for one Jacobian ``J (n, n+m)``."""
    n = J.shape[0]
    Q = funnel.Q
    Qs = _q_at(funnel, k, s)
    Acl = J[:, :n] + J[:, n:] @ funnel.K[k]
    L = -(Q[k + 1] - Q[k]) / Ts + Acl @ Qs + Qs @ Acl.T + 2 * funnel.rate * Qs
    L_inv = np.linalg.inv(np.linalg.cholesky(Qs))
    M = L_inv @ L @ L_inv.T
    return float(np.linalg.eigvalsh((M + M.T) / 2)[-1])


@pytest.fixture(scope="module")
def double_integrator():
    scenario = load_scenario("double_integrator", check_demos=False)
    N = 40
    t = scenario.Ts * (np.arange(N) + 0.5)
    us = np.column_stack([np.where(t < 2, 1.0, -1.0), 0.2 * np.sin(t)])  # (N, 2)
    trajectory = simulate(scenario.dynamics, np.array([0.5, 0.5, 0.0, 0.0]), us, scenario.Ts)
    final = trajectory.xs[-1, :2]
    goal = shapely_box(final[0] - 1, final[1] - 1, final[0] + 1, final[1] + 1)
    scenario = dataclasses.replace(scenario, goal=goal, unsafe={})
    return scenario, trajectory, synthesize_funnel(scenario, trajectory)


@pytest.fixture(scope="module")
def quadrotor():
    """The first 2 s of demo 1 with Goal moved around where it ends."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us[:20], scenario.Ts)
    final = trajectory.xs[-1, :2]
    goal = shapely_box(final[0] - 1.5, final[1] - 1.5, final[0] + 1.5, final[1] + 1.5)
    scenario = dataclasses.replace(scenario, goal=goal)
    return scenario, trajectory, synthesize_funnel(scenario, trajectory, state_bounds=THETA_BOUNDS)


def test_lqr_seed_converges_to_stationary_lqr() -> None:
    scenario = load_scenario("double_integrator", check_demos=False)
    Ts, N = scenario.Ts, 400
    trajectory = simulate(scenario.dynamics, np.zeros(4), np.zeros((N, 2)), Ts)
    K, P = lqr_seed(scenario, trajectory)
    I2 = np.eye(2)
    Ad = np.block([[I2, Ts * I2], [0 * I2, I2]])  # exact zero-order hold of xdd = u
    Bd = np.vstack([Ts**2 / 2 * I2, Ts * I2])
    Qw = Ts * np.diag(scenario.feedback.state_weights)
    Rw = Ts * np.diag(scenario.feedback.input_weights)
    S = solve_discrete_are(Ad, Bd, Qw, Rw)
    K_stationary = -np.linalg.solve(Rw + Bd.T @ S @ Bd, Bd.T @ S @ Ad)
    np.testing.assert_allclose(P[0], S, rtol=1e-6)
    np.testing.assert_allclose(K[0], K_stationary, rtol=1e-6)
    assert np.abs(K[-1] - K_stationary).max() > 1e-2  # the terminal end has not converged
    # ending at rest with the stationary cost-to-go: the gains hold to the end
    K_end, P_end = lqr_seed(scenario, trajectory, stationary_end=True)
    np.testing.assert_allclose(P_end[-1], S, rtol=1e-6)
    np.testing.assert_allclose(K_end[-1], K_stationary, rtol=1e-6)


def test_double_integrator_funnel_is_exact(double_integrator) -> None:
    scenario, trajectory, funnel = double_integrator
    assert funnel.success, funnel.message
    A = scenario.dynamics.f_x(np.zeros(4), np.zeros(2))
    B = scenario.dynamics.f_u(np.zeros(4), np.zeros(2))
    for vertices in funnel.vertices:  # linear dynamics: the hull is the exact Jacobian
        assert len(vertices) == 1
        np.testing.assert_allclose(vertices[0], np.hstack([A, B]), atol=1e-8)
    assert funnel.margins.max() < 0
    # Error from 64 points on the boundary of E(0), propagated exactly interval by interval.
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(64, 4))
    L = np.linalg.cholesky(funnel.Q[0])
    e = funnel.rho * directions / np.linalg.norm(directions, axis=1, keepdims=True) @ L.T
    Ts = scenario.Ts
    for k in range(len(funnel.K)):
        Acl = A + B @ funnel.K[k]
        for s in np.linspace(0.0, 1.0, 11):
            e_s = e @ expm(Acl * s * Ts).T
            V = np.einsum("bi,ij,bj->b", e_s, np.linalg.inv(_q_at(funnel, k, s)), e_s)
            bound = funnel.rho**2 * np.exp(-2 * funnel.rate * Ts * (k + s))
            assert np.all(V <= bound * (1 + 1e-9))
        e = e @ expm(Acl * Ts).T


def test_vertex_lmis_hold_on_a_finer_grid_and_for_sampled_jacobians(quadrotor) -> None:
    scenario, _, funnel = quadrotor
    assert funnel.success, funnel.message
    rng = np.random.default_rng(1)
    names = funnel.variables
    for k, vertices in enumerate(funnel.vertices):
        for s in np.linspace(0.0, 1.0, 11):  # 10x finer than the sample grid
            worst = max(_worst_eigenvalue(funnel, scenario.Ts, k, s, J) for J in vertices)
            assert worst < 0, (k, s, worst)
        # Random Jacobians at random times: points of the box (theta, u1), other states random.
        lower, upper = funnel.boxes[k]
        z = rng.uniform(lower, upper, size=(20, len(names)))
        x = rng.normal(size=(20, scenario.n))
        u = rng.normal(size=(20, scenario.m))
        for d, name in enumerate(names):
            if name in scenario.state_names:
                x[:, scenario.state_names.index(name)] = z[:, d]
            else:
                u[:, scenario.input_names.index(name)] = z[:, d]
        J = np.concatenate([scenario.dynamics.f_x(x, u), scenario.dynamics.f_u(x, u)], axis=2)
        for Jb, s in zip(J, rng.uniform(size=20), strict=True):
            assert _worst_eigenvalue(funnel, scenario.Ts, k, s, Jb) < 0


def test_local_hull_contains_sampled_jacobians(quadrotor) -> None:
    scenario, _, funnel = quadrotor
    rng = np.random.default_rng(2)
    for k in (0, 7, 19):
        vertices = funnel.vertices[k].reshape(len(funnel.vertices[k]), -1)  # (V, n (n+m))
        lower, upper = funnel.boxes[k]
        corners = np.array(np.meshgrid(*zip(lower, upper, strict=True))).reshape(2, -1).T
        samples = np.vstack([rng.uniform(lower, upper, size=(30, 2)), corners])
        theta, u1 = samples[:, 0], samples[:, 1]
        assert funnel.variables == ("theta", "u1")
        x = np.zeros((len(samples), scenario.n))
        x[:, 2] = theta
        u = np.column_stack([u1, np.zeros(len(samples))])
        J = np.concatenate([scenario.dynamics.f_x(x, u), scenario.dynamics.f_u(x, u)], axis=2)
        for target in J.reshape(len(J), -1):  # mu >= 0, sum mu = 1, sum mu_v J_v = J
            A_eq = np.vstack([vertices.T, np.ones(len(vertices))])
            b_eq = np.append(target, 1.0)
            fit = linprog(np.zeros(len(vertices)), A_eq=A_eq, b_eq=b_eq, bounds=(0, None))
            assert fit.status == 0, (k, target)
        # A Jacobian from outside the box is (here) outside the hull: the test can fail.
        x[0, 2], u[0, 0] = upper[0] + 0.3, upper[1]
        outside = np.concatenate(
            [scenario.dynamics.f_x(x[0], u[0]), scenario.dynamics.f_u(x[0], u[0])], axis=1
        )
        A_eq = np.vstack([vertices.T, np.ones(len(vertices))])
        fit = linprog(np.zeros(len(vertices)), A_eq=A_eq, b_eq=np.append(outside.ravel(), 1.0),
                      bounds=(0, None))  # fmt: skip
        assert fit.status == 2


def test_nominal_stays_in_its_enclosure(quadrotor) -> None:
    scenario, trajectory, funnel = quadrotor
    for k, u in enumerate(trajectory.us):
        t0 = k * scenario.Ts
        solution = solve_ivp(
            lambda _t, y, u=u: scenario.dynamics.f(y, u), (t0, t0 + scenario.Ts),
            trajectory.xs[k], rtol=1e-10, atol=1e-10, dense_output=True,
        )  # fmt: skip
        states = solution.sol(np.linspace(t0, t0 + scenario.Ts, 101)).T
        lower, upper = funnel.enclosure.range[k]
        assert np.all(states >= lower - 1e-7) and np.all(states <= upper + 1e-7), k


def test_check_rejects_a_perturbed_metric(quadrotor) -> None:
    scenario, trajectory, funnel = quadrotor
    assert check_funnel(scenario, trajectory, funnel, THETA_BOUNDS) is None
    P = funnel.P.copy()
    P[10] *= 0.5  # Q[10] doubles: the funnel bulges at t_10 and shrinks too fast after it
    message = check_funnel(scenario, trajectory, dataclasses.replace(funnel, P=P), THETA_BOUNDS)
    assert message is not None and "(F2) fails" in message
    P = funnel.P.copy()
    P[3] = -P[3]
    message = check_funnel(scenario, trajectory, dataclasses.replace(funnel, P=P), THETA_BOUNDS)
    assert (
        message == "P[3] is not positive definite" + message[len("P[3] is not positive definite") :]
    )
    bigger = dataclasses.replace(funnel, rho=2 * funnel.rho)
    assert check_funnel(scenario, trajectory, bigger, THETA_BOUNDS) is not None


def test_svec_is_an_isometry_and_basis_matches_it() -> None:
    rng = np.random.default_rng(3)
    M, N = rng.normal(size=(2, 4, 4))
    M, N = M + M.T, N + N.T
    assert svec(M) @ svec(N) == pytest.approx(np.trace(M @ N))
    E = basis(4)
    q = rng.normal(size=len(E))
    Q = np.einsum("l,lij->ij", q, E)
    np.testing.assert_array_equal(Q, Q.T)
    diagonal = np.isin(np.arange(len(q)), [0, 2, 5, 9])  # column-major upper triangle
    np.testing.assert_allclose(svec(Q), q * np.where(diagonal, 1.0, np.sqrt(2.0)))


def _demo_start(samples: int):
    """quadrotor_hill_flythrough, the LQR seed ``K (N, m, n)``, ``Q_seed (N+1, n, n)`` and the
    nominal's
    Jacobians ``J (N, n, n+m)`` over the first ``samples`` of demo 1."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us[:samples], scenario.Ts)
    K, P = lqr_seed(scenario, trajectory)
    x, u = trajectory.xs[:-1], trajectory.us
    J = np.concatenate([scenario.dynamics.f_x(x, u), scenario.dynamics.f_u(x, u)], axis=2)
    return scenario, K, np.linalg.inv(P), J


def test_clarabel_program_matches_cvxpy() -> None:
    """A small nonlinear program (quadrotor, 8 intervals, two vertices each, caps active)."""
    scenario, K, Q_seed, J = _demo_start(8)
    vertices = tuple(np.stack([Jk, Jk * 1.05]) for Jk in J)
    caps = tuple((k, np.eye(6)[2:3], np.full((1, 1), 4 * Q_seed[0][2, 2])) for k in range(9))
    caps += ((8, np.eye(6)[:2], 1.5 * Q_seed[0][:2, :2]),)  # a 2 x 2 cap
    W = np.broadcast_to(np.eye(6), (9, 6, 6))
    program = FunnelProgram(
        Ts=scenario.Ts, K=K, vertices=vertices, c=0.3, Q_init=Q_seed[0], floor=1e-6, caps=caps,
        W=W, initial_weight=1e3,
    )  # fmt: skip
    (Q_direct, tau), (Q_reference, tau_reference) = solve_clarabel(program), solve_cvxpy(program)
    assert tau == pytest.approx(1.0, abs=1e-6) and tau_reference == pytest.approx(1.0, abs=1e-6)
    objective = [np.einsum("kij,kji->", W, Q) for Q in (Q_direct, Q_reference)]  # tau = 1
    assert objective[0] == pytest.approx(objective[1], rel=1e-5)
    np.testing.assert_allclose(Q_direct, Q_reference, atol=1e-4 * np.abs(Q_reference).max())
    assert Q_direct[:, 2, 2].max() <= caps[0][2][0, 0] * (1 + 1e-6)
    assert np.linalg.eigvalsh(caps[-1][2] - Q_direct[8, :2, :2]).min() >= -1e-6
    # A tighter 2 x 2 cap: both hold the same fraction tau < 1 of the initial set.
    tight = caps[:-1] + ((8, np.eye(6)[:2], 0.8 * Q_seed[0][:2, :2]),)
    program = dataclasses.replace(program, caps=tight)
    (_, tau), (_, tau_reference) = solve_clarabel(program), solve_cvxpy(program)
    assert tau < 0.99 and tau == pytest.approx(tau_reference, rel=1e-4)


def test_clarabel_matches_cvxpy_with_pieces_of_different_length() -> None:
    """The program on pieces of 4 and 2 samples (durations per interval) as cvxpy solves it."""
    scenario, K, Q_seed, J = _demo_start(6)
    bounds = pieces(6, 4)
    vertices = tuple(np.stack([J[a], J[a] * 1.05]) for a in bounds[:-1])
    caps = tuple((k, np.eye(6)[2:3], np.full((1, 1), 4 * Q_seed[0][2, 2])) for k in range(3))
    program = FunnelProgram(
        Ts=scenario.Ts * np.diff(bounds).astype(np.float64), K=K[bounds[:-1]], vertices=vertices,
        c=0.3, Q_init=Q_seed[0], floor=1e-6, caps=caps, W=np.broadcast_to(np.eye(6), (3, 6, 6)),
        initial_weight=1e3,
    )  # fmt: skip
    (Q_direct, tau), (Q_reference, tau_reference) = solve_clarabel(program), solve_cvxpy(program)
    assert tau == pytest.approx(tau_reference, rel=1e-4)
    np.testing.assert_allclose(Q_direct, Q_reference, atol=1e-4 * np.abs(Q_reference).max())
    # The durations matter: the same program with one duration for all has another optimum.
    uniform = FunnelProgram(**{**program.__dict__, "Ts": scenario.Ts})
    Q_uniform, _ = solve_clarabel(uniform)
    assert np.abs(Q_uniform - Q_direct).max() > 1e-3 * np.abs(Q_direct).max()


def test_a_stack_of_corners_is_held_as_cvxpy_holds_it() -> None:
    """``Q_init (p, n, n)`` of rank-one ``v v^T`` (the corners of a cell of Init): Clarabel and
    cvxpy agree, ``Q[0] / tau`` holds every corner (``v^T (Q[0] / tau)^-1 v <= 1``), and one
    corner pushed out beyond what the caps allow lowers tau."""
    scenario, K, Q_seed, J = _demo_start(8)
    vertices = tuple(np.stack([Jk, Jk * 1.05]) for Jk in J)
    caps = tuple((k, np.eye(6)[2:3], np.full((1, 1), 4 * Q_seed[0][2, 2])) for k in range(9))
    rng = np.random.default_rng(5)
    L = np.linalg.cholesky(Q_seed[0])
    corners = rng.normal(size=(12, 6))
    corners = 0.9 * corners / np.linalg.norm(corners, axis=1, keepdims=True) @ L.T  # inside
    program = FunnelProgram(
        Ts=scenario.Ts, K=K, vertices=vertices, c=0.3,
        Q_init=np.einsum("pi,pj->pij", corners, corners), floor=1e-6, caps=caps,
        W=np.broadcast_to(np.eye(6), (9, 6, 6)), initial_weight=1e3,
    )  # fmt: skip
    (Q_direct, tau), (Q_reference, tau_reference) = solve_clarabel(program), solve_cvxpy(program)
    assert tau == pytest.approx(tau_reference, rel=1e-4)
    np.testing.assert_allclose(Q_direct, Q_reference, atol=1e-4 * np.abs(Q_reference).max())
    held = np.einsum("pi,ij,pj->p", corners, np.linalg.inv(Q_direct[0] / tau), corners)
    assert held.max() <= 1 + 1e-5
    far = corners.copy()
    far[0] = 0.0
    far[0, 2] = 10 * np.sqrt(caps[0][2][0, 0])  # pitch far beyond the pitch cap
    wide = dataclasses.replace(program, Q_init=np.einsum("pi,pj->pij", far, far))
    (_, tau_far), (_, tau_far_reference) = solve_clarabel(wide), solve_cvxpy(wide)
    # Q_22 <= cap and Q >= tau v v^T with v_2^2 = 100 cap: tau <= 1/100
    assert tau_far <= 0.01 and tau_far == pytest.approx(tau_far_reference, abs=1e-6)
