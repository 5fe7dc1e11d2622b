"""What the declared uncertainty costs a pilot who knows it: the minimum time to rest in Goal at
its worst corner, against the nominal model's (issue 29).

For each demo start, IPOPT's minimum time to arrive at rest in Goal (``bench.uncertified``'s
at-rest constraints: clearance d, Goal itself, the full input bounds, ``state_bounds``, no tube),
first under the nominal model (``T_rest``), then once per corner of the uncertainty
(``bench.uncertified.uncertainty_corners``: every parameter at an end of its interval, times a
constant push at every corner of the disturbance box), flown as if that corner were known in
advance, warm-started from the nominal solution. ``T_known`` is the largest of them.

Why it is a floor for any certificate: a law certified for the declared set must bring every
start to rest-like states in Goal by its T under each of these models (a constant push is one
admissible disturbance signal, a corner one admissible parameter value), and knowing the model in
advance can only make a flight faster. So ``T_known / T_rest`` is the part of a certified
``T / T_rest`` that no certificate can remove; what lies above it is the certificate's cost
(unknown parameters, signals that change, the tube). Two caveats, both printed: IPOPT finds local
minima (a corner's true minimum may be smaller), and corners IPOPT fails on are left out (the
floor is then over fewer models). T here is phase 1's free final time (its hold is finer than
Ts), so the ratio is not quantised to Ts.

Printed per demo: ``T_rest``, ``T_known``, the ratio and the worst corner; for quadrotor_hill
also at the bound issue 29 asked for (``ASKED``), 5-10x what it declares. Run:
``python -m bench known_floor`` (needs the ``bench`` extra: casadi); about 3 s per corner.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from bench.bench_optimize import COMPRESSION, IpoptSolution, MinimumTimeNLP, _retime
from bench.uncertified import KnownUncertainty, uncertainty_corners, uncertified_constraints
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.optimize.penalties import Constraints

SCENARIOS = ("quadrotor_hill", "quadrotor_hill_gusty")
# issue 29's asked bound: wind wX in [-1, 0] m/s, mass +-5%, a gust of 0.25 m/s^2 on vX' and vY'
ASKED = {
    "quadrotor_hill": (
        {"wX": (-1.0, 0.0), "m": (0.95, 1.05)},
        {"vX": 0.25, "vY": 0.25},
    )
}


@dataclass(frozen=True, kw_only=True)
class KnownFloor:
    """One demo start: ``T_rest`` (nominal model), ``T_known`` (the largest over the ``solved``
    of ``corners`` models, ``worst`` the corner that set it; NaN and None when none solved)."""

    T_rest: float
    T_known: float
    worst: KnownUncertainty | None
    solved: int
    corners: int


def _at_rest_nominal(scenario: Scenario, demo: int, rest: Constraints) -> IpoptSolution:
    """Phase 1 of ``bench_optimize.ipopt_minimum_time`` under the nominal model."""
    d, Ts = scenario.demos[demo], scenario.Ts
    T_demo = d.us.shape[0] * Ts
    xs = simulate(scenario.dynamics, d.x0, d.us, Ts).xs
    N = max(2, round(d.us.shape[0] / COMPRESSION))
    X, U = _retime(scenario, xs, d.us, T_demo, N, T_demo / COMPRESSION)
    nlp = MinimumTimeNLP(scenario, d.x0, rest, T_max=T_demo)
    return nlp.solve(N, X, U, T_demo / COMPRESSION, free=True)


def known_uncertainty_floor(
    scenario: Scenario, demo: int, rest: Constraints, corners: list[KnownUncertainty]
) -> KnownFloor:
    """The module docstring's ``T_rest`` and ``T_known`` for demo number ``demo``."""
    nominal = _at_rest_nominal(scenario, demo, rest)
    if not nominal.success:
        return KnownFloor(T_rest=np.nan, T_known=np.nan, worst=None, solved=0, corners=len(corners))
    d = scenario.demos[demo]
    T_max = d.us.shape[0] * scenario.Ts
    N = nominal.U.shape[0]
    T_known, worst, solved = np.nan, None, 0
    for corner in corners:
        nlp = MinimumTimeNLP(scenario, d.x0, rest, T_max=T_max, known=corner)
        found = nlp.solve(N, nominal.X, nominal.U, nominal.T, free=True)
        if not found.success:
            continue
        solved += 1
        if not found.T <= T_known:  # NaN on the first
            T_known, worst = found.T, corner
    return KnownFloor(
        T_rest=nominal.T, T_known=T_known, worst=worst, solved=solved, corners=len(corners)
    )


def compare(
    name: str,
    parameters: Mapping[str, tuple[float, float]] | None = None,
    disturbance: Mapping[str, float] | None = None,
) -> None:
    """One line per demo of scenario ``name``, at its declared uncertainty or at the one given."""
    scenario = load_scenario(name)
    declared = scenario.uncertainty
    if parameters is None or disturbance is None:
        parameters = declared.parameters
        disturbance = {
            state: float(h)
            for state, h in zip(scenario.state_names, declared.declared_box, strict=True)
        }
        label = "declared"
    else:
        label = "asked by issue 29"
    corners = uncertainty_corners(scenario, parameters, disturbance)
    bound = ", ".join(
        [f"{k} in [{lo:g}, {hi:g}]" for k, (lo, hi) in parameters.items()]
        + [f"|{k}'| <= {h:g}" for k, h in disturbance.items() if h > 0]
    )
    print(f"{name}, the uncertainty {label} ({bound}; {len(corners)} corners):", flush=True)
    print(f"{'demo':<8} {'T_rest':>7} {'T_known':>7} {'ratio':>6}  worst corner")
    rest = uncertified_constraints(scenario, at_rest=True)
    ratios = []
    for i, demo in enumerate(scenario.demos):
        floor = known_uncertainty_floor(scenario, i, rest, corners)
        ratios.append(floor.T_known / floor.T_rest)
        where = "none solved" if floor.worst is None else floor.worst.describe(scenario)
        if floor.solved < floor.corners:
            where += f" ({floor.solved} of {floor.corners} corners solved)"
        print(
            f"{demo.name:<8} {floor.T_rest:>7.3f} {floor.T_known:>7.3f} {ratios[-1]:>6.3f}"
            f"  {where}",
            flush=True,
        )
    print(
        f"  T_known / T_rest: {np.nanmin(ratios):.3f}-{np.nanmax(ratios):.3f} (the part of a"
        " certified T / T_rest no certificate removes)"
    )


def run() -> None:
    for name in SCENARIOS:
        compare(name)
        if name in ASKED:
            compare(name, *ASKED[name])
