"""Stage ``controller``: emit the lookup feedback controller ``controller.json``.

Format ``safety-controller/1`` (``emit_controller``; documented in the README and read by
``pipeline.controller``): the feedback ``K``, metric ``P`` and rate, and for every nominal
trajectory its demo's ``name``, start ``x0``, robustness radius, duration ``T``, held inputs
``u_ref (N, m)`` and states ``x_ref`` on a fine grid ``t`` (RK4 substeps), so that linear
interpolation error is negligible against the tube. Format ``safety-controller/2``
(``emit_funnel_controller``): the same per trajectory plus its funnel
(``pipeline.numerics.funnel.synthesis``): gains ``K (N, m, n)``, metrics ``P (N+1, n, n)`` at the
samples with ``Q = P^-1`` linear in t between them (``metric_interpolation: "inverse-linear"``),
``radius = rho`` and ``rate``; no ``feedback`` block. Its reference grid has
``REFERENCE_SUBSTEPS`` RK4 steps per sample, more on the sample intervals where the law's
tracking of the interpolated ``x_ref`` needs them to stay inside the certificate
(``pipeline.numerics.funnel.law``). The interpolation error is measured in the tube's
metric at the time, ``P(t)``.

The law after ``T`` (``pipeline.numerics.terminal.design``): an equilibrium at Goal's centre, its
LQR gain and the largest certified invariant ellipsoid. The ``terminal`` block is written only when
that ellipsoid holds every trajectory's end tube ``||x - x_ref(T)||_P <= radius e^{-lambda T}``;
otherwise the file has none, the law refuses ``t > T``, and the message says why. In a ``/2``
file the block also states ``disturbance``, the additive bound ``b (n,)`` its ellipsoid was
certified robustly invariant for (T1'; zeros: the exact model; (T7)'s box at the equilibrium when
the design held the parameter intervals in its hull); a funnel run that designed its
terminal controller before its funnels (``terminal.hold_design``, the funnels ending inside by
``synthesize_funnel(terminal=...)``) passes that design, else one is designed for the ends here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from pipeline.controller import FORMAT, FUNNEL_FORMAT, INVERSE_LINEAR, inverse_linear, load
from pipeline.io.artifacts import atomic_write_json
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate, simulate_graded
from pipeline.numerics.funnel.check import Funnel
from pipeline.numerics.funnel.law import BASE_SUBSTEPS
from pipeline.numerics.terminal.design import TerminalDesign, design_terminal
from pipeline.numerics.terminal.equilibrium import TerminalError
from pipeline.numerics.terminal.fit import end_levels
from pipeline.numerics.uncertainty import declared_bound, held_state_bounds
from pipeline.numerics.verify.recertify import ShippedFunnel, reference_substeps
from pipeline.results.controller import ControllerResult as ControllerResult
from pipeline.results.stage import Stage, StageInputs

REFERENCE_SUBSTEPS = BASE_SUBSTEPS  # the reference grid, finer where the funnel law needs it


def terminal_block(
    scenario: Scenario,
    K: FloatArray,
    P: FloatArray,
    ends: Sequence[FloatArray],
    end_radii: Sequence[float],
    period: float = 0.0,
    end_metrics: FloatArray | None = None,
    disturbance: FloatArray | None = None,
    design: TerminalDesign | None = None,
    held_period: float = 0.0,
    measurement: FloatArray | None = None,
) -> tuple[dict | None, float, str]:
    """The ``terminal`` block (None when there is none), the end tubes' fit and a sentence.

    Args:
      K: (m, n) tube gain; P: (n, n) tube metric; ends: ``x_ref_i(T_i) (n,)`` each; end_radii:
        ``radius_i e^{-lambda T_i}``, the end tubes' P-norm radii; end_metrics: (k, n, n) each
        end tube's own metric (a funnel's ``P_i[N]``) instead of ``P``.
      disturbance: (n,) the additive bound the ellipsoid must be robustly invariant for, written
        in the block (None: the exact model and no ``disturbance`` key, as in ``/1``).
      design: a terminal controller designed already (for that bound); only its fit is found.
      period: the constant certificate's held law (its held rate); held_period: a funnel
        file's, its hold an additive term ((T4) of ``pipeline.numerics.terminal.check``).
      measurement: (n,) the box of the error on the state the law sees ((T5); None: exact).
    """
    if design is None:
        try:
            design = design_terminal(
                scenario, K, P, ends, end_radii, period, end_metrics, disturbance, held_period,
                measurement,
            )  # fmt: skip
        except TerminalError as error:
            return None, np.inf, f"no terminal controller ({error}); the law refuses t > T"
    else:
        metrics = P if end_metrics is None else end_metrics
        needed = end_levels(design.P, design.x_eq, metrics, ends, end_radii)
        fit = float(np.sqrt(needed.max() / design.check.level))
        design = dataclasses.replace(design, fit=fit)
    where = np.round(design.x_eq, 3).tolist()
    if design.fit > 1:
        return (
            None,
            design.fit,
            (
                f"no terminal controller: the end tubes do not fit the certified invariant "
                f"ellipsoid at the equilibrium {where} (the worst needs {design.fit:.3g}x its "
                "radius; e.g. a fast arrival cannot be held in Goal: bound the speed at T with "
                "goal.bounds); the law refuses t > T"
            ),
        )
    block = {
        "x_eq": design.x_eq.tolist(),
        "u_eq": design.u_eq.tolist(),
        "K": design.K.tolist(),
        "P": design.P.tolist(),
        "level": design.check.level,
    }
    if design.disturbance is not None:  # the box (T7) held, the parameters in the hull
        block["disturbance"] = design.disturbance.tolist()
    elif disturbance is not None:
        block["disturbance"] = np.asarray(disturbance, dtype=np.float64).tolist()
    return (
        block,
        design.fit,
        (
            f"terminal controller ({design.gain} gain) at {where}: invariant ellipsoid certified "
            f"(decay {design.check.decay:.3g}/s on {design.check.vertices} hull vertices) holding "
            f"every end tube (at most {design.fit:.0%} of its radius)"
        ),
    )


def _reference(
    scenario: Scenario,
    x0: FloatArray,
    us: FloatArray,
    radius: float,
    substeps: int | np.ndarray,
    name: str | None = None,
) -> tuple[dict, FloatArray, FloatArray]:
    """The trajectory's entry (its demo's ``name`` when given, ``x0``, ``radius``, ``T``,
    ``u_ref``, ``t``, ``x_ref`` on the RK4 grid of ``substeps`` per sample, one number or
    ``(N,)``) and the error of interpolating that grid linearly: the midpoints' times ``(M,)``
    and errors ``(M, n)`` against a 2x finer simulation."""
    steps = np.broadcast_to(np.asarray(substeps, dtype=np.int64), (len(us),))
    fine = simulate_graded(scenario.dynamics, x0, us, scenario.Ts, steps)
    finer = simulate_graded(scenario.dynamics, x0, us, scenario.Ts, 2 * steps)
    mid = 0.5 * (fine.dense_xs[:-1] + fine.dense_xs[1:])
    item: dict[str, object] = {} if name is None else {"name": name}
    item |= {
        "x0": np.asarray(x0).tolist(),
        "radius": float(radius),
        "T": fine.duration,
        "u_ref": np.asarray(us).tolist(),
        "t": fine.dense_ts.tolist(),
        "x_ref": fine.dense_xs.tolist(),
    }
    return item, finer.dense_ts[1::2], mid - finer.dense_xs[1::2]


def _document(scenario: Scenario, version: str, trajectories: list[dict], **fields) -> dict:
    """The document's top level around ``trajectories``, then ``fields``."""
    return {
        "format": version,
        "scenario": scenario.name,
        "state_names": list(scenario.state_names),
        "input_names": list(scenario.input_names),
        "Ts": scenario.Ts,
        "input_bounds": {
            "lower": scenario.input_lower.tolist(),
            "upper": scenario.input_upper.tolist(),
        },
        **fields,
    } | {"trajectories": trajectories}


def uncertainty_block(scenario: Scenario, bound: FloatArray) -> dict:
    """The ``/2`` file's ``uncertainty``: the additive bound ``(n,)`` its funnels hold (what
    certify checks against the scenario's declaration) and, for people, what it came from (the
    declared box, the ellipsoid's semi-axes when one is declared, the parameter intervals)."""
    declared = scenario.uncertainty
    block = {
        "additive_bound": bound.tolist(),
        "disturbance": dict(zip(scenario.state_names, declared.declared_box.tolist(), strict=True)),
        "parameters": {name: list(interval) for name, interval in declared.parameters.items()},
    }
    if declared.ellipsoidal:  # held by its bounding box, inside additive_bound
        axes = zip(scenario.state_names, declared.ellipsoid.tolist(), strict=True)
        block["disturbance_ellipsoid"] = {name: a for name, a in axes if a > 0}
    if declared.measured:  # the law sees x + eta, |eta| <= E (funnel.law (I7)); certify checks
        block["measurement_bound"] = declared.measurement.tolist()
    return block


def _write(
    path: Path, document: dict, terminal: dict | None, terminal_message: str
) -> ControllerResult:
    """Write ``document`` (with ``terminal`` when there is one), read it back, say what it is."""
    if terminal is not None:
        document["terminal"] = terminal
    atomic_write_json(path, document)
    load(path)  # the file as emitted must validate
    count, worst = len(document["trajectories"]), document["interpolation_error_P_norm"]
    return ControllerResult(
        path=path,
        trajectories=count,
        interpolation_error=worst,
        success=True,
        message=f"{count} trajectories; x_ref interpolation error <= {worst:.1e} in P-norm",
        terminal=terminal is not None,
        terminal_message=terminal_message,
    )


def emit_controller(
    scenario: Scenario,
    K: FloatArray,
    P: FloatArray,
    rate: float,
    starts: Sequence[FloatArray],
    inputs: Sequence[FloatArray],
    radii: Sequence[float],
    path: Path,
    substeps: int = REFERENCE_SUBSTEPS,
    radius_floor: float | None = None,
    feedback_period: float = 0.0,
    names: Sequence[str] | None = None,
) -> ControllerResult:
    """Write ``controller.json`` (``safety-controller/1``) and read it back.

    Args:
      starts: ``(n,)`` each; inputs: ``(N_i, m)`` each; radii: P-norm robustness radii.
      K: (m, n) feedback gain; P: (n, n) contraction metric; rate: lambda (1/s).
      radius_floor: the radius that covers Init (the covering radius kept by the optimizer).
        When the end tubes do not fit the terminal ellipsoid, the radii are lowered to it
        (smaller balls, still covering Init: the certify stage re-checks) if that makes them fit.
      feedback_period: the zero-order-hold period ``h`` (s) the tube's ``rate`` was certified
        for (``pipeline.numerics.tube.sampled``; 0: continuous feedback).
      names: each trajectory's demo (``"demo_01"``), written as its ``name``; None: no names.
    """
    trajectories, worst, ends, end_radii = [], 0.0, [], []
    labels = [None] * len(starts) if names is None else list(names)
    for x0, us, radius, name in zip(starts, inputs, radii, labels, strict=True):
        item, _, error = _reference(scenario, x0, us, radius, substeps, name)
        worst = max(worst, float(np.sqrt(np.einsum("ki,ij,kj->k", error, P, error)).max()))
        ends.append(np.asarray(item["x_ref"][-1]))
        end_radii.append(float(radius) * float(np.exp(-rate * item["T"])))
        trajectories.append(item)
    document = _document(
        scenario,
        FORMAT,
        trajectories,
        feedback={"K": np.asarray(K).tolist(), "P": np.asarray(P).tolist(), "rate": rate},
        interpolation_error_P_norm=worst,
        feedback_period=feedback_period,
    )
    terminal, fit, terminal_message = terminal_block(
        scenario, K, P, ends, end_radii, feedback_period
    )
    if terminal is None and np.isfinite(fit) and radius_floor is not None:
        lowered = [min(float(r), radius_floor) for r in radii]
        decay = [np.exp(-rate * item["T"]) for item in trajectories]
        retry, _, message = terminal_block(
            scenario,
            K,
            P,
            ends,
            [r * d for r, d in zip(lowered, decay, strict=True)],
            feedback_period,
        )
        if retry is not None:
            for item, radius in zip(trajectories, lowered, strict=True):
                item["radius"] = radius
            terminal = retry
            terminal_message = f"{message}; radii lowered to the covering radius {radius_floor:.4g}"
    return _write(path, document, terminal, terminal_message)


def emit_funnel_controller(
    scenario: Scenario,
    trajectories: Sequence[Trajectory],
    funnels: Sequence[Funnel],
    path: Path,
    *,
    feedback_period: float = 0.0,
    substeps: int = REFERENCE_SUBSTEPS,
    names: Sequence[str] | None = None,
    disturbance: FloatArray | None = None,
    terminal: TerminalDesign | None = None,
) -> ControllerResult:
    """Write ``controller.json`` as ``safety-controller/2`` (one funnel per trajectory) and read
    it back.

    Args:
      trajectories: the nominals (``xs (N_i+1, n)``, ``us (N_i, m)`` each); funnels: their
        certified funnels (``synthesize_funnel``; ``K (N_i, m, n)``, ``P (N_i+1, n, n)``,
        ``rho``, ``rate``), in the same order.
      feedback_period: the law is held every ``h`` s (0: continuous), recorded in the file: the
        reference grid is chosen for its (I6) term (``pipeline.numerics.funnel.law``), the
        terminal ellipsoid certified for it ((T4) of ``terminal.check``).
      names: each trajectory's demo (``"demo_01"``), written as its ``name``; None: no names.
      disturbance: (n,) the additive bound the funnels hold (default: the scenario's declared
        uncertainty's, ``pipeline.numerics.uncertainty.additive_bound``);
        the terminal ellipsoid is certified robustly invariant for it and the block states it
        (None: zeros, the exact model).
      terminal: the terminal controller the funnels were made to end in (``hold_design``, for
        the same bound); None: one is designed here for the ends (``design_terminal``).

    Raises:
      ValueError: a funnel that was not certified (``success`` False), or whose shapes do not
        fit its trajectory.
    """
    if names is not None and len(names) != len(trajectories):
        raise ValueError(f"{len(names)} names for {len(trajectories)} trajectories")
    if disturbance is None:
        disturbance = declared_bound(scenario)  # as certify derives it
    measurement = scenario.uncertainty.measurement_box  # funnel.law (I7)
    items, worst, ends, end_radii, end_metrics = [], 0.0, [], [], []
    for i, (trajectory, funnel) in enumerate(zip(trajectories, funnels, strict=True)):
        N, n, m = len(trajectory.us), scenario.n, scenario.m
        if not funnel.success:
            raise ValueError(f"funnel {i} was not certified ({funnel.message}): not emitted")
        if funnel.K.shape != (N, m, n) or funnel.P.shape != (N + 1, n, n):
            raise ValueError(
                f"funnel {i}: K {funnel.K.shape}, P {funnel.P.shape} do not fit its trajectory "
                f"of N = {N} intervals; expected K ({N}, {m}, {n}), P ({N + 1}, {n}, {n})"
            )
        # the law tracks x_ref interpolated on this grid: fine enough where the funnel needs it
        # (pipeline.numerics.funnel.law), at least `substeps` per sample elsewhere
        nominal = simulate(
            scenario.dynamics, trajectory.xs[0], trajectory.us, scenario.Ts, BASE_SUBSTEPS
        )
        grid = np.maximum(
            substeps,
            reference_substeps(
                scenario,
                nominal,
                ShippedFunnel(K=funnel.K, P=funnel.P, rho=funnel.rho, rate=funnel.rate),
                held_state_bounds(scenario),
                disturbance,
                feedback_period,
                measurement,
            ),
        )
        name = None if names is None else names[i]
        item, times, error = _reference(
            scenario, trajectory.xs[0], trajectory.us, funnel.rho, grid, name
        )
        metric = inverse_linear(funnel.P, scenario.Ts, times)  # (M, n, n): P(t), eq. (F1)
        worst = max(worst, float(np.sqrt(np.einsum("ki,kij,kj->k", error, metric, error)).max()))
        item |= {"K": funnel.K.tolist(), "P": funnel.P.tolist(), "rate": funnel.rate}
        items.append(item)
        ends.append(np.asarray(item["x_ref"][-1]))
        end_radii.append(funnel.rho * float(np.exp(-funnel.rate * item["T"])))
        end_metrics.append(funnel.P[-1])
    document = _document(
        scenario,
        FUNNEL_FORMAT,
        items,
        metric_interpolation=INVERSE_LINEAR,
        interpolation_error_P_norm=worst,
        feedback_period=feedback_period,
        **(
            {} if disturbance is None else {"uncertainty": uncertainty_block(scenario, disturbance)}
        ),
    )
    first = funnels[0]  # the terminal design's "tube" candidate: the first funnel's end
    bound = np.zeros(scenario.n) if disturbance is None else np.asarray(disturbance, float)
    block, _, terminal_message = terminal_block(
        scenario, first.K[-1], first.P[-1], ends, end_radii, 0.0, np.stack(end_metrics), bound,
        terminal, held_period=feedback_period, measurement=measurement,
    )  # fmt: skip
    return _write(path, document, block, terminal_message)


# the Scenario fields either emission reads: the file's header, the reference grid, the terminal
EMITTED_FIELDS = (
    "Ts",
    "dynamics",
    "feedback",
    "goal",
    "goal_bounds",
    "input_lower",
    "input_upper",
    "name",
    "operating_region",
    "position_index",
    "state_bounds",
)


@dataclass(frozen=True, kw_only=True)
class ConstantControllerInputs(StageInputs):
    """What stage ``controller`` reads with the constant certificate: the feedback ``K (m, n)``,
    ``P (n, n)``, ``rate``; per kept trajectory its name, start ``(n,)``, inputs ``(N_i, m)``
    and radius; the radius floor, the feedback period and where to write (``path``)."""

    scenario_fields: ClassVar = EMITTED_FIELDS
    scenario: Scenario
    K: FloatArray
    P: FloatArray
    rate: float
    names: tuple[str, ...]
    starts: tuple[FloatArray, ...]
    inputs: tuple[FloatArray, ...]
    radii: tuple[float, ...]
    radius_floor: float
    feedback_period: float
    path: Path


def _constant_controller_stage(inputs: ConstantControllerInputs) -> ControllerResult:
    return emit_controller(
        inputs.scenario,
        inputs.K,
        inputs.P,
        inputs.rate,
        inputs.starts,
        inputs.inputs,
        inputs.radii,
        inputs.path,
        radius_floor=inputs.radius_floor,
        feedback_period=inputs.feedback_period,
        names=inputs.names,
    )


@dataclass(frozen=True, kw_only=True)
class FunnelControllerInputs(StageInputs):
    """What stage ``controller`` reads with the funnel certificate: per certified trajectory
    its name, final nominal and funnel; the feedback period, where to write (``path``), and the
    terminal controller the funnels were made to end in (None: one is designed for the ends)."""

    scenario_fields: ClassVar = (*EMITTED_FIELDS, "uncertainty", "unsafe")
    scenario: Scenario
    names: tuple[str, ...]
    trajectories: tuple[Trajectory, ...]
    funnels: tuple[Funnel, ...]
    feedback_period: float
    path: Path
    terminal: TerminalDesign | None = None


def _funnel_controller_stage(inputs: FunnelControllerInputs) -> ControllerResult:
    return emit_funnel_controller(
        inputs.scenario,
        inputs.trajectories,
        inputs.funnels,
        inputs.path,
        feedback_period=inputs.feedback_period,
        names=inputs.names,
        terminal=inputs.terminal,
    )


CONSTANT_CONTROLLER = Stage(
    "controller", _constant_controller_stage, ConstantControllerInputs, ControllerResult
)
FUNNEL_CONTROLLER = Stage(
    "controller", _funnel_controller_stage, FunnelControllerInputs, ControllerResult
)
