"""The orchestrator: wires the stages in order and keeps their artifacts under ``reports/NAME``.

    load -> feedback -> radius(demos) -> coverage(demos) -> covering radius -> optimize
         -> radius(optimized) -> coverage(optimized) -> controller -> montecarlo -> report

The optimizer keeps every tube at the required radius ``max(r_d, covering radius)``: ``r_d`` is
the radius that the clearance ``d`` certifies, and the covering radius the smallest common one
whose balls around the demo starts cover Init, so that coverage survives the optimization.

It holds no numerics: each stage is a function from typed inputs to a frozen result, stored by
``pipeline.runtime.runner.StageRunner`` with a hash of its inputs so that unchanged stages are
reused.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.io.artifacts import atomic_write_json, file_hash, inputs_key
from pipeline.io.errors import ScenarioError
from pipeline.io.executor import Executor, make_executor
from pipeline.io.progress import progress_bar
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.verify import VERIFY_SUBSTEPS
from pipeline.runtime.options import RunOptions
from pipeline.runtime.runner import StageRunner
from pipeline.runtime.summary import demo_table, print_summary, stress_summary, summarise
from stages.controller import emit_controller
from stages.coverage import CoverageResult, CoveringRadius, cover_init, covering_radius
from stages.feedback import FeedbackResult, design_feedback
from stages.montecarlo import validate_closed_loop
from stages.optimize import ConstraintMargins, OptimizeOptions, OptimizeResult, optimize
from stages.radius import RadiusResult, robustness_radius
from stages.report import ReportResult, write_reports
from stages.stress import stress_test

REPORTS_ROOT = Path(__file__).resolve().parents[2] / "reports"
REPORT_FILES = ("report.html", "report.pdf", "scenario.png")


def _trajectories(
    scenario: Scenario, starts: Sequence[np.ndarray], inputs: Sequence[np.ndarray]
) -> list[Trajectory]:
    return [
        simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=VERIFY_SUBSTEPS)
        for x0, us in zip(starts, inputs, strict=True)
    ]


def _radii(
    scenario: Scenario, feedback: FeedbackResult, trajectories: Sequence[Trajectory]
) -> tuple[RadiusResult, ...]:
    tube = feedback.certified_tube
    return tuple(robustness_radius(scenario, tube, tr) for tr in trajectories)


def _coverage(
    scenario: Scenario,
    feedback: FeedbackResult,
    starts: Sequence[np.ndarray],
    radii: Sequence[RadiusResult],
) -> CoverageResult:
    return cover_init(
        scenario, feedback, np.array(starts), np.array([max(r.radius, 0.0) for r in radii])
    )


def synthesize(
    scenario_name: str | Path, out: Path | None = None, options: RunOptions | None = None
) -> int:
    """Run every stage on a scenario; returns the exit code (0 certified and validated, 1 not)."""
    options = options or RunOptions()
    executor = make_executor(options.executor, options.jobs)
    try:
        return _synthesize(scenario_name, out, options, executor)
    finally:
        executor.close()


def _synthesize(
    scenario_name: str | Path, out: Path | None, options: RunOptions, executor: Executor
) -> int:
    started = time.perf_counter()
    scenario = load_scenario(scenario_name)
    if not scenario.demos:
        raise ScenarioError(
            "no demonstrations to synthesize from",
            file=scenario.path,
            field="demos",
            found=[],
            expected=f"at least one demo (record one: python -m pipeline record {scenario.name})",
        )
    out = Path(out) if out is not None else REPORTS_ROOT / scenario.name
    say = (lambda _text: None) if options.quiet else print
    runner = StageRunner(out, force=options.force, log=say)
    base = inputs_key(scenario.source_hash, [file_hash(d.file) for d in scenario.demos])
    demo_starts = [d.x0 for d in scenario.demos]
    demo_inputs = [d.us for d in scenario.demos]
    demo_trajectories = _trajectories(scenario, demo_starts, demo_inputs)
    say(
        f"scenario {scenario.name}: {len(scenario.demos)} demos, all valid "
        f"(never in Unsafe, end in Goal)\n{demo_table(scenario, demo_trajectories)}\n"
    )

    feedback = runner.run(
        "feedback", inputs_key(base, "feedback/2"), lambda: design_feedback(scenario)
    )
    if not feedback.success:
        print(f"not certified: the feedback could not be certified: {feedback.message}")
        return 1
    tube = inputs_key(base, feedback.K, feedback.P, feedback.rate)
    demo_radii = runner.run(
        "radius_demos",
        inputs_key(tube, "radius/2"),
        lambda: _radii(scenario, feedback, demo_trajectories),
    )
    demo_coverage = runner.run(
        "coverage_demos",
        inputs_key(tube, "coverage/1"),
        lambda: _coverage(scenario, feedback, demo_starts, demo_radii),
    )

    r_d = feedback.required_radius(scenario.clearance)
    covering: CoveringRadius = runner.run(
        "covering_radius",
        inputs_key(tube, "covering/1"),
        lambda: covering_radius(
            scenario,
            feedback,
            np.array(demo_starts),
            upper=max(r_d, *(r.radius for r in demo_radii)),
        ),
    )
    r_required = covering.kept_radius(r_d)
    margins = ConstraintMargins.of_tube(feedback.certified_tube, r_required)
    optimize_options = OptimizeOptions(method=options.method, search=options.search)
    with progress_bar(len(scenario.demos), "demos optimized", options.quiet) as advance:
        optimized: OptimizeResult = runner.run(
            "optimize",
            inputs_key(tube, "optimize/2", r_required, repr(optimize_options)),
            lambda: optimize(
                scenario, margins, optimize_options, executor=executor, progress=advance
            ),
        )
    if options.verbose:
        _print_optimization_logs(optimized)
    # a demo whose optimisation failed keeps its own (valid) nominal trajectory
    final_inputs = [
        t.u if t.success else d.us
        for t, d in zip(optimized.trajectories, scenario.demos, strict=True)
    ]
    final_trajectories = _trajectories(scenario, demo_starts, final_inputs)
    final_key = inputs_key(tube, *final_inputs)
    final_radii = runner.run(
        "radius_optimized",
        inputs_key(final_key, "radius/2"),
        lambda: _radii(scenario, feedback, final_trajectories),
    )
    final_coverage = runner.run(
        "coverage_optimized",
        inputs_key(final_key, "coverage/1"),
        lambda: _coverage(scenario, feedback, demo_starts, final_radii),
    )

    usable = [i for i, r in enumerate(final_radii) if r.radius > 0]
    controller_path = out / "controller.json"
    controller = runner.run(
        "controller",
        inputs_key(final_key, [final_radii[i].radius for i in usable]),
        lambda: emit_controller(
            scenario,
            feedback.K,
            feedback.P,
            feedback.rate,
            [demo_starts[i] for i in usable],
            [final_inputs[i] for i in usable],
            [final_radii[i].radius for i in usable],
            controller_path,
        ),
        rerun=not controller_path.is_file(),
    )
    with progress_bar(options.samples, "closed-loop runs", options.quiet) as advance:
        montecarlo = runner.run(
            "montecarlo",
            inputs_key(file_hash(controller_path), options.samples, options.seed, "mc/2"),
            lambda: validate_closed_loop(
                scenario,
                controller_path,
                samples=options.samples,
                seed=options.seed,
                executor=executor,
                progress=advance,
            ),
        )
    stress = None
    if options.stress:
        stress = runner.run(
            "stress",
            inputs_key(file_hash(controller_path), options.seed, "stress/1"),
            lambda: stress_test(scenario, controller_path, seed=options.seed),
        )

    summary = summarise(
        scenario,
        feedback,
        demo_trajectories,
        demo_radii,
        demo_coverage,
        covering,
        optimized,
        final_trajectories,
        final_radii,
        final_coverage,
        controller,
        montecarlo,
        runner.timings(),
        time.perf_counter() - started,
        command=sys.argv,
    )
    if stress is not None:
        summary["stress"] = stress_summary(stress)
    atomic_write_json(out / "summary.json", summary)
    runner.run(
        "report",
        inputs_key(summary, "report/2"),
        lambda: write_reports(scenario, out),
        rerun=not all((out / name).is_file() for name in REPORT_FILES),
    )
    if options.quiet:
        print(f"verdict: {summary['verdict']['text']}")
    else:
        print_summary(summary)
    return 0 if summary["verdict"]["certified"] and summary["verdict"]["validated"] else 1


def rebuild_reports(scenario_name: str | Path, out: Path | None = None) -> ReportResult:
    """The report stage alone, from a finished run's saved artifacts (``python -m pipeline
    report``)."""
    scenario = load_scenario(scenario_name)
    return write_reports(scenario, Path(out) if out is not None else REPORTS_ROOT / scenario.name)


def _print_optimization_logs(optimized: OptimizeResult) -> None:
    for trajectory in optimized.trajectories:
        print(f"\n{trajectory.demo}: horizons tried (N', feasible, iterations, final J)")
        for attempt in trajectory.tries:
            print(
                f"  N'={attempt.N:4d}  {'feasible  ' if attempt.feasible else 'infeasible'}"
                f"  {attempt.iterations:4d}  {attempt.cost:.3e}"
            )
        print(f"{trajectory.demo}: descent log at N' = {trajectory.N}")
        print(trajectory.log.table())
