"""What the command line shows: the ``pipeline`` logger's lines on stdout (one per stage) and,
at the end, the run's table, headline, claims, verdict and where the files went.

Each term that is not self-explanatory is explained where it is printed: "radius limited by"
(the constraint the tube touches first, each kind named with its bound), "tube ratio" (the
closed-loop error at the final time against the certified bound), "input slack" (the distance of
the feedback's input to its bounds). Numbers carry the scenario's units (``Scenario.units``):
clearances in the position unit, inputs in their own; radii are in the P-norm
``||e||_P = sqrt(e^T P e)``, which mixes the states' units and so has none.
"""

from __future__ import annotations

import logging
import math
import re
import sys
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from pipeline.io.errors import UserError
from pipeline.reporting.numbers import fixed, formatted, montecarlo_counts, scientific
from pipeline.reporting.summary import Summary
from pipeline.runtime.outdir import stale_name
from pipeline.runtime.synthesis import Synthesis

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from pipeline.controller import Controller
    from pipeline.model.scenario import Scenario
    from pipeline.results.coverage import CoverageResult, CoveringRadius
    from pipeline.results.optimize import OptimizeResult
    from pipeline.results.radius import RadiusResult

LOGGER = "pipeline"
STALE_CONTROLLER = stale_name(Path("controller.json")).name
SCENE_PICTURE = "scenario.png"
# The radius stage's constraint names (pipeline.numerics.tube.radius, funnel.bounds), explained.
BINDING = re.compile(
    r"(?P<kind>unsafe|goal bound|region|input|state) '(?P<name>[^']+)'(?: (?P<side>lower|upper))?$"
)
MEANING = {
    "unsafe": "the tube touches this Unsafe set",
    "goal": "at the final time the tube reaches the edge of Goal",
    "goal bound": "at the final time the tube reaches this bound of Goal (goal.bounds)",
    "region": "the operating region's edge (where the contraction certificate holds)",
    "input": "the input bound: the feedback's input would be clipped beyond it",
    "state": "the physical envelope (state_bounds)",
}


@contextmanager
def show_progress(*, verbose: bool = False, quiet: bool = False) -> Iterator[None]:
    """While open, print the ``pipeline`` logger's messages: each stage's line (INFO) on stdout,
    with ``verbose`` the optimizer's iteration logs (DEBUG) and a crashed stage's traceback, with
    ``quiet`` warnings only (on stderr). Without ``verbose`` a message that carries a traceback
    is not printed: the result's one line says what failed and where the traceback is saved.
    The logger is left as it was found."""
    logger = logging.getLogger(LOGGER)
    handler = _StdoutHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    if not verbose:
        handler.addFilter(lambda record: record.exc_info is None)
    level = logger.level
    logger.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    logger.addHandler(handler)
    try:
        with warnings.catch_warnings():  # a library's warnings (SciPy's): --verbose shows them
            warnings.showwarning = _log_warning
            yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:  # type: ignore[no-untyped-def]
    """A Python warning as a DEBUG line of the ``pipeline`` logger, not on stderr: the stages'
    results say what went wrong in the scenario's terms."""
    logging.getLogger(f"{LOGGER}.warnings").debug(
        f"{category.__name__}: {message} ({filename}:{lineno})"
    )


class _StdoutHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Warnings on stderr, everything else on stdout (``sys.stdout`` looked up per message, so
    that pytest's capture and redirections see it). A progress bar on the terminal
    (``pipeline.io.progress``) is cleared for the line and redrawn under it: a stage's line,
    logged while its bar is open, starts its own line instead of following the bar's text."""

    def emit(self, record: logging.LogRecord) -> None:
        self.stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
        with tqdm.external_write_mode(file=self.stream):
            super().emit(record)


def format_result(
    result: Synthesis,
    *,
    scenario: Scenario | None = None,
    quiet: bool = False,
    verbose: bool = False,
) -> str:
    """The end of the run: the summary (or only the verdict with ``quiet``; its tables with
    ``verbose``) and the files. ``scenario`` (the one run) gives the units; without it numbers
    are printed bare."""
    if result.summary is None:  # failed before a summary: the stage and the error
        return result.message
    if quiet:
        return f"verdict ({result.summary.certificate} certificate): {result.message}"
    summary = format_summary(result.summary, scenario, verbose=verbose)
    return f"{summary}\n\n{format_outputs(result)}"


def format_done(result: Synthesis, seconds: float) -> str:
    """The last line of a run: its wall time ``seconds`` and verdict, e.g. ``done in 49 s:
    certified and validated`` (the reasons are printed above it)."""
    shown = f"{seconds:.1f}" if seconds < 10 else f"{seconds:.0f}"
    return f"done in {shown} s: {result.verdict.value}"


def units_of(scenario: str | Path) -> Scenario | None:
    """The scenario whose units and labels the summary is printed in (``None``, numbers bare,
    when it no longer loads: the run already said what it found)."""
    from pipeline.model.scenario import load_scenario

    try:
        return load_scenario(scenario, check_demos=False)
    except UserError:
        return None


def format_outputs(result: Synthesis) -> str:
    """Where the files went: the folder, then one line per main file."""
    files = result.outputs
    lines = [f"outputs in {files.folder}:"]
    if files.report_html is not None:
        lines.append(f"  {files.report_html.name:<22} the report (open in a browser)")
    if files.report_pdf is not None:
        lines.append(f"  {files.report_pdf.name:<22} the same report as PDF")
    if files.controller is not None:
        lines.append(
            f"  {files.controller.name:<22} the certified controller (pipeline.controller)"
            + ("" if result.controller is None else f", {_trajectories(result.controller)}")
        )
    elif (files.folder / STALE_CONTROLLER).is_file():
        lines.append(f"  {STALE_CONTROLLER:<22} NOT certified: kept for inspection only")
    else:
        lines.append(f"  {'controller.json':<22} not written: the run did not certify it")
    lines.append(f"  {files.summary.name:<22} the numbers above, verdict and claims (JSON)")
    if (files.folder / SCENE_PICTURE).is_file():
        lines.append(f"  {SCENE_PICTURE:<22} the scenario's sets and flights (picture)")
    lines.append(
        f"  {files.artifacts.name + '/':<22} each stage's cached result (reused by re-runs)"
    )
    return "\n".join(lines)


def _trajectories(controller: Controller) -> str:
    """``trajectories 0: demo_01, 1: demo_02, ...``: the indices of ``controller.trajectories``
    (what ``select`` returns) beside their demonstrations, as the report and ``repr`` say."""
    return f"trajectories {', '.join(controller.labels())}"


def format_summary(
    summary: Summary, scenario: Scenario | None = None, *, verbose: bool = False
) -> str:
    """The end of a run in ``scenario``'s units: what ships, Init's coverage, Monte Carlo, the
    claims and the verdict; with ``verbose`` first the tables (a funnel run: each shipped
    funnel, then the constant certificate that seeds them; a constant run: each demo and what
    limits its radius)."""
    length = length_unit(scenario)
    lines: list[str] = []
    if verbose and summary.certificate == "funnel" and summary.funnels:
        lines += _funnel_table(summary, length)
        lines.append(
            "\nseed and comparison: the constant certificate (one K, P; verified by the stages, "
            "not shipped)"
        )
    if verbose:
        lines += _demo_lines(summary, scenario, length)
    h, mc, fb = summary.headline, summary.montecarlo, summary.feedback
    if summary.certificate == "funnel" and summary.funnels:
        lines += _shipped_lines(summary, length)
    else:
        lines.append(
            f"\nmean duration {h.T_demo_mean:.1f} s -> {h.T_optimized_mean:.1f} s "
            f"({h.faster_percent_mean:.0f}% faster); min nominal clearance "
            f"{_quantity(h.min_clearance_before, length, '.2f')} -> "
            f"{_quantity(h.min_clearance_after, length, '.2f')} "
            f"(required d = {_quantity(h.required_clearance, length, 'g')}); closed loop "
            f"{_quantity(mc.min_clearance, length, '.2f')}"
        )
        lines.append(f"Init coverage: {h.coverage_before:.1%} -> {h.coverage_after:.1%}")
        if fb.kept_radius > fb.required_radius:
            lines.append(
                f"  tubes kept at the covering radius {fb.kept_radius:.4g} > r_d = "
                f"{fb.required_radius:.4g} (P-norm; balls of radius r_d about the demo starts "
                "miss parts of Init)"
            )
    counts = montecarlo_counts(mc.samples, h.montecarlo_failures, mc.failures)
    lines.append(
        f"Monte Carlo: {counts}; failure probability <= {scientific(mc.failure_bound_95)} (95%)"
    )
    if mc.tube_ratio_at_T is not None:
        q = mc.tube_ratio_at_T
        lines.append(
            f"  tube ratio at the final time (closed-loop error / its certified bound; <= 1 "
            f"inside the tube): median {fixed(q.median, 3)}, max {fixed(q.max, 3)}"
        )
    for claim in summary.claims:
        lines.append(f"  [{claim.kind.value}] {claim.claim}")
    if "input slack" in mc.falsification.binding:
        lines.append(
            "    (input slack: how far the feedback's input stays from its bounds, in that"
            f" input's unit{_input_units(scenario)}; below 0 it would be clipped)"
        )
    if summary.stress is not None:
        lines.append(f"  [stress test, not certified] {summary.stress.message}")
    lines.append(f"\nverdict ({summary.certificate} certificate): {summary.text}")
    if not verbose:
        lines.append(
            "(the tables per "
            + (
                "funnel and of the constant certificate that seeds them"
                if summary.funnels
                else "demonstration"
            )
            + ": -v, or report.html)"
        )
    return "\n".join(lines)


def _demo_lines(summary: Summary, scenario: Scenario | None, length: str) -> list[str]:
    """The per-demo table and what limits each radius (the constant certificate's)."""
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
        f"(clear: the nominal path's smallest distance to Unsafe, {length or 'position units'};"
        " r: robustness radius, the largest tube that stays safe, in the P-norm (no unit);"
        " time: optimization wall time)"
    )
    if summary.certificate == "funnel":
        constant = [d.T_constant for d in summary.demos if d.T_constant is not None]
        if constant:
            lines.append(
                f"(funnel run: T opt and clear after are the shipped nominals'; r and the limits"
                f" below are the constant certificate's, on its own optimized nominals, T "
                f"{min(constant):.1f}-{max(constant):.1f} s)"
            )
    lines.append(
        "\nradius limited by (the constraint the tube touches first; demonstration -> optimized):"
    )
    for d in summary.demos:
        before = f"{d.binding_before} at {d.binding_time_before:.1f} s"
        after = f"{d.binding_after} at {d.binding_time_after:.1f} s"
        lines.append(f"  {d.demo:<9} {before:<30} -> {after}")
    bindings = dict.fromkeys(b for d in summary.demos for b in (d.binding_before, d.binding_after))
    region = summary.feedback.region
    lines += [f"  ({explain_binding(b, scenario, region)})" for b in bindings if b]
    return lines


def _span(values: Sequence[float], spec: str) -> str:
    """``low-high`` by ``spec`` (one number when they agree); ``n/a (none)`` for no value."""
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return "n/a (none)"
    low, high = format(min(finite), spec), format(max(finite), spec)
    return low if low == high else f"{low}-{high}"


def _shipped_lines(summary: Summary, length: str) -> list[str]:
    """What controller.json guarantees (a funnel run): a few lines over all its funnels."""
    h, mc = summary.headline, summary.montecarlo
    shipped = [f for f in summary.funnels if f.shipped]
    bindings = sorted({f.binding for f in shipped})
    held = all(f.binding == "design" and f.level >= 0.999 for f in shipped) and shipped
    set_by = (
        "the funnel's design (each start's cell of Init held whole)"
        if held
        else ", ".join(bindings) or "none"
    )
    unit = f" {length}" if length else ""
    speed = f" {length}/s" if length else " (position units)/s"
    return [
        f"\nshipped: controller.json, {len(shipped)} of {len(summary.funnels)} funnels "
        f"E_i(t), T {_span([f.T for f in summary.funnels], '.1f')} s (demonstrations "
        f"{h.T_demo_mean:.1f} s on average: {h.faster_percent_mean:.0f}% faster)",
        f"  levels rho {_span([f.level for f in shipped], '.3f')}, set by {set_by}",
        f"  clearance of the funnels to Unsafe >= "
        f"{_span([min((f.clearance for f in shipped), default=math.nan)], '.2f')}{unit}"
        f" (closed loop, Monte Carlo: {_quantity(mc.min_clearance, length, '.2f')}); at T "
        f"each funnel lies in Goal, within "
        f"{_span([max((f.extent_at_T for f in shipped), default=math.nan)], '.2f')}{unit} of "
        f"its nominal, arriving at {_span([f.arrival_speed for f in shipped], '.1f')}{speed}",
        f"Init coverage: {h.coverage_after:.1%} (by the funnels' initial sets E_i(0))",
    ]


def _funnel_table(summary: Summary, length: str) -> list[str]:
    """Each shipped funnel (``-v``): T, level, what sets it, extent at T, clearance, arrival."""
    unit = length or "pos. units"
    lines = [
        f"\n{'funnel':<9} {'T':>5} {'level':>6}  {'set by (next: its level)':<40} "
        f"{'extent@T':>8} {'clearance':>9} {'arrival':>8}"
    ]
    for f in summary.funnels:
        if not f.shipped:
            lines.append(f"{f.demo:<9} {f.T:>4.1f}s {'dropped':>6}")
            continue
        nearest = f" (next: {f.nearest} {f.nearest_level:.2f})" if f.nearest else ""
        lines.append(
            f"{f.demo:<9} {f.T:>4.1f}s {f.level:>6.3f}  {(f.binding + nearest)[:40]:<40} "
            f"{f.extent_at_T:>8.3f} {f.clearance:>9.3f} {f.arrival_speed:>8.2f}"
        )
    lines.append(
        f"(level rho: E_i(0) holds rho times its start's cell of Init, 1 at most; set by: the "
        f"constraint that sets it, 'design' when the funnel's own LMI caps do; extent@T: the "
        f"funnel's largest position offset at T, {unit}; clearance: the funnel's smallest "
        f"distance to Unsafe over [0, T], {unit}; arrival: the nominal's speed at T, {unit}/s)"
    )
    return lines


def explain_binding(
    binding: str,
    scenario: Scenario | None = None,
    region: Mapping[str, tuple[float, float]] | None = None,
) -> str:
    """What a "radius limited by" constraint is, in a few words, with its bound and unit when
    known (from ``region``, the feedback's operating region, else ``scenario``):
    ``"region 'force' upper: force (thrust) <= 14.9 N, the operating region's edge ..."``."""
    if binding == "goal":
        return f"goal: {MEANING['goal']}"
    found = BINDING.match(binding)
    if found is None:
        return f"{binding}: a constraint of the radius (see the report)"
    kind, name, side = found.group("kind", "name", "side")
    bound = _bound(kind, name, side, scenario, region or {})
    if bound is None:
        return f"{binding}: {MEANING[kind]}"
    label = name if scenario is None else scenario.label(name, unit=False)
    unit = "" if scenario is None else scenario.unit(name)
    relation = ">=" if side == "lower" else "<="
    return f"{binding}: {label} {relation} {_quantity(bound, unit, 'g')}, {MEANING[kind]}"


def _bound(
    kind: str,
    name: str,
    side: str | None,
    scenario: Scenario | None,
    region: Mapping[str, tuple[float, float]],
) -> float | None:
    """The value of the bound ``kind 'name' side`` (None when not known)."""
    if side is None:
        return None
    index = 0 if side == "lower" else 1
    if kind == "region" and name in region:
        return float(region[name][index])
    if scenario is None:
        return None
    if kind == "region" and name in scenario.operating_region:
        return float(scenario.operating_region[name][index])
    if kind == "input" and name in scenario.input_names:
        j = scenario.input_names.index(name)
        return float((scenario.input_lower, scenario.input_upper)[index][j])
    if kind == "state" and name in scenario.state_bounds:
        return float(scenario.state_bounds[name][index])
    if kind == "goal bound" and name in scenario.goal_bounds:
        return float(scenario.goal_bounds[name][index])
    return None


def length_unit(scenario: Scenario | None) -> str:
    """The position states' common unit (``""`` without a scenario, undeclared or mixed)."""
    return "" if scenario is None else scenario.position_unit()


def _input_units(scenario: Scenario | None) -> str:
    """`` (force: N, torque: N m)`` for the inputs with a declared unit ("" for none)."""
    if scenario is None:
        return ""
    known = [
        f"{name}: {scenario.unit(name)}" for name in scenario.input_names if scenario.unit(name)
    ]
    return f" ({', '.join(known)})" if known else ""


def _quantity(value: float, unit: str, spec: str) -> str:
    """``value`` formatted by ``spec``, followed by its unit when there is one (``n/a (...)``,
    without the unit, when it is not finite)."""
    shown = formatted(value, spec)
    return f"{shown} {unit}" if unit and math.isfinite(value) else shown


def describe_radii(radii: Sequence[RadiusResult]) -> str:
    """A radius stage's line: the smallest and largest radius."""
    values = [r.radius for r in radii]
    return f"robustness radii {min(values):.3g} to {max(values):.3g} (P-norm)"


def describe_covering(covering: CoveringRadius) -> str:
    """The covering radius stage's line: its message, saying the radius is in the P-norm."""
    return f"{covering.message} (radius in the P-norm)"


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
