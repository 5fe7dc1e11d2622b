"""What the command line shows: the ``pipeline`` logger's lines on stdout (one per stage) and,
at the end, the run's table, headline, claims, verdict and where the files went.

Each term that is not self-explanatory is explained where it is printed: "radius limited by"
(the constraint the tube touches first), "tube ratio" (the closed-loop error at the final time
against the certified bound), "input slack" (the distance of the feedback's input to its bounds).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING

from pipeline.reporting.summary import Summary
from pipeline.runtime.synthesis import Synthesis

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from stages.coverage import CoverageResult
    from stages.optimize import OptimizeResult
    from stages.radius import RadiusResult

LOGGER = "pipeline"


@contextmanager
def show_progress(*, verbose: bool = False, quiet: bool = False) -> Iterator[None]:
    """While open, print the ``pipeline`` logger's messages: each stage's line (INFO) on stdout,
    with ``verbose`` the optimizer's iteration logs (DEBUG), with ``quiet`` warnings only (on
    stderr). The logger is left as it was found."""
    logger = logging.getLogger(LOGGER)
    handler = _StdoutHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    level = logger.level
    logger.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


class _StdoutHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Warnings on stderr, everything else on stdout (``sys.stdout`` looked up per message, so
    that pytest's capture and redirections see it)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
        super().emit(record)


def format_result(result: Synthesis, *, quiet: bool = False) -> str:
    """The end of the run: the summary (or only the verdict with ``quiet``) and the files."""
    if result.summary is None:  # failed before a summary: the stage and the error
        return result.message
    if quiet:
        return f"verdict ({result.summary.certificate} certificate): {result.message}"
    return f"{format_summary(result.summary)}\n\n{format_outputs(result)}"


def format_outputs(result: Synthesis) -> str:
    """Where the files went, one line each."""
    files = result.outputs
    lines = [f"outputs in {files.folder}:"]
    if files.report_html is not None:
        lines.append(f"  {files.report_html.name:<16} the report (open in a browser)")
    if files.report_pdf is not None:
        lines.append(f"  {files.report_pdf.name:<16} the same report as PDF")
    if files.controller is not None:
        lines.append(
            f"  {files.controller.name:<16} the certified controller (pipeline.controller)"
        )
    else:
        lines.append(f"  {'controller.json':<16} not written: the run did not certify it")
    lines.append(f"  {files.summary.name:<16} the numbers above, verdict and claims (JSON)")
    lines.append(
        f"  {files.artifacts.name + '/':<16} each stage's cached result (reused by re-runs)"
    )
    return "\n".join(lines)


def format_summary(summary: Summary) -> str:
    """The end-of-run table, headline, claims and verdict."""
    lines = [
        f"\n{'demo':<9} {'T demo':>7} {'T opt':>6} {'faster':>7} {'clear before':>13}"
        f" {'clear after':>12} {'r before':>9} {'r after':>8} {'iters':>6} {'time':>6}"
    ]
    for d in summary.demos:
        mark = "" if d.optimized else "  (kept as flown)"
        lines.append(
            f"{d.demo:<9} {d.T_demo:>6.1f}s {d.T_optimized:>5.1f}s "
            f"{d.faster_percent:>6.0f}% {d.clearance_before:>13.3f} "
            f"{d.clearance_after:>12.3f} {d.radius_before:>9.3f} "
            f"{d.radius_after:>8.3f} {d.iterations:>6d} {d.seconds:>5.1f}s{mark}"
        )
    lines.append(
        "(clear: smallest distance of the nominal path to Unsafe, m; r: robustness radius, the"
        " largest tube (P-norm) that stays safe)"
    )
    lines.append(
        "\nradius limited by (the constraint the tube touches first; demonstration -> optimized):"
    )
    for d in summary.demos:
        before = f"{d.binding_before} at {d.binding_time_before:.1f} s"
        after = f"{d.binding_after} at {d.binding_time_after:.1f} s"
        lines.append(f"  {d.demo:<9} {before:<30} -> {after}")
    if summary.certificate == "funnel":
        lines += _funnel_lines(summary)
    h, mc, fb = summary.headline, summary.montecarlo, summary.feedback
    lines.append(
        f"\nmean duration {h.T_demo_mean:.1f} s -> {h.T_optimized_mean:.1f} s "
        f"({h.faster_percent_mean:.0f}% faster); min nominal clearance "
        f"{h.min_clearance_before:.2f} -> {h.min_clearance_after:.2f} m "
        f"(required {h.required_clearance:g}); closed loop {mc.min_clearance:.2f} m"
    )
    lines.append(f"Init coverage: {h.coverage_before:.1%} -> {h.coverage_after:.1%}")
    if fb.kept_radius > fb.required_radius:
        lines.append(
            f"  tubes kept at the covering radius {fb.kept_radius:.4g} > r_d = "
            f"{fb.required_radius:.4g} (balls of radius r_d about the demo starts miss parts"
            " of Init)"
        )
    lines.append(
        f"Monte Carlo: {mc.samples} runs, {h.montecarlo_failures} failures, "
        f"failure probability <= {mc.failure_bound_95:.2e} (95%)"
    )
    if mc.tube_ratio_at_T is not None:
        q = mc.tube_ratio_at_T
        lines.append(
            f"  tube ratio at the final time (closed-loop error / its certified bound; <= 1 "
            f"inside the tube): median {q.median:.3f}, max {q.max:.3f}"
        )
    for claim in summary.claims:
        lines.append(f"  [{claim.kind.value}] {claim.claim}")
    if "input slack" in mc.falsification.binding:
        lines.append(
            "    (input slack: how far the feedback's input stays from its bounds; below 0 it"
            " would be clipped)"
        )
    if summary.stress is not None:
        lines.append(f"  [stress test, not certified] {summary.stress.message}")
    lines.append(f"\nverdict ({summary.certificate} certificate): {summary.text}")
    return "\n".join(lines)


def _funnel_lines(summary: Summary) -> list[str]:
    """Each optimized trajectory's funnel: its level, what bounds it, its synthesis time."""
    lines = [
        "\nfunnels (level rho: E_i(0) holds rho times the constant ball's slice of Init, 1 at"
        " most; bound by: the constraint that sets it, 'design' when the funnel's own LMI caps"
        " do, which at level 1 means the slice is held whole; synthesis time):"
    ]
    for d in summary.demos:
        if d.funnel_level is None:
            continue
        level = "dropped" if d.funnel_binding == "dropped" else f"{d.funnel_level:.3f}"
        binding = "" if d.funnel_binding == "dropped" else d.funnel_binding or ""
        seconds = "" if d.funnel_seconds is None else f"{d.funnel_seconds:.1f} s"
        lines.append(f"  {d.demo:<9} {level:>7}  {binding:<30} {seconds:>7}")
    return lines


def describe_radii(radii: Sequence[RadiusResult]) -> str:
    """A radius stage's line: the smallest and largest radius."""
    values = [r.radius for r in radii]
    return f"robustness radii {min(values):.3g} to {max(values):.3g} (P-norm)"


def describe_coverage(coverage: CoverageResult) -> str:
    """A coverage stage's line: the fraction of Init covered."""
    return f"Init {coverage.covered_fraction:.1%} covered" + ("" if coverage.covered else " (gap)")


def optimization_logs(optimized: OptimizeResult) -> str:
    """Each demo's horizons tried and descent log (``-v``)."""
    lines = []
    for trajectory in optimized.trajectories:
        lines.append(f"\n{trajectory.demo}: horizons tried (N', feasible, iterations, final J)")
        lines += [
            f"  N'={attempt.N:4d}  {'feasible  ' if attempt.feasible else 'infeasible'}"
            f"  {attempt.iterations:4d}  {attempt.cost:.3e}"
            for attempt in trajectory.tries
        ]
        lines.append(f"{trajectory.demo}: descent log at N' = {trajectory.N}")
        lines.append(trajectory.log.table())
    return "\n".join(lines)
