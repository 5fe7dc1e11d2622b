"""Stage ``controller``: emit the lookup feedback controller ``controller.json``.

Format ``safety-controller/1`` (documented in the README and read by ``pipeline.controller``):
the feedback ``K``, metric ``P`` and rate, and for every nominal trajectory its start ``x0``,
robustness radius, duration ``T``, held inputs ``u_ref (N, m)`` and states ``x_ref`` on a fine
grid ``t`` (RK4 substeps), so that linear interpolation error is negligible against the tube.

The law after ``T`` (``pipeline.numerics.terminal``): an equilibrium at Goal's centre, its LQR
gain and the largest certified invariant ellipsoid. The ``terminal`` block is written only when
that ellipsoid holds every trajectory's end tube ``||x - x_ref(T)||_P <= radius e^{-lambda T}``;
otherwise the file has none, the law refuses ``t > T``, and the message says why.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.controller import FORMAT, load
from pipeline.io.artifacts import atomic_write_json
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.terminal import TerminalError, design_terminal

REFERENCE_SUBSTEPS = 20


@dataclass(frozen=True, kw_only=True)
class ControllerResult:
    path: Path
    trajectories: int
    interpolation_error: float
    success: bool
    message: str
    terminal: bool = False  # a certified terminal controller was written
    terminal_message: str = ""  # what it is, or why there is none


def terminal_block(
    scenario: Scenario,
    K: FloatArray,
    P: FloatArray,
    ends: Sequence[FloatArray],
    end_radii: Sequence[float],
    period: float = 0.0,
) -> tuple[dict | None, float, str]:
    """The ``terminal`` block (None when there is none), the end tubes' fit and a sentence.

    Args:
      K: (m, n) tube gain; P: (n, n) tube metric; ends: ``x_ref_i(T_i) (n,)`` each; end_radii:
        ``radius_i e^{-lambda T_i}``, the end tubes' P-norm radii.
    """
    try:
        design = design_terminal(scenario, K, P, ends, end_radii, period)
    except TerminalError as error:
        return None, np.inf, f"no terminal controller ({error}); the law refuses t > T"
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
    return (
        block,
        design.fit,
        (
            f"terminal controller ({design.gain} gain) at {where}: invariant ellipsoid certified "
            f"(decay {design.check.decay:.3g}/s on {design.check.vertices} hull vertices) holding "
            f"every end tube (at most {design.fit:.0%} of its radius)"
        ),
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
) -> ControllerResult:
    """Write ``controller.json`` and read it back.

    Args:
      starts: ``(n,)`` each; inputs: ``(N_i, m)`` each; radii: P-norm robustness radii.
      K: (m, n) feedback gain; P: (n, n) contraction metric; rate: lambda (1/s).
      radius_floor: the radius that covers Init (the covering radius kept by the optimizer).
        When the end tubes do not fit the terminal ellipsoid, the radii are lowered to it
        (smaller balls, still covering Init: the certify stage re-checks) if that makes them fit.
      feedback_period: the zero-order-hold period ``h`` (s) the tube's ``rate`` was certified
        for (``pipeline.numerics.sampled``; 0: continuous feedback).
    """
    trajectories, worst, ends, end_radii = [], 0.0, [], []
    for x0, us, radius in zip(starts, inputs, radii, strict=True):
        fine = simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=substeps)
        # interpolation error: the fine grid's midpoints against a 2x finer simulation
        finer = simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=2 * substeps)
        mid = 0.5 * (fine.dense_xs[:-1] + fine.dense_xs[1:])
        error = mid - finer.dense_xs[1::2]
        worst = max(worst, float(np.sqrt(np.einsum("ki,ij,kj->k", error, P, error)).max()))
        ends.append(fine.dense_xs[-1])
        end_radii.append(float(radius) * float(np.exp(-rate * fine.duration)))
        trajectories.append(
            {
                "x0": np.asarray(x0).tolist(),
                "radius": float(radius),
                "T": fine.duration,
                "u_ref": np.asarray(us).tolist(),
                "t": fine.dense_ts.tolist(),
                "x_ref": fine.dense_xs.tolist(),
            }
        )
    document = {
        "format": FORMAT,
        "scenario": scenario.name,
        "state_names": list(scenario.state_names),
        "input_names": list(scenario.input_names),
        "Ts": scenario.Ts,
        "input_bounds": {
            "lower": scenario.input_lower.tolist(),
            "upper": scenario.input_upper.tolist(),
        },
        "feedback": {"K": np.asarray(K).tolist(), "P": np.asarray(P).tolist(), "rate": rate},
        "trajectories": trajectories,
        "interpolation_error_P_norm": worst,
        "feedback_period": feedback_period,
    }
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
    if terminal is not None:
        document["terminal"] = terminal
    atomic_write_json(path, document)
    load(path)  # the file as emitted must validate
    return ControllerResult(
        path=path,
        trajectories=len(trajectories),
        interpolation_error=worst,
        success=True,
        message=f"{len(trajectories)} trajectories; x_ref interpolation error <= {worst:.1e} in "
        "P-norm",
        terminal=terminal is not None,
        terminal_message=terminal_message,
    )
