"""Stage ``stress`` (``--stress``): how much margin is left under perturbations the certificate
does not cover, and what the feedback buys. Reported separately, never part of the certificate
or the verdict.

A scenario that declares its uncertainty (``uncertainty:``, held by the certificate) is stressed
beyond it: every run draws from the declaration widened ``BEYOND`` (2) times about the nominal
(``Uncertainty.scaled``: the parameter intervals and the gust box), as the Monte Carlo stage
draws the declared one (``pipeline.numerics.closed_loop.gusts.sample``: parameters uniform or at
corners, 0.5 s piecewise-constant gusts, half the runs bang-bang at random corners), on the compiled
kernel, continued to ``T + 10`` s when the file has a law past ``T``. A run fails if it enters
Unsafe, misses Goal, clips, leaves the state bounds or (after ``T``) Goal, as in the Monte Carlo
stage; the ``stress:`` block is not used then.

Without a declaration, each run draws a constant additive term in the state derivative, uniform
within the scenario's ``stress.disturbance`` bounds (e.g. wind), and Gaussian measurement noise
with the standard deviations of ``stress.measurement_noise``, redrawn every RK4 step.

Either way the same runs are repeated with ``K = 0`` (the reference input replayed open loop;
a terminal law past ``T`` keeps its own gain).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from pipeline.controller import load
from pipeline.model.scenario import Scenario
from pipeline.numerics.closed_loop.gusts import sample
from pipeline.numerics.closed_loop.rollouts import (
    HOLD_SECONDS,
    check_runs_compiled,
    hold_runs_compiled,
)
from pipeline.numerics.closed_loop.simulate import RunChecks, check_runs
from pipeline.numerics.closed_loop.worst_case import horizon
from pipeline.results.stage import FileInput, Stage, StageInputs
from pipeline.results.stress import StressResult as StressResult
from pipeline.results.stress import StressRun as StressRun

BEYOND = 2.0  # the declared uncertainty's multiple that a declaring scenario is stressed with


def _beyond_campaign(
    scenario: Scenario, controller_path: Path, samples: int, seed: int, gain_scale: float
) -> StressRun:
    """The runs under the declared uncertainty widened ``BEYOND`` times (see the module)."""
    stressed = dataclasses.replace(scenario, uncertainty=scenario.uncertainty.scaled(BEYOND))
    controller = load(controller_path).with_gain(gain_scale)
    rng = np.random.default_rng(seed)  # the same draws for both campaigns
    lo, hi = scenario.init_lower, scenario.init_upper
    x0 = lo + (hi - lo) * rng.random((samples, scenario.n))
    draws = sample(stressed.uncertainty, rng, samples, horizon(controller, HOLD_SECONDS))
    checks = check_runs_compiled(stressed, controller, x0, draws=draws)
    masks = checks.failures()
    for kind in ("tube", "uncovered", *(() if scenario.state_bounds else ("bounds",))):
        masks.pop(kind)
    if controller.terminal is not None:
        covered = checks.covered
        after = hold_runs_compiled(
            stressed,
            controller,
            x0[covered],
            HOLD_SECONDS,
            draws=draws.rows(covered),
            ends=checks.final_state[covered],
        )
        masks["after_T"] = np.zeros(samples, dtype=bool)
        # beyond the declared bound the terminal ellipsoid is not certified: Goal is the test
        masks["after_T"][covered] = after.failures(ellipsoid=False)
    return _stress_run(gain_scale, samples, masks, checks)


def _stress_run(
    gain_scale: float, samples: int, masks: dict[str, np.ndarray], checks: RunChecks
) -> StressRun:
    """The campaign's counts: failures per kind (``masks``: name -> (samples,) bool), the share
    of runs with any, and the smallest clearance and Goal margin of ``checks``."""
    failed = np.any(list(masks.values()), axis=0)
    return StressRun(
        gain_scale=gain_scale,
        samples=samples,
        failures={k: int(v.sum()) for k, v in masks.items()},
        failed_fraction=float(failed.mean()),
        min_clearance=float(checks.clearance.min()),
        min_goal_margin=float(checks.goal_margin.min()),
    )


def _campaign(
    scenario: Scenario, controller_path: Path, samples: int, seed: int, gain_scale: float
) -> StressRun:
    stress = scenario.spec.stress
    if stress is None:  # stress_test returns before any campaign without a 'stress' section
        raise ValueError(f"{scenario.name}: no 'stress' section to run a stress campaign from")
    controller = load(controller_path).with_gain(gain_scale)
    rng = np.random.default_rng(seed)  # the same draws for both campaigns
    lo, hi = scenario.init_lower, scenario.init_upper
    x0 = lo + (hi - lo) * rng.random((samples, scenario.n))
    bounds = np.array([stress.disturbance.get(name, 0.0) for name in scenario.state_names])
    disturbance = bounds * rng.uniform(-1.0, 1.0, size=(samples, scenario.n))
    noise_std = np.array([stress.measurement_noise.get(name, 0.0) for name in scenario.state_names])
    checks, _ = check_runs(
        scenario, controller, x0, disturbance=disturbance, noise_std=noise_std, rng=rng
    )
    masks = checks.failures()
    masks.pop("tube")  # the tube is not claimed under perturbations
    masks.pop("uncovered")
    masks.pop("bounds")  # as before the state bounds were checked
    return _stress_run(gain_scale, samples, masks, checks)


def stress_test(
    scenario: Scenario, controller_path: Path, samples: int = 1000, seed: int = 0
) -> StressResult:
    """Closed loop under the scenario's stress perturbations, with and without the feedback:
    beyond the declared uncertainty when the scenario declares one, else its ``stress`` block."""
    if not scenario.uncertainty.empty:
        with_feedback = _beyond_campaign(scenario, controller_path, samples, seed, 1.0)
        without = _beyond_campaign(scenario, controller_path, samples, seed, 0.0)
        return StressResult(
            with_feedback=with_feedback,
            without_feedback=without,
            success=True,
            message=(
                f"beyond the declared uncertainty ({BEYOND:g}x its parameter intervals and "
                f"gusts), {with_feedback.failed_fraction:.1%} of {samples} runs fail with the "
                f"feedback (min clearance {with_feedback.min_clearance:.2f} m) and "
                f"{without.failed_fraction:.1%} with K = 0 (min clearance "
                f"{without.min_clearance:.2f} m); not part of the certificate"
            ),
            beyond_declared=BEYOND,
        )
    if scenario.spec.stress is None:
        return StressResult(
            with_feedback=_empty(),
            without_feedback=_empty(),
            success=False,
            message=f"scenario '{scenario.name}' declares no 'stress' section",
        )
    with_feedback = _campaign(scenario, controller_path, samples, seed, 1.0)
    without = _campaign(scenario, controller_path, samples, seed, 0.0)
    message = (
        f"under stress, {with_feedback.failed_fraction:.1%} of {samples} runs fail with the "
        f"feedback (min clearance {with_feedback.min_clearance:.2f} m) and "
        f"{without.failed_fraction:.1%} with K = 0 (min clearance "
        f"{without.min_clearance:.2f} m)"
    )
    return StressResult(
        with_feedback=with_feedback, without_feedback=without, success=True, message=message
    )


def _empty() -> StressRun:
    nan = float("nan")
    return StressRun(
        gain_scale=1.0,
        samples=0,
        failures={},
        failed_fraction=nan,
        min_clearance=nan,
        min_goal_margin=nan,
    )


@dataclass(frozen=True, kw_only=True)
class StressInputs(StageInputs):
    """What stage ``stress`` reads: the scenario's ``stress`` section (in ``spec``), the
    ``controller.json`` it flies (keyed by its bytes) and the seed."""

    scenario_fields: ClassVar = (
        "dynamics",
        "goal",
        "goal_bounds",
        "init_lower",
        "init_upper",
        "name",
        "position_index",
        "spec",
        "unsafe",
        "uncertainty",
        "state_bounds",
    )
    scenario: Scenario
    controller: FileInput
    seed: int


def _stress_stage(inputs: StressInputs) -> StressResult:
    return stress_test(inputs.scenario, inputs.controller.path, seed=inputs.seed)


STRESS = Stage("stress", _stress_stage, StressInputs, StressResult)
