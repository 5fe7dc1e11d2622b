"""The terminal hover's law held every h seconds, its push taken to first order (T4').

``terminal.check`` (T4') is ``funnel.sampled`` (I6') on the terminal ellipsoid: one interval
with a constant metric, the equilibrium's residual joined to the disturbance, the measurement's
offset at ``t_j``. Brute force on random stiff loops: the held error equation flown from points
of ``E_c`` with the Jacobian switched among random hull points, the residual, the disturbance
and the measurement error at the corners of their boxes; while the state stays in ``E_c`` the
remainder is inside (R)'s box and the rate ``dV/dt`` flown is at most what (T4')'s eigenvalue
and multiplier predict. On double_integrator_hold held every 0.2 s (T4)'s box fails and (T4')
holds: the held law flown from the boundary stays inside.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.numerics.funnel.law import LMI_MARGIN, corners
from pipeline.numerics.funnel.robust import RobustCheck
from pipeline.numerics.funnel.sampled import remainder_box
from pipeline.numerics.terminal.check import (
    check_level,
    held_speed,
    hold_bound,
    joint_margin,
    largest_level,
)
from pipeline.numerics.terminal.equilibrium import equilibrium, lqr_terminal
from tests.helpers.robust import GUST, held_hover_flights, rk4_step, stiff_hull


def _flown(period, seed, steps=40, batch=3000):
    """The brute force of the module docstring: the worst ratios (remainder over its box, the
    rate's excess over the prediction in ``c``) and the share still inside at the end."""
    rng = np.random.default_rng(seed)
    n, radius = 4, 1.0
    A, B, K, Q = stiff_hull(rng)
    P = np.linalg.inv(Q)
    residual = np.array([0.002, -0.001, 0.0, 0.003])
    b = np.array([0.0, 0.05, 0.0, 0.05])
    E = np.array([0.003, 0.003, 0.0, 0.0])
    extent = radius * np.sqrt(np.diag(Q))
    reach = radius * np.sqrt(np.einsum("ji,il,jl->j", K, Q, K)) + np.abs(K) @ E
    speed = held_speed(A, B, extent, reach, residual, b)
    R = remainder_box(A, B, K, speed, E, np.abs(residual) + b, E, period)
    box = b + np.abs(residual) + R
    hull = (np.concatenate([A, B], axis=2),)
    check = RobustCheck(np.stack([Q, Q]), K[None], hull, 0.0, 1.0, radius, period)
    r, alpha = check.margins(box)
    assert joint_margin(P, K, A, B, radius, box, period) == pytest.approx(2 * r[0], abs=1e-12)
    Acl = A + B @ K
    dt, c = period / steps, radius**2
    v = rng.standard_normal((batch, n))
    scale = np.where(np.arange(batch) % 2, 0.999, rng.random(batch))
    e = (radius * scale)[:, None] * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P, v))[:, None]
    e_j, inside = e.copy(), np.ones(batch, dtype=bool)
    eta = E * rng.choice([-1.0, 1.0], size=(batch, n))  # the error seen at t_j
    integral = np.zeros((batch, n, n))
    worst_box, worst_rate = 0.0, -np.inf
    for _ in range(steps):
        weights = rng.dirichlet(np.full(len(A), 0.3), size=batch)  # near the vertices
        Ab, Bb = np.einsum("bv,vij->bij", weights, A), np.einsum("bv,vij->bij", weights, B)
        w = b * rng.choice([-1.0, 1.0], size=(batch, n))
        drive = np.einsum("bij,bj->bi", Bb, (e_j + eta) @ K.T) + residual + w

        def field(x, Ab=Ab, drive=drive):
            return np.einsum("bij,bj->bi", Ab, x) + drive

        V_t = np.einsum("bi,ij,bj->b", e, P, e)
        flown = 2 * np.einsum("bi,ij,bj->b", e, P, field(e))  # Q constant: V' = 2 e^T P e'
        excess = (flown - r[0] * (V_t + c) - alpha[0] * (c - V_t))[inside] / c
        assert np.all(excess <= 1e-9), excess.max()
        worst_rate = max(worst_rate, float(excess.max(initial=-np.inf)))
        integral += dt * np.einsum("bv,vij->bij", weights, Acl)
        e = rk4_step(field, e, dt)
        inside &= np.einsum("bi,ij,bj->b", e, P, e) <= c
        # (R): B_v K (e(t_j) + eta - e(t)) + tau B_v K Mbar e(t), tau Mbar = the integral
        rest = np.einsum(
            "vij,jl,bl->bvi", B, K, (e_j + eta - e + np.einsum("bij,bj->bi", integral, e))[inside]
        )
        assert np.all(np.abs(rest) <= R * (1 + 1e-9) + 1e-12)
        if inside.any():
            worst_box = max(worst_box, float((np.abs(rest) / np.maximum(R, 1e-300)).max()))
    return worst_box, worst_rate, inside.mean()


@pytest.mark.parametrize(("period", "seed"), [(0.005, 0), (0.01, 3), (0.02, 1)])
def test_the_terminal_push_to_first_order_bounds_the_rate_flown(period, seed):
    """Measured: the remainder reaches 54-84% of its box, the rate comes within 0.11-0.23
    ``c`` of the prediction; every flight stays inside."""
    worst_box, worst_rate, inside = _flown(period, seed)
    assert inside > 0.9
    assert worst_box > 0.3, worst_box  # the box is not vacuous
    assert worst_rate > -0.5, worst_rate  # nor the prediction


def test_a_terminal_law_the_box_refuses_is_certified_by_the_push_and_stays_inside():
    """double_integrator_hold's LQR hover held every 0.2 s under gusts of 0.02: at the largest
    level, (T4)'s box fails both (T1') and (T1''), (T4') holds; flown from 64 boundary points
    under outward and bang-bang gusts for 6 s, ``V <= c`` throughout. At 0.5 s it is refused."""
    scenario = load_scenario("double_integrator_hold", check_demos=False)
    x_eq, u_eq = equilibrium(scenario)
    K, P = lqr_terminal(scenario, x_eq, u_eq)
    b, h = np.array([0.0, 0.0, GUST, GUST]), 0.2
    check = largest_level(scenario, x_eq, u_eq, K, P, disturbance=b, held_period=h)
    assert check.success, check.failures
    r = np.sqrt(check.level)
    Q = np.linalg.inv(P)
    extent = r * np.sqrt(np.diag(Q))
    reach = r * np.sqrt(np.einsum("ji,il,jl->j", K, Q, K))
    A, B = scenario.dynamics.f_x(x_eq, u_eq)[None], scenario.dynamics.f_u(x_eq, u_eq)[None]
    residual = scenario.dynamics.f(x_eq, u_eq)
    boxed = b + hold_bound(A, B, K, extent, reach, residual, b, h)  # (T4)
    w = corners(boxed)
    w_max = float(np.sqrt(np.einsum("ci,ij,cj->c", w, P, w).max()))
    assert not check.decay * r > 2 * w_max  # (T1') with (T4)'s box
    assert not joint_margin(P, K, A, B, r, boxed + np.abs(residual)) < -LMI_MARGIN  # (T1'')
    level = 0.0
    flights = held_hover_flights(scenario, x_eq, u_eq, K, P, check.level, b, h, substeps=40, seed=5)
    for _, x in flights:
        level = max(level, float(np.einsum("bi,ij,bj->b", x - x_eq, P, x - x_eq).max()))
    assert level <= check.level and level > 0.9 * check.level, (level, check.level)
    longer = check_level(scenario, x_eq, u_eq, K, P, check.level, disturbance=b, held_period=0.5)
    assert not longer.success
