"""The run's summary, built from the stage results: headline numbers, the verdict and the kind
of every claim (the typed ``Summary`` of ``pipeline.reporting.summary``, written as
``summary.json``); ``pipeline.runtime.terminal`` prints it.

Claims carry their kind: *certified* (LMI and tube bounds, re-verified on controller.json as
written), *statistically validated* (Monte Carlo with its bound), *falsification-searched*
(worst case found by search, no bound). The verdict is for the certificate the run shipped
(``constant`` or ``funnel``); its coverage is that certificate's (the constant balls, or the
funnels' initial ellipsoids ``E_i(0)``).
"""

from __future__ import annotations

import platform
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.controller import ControllerFormatError, load
from pipeline.model import geometry
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.reporting.summary import (
    Claim,
    DemoSummary,
    FunnelSummary,
    Headline,
    Reproducibility,
    StressRunSummary,
    StressSummary,
    Summary,
    Verdict,
)
from pipeline.runtime.shipped import funnel_summaries
from pipeline.runtime.terminal import length_unit
from pipeline.runtime.verdict import (
    Evidence,
    after_horizon,
    certificate_claims,
    certification_summary,
    controller_summary,
    feedback_summary,
    montecarlo_claims,
    montecarlo_summary,
)

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from pipeline.results.certify import CertificationResult
    from pipeline.results.controller import ControllerResult
    from pipeline.results.coverage import CoverageResult, CoveringRadius
    from pipeline.results.feedback import FeedbackResult
    from pipeline.results.funnel import FunnelStageResult
    from pipeline.results.montecarlo import MonteCarloResult
    from pipeline.results.optimize import OptimizeResult
    from pipeline.results.radius import RadiusResult
    from pipeline.results.stress import StressResult, StressRun

KEY_PACKAGES = (
    "numpy",
    "scipy",
    "shapely",
    "cvxpy",
    "clarabel",
    "control",
    "sympy",
    "numba",
    "matplotlib",
)


def _versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("safety-synthesis", *KEY_PACKAGES):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


@dataclass(frozen=True, kw_only=True)
class StageResults:
    """The stage results a summary is made from (one entry per demo in the sequences).

    ``certificate`` is what the run shipped; with ``"funnel"``, ``funnels`` and
    ``funnel_coverage`` are the funnel stage's result and Init's coverage by its ``E_i(0)``."""

    scenario: Scenario
    feedback: FeedbackResult
    demo_trajectories: Sequence[Trajectory]
    demo_radii: Sequence[RadiusResult]
    demo_coverage: CoverageResult
    covering: CoveringRadius
    optimized: OptimizeResult
    final_trajectories: Sequence[Trajectory]
    final_radii: Sequence[RadiusResult]
    final_coverage: CoverageResult
    controller: ControllerResult
    certification: CertificationResult
    montecarlo: MonteCarloResult
    certificate: str = "constant"
    funnels: FunnelStageResult | None = None
    funnel_coverage: CoverageResult | None = None
    # a funnel run: the constant certificate's optimized nominals (final_trajectories are the
    # shipped ones, re-optimized against the funnels)
    constant_trajectories: Sequence[Trajectory] | None = None
    feedback_period: float = 0.0  # the law is held every h s (0: continuous)

    def __post_init__(self) -> None:
        if self.certificate == "funnel":
            if self.funnels is None or self.funnel_coverage is None:
                raise ValueError("a funnel run's results need its funnels and their coverage")
        elif self.certificate != "constant":
            raise ValueError(f"certificate {self.certificate!r}; expected 'constant' or 'funnel'")

    @property
    def coverage(self) -> CoverageResult:
        """Init's coverage by the shipped certificate's initial sets."""
        if self.funnel_coverage is not None and self.certificate == "funnel":
            return self.funnel_coverage
        return self.final_coverage

    @property
    def evidence(self) -> Evidence:
        """What the verdict is derived from (``pipeline.runtime.verdict``)."""
        no_funnel = None
        if self.funnels is not None and not self.funnels.usable:
            no_funnel = self.funnels.message
        return Evidence(
            scenario=self.scenario,
            certificate=self.certificate,
            feedback=self.feedback,
            covering=self.covering,
            demo_coverage=self.demo_coverage,
            coverage=self.coverage,
            optimized=self.optimized,
            final_radii=self.final_radii,
            no_funnel=no_funnel,
            controller=self.controller,
            certification=self.certification,
            montecarlo=self.montecarlo,
            feedback_period=self.feedback_period,
        )


def _funnel_fields(run: StageResults, i: int) -> dict[str, Any]:
    """Trajectory ``i``'s funnel in ``DemoSummary``'s terms (empty for the constant one)."""
    if run.funnels is None:
        return {}
    funnel = run.funnels.funnels[i]
    kept = i in run.funnels.usable
    constant = run.constant_trajectories
    return {
        "T_constant": None if constant is None else constant[i].duration,
        "funnel_level": funnel.rho if kept else 0.0,
        "funnel_binding": funnel.binding if kept else "dropped",
        "funnel_seconds": funnel.seconds,
    }


def _shipped_clearance(run: StageResults, i: int) -> float:
    """The smallest distance to Unsafe over shipped nominal ``i``'s dense grid (a funnel run's:
    its nominals are not the ones the constant radius stage measured)."""
    positions = run.scenario.positions(run.final_trajectories[i].dense_xs)
    unsafe = run.scenario.unsafe.values()
    return min(float(np.min(geometry.distance(positions, region))) for region in unsafe)


def _demos(run: StageResults) -> tuple[DemoSummary, ...]:
    demos = []
    for i, demo in enumerate(run.scenario.demos):
        opt = run.optimized.trajectories[i]
        before, after = run.demo_trajectories[i].duration, run.final_trajectories[i].duration
        radius_before, radius_after = run.demo_radii[i], run.final_radii[i]
        demos.append(
            DemoSummary(
                demo=demo.name,
                start=tuple(demo.x0.tolist()),
                T_demo=before,
                T_optimized=after,
                faster_percent=100 * (1 - after / before),
                optimized=bool(opt.success),
                message=opt.message,
                iterations=int(sum(t.iterations for t in opt.tries)),
                horizons_tried=len(opt.tries),
                seconds=opt.seconds,
                clearance_before=radius_before.nominal_clearance,
                clearance_after=(
                    radius_after.nominal_clearance
                    if run.funnels is None
                    else _shipped_clearance(run, i)
                ),
                radius_before=radius_before.radius,
                radius_after=radius_after.radius,
                binding_before=radius_before.binding,
                binding_after=radius_after.binding,
                binding_time_before=radius_before.binding_time,
                binding_time_after=radius_after.binding_time,
                **_funnel_fields(run, i),
            )
        )
    return tuple(demos)


def _funnels(run: StageResults) -> tuple[FunnelSummary, ...]:
    """What controller.json guarantees per funnel (a funnel run whose file was written): read
    from the file certify checked (this run's; a reused controller stage's result may name the
    folder of the run that first wrote it)."""
    if run.certificate != "funnel" or run.funnels is None or not run.controller.success:
        return ()
    try:
        law = load(run.certification.path)
    except (OSError, ControllerFormatError):
        return ()
    return funnel_summaries(run.scenario, law, run.funnels) if law.funnel else ()


def _claims(run: StageResults, evidence: Evidence, certified: bool) -> tuple[Claim, ...]:
    return (
        *certificate_claims(evidence, certified, run.funnels.rejected if run.funnels else ()),
        after_horizon(evidence, certified),
        *montecarlo_claims(run.montecarlo),
    )


def summarise(
    run: StageResults,
    *,
    timings: Mapping[str, float],
    total_seconds: float,
    command: Sequence[str],
    stress: StressResult | None = None,
) -> Summary:
    """The run's typed summary; "certified" only when the final check of controller.json as
    written (stage ``certify``) passed and the stages' own results agree
    (``pipeline.runtime.verdict``, which ``report`` derives it from again)."""
    scenario, mc, evidence = run.scenario, run.montecarlo, run.evidence
    demos = _demos(run)
    certified = evidence.certified
    T_before = np.array([d.T_demo for d in demos])
    T_after = np.array([d.T_optimized for d in demos])
    return Summary(
        scenario=scenario.name,
        verdict=Verdict.of(certified=certified, validated=bool(mc.success)),
        reasons=evidence.reasons(),
        claims=_claims(run, evidence, certified),
        headline=Headline(
            T_demo_mean=float(T_before.mean()),
            T_optimized_mean=float(T_after.mean()),
            faster_percent_mean=float(100 * np.mean(1 - T_after / T_before)),
            min_clearance_before=float(min(d.clearance_before for d in demos)),
            min_clearance_after=float(min(d.clearance_after for d in demos)),
            required_clearance=scenario.clearance,
            **evidence.headline(),
        ),
        feedback=feedback_summary(evidence),
        demos=demos,
        montecarlo=montecarlo_summary(mc),
        controller=controller_summary(evidence),
        certification=certification_summary(run.certification),
        timings=dict(timings),
        total_seconds=total_seconds,
        reproducibility=Reproducibility(
            versions=_versions(),
            scenario_sha256=scenario.source_hash,
            montecarlo_seed=mc.seed,
            command=tuple(command),
        ),
        stress=None if stress is None else stress_summary(stress),
        certificate=run.certificate,
        funnels=_funnels(run),
    )


def demo_table(scenario: Scenario, trajectories: Sequence[Trajectory]) -> str:
    """The demonstrations as flown: start, duration, the smallest distance of the dense path to
    each Unsafe set (in the position unit), and whether it ends in Goal. ``trajectories``: one
    per demo."""
    names = list(scenario.unsafe)
    header = f"{'demo':<12} {'start':<22} {'T (s)':>6}" + "".join(
        f" {('to ' + name)[:14]:>14}" for name in names
    )
    unit = length_unit(scenario)
    lines = [header + "  ends in Goal" + (f"   (distances in {unit})" if unit else "")]
    for demo, trajectory in zip(scenario.demos, trajectories, strict=True):
        positions = scenario.positions(trajectory.dense_xs)
        start = "(" + ", ".join(f"{v:.2f}" for v in scenario.positions(demo.x0)) + ")"
        clearance = "".join(
            f" {float(geometry.distance(positions, scenario.unsafe[name]).min()):>14.3f}"
            for name in names
        )
        ends = "yes" if bool(scenario.in_goal(trajectory.dense_xs[-1])) else "NO"
        lines.append(f"{demo.name:<12} {start:<22} {trajectory.duration:>6.1f}{clearance}  {ends}")
    return "\n".join(lines)


def stress_summary(stress: StressResult) -> StressSummary:
    """The stress test's numbers (reported separately; never part of the certificate)."""

    def run(r: StressRun) -> StressRunSummary:
        return StressRunSummary(
            samples=r.samples,
            failures=dict(r.failures),
            failed_fraction=r.failed_fraction,
            min_clearance=r.min_clearance,
            min_goal_margin=r.min_goal_margin,
        )

    return StressSummary(
        kind="stress test (not part of the certificate)",
        message=stress.message,
        with_feedback=run(stress.with_feedback),
        without_feedback=run(stress.without_feedback),
    )
