"""The optimizer's design choices on quadrotor_hill_flythrough, side by side (docs/architecture.md).

Every variant optimizes all demos with ``stages.optimize.optimize_demo`` and the feedback
stage's margins; printed: demos feasible at their own length, demos optimized and verified, mean
optimized duration, wall time as a ratio to the default's in this run, and the horizons found.
"""

from __future__ import annotations

import time

import numpy as np

from pipeline.model.scenario import load_scenario
from stages.feedback import design_feedback
from stages.optimize import ConstraintMargins, OptimizeOptions, optimize_demo

VARIANTS = {
    "open loop, bisection, truncate (paper)": OptimizeOptions(
        parameterization="open_loop", search="bisection", seed_mode="truncate"
    ),
    "stabilised, bisection, truncate": OptimizeOptions(search="bisection", seed_mode="truncate"),
    "stabilised, continuation, truncate": OptimizeOptions(seed_mode="truncate"),
    "stabilised, continuation, compress, no overshoot": OptimizeOptions(overshoot=0.0),
    "default (stabilised, continuation, compress)": OptimizeOptions(),
    "L-BFGS-B, no overshoot": OptimizeOptions(method="lbfgs", overshoot=0.0),
    "L-BFGS-B": OptimizeOptions(method="lbfgs"),
}


def run(scenario_name: str = "quadrotor_hill_flythrough") -> None:
    scenario = load_scenario(scenario_name)
    feedback = design_feedback(scenario)
    r_d = feedback.required_radius(scenario.clearance)
    margins = ConstraintMargins.of_tube(feedback.certified_tube, r_d)
    demos = range(len(scenario.demos))
    print(f"{scenario_name}, {len(demos)} demos, gradient descent unless said", flush=True)
    rows = []
    for name, options in VARIANTS.items():
        start = time.perf_counter()
        results = [optimize_demo(scenario, i, margins, options) for i in demos]
        rows.append((name, time.perf_counter() - start, results))
    default = next(seconds for name, seconds, _ in rows if name.startswith("default"))
    print(f"{'variant':<50} {'own N ok':>8} {'verified':>8} {'mean T':>7} {'time':>5}  N per demo")
    for name, seconds, results in rows:
        own = sum(r.tries[0].feasible for r in results)
        verified = sum(r.success for r in results)
        mean_T = np.mean([r.N * scenario.Ts for r in results])
        print(
            f"{name:<50} {own:>6}/{len(demos)} {verified:>6}/{len(demos)} {mean_T:>6.2f}s"
            f" {seconds / default:>5.2f}  {[r.N for r in results]}"
        )
    print("(own N ok: feasible at the demo's own length; time: wall time / the default's)")
