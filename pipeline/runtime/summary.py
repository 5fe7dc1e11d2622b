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

from pipeline.model import geometry
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.reporting.summary import (
    CertificationSummary,
    Claim,
    ClaimKind,
    ControllerSummary,
    DemoSummary,
    FalsificationSummary,
    FeedbackSummary,
    Headline,
    MonteCarloSummary,
    Quantiles,
    Reproducibility,
    StressRunSummary,
    StressSummary,
    Summary,
    Verdict,
)
from pipeline.runtime.terminal import length_unit

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from stages.certify import CertificationResult
    from stages.controller import ControllerResult
    from stages.coverage import CoverageResult, CoveringRadius
    from stages.feedback import FeedbackResult
    from stages.funnel import FunnelStageResult
    from stages.montecarlo import MonteCarloResult
    from stages.optimize import OptimizeResult
    from stages.radius import RadiusResult
    from stages.stress import StressResult, StressRun

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


def _reasons(run: StageResults, demos: Sequence[DemoSummary]) -> tuple[str, ...]:
    """Why the run is not certified and validated (empty when it is)."""
    reasons = []
    if not run.coverage.covered:
        gap = run.coverage.largest_gap()
        where = (
            "" if gap is None else f"; record a new demonstration from {np.round(gap, 3).tolist()}"
        )
        reasons.append(f"coverage gap: {run.coverage.message}{where}")
    failed = [d.demo for d in demos if not d.optimized]
    if failed:
        reasons.append(f"not optimized (kept as flown): {', '.join(failed)}")
    if run.funnels is None and any(r.radius <= 0 for r in run.final_radii):
        reasons.append("a nominal trajectory has no robustness radius")
    if run.funnels is not None and not run.funnels.usable:
        reasons.append(f"no funnel certified: {run.funnels.message}")
    if not run.certification.success:
        reasons.append(run.certification.message)
    if not run.montecarlo.success:
        reasons.append(f"Monte Carlo failure: {run.montecarlo.message}")
    return tuple(reasons)


def _claims(run: StageResults, certified: bool) -> tuple[Claim, ...]:
    mc = run.montecarlo
    falsification = mc.falsification
    return (
        *_certificate_claims(run, certified),
        _after_horizon(run, certified),
        Claim(
            claim=f"failure probability <= {mc.failure_bound:.2e}",
            kind=ClaimKind.STATISTICALLY_VALIDATED,
            how=f"{mc.samples} i.i.d. closed-loop runs from controller.json, "
            "one-sided 95% Clopper-Pearson bound",
        ),
        Claim(
            claim=f"worst safety margin found {falsification.worst_margin:.3f}"
            + (f" ({falsification.binding})" if falsification.binding else ""),
            kind=ClaimKind.FALSIFICATION_SEARCHED,
            how=f"Init corners, Sobol points and Nelder-Mead ({falsification.evaluations} "
            "closed-loop runs); evidence, not a bound",
        ),
    )


def _certificate_claims(run: StageResults, certified: bool) -> tuple[Claim, ...]:
    """What the certificate proves, "certified" only where the check of controller.json as
    written (stage ``certify``) proved it."""
    feedback, check = run.feedback, run.certification
    contraction = ClaimKind.CERTIFIED if check.contraction_margin < 0 else ClaimKind.NOT_ESTABLISHED
    if run.funnels is not None:
        dropped = "" if not run.funnels.rejected else f"; {'; '.join(run.funnels.rejected)}"
        shipped = len(run.funnels.usable)
        return (
            Claim(
                claim=f"each of the {shipped} shipped funnels is invariant under the law as "
                "shipped: no flight that starts in E_i(0) leaves E_i(t) = {||x - x_ref_i(t)||_"
                "P_i(t) <= rho_i} before T_i (the law tracks x_ref interpolated; its error is in "
                "the proof)",
                kind=contraction if check.success else ClaimKind.NOT_ESTABLISHED,
                how=f"LMIs (F3) at every vertex of a sound Jacobian hull of each interval's tube, "
                "at both ends of every interval, solved by Clarabel; re-verified on "
                "controller.json as written with the interpolated reference's bounded term "
                f"(largest eigenvalue plus term {check.contraction_margin:.2e} < -1e-6)"
                f"{dropped}",
            ),
            Claim(
                claim="every start in Init lies in a funnel that avoids Unsafe, keeps the "
                "inputs and state bounds, and ends in Goal",
                kind=ClaimKind.CERTIFIED if certified else ClaimKind.NOT_ESTABLISHED,
                how="funnel levels bounded on a dense grid with a bound between grid points; "
                f"Init covered by the funnels' initial ellipsoids by box subdivision "
                f"({run.coverage.message}); both re-verified on controller.json as written",
            ),
        )
    return (
        Claim(
            claim=f"contraction at rate {feedback.rate:g} over the operating region",
            kind=contraction,
            how=f"LMI ({feedback.gain} gain) solved by Clarabel, eigenvalues re-checked at "
            f"all {len(feedback.vertices)} vertices of a sound Jacobian hull "
            f"(largest eigenvalue {feedback.certified_margin:.2e} < 0); re-verified on "
            f"controller.json as written (largest eigenvalue {check.contraction_margin:.2e})",
        ),
        Claim(
            claim="every start in Init lies in a tube that avoids Unsafe"
            + (", keeps the state bounds," if run.scenario.state_bounds else "")
            + " and ends in Goal",
            kind=ClaimKind.CERTIFIED if certified else ClaimKind.NOT_ESTABLISHED,
            how="robustness radii on a dense grid with a bound between grid points; "
            f"Init covered by box subdivision ({run.final_coverage.message}); both re-verified "
            "on controller.json as written",
        ),
    )


def _after_horizon(run: StageResults, certified: bool) -> Claim:
    """After ``T``: safe for all time when the file's terminal controller is certified; else
    not established (the law refuses ``t > T``), with the reason."""
    check = run.certification
    if check.terminal and certified:
        return Claim(
            claim="after T every covered start stays in Goal for all time (terminal controller)",
            kind=ClaimKind.CERTIFIED,
            how=f"invariant ellipsoid of the terminal law re-verified on controller.json "
            f"(decay {check.terminal_decay:.3g}/s at every hull vertex over its bounding box, "
            f"inside Goal, no clipping) holding every end tube (at most {check.terminal_fit:.0%} "
            "of its radius, exact S-procedure test)",
        )
    return Claim(
        claim="after T: nothing (the law refuses t > T)",
        kind=ClaimKind.NOT_ESTABLISHED,
        how=run.controller.terminal_message or "no terminal controller",
    )


def _feedback(run: StageResults) -> FeedbackSummary:
    feedback, covering = run.feedback, run.covering
    r_d = feedback.required_radius(run.scenario.clearance)
    return FeedbackSummary(
        gain=feedback.gain,
        K=tuple(tuple(row) for row in np.asarray(feedback.K).tolist()),
        P_eigenvalues=tuple(np.linalg.eigvalsh(feedback.certified_tube.P).tolist()),
        rate=feedback.rate,
        region={k: (float(v[0]), float(v[1])) for k, v in feedback.region.items()},
        required_radius=r_d,
        covering_radius=covering.radius if covering.covered else None,
        kept_radius=covering.kept_radius(r_d),
        input_margin_at_r_d=tuple(feedback.input_margin(r_d).tolist()),
        region_extent_at_r_d=feedback.region_extent(r_d),
        vertices=len(feedback.vertices),
        message=feedback.message,
    )


def _montecarlo(mc: MonteCarloResult) -> MonteCarloSummary:
    falsification = mc.falsification
    return MonteCarloSummary(
        samples=mc.samples,
        seed=mc.seed,
        failures=dict(mc.failures),
        failure_bound_95=mc.failure_bound,
        min_clearance=mc.min_clearance,
        min_goal_margin=mc.min_goal_margin,
        max_tube_tightness=mc.max_tube_tightness,
        tube_ratio_at_T=_quantiles(mc.tube_final),
        falsification=FalsificationSummary(
            worst_x0=tuple(falsification.worst_x0.tolist()),
            worst_margin=falsification.worst_margin,
            binding=falsification.binding,
            evaluations=falsification.evaluations,
        ),
        message=mc.message,
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
    written (stage ``certify``) passed and the stages' own results agree."""
    scenario, mc = run.scenario, run.montecarlo
    demos = _demos(run)
    if run.funnels is not None:  # what certify proved on the shipped funnels, and coverage
        certified = bool(run.certification.success and run.coverage.covered and run.funnels.usable)
    else:
        certified = bool(
            run.certification.success
            and run.feedback.success
            and run.final_coverage.covered
            and all(r.radius > 0 for r in run.final_radii)
        )
    T_before = np.array([d.T_demo for d in demos])
    T_after = np.array([d.T_optimized for d in demos])
    check = run.certification
    return Summary(
        scenario=scenario.name,
        verdict=Verdict.of(certified=certified, validated=bool(mc.success)),
        reasons=_reasons(run, demos),
        claims=_claims(run, certified),
        headline=Headline(
            T_demo_mean=float(T_before.mean()),
            T_optimized_mean=float(T_after.mean()),
            faster_percent_mean=float(100 * np.mean(1 - T_after / T_before)),
            min_clearance_before=float(min(d.clearance_before for d in demos)),
            min_clearance_after=float(min(d.clearance_after for d in demos)),
            required_clearance=scenario.clearance,
            coverage_before=run.demo_coverage.covered_fraction,
            coverage_after=run.coverage.covered_fraction,
            covered_before=bool(run.demo_coverage.covered),
            covered_after=bool(run.coverage.covered),
            montecarlo_samples=mc.samples,
            montecarlo_failures=int(sum(mc.failures.values())),
            failure_bound_95=mc.failure_bound,
        ),
        feedback=_feedback(run),
        demos=demos,
        montecarlo=_montecarlo(mc),
        controller=ControllerSummary(
            path=str(run.controller.path),
            trajectories=run.controller.trajectories,
            interpolation_error_P=run.controller.interpolation_error,
        ),
        certification=CertificationSummary(
            certified=check.success,
            sha256=check.sha256,
            metric_eigenvalue=check.metric_eigenvalue,
            contraction_margin=check.contraction_margin,
            vertices=check.vertices,
            covered_fraction=check.covered_fraction,
            message=check.message,
        ),
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
    )


def _quantiles(values: FloatArray) -> Quantiles | None:
    """Median, 95th percentile and maximum of ``values (k,)``; None when empty."""
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return None
    median, p95, top = np.quantile(values, [0.5, 0.95, 1.0])
    return Quantiles(median=float(median), p95=float(p95), max=float(top))


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
