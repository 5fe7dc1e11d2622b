"""Stage ``certify``: the final, independent check of ``controller.json`` as it ships.

Every "certified" claim of a run comes from here. The file is read back with
``pipeline.controller.load`` (the reader users run) and re-verified against the scenario, using
nothing but the file and the scenario (no stage result). A ``safety-controller/1`` file (one
``K``, ``P``, rate):

1. the file is for this scenario: state and input names, ``Ts`` and input bounds agree;
2. the metric: ``P = P^T`` with ``lambda_min(P) > 0``;
3. the contraction inequality at every vertex ``[A_v B_v]`` of a sound hull of the Jacobians
   over the operating region (``pipeline.numerics.hull``, rebuilt from the scenario):

       lambda_max((A_v + B_v K)^T P + P (A_v + B_v K) + 2 lambda P) < 0,                (C)

   eigenvalues by numpy (``pipeline.numerics.tube.contraction``, as the designer's check), which
   gives ``||e(t)||_P <= e^{-lambda t} ||e(0)||_P`` while the state and input stay in the
   region. With ``feedback_period h > 0`` (the law held for ``h`` seconds) the file's rate must
   instead be at most ``lambda_h``, the held law's rate (``pipeline.numerics.tube.sampled``) from
   the largest rate (C) certifies at the vertices, and ``h`` must divide ``Ts``;
4. each trajectory's reference ``x_ref`` is the scenario's dynamics simulated from its ``x0``
   under its ``u_ref`` (to ``REFERENCE_TOLERANCE`` in P-norm per unit radius), its linear
   interpolation (what the law tracks) is within ``INTERPOLATION_TOLERANCE`` radius of the
   dynamics on a finer grid, the file's ``interpolation_error_P_norm`` (the Monte Carlo's slack)
   agrees with that measurement within ``STATED_ERROR_RANGE``, and its radius is
   at most the largest radius whose tube ``||x - x_ref(t)||_P <= r e^{-lambda t}`` avoids
   Unsafe, keeps the inputs in their bounds and the tube in the operating region and the
   scenario's ``state_bounds``, and ends in Goal, on the dense grid with a bound between grid
   points (``pipeline.numerics.tube.radius``);
5. Init is covered by the initial balls ``||x - x0_i||_P <= radius_i`` (sound box subdivision,
   ``pipeline.numerics.verify.cover``), each box's corners within ``1 - COVER_MARGIN`` of a ball's
   squared radius;
6. the optional ``terminal`` block (``pipeline.numerics.terminal.check``): ``V = e^T P_T e``
decreases
   on ``V <= level`` at every vertex of a sound hull over its bounding box (numpy eigenvalues,
   (T1') with the equilibrium's residual and the scenario's declared additive bound, or the
   file's ``disturbance`` where larger; a file stating less than the declaration fails), the
   law does not clip there, the ellipsoid lies in
   Goal and in the ``state_bounds``, and it holds every end tube ``||x - x_ref(T)||_P <= radius
   e^{-lambda T}`` (exact S-procedure containment). Then "safe for all time" is certified;
   without the block the law refuses ``t > T``, and a scenario with ``terminal: hold`` is not
   certified.

A ``safety-controller/2`` file (a funnel per trajectory: ``K_i[k]``, ``P_i[k]``, ``rho_i =
radius_i``) replaces steps 2-3 and the radius of step 4: each funnel is rebuilt from the file's
``x_ref``, ``u_ref``, ``K``, ``P``, ``radius`` and the scenario's state and input bounds
(``pipeline.numerics.verify.recertify``: local sound hulls per sample interval, then
``funnel.check.check_funnel``: ``P[k] > 0``, the vertex inequalities (F3) at both ends of every
interval by numpy eigenvalues, the tube in Unsafe's clearance, the inputs and state bounds, and
``E(T)`` in Goal). The law tracks ``x_ref`` interpolated on the file's grid: its error bound
enters the inequality and the inputs (``pipeline.numerics.funnel.law`` (I1)-(I3)), so the proof
covers the law as shipped; the grid may be finer on some sample intervals than on others. Margins:
(F2) plus that term below ``-LMI_MARGIN``, each level within ``1 - LEVEL_MARGIN`` of its limits,
and the RK4 error of ``x_ref`` (estimated against a grid twice as fine) below ``LEVEL_MARGIN``
radius (both 1e-6: far above rounding, and the integration error is checked against it). The
reference checks of step 4 measure in the tube's metric at the time, ``P_i(t)``; step 5
covers Init by the balls ``||x - x0_i||_{P_i[0]} <= radius_i``; step 6's end tubes are
``||x - x_ref_i(T)||_{P_i[N]} <= radius_i e^{-rate_i T}``. With ``feedback_period h > 0`` (the
law held for ``h`` seconds) ``h`` must divide ``Ts``, each funnel is re-checked for the held law
(its offset (I6) of ``pipeline.numerics.funnel.law`` in the inequality and the inputs, with the
checked additive bound in ``Edot``), and the terminal block for the held terminal law (its hold
an additive term, (T4) of ``pipeline.numerics.terminal.check``).

Declared uncertainty (the scenario's ``uncertainty:``). The funnels are re-checked for ``x' =
f(x, u) + w``, ``|w| <= b``, with ``b`` derived here from the scenario's declaration
(``pipeline.numerics.uncertainty`` (U1)) and raised to the file's ``uncertainty.additive_bound``
where that is larger: (F2) joined with the disturbance by the S-procedure must keep its margin
(``pipeline.numerics.funnel.robust`` (I5)). A declared measurement error ``|eta| <= E``
(``uncertainty.measurement``) is re-checked likewise: ``E`` from the scenario, raised to the
file's ``uncertainty.measurement_bound`` where larger, in the law's offset and (I5)'s box
(``funnel.law`` (I7)) and in the terminal check ((T5)). A file that holds less than the scenario
declares, or a ``/1`` file for a scenario that declares any uncertainty, is not certified.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.controller import Controller, ControllerFormatError, load
from pipeline.io.artifacts import file_hash
from pipeline.model.limits import divides
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.law import LEVEL_MARGIN, LMI_MARGIN
from pipeline.numerics.hull import DEFAULT_SEGMENTS, HullError, JacobianHull, jacobian_hull
from pipeline.numerics.tube.contraction import contraction_margin, contraction_rate
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.tube.radius import radius_limits
from pipeline.numerics.tube.sampled import held_rate
from pipeline.numerics.uncertainty import held_state_bounds
from pipeline.numerics.verify.cover import DEFAULT_DEPTH, subdivide
from pipeline.numerics.verify.declared import checked_bound, checked_measurement, terminal_claim
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS
from pipeline.numerics.verify.recertify import ShippedFunnel, recheck_funnel
from pipeline.numerics.verify.reference import ReferenceCheck, check_reference
from pipeline.numerics.verify.terminal import recheck_terminal
from pipeline.results.certify import CertificationResult as CertificationResult

REFERENCE_TOLERANCE = 1e-9  # ||x_ref - simulated||_P / radius
RADIUS_TOLERANCE = 1e-12  # relative: a radius may exceed the re-verified one by rounding only
ROUNDING_MARGIN = 1e-9  # times ||P||: the contraction eigenvalue must clear rounding
INTERPOLATION_TOLERANCE = 1e-2  # ||interpolated x_ref - dynamics||_P / radius
STATED_ERROR_RANGE = (0.5, 4.0)  # the file's interpolation_error_P_norm / the one measured here
# Init's corners must lie within this fraction of a ball's squared radius: floating-point rounding
# of the quadratic form (~1e-15 relative) cannot decide coverage
COVER_MARGIN = 1e-6


def _feedback(controller: Controller) -> tuple[np.ndarray, np.ndarray, float]:
    """``(P (n, n), K (m, n), rate)`` of a ``/1`` file's ``feedback`` block (``load`` requires
    it; a ``TypeError``, not an ``assert`` that ``python -O`` would drop, if it is missing)."""
    if controller.P is None or controller.K is None or controller.rate is None:
        raise TypeError(f"{controller.source}: no feedback block (P, K, rate): not a /1 file")
    return controller.P, controller.K, controller.rate


def _divides(controller: Controller) -> list[str]:
    """The file's ``feedback_period`` divides ``Ts`` (a held law's windows start at every
    sample), or why not."""
    h = controller.feedback_period
    if not divides(h, controller.Ts):
        return [f"feedback_period {h:g} s does not divide Ts {controller.Ts:g} s"]
    return []


def _held(controller: Controller, A: np.ndarray, B: np.ndarray) -> list[str]:
    """Step 3 for held feedback: ``h`` divides ``Ts`` and the file's rate is at most
    ``lambda_h`` (from the largest rate (C) certifies at the vertices ``A (V, n, n)``, ``B (V, n,
    m)``)."""
    P, K, file_rate = _feedback(controller)
    h = controller.feedback_period
    if _divides(controller):
        return _divides(controller)
    rate = contraction_rate(P, K, A, B)
    held = held_rate(P, K, A, B, rate, h)
    if not file_rate <= held.held_rate:
        return [
            f"the rate {file_rate:g} exceeds {held.held_rate:.4g}, the tube rate of the "
            f"law held every {h:g} s (continuous rate {rate:.4g})"
        ]
    return []


def verify_terminal(scenario: Scenario, controller: Controller) -> tuple[float, float, list[str]]:
    """Step 6: ``(decay, fit, failures)`` of the file's terminal block
    (``verify.terminal.recheck_terminal``: (T1') under the declared bound, the end tubes inside)."""
    return recheck_terminal(scenario, controller)


def contraction_bound(controller: Controller) -> float:
    """What the largest contraction eigenvalue must be below: ``-ROUNDING_MARGIN ||P||`` (at
    least ``ROUNDING_MARGIN``) for a ``/1`` file, ``-LMI_MARGIN`` (the (F2) eigenvalue plus the
    law's terms, ``funnel.law``) for a ``/2`` file."""
    if controller.funnel or controller.P is None:
        return -LMI_MARGIN
    return -ROUNDING_MARGIN * max(1.0, float(np.linalg.norm(controller.P, 2)))


def _same_scenario(scenario: Scenario, controller: Controller) -> list[str]:
    """Where the file's names, ``Ts`` and input bounds disagree with the scenario's."""
    problems = []
    if controller.state_names != tuple(scenario.state_names):
        problems.append(f"state_names {list(controller.state_names)} != {scenario.state_names}")
    if controller.input_names != tuple(scenario.input_names):
        problems.append(f"input_names {list(controller.input_names)} != {scenario.input_names}")
    if controller.Ts != scenario.Ts:
        problems.append(f"Ts {controller.Ts:g} != the scenario's sampling_time {scenario.Ts:g}")
    if not (
        np.array_equal(controller.lower, scenario.input_lower)
        and np.array_equal(controller.upper, scenario.input_upper)
    ):
        problems.append("input_bounds differ from the scenario's")
    return [f"the file is not for this scenario: {p}" for p in problems]


def contraction_check(
    scenario: Scenario, P: np.ndarray, K: np.ndarray, rate: float, segments: int
) -> tuple[float, JacobianHull]:
    """Step 3: the largest eigenvalue of (C)'s left side over the vertices of a sound Jacobian
    hull over the operating region, rebuilt here (``HullError`` if there is none), and the hull."""
    hull = jacobian_hull(scenario.dynamics, scenario.operating_region, segments)
    return contraction_margin(P, K, hull.A, hull.B, rate), hull


def _constant(
    scenario: Scenario, controller: Controller, failures: list[str], segments: int
) -> tuple[float, int, list[float], tuple[float, float]]:
    """Steps 2-4 for a ``/1`` file: ``(contraction margin, vertices, verified radii, (reference
    error, interpolation error))``; what fails is appended to ``failures``."""
    P, K, rate = _feedback(controller)
    # 2. The metric.
    metric = float(np.linalg.eigvalsh(P)[0])
    if not metric > 0:
        failures.append(f"P is not positive definite (smallest eigenvalue {metric:.3g})")

    # 3. Contraction (C) at every vertex of a sound Jacobian hull over the operating region.
    try:
        margin, hull = contraction_check(scenario, P, K, rate, segments)
        vertices = len(hull.vertices)
    except HullError as error:
        margin, vertices = float("nan"), 0
        failures.append(f"no Jacobian hull over the operating region: {error}")
    if controller.feedback_period > 0 and vertices:
        failures += _held(controller, hull.A, hull.B)
    # strictly below zero by more than floating-point rounding of M and of the hull's vertices
    if not margin < contraction_bound(controller):
        failures.append(
            f"the contraction inequality fails at rate {rate:g}: largest eigenvalue "
            f"{margin:.3g} >= {contraction_bound(controller):.1g} over {vertices} hull vertices"
        )

    # 4. Each reference and its radius, in the file's tube.
    tube = Tube(
        K=K,
        P=P,
        rate=rate,
        region=scenario.operating_region,
        state_names=scenario.state_names,
        input_names=scenario.input_names,
        position_index=scenario.position_index,
    )
    verified, errors = [], (0.0, 0.0)
    for i, tr in enumerate(controller.trajectories):
        errors, reference = _reference(scenario, controller, i, failures, errors)
        if reference.substeps is None:
            verified.append(0.0)
            continue
        nominal = simulate(scenario.dynamics, tr.x0, tr.u_ref, scenario.Ts, VERIFY_SUBSTEPS)
        limits = radius_limits(scenario, tube, nominal)
        verified.append(limits.radius)
        if not tr.radius <= limits.radius * (1 + RADIUS_TOLERANCE):
            binding = min(limits.limits, key=lambda key: limits.limits[key][0])
            failures.append(
                f"trajectories[{i}]: radius {tr.radius:.6g} > {limits.radius:.6g}, the largest "
                f"the tube allows ({binding} binds at t = {limits.limits[binding][1]:.2f} s)"
            )
    return margin, vertices, verified, errors


def _funnels(
    scenario: Scenario, controller: Controller, failures: list[str]
) -> tuple[float, int, list[float], tuple[float, float], float]:
    """Steps 2-4 for a ``/2`` file, each funnel rebuilt from the file and re-checked
    (``pipeline.numerics.verify.recertify``): ``(largest (F2) eigenvalue, vertices, verified levels,
    (reference error, interpolation error), the largest multiple of the disturbance checked
    that every funnel holds)``; what fails is appended to ``failures``."""
    period = controller.feedback_period
    if period > 0:
        failures += _divides(controller)
    disturbance, short = checked_bound(scenario, controller.disturbance_bound, "uncertainty")
    failures += short
    measurement, short = checked_measurement(scenario, controller.measurement_bound)
    failures += short
    margin, vertices, verified, errors = -np.inf, 0, [], (0.0, 0.0)
    multiple = float("inf")
    for i, tr in enumerate(controller.trajectories):
        errors, reference = _reference(scenario, controller, i, failures, errors)
        if reference.substeps is None or reference.nominal is None:
            verified.append(0.0)
            continue
        shipped = ShippedFunnel(K=tr.K, P=tr.P, rho=tr.radius, rate=tr.rate)
        check = recheck_funnel(
            scenario, reference.nominal, shipped, held_state_bounds(scenario), reference.substeps,
            centre_error=reference.integration * tr.radius, disturbance=disturbance,
            period=period, measurement=measurement, enough=multiple,
        )  # fmt: skip
        margin, vertices = max(margin, check.margin), vertices + check.vertices
        multiple = min(multiple, check.disturbance_multiple)
        verified.append(check.radius)
        if check.failure is not None:
            failures.append(f"trajectories[{i}]: the funnel is not certified: {check.failure}")
    return margin, vertices, verified, errors, multiple


def _reference(
    scenario: Scenario,
    controller: Controller,
    i: int,
    failures: list[str],
    errors: tuple[float, float],
) -> tuple[tuple[float, float], ReferenceCheck]:
    """Step 4's reference checks of trajectory ``i`` in its tube metric ``P_i(t)``
    (``verify.reference.check_reference``). Returns ``(largest (reference error, interpolation
    error) so far, the check: the file grid's RK4 steps on each sample interval (None: not an
    RK4 grid) and the estimated RK4 error)``."""
    tr = controller.trajectories[i]
    check = check_reference(scenario, tr, controller.Ts, VERIFY_SUBSTEPS)
    if check.substeps is None:
        failures.append(
            f"trajectories[{i}]: t is not an RK4 grid of the samples (every sample time, equal "
            "steps inside each sample interval)"
        )
        return errors, check
    if not check.error <= REFERENCE_TOLERANCE:
        failures.append(
            f"trajectories[{i}]: x_ref is not the dynamics under u_ref from x0 "
            f"(P-norm error {check.error:.3g} radius)"
        )
    if controller.funnel and not check.integration <= LEVEL_MARGIN:
        failures.append(
            f"trajectories[{i}]: the RK4 error of x_ref is estimated at {check.integration:.3g} "
            f"radius, not below the level margin {LEVEL_MARGIN:g} that must absorb it"
        )
    if not check.interpolation <= INTERPOLATION_TOLERANCE * tr.radius:
        failures.append(
            f"trajectories[{i}]: the interpolated x_ref is {check.interpolation / tr.radius:.3g} "
            f"radius from the dynamics (> {INTERPOLATION_TOLERANCE:g}): the controller stage's "
            "grid is too coarse for these dynamics (a bug of the pipeline; please report it)"
        )
    errors = (max(errors[0], check.error), max(errors[1], check.interpolation))
    return errors, check


def certify_controller(
    scenario: Scenario,
    path: Path,
    *,
    segments: int = DEFAULT_SEGMENTS,
    max_depth: int = DEFAULT_DEPTH,
) -> CertificationResult:
    """Re-verify the emitted ``controller.json`` at ``path`` against ``scenario`` (steps 1-5 of
    the module docstring); ``success`` only when every check passes. No check is an ``assert``:
    the outcome is the same under ``python -O`` (``tests/stages/test_certify.py`` runs there)."""
    path = Path(path)

    def refused(sha256: str, failures: list[str]) -> CertificationResult:
        return CertificationResult(
            path=path,
            sha256=sha256,
            metric_eigenvalue=float("nan"),
            contraction_margin=float("nan"),
            vertices=0,
            radii=(),
            verified_radii=(),
            reference_error=float("nan"),
            covered_fraction=0.0,
            failures=tuple(failures),
            success=False,
            message="; ".join(failures),
        )

    try:
        controller = load(path)
        sha256 = file_hash(path)
    except (OSError, ControllerFormatError) as error:
        return refused("", [f"controller.json cannot be certified: {error}"])
    failures = _same_scenario(scenario, controller)
    if failures:
        return refused(sha256, failures)
    multiple = float("nan")  # of the declared uncertainty the funnels hold (no declaration: nan)
    if controller.funnel:
        margin, vertices, verified, (reference_error, interpolation), robust = _funnels(
            scenario, controller, failures
        )
        if not scenario.uncertainty.empty:
            multiple = robust
    else:
        if not scenario.uncertainty.empty:
            failures.append(
                "uncertainty: the scenario declares disturbance, parameter or measurement bounds, "
                "which a constant certificate (/1) does not hold; synthesize with certificate: "
                "funnel"
            )
        margin, vertices, verified, (reference_error, interpolation) = _constant(
            scenario, controller, failures, segments
        )
    metric = min(float(np.linalg.eigvalsh(tr.P).min()) for tr in controller.trajectories)

    # The Monte Carlo allows twice the stated interpolation error as tube slack: it must be
    # the error this check measures, neither understated nor inflated.
    low, high = STATED_ERROR_RANGE
    stated = controller.interpolation_error
    if not low * interpolation - 1e-12 <= stated <= high * interpolation + 1e-9:
        failures.append(
            f"interpolation_error_P_norm: the file states {stated:.3g}, measured "
            f"{interpolation:.3g} (expected {low:g}x to {high:g}x of it)"
        )

    # 5. Coverage of Init by the file's initial balls.
    cover = subdivide(
        np.stack([tr.P[0] for tr in controller.trajectories]),  # each ball's metric at t = 0
        scenario.init_lower,
        scenario.init_upper,
        np.stack([tr.x0 for tr in controller.trajectories]),
        np.array([tr.radius for tr in controller.trajectories]),
        max_depth,
        margin=COVER_MARGIN,
    )
    if not cover.covered:
        failures.append(
            f"Init is not covered by the file's balls ({cover.fraction:.1%} certified covered)"
        )

    # 6. The terminal controller, when the file has one.
    decay = fit = float("nan")
    terminal_box: tuple[float, ...] = ()
    if controller.terminal is not None:
        decay, fit, problems = verify_terminal(scenario, controller)
        failures += problems
        box, parameters, _ = terminal_claim(scenario, controller.terminal)
        if not problems and parameters is not None and box is not None:  # certified by (T7)
            terminal_box = tuple(map(float, box))
    elif scenario.terminal == "hold":
        failures.append(
            "the scenario asks terminal: hold but controller.json has no terminal controller "
            "(the end tubes do not fit a certified invariant ellipsoid in Goal: tighten the "
            "speed bounds at T in goal.bounds)"
        )
    after = (
        f"; after T: terminal ellipsoid invariant (decay {decay:.3g}/s) and holding every end "
        f"tube (at most {fit:.0%} of its radius)"
        if controller.terminal is not None
        else "; no terminal controller (the law refuses t > T)"
    )

    success = not failures
    held = (
        f" with the law held every {controller.feedback_period:g} s"
        if controller.feedback_period > 0
        else ""
    )
    if controller.funnel:
        what = (
            f"{len(verified)} funnels (K[k], P[k], Q = P^-1 linear in t) rebuilt: P[k] > 0, "
            f"the funnel inequality dV/dt <= -2 rate V (F2){held} on {vertices} local hull "
            f"vertices (margin {margin:.1e}, < 0: holds), levels within their constraints"
        )
    else:
        what = (
            f"P > 0, contraction at rate {controller.rate:g}{held} on {vertices} hull vertices "
            f"(margin {margin:.1e}, < 0: holds), {len(verified)} radii within their tubes"
        )
    if np.isfinite(multiple):
        what += f", robust to {multiple:.3g}x the declared uncertainty (its additive bound)"
    message = (
        f"controller.json re-verified: {what}, Init covered" + after
        if success
        else "controller.json is not certified: " + "; ".join(failures)
    )
    return CertificationResult(
        path=path,
        sha256=sha256,
        metric_eigenvalue=metric,
        contraction_margin=margin,
        vertices=vertices,
        radii=tuple(tr.radius for tr in controller.trajectories),
        verified_radii=tuple(verified),
        reference_error=reference_error,
        covered_fraction=cover.fraction,
        failures=tuple(failures),
        success=success,
        message=message,
        terminal=controller.terminal is not None,
        terminal_decay=decay,
        terminal_fit=fit,
        terminal_box=terminal_box,
        contraction_bound=contraction_bound(controller),
        disturbance_multiple=multiple,
    )
