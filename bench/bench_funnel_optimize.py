"""Optimizing nominal flights against their funnels' extents (issue 16 part 4), on
quadrotor_hill_flythrough.

Per demo: the constant certificate's optimized flight (``stages.optimize.optimize`` at the radius
the orchestrator keeps, ``covering_radius``) -> ``synthesize_funnel`` around it (initial set as
``bench_funnel`` derives it: the slice along Init's free directions ``S`` of the constant
certificate's ball ``||e||_P <= r``, ``r`` that flight's robustness radius,
``Q_init = r^2 S (S^T P S)^-1 S^T``; envelope the scenario's ``state_bounds``) -> optimize again
within that funnel's extents (``stages.optimize.reoptimize_with_funnels``: no operating region,
Unsafe kept by the tube alone) -> ``synthesize_funnel`` around the new flight -> ``check_funnel``
(numpy only, independent of the solver), for ``ROUNDS`` rounds. Printed per round: T before and
after, the new funnel's verdict, ``tau`` (the share of the initial set the LMIs held:
``limits['design']^2``), ``rho``, the binding constraint, the synthesis seconds, and the new
nominal's smallest distance to Unsafe (the tube, not ``d``, is what must clear it). A round is
kept only if its funnel certifies; otherwise the previous flight stands.
Both for margins at each funnel's rho and at level 1 (``LEVELS``).
Run: ``python -m bench funnel_optimize`` (every demo; about ten minutes on 2 cores).
"""

from __future__ import annotations

import os
import time

import numpy as np

from pipeline.model import geometry
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.check import check_funnel
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from stages.coverage import covering_radius
from stages.feedback import design_feedback
from stages.optimize import (
    ConstraintMargins,
    OptimizeOptions,
    optimize,
    reoptimize_with_funnels,
)
from stages.radius import robustness_radius

ROUNDS = 2
# The margins' level: None = each funnel's certified rho (the tube it proved), 1.0 = the tube that
# holds the whole required initial set (what coverage needs).
LEVELS = (None, 1.0)


def run(scenario_name: str = "quadrotor_hill_flythrough", demos: list[int] | None = None) -> None:
    only = os.environ.get("BENCH_DEMOS")  # e.g. BENCH_DEMOS=0,4 for a quick look
    demos = demos if demos is not None else (list(map(int, only.split(","))) if only else None)
    for level in LEVELS:
        _run(scenario_name, demos, level)


def _run(scenario_name: str, demos: list[int] | None, level: float | None) -> None:
    scenario = load_scenario(scenario_name, check_demos=False)
    state_bounds = dict(scenario.state_bounds)
    feedback = design_feedback(scenario)
    tube = feedback.certified_tube
    starts = np.array([demo.x0 for demo in scenario.demos])
    r_d = feedback.required_radius(scenario.clearance)
    trajectories0 = [simulate(scenario.dynamics, d.x0, d.us, scenario.Ts) for d in scenario.demos]
    upper = max(r_d, *(robustness_radius(scenario, tube, t).radius for t in trajectories0))
    r_required = covering_radius(scenario, feedback, starts, upper=upper).kept_radius(r_d)
    margins = ConstraintMargins.of_tube(tube, r_required)
    options = OptimizeOptions()
    start = time.perf_counter()
    constant = optimize(scenario, margins, options, demos=demos)
    print(
        f"{scenario_name}: constant certificate at radius {r_required:.3f}, optimized in "
        f"{time.perf_counter() - start:.1f} s; funnels within {state_bounds} and the input bounds"
        f"; margins at level {'rho' if level is None else level}"
    )
    P = feedback.P
    S = np.eye(scenario.n)[:, np.flatnonzero(scenario.init_upper > scenario.init_lower)]
    S_slice = S @ np.linalg.inv(S.T @ P @ S) @ S.T  # (n, n) the ball's slice along Init

    def flight(x0, u):
        return simulate(scenario.dynamics, x0, u, scenario.Ts)

    def clearance(trajectory) -> float:
        positions = scenario.positions(trajectory.dense_xs)
        return min(float(geometry.distance(positions, s).min()) for s in scenario.unsafe.values())

    print(
        f"{'demo':<8} {'round':>5} {'T before':>8} {'T after':>7} {'funnel':>8} {'tau':>6} "
        f"{'rho':>6} {'bound by':<20} {'synth s':>7} {'opt s':>6} {'clear':>6}"
    )
    for current in constant.trajectories:
        if not current.success:
            print(f"{current.demo:<8} constant optimization failed: {current.message}")
            continue
        trajectory = flight(current.x0, current.u)
        r = robustness_radius(scenario, tube, trajectory).radius
        initial = r**2 * S_slice
        funnel = synthesize_funnel(scenario, trajectory, state_bounds=state_bounds, initial=initial)
        _row(current.demo, 0, None, current.N, funnel, None, clearance(trajectory), scenario.Ts)
        for round_ in range(1, ROUNDS + 1):
            if not funnel.success:
                break
            again = reoptimize_with_funnels(scenario, [current], [funnel], options, level=level)
            new = again.trajectories[0]
            if not new.success:
                print(f"{current.demo:<8} {round_:>5} re-optimization failed: {new.message}")
                break
            trajectory = flight(new.x0, new.u)
            new_funnel = synthesize_funnel(
                scenario, trajectory, state_bounds=state_bounds, initial=initial
            )
            verdict = new_funnel.success and (
                check_funnel(scenario, trajectory, new_funnel, state_bounds) is None
            )
            _row(
                current.demo, round_, current.N, new.N, new_funnel, new.seconds,
                clearance(trajectory), scenario.Ts, verdict,
            )  # fmt: skip
            if not verdict:
                print(f"{'':<8} {'':>5} new funnel not certified: {new_funnel.message}")
                break
            current, funnel = new, new_funnel
    print(
        "T: N Ts (s); funnel: certified by synthesize_funnel and re-checked by check_funnel; "
        "tau: share of the required initial set the LMIs held (1: all of it); clear: the "
        "nominal's smallest grid distance to Unsafe (m); round 0 is the constant certificate's "
        "flight with its funnel"
    )


def _row(demo, round_, N_before, N_after, funnel, seconds, clear, Ts, verdict=None) -> None:
    before = "" if N_before is None else f"{N_before * Ts:.1f}"
    opt = "" if seconds is None else f"{seconds:.1f}"
    ok = funnel.success if verdict is None else verdict
    tau = funnel.limits.get("design", float("nan")) ** 2
    print(
        f"{demo:<8} {round_:>5} {before:>8} {N_after * Ts:7.1f} "
        f"{'certified' if ok else 'REJECTED':>8} {tau:6.3f} {funnel.rho:6.3f} "
        f"{funnel.binding:<20} {funnel.seconds:7.1f} {opt:>6} {clear:6.2f}"
    )
