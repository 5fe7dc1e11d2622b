"""The constant and the funnel certificate against the uncertified minimum time (issue 16).

For each scenario, one run per certificate (``pipeline.synthesize``, 1,000 Monte Carlo runs, in a
temporary folder) and, from each demo's start, IPOPT's minimum time with no tube
(``bench.uncertified``: clearance d, Goal itself, the full input bounds, the scenario's
``state_bounds``). Printed per demo: T with each certificate, ``T_unc`` and the ratios
``T / T_unc``, and ``T_rest``, the uncertified minimum time to arrive at rest in Goal (issue 29:
hover, ``bench.uncertified`` ``at_rest``), which a certificate ending in a hover is measured
against; per certificate: verdict, Init coverage and the run's wall time; and the issue's
targets (funnel within 1.10 of ``T_unc`` on quadrotor_hill_flythrough, 1.25 on
quadrotor_hill_gusty_flythrough; within 1.15 of ``T_rest`` on quadrotor_hill and
quadrotor_hill_hold, 1.30 on quadrotor_hill_gusty). Run: ``python -m bench certificates`` (needs
the ``bench`` extra: casadi).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

import pipeline
from bench.bench_optimize import ipopt_minimum_time
from bench.uncertified import uncertified_constraints

TARGETS = {"quadrotor_hill_flythrough": 1.10, "quadrotor_hill_gusty_flythrough": 1.25}
# against T_rest: the flight ends in a hover (issue 29's 1.15 and, with the wider Init, 1.30;
# asked under a larger declared uncertainty than the one they ship)
REST_TARGETS = {"quadrotor_hill_hold": 1.15, "quadrotor_hill": 1.15, "quadrotor_hill_gusty": 1.30}
CERTIFICATES = ("constant", "funnel")
SAMPLES = 1000


def _synthesize(name: str, certificate: str, root: Path) -> tuple[pipeline.Synthesis, float]:
    start = time.perf_counter()
    result = pipeline.synthesize(
        name, out=root / f"{name}-{certificate}", certificate=certificate, samples=SAMPLES
    )
    return result, time.perf_counter() - start


def compare(name: str) -> None:
    """The table above for scenario ``name``."""
    scenario = pipeline.load_scenario(name)
    # the constant certificate refuses a declared uncertainty (exit 2)
    certificates = CERTIFICATES if scenario.uncertainty.empty else ("funnel",)
    with tempfile.TemporaryDirectory() as folder:
        runs = {c: _synthesize(name, c, Path(folder)) for c in certificates}
    for certificate, (result, seconds) in runs.items():
        summary = result.summary
        coverage = np.nan if summary is None else 100 * summary.headline.coverage_after
        print(
            f"{name}, {certificate} certificate: {result.verdict.value}; Init {coverage:.1f}%"
            f" covered; run {seconds:.1f} s (1 worker, {SAMPLES} Monte Carlo runs)"
        )
    free = uncertified_constraints(scenario)
    rest = uncertified_constraints(scenario, at_rest=True)
    print(
        f"{'demo':<8} {'T_unc':>6} {'T_rest':>6} "
        + " ".join(f"{'T_' + c:>10} {'ratio':>6}" for c in runs)
    )
    ratios: dict[str, list[float]] = {c: [] for c in runs}
    rest_ratios: list[float] = []
    for i, demo in enumerate(scenario.demos):
        unc = ipopt_minimum_time(scenario, i, free)
        T_unc = unc.N * scenario.Ts if unc.U is not None else np.nan
        at_rest = ipopt_minimum_time(scenario, i, rest)
        T_rest = at_rest.N * scenario.Ts if at_rest.U is not None else np.nan
        line = f"{demo.name:<8} {T_unc:>6.2f} {T_rest:>6.2f} "
        funnel = runs["funnel"][0].summary
        rest_ratios.append(np.nan if funnel is None else funnel.demos[i].T_optimized / T_rest)
        for certificate, (result, _) in runs.items():
            T = np.nan if result.summary is None else result.summary.demos[i].T_optimized
            ratios[certificate].append(T / T_unc)
            line += f" {T:>10.2f} {T / T_unc:>6.2f}"
        print(line + ("" if unc.U is not None else f"  (IPOPT failed: {unc.message})"))
    for certificate, values in ratios.items():
        print(
            f"  T_{certificate} / T_unc: {np.nanmin(values):.2f}-{np.nanmax(values):.2f},"
            f" median {np.nanmedian(values):.2f}"
        )
    if name in TARGETS:
        worst = np.nanmax(ratios["funnel"])
        met = "met" if worst <= TARGETS[name] else "NOT met"
        print(f"  target: funnel within {TARGETS[name]:.2f} x T_unc on every demo: {met}")
    if name in REST_TARGETS:
        worst = np.nanmax(rest_ratios)
        met = "met" if worst <= REST_TARGETS[name] else "NOT met"
        print(
            f"  T_funnel / T_rest: {np.nanmin(rest_ratios):.2f}-{worst:.2f}; target: within "
            f"{REST_TARGETS[name]:.2f} x T_rest on every demo: {met}"
        )


def run() -> None:
    for name in (*TARGETS, *REST_TARGETS):
        compare(name)
