"""Funnels that hold under a bounded disturbance (pipeline.numerics.funnel.law (I4), funnel.lmi).

``xdot = f(x, u) + w`` with any ``|w_i| <= d_i``: the check adds ``2 max ||w_c||_P / rho`` to the
(F3) eigenvalue; the synthesis asks ``||w_c||_{Q^-1} <= gamma`` at every corner ``w_c``. A
known answer for the check, the LMI against cvxpy, a double integrator's robust funnel flown
from its boundary under the worst disturbance, and the reduction to today's funnels without one.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from shapely.geometry import box

from pipeline.controller import inverse_linear
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.check import check_funnel
from pipeline.numerics.funnel.law import LawOffset, corners, disturbance_term
from pipeline.numerics.funnel.lmi import FunnelProgram, solve_clarabel, solve_cvxpy
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from tests.helpers.robust import DISTURBANCE, double_integrator_case


def test_the_disturbance_term_has_the_scalar_closed_form():
    """``edot = -a e + w``, ``|w| <= d``: the interval ``|e| <= d / a`` is the smallest invariant
    one. In the metric ``P = p`` at level rho the half-width is ``rho / sqrt(p)``, the (F2)
    eigenvalue is ``-2 a``, and the check ``-2 a + term < 0`` holds exactly when ``rho / sqrt(p)
    > d / a``."""
    a, d, p = 0.7, 0.3, 4.0
    P = np.full((3, 1, 1), p)
    exact = d / a * np.sqrt(p)  # the level at which the interval is d / a wide
    for level, holds in ((exact * (1 + 1e-9), True), (exact * (1 - 1e-9), False)):
        term = disturbance_term(P, level, 0.0, 0.1, np.array([d]))
        assert (-2 * a + term.max() < 0) == holds


def test_corners_are_one_of_each_pair_over_the_disturbed_states():
    assert corners(np.zeros(3)).shape == (0, 3)
    w = corners(np.array([0.0, 0.2, 0.5]))
    assert w.shape == (2, 3) and np.all(w[:, 0] == 0)
    assert {tuple(np.abs(c)) for c in w} == {(0.0, 0.2, 0.5)}
    assert not np.allclose(w[0], -w[1])  # not both of a +- pair


def test_the_disturbance_constraint_is_the_same_program_in_cvxpy():
    """The Clarabel assembly of ``[[Q, w], [w^T, gamma^2]] >= 0`` against cvxpy's statement, and
    the bound it imposes: ``w^T Q^-1 w <= gamma^2`` at every knot (binding here)."""
    A, B, K = np.array([[0, 1], [0, 0.0]]), np.array([[0], [1.0]]), np.array([[-1.0, -1.4]])
    N, w, gamma = 5, np.array([0.0, 0.1]), 0.25
    vertices = tuple(np.hstack([A, B])[None] for _ in range(N))
    program = FunnelProgram(
        Ts=0.1, K=np.repeat(K[None], N, 0), vertices=vertices, c=0.5, Q_init=np.eye(2) * 0.01,
        floor=1e-6, caps=(), W=np.repeat(np.eye(2)[None], N + 1, 0), initial_weight=100.0,
        disturbance=corners(w), gamma=gamma,
    )  # fmt: skip
    ours, reference = solve_clarabel(program), solve_cvxpy(program)
    assert not isinstance(ours, str) and not isinstance(reference, str)
    assert np.allclose(ours[0], reference[0], atol=1e-4) and ours[1] == pytest.approx(1.0)
    bound = [w @ np.linalg.solve(Q, w) for Q in ours[0]]
    assert np.allclose(bound, gamma**2, rtol=1e-5)


def _robust(funnel, scenario, bound):
    law = LawOffset.none(len(funnel.K), scenario.n, scenario.m, scenario.Ts)
    return law.with_disturbance(funnel.P, funnel.rho, funnel.rate, scenario.Ts, bound)


def test_a_robust_funnel_holds_under_the_worst_disturbance_from_its_boundary():
    """The robust funnel passes the check with the disturbance's term; flown from 40 boundary
    points with ``w = d sign(P e)`` (the disturbance pushing outward hardest in each state), RK4
    at Ts / 40, the state never leaves it. The nominal design fails that check, naming the
    term."""
    scenario, trajectory, initial = double_integrator_case()
    funnel = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=DISTURBANCE)
    assert funnel.success, funnel.message
    assert (
        check_funnel(scenario, trajectory, funnel, {}, _robust(funnel, scenario, DISTURBANCE))
        is None
    )
    nominal = synthesize_funnel(scenario, trajectory, initial=initial)
    failure = check_funnel(
        scenario, trajectory, nominal, {}, _robust(nominal, scenario, DISTURBANCE)
    )
    assert failure is not None and "the disturbance's term" in failure

    rng = np.random.default_rng(3)
    Ts, h, N = scenario.Ts, scenario.Ts / 40, len(funnel.K)
    fine = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, 40)
    P_t = inverse_linear(funnel.P, Ts, fine.dense_ts)  # (M, n, n)
    v = rng.standard_normal((40, scenario.n))
    e = funnel.rho * v / np.sqrt(np.einsum("bi,ij,bj->b", v, funnel.P[0], v))[:, None]
    x, worst = fine.dense_xs[0] + e, 0.0
    for j in range(N * 40):
        k = j // 40
        u = trajectory.us[k] + (x - fine.dense_xs[j]) @ funnel.K[k].T

        def f(state, j=j, u=u):
            w = DISTURBANCE * np.sign((state - fine.dense_xs[j]) @ P_t[j])
            return scenario.dynamics.f(state, u) + w

        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        e = x - fine.dense_xs[j + 1]
        worst = max(worst, np.sqrt(np.einsum("bi,ij,bj->b", e, P_t[j + 1], e)).max() / funnel.rho)
    assert worst <= 1 + 1e-6, worst


def test_no_disturbance_is_exactly_the_nominal_funnel():
    scenario, trajectory, initial = double_integrator_case()
    nominal = synthesize_funnel(scenario, trajectory, initial=initial)
    zero = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=np.zeros(4))
    assert np.array_equal(nominal.P, zero.P) and nominal.rho == zero.rho
    with pytest.raises(ValueError, match="expected 4 bounds >= 0"):
        synthesize_funnel(scenario, trajectory, initial=initial, disturbance=-DISTURBANCE)


def test_a_rejected_robust_funnel_says_each_reason_once():
    """A disturbance no funnel can hold (100x): every LMI margin fails, and the message names
    each distinct reason once, with the margins it applies to."""
    scenario, trajectory, initial = double_integrator_case()
    funnel = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=100 * DISTURBANCE)
    assert not funnel.success
    reasons = funnel.message.removeprefix("funnel rejected: ").split("; ")
    assert len(reasons) == len(set(r.partition(": ")[2] for r in reasons))
    assert all(r.startswith("margin") for r in reasons)


def _hover_case():
    """quadrotor_hill hovering 3 s at (2, 2.5) with Goal a box around it, a 3% share of the
    declared bound of issue 29 (|w_vX| <= 0.033, |w_vY| <= 0.032 m/s^2): local hulls with
    several vertices (pitch, thrust)."""
    scenario = load_scenario("quadrotor_hill", check_demos=False)
    x0, N = np.array([2.0, 2.5, 0, 0, 0, 0]), 30
    trajectory = simulate(scenario.dynamics, x0, np.tile([9.81, 0.0], (N, 1)), scenario.Ts)
    scenario = dataclasses.replace(scenario, goal=box(0.0, 1.0, 4.0, 4.0))
    bound = np.array([0, 0, 0, 0.033, 0.032, 0])
    return scenario, trajectory, np.diag([0.05, 0.05, 0, 0, 0, 0]) ** 2, bound


def _worst_boundary_rate(scenario, funnel, bound, rng) -> float:
    """The largest ``dV/dt`` found on ``funnel``'s boundary: on a 10x finer time grid inside
    every sample interval, at random points of the interval's hull, for random boundary states
    and the worst of the box's corners and 20 uniform draws of ``|w| <= bound``."""
    n, Ts, rho = scenario.n, scenario.Ts, funnel.rho
    Q = np.linalg.inv(funnel.P)
    w = np.vstack([corners(bound), -corners(bound), rng.uniform(-bound, bound, (20, n))])
    worst = -np.inf
    for k, vertices in enumerate(funnel.vertices):
        dQ = (Q[k + 1] - Q[k]) / Ts  # (F1)
        for s in np.arange(1, 10) / 10:
            P = np.linalg.inv((1 - s) * Q[k] + s * Q[k + 1])
            P = (P + P.T) / 2
            dP = -P @ dQ @ P
            mix = rng.dirichlet(np.ones(len(vertices)), size=8)  # random hull points
            for J in np.einsum("hv,vij->hij", mix, vertices):
                A_cl = J[:, :n] + J[:, n:] @ funnel.K[k]
                v = rng.standard_normal((16, n))
                e = rho * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P, v))[:, None]
                drift = np.einsum("bi,ij,bj->b", e, dP + 2 * P @ A_cl, e)
                push = 2 * (e @ P @ w.T).max(axis=1)
                worst = max(worst, float((drift + push).max()))
    return worst


@pytest.mark.parametrize("case", ["double_integrator", "quadrotor hover"])
def test_the_robust_funnel_holds_between_samples_at_random_hull_points_and_gusts(case):
    """The claim checked pointwise, independently of the LMIs: ``dV/dt = e^T P' e + 2 e^T P (A +
    B K) e + 2 e^T P w < 0`` on the boundary ``e^T P(t) e = rho^2`` at every sampled time, hull
    point and gust (``_worst_boundary_rate``): no flight crosses it outward. The funnel designed
    for the exact model, checked the same way, is crossed (the check can fail)."""
    if case == "double_integrator":
        scenario, trajectory, initial = double_integrator_case()
        bound = DISTURBANCE
    else:
        scenario, trajectory, initial, bound = _hover_case()
    bounds = dict(scenario.state_bounds)
    robust = synthesize_funnel(
        scenario, trajectory, initial=initial, disturbance=bound, state_bounds=bounds
    )
    exact = synthesize_funnel(scenario, trajectory, initial=initial, state_bounds=bounds)
    assert robust.success and exact.success, (robust.message, exact.message)
    rng = np.random.default_rng(7)
    assert _worst_boundary_rate(scenario, robust, bound, rng) < 0
    assert _worst_boundary_rate(scenario, exact, bound, rng) > 0
