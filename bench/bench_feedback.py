"""Feedback, radius and coverage stages on quadrotor_hill_flythrough, timed against one trajectory
simulation.

Prints the wall time of each and its ratio to simulating one demo (RK4, default substeps) in the
same run, so the numbers compare across machines.
"""

from __future__ import annotations

import numpy as np

from bench.timing import best_time
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.hull import jacobian_hull
from stages.coverage import cover_init
from stages.feedback import design_feedback
from stages.radius import robustness_radius


def run(scenario_name: str = "quadrotor_hill_flythrough") -> None:
    scenario = load_scenario(scenario_name, check_demos=False)
    demos = scenario.demos
    if not demos:
        print(f"{scenario_name} has no demos; nothing to time")
        return
    demo = demos[0]
    t_sim = best_time(lambda: simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts))
    trajectories = [simulate(scenario.dynamics, d.x0, d.us, scenario.Ts) for d in demos]

    t_hull = best_time(lambda: jacobian_hull(scenario.dynamics, scenario.operating_region))
    feedback = design_feedback(scenario)
    t_auto = best_time(lambda: design_feedback(scenario), repeat=3)
    t_lqr = best_time(lambda: design_feedback(scenario, gain="lqr"), repeat=3)
    t_joint = best_time(lambda: design_feedback(scenario, gain="joint"), repeat=3)

    def radii() -> list[float]:
        return [
            robustness_radius(scenario, feedback.certified_tube, t).radius for t in trajectories
        ]

    t_radius = best_time(radii) / len(trajectories)
    centers = np.array([d.x0 for d in demos])
    r_d = feedback.required_radius(scenario.clearance)
    radius_values = np.array(radii())
    t_cover = best_time(lambda: cover_init(scenario, feedback, centers, radius_values))
    small = np.full(len(demos), 0.3 * r_d)
    t_cover_gaps = best_time(lambda: cover_init(scenario, feedback, centers, small), repeat=3)
    gaps = cover_init(scenario, feedback, centers, small)

    print(f"{scenario_name}: {len(demos)} demos, {feedback.message}")
    print(f"one trajectory simulation ({demo.N} samples): {t_sim * 1e3:.2f} ms (= 1)")
    rows = [
        ("Jacobian hull", t_hull),
        ("feedback design, gain=auto (LQR + joint)", t_auto),
        ("feedback design, gain=lqr", t_lqr),
        ("feedback design, gain=joint", t_joint),
        ("radius, per trajectory", t_radius),
        ("coverage, demo radii (covered)", t_cover),
        (f"coverage, radii 0.3 r_d (gaps: {len(gaps.uncovered_boxes)} boxes)", t_cover_gaps),
    ]
    width = max(len(name) for name, _ in rows)
    for name, seconds in rows:
        print(f"{name:<{width}}  {seconds * 1e3:9.2f} ms  {seconds / t_sim:9.3g} x simulation")
