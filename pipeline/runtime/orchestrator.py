"""The orchestrator: wires the stages in order and keeps their artifacts under the output folder
(``./reports/NAME`` under the current directory unless given ``out``).

    load -> feedback -> radius(demos) -> coverage(demos) -> covering radius -> optimize
         -> radius(optimized) -> coverage(optimized) [-> funnel -> coverage(funnel)]
         -> controller -> certify -> montecarlo -> report

The certificate (``--certificate``, default the scenario's ``certificate``) decides what is
shipped: ``constant`` writes ``safety-controller/1`` from the feedback's one ``P``, ``K`` and
the robustness radii; ``funnel`` synthesizes a time-varying funnel around each optimized
trajectory (stage ``funnel``, asked to hold the part of Init the constant ball holds), covers
Init by their initial ellipsoids ``E_i(0)`` and writes ``safety-controller/2``. The controller
stage writes ``controller.json`` on every run, from this run's certified results; the certify
stage then re-verifies that file as written (never cached), and the verdict's "certified" is
its result.

The optimizer keeps every tube at the required radius ``max(r_d, covering radius)``: ``r_d`` is
the radius that the clearance ``d`` certifies, and the covering radius the smallest common one
whose balls around the demo starts cover Init, so that coverage survives the optimization.

It holds no numerics: each stage is a function from typed inputs to a frozen result, stored by
``pipeline.runtime.runner.StageRunner`` with a hash of its inputs so that unchanged stages are
reused. It prints nothing: progress goes to the ``pipeline`` logger (one line per stage), the
outcome is the returned ``Synthesis``; the command line prints both.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.controller import load as load_controller
from pipeline.io.artifacts import atomic_write_json, file_hash, inputs_key, remove_temporaries
from pipeline.io.errors import ScenarioError, UserError
from pipeline.io.executor import Executor, make_executor
from pipeline.io.folders import default_output_folder
from pipeline.io.lock import folder_lock
from pipeline.io.progress import progress_bar
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import Trajectory
from pipeline.reporting.pdf import find_browser
from pipeline.reporting.summary import Verdict
from pipeline.runtime import run_inputs
from pipeline.runtime.codekey import code_key
from pipeline.runtime.options import RunOptions
from pipeline.runtime.outdir import (
    check_output_folder,
    check_report_folder,
    clear_stale,
    mark_failed,
    stale_name,
)
from pipeline.runtime.runner import StageRunner
from pipeline.runtime.stored import load_report_data, write_manifest
from pipeline.runtime.summary import StageResults, demo_table, summarise
from pipeline.runtime.synthesis import Outputs, Synthesis
from pipeline.runtime.terminal import (
    describe_coverage,
    describe_covering,
    describe_radii,
    optimization_logs,
)
from stages.certify import certify_controller
from stages.controller import emit_controller, emit_funnel_controller
from stages.coverage import (
    CoverageResult,
    CoveringRadius,
    cover_balls,
    cover_init,
    covering_radius,
)
from stages.feedback import FeedbackResult, design_feedback
from stages.funnel import FunnelStageResult, synthesize_funnels
from stages.montecarlo import validate_closed_loop
from stages.optimize import (
    ConstraintMargins,
    OptimizeOptions,
    OptimizeResult,
    optimize,
    reoptimize_with_funnels,
)
from stages.radius import RadiusResult, robustness_radius
from stages.report import ReportResult, write_reports
from stages.stress import stress_test

log = logging.getLogger(__name__)
REPORT_FILES = ("report.html", "scenario.png")  # report.pdf too where a browser prints it
# the code each cached stage's key covers besides its own module (see pipeline.runtime.codekey)
RADIUS_CODE = ("stages.radius", "pipeline.model.simulate", "pipeline.numerics.verify")
REPORT_CODE = ("stages.report", "pipeline.runtime.summary", "pipeline.runtime.stored")
REPORT_STAGES = (  # the controller's result is the file itself, keyed by its hash
    "feedback",
    "radius_demos",
    "coverage_demos",
    "covering_radius",
    "optimize",
    "radius_optimized",
    "coverage_optimized",
    "montecarlo",
)
FUNNEL_STAGES = ("funnel", "coverage_funnel")  # with the funnel certificate
FUNNEL_ROUNDS = 6  # re-optimize rounds against the funnels at most (issue 16 part 4)
ROUND_FLOOR = 0.6  # a round shortens a nominal to no fewer than this fraction of its samples
SETTLED = 0.95  # a trajectory whose floor fraction reaches this is not optimized again
LEVEL_TOLERANCE = 1e-3  # a new funnel's level may fall this far below the kept one's


def _radii(
    scenario: Scenario, feedback: FeedbackResult, trajectories: Sequence[Trajectory]
) -> tuple[RadiusResult, ...]:
    tube = feedback.certified_tube
    return tuple(robustness_radius(scenario, tube, tr) for tr in trajectories)


def _cover_radii(radii: Sequence[RadiusResult]) -> np.ndarray:
    """(k,) the radii coverage reads: negative ones (no valid tube) count as 0."""
    return np.array([max(r.radius, 0.0) for r in radii])


def _coverage(
    scenario: Scenario,
    feedback: FeedbackResult,
    starts: Sequence[np.ndarray],
    radii: Sequence[RadiusResult],
) -> CoverageResult:
    return cover_init(scenario, feedback, np.array(starts), _cover_radii(radii))


def _funnels(
    scenario: Scenario,
    runner: StageRunner,
    executor: Executor,
    tube: str,
    feedback: FeedbackResult,
    starts: Sequence[np.ndarray],
    inputs: Sequence[np.ndarray],
    trajectories: Sequence[Trajectory],
    initial_radii: Sequence[float],
    quiet: bool,
    stage: str = "funnel",
) -> tuple[FunnelStageResult, CoverageResult]:
    """Stages ``stage`` (``funnel`` or ``funnel_k`` in re-optimize round k: one funnel per
    trajectory, on ``executor``) and ``coverage_<stage>`` (Init by the usable funnels' initial
    ellipsoids ``E_i(0)``, each in its own metric ``P_i[0]``)."""
    names = [d.name for d in scenario.demos]
    with progress_bar(len(trajectories), "funnels", quiet) as advance:
        funnels: FunnelStageResult = runner.run(
            stage,
            inputs_key(code_key("stages.funnel"), tube, names, *starts, *inputs, initial_radii),
            lambda: synthesize_funnels(
                scenario,
                names,
                trajectories,
                feedback.certified_tube.P,
                np.asarray(initial_radii),
                executor=executor,
                progress=advance,
            ),
            describe=lambda result: result.message,
        )
    coverage: CoverageResult = runner.run(
        f"coverage_{stage}",
        inputs_key(code_key("stages.coverage"), tube, runner.digest(stage), *starts),
        lambda: cover_balls(
            scenario, funnels.starts, np.array(starts), funnels.levels, noun="funnel start"
        ),
        describe=describe_coverage,
    )
    return funnels, coverage


def _reoptimize_rounds(
    scenario: Scenario,
    runner: StageRunner,
    executor: Executor,
    tube: str,
    feedback: FeedbackResult,
    optimized: OptimizeResult,
    starts: Sequence[np.ndarray],
    inputs: list[np.ndarray],
    trajectories: list[Trajectory],
    funnels: FunnelStageResult,
    coverage: CoverageResult,
    initial_radii: Sequence[float],
    options: OptimizeOptions,
    quiet: bool,
) -> tuple[list[np.ndarray], list[Trajectory], FunnelStageResult, CoverageResult]:
    """The alternation of issue 16 part 4, as a continuation that keeps Init covered.

    Round k optimizes each nominal again against its current funnel's time-varying extents
    (stage ``reoptimize_k``), but to no fewer than ``ceil(f_i N_i)`` samples, and synthesizes
    and checks new funnels around the new nominals (``funnel_k``, ``coverage_funnel_k``).
    Trajectory i's new nominal and funnel are kept only when that funnel is certified and its
    level holds at least what the kept one held (``_accepted``: both levels are fractions of
    the same required set (I1)); the mixed set is covered again (``coverage_funnel_k_kept``)
    and the round is kept only when it covers Init at least as well and shortens the total T.
    A trajectory that was not kept (or all of them, when the round is not) may move only half as
    far next round (``f_i <- (1 + f_i) / 2``); one whose floor passes ``SETTLED`` is not
    optimized again. Stop when every trajectory is settled, when no trajectory could be
    optimized again, or after ``FUNNEL_ROUNDS``. Returns the kept inputs, trajectories, funnels
    and coverage (a round is never kept unverified: its funnels passed ``check_funnel`` and the
    certify-style rebuild in their stage).

    Why (measured on quadrotor_hill_gusty, ``--samples 2000``): one unbounded round shortened
    T from 11.8 s to ~3 s, but the new funnels, bound by their own LMI caps ('design': the
    local hull at the new nominal's high thrust and pitch) or by Goal, held only 11-21% of
    their required sets and Init went uncovered, so the round was discarded. Shorter steps
    keep each new nominal within reach of the funnel that was certified around the previous.
    Measured with these settings (``--samples 2000 --jobs 2``): gusty, 40% steps kept 1 of 9
    new funnels (the others held 20-100% of their sets), 20% steps then 5-8 of 9 a round;
    after six rounds T 5.7-8.1 s (mean 6.9 s, from 11.8 s), Init covered, certified. On
    quadrotor_hill (``--certificate funnel``) T 2.8-3.0 s, certified.
    """
    fraction = [ROUND_FLOOR] * len(trajectories)
    previous = list(optimized.trajectories)
    for k in range(1, FUNNEL_ROUNDS + 1):
        active = [i for i in funnels.usable if fraction[i] < SETTLED]
        if not active:
            log.info(f"[round {k}] every trajectory settled: the previous funnels are kept")
            break
        previous = [
            dataclasses.replace(t, u=u, N=len(u)) for t, u in zip(previous, inputs, strict=True)
        ]
        shortest = [
            math.ceil(fraction[i] * len(u)) if i in active else len(u) for i, u in enumerate(inputs)
        ]
        with progress_bar(len(previous), f"round {k}: optimized again", quiet) as advance:
            again: OptimizeResult = runner.run(
                f"reoptimize_{k}",
                inputs_key(
                    code_key("stages.optimize"),
                    runner.digest(_round_stage(k - 1)),
                    *inputs,
                    shortest,
                    repr(options),
                ),  # fmt: skip
                functools.partial(
                    reoptimize_with_funnels,
                    scenario,
                    previous,
                    funnels.funnels,
                    options,
                    executor,
                    advance,
                    shortest=shortest,
                ),  # fmt: skip
                describe=lambda result: result.message,
            )
        moved = [i for i in active if again.trajectories[i].success]
        if not moved:
            log.info(f"[round {k}] no trajectory optimized again: the previous funnels are kept")
            break
        new_inputs = [again.trajectories[i].u if i in moved else u for i, u in enumerate(inputs)]
        new_trajectories = run_inputs.trajectories(scenario, starts, new_inputs)
        new_funnels, new_coverage = _funnels(
            scenario, runner, executor, tube, feedback, starts, new_inputs,
            new_trajectories, initial_radii, quiet, stage=_round_stage(k),
        )  # fmt: skip
        kept = [i for i in _accepted(funnels, new_funnels) if i in moved]
        if set(kept) != set(range(len(inputs))):
            new_inputs = [new_inputs[i] if i in kept else u for i, u in enumerate(inputs)]
            new_trajectories = [
                new_trajectories[i] if i in kept else t for i, t in enumerate(trajectories)
            ]
            new_funnels = _mixed(funnels, new_funnels, kept)
            new_coverage = runner.run(
                f"coverage_{_round_stage(k)}_kept",
                inputs_key(
                    code_key("stages.coverage"),
                    tube,
                    runner.digest(_round_stage(k - 1)),
                    runner.digest(_round_stage(k)),
                    kept,
                    *starts,
                ),  # fmt: skip
                functools.partial(
                    cover_balls,
                    scenario,
                    new_funnels.starts,
                    np.array(starts),
                    new_funnels.levels,
                    noun="funnel start",
                ),
                describe=describe_coverage,
            )
        before = sum(trajectories[i].duration for i in funnels.usable)
        after = sum(new_trajectories[i].duration for i in new_funnels.usable)
        shorter = after < before and len(new_funnels.usable) >= len(funnels.usable)
        if not (shorter and new_coverage.covered_fraction >= coverage.covered_fraction):
            log.info(
                f"[round {k}] not kept: total T {after:.2f} s against {before:.2f} s, Init "
                f"{100 * new_coverage.covered_fraction:.1f}% covered against "
                f"{100 * coverage.covered_fraction:.1f}%; the previous funnels are kept"
            )
            kept = []
        for i in active:
            fraction[i] = fraction[i] if i in kept else (1 + fraction[i]) / 2
        if not kept:
            continue
        log.info(
            f"[round {k}] kept: total T {before:.2f} s -> {after:.2f} s, new nominals kept for "
            f"{len(kept)} of {len(active)} trajectories optimized again"
        )
        inputs, trajectories, funnels, coverage = (
            new_inputs, new_trajectories, new_funnels, new_coverage
        )  # fmt: skip
        previous = [again.trajectories[i] if i in kept else t for i, t in enumerate(previous)]
    return inputs, trajectories, funnels, coverage


def _accepted(
    before: FunnelStageResult, after: FunnelStageResult, tolerance: float = LEVEL_TOLERANCE
) -> tuple[int, ...]:
    """Indices i whose new funnel is usable and whose level holds at least what the kept one
    held: ``rho_after_i >= rho_before_i - tolerance`` (both fractions of the same required set
    (I1), 0 for a dropped funnel)."""
    old, new = before.levels, after.levels
    return tuple(i for i in after.usable if new[i] >= old[i] - tolerance)


def _mixed(
    before: FunnelStageResult, after: FunnelStageResult, kept: Sequence[int]
) -> FunnelStageResult:
    """The funnels of ``after`` for the trajectories in ``kept``, those of ``before`` for the
    others (each certified around its own nominal, which the caller keeps with it)."""
    source = [after if i in kept else before for i in range(len(before.funnels))]
    usable = tuple(i for i, result in enumerate(source) if i in result.usable)
    rejected = tuple(
        line
        for i, result in enumerate(source)
        for line in result.rejected
        if line.startswith(f"{result.names[i]} dropped")
    )
    levels = [source[i].funnels[i].rho for i in usable]
    return dataclasses.replace(
        before,
        funnels=tuple(result.funnels[i] for i, result in enumerate(source)),
        usable=usable,
        rejected=rejected,
        success=len(usable) == len(source),
        message=f"new funnels kept for {len(kept)} of {len(source)} trajectories; "
        f"{len(usable)} certified"
        + (f", levels {min(levels):.3f} to {max(levels):.3f}" if levels else ""),
    )


def _round_stage(k: int) -> str:
    """The funnel stage of re-optimize round ``k`` (0: the first funnels)."""
    return "funnel" if k == 0 else f"funnel_{k}"


def run_synthesis(
    scenario_name: str | Path, out: Path | None = None, options: RunOptions | None = None
) -> Synthesis:
    """Run every stage on a scenario (the public form is ``pipeline.synthesize``).

    Bad input (the scenario, the output folder, a folder in use) raises ``UserError`` before any
    work. A run that fails writes ``summary.json`` saying so, renames the previous
    ``controller.json`` and reports to ``*.stale.*`` (``pipeline.runtime.outdir``) and returns a
    ``Synthesis`` with ``Verdict.FAILED``.
    """
    started = time.perf_counter()
    options = options or RunOptions()
    scenario = load_scenario(scenario_name)
    if not scenario.demos:
        raise ScenarioError(
            "no demonstrations to synthesize from",
            file=scenario.path,
            field="demos",
            found=[],
            expected=f"at least one demo (record one: python -m pipeline record {scenario.name})",
        )
    certificate = run_inputs.certificate_of(scenario, options)
    run_inputs.check_period(scenario, options.feedback_period, certificate)
    out = (Path(out) if out is not None else default_output_folder(scenario.name)).absolute()
    check_output_folder(out, scenario.name)
    log.info(f"outputs: {out}")
    with folder_lock(out):
        for folder in (out, out / "artifacts"):
            remove_temporaries(folder)  # left by killed writers; none can be active now
        runner = StageRunner(out, force=options.force)
        executor = make_executor(options.executor, options.jobs)
        try:
            return _synthesize(scenario, out, options, executor, runner, started)
        except (UserError, KeyboardInterrupt):
            raise
        except Exception as error:
            return _failed(out, scenario, runner.current, f"{type(error).__name__}: {error}")
        finally:
            executor.close()


def _failed(out: Path, scenario: Scenario, stage: str, reason: str) -> Synthesis:
    """Record a failed run (``summary.json``, stale outputs renamed); its ``Synthesis``."""
    stale = mark_failed(out, scenario.name, stage, reason)
    renamed = f"; previous outputs renamed: {', '.join(p.name for p in stale)}" if stale else ""
    return Synthesis(
        scenario=scenario.name,
        verdict=Verdict.FAILED,
        success=False,
        message=f"failed: stage {stage}: {reason} ({out / 'summary.json'}{renamed})",
        claims=(),
        controller=None,
        demos=(),
        summary=None,
        outputs=Outputs.of(out),
    )


def _synthesize(
    scenario: Scenario,
    out: Path,
    options: RunOptions,
    executor: Executor,
    runner: StageRunner,
    started: float,
) -> Synthesis:
    core = run_inputs.spec_key(scenario, "description", "stress")  # what the numerical stages read
    demo_starts = [d.x0 for d in scenario.demos]
    demo_inputs = [d.us for d in scenario.demos]
    demos = inputs_key([d.name for d in scenario.demos], *demo_starts, *demo_inputs)
    demo_trajectories = run_inputs.trajectories(scenario, demo_starts, demo_inputs)
    log.info(
        f"scenario {scenario.name}: {len(scenario.demos)} demos, all valid "
        f"(never in Unsafe, end in Goal)\n{demo_table(scenario, demo_trajectories)}\n"
    )
    quiet = not log.isEnabledFor(logging.INFO)  # progress bars only where lines are shown

    feedback = runner.run(
        "feedback",
        inputs_key(code_key("stages.feedback"), core),
        lambda: design_feedback(scenario),
        describe=lambda result: result.message,
    )
    if not feedback.success:
        reason = f"the feedback could not be certified: {feedback.message}"
        return _failed(out, scenario, "feedback", reason)
    if options.feedback_period > 0:
        feedback, held = run_inputs.held_feedback(scenario, feedback, options.feedback_period)
        if not held.success:
            reason = (
                f"zero-order-hold feedback every {held.period:g} s cannot be certified: the "
                f"held tube's rate {held.held_rate:.3g}/s is not > 0 (continuous rate "
                f"{held.rate:.3g}/s, C1 = {held.C1:.3g}); use a shorter --feedback-period"
            )
            return _failed(out, scenario, "feedback", reason)
        log.info(
            f"[held feedback] every {held.period:g} s: tube rate {held.held_rate:.4g}/s "
            f"(continuous {held.rate:.4g}/s; pipeline.numerics.sampled)"
        )
    tube = inputs_key(core, runner.digest("feedback"), options.feedback_period)
    demo_radii = runner.run(
        "radius_demos",
        inputs_key(code_key(*RADIUS_CODE), tube, demos),
        lambda: _radii(scenario, feedback, demo_trajectories),
        describe=describe_radii,
    )
    demo_coverage = runner.run(
        "coverage_demos",
        inputs_key(code_key("stages.coverage"), tube, *demo_starts, _cover_radii(demo_radii)),
        lambda: _coverage(scenario, feedback, demo_starts, demo_radii),
        describe=describe_coverage,
    )

    r_d = feedback.required_radius(scenario.clearance)
    upper = max(r_d, *(r.radius for r in demo_radii))
    covering: CoveringRadius = runner.run(
        "covering_radius",
        inputs_key(code_key("stages.coverage"), tube, *demo_starts, upper),
        lambda: covering_radius(scenario, feedback, np.array(demo_starts), upper=upper),
        describe=describe_covering,
    )
    r_required = covering.kept_radius(r_d)
    margins = ConstraintMargins.of_tube(feedback.certified_tube, r_required)
    optimize_options = OptimizeOptions(method=options.method, search=options.search)
    with progress_bar(len(scenario.demos), "demos optimized", quiet) as advance:
        optimized: OptimizeResult = runner.run(
            "optimize",
            inputs_key(
                code_key("stages.optimize"), tube, demos, r_required, repr(optimize_options)
            ),
            lambda: optimize(
                scenario, margins, optimize_options, executor=executor, progress=advance
            ),
            describe=lambda result: result.message,
        )
    if log.isEnabledFor(logging.DEBUG):
        log.debug(optimization_logs(optimized))
    # a demo whose optimisation failed keeps its own (valid) nominal trajectory
    final_inputs = [
        t.u if t.success else d.us
        for t, d in zip(optimized.trajectories, scenario.demos, strict=True)
    ]
    final_trajectories = run_inputs.trajectories(scenario, demo_starts, final_inputs)
    final_radii = runner.run(
        "radius_optimized",
        inputs_key(code_key(*RADIUS_CODE), tube, *demo_starts, *final_inputs),
        lambda: _radii(scenario, feedback, final_trajectories),
        describe=describe_radii,
    )
    final_coverage = runner.run(
        "coverage_optimized",
        inputs_key(code_key("stages.coverage"), tube, *demo_starts, _cover_radii(final_radii)),
        lambda: _coverage(scenario, feedback, demo_starts, final_radii),
        describe=describe_coverage,
    )

    controller_path = out / "controller.json"
    certificate = run_inputs.certificate_of(scenario, options)
    funnels: FunnelStageResult | None = None
    funnel_coverage: CoverageResult | None = None
    constant_trajectories: list[Trajectory] | None = None
    if certificate == "funnel":
        # The funnels are asked to hold the constant ball's slice of Init (stage funnel, (I1));
        # a trajectory without a robustness radius asks for the radius the optimizer kept.
        initial_radii = [r.radius if r.radius > 0 else r_required for r in final_radii]
        funnels, funnel_coverage = _funnels(
            scenario, runner, executor, tube, feedback, demo_starts, final_inputs,
            final_trajectories, initial_radii, quiet,
        )  # fmt: skip
        if not funnels.usable:
            return _failed(out, scenario, "funnel", f"no funnel certified: {funnels.message}")
        constant_trajectories = final_trajectories
        final_inputs, final_trajectories, funnels, funnel_coverage = _reoptimize_rounds(
            scenario, runner, executor, tube, feedback, optimized, demo_starts, final_inputs,
            final_trajectories, funnels, funnel_coverage, initial_radii, optimize_options, quiet,
        )  # fmt: skip
        usable = list(funnels.usable)
        controller = runner.run(
            "controller",
            inputs_key(code_key("stages.controller"), runner.digest("funnel"), usable),
            lambda: emit_funnel_controller(
                scenario,
                [final_trajectories[i] for i in usable],
                [funnels.funnels[i] for i in usable],
                controller_path,
                feedback_period=options.feedback_period,
            ),
            rerun=True,  # always written from this run's certified results
            describe=lambda result: result.message,
        )
    elif certificate == "constant":
        usable = [i for i, r in enumerate(final_radii) if r.radius > 0]
        controller = runner.run(
            "controller",
            inputs_key(
                code_key("stages.controller"),
                tube,
                usable,
                *demo_starts,
                *final_inputs,
                [final_radii[i].radius for i in usable],
                r_required,
            ),
            lambda: emit_controller(
                scenario,
                feedback.certified_tube.K,
                feedback.certified_tube.P,
                feedback.rate,
                [demo_starts[i] for i in usable],
                [final_inputs[i] for i in usable],
                [final_radii[i].radius for i in usable],
                controller_path,
                radius_floor=r_required,
                feedback_period=options.feedback_period,
            ),
            rerun=True,  # always written from this run's certified results
            describe=lambda result: result.message,
        )
    else:
        raise ValueError(f"certificate {certificate!r}; expected 'constant' or 'funnel'")
    started_certify = time.perf_counter()
    certification = certify_controller(scenario, controller_path)
    certify_seconds = time.perf_counter() - started_certify
    log.info(f"[certify] {certify_seconds:.1f} s: {certification.message}")
    with progress_bar(options.samples, "closed-loop runs", quiet) as advance:
        montecarlo = runner.run(
            "montecarlo",
            inputs_key(
                code_key("stages.montecarlo"),
                core,
                file_hash(controller_path),
                options.samples,
                options.seed,
            ),
            lambda: validate_closed_loop(
                scenario,
                controller_path,
                samples=options.samples,
                seed=options.seed,
                executor=executor,
                progress=advance,
            ),
            describe=lambda result: result.message,
        )
    stress = None
    if options.stress:
        stress = runner.run(
            "stress",
            inputs_key(
                code_key("stages.stress"),
                run_inputs.spec_key(scenario, "description"),
                file_hash(controller_path),
                options.seed,
            ),
            lambda: stress_test(scenario, controller_path, seed=options.seed),
            describe=lambda result: result.message,
        )

    results = StageResults(
        scenario=scenario,
        feedback=feedback,
        demo_trajectories=demo_trajectories,
        demo_radii=demo_radii,
        demo_coverage=demo_coverage,
        covering=covering,
        optimized=optimized,
        final_trajectories=final_trajectories,
        final_radii=final_radii,
        final_coverage=final_coverage,
        controller=controller,
        certification=certification,
        montecarlo=montecarlo,
        certificate=certificate,
        funnels=funnels,
        funnel_coverage=funnel_coverage,
        constant_trajectories=constant_trajectories,
    )
    summary = summarise(
        results,
        timings={**runner.timings(), "certify": certify_seconds},
        total_seconds=time.perf_counter() - started,
        command=sys.argv,
        stress=stress,
    )
    atomic_write_json(out / "summary.json", summary.to_json())
    write_manifest(scenario, out, file_hash(controller_path))
    runner.run(  # keyed on what the report shows: never on this run's timings
        "report",
        inputs_key(
            code_key(*REPORT_CODE),
            scenario.source_hash,
            run_inputs.spec_key(scenario),
            [runner.digest(name) for name in REPORT_STAGES],
            [runner.digest(name) for name in FUNNEL_STAGES if funnels is not None],
            None if stress is None else runner.digest("stress"),
            file_hash(controller_path),
        ),
        lambda: write_reports(load_report_data(scenario, out)),
        rerun=not _reports_present(out),
        describe=lambda result: result.message,
    )
    clear_stale(out)
    if not summary.certified:  # this run did not certify it: no current-looking controller.json
        os.replace(controller_path, stale_name(controller_path))
        log.info(f"controller.json renamed to {stale_name(controller_path).name}: not certified")
    return Synthesis(
        scenario=scenario.name,
        verdict=summary.verdict,
        success=summary.verdict is Verdict.CERTIFIED_AND_VALIDATED,
        message=summary.text,
        claims=summary.claims,
        controller=load_controller(controller_path) if summary.certified else None,
        demos=summary.demos,
        summary=summary,
        outputs=Outputs.of(out),
    )


def _reports_present(out: Path) -> bool:
    """Every report file is there (the PDF only where a browser can print it)."""
    names = REPORT_FILES if find_browser() is None else (*REPORT_FILES, "report.pdf")
    return all((out / name).is_file() for name in names)


def rebuild_reports(
    scenario_name: str | Path, source: Path | None = None, out: Path | None = None
) -> ReportResult:
    """The report stage alone (``python -m pipeline report``): reads a finished run's saved
    artifacts in ``source`` (default ``./reports/NAME``) and writes ``report.html``,
    ``report.pdf`` and ``scenario.png`` into ``out`` (default: ``source``). A missing, corrupt or
    stale artifact is a ``UserError`` naming it."""
    scenario = load_scenario(scenario_name)
    source = Path(source) if source is not None else default_output_folder(scenario.name)
    out = Path(out) if out is not None else source
    if not source.is_dir():  # nothing to lock: the loader names the missing file and its fix
        return write_reports(load_report_data(scenario, source))
    if out != source:
        check_report_folder(out)
    with folder_lock(source):
        return write_reports(load_report_data(scenario, source, write_to=out))
