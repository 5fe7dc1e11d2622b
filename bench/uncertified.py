"""The uncertified minimum time from a demo's start: CasADi + IPOPT with no tube (issue 16).

The same minimum-time NLP as ``bench_optimize`` (direct multiple shooting, RK4 with 4 substeps,
the hold Ts, phases 1 and 2 of its docstring), but with the scenario's real limits and nothing
reserved for a certificate:

    dist(p(x_i), Unsafe_j) >= d              at every grid point (the clearance d, no tube)
    p(x_{N s}) in Goal                        (Goal itself, not shrunk)
    u[k] in the full input bounds
    x_i in state_bounds                       (the physical envelope; quadrotor_hill_flythrough
    |theta| <= 0.8)

``T_certified / T_uncertified`` is then the time the certificate costs on that start.

``at_rest``: the flight must also arrive at rest, every state but the position at its value in
``feedback.reference_state`` (the design equilibrium, ``f(x*, u*) = 0``; quadrotor_hill_flythrough:
hover, speeds and pitch rate 0, pitch at trim 0). That is the uncertified time a certificate that
ends in a hover (issue 29, ``terminal: hold``) is measured against.

``KnownUncertainty``: one corner of a declared uncertainty (parameters at an end of their
intervals, a constant push at a corner of the disturbance box), flown as if the pilot knew it
(``bench.known_floor``).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pipeline.model.scenario import Scenario
from pipeline.numerics.optimize.margins import MarginProfile
from pipeline.numerics.optimize.penalties import Constraints


def uncertified_constraints(scenario: Scenario, *, at_rest: bool = False) -> Constraints:
    """The constraints above in the ``Constraints`` form ``MinimumTimeNLP`` reads (``at_rest``:
    arriving at the design equilibrium in every state but the position)."""
    goal_bounds = dict(scenario.goal_bounds)
    if at_rest:
        rest = scenario.feedback.reference_state
        for i, name in enumerate(scenario.state_names):
            if i not in scenario.position_index:
                goal_bounds[name] = (float(rest[i]), float(rest[i]))
    names = list(scenario.state_bounds)
    index = np.array([scenario.state_names.index(name) for name in names], dtype=np.int64)
    lower = np.array([scenario.state_bounds[name][0] for name in names], dtype=np.float64)
    upper = np.array([scenario.state_bounds[name][1] for name in names], dtype=np.float64)
    goal = list(goal_bounds)
    return Constraints(
        input_lower=np.asarray(scenario.input_lower, dtype=np.float64),
        input_upper=np.asarray(scenario.input_upper, dtype=np.float64),
        region=dict(scenario.state_bounds),
        region_state_index=index,
        region_state_lower=lower,
        region_state_upper=upper,
        region_input_index=np.zeros(0, dtype=np.int64),
        region_input_lower=np.zeros(0),
        region_input_upper=np.zeros(0),
        goal_region=scenario.goal,
        goal_index=np.array([scenario.state_names.index(n) for n in goal], dtype=np.int64),
        goal_lower=np.array([goal_bounds[n][0] for n in goal], dtype=np.float64),
        goal_upper=np.array([goal_bounds[n][1] for n in goal], dtype=np.float64),
        unsafe=dict(scenario.unsafe),
        unsafe_margin=float(scenario.clearance),
        position_index=tuple(scenario.position_index),
        profile=MarginProfile.zero(scenario.n, scenario.m),
    )


@dataclass(frozen=True, kw_only=True)
class KnownUncertainty:
    """One admissible model: ``parameters (q,)`` in ``uncertainty.parameter_names``' order (the
    scenario's parametric dynamics' trailing inputs) and a constant ``push (n,)`` added to the
    state derivatives."""

    parameters: np.ndarray
    push: np.ndarray

    def describe(self, scenario: Scenario) -> str:
        """``"wX=-1, m=1.05, vX'+=-0.25"``: the corner in the scenario's names."""
        names = scenario.uncertainty.parameter_names
        parts = [f"{name}={value:g}" for name, value in zip(names, self.parameters, strict=True)]
        parts += [
            f"{scenario.state_names[i]}'+={self.push[i]:+g}" for i in np.flatnonzero(self.push)
        ]
        return ", ".join(parts)


def uncertainty_corners(
    scenario: Scenario,
    parameters: Mapping[str, tuple[float, float]],
    disturbance: Mapping[str, float],
) -> list[KnownUncertainty]:
    """Every corner of ``parameters`` (intervals, by name; the scenario's uncertain parameters,
    each named once) times the box ``disturbance`` (half-widths by state name): ``2^(q + k)``
    models, k the states with a nonzero half-width."""
    names = scenario.uncertainty.parameter_names
    if set(parameters) != set(names):
        raise ValueError(
            f"corners need intervals for exactly {list(names)}, got {list(parameters)}"
        )
    pushed = [(scenario.state_names.index(name), h) for name, h in disturbance.items() if h > 0]
    corners = []
    for ends in itertools.product(*(parameters[name] for name in names)):
        for signs in itertools.product((-1.0, 1.0), repeat=len(pushed)):
            push = np.zeros(scenario.n)
            for (i, h), sign in zip(pushed, signs, strict=True):
                push[i] = sign * h
            corners.append(KnownUncertainty(parameters=np.array(ends, dtype=float), push=push))
    return corners
