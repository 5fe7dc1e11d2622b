"""The terminal controller's equilibrium in Goal and its LQR law (``terminal.design``).

``(x_eq, u_eq)`` with ``f(x_eq, u_eq) = 0`` (to ``EQUILIBRIUM_TOLERANCE``), the position at a
given point of Goal and everything else inside the scenario's bounds; ``K_T`` and ``P_T`` from
``control.lqr`` at it, with the scenario's feedback weights.
"""

from __future__ import annotations

import control
import numpy as np
from scipy.optimize import least_squares
from shapely.ops import polylabel

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario

EQUILIBRIUM_TOLERANCE = 1e-9  # ||f(x_eq, u_eq)|| accepted as an equilibrium


class TerminalError(ValueError):
    """No terminal controller: no equilibrium in Goal, or its linearisation not stabilisable."""


def goal_centre(scenario: Scenario) -> FloatArray:
    """(2,) the point of Goal farthest from its boundary (the pole of inaccessibility)."""
    point = polylabel(scenario.goal, tolerance=1e-6)
    return np.array([point.x, point.y])


def equilibrium(
    scenario: Scenario, position: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """``(x_eq (n,), u_eq (m,))`` with ``f = 0``, the position at ``position (2,)`` (default
    ``goal_centre``), the other states in Goal's bounds, the operating region and the state
    bounds and the inputs within their bounds; ``TerminalError`` when the least-squares search
    finds none."""
    dynamics, spec = scenario.dynamics, scenario.feedback
    n, m = len(scenario.state_names), len(scenario.input_names)
    position_index = list(scenario.position_index)
    free = [i for i in range(n) if i not in position_index]
    lower = np.concatenate([np.full(n, -np.inf), scenario.input_lower])
    upper = np.concatenate([np.full(n, np.inf), scenario.input_upper])
    boxes = {**scenario.operating_region, **scenario.goal_bounds}
    for name, (lo, hi) in [*boxes.items(), *scenario.state_bounds.items()]:
        k = (scenario.state_names + scenario.input_names).index(name)
        lower[k], upper[k] = max(lower[k], lo), min(upper[k], hi)
    z0 = np.concatenate([np.array(spec.reference_state, float), np.array(spec.reference_input)])
    z0[position_index] = goal_centre(scenario) if position is None else position
    keep = np.array(free + list(range(n, n + m)))
    lo, hi = lower[keep], upper[keep]
    if np.any(lo > hi):
        raise TerminalError("Goal's bounds and the operating region leave no state to hold")
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    start = np.clip(z0[keep], lo + 1e-6 * span, hi - 1e-6 * span)

    def residual(z: FloatArray) -> FloatArray:
        full = z0.copy()
        full[keep] = z
        return dynamics.f(full[:n], full[n:])

    found = least_squares(residual, start, bounds=(lo, hi), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    z = z0.copy()
    z[keep] = found.x
    error = float(np.linalg.norm(residual(found.x)))
    if not error <= EQUILIBRIUM_TOLERANCE:
        raise TerminalError(
            f"no equilibrium with the position at {np.round(z0[position_index], 3).tolist()}: "
            f"smallest |f(x, u)| found {error:.2g} within the bounds"
        )
    return z[:n], z[n:]


def lqr_terminal(
    scenario: Scenario, x_eq: FloatArray, u_eq: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``(K_T (m, n), P_T (n, n))``: ``control.lqr`` at the equilibrium with the scenario's
    feedback weights, ``K_T = -K_lqr`` (sign of ``u = u_eq + K_T e``), ``P_T`` the Riccati
    solution (``A_cl^T P_T + P_T A_cl = -(Q + K^T R K)`` at the equilibrium)."""
    spec = scenario.feedback
    A, B = scenario.dynamics.f_x(x_eq, u_eq), scenario.dynamics.f_u(x_eq, u_eq)
    try:
        K, S, _ = control.lqr(A, B, np.diag(spec.state_weights), np.diag(spec.input_weights))
    except (ValueError, np.linalg.LinAlgError, control.ControlArgument) as error:
        raise TerminalError(
            f"the linearisation at the equilibrium is not stabilisable ({error})"
        ) from None
    S = np.asarray(S, dtype=np.float64)
    return -np.asarray(K, dtype=np.float64), (S + S.T) / 2
