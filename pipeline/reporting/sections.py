"""The report's sections, built from ``ReportData`` (summary.json plus the stage results).

Summary, Scenario, (a scenario that declares an uncertainty: Declared uncertainty,
``reporting.uncertainty``), Optimization, Feedback, Coverage, Monte Carlo, Inputs (these five in
``stage_sections``), (a funnel run: Seed and comparison, the constant certificate) and
Reproducibility, numbered in that order (``titles``). The paper's reference numbers (Winn & Julius,
§IV-B) are quoted beside ours.
"""

from __future__ import annotations

import shlex
from collections.abc import Callable, Sequence
from functools import partial

import numpy as np

from pipeline.io.artifacts import file_hash
from pipeline.reporting import certificates, figures, shipped, stage_sections, uncertainty
from pipeline.reporting.content import (
    Figure,
    Headline,
    Headlines,
    Paragraph,
    Section,
    Table,
    Verdict,
    fixed,
    percent,
    scientific,
    seconds,
)
from pipeline.reporting.data import ReportData
from pipeline.reporting.law import law_items
from pipeline.reporting.numbers import failure_kinds, runs_failed
from pipeline.reporting.plotting import FIGURE_WIDTH
from pipeline.reporting.summary import Summary
from pipeline.reporting.summary import Verdict as VerdictKind

PAPER_SCENARIO = "quadrotor_hill_flythrough"  # the paper's example (§IV-B), its numbers quoted
PAPER_FASTER_PERCENT = 42  # §IV-B: "The optimal trajectory is 42% faster"
PAPER_DEMO_CLEARANCE = 0.22  # §IV-B: the human demo's buffer to Unsafe, against d = 1.0
TITLES = (
    ("summary", "Summary"),
    ("scenario", "Scenario and trajectories"),
    ("optimization", "Optimization"),
    ("feedback", "Feedback and contraction certificate"),
    ("coverage", "Coverage of Init"),
    ("montecarlo", "Monte Carlo validation"),
    ("inputs", "Inputs"),
    ("reproducibility", "Reproducibility"),
)
SEED = ("seed", shipped.SEED_TITLE)  # a funnel run's section before Reproducibility
# a run whose scenario declares an uncertainty: its section after "Scenario and trajectories"
DECLARED = ("uncertainty", uncertainty.TITLE)


def titles(funnel: bool = False, declared: bool = False) -> list[tuple[str, str]]:
    """The sections' (key, title) in order: ``TITLES``, with "Declared uncertainty" after the
    scenario when ``declared`` and "Seed and comparison" before Reproducibility when
    ``funnel``."""
    shown = list(TITLES)
    if declared:
        shown.insert(2, DECLARED)
    if funnel:
        shown.insert(-1, SEED)
    return shown


def headline_items(summary: Summary, length: str = "m") -> tuple[Headline, ...]:
    """The headline numbers of ``summary.json``, formatted as the report shows them; the
    paper's numbers beside them only for the paper's scenario (``PAPER_SCENARIO``). A funnel
    run's cards start with what controller.json guarantees (``shipped.shipped_items``) and
    show no number of the constant certificate (the seed, section "Seed and comparison")."""
    h, mc = summary.headline, summary.montecarlo
    stages = summary.timings
    reused = sum(1 for v in stages.values() if v == 0.0)
    paper = summary.scenario == PAPER_SCENARIO
    kinds = failure_kinds(mc.failures)
    funnel = summary.certificate == "funnel"
    unit = f" {length}" if length else ""
    clearance = Headline(
        "Nominal clearance to Unsafe",
        f"{fixed(h.min_clearance_before)} → {fixed(h.min_clearance_after)}{unit}",
        f"closest nominal trajectory, demos → {'shipped' if funnel else 'optimized'}; kept "
        f"≥ d = {h.required_clearance:g}{unit} by the optimizer"
        + (f"; the paper's demo: {PAPER_DEMO_CLEARANCE}" if paper else ""),
    )
    if funnel:
        coverage = Headline(
            "Init coverage",
            percent(h.coverage_after),
            "by the shipped funnels' initial sets E_i(0), certified on controller.json"
            if h.covered_after
            else "NOT fully covered by the shipped funnels' initial sets E_i(0)",
        )
    else:
        coverage = Headline(
            "Init coverage",
            f"{percent(h.coverage_before)} → {percent(h.coverage_after)}",
            "certified covered after optimization"
            if h.covered_after
            else "NOT fully covered after optimization",
        )
    return (
        *shipped.shipped_items(summary, length),
        Headline(
            "Faster (mean over demos)",
            percent(h.faster_percent_mean / 100, 0),
            f"terminal time {seconds(h.T_demo_mean)} → {seconds(h.T_optimized_mean)}"
            + (" (shipped)" if funnel else "")
            + (f"; the paper: {PAPER_FASTER_PERCENT}%" if paper else ""),
        ),
        clearance,
        Headline(
            "Closed-loop clearance (Monte Carlo)",
            f"{fixed(summary.montecarlo.min_clearance)}{unit}",
            f"closest of the {summary.montecarlo.samples} closed-loop runs from Init "
            "(controller.json flown); > 0: never in Unsafe",
        ),
        coverage,
        Headline(
            "Monte Carlo",
            runs_failed(h.montecarlo_samples, h.montecarlo_failures),
            (f"{kinds} (a run can fail in several ways); " if kinds else "")
            + f"failure probability ≤ {scientific(h.failure_bound_95)} (95% one-sided)",
        ),
        Headline(
            "Wall time",
            seconds(summary.total_seconds),
            "all stages of this run" + (f"; {reused} reused from the cache" if reused else ""),
        ),
    )


def _starts(data: ReportData) -> list[str]:
    """Each demonstration's start position, as shown: ``(1.33, 2.17)``."""
    s = data.scenario
    return [
        "(" + ", ".join(f"{v:.2f}" for v in np.asarray(d.start)[list(s.position_index)]) + ")"
        for d in data.summary.demos
    ]


def _demo_table(data: ReportData) -> Table:
    """The per-demonstration table: what ships in a funnel run (``shipped.funnel_table``),
    the optimized trajectories and their robustness radii in a constant run."""
    s, summary = data.scenario, data.summary
    if data.funnel:
        return shipped.funnel_table(summary, _starts(data), s.position_unit())
    position = [s.state_names[i] for i in s.position_index]
    demos = tuple(
        (
            d.demo,
            start,
            fixed(d.T_demo, 1),
            fixed(d.T_optimized, 1),
            f"{d.faster_percent:.0f}%",
            fixed(d.clearance_before, 3),
            fixed(d.clearance_after, 3),
            fixed(d.radius_before, 3),
            fixed(d.radius_after, 3),
            "yes" if d.optimized else "no (kept as flown)",
        )
        for d, start in zip(summary.demos, _starts(data), strict=True)
    )
    return Table(
        (
            "demo",
            f"start ({', '.join(position)}) [m]",
            "T demo (s)",
            "T opt (s)",
            "faster",
            "clearance before (m)",
            "clearance after (m)",
            "radius before (P-norm)",
            "radius after (P-norm)",
            "optimized",
        ),
        demos,
        "Per demonstration",
        numeric=(False, False, *([True] * 7), False),
        stack=True,
    )


def _summary(data: ReportData) -> tuple:
    s, summary = data.scenario, data.summary
    n = len(s.demos)
    timings = [
        (stage, fixed(t, 2), "reused" if t == 0.0 else "") for stage, t in summary.timings.items()
    ]
    timings.append(("total (incl. loading and summary)", fixed(summary.total_seconds, 2), ""))
    seed = 1 + titles(True, not s.uncertainty.empty).index(SEED)
    period = data.law.feedback_period if data.funnel else 0.0
    against = (
        f"re-optimized against funnels and the funnels of the law held every {period:g} s "
        "certified around the final ones"
        if period > 0
        else "re-optimized against their funnels"
    )
    ships = (
        "then a funnel E_i(t) is certified around each (the funnel certificate, "
        f"controller.json), with the nominals {against}, and validated "
        "by simulation. The constant certificate that seeds it is not shipped (section "
        f"{seed}, {shipped.SEED_TITLE})."
        if data.funnel
        else "then the feedback controller built from the optimized trajectories is certified "
        "and validated by simulation."
    )
    return (
        Paragraph(
            f"Scenario {s.name}: {s.spec.description or 'no description'} {n} demonstrations, "
            f"sampling time Ts = {s.Ts:g} s, required clearance d = {s.clearance:g} m. Each "
            "demonstration is made as fast as possible without losing its robustness radius "
            f"(Winn & Julius, Remark 4), {ships}"
        ),
        Verdict(
            summary.verdict is VerdictKind.CERTIFIED_AND_VALIDATED,
            summary.text,
            summary.reasons,
        ),
        Headlines(headline_items(summary, s.position_unit()) + law_items(data)),
        Table(
            ("claim", "kind", "how it was established"),
            tuple((c.claim, c.kind.value, c.how) for c in summary.claims),
            "Claims: certified (proof, re-checked), statistically validated (sampling with a "
            "bound), falsification-searched (search, no bound)",
            badges=1,
            stack=True,
        ),
        _demo_table(data),
        Table(
            ("stage", "wall time (s)", ""),
            tuple(timings),
            "Wall time per stage (0: result reused from a previous run with the same inputs)",
            numeric=(False, True, False),
        ),
    )


def _seed(data: ReportData) -> tuple:
    """Seed and comparison (funnel run): the constant certificate, once."""
    return (
        shipped.seed_paragraph(data.summary),
        *certificates.comparison(data),
        shipped.constant_demo_table(data.summary, data.feedback.position_extent(1.0)),
        *stage_sections.constant_feedback(data),
    )


def _modgoal(data: ReportData) -> str:
    """What ModGoal is for in this run: where the constant certificate's nominals must end;
    a funnel run's shipped nominals need not (their funnel at T, E_i(T), must lie in Goal)."""
    if data.funnel:
        return (
            "where the constant certificate's optimized trajectories must end; the shipped "
            "nominals (funnel certificate) need not end in it: each funnel at its final time, "
            "E_i(T), must lie in Goal"
        )
    return "where the optimized trajectories must end"


def _scenario(data: ReportData) -> tuple:
    s = data.scenario
    index = figures.bisection_demo(data)
    opt = data.optimize.trajectories[index]
    before = data.summary.demos[index].clearance_before
    free = ", ".join(
        f"{name} in [{lo:g}, {hi:g}]"
        for name, lo, hi in zip(s.state_names, s.init_lower, s.init_upper, strict=True)
        if hi > lo
    )
    shipped = (file_hash(data.controller_path),) if data.funnel else ()  # drawn from the file
    return (
        Paragraph(
            f"Unsafe: {', '.join(s.unsafe)} (grey; dotted: bloated by d). Goal: green; ModGoal: "
            f"Goal shrunk by d (dashed), {_modgoal(data)}. Init: {free} (other states fixed)."
        ),
        Figure(
            "overview",
            "All demonstrations (blue) and their optimized trajectories (orange"
            + (", as shipped in controller.json" if data.funnel else "")
            + f"). Markers are {figures.MARKER_PERIOD:g} s apart, so their spacing shows the "
            "speed. "
            + (
                "The cyan outlines are the position projection of each shipped trajectory's "
                "funnel {x : ||x - x_ref(t)||_P_i(t) <= ρ_i}, every "
                f"{figures.TUBE_PERIOD:g} s and at T; the arrows: each nominal's velocity when "
                f"it arrives ({figures.ARROW_SECONDS:g} s of travel)."
                if data.funnel
                else "The orange ellipses are the position projection of each optimized "
                "trajectory's robustness tube {x : ||x - x_ref(t)||_P <= r e^(-λt)}: outlined "
                f"at the start, shaded every {figures.TUBE_PERIOD:g} s along the path."
            ),
            partial(figures.draw_overview, data=data),
            (
                FIGURE_WIDTH,
                figures.scene_height(data, [*data.demo_paths, *data.shipped_paths], below=1.1),
            ),
            data.fingerprint("feedback", "optimize", "radius_optimized", *shipped),
        ),
        *certificates.funnel_figure(data),
        Figure(
            "bisection",
            f"As in the paper's Fig. 2, for {opt.demo} (flown closest to Unsafe: "
            f"{before:.2f} m): the demonstration, the search's intermediate feasible "
            "trajectories (purple; their horizon T' on the colour scale, darker = shorter) "
            "and the optimal one "
            f"({opt.N_demo} → {opt.N} samples), with the tubes (robustness bounds) of the "
            "demonstration (blue) and of the optimal trajectory (orange) along their paths: "
            f"outlined at the start, shaded every {figures.TUBE_PERIOD:g} s. Markers every "
            f"{figures.TUBE_PERIOD:g} s."
            + (
                " Funnel run: the orange path is the trajectory shipped in controller.json from "
                "this demonstration, its funnel E_i(t) outlined in cyan every "
                f"{figures.TUBE_PERIOD:g} s and at T instead of a shaded tube (dashed: the "
                "constant certificate's optimum, the seed, where the shipped nominal was "
                "re-optimized); the demonstration's tube is the constant certificate's."
                if data.funnel
                else ""
            ),
            partial(figures.draw_bisection, data=data, index=index),
            (
                FIGURE_WIDTH,
                figures.scene_height(data, figures.bisection_paths(data, index), below=2.3),
            ),
            data.fingerprint(
                "feedback", "optimize", "radius_demos", "radius_optimized", index, *shipped
            ),
        ),
    )


def _reproducibility(data: ReportData) -> tuple:
    summary = data.summary
    repro = summary.reproducibility
    command = list(repro.command)
    if command and command[0].endswith("__main__.py"):
        command = ["python", "-m", "pipeline", *command[1:]]
    versions = tuple((name, version) for name, version in repro.versions.items())
    return (
        Table(
            ("item", "value"),
            (
                ("command line", shlex.join(command)),
                ("scenario file", str(data.scenario.path)),
                ("scenario sha256", repro.scenario_sha256),
                ("controller.json sha256", file_hash(data.controller_path)),
                ("Monte Carlo seed", str(repro.montecarlo_seed)),
                ("output folder", str(data.run_folder)),
            ),
            "Run",
        ),
        Table(("package", "version"), versions, "Versions"),
        Table(
            ("stage", "artifact input key"),
            tuple(data.keys.items()),
            "Artifacts (artifacts/<stage>.json + .npz; a stage re-runs only when its key changes)",
        ),
        Paragraph(
            f"Rebuild this report from the saved artifacts: python -m pipeline report "
            f"{data.scenario.name} --from {data.run_folder}",
            "note",
        ),
    )


BUILDERS: dict[str, Callable[[ReportData], tuple]] = {
    "summary": _summary,
    "scenario": _scenario,
    "uncertainty": uncertainty.section,
    "optimization": stage_sections.optimization,
    "feedback": stage_sections.feedback,
    "coverage": stage_sections.coverage,
    "montecarlo": stage_sections.montecarlo,
    "inputs": stage_sections.inputs,
    "seed": _seed,
    "reproducibility": _reproducibility,
}


def build_sections(data: ReportData) -> list[Section]:
    """The report's sections, in order (``titles``): a funnel run's has "Seed and comparison"
    (the constant certificate, not shipped) before Reproducibility, and a run whose scenario
    declares an uncertainty "Declared uncertainty" after the scenario."""
    shown = titles(data.funnel, not data.scenario.uncertainty.empty)
    return [
        Section(key, number + 1, title, tuple(BUILDERS[key](data)))
        for number, (key, title) in enumerate(shown)
    ]


def section_headings(funnel: bool = False, declared: bool = False) -> Sequence[str]:
    """``"N. Title"`` of every section (a funnel run's or a constant run's, with or without a
    declared uncertainty), for tests and navigation."""
    return [f"{n + 1}. {title}" for n, (_, title) in enumerate(titles(funnel, declared))]
