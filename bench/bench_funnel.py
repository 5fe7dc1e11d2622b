"""Time-varying funnel vs the constant certificate on quadrotor_hill_flythrough's demos (issue 16,
phase 1).

For each demo the constant certificate (stages.feedback + stages.radius) gives the ball
``||e||_P <= r`` at t = 0. The funnel (pipeline.numerics.funnel.synthesis) is asked to hold the same
part of Init, the ball's slice along Init's free directions ``S`` (position; what coverage uses):
``Q_init = r^2 S (S^T P S)^-1 S^T``, within the scenario's real envelope (theta in [-0.8, 0.8]
rad, the input bounds) instead of the operating region. Printed per demo: the funnel level rho
(1: that slice is certified; the hull boxes cap it at 1), the room (the smallest level one
constraint alone allows) and which constraint that is, the largest tube extent along the flight
in position / theta / u1 for both certificates, the pitch and thrust each leaves the nominal
(limit minus the tube's largest extent there), and the funnel's synthesis time: CPU seconds
(``time.process_time``, this process; the machine may be shared) and wall seconds, against the
target of 4 s per trajectory (9 funnels, and a second round, within ``make synthesize``'s two
minutes on 2 cores). Run: ``python -m bench funnel``.
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.synthesis import HOLD, synthesize_funnel
from stages.feedback import design_feedback
from stages.radius import robustness_radius

STATE_BOUNDS = {"theta": (-0.8, 0.8)}  # the issue's physical envelope for quadrotor_hill_flythrough
TARGET = 4.0  # s of funnel synthesis per trajectory


def run(scenario_name: str = "quadrotor_hill_flythrough") -> None:
    scenario = load_scenario(scenario_name, check_demos=False)
    start = time.perf_counter()
    feedback = design_feedback(scenario)
    t_feedback = time.perf_counter() - start
    P, K = feedback.P, feedback.K
    P_inv = np.linalg.inv(P)
    c = list(scenario.position_index)
    i_theta = scenario.state_names.index("theta")
    j_u1 = scenario.input_names.index("u1")
    lo_theta, hi_theta = scenario.operating_region["theta"]
    lo_u1, hi_u1 = scenario.operating_region["u1"]
    S = np.eye(scenario.n)[:, np.flatnonzero(scenario.init_upper > scenario.init_lower)]
    S_slice = S @ np.linalg.inv(S.T @ P @ S) @ S.T  # (n, n) the ball's slice along Init
    print(f"{scenario_name}: constant certificate {feedback.message} ({t_feedback:.1f} s)")
    header = (
        f"{'demo':>4} {'r':>6} {'rho':>6} {'room':>5} {'room bound by':<19} {'pos c/f (m)':>11} "
        f"{'theta c/f':>11} {'u1 c/f (N)':>11} {'|theta| usable c/f':>18} "
        f"{'u1 usable: const':>17} {'funnel':>13} {'cpu (s)':>7} {'wall (s)':>8}"
    )
    print(header)
    seconds: list[float] = []
    for index, demo in enumerate(scenario.demos, start=1):
        trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
        r = robustness_radius(scenario, feedback.tube, trajectory).radius
        # Constant: the ball of radius r shrinks as exp(-lambda t): the largest extent is at t = 0.
        pos_c = r * np.sqrt(np.linalg.eigvalsh(P_inv[np.ix_(c, c)])[-1])
        theta_c = r * np.sqrt(P_inv[i_theta, i_theta])
        u1_c = r * np.sqrt(K[j_u1] @ P_inv @ K[j_u1])
        cpu = time.process_time()
        funnel = synthesize_funnel(
            scenario, trajectory, state_bounds=STATE_BOUNDS, initial=r**2 * S_slice
        )
        seconds.append(time.process_time() - cpu)
        if not funnel.success:
            print(
                f"{index:>4} {r:6.3f} funnel failed: {funnel.message} "
                f"({seconds[-1]:.1f} s cpu, {funnel.seconds:.1f} s wall)"
            )
            continue
        Q, rho = funnel.Q, funnel.rho
        pos_f = rho * np.sqrt(np.linalg.eigvalsh(Q[:, c][:, :, c])[:, -1].max())
        theta_f = rho * np.sqrt(Q[:, i_theta, i_theta].max())
        gain = funnel.K[:, j_u1]  # (N, n)
        u1_f = rho * np.sqrt(
            max(np.einsum("ki,kil,kl->k", gain, Q[e : len(Q) - 1 + e], gain).max() for e in (0, 1))
        )
        lower, upper = scenario.input_lower[j_u1], scenario.input_upper[j_u1]
        constraints = {k: v for k, v in funnel.limits.items() if k != "design"}
        tightest = min(constraints, key=constraints.__getitem__)
        print(
            f"{index:>4} {r:6.3f} {rho:6.3f} {constraints[tightest]:5.2f} {tightest:<19} "
            f"{pos_c:5.2f}/{pos_f:5.2f} "
            f"{theta_c:5.3f}/{theta_f:5.3f} {u1_c:5.2f}/{u1_f:5.2f} "
            f"{hi_theta - theta_c:8.3f}/{STATE_BOUNDS['theta'][1] - theta_f:<9.3f} "
            f"[{lo_u1 + u1_c:5.2f}, {hi_u1 - u1_c:5.2f}]   "
            f"[{lower + u1_f:5.2f}, {upper - u1_f:5.2f}] {seconds[-1]:7.2f} {funnel.seconds:8.1f}"
        )
    print(
        "c/f: constant / funnel, largest extent over the flight of the tube that holds the same "
        f"initial ball; the constant certificate's region is theta in [{lo_theta:g}, "
        f"{hi_theta:g}], u1 in [{lo_u1:g}, {hi_u1:g}]; the funnel's envelope is theta in "
        f"{list(STATE_BOUNDS['theta'])}, u1 in [{lower:g}, {upper:g}]"
    )
    met = all(value <= TARGET for value in seconds)
    print(
        f"  [{'met' if met else 'MISSED'}] funnel synthesis per trajectory <= {TARGET:g} s: "
        f"{min(seconds):.2f}-{max(seconds):.2f} s cpu, mean {np.mean(seconds):.2f} s "
        f"(funnel.py HOLD = {HOLD} samples per LMI piece)"
    )
