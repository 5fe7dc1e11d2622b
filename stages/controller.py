"""Stage ``controller``: emit the lookup feedback controller ``controller.json``.

Format ``safety-controller/1`` (documented in the README and read by ``pipeline.controller``):
the feedback ``K``, metric ``P`` and rate, and for every nominal trajectory its start ``x0``,
robustness radius, duration ``T``, held inputs ``u_ref (N, m)`` and states ``x_ref`` on a fine
grid ``t`` (RK4 substeps), so that linear interpolation error is negligible against the tube.
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

REFERENCE_SUBSTEPS = 20


@dataclass(frozen=True)
class ControllerResult:
    path: Path
    trajectories: int
    interpolation_error: float
    success: bool
    message: str


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
) -> ControllerResult:
    """Write ``controller.json`` and read it back.

    Args:
      starts: ``(n,)`` each; inputs: ``(N_i, m)`` each; radii: P-norm robustness radii.
      K: (m, n) feedback gain; P: (n, n) contraction metric; rate: lambda (1/s).
    """
    trajectories, worst = [], 0.0
    for x0, us, radius in zip(starts, inputs, radii, strict=True):
        fine = simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=substeps)
        # interpolation error: the fine grid's midpoints against a 2x finer simulation
        finer = simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=2 * substeps)
        mid = 0.5 * (fine.dense_xs[:-1] + fine.dense_xs[1:])
        error = mid - finer.dense_xs[1::2]
        worst = max(worst, float(np.sqrt(np.einsum("ki,ij,kj->k", error, P, error)).max()))
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
    }
    atomic_write_json(path, document)
    load(path)  # the file as emitted must validate
    return ControllerResult(
        path,
        len(trajectories),
        worst,
        True,
        f"{len(trajectories)} trajectories; x_ref interpolation error <= {worst:.1e} in P-norm",
    )
