"""A run's verdict and the numbers that carry it, derived from its evidence (``Evidence``): the
certify stage's check of ``controller.json`` as written, the Monte Carlo result of that file, and
the stage results the certificate rests on.

``pipeline.runtime.summary.summarise`` derives them for a run; ``report`` derives them again from
the output folder (``pipeline.runtime.stored``), with the same functions, and never reads them
from ``summary.json``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.model.scenario import Scenario
from pipeline.numerics.tube.feedback_search import fix_for
from pipeline.numerics.uncertainty import additive_bound
from pipeline.numerics.verify.cover import balls_to_cover
from pipeline.reporting.numbers import margin, montecarlo_counts
from pipeline.reporting.summary import (
    CertificationSummary,
    Claim,
    ClaimKind,
    ControllerSummary,
    FalsificationSummary,
    FeedbackSummary,
    MonteCarloSummary,
    Quantiles,
)

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from pipeline.model.dynamics import FloatArray
    from pipeline.results.certify import CertificationResult
    from pipeline.results.controller import ControllerResult
    from pipeline.results.coverage import CoverageResult, CoveringRadius
    from pipeline.results.feedback import FeedbackResult
    from pipeline.results.montecarlo import MonteCarloResult
    from pipeline.results.optimize import OptimizeResult
    from pipeline.results.radius import RadiusResult


FEW_DEMOS = 8  # "record more demonstrations" up to this many (or as many as the scenario has)


@dataclass(frozen=True, kw_only=True)
class Evidence:
    """What a run's verdict is derived from.

    Attributes:
      certificate: what the run shipped, ``"constant"`` or ``"funnel"``.
      coverage: Init's coverage by the shipped certificate's initial sets (the constant balls,
        or the funnels' initial ellipsoids ``E_i(0)``); demo_coverage: by the demos' balls.
      final_radii: the robustness radius of each final nominal (one per demo).
      no_funnel: a funnel run that kept no funnel: the funnel stage's message (else None).
      certification: stage ``certify`` on ``controller.json`` as written; montecarlo: the
        closed-loop runs of that file.
      feedback_period: the file's: the law is evaluated every ``h`` s and held in between (0:
        continuous feedback); the funnel certificate's claims say so.
    """

    scenario: Scenario
    certificate: str
    feedback: FeedbackResult
    covering: CoveringRadius
    demo_coverage: CoverageResult
    coverage: CoverageResult
    optimized: OptimizeResult
    final_radii: Sequence[RadiusResult]
    no_funnel: str | None = None
    controller: ControllerResult
    certification: CertificationResult
    montecarlo: MonteCarloResult
    feedback_period: float = 0.0

    @property
    def certified(self) -> bool:
        """The check of controller.json as written passed and the stages' own results agree."""
        if self.certificate == "funnel":
            return bool(
                self.certification.success and self.coverage.covered and self.no_funnel is None
            )
        if self.certificate == "constant":
            return bool(
                self.certification.success
                and self.feedback.success
                and self.coverage.covered
                and all(r.radius > 0 for r in self.final_radii)
            )
        raise ValueError(f"certificate {self.certificate!r}; expected 'constant' or 'funnel'")

    def reasons(self) -> tuple[str, ...]:
        """Why the run is not certified and validated (empty when it is)."""
        reasons = []
        if not self.coverage.covered:
            reasons.append(f"coverage gap: {self.coverage.message}{self.gap_advice()}")
        failed = [
            demo.name
            for demo, tried in zip(self.scenario.demos, self.optimized.trajectories, strict=True)
            if not tried.success
        ]
        if failed:
            reasons.append(f"not optimized (kept as flown): {', '.join(failed)}")
        if self.certificate == "constant" and any(r.radius <= 0 for r in self.final_radii):
            reasons.append("a nominal trajectory has no robustness radius")
        if self.no_funnel is not None:
            reasons.append(f"no funnel certified: {self.no_funnel}")
        if not self.certification.success:
            reasons.append(self.certification.message)
        if not self.montecarlo.success:
            mc = self.montecarlo
            counts = montecarlo_counts(mc.samples, failed_runs(mc), mc.failures)
            reasons.append(f"Monte Carlo failure: {counts}")
        return tuple(reasons)

    def gap_advice(self) -> str:
        """What closes the coverage gap: a few more demos (how many, and where the first
        starts), or, when the tubes are too small for a few to do it, the feedback's limit."""
        gap = self.coverage.largest_gap()
        radii = [r.radius for r in self.final_radii if r.radius > 0]
        if gap is None or not radii or not self.feedback.success:
            return ""
        s, P = self.scenario, self.feedback.certified_tube.P
        radius = float(np.median(radii))
        more = balls_to_cover(
            P, radius, s.init_lower, s.init_upper, 1 - self.coverage.covered_fraction
        )
        start = np.round(gap, 3).tolist()
        if more <= max(FEW_DEMOS, len(s.demos)):
            plural = "s" if more > 1 else ""
            return f"; record about {more} more demonstration{plural}, the first from {start}"
        bindings = [r.binding for r in self.final_radii if r.radius > 0]
        binding = max(set(bindings), key=bindings.count)
        fix = fix_for(s, binding) + (
            "" if s.feedback.tune else ", or let the search tune the feedback (feedback: auto)"
        )
        return (
            f"; the feedback, not the demos, is the limit: tubes of radius {radius:.3g} would "
            f"need about {more} more demonstrations; their radius is limited by {binding}: {fix}"
        )

    def headline(self) -> dict[str, Any]:
        """The headline's coverage and Monte Carlo fields (``Headline``'s keywords)."""
        mc = self.montecarlo
        return {
            "coverage_before": self.demo_coverage.covered_fraction,
            "coverage_after": self.coverage.covered_fraction,
            "covered_before": bool(self.demo_coverage.covered),
            "covered_after": bool(self.coverage.covered),
            "montecarlo_samples": mc.samples,
            "montecarlo_failures": failed_runs(mc),  # runs, not failure kinds
            "failure_bound_95": mc.failure_bound,
        }


def certificate_kinds(evidence: Evidence, certified: bool) -> tuple[ClaimKind, ClaimKind]:
    """The kinds of the certificate's two claims: the contraction (constant) or invariance
    (funnel) claim, certified where the check of controller.json found the inequality strict
    (and, for the funnels, passed), and the coverage claim, certified with the run."""
    check = evidence.certification
    holds = check.contraction_margin < check.contraction_bound  # certify's own criterion
    contraction = ClaimKind.CERTIFIED if holds else ClaimKind.NOT_ESTABLISHED
    if evidence.certificate == "funnel" and not check.success:
        contraction = ClaimKind.NOT_ESTABLISHED
    return contraction, ClaimKind.CERTIFIED if certified else ClaimKind.NOT_ESTABLISHED


def certificate_claims(
    evidence: Evidence, certified: bool, dropped: Sequence[str] = ()
) -> tuple[Claim, Claim]:
    """The certificate's two claims, their kinds (``certificate_kinds``) and numbers from the
    evidence (the check of controller.json as written, the shipped coverage); ``dropped``: why
    trajectories were dropped (the funnel stage's lines; none when re-derived)."""
    check, feedback = evidence.certification, evidence.feedback
    contraction, covered = certificate_kinds(evidence, certified)
    coverage = evidence.coverage.message
    if evidence.certificate == "funnel":
        reasons = "".join(f"; {line}" for line in dropped)
        declared = declared_bound_text(evidence.scenario)
        under = f" under the declared uncertainty ({declared})" if declared else ""
        joint = ", joined with the disturbance's push by the S-procedure (I5)" if declared else ""
        eigenvalue = "twice the S-procedure's eigenvalue" if declared else "largest eigenvalue"
        h = evidence.feedback_period
        held = f", evaluated every {h:g} s and held in between" if h > 0 else ""
        proof = "its error and the hold's are" if h > 0 else "its error is"
        return (
            Claim(
                claim=f"each of the {len(check.radii)} shipped funnels is invariant under the law "
                f"as shipped{held}: no flight that starts in E_i(0) leaves E_i(t) = {{||x - "
                f"x_ref_i(t)||_P_i(t) <= rho_i}} before T_i{under} (the law tracks x_ref "
                f"interpolated; {proof} in the proof)",
                kind=contraction,
                how="the funnel's LMIs (F3: V = e^T P_i(t) e decreases at the rate, in Q = P^-1 "
                f"form{joint}) at every vertex of a sound Jacobian hull of each interval's tube, "
                "at both ends of every interval, solved by Clarabel; re-verified on "
                "controller.json as written with the interpolated reference's bounded term "
                f"({eigenvalue} plus term {check.contraction_margin:.2e} < "
                f"{check.contraction_bound:.0e}){reasons}",
            ),
            Claim(
                claim="every start in Init lies in a funnel that avoids Unsafe, keeps the "
                "inputs and state bounds, and ends in Goal",
                kind=covered,
                how="funnel levels bounded on a dense grid with a bound between grid points; "
                f"Init covered by the funnels' initial ellipsoids by box subdivision "
                f"({coverage}); both re-verified on controller.json as written",
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
            + (", keeps the state bounds," if evidence.scenario.state_bounds else "")
            + " and ends in Goal",
            kind=covered,
            how="robustness radii on a dense grid with a bound between grid points; "
            f"Init covered by box subdivision ({coverage}); both re-verified "
            "on controller.json as written",
        ),
    )


def declared_bound_text(scenario: Scenario) -> str:
    """The declared uncertainty as the additive bound certify holds the file to
    (``pipeline.numerics.uncertainty.additive_bound``), e.g. ``|w_vx| <= 0.02, |w_vy| <= 0.02``
    (state derivative units), then the measurement box, e.g. ``|eta_X| <= 0.02`` (state units);
    "" when the scenario declares none."""
    if scenario.uncertainty.empty:
        return ""
    parts = [box_text(scenario, additive_bound(scenario))]
    parts += [  # the error on the state the law sees (funnel.law (I7), terminal.check (T5))
        f"|eta_{name}| <= {e:.3g}"
        for name, e in zip(scenario.state_names, scenario.uncertainty.measurement, strict=True)
        if e > 0
    ]
    return ", ".join(part for part in parts if part)


def box_text(scenario: Scenario, box: Sequence[float] | np.ndarray) -> str:
    """``|w_vx| <= 0.02, |w_vy| <= 0.02`` for the nonzero entries of ``box (n,)``."""
    return ", ".join(
        f"|w_{name}| <= {b:.3g}" for name, b in zip(scenario.state_names, box, strict=True) if b > 0
    )


def after_horizon(evidence: Evidence, certified: bool) -> Claim:
    """After ``T``: safe for all time when the file's terminal controller is certified; else
    not established (the law refuses ``t > T``), with the reason."""
    check = evidence.certification
    if check.terminal and certified:
        bound = declared_bound_text(evidence.scenario)
        under = f" under the declared uncertainty ({bound})" if bound else ""
        robust = ", robustly for every x' = f(x, u) + w with w in that bound" if bound else ""
        if check.terminal_box:  # (T7)
            local = box_text(evidence.scenario, check.terminal_box)
            under = " under the declared uncertainty"
            robust = (
                ", robustly for every declared parameter value, its interval in the hull, and "
                f"every additive w with {local} (the gust and the parameters' shift at the "
                "equilibrium, (T7))"
            )
        h = evidence.feedback_period
        held = f", evaluated every {h:g} s and held in between" if h > 0 else ""
        return Claim(
            claim=f"after T every covered start stays in Goal for all time{under} (terminal "
            f"controller{held})",
            kind=ClaimKind.CERTIFIED,
            how=f"invariant ellipsoid of the terminal law re-verified on controller.json "
            f"(decay {check.terminal_decay:.3g}/s at every hull vertex over its bounding box, "
            f"inside Goal, no clipping"
            + robust
            + f") holding every end tube (at most {check.terminal_fit:.0%} "
            "of its radius, exact S-procedure test)",
        )
    return Claim(
        claim="after T: nothing (the law refuses t > T)",
        kind=ClaimKind.NOT_ESTABLISHED,
        how=evidence.controller.terminal_message or "no terminal controller",
    )


def failed_runs(mc: MonteCarloResult) -> int:
    """The runs that failed in any way (each once; ``mc.failures`` counts failure kinds)."""
    return len(mc.failed_x0)


def montecarlo_claims(mc: MonteCarloResult) -> tuple[Claim, Claim]:
    """The statistical claim of the closed-loop runs and the falsification search's."""
    falsification = mc.falsification
    return (
        Claim(
            claim=f"failure probability <= {mc.failure_bound:.2e}",
            kind=ClaimKind.STATISTICALLY_VALIDATED,
            how=f"{mc.samples} i.i.d. closed-loop runs from controller.json, "
            "one-sided 95% Clopper-Pearson bound",
        ),
        Claim(
            claim="worst safety margin found "
            + margin(falsification.worst_margin, falsification.binding),
            kind=ClaimKind.FALSIFICATION_SEARCHED,
            how=f"Init corners, Sobol points and Nelder-Mead ({falsification.evaluations} "
            "closed-loop runs); evidence, not a bound",
        ),
    )


def feedback_summary(evidence: Evidence) -> FeedbackSummary:
    feedback, covering = evidence.feedback, evidence.covering
    r_d = feedback.required_radius(evidence.scenario.clearance)
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


def montecarlo_summary(mc: MonteCarloResult) -> MonteCarloSummary:
    falsification = mc.falsification
    return MonteCarloSummary(
        samples=mc.samples,
        seed=mc.seed,
        failures=dict(mc.failures),
        failure_bound_95=mc.failure_bound,
        min_clearance=mc.min_clearance,
        min_goal_margin=mc.min_goal_margin,
        max_tube_tightness=mc.max_tube_tightness,
        tube_ratio_at_T=quantiles(mc.tube_final),
        falsification=FalsificationSummary(
            worst_x0=tuple(falsification.worst_x0.tolist()),
            worst_margin=falsification.worst_margin,
            binding=falsification.binding,
            evaluations=falsification.evaluations,
        ),
        message=mc.message,
    )


def controller_summary(evidence: Evidence) -> ControllerSummary:
    controller = evidence.controller
    return ControllerSummary(
        path=str(controller.path),
        trajectories=controller.trajectories,
        interpolation_error_P=controller.interpolation_error,
    )


def certification_summary(check: CertificationResult) -> CertificationSummary:
    return CertificationSummary(
        certified=check.success,
        sha256=check.sha256,
        metric_eigenvalue=check.metric_eigenvalue,
        contraction_margin=check.contraction_margin,
        vertices=check.vertices,
        covered_fraction=check.covered_fraction,
        message=check.message,
    )


def quantiles(values: FloatArray) -> Quantiles | None:
    """Median, 95th percentile and maximum of ``values (k,)``; None when empty."""
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return None
    median, p95, top = np.quantile(values, [0.5, 0.95, 1.0])
    return Quantiles(median=float(median), p95=float(p95), max=float(top))
