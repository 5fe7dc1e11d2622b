"""The report's section "Declared uncertainty" (only when the scenario declares one).

A scenario's ``uncertainty:`` block (``pipeline.model.uncertainty``) declares a gust box
``|d_i| <= D_i`` on the state derivatives (``D_i``: the declared box plus the semi-axis of a
declared gust ellipsoid ``sum (g_i / a_i)^2 <= 1``, whose term ``g`` is added), intervals
``[p_lo_j, p_hi_j]`` for parameters around the nominal values ``p0_j`` the nominals are flown
with, and a box ``|eta_i| <= E_i`` on the error of the state the law measures. The
certificates hold the first two as one additive term,

    x' = f(x, u, p0) + w,   |w_i| <= b_i = D_i + max |sum_j df_i/dp_j (p_j - p0_j)|     (U1)

derived by the pipeline (``pipeline.numerics.uncertainty``: outward-rounded interval arithmetic
over the parameter box and the box the tubes are kept in), not declared; the measurement error
enters the law's offset ((I7) of ``funnel.law``, (T5) of ``terminal.check``) instead.

Every number shown comes from the scenario as loaded (the declaration, and (U1) derived from it
by the function certify uses) or from this run's results: certify's check of ``controller.json``
(its disturbance multiple), the Monte Carlo result and the stress test's. Only what certify
proved is called certified; the stress test and the Monte Carlo are labelled as what they are.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.frozen import freeze_fields
from pipeline.model.scenario import Scenario
from pipeline.numerics.closed_loop.gusts import CORNER_SHARE, GUST_PERIOD, WORST_SHARE
from pipeline.numerics.hull import HullError
from pipeline.numerics.uncertainty import additive_bound, certified_box, parameter_bound
from pipeline.reporting.content import Paragraph, Table, number, percent
from pipeline.reporting.data import ReportData
from pipeline.reporting.numbers import runs_failed

TITLE = "Declared uncertainty"
MULTIPLE = "certify's disturbance multiple s"


@dataclass(frozen=True, kw_only=True, eq=False)
class DerivedBound:
    """The additive bound (U1) of a scenario's declaration, per state and by source (``n``
    states, ``q`` uncertain parameters); every entry the upper end of an outward-rounded
    interval (``pipeline.numerics.uncertainty``).

    Attributes:
      gust: (n,) ``D``, the declared disturbance box plus the declared ellipsoid's semi-axes
        (``Uncertainty.disturbance``).
      each: (q, n) each parameter's term alone, the others at their nominal values.
      parameters: (n,) all the parameters' term together, as it enters ``total``.
      total: (n,) ``b``, the bound the certificates hold (``additive_bound``, what certify
        derives again from the scenario).
    """

    gust: FloatArray
    each: FloatArray
    parameters: FloatArray
    total: FloatArray

    def __post_init__(self) -> None:
        freeze_fields(self)


def derived_bound(scenario: Scenario) -> DerivedBound:
    """(U1) for ``scenario``'s declaration over ``certified_box``; raises ``HullError`` when a
    variable the parameters' term depends on has no bound (the run's prechecks refuse that)."""
    u = scenario.uncertainty
    box = certified_box(scenario)
    each, nominal = [], u.parameter_nominal
    for j in range(len(u.parameter_names)):
        alone = np.arange(len(u.parameter_names)) == j  # parameter j's interval, the others at p0
        single = dataclasses.replace(
            u,
            parameter_lower=np.where(alone, u.parameter_lower, nominal),
            parameter_upper=np.where(alone, u.parameter_upper, nominal),
        )
        each.append(parameter_bound(single, box))
    return DerivedBound(
        gust=np.array(u.disturbance, dtype=np.float64),
        each=np.array(each).reshape(len(u.parameter_names), scenario.n),
        parameters=parameter_bound(u, box),
        total=additive_bound(scenario),
    )


def rate_unit(unit: str) -> str:
    """The unit of a state's derivative: ``m/s`` -> ``m/s^2``, ``m`` -> ``m/s``, none -> ``1/s``."""
    if not unit:
        return "1/s"
    return f"{unit[:-2]}/s^2" if unit.endswith("/s") else f"{unit}/s"


def _with(value: float, unit: str) -> str:
    return f"{number(value, 3)} {unit}".rstrip()


def _per_state(s: Scenario, values: FloatArray, symbol: str) -> str:
    """``|w_vX| <= 0.05 m/s^2, ...`` over the states where ``values (n,)`` is positive."""
    parts = [
        f"|{symbol}_{name}| <= {_with(float(v), rate_unit(s.unit(name)))}"
        for name, v in zip(s.state_names, values, strict=True)
        if v > 0
    ]
    return ", ".join(parts) or "0 in every state"


def declared_table(s: Scenario, bound: DerivedBound | None) -> Table:
    """One row per declared item: the gust per state, each parameter's interval and nominal, the
    measurement error per state, and what each contributes (``bound``: None when (U1) could
    not be derived)."""
    u = s.uncertainty
    rows: list[tuple[str, str, str, str]] = []
    box = u.declared_box
    for i, name in enumerate(s.state_names):
        if box[i] > 0:
            unit = rate_unit(s.unit(name))
            rows.append(
                (
                    f"gust on {name}'",
                    f"|d_{name}| <= {_with(float(box[i]), unit)}",
                    "0",
                    f"{_with(float(box[i]), unit)} to b_{name}, as declared",
                )
            )
    axes = [
        (name, _with(float(a), rate_unit(s.unit(name))))
        for name, a in zip(s.state_names, u.ellipsoid, strict=True)
        if a > 0
    ]
    if axes:  # sum (g_i / a_i)^2 <= 1, held by its bounding box |g_i| <= a_i
        rows.append(
            (
                "gust ellipsoid on " + ", ".join(f"{name}'" for name, _ in axes),
                " + ".join(f"(g_{name} / {a})^2" for name, a in axes) + " <= 1",
                "0",
                "held by its bounding box: " + ", ".join(f"{a} to b_{name}" for name, a in axes),
            )
        )
    for j, name in enumerate(u.parameter_names):
        unit = f" {s.unit(name)}" if s.unit(name) else ""
        lo, hi = float(u.parameter_lower[j]), float(u.parameter_upper[j])
        effect = (
            "not derived"
            if bound is None
            else f"alone (the others nominal): {_per_state(s, bound.each[j], 'Δf')}"
        )
        rows.append(
            (
                f"parameter {name} (constant, unknown)",
                f"[{number(lo, 4)}, {number(hi, 4)}]{unit}",
                f"{number(float(u.parameter_nominal[j]), 4)}{unit}",
                effect,
            )
        )
    for i, name in enumerate(s.state_names):
        if u.measurement[i] > 0:
            unit = f" {s.unit(name)}" if s.unit(name) else ""
            rows.append(
                (
                    f"measurement error on {name}",
                    f"|eta_{name}| <= {number(float(u.measurement[i]), 3)}{unit}",
                    "0 (exact)",
                    "the law sees x + eta: held in the law's offset (I7) and the terminal "
                    "check (T5), not in the additive bound",
                )
            )
    return Table(
        ("declared", "bound", "nominal", "what it contributes"),
        tuple(rows),
        "Declared in the scenario file's uncertainty block. A gust d is any signal inside its "
        "box (and g inside its ellipsoid, added to d), in the unit of the state's derivative; "
        "a parameter's true value "
        "is any in its interval (the nominal trajectories are flown with the nominal value); a "
        "measurement error is in the state's unit. Contributions are upper bounds derived by "
        "the pipeline (Δf: the change of the derivative f(x, u, p) - f(x, u, p0) over the box "
        "the certificates keep their tubes in)",
        stack=True,
    )


def bound_table(s: Scenario, bound: DerivedBound) -> Table:
    """Per state with a positive bound: the gust, the parameters' term and ``b``."""
    rows = tuple(
        (
            s.label(name),
            _with(float(bound.gust[i]), rate_unit(s.unit(name))),
            _with(float(bound.parameters[i]), rate_unit(s.unit(name))),
            _with(float(bound.total[i]), rate_unit(s.unit(name))),
        )
        for i, name in enumerate(s.state_names)
        if bound.total[i] > 0
    )
    zero = [name for name, b in zip(s.state_names, bound.total, strict=True) if b == 0]
    return Table(
        ("state", "gust D_i", "parameters' term", "additive bound b_i"),
        rows,
        "The additive bound the certificates hold, |w_i| <= b_i in x' = f(x, u, p0) + w: "
        "derived by the pipeline, not declared, as b_i = D_i (the declared box plus a declared "
        "ellipsoid's semi-axis) + max |Σ_j ∂f_i/∂p_j (p_j - p0_j)| over the parameter box and "
        "the box the tubes are kept in (state bounds, the operating region, the input bounds), "
        "in outward-rounded interval arithmetic ((U1), mean value theorem)"
        + (f"; b = 0 for {', '.join(zero)}" if zero else ""),
        numeric=(False, True, True, True),
    )


def _multiple_row(data: ReportData) -> tuple[str, str, str]:
    """Certify's disturbance multiple: what it proved, or why there is none."""
    check = data.certification
    multiple = check.disturbance_multiple
    if not data.funnel or not math.isfinite(multiple):
        return (
            MULTIPLE,
            "not computed",
            "certify computes it for funnel files (safety-controller/2) only",
        )
    held = "certified" if check.success and multiple >= 1 else "not certified"
    at_b = [
        "the input caps",
        *(("the measurement box",) if data.scenario.uncertainty.measured else ()),
        *(("the terminal controller",) if data.law.terminal is not None else ()),
    ]
    return (
        MULTIPLE,
        f"{number(multiple, 4)} × b",
        f"{held}{'' if check.success else ' (controller.json is not certified)'}: the shipped "
        f"funnels' invariance inequality (I5) still holds with {number(multiple, 4)} times the "
        "additive bound b (the largest such s, by bisection in certify); only (I5) is checked "
        f"at s × b, {' and '.join([', '.join(at_b[:-1]), at_b[-1]] if len(at_b) > 1 else at_b)} "
        "at the declaration itself",
    )


def _stress_row(data: ReportData) -> tuple[str, str, str]:
    """The stress test beyond the declaration, labelled not certified."""
    stress = data.stress
    if stress is None:
        return ("stress test", "not run", "synthesize --stress flies the declaration widened")
    if stress.beyond_declared is None:
        return (
            "stress test",
            "from the scenario's stress block",
            "not certified; not of the declared uncertainty (section Monte Carlo validation)",
        )
    run, open_loop = stress.with_feedback, stress.without_feedback
    factor = number(stress.beyond_declared, 3)
    return (
        f"stress test: {factor} × the declaration",
        f"{percent(run.failed_fraction)} of {run.samples} runs failed",
        f"not certified (sampled, no bound): every run drew from the declared boxes and "
        f"intervals widened {factor} times about the nominal, as the Monte Carlo draws the "
        f"declared ones; without the feedback (K = 0) {percent(open_loop.failed_fraction)} "
        "failed",
    )


def _sampling(data: ReportData) -> Paragraph:
    """How the Monte Carlo drew the declared uncertainty, with the run's numbers."""
    s, mc = data.scenario, data.montecarlo
    u = s.uncertainty
    worst = mc.falsification.worst_draws
    period = GUST_PERIOD if worst is None else worst.period
    drawn = []
    if u.parameter_names:
        drawn.append(
            f"the parameters {', '.join(u.parameter_names)} uniformly from their intervals, "
            "constant over the run"
        )
    pushed = [name for name, d in zip(s.state_names, u.disturbance, strict=True) if d > 0]
    if pushed:
        derivatives = ", ".join(f"{name}'" for name in pushed)
        inside = (
            "its box" if not u.ellipsoidal else "the declared box plus the ellipsoid's bounding box"
        )
        drawn.append(
            f"a gust on {derivatives} uniform in {inside}, piecewise constant with a "
            f"new value every {period:g} s"
        )
    if u.measured:
        drawn.append(f"a measurement error uniform in its box, on the same {period:g} s periods")
    corners = (
        f"on average {CORNER_SHARE:.0%} of the runs fly bang-bang at random corners of the "
        f"boxes and intervals and {WORST_SHARE:.0%} the falsification's worst bang-bang case "
        f"(its search: {mc.falsification.evaluations} closed-loop runs)"
        if worst is not None
        else f"on average {CORNER_SHARE + WORST_SHARE:.0%} of the runs fly bang-bang at random "
        "corners of the boxes and intervals (the falsification search kept no worst case)"
    )
    failed = len(mc.failed_x0)
    return Paragraph(
        f"Monte Carlo validation: each of the {mc.samples} closed-loop runs (seed {mc.seed}) "
        f"drew {'; '.join(drawn)}; {corners}. {runs_failed(mc.samples, failed)}: statistically "
        f"validated (failure probability ≤ {mc.failure_bound:.2e}, one-sided 95%), not "
        "certified."
    )


def section(data: ReportData) -> tuple:
    """The section's blocks (``data.scenario`` declares an uncertainty)."""
    s, check = data.scenario, data.certification
    try:
        bound: DerivedBound | None = derived_bound(s)
    except HullError as error:
        bound = None
        note = f"The additive bound could not be derived: {error}."
    held = "certify re-checked controller.json under it: " + (
        "certified" if check.success else "not certified"
    )
    stated = data.law.disturbance_bound
    if bound is not None:
        note = (
            f"The certificates hold x' = f(x, u, p0) + w with {_per_state(s, bound.total, 'w')} "
            f"(the additive bound b below, derived by the pipeline from the declaration); {held}."
        )
        if stated is not None and np.any(np.asarray(stated) > bound.total):
            note += (
                f" controller.json states {_per_state(s, np.asarray(stated), 'w')}; certify "
                "checks the larger of the two in each state."
            )
    if check.terminal_box:  # (T7) of pipeline.numerics.terminal.check: set only when it held
        box = _per_state(s, np.asarray(check.terminal_box), "w")
        note += (
            " The terminal ellipsoid holds the parameters another way (T7): their intervals "
            "as variables of its Jacobian hull, and in its additive box only the gust and "
            f"their shift at the hover, {box}; certify re-checked it so."
        )
    return (
        Paragraph(
            "What the certificates are held to besides the nominal model: the true system is "
            "x' = f(x, u, p) + d with the law measuring x + eta, for every gust d, parameter "
            "value p and measurement error eta declared below"
            + (" (d: the box's gust plus the ellipsoid's g)" if s.uncertainty.ellipsoidal else "")
            + ("" if s.uncertainty.measured else " (no measurement error declared: eta = 0)")
            + f". {note}"
        ),
        declared_table(s, bound),
        *((bound_table(s, bound),) if bound is not None else ()),
        Table(
            ("margin", "value", "what it is"),
            (_multiple_row(data), _stress_row(data)),
            "Beyond the declaration: how much more the certificate holds (certify) and what "
            "sampling found beyond it (stress test)",
        ),
        _sampling(data),
    )
