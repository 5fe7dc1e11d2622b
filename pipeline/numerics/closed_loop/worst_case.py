"""A bang-bang worst case under the declared uncertainty: the falsification search's second half.

``stages.montecarlo.falsify`` first searches Init for the worst start of the nominal closed loop.
With a declared uncertainty (``pipeline.model.uncertainty``) this module then searches the
uncertainty for its worst realisation, cheaply and only at the boxes' corners (bang-bang: the
extremes a worst case of a bounded disturbance is made of, by the maximum principle for the
linearised error):

1. the worst few starts found, each flown under every constant corner pattern (each disturbed
   state's gust at ``+-`` its bound for the whole run, with each parameter corner; at most
   ``PATTERNS`` of them, a seeded subset beyond) and ``SWITCHING`` random switching patterns (a
   new corner every gust period, ``pipeline.numerics.closed_loop.gusts``);
2. from the worst pair, a greedy search over single sign flips (one gust period of one state,
   or one parameter), all flips of a round flown in one batch, for ``ROUNDS`` rounds or until no
   flip lowers the margin.

The margin is the smallest of the run's clearance to Unsafe, Goal margin, input slack and
state-bounds margin, to ``T`` and, when the file has a law past ``T``, over the continuation to
``T + hold`` (clearance, Goal at every grid point, slack, state bounds). It is evidence, not a
bound; the pattern found is flown again by a share of the Monte Carlo runs
(``pipeline.numerics.closed_loop.gusts.sample``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from pipeline.controller import Controller
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.closed_loop.gusts import Draws, corners, gust_count
from pipeline.numerics.closed_loop.rollouts import check_runs_compiled, hold_runs_compiled

PATTERNS = 64  # constant corner patterns at most
SWITCHING = 16  # random switching corner patterns
ROUNDS = 3  # greedy sign-flip rounds


@dataclass(frozen=True, kw_only=True)
class WorstCase:
    """The worst start and bang-bang realisation found (``q`` parameters, ``G`` gusts)."""

    x0: FloatArray  # (n,)
    draws: Draws  # one run: parameters (1, q) at corners, gusts (1, G, n) at corners
    margin: float
    binding: str
    evaluations: int


def horizon(controller: Controller, hold_seconds: float) -> float:
    """The longest time a run is flown: ``max T_i``, plus ``hold_seconds`` with a law past T."""
    longest = max(tr.T for tr in controller.trajectories)
    return longest + (hold_seconds if controller.terminal is not None else 0.0)


def margins(
    scenario: Scenario,
    controller: Controller,
    x0: FloatArray,
    draws: Draws,
    hold_seconds: float,
) -> tuple[FloatArray, list[str]]:
    """``(margin (B,), binding)``: each run's smallest margin (see the module) and its kind."""
    checks = check_runs_compiled(scenario, controller, x0, draws=draws)
    bounds = checks.bounds_margin if checks.bounds_margin is not None else np.inf
    parts = {
        "clearance to Unsafe, m": checks.clearance,
        "Goal margin, m": checks.goal_margin,
        "input slack, input units": checks.input_slack,
        "state-bounds margin": np.broadcast_to(bounds, checks.clearance.shape),
    }
    if controller.terminal is not None:
        after = hold_runs_compiled(
            scenario, controller, x0, hold_seconds, draws=draws, ends=checks.final_state
        )
        parts["after T: clearance to Unsafe, m"] = after.clearance
        parts["after T: Goal margin, m"] = after.path_goal_margin
        parts["after T: input slack, input units"] = after.input_slack
        parts["after T: state-bounds margin"] = after.bounds_margin
    stacked = np.stack(list(parts.values()))
    names = list(parts)
    ok = checks.finite & checks.covered
    margin = np.where(ok, stacked.min(axis=0), -np.inf)
    binding = [
        names[k] if f and c else ("not covered" if not c else "non-finite state")
        for k, f, c in zip(stacked.argmin(axis=0), checks.finite, checks.covered, strict=True)
    ]
    return margin, binding


def search(
    scenario: Scenario,
    controller: Controller,
    starts: FloatArray,
    hold_seconds: float,
    seed: int = 0,
) -> WorstCase:
    """The worst bang-bang realisation from ``starts (S, n)`` (worst first), as the module says."""
    uncertainty = scenario.uncertainty
    rng = np.random.default_rng(seed)
    q, n = len(uncertainty.parameter_names), len(uncertainty.disturbance)
    G = gust_count(horizon(controller, hold_seconds))
    disturbed = np.flatnonzero(uncertainty.disturbance > 0)
    constant = np.array(list(itertools.product([-1.0, 1.0], repeat=len(disturbed) + q)))
    if len(constant) > PATTERNS:
        constant = constant[rng.choice(len(constant), PATTERNS, replace=False)]
    parameter_signs = [constant[:, len(disturbed) :]]
    gust_signs = np.zeros((len(constant), G, n))
    gust_signs[:, :, disturbed] = constant[:, None, : len(disturbed)]
    switching = rng.choice([-1.0, 1.0], size=(SWITCHING, G, n))
    parameter_signs.append(rng.choice([-1.0, 1.0], size=(SWITCHING, q)))
    patterns = corners(
        uncertainty,
        np.concatenate(parameter_signs),
        np.concatenate([gust_signs, switching]),
    )
    P, S = len(patterns.gusts), len(starts)
    x0 = np.repeat(starts, P, axis=0)
    everything = Draws(
        parameters=np.tile(patterns.parameters, (S, 1)),
        gusts=np.tile(patterns.gusts, (S, 1, 1)),
        start=np.zeros(S * P),
    )
    margin, binding = margins(scenario, controller, x0, everything, hold_seconds)
    evaluations = len(x0)
    best = int(np.argmin(margin))
    worst_x0, worst = x0[best], everything.rows(np.array([best]))
    worst_margin, worst_binding = float(margin[best]), binding[best]
    for _ in range(ROUNDS):
        flips = _flips(worst, disturbed, uncertainty)
        margin, binding = margins(
            scenario, controller, np.tile(worst_x0, (len(flips.gusts), 1)), flips, hold_seconds
        )
        evaluations += len(margin)
        best = int(np.argmin(margin))
        if not margin[best] < worst_margin:
            break
        worst = flips.rows(np.array([best]))
        worst_margin, worst_binding = float(margin[best]), binding[best]
    return WorstCase(
        x0=worst_x0,
        draws=worst,
        margin=worst_margin,
        binding=worst_binding,
        evaluations=evaluations,
    )


def _flips(draws: Draws, disturbed: np.ndarray, uncertainty: Uncertainty) -> Draws:
    """Every draw differing from ``draws`` (one run at corners) in one gust sign of one disturbed
    state and one period, or in one parameter's corner (upper <-> lower)."""
    G = draws.gusts.shape[1]
    q = draws.parameters.shape[1]
    count = G * len(disturbed) + q
    gusts = np.repeat(draws.gusts, count, axis=0)
    parameters = np.repeat(draws.parameters, count, axis=0)
    for k, (g, i) in enumerate(itertools.product(range(G), disturbed)):
        gusts[k, g, i] = -gusts[k, g, i]
    for j in range(q):  # a corner's other side: lower + upper - value
        k = G * len(disturbed) + j
        parameters[k, j] = uncertainty.parameter_lower[j] + uncertainty.parameter_upper[j]
        parameters[k, j] -= draws.parameters[0, j]
    return Draws(
        parameters=parameters,
        gusts=gusts,
        start=np.zeros(count),
        period=draws.period,
    )
