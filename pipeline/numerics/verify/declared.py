"""What each block of a shipped file is re-checked under: the scenario's declared uncertainty,
derived here (``pipeline.numerics.uncertainty``) and never read from the file, raised to what the
block states where that is larger, so that both claims are verified. A block stating less than
the scenario declares is a failure, and is still re-checked under the declaration.
"""

from __future__ import annotations

import numpy as np

from pipeline.controller import TerminalController
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.hull import HullError
from pipeline.numerics.uncertainty import additive_bound, declared_bound, equilibrium_bound


def checked_bound(
    scenario: Scenario, stated: FloatArray | None, what: str
) -> tuple[FloatArray | None, list[str]]:
    """``(b (n,), failures)``: the additive bound a block of the file is re-checked under: the
    scenario's declaration (``pipeline.numerics.uncertainty``, derived here, never read from
    the file) raised to the bound the block ``stated`` where that is larger (both claims are
    then verified); None when neither declares any. A block stating less than the scenario
    declares is a failure named by ``what`` (it is still re-checked, with the declaration)."""
    try:
        declared = declared_bound(scenario)
    except HullError as error:
        return np.full(scenario.n, np.inf), [f"{what}: the declared uncertainty: {error}"]
    failures = _short_of(scenario, declared, stated, f"{what}: the file holds |w_", "uncertainty:")
    if declared is None:
        return (None if stated is None else np.asarray(stated)), failures
    return (declared if stated is None else np.maximum(stated, declared)), failures


def _short_of(
    scenario: Scenario,
    declared: FloatArray | None,
    stated: FloatArray | None,
    holds: str,
    where: str,
) -> list[str]:
    """The failure of a file whose ``stated (n,)`` box (None: zeros) is below the scenario's
    ``declared`` one in some state (the first such), worded ``holds`` + ``name| <= ...``; none
    when nothing is declared."""
    if declared is None:
        return []
    held = np.zeros(scenario.n) if stated is None else np.asarray(stated)
    short = np.flatnonzero(held < declared)
    if not len(short):
        return []
    i = int(short[0])
    return [
        f"{holds}{scenario.state_names[i]}| <= {held[i]:.4g}, the scenario declares "
        f"{declared[i]:.4g} ({where} block); synthesize again"
    ]


def checked_measurement(
    scenario: Scenario, stated: FloatArray | None
) -> tuple[FloatArray | None, list[str]]:
    """``(E (n,), failures)``: the measurement box the file is re-checked under: the scenario's
    ``uncertainty.measurement`` (never read from the file) raised to the file's stated
    ``uncertainty.measurement_bound`` where that is larger; None when neither declares any. A
    file stating less than the scenario declares is a failure (re-checked with the declaration)."""
    declared = scenario.uncertainty.measurement_box
    failures = _short_of(
        scenario, declared, stated, "uncertainty: the file holds |eta_", "uncertainty.measurement"
    )
    if declared is None:
        return (None if stated is None or not np.any(stated) else np.asarray(stated)), failures
    return (declared if stated is None else np.maximum(stated, declared)), failures


def terminal_claim(
    scenario: Scenario, terminal: TerminalController
) -> tuple[FloatArray | None, Uncertainty | None, list[str]]:
    """``(b (n,), parameters, failures)``: what the file's ``terminal`` block is re-checked
    under. A block stating at least the declared additive bound, or under no declared parameter
    intervals: ``checked_bound`` (T1'), no parameters in the hull. Otherwise (T7) of
    ``terminal.check``: the scenario's parameter intervals in the hull and ``b`` the declared
    disturbance plus their term at the block's own ``(x_eq, u_eq)`` (``uncertainty.
    equilibrium_bound``, derived here), raised to the block's box where that is larger; a block
    stating less than that is a failure (re-checked with it). Either way a block without
    failures holds the declared uncertainty."""
    stated, parameters = terminal.disturbance, scenario.uncertainty
    if stated is None or parameters.parametric is None or _holds_whole_box(scenario, stated):
        bound, failures = checked_bound(scenario, stated, "terminal")
        return bound, None, failures
    try:
        local = equilibrium_bound(parameters, scenario, terminal.x_eq, terminal.u_eq)
    except HullError as error:
        return np.full(scenario.n, np.inf), None, [f"terminal: the declared uncertainty: {error}"]
    failures = _short_of(
        scenario, local, stated, "terminal: the file holds |w_",
        "uncertainty: at the terminal equilibrium, (T7)",
    )  # fmt: skip
    return np.maximum(stated, local), parameters, failures


def _holds_whole_box(scenario: Scenario, stated: FloatArray) -> bool:
    """``stated (n,)`` is at least the declared additive bound over the whole box in every
    state (False where that bound cannot be derived: (T7) alone can hold the block)."""
    try:
        return bool(np.all(stated >= additive_bound(scenario)))
    except HullError:
        return False
