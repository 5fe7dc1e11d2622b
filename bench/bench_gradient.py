"""Cost and gradient timings on quadrotor_hill_flythrough, as ratios measured side by side in one
run.

For N = 50, 100, 200, 400: one ``cost`` call, each gradient method (``cost_and_gradient``) and a
central finite-difference gradient (``2 N m`` cost calls), as multiples of one ``cost`` call.
Then one cost + gradient pair on a 100-sample input against one ``solve_ivp`` simulation of it
(rtol = atol = 1e-8). Targets (issue 3): adjoint <= 3 costs at every N; N = 400 at most 5x
N = 100 for both methods; cost + gradient >= 20x faster than solve_ivp.

The inputs fly a loop over the hill and back (a PD tracker, so that every N has a finite cost
with penalties active on part of the grid), not a demo: the demos are ~150 samples long.
"""

from __future__ import annotations

import math

import numpy as np

from bench.timing import best_time
from pipeline import load_scenario
from pipeline.model.simulate import rk4_step, simulate_reference
from pipeline.numerics.optimize.problem import make_problem

SIZES = (50, 100, 200, 400)


def tracking_input(scenario, x0: np.ndarray, N: int) -> np.ndarray:
    """Inputs (N, 2) of a PD tracker flying X between 2 and 19 m at 5.4 m height (quadrotor)."""
    mu, g, wX = 0.5, 9.81, -0.5
    x, us = x0.copy(), np.empty((N, 2))
    for k in range(N):
        t = k * scenario.Ts
        X_ref = 10.5 - 8.5 * math.cos(2 * math.pi * t / 30.0)
        vX_ref = 8.5 * (2 * math.pi / 30.0) * math.sin(2 * math.pi * t / 30.0)
        X, Y, theta, vX, vY, omega = x
        aX = 1.0 * (X_ref - X) + 2.0 * (vX_ref - vX)
        aY = 2.0 * (5.4 - Y) - 2.5 * vY
        Fx, Fy = aX - mu * (wX - vX), aY + mu * vY + g
        theta_ref = max(-0.5, min(0.5, math.atan2(-Fx, Fy)))
        us[k] = [min(14.5, math.hypot(Fx, Fy)), 40.0 * (theta_ref - theta) - 12.0 * omega]
        for _ in range(4):
            x = rk4_step(scenario.dynamics, x, us[k], scenario.Ts / 4)
    return us


def run() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    x0 = np.array([2.0, 2.5, 0.0, 0.0, 0.0, 0.0])
    print(
        f"quadrotor_hill_flythrough, Ts = {scenario.Ts} s, 4 RK4 substeps (3 penalty points)"
        " per sample"
    )
    print(f"{'N':>5} {'cost (ms)':>10} {'adjoint':>8} {'sensitivity':>12} {'finite diff':>12}")
    per_size = {}
    for N in SIZES:
        u = tracking_input(scenario, x0, N)
        problem = make_problem(scenario, x0=x0, u_seed=u)
        assert np.isfinite(problem.cost(u)), f"benchmark input N={N} has an infinite cost"
        problem.cost_and_gradient(u, "adjoint")  # compile / load the kernels
        problem.cost_and_gradient(u, "sensitivity")
        number = max(1, 4000 // N)
        t_cost = best_time(lambda p=problem, u=u: p.cost(u), repeat=7, number=number)
        t_adj = best_time(
            lambda p=problem, u=u: p.cost_and_gradient(u, "adjoint"), repeat=7, number=number
        )
        t_sens = best_time(
            lambda p=problem, u=u: p.cost_and_gradient(u, "sensitivity"), repeat=7, number=number
        )
        t_fd = best_time(lambda p=problem, u=u: _finite_differences(p, u), repeat=1)
        per_size[N] = (t_cost, t_adj, t_sens)
        print(
            f"{N:>5} {1e3 * t_cost:>10.3f} {t_adj / t_cost:>8.2f} {t_sens / t_cost:>12.2f}"
            f" {t_fd / t_cost:>12.0f}"
        )
    print("(gradient columns: cost_and_gradient time / cost time)")

    u = tracking_input(scenario, x0, 100)
    problem = make_problem(scenario, x0=x0, u_seed=u)
    t_pair = best_time(lambda: problem.cost_and_gradient(u, "adjoint"), repeat=7, number=20)
    t_pair_sens = best_time(
        lambda: problem.cost_and_gradient(u, "sensitivity"), repeat=7, number=20
    )
    t_ivp = best_time(
        lambda: simulate_reference(scenario.dynamics, x0, u, scenario.Ts, rtol=1e-8, atol=1e-8),
        repeat=3,
    )
    print(
        f"N = 100: one solve_ivp simulation (DOP853, rtol 1e-8) = {1e3 * t_ivp:.1f} ms;"
        f" cost + adjoint gradient is {t_ivp / t_pair:.0f}x faster,"
        f" cost + sensitivity gradient {t_ivp / t_pair_sens:.0f}x faster"
    )
    growth_adj = per_size[400][1] / per_size[100][1]
    growth_sens = per_size[400][2] / per_size[100][2]
    worst_adj = max(t_adj / t_cost for t_cost, t_adj, _ in per_size.values())
    for label, ok in [
        (f"adjoint <= 3 costs at every N (worst {worst_adj:.2f})", worst_adj <= 3.0),
        (
            f"linear growth N=400 / N=100 <= 5 (adjoint {growth_adj:.2f},"
            f" sensitivity {growth_sens:.2f})",
            max(growth_adj, growth_sens) <= 5.0,
        ),
        (
            f"cost + gradient >= 20x faster than solve_ivp ({t_ivp / t_pair:.0f}x)",
            t_ivp >= 20 * t_pair,
        ),
    ]:
        print(f"  [{'met' if ok else 'MISSED'}] {label}")


def _finite_differences(problem, u: np.ndarray) -> np.ndarray:
    q = np.empty_like(u)
    step = 1e-6
    for k, j in np.ndindex(*u.shape):
        e = np.zeros_like(u)
        e[k, j] = step
        q[k, j] = (problem.cost(u + e) - problem.cost(u - e)) / (2 * step)
    return q
