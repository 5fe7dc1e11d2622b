"""Report sections 3-7, one per stage: optimization, feedback, coverage, Monte Carlo, inputs.

Each builder reads ``ReportData`` and returns its section's blocks; ``sections`` orders them.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from pipeline.io.artifacts import file_hash
from pipeline.reporting import certificates, figures, loop_figures, shipped
from pipeline.reporting.content import (
    Figure,
    Paragraph,
    Table,
    check,
    fixed,
    number,
    percent,
    scientific,
    vector,
)
from pipeline.reporting.data import ReportData
from pipeline.reporting.law import gain_table, held_rate, labelled, law
from pipeline.reporting.numbers import margin, montecarlo_counts
from pipeline.reporting.plotting import FIGURE_WIDTH
from pipeline.reporting.summary import Quantiles, StressRunSummary, StressSummary


def optimization(data: ReportData) -> tuple:
    options = data.optimize.options
    method = "gradient descent (§III-B, eq. (38))" if options.method == "gd" else "L-BFGS-B"
    search = (
        "bisection (Remark 4)"
        if options.search == "bisection"
        else "continuation (the last feasible horizon shortened by a tenth, the step halved "
        "after a failure)"
    )
    rows = []
    for k, opt in enumerate(data.optimize.trajectories):
        tries = ", ".join(f"{t.N}{'✓' if t.feasible else '✗'}" for t in opt.tries)
        i = data.shipped_index(k) if data.funnel else None
        to_shipped = "" if i is None else f" → {len(data.shipped_paths[i].us)}"
        rows.append(
            (
                opt.demo,
                f"{opt.N_demo} → {opt.N}{to_shipped}",
                tries,
                str(sum(t.iterations for t in opt.tries)),
                fixed(opt.seconds, 2),
                opt.message,
            )
        )
    checks = []
    for opt in data.optimize.trajectories:
        v = opt.verification
        if v is None:
            checks.append((opt.demo, "not verified", "", "", "", "no"))
            continue
        clearance = ", ".join(f"{k} {fixed(x, 3)}" for k, x in v.clearance.items())
        checks.append(
            (
                opt.demo,
                clearance,
                fixed(v.goal_margin, 3),
                fixed(v.input_margin, 3),
                fixed(v.region_margin, 4),
                check(not v.failures),
            )
        )
    return (
        Paragraph(
            f"Method: {method} on the penalty cost J (eqs. (40)-(42)); {options.parameterization} "
            f"parameterization; at most {options.max_iterations} iterations per horizon, fewer "
            f"when J, extrapolated at its rate over the last {options.stall_window} iterations, "
            f"would still be above {options.stall_margin:g} times the goal's threshold at that "
            "cap (the horizon then counts as infeasible); Unsafe "
            f"bloated by d + {options.eps_d:g}, Goal shrunk by d + {options.eps_g:g}. A horizon N' "
            "is feasible when J reaches 0; the descent minimises J with every margin tightened "
            f"by {options.overshoot:g} and stops as soon as the untightened J is exactly 0. The "
            f"shortest feasible N' is found by {search}, each try seeded by "
            f"{options.seed_mode} of the best feasible input."
        ),
        Figure(
            "optimization",
            "Top: the tightened J over the descent at the final horizon, one colour per "
            "demonstration (log scale; a triangle on the bottom axis marks where the untightened "
            "J reached 0, i.e. feasible). "
            + (
                "Middle: the step size λ (grows by α after an accepted step, shrinks by β after a "
                "rejected one). "
                if options.method == "gd"
                else ""
            )
            + "Bottom: the horizons tried, in order (circle: feasible, cross: infeasible).",
            partial(figures.draw_optimization, data=data),
            (FIGURE_WIDTH, 7.4 if options.method == "gd" else 5.2),
            data.fingerprint("optimize"),
        ),
        Table(
            (
                "demo",
                "samples",
                "horizons tried (N', ✓ feasible)",
                "iterations",
                "time (s)",
                "result",
            ),
            tuple(rows),
            "Search on the horizon per demo"
            + (
                " (samples: the demonstration → the seed's optimum, constant certificate → "
                "shipped, after the nominals were re-optimized against their funnels)"
                if data.funnel
                else ""
            ),
            numeric=(False, True, False, True, True, False),
        ),
        Table(
            (
                "demo",
                "clearance to Unsafe (m)",
                "goal margin (m)",
                "input margin",
                "region margin",
                "passed",
            ),
            tuple(checks),
            "Continuous-time verification of each optimized trajectory (lower bounds over [0, T])",
            numeric=(False, False, True, True, True, False),
        ),
    )


def _quantile_text(quantiles: Quantiles | None) -> str:
    if quantiles is None:
        return "n/a (re-run synthesize)"
    return ", ".join(fixed(q, 3) for q in (quantiles.median, quantiles.p95, quantiles.max))


def _constant_paragraph(data: ReportData) -> Paragraph:
    fb = data.feedback
    return Paragraph(
        "The controller is u = u_ref(t) + K (x - x_ref(t)). The certificate: P > 0 with "
        "(A_i + B_i K)^T P + P (A_i + B_i K) + 2λP < 0 at every vertex of a polytope that "
        "soundly contains the Jacobians [f_x f_u] over the operating region, so "
        "||x(t) - x_ref(t)||_P <= e^(-λt) ||x(0) - x_ref(0)||_P while the tube stays in the "
        f"region. Design: {fb.message}."
    )


def _constant_tables(data: ReportData) -> tuple:
    """The constant certificate's gain, certificate, operating region and input margins."""
    s, fb, summary = data.scenario, data.feedback, data.summary.feedback
    K = np.asarray(fb.K)
    eig = np.asarray(summary.P_eigenvalues)
    r_d = summary.required_radius
    region_rows = []
    for name, (lower, upper) in fb.region.items():
        extent = summary.region_extent_at_r_d.get(name, 0.0)
        region_rows.append((s.label(name), number(lower), number(upper), number(extent)))
    input_rows = tuple(
        (s.label(name), number(lo), number(hi), number(margin))
        for name, lo, hi, margin in zip(
            s.input_names, s.input_lower, s.input_upper, summary.input_margin_at_r_d, strict=True
        )
    )
    quantities = (
        (
            "contraction rate λ",
            f"{fb.rate:g} 1/s"
            if data.law.feedback_period == 0
            else f"{fb.rate:g} 1/s continuous; {held_rate(data)} with the law held every "
            f"{data.law.feedback_period:g} s (the tube's rate)",
        ),
        ("gain design", f"{fb.gain} (solver status: {fb.solver_status})"),
        ("P eigenvalues", vector(eig, 4)),
        ("P condition number", number(float(eig[-1] / eig[0]), 4)),
        (
            "required radius r_d (P-norm; its tube's position extent is d)",
            f"{number(r_d, 4)} (d = {s.clearance:g} m)",
        ),
        (
            "covering radius (smallest common radius of balls at the demo starts covering Init)",
            "none found" if summary.covering_radius is None else number(summary.covering_radius, 4),
        ),
        (
            "radius kept by the optimizer, max(r_d, covering radius)",
            number(summary.kept_radius, 4),
        ),
        ("position extent per unit P-radius", f"{number(fb.position_extent(1.0), 4)} m"),
        ("Jacobian hull", f"{len(fb.vertices)} vertices; " + "; ".join(fb.hull)),
        ("certified margin (max generalised eigenvalue, < 0)", scientific(fb.certified_margin)),
        ("design objective", number(fb.objective, 4)),
    )
    return (
        gain_table(
            s,
            K,
            "Feedback gain K (inputs × states)"
            + (
                f" of the constant certificate ({certificates.CONSTANT_STATUS})"
                if data.funnel
                else ""
            ),
        ),
        Table(("quantity", "value"), quantities, "Certificate"),
        Table(
            ("variable", "lower", "upper", "tube extent at r_d"),
            tuple(region_rows),
            "Operating region (where the certificate holds) and the margin the tube needs, in "
            "each variable's unit",
            numeric=(False, True, True, True),
        ),
        Table(
            ("input", "lower bound", "upper bound", "max |K_j e| at r_d"),
            input_rows,
            "Input margins: the feedback's share of each input at the required radius, in the "
            "input's unit",
            numeric=(False, True, True, True),
        ),
    )


def constant_feedback(data: ReportData) -> tuple:
    """The constant certificate's feedback, for a funnel run's "Seed and comparison"."""
    return (_constant_paragraph(data), *_constant_tables(data))


def feedback(data: ReportData) -> tuple:
    """The shipped law: in a funnel run its per-trajectory gains (the constant certificate's
    K and P are in "Seed and comparison"), in a constant run K, P and their certificate."""
    if data.funnel:
        return (*certificates.shipped_feedback(data), *law(data))
    tables = _constant_tables(data)
    return (_constant_paragraph(data), *tables[:2], *law(data), *tables[2:])


def coverage(data: ReportData) -> tuple:
    rows: list[tuple[str, ...]] = []
    for name, c in (
        ("demonstrations", data.coverage_demos),
        ("optimized", data.coverage_optimized),
    ):
        rows.append(
            (
                name,
                check(c.covered),
                percent(c.covered_fraction),
                str(len(c.boxes)),
                str(len(c.uncovered_boxes)),
                str(c.depth),
                c.message,
            )
        )
    if data.funnel:  # what ships first: the funnels' E_i(0), certified on controller.json
        rows = [
            shipped.coverage_row(data.summary),
            *((f"{r[0]}, constant balls (seed, not shipped)", *r[1:]) for r in rows),
        ]
    s = data.scenario
    free = [s.state_names[i] for i in data.coverage_demos.free]
    shown = " and ".join(free[:2]) if free else "its single point"
    through = f" (through the start's {', '.join(free[2:])})" if len(free) > 2 else ""
    projected = f" (projected along {', '.join(free[2:])})" if len(free) > 2 else ""
    extent = data.feedback.position_extent(1.0)  # m per unit of P-radius
    radii = tuple(
        (
            d.name,
            fixed(before.radius, 3),
            fixed(before.radius * extent, 3),
            before.binding,
            fixed(after.radius, 3),
            fixed(after.radius * extent, 3),
            after.binding,
        )
        for d, before, after in zip(
            data.scenario.demos, data.radius_demos, data.radius_optimized, strict=True
        )
    )
    return (
        Paragraph(
            "Init must lie in the union of the shipped funnels' initial sets E_i(0) = {x : "
            "||x - x0_i||_P_i[0] <= ρ_i} (controller.json), certified by the certify stage by "
            "subdividing Init into boxes until each box's vertices lie in one of them. The "
            "constant certificate's balls ||x - x0_i||_P <= r_i (the seed, not shipped) are "
            "shown beside them."
            if data.funnel
            else "Init must lie in the union of the balls ||x - x0_i||_P <= r_i around the "
            "starts of the nominal trajectories (r_i: robustness radius). Certified by "
            "subdividing Init into boxes until each box's vertices lie in one ball; boxes left "
            "are reported uncovered."
        ),
        Figure(
            "coverage",
            f"Init (black) over {shown} with the slices of the balls at each start{through}: "
            "before (demonstrations, blue) and after optimization (orange). Grey: boxes certified "
            f"covered; red: boxes not certified covered{projected}."
            + (
                " The first two are the constant certificate's balls (verified, not shipped); "
                "the third (cyan) shows the slices of the shipped funnels' initial ellipsoids "
                "E_i(0), each in its own metric P_i[0] from controller.json, which cover "
                f"{percent(data.summary.headline.coverage_after)} of Init (certified by the same "
                "box subdivision in the certify stage)."
                if data.funnel
                else ""
            ),
            partial(figures.draw_coverage, data=data),
            (FIGURE_WIDTH, 3.9),
            data.fingerprint(
                "feedback",
                "coverage_demos",
                "coverage_optimized",
                "radius_demos",
                "radius_optimized",
                "controller",
                data.funnel,
            ),
        ),
        Table(
            ("trajectories", "covered", "fraction", "boxes", "uncovered", "depth", "message"),
            tuple(rows),
            "Coverage certificate",
            numeric=(False, False, True, True, True, True, False),
        ),
        *(() if data.funnel else (_radius_table(radii),)),
    )


def _radius_table(radii: tuple) -> Table:
    return Table(
        (
            "demo",
            "radius before",
            "extent before (m)",
            "bound by",
            "radius after",
            "extent after (m)",
            "bound by",
        ),
        radii,
        "Robustness radii in the P-norm (no unit: ||e||_P weighs every state's error), "
        "their tubes' largest position offset (m), and the constraint that sets each",
        numeric=(False, True, True, False, True, True, False),
    )


def _stress(stress: StressSummary | None, beyond: float | None = None) -> tuple:
    """The stress test's table (``summary.stress``), if the run made one; ``beyond``: the
    declared uncertainty's multiple it drew (None: the scenario's stress settings)."""
    if stress is None:
        return (
            Paragraph(
                "Stress test (perturbed closed loop): not run (synthesize --stress).", "note"
            ),
        )
    runs = (stress.with_feedback, stress.without_feedback)

    def failures(run: StressRunSummary) -> str:
        counts = {k: v for k, v in run.failures.items() if v}
        return ", ".join(f"{k} {v}" for k, v in counts.items()) or "none"

    rows = (
        ("runs", *(str(r.samples) for r in runs)),
        ("failed", *(percent(r.failed_fraction) for r in runs)),
        ("failures by kind", *(failures(r) for r in runs)),
        ("minimum clearance to Unsafe (m)", *(fixed(r.min_clearance, 3) for r in runs)),
        ("minimum goal margin (m)", *(fixed(r.min_goal_margin, 3) for r in runs)),
    )
    return (
        Paragraph(f"Stress test ({stress.kind}): {stress.message}."),
        Table(
            ("", "with the feedback", "without (K = 0)"),
            rows,
            "Stress test: disturbance and measurement noise from the scenario's stress settings"
            if beyond is None
            else f"Stress test: the declared uncertainty widened {beyond:g} times about the "
            "nominal (section Declared uncertainty); not certified",
            numeric=(False, True, True),
        ),
    )


def _held(data: ReportData) -> str:
    """The runs continued past T under the terminal law ("" when none were)."""
    mc = data.montecarlo
    if not mc.hold_runs or mc.failures.get("after_T"):
        return ""
    return (
        f" {mc.hold_runs} covered runs, continued past T under the terminal law, stayed in Goal "
        f"(V / level ≤ {number(mc.hold_max_level_ratio, 3)})."
    )


def montecarlo(data: ReportData) -> tuple:
    mc = data.montecarlo
    f = mc.falsification
    h = data.summary.headline
    counts = montecarlo_counts(h.montecarlo_samples, h.montecarlo_failures, mc.failures)
    stress_blocks = _stress(
        data.summary.stress, None if data.stress is None else data.stress.beyond_declared
    )
    inside = "its funnel E_i(t)" if data.funnel else "the predicted tube"
    return (
        Paragraph(
            f"{mc.samples} initial states drawn i.i.d. uniformly from Init (seed {mc.seed}); each "
            "closed loop simulated with the controller read back from controller.json and checked "
            "in continuous time: never in Unsafe, ends in Goal, no input clipping, error inside "
            f"{inside}. Result: {counts}; failure probability ≤ {scientific(mc.failure_bound)} "
            f"(one-sided 95% Clopper-Pearson).{_held(data)}"
        ),
        Figure(
            "montecarlo",
            f"Top: {len(mc.paths)} of the {mc.samples} closed-loop runs (teal); failed starts as "
            "red crosses, the falsification search's worst start as a red star. Bottom: the "
            "distributions of each run's minimum clearance to Unsafe and of its tube tightness "
            "(1 = on the tube's boundary); failures in red beyond the dashed threshold. The "
            f"dotted line at d = {data.scenario.clearance:g} m is the clearance the optimizer "
            "keeps for the nominals, not a closed-loop requirement: a closed-loop run fails "
            "only below 0.",
            partial(loop_figures.draw_montecarlo, data=data),
            (FIGURE_WIDTH, 8.4),
            data.fingerprint("montecarlo"),
        ),
        Table(
            ("failure kind", "runs"),
            tuple((kind, str(count)) for kind, count in mc.failures.items()),
            f"Failures by kind ({counts}; a run can fail in several ways, so the kinds need not "
            "add up to the runs failed)",
            numeric=(False, True),
        ),
        Table(
            ("quantity", "value"),
            (
                (
                    "failure probability, one-sided 95% Clopper-Pearson bound",
                    scientific(mc.failure_bound),
                ),
                ("minimum clearance to Unsafe (m)", fixed(mc.min_clearance, 3)),
                ("minimum goal margin (m)", fixed(mc.min_goal_margin, 3)),
                ("maximum tube tightness", fixed(mc.max_tube_tightness, 4)),
                (
                    "tube ratio at the final time, ||e(T)||_P e^(λT) / ||e(0)||_P: median, 95%,"
                    " max (1 = the certified bound; below: λ is conservative)",
                    _quantile_text(data.summary.montecarlo.tube_ratio_at_T),
                ),
                (
                    "falsification: worst margin found",
                    margin(f.worst_margin, f.binding, 4),
                ),
                ("falsification: worst start", labelled(data.scenario, f.worst_x0)),
                ("falsification: closed-loop runs", str(f.evaluations)),
            ),
            "Margins",
        ),
        *stress_blocks,
    )


def inputs(data: ReportData) -> tuple:
    s = data.scenario
    index, starts = loop_figures.inputs_trajectory(data)
    label = data.law.label(index)  # "index: name", as controller.trajectories[index]
    if data.law.trajectories[index].name is None:  # a file without names: the demo by its start
        x0 = data.law.trajectories[index].x0
        label += f" (from {next((d.name for d in s.demos if np.allclose(d.x0, x0)), 'none')})"
    return (
        Paragraph(
            f"Reference trajectory {label} of controller.json (index from 0, as in "
            "controller.trajectories, and its demonstration): the one the "
            f"controller selects for the falsification's worst start "
            f"({labelled(s, starts[0])}). "
            "Closed-loop inputs are the controller's output before clipping, simulated here from "
            "controller.json."
        ),
        Figure(
            "inputs",
            "The optimized reference input u_ref (orange, held for Ts), the demonstration's input "
            "as flown (blue), and the closed-loop input from the worst start (teal) and from "
            "Init's corners assigned to this trajectory (thin teal), against the input bounds "
            "(dashed) and the operating region (dotted).",
            partial(loop_figures.draw_inputs, data=data),
            (FIGURE_WIDTH, 1.6 + 2.0 * s.m),
            data.fingerprint("montecarlo", file_hash(data.controller_path)),
        ),
    )
