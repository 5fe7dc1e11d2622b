"""Re-verify a ``safety-controller`` file's ``terminal`` block from the file and the scenario.

``recheck_terminal`` (either format): the ``terminal`` block by (T1') of
``pipeline.numerics.terminal.check`` under the scenario's declared additive bound (``uncertainty.
additive_bound``; the block's own ``disturbance`` only where it is larger) or, for a block that
states less under declared parameter intervals, by (T7) (the intervals in the hull, the bound at
the block's equilibrium: ``terminal_claim``), for a held law ((T4)
in a ``/2`` file, the held rate in a ``/1`` file), the law seeing the state within the declared
measurement box ((T5); the file's ``uncertainty.measurement_bound`` where larger; a file stating
less fails in the funnels' check), and every end tube inside its ellipsoid (``terminal.fit``).
"""

from __future__ import annotations

import numpy as np

from pipeline.controller import Controller
from pipeline.model.scenario import Scenario
from pipeline.numerics.funnel.law import LEVEL_MARGIN
from pipeline.numerics.terminal.check import check_level
from pipeline.numerics.terminal.fit import end_levels
from pipeline.numerics.verify.declared import checked_measurement, terminal_claim


def recheck_terminal(scenario: Scenario, controller: Controller) -> tuple[float, float, list[str]]:
    """``(decay, fit, failures)`` of the file's terminal block (certify's step 6): (T1') of
    ``pipeline.numerics.terminal.check`` under ``verify.declared.checked_bound``, no clipping,
    inside Goal and the state bounds, and every end tube inside (``terminal.fit.end_levels``). A
    funnel file's end tubes are widened by ``LEVEL_MARGIN``: ``x_ref(T)`` is the RK4 value, within
    that share of the radius of the exact nominal's (certify's step 4)."""
    terminal = controller.terminal
    if terminal is None:
        raise TypeError(f"{controller.source}: no terminal block to verify")
    bound, parameters, failures = terminal_claim(scenario, terminal)
    bound = np.zeros(scenario.n) if bound is None else bound
    measurement, _ = checked_measurement(scenario, controller.measurement_bound)  # (T5)
    if not np.all(np.isfinite(bound)):
        return float("nan"), float("nan"), failures
    check = check_level(
        scenario,
        terminal.x_eq,
        terminal.u_eq,
        terminal.K,
        terminal.P,
        terminal.level,
        # a funnel file's held law: its hold joins the disturbance (T4); a /1 file's: the
        # constant certificate's held rate
        period=0.0 if controller.funnel else controller.feedback_period,
        disturbance=bound,
        held_period=controller.feedback_period if controller.funnel else 0.0,
        measurement=measurement,
        parameters=parameters,
    )
    widen = 1 + LEVEL_MARGIN if controller.funnel else 1.0
    ends = [tr.x_ref[-1] for tr in controller.trajectories]
    radii = [widen * tr.radius * float(np.exp(-tr.rate * tr.T)) for tr in controller.trajectories]
    metrics = np.stack([tr.P[-1] for tr in controller.trajectories])  # each end tube's metric
    needed = end_levels(terminal.P, terminal.x_eq, metrics, ends, radii)
    fit = float(np.sqrt(needed.max() / terminal.level))
    failures += [f"terminal: {failure}" for failure in check.failures]
    if not fit <= 1:
        i = int(np.argmax(needed))
        failures.append(
            f"terminal: trajectories[{i}]'s end tube is not inside the terminal ellipsoid (it "
            f"needs level {needed[i]:.4g} > {terminal.level:.4g})"
        )
    return check.decay, fit, failures
