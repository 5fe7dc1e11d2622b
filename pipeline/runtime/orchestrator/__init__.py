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

The run writes ``controller.json``, ``summary.json``, its input manifest and the reports into
``OUT/.staging`` and publishes them as a whole after the report (``pipeline.runtime.outdir``):
until then the folder holds the previous run's files, all of them; a run stopped while
publishing leaves the marker ``OUT/INCOMPLETE``, which every reader refuses.

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
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from threadpoolctl import threadpool_limits

from pipeline.controller import load as load_controller
from pipeline.io.artifacts import atomic_write_json, file_hash, remove_temporaries
from pipeline.io.errors import ScenarioError, UserError
from pipeline.io.executor import Executor, make_executor
from pipeline.io.folders import default_output_folder
from pipeline.io.lock import folder_lock
from pipeline.io.progress import progress_bar
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.prechecks import check_scenario
from pipeline.reporting.summary import Verdict
from pipeline.results.optimize import OptimizeResult
from pipeline.results.stage import FileInput
from pipeline.runtime import run_inputs
from pipeline.runtime.options import RunOptions
from pipeline.runtime.outdir import (
    INCOMPLETE,
    check_output_folder,
    check_report_folder,
    mark_failed,
    publish,
    staging_folder,
)
from pipeline.runtime.runner import StageRunner, stage_key
from pipeline.runtime.stored import (
    EVIDENCE_STAGES,
    load_report_data,
    published_report_key,
    staged_report_data,
    write_manifest,
)
from pipeline.runtime.summary import StageResults, demo_table, summarise
from pipeline.runtime.synthesis import Outputs, Synthesis
from pipeline.runtime.terminal import (
    describe_coverage,
    describe_covering,
    describe_radii,
    optimization_logs,
)
from stages.certificates import CERTIFICATES, CertificateRun, Targets, nominals
from stages.certify import certify_controller
from stages.coverage import (
    COVERAGE,
    COVERING_RADIUS,
    CoverageInputs,
    CoverageResult,
    CoveringRadiusInputs,
)
from stages.feedback import FEEDBACK, FeedbackInputs, FeedbackResult
from stages.montecarlo import MONTECARLO, MonteCarloInputs
from stages.optimize import OPTIMIZE, ConstraintMargins, OptimizeInputs, OptimizeOptions
from stages.radius import RADIUS, RadiusInputs, RadiusResult
from stages.report import REPORT, ReportInputs, ReportResult, write_reports
from stages.stress import STRESS, StressInputs

log = logging.getLogger(__name__)
T = TypeVar("T")
REPORT_FILES = ("report.html", "report.pdf", "scenario.png")
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


def _radii_and_coverage(
    scenario: Scenario,
    runner: StageRunner,
    feedback: FeedbackResult,
    which: str,
    trajectories: Sequence[Trajectory],
) -> tuple[tuple[RadiusResult, ...], CoverageResult]:
    """Stages ``radius_<which>`` (the robustness radius of each trajectory) and
    ``coverage_<which>`` (Init by the balls of those radii around the starts; a negative
    radius, no valid tube, counts as 0)."""
    tube = feedback.certified_tube
    radii: tuple[RadiusResult, ...] = runner.run(
        RADIUS,
        RadiusInputs(scenario=scenario, tube=tube, trajectories=tuple(trajectories)),
        name=f"radius_{which}",
        describe=describe_radii,
    )
    P = np.asarray(tube.P, dtype=np.float64)
    coverage = runner.run(
        COVERAGE,
        CoverageInputs(
            scenario=scenario,
            metrics=P,
            centers=np.array([t.xs[0] for t in trajectories]).reshape(-1, P.shape[0]),
            radii=np.array([max(r.radius, 0.0) for r in radii]),
        ),
        name=f"coverage_{which}",
        describe=describe_coverage,
    )
    return radii, coverage


def run_synthesis(
    scenario: Scenario | str | Path, out: Path | None = None, options: RunOptions | None = None
) -> Synthesis:
    """Run every stage on a scenario (the public form is ``pipeline.synthesize``): a
    ``Scenario`` from ``load_scenario`` (its demos checked, the default), or its name or path.

    Bad input (the scenario, the output folder, a folder in use) raises ``UserError`` before any
    work. The new files are staged in ``out/.staging`` and published together at the end
    (``pipeline.runtime.outdir.publish``). A run that fails writes ``summary.json`` saying so,
    renames the previous ``controller.json`` and reports to ``*.stale.*``
    (``pipeline.runtime.outdir``) and returns a ``Synthesis`` with ``Verdict.FAILED``.
    """
    started = time.perf_counter()
    options = options or RunOptions()
    if not isinstance(scenario, Scenario):
        scenario = load_scenario(scenario)
    if not scenario.demos:
        raise ScenarioError(
            "no demonstrations to synthesize from",
            file=scenario.path,
            field="demos",
            found=[],
            expected=f"at least one demo (record one: python -m pipeline record {scenario.name})",
        )
    check_scenario(scenario)  # hull, demo inputs in the region, a controllable reference
    certificate = run_inputs.certificate_of(scenario, options)
    period = run_inputs.period_of(scenario, options)  # --feedback-period, else the scenario's
    source = run_inputs.period_source(scenario, options)
    run_inputs.check_period(scenario, period, certificate, source)
    options = dataclasses.replace(options, feedback_period=period)  # what the run certifies
    run_inputs.check_uncertainty(scenario, certificate)
    run_inputs.check_keyable(scenario)  # a field replaced by a value of another type
    out = (Path(out) if out is not None else default_output_folder(scenario.name)).absolute()
    check_output_folder(out, scenario.name)
    log.info(f"outputs: {out}")
    # single-threaded BLAS in this process too, as in the workers: the matrices are
    # small, and OpenBLAS's threads made L-BFGS-B 5x slower in CPU (2.4 s -> 0.44 s on one demo)
    with folder_lock(out), threadpool_limits(limits=1, user_api="blas"):
        for folder in (out, out / "artifacts"):
            remove_temporaries(folder)  # left by killed writers; none can be active now
        staging = staging_folder(out)  # emptied: what a killed run staged is not this run's
        runner = StageRunner(out, force=options.force)
        executor = make_executor(options.executor, options.jobs)
        try:
            return _synthesize(scenario, out, staging, options, executor, runner, started)
        except (UserError, KeyboardInterrupt):
            raise
        except Exception as error:  # a crash: its traceback logged and saved
            log.error(f"stage {runner.current} raised", exc_info=error)
            reason = f"{type(error).__name__}: {error}"
            return _failed(out, scenario, runner.current, reason, crash=error)
        finally:
            executor.close()


def _failed(
    out: Path, scenario: Scenario, stage: str, reason: str, crash: Exception | None = None
) -> Synthesis:
    """Record a failed run (``summary.json``, with the traceback of the exception ``crash`` if
    one ended it; stale outputs renamed); its ``Synthesis``."""
    lines = "".join(traceback.format_exception(crash)).splitlines() if crash else None
    stale = mark_failed(out, scenario.name, stage, reason, traceback=lines)
    saved = f"{out / 'summary.json'}{', with the traceback' if crash else ''}"
    renamed = f"; previous outputs renamed: {', '.join(p.name for p in stale)}" if stale else ""
    return Synthesis(
        scenario=scenario.name,
        verdict=Verdict.FAILED,
        success=False,
        message=f"failed: stage {stage}: {reason} ({saved}{renamed})",
        claims=(),
        controller=None,
        demos=(),
        summary=None,
        outputs=Outputs.of(out),
    )


def _synthesize(
    scenario: Scenario,
    out: Path,
    staging: Path,
    options: RunOptions,
    executor: Executor,
    runner: StageRunner,
    started: float,
) -> Synthesis:
    period = run_inputs.period_of(scenario, options)  # resolved in run_synthesis
    demo_starts = [d.x0 for d in scenario.demos]
    demo_inputs = [d.us for d in scenario.demos]
    demo_trajectories = nominals(scenario, demo_starts, demo_inputs)
    log.info(
        f"scenario {scenario.name}: {len(scenario.demos)} demos, all valid "
        "(never in Unsafe, end in Goal)"
    )
    log.debug(f"{demo_table(scenario, demo_trajectories)}\n")  # the table under -v
    quiet = not log.isEnabledFor(logging.INFO)  # progress bars only where lines are shown

    feedback = runner.run(FEEDBACK, FeedbackInputs(scenario=scenario), describe=_message)
    if not feedback.success:
        reason = f"the feedback could not be certified: {feedback.message}"
        return _failed(out, scenario, "feedback", reason)
    scenario = feedback.applied_to(scenario)  # a tuned design's region, rate and weights
    # the constant tube at the held law's rate; the funnel certificate holds the held law in
    # its funnels (funnel.law (I6)), and uses the constant tube only to start from
    constant = run_inputs.certificate_of(scenario, options) == "constant"
    if period > 0 and constant:
        feedback, held = run_inputs.held_feedback(scenario, feedback, period)
        if not held.success:
            reason = (
                f"zero-order-hold feedback every {held.period:g} s cannot be certified: the "
                f"held tube's rate {held.held_rate:.3g}/s is not > 0 (continuous rate "
                f"{held.rate:.3g}/s, C1 = {held.C1:.3g}); use a shorter feedback period"
            )
            return _failed(out, scenario, "feedback", reason)
        log.info(
            f"[held feedback] every {held.period:g} s: tube rate {held.held_rate:.4g}/s "
            f"(continuous {held.rate:.4g}/s; pipeline.numerics.tube.sampled)"
        )
    tube = feedback.certified_tube
    demo_radii, demo_coverage = _radii_and_coverage(
        scenario, runner, feedback, "demos", demo_trajectories
    )

    r_d = feedback.required_radius(scenario.clearance)
    covering = runner.run(
        COVERING_RADIUS,
        CoveringRadiusInputs(
            scenario=scenario,
            P=tube.P,
            centers=np.array(demo_starts),
            upper=max(r_d, *(r.radius for r in demo_radii)),
        ),
        describe=describe_covering,
    )
    r_required = covering.kept_radius(r_d)
    optimize_options = OptimizeOptions(
        method=run_inputs.method_of(scenario, options), search=options.search
    )
    certificate = CERTIFICATES[run_inputs.certificate_of(scenario, options)]
    # where the nominals end: Goal, or a hold run's terminal core (stages.certificates)
    targets = certificate.targets(scenario, period)

    def optimize(targets: Targets, name: str, what: str) -> OptimizeResult:
        with progress_bar(len(scenario.demos), what, quiet) as advance:
            return runner.run(
                OPTIMIZE,
                OptimizeInputs(
                    scenario=targets.scenario,
                    margins=targets.margins(ConstraintMargins.of_tube(tube, r_required)),
                    options=optimize_options,
                ),
                name=name,
                describe=_message,
                executor=executor,
                progress=advance,
            )

    if targets.placing:  # first to rest wherever the terminal set fits, then to where they did
        resting = optimize(targets, "optimize_rest", "demos optimized to rest")
        rested = [i for i, t in enumerate(resting.trajectories) if t.success]
        flown = nominals(
            scenario, [demo_starts[i] for i in rested], [resting.trajectories[i].u for i in rested]
        )
        ends = [trajectory.xs[-1] for trajectory in flown]
        targets = certificate.placed(scenario, targets, ends, period)
    optimized = optimize(targets, OPTIMIZE.name, "demos optimized")
    if log.isEnabledFor(logging.DEBUG):
        log.debug(optimization_logs(optimized))
    # a demo whose optimisation failed keeps its own (valid) nominal trajectory
    final_inputs = [
        t.u if t.success else d.us
        for t, d in zip(optimized.trajectories, scenario.demos, strict=True)
    ]
    final_trajectories = nominals(scenario, demo_starts, final_inputs)
    final_radii, final_coverage = _radii_and_coverage(
        scenario, runner, feedback, "optimized", final_trajectories
    )

    controller_path = staging / "controller.json"  # published as out / "controller.json"
    certified = certificate.ship(
        CertificateRun(
            scenario=scenario,
            runner=runner,
            executor=executor,
            feedback=feedback,
            starts=demo_starts,
            optimized=optimized,
            inputs=final_inputs,
            trajectories=final_trajectories,
            radii=final_radii,
            r_required=r_required,
            options=optimize_options,
            feedback_period=period,
            controller_path=controller_path,
            quiet=quiet,
            publish=functools.partial(_published, out),
            describe_coverage=describe_coverage,
            targets=targets,
        )
    )
    if certified.controller is None:
        return _failed(out, scenario, certified.failed_stage, certified.failure)
    controller = certified.controller
    started_certify = time.perf_counter()
    certification = certify_controller(scenario, controller_path)
    certify_seconds = time.perf_counter() - started_certify
    log.info(f"[certify] {certify_seconds:.1f} s: {certification.message}")
    # unchanged from here until it is published
    shipped = FileInput(path=controller_path, sha256=file_hash(controller_path))
    with progress_bar(options.samples, "closed-loop runs", quiet) as advance:
        montecarlo = runner.run(
            MONTECARLO,
            MonteCarloInputs(
                scenario=scenario, controller=shipped, samples=options.samples, seed=options.seed
            ),
            describe=_message,
            executor=executor,
            progress=advance,
        )
    stress = None
    if options.stress:
        stress = runner.run(
            STRESS,
            StressInputs(scenario=scenario, controller=shipped, seed=options.seed),
            describe=_message,
        )

    results = StageResults(
        scenario=scenario,
        feedback=feedback,
        demo_trajectories=demo_trajectories,
        demo_radii=demo_radii,
        demo_coverage=demo_coverage,
        covering=covering,
        optimized=optimized,
        final_trajectories=certified.trajectories,
        final_radii=final_radii,
        final_coverage=final_coverage,
        controller=controller,
        certification=certification,
        montecarlo=montecarlo,
        certificate=certificate.name,
        funnels=certified.funnels,
        funnel_coverage=certified.funnel_coverage,
        constant_trajectories=certified.constant_trajectories,
        feedback_period=period,
    )
    summary = summarise(
        results,
        timings={**runner.timings(), "certify": certify_seconds},
        total_seconds=time.perf_counter() - started,
        command=sys.argv,
        stress=stress,
    )
    atomic_write_json(staging / "summary.json", summary.to_json())
    shown = (  # what the report shows: never this run's timings
        *REPORT_STAGES,
        *certified.report_stages,
        *(("stress",) if stress is not None else ()),
    )
    report_inputs = ReportInputs(
        scenario=scenario,
        results=tuple((name, runner.digest(name)) for name in shown),
        controller=shipped,
    )
    report_key = stage_key(REPORT, report_inputs)
    named = (*EVIDENCE_STAGES, *(("stress",) if stress is not None else ()))
    digests = {name: runner.digest(name) for name in named}  # what report reads, by content
    write_manifest(scenario, staging, shipped.sha256, digests, report_key)
    # the published reports are this run's when their key is this one (else written anew)
    current = published_report_key(out) == report_key and _reports_present(out)
    runner.run(
        REPORT,
        report_inputs,
        rerun=not current,
        describe=_message,
        finish=functools.partial(_published, out),
        data=lambda: staged_report_data(scenario, out, staging, summary, certification, stress),
    )
    publish(out, staging, certified=summary.certified)
    return Synthesis(
        scenario=scenario.name,
        verdict=summary.verdict,
        success=summary.verdict is Verdict.CERTIFIED_AND_VALIDATED,
        message=summary.text,
        claims=summary.claims,
        controller=load_controller(out / "controller.json") if summary.certified else None,
        demos=summary.demos,
        summary=summary,
        outputs=Outputs.of(out),
    )


def _message(result: Any) -> str:
    """What a stage's result says of itself (its ``message``)."""
    return str(result.message)


def _published(out: Path, result: T) -> T:
    """A result naming a staged file (``path``, ``html``, ``pdf`` in ``out/.staging``) with the
    name it is published under in ``out``."""
    moved = {
        name: out / value.name
        for name in ("path", "html", "pdf")
        if isinstance(value := getattr(result, name, None), Path)
    }
    return dataclasses.replace(result, **moved)  # type: ignore[type-var]


def _reports_present(out: Path) -> bool:
    """Every report file is there (and no publish was cut short)."""
    return not (out / INCOMPLETE).exists() and all((out / name).is_file() for name in REPORT_FILES)


def rebuild_reports(
    scenario_name: str | Path, source: Path | None = None, out: Path | None = None
) -> ReportResult:
    """The report stage alone (``python -m pipeline report``): reads a finished run's saved
    artifacts in ``source`` (default ``./reports/NAME``) and writes ``report.html``,
    ``report.pdf`` and ``scenario.png`` into ``out`` (default: ``source``). The verdict is
    derived again (``controller.json`` certified again, the Monte Carlo result of that file:
    ``pipeline.runtime.stored``), never read from ``summary.json``. A missing, corrupt, stale or
    mismatched file, or a folder whose publish was cut short, is a ``UserError`` naming it."""
    scenario = load_scenario(scenario_name)
    source = Path(source) if source is not None else default_output_folder(scenario.name)
    out = Path(out) if out is not None else source
    if not source.is_dir():  # nothing to lock: the loader names the missing file and its fix
        return write_reports(load_report_data(scenario, source))
    if out != source:
        check_report_folder(out)
    with folder_lock(source), threadpool_limits(limits=1, user_api="blas"):
        return write_reports(load_report_data(scenario, source, write_to=out))
