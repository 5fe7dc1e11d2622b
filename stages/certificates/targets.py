"""Where a funnel run ends its nominals (issue 29 item 3, arrive and stay).

In a ``terminal: hold`` scenario the terminal controller is designed first
(``terminal.hold_design``, robust to the declared uncertainty's additive bound), the optimize
stages end every nominal in the core of its ellipsoid (``Targets``: Goal's extra bounds replaced
by a box inside ``CORE`` of its level, checked at the box's corners), and every funnel must end
inside the ellipsoid (stage funnel's ``terminal``). First the nominals come to rest anywhere the
set still fits in Goal (``rest_targets``), then the terminal controller is moved to where they
came to rest (``placed_targets``).

Why the core (double_integrator_hold): without it the nominals ended at Goal's corner, ~0.9 m
from its centre at 0.14-0.47 m/s, outside every terminal ellipsoid centred in Goal, and no run
with a terminal controller was certified. Why the box fills the ellipsoid (``CORE`` 1, not half
its level): a box inside a correlated ellipsoid is small (its corners add the correlated states'
worst signs), so the nominals' ends stay far inside it anyway, and each funnel's own end check
(T2) keeps the room its tube needs; on quadrotor_hill the half-level box cost two demos a sample
(their shorter nominals failed on its near edges).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from types import MappingProxyType

import numpy as np

from pipeline.model.scenario import Scenario
from pipeline.numerics.terminal.design import TerminalDesign, hold_design, hover_box
from pipeline.numerics.terminal.equilibrium import TerminalError, lqr_terminal
from pipeline.numerics.terminal.fit import TerminalTarget
from pipeline.numerics.uncertainty import additive_bound
from stages.certificates import Targets

log = logging.getLogger("pipeline.certificates")  # the run's logger: its lines are shown
CORE = 1.0  # a hold run's nominals end in a box inside this fraction of the terminal level


def target_of(design: TerminalDesign) -> TerminalTarget:
    """The terminal controller's ellipsoid as the funnels' target."""
    return TerminalTarget(x_eq=design.x_eq, P=design.P, level=design.check.level)


def hold_targets(
    scenario: Scenario,
    period: float = 0.0,
    core: float = CORE,
    position: np.ndarray | None = None,
) -> Targets:
    """Where a ``terminal: hold`` run ends its nominals: the terminal controller designed first
    (``hold_design`` for the declared uncertainty's additive bound, zeros for the exact model;
    its equilibrium at ``position (2,)``, default Goal's centre), and ``scenario`` with Goal's
    extra bounds, per state, the box inside ``core`` of its level (``TerminalTarget.core_box``)
    intersected with the scenario's own. Another scenario, or one whose terminal controller
    cannot be designed (logged), keeps its Goal (``Targets``)."""
    if scenario.terminal != "hold":
        return Targets(scenario=scenario)
    try:
        measurement = scenario.uncertainty.measurement_box  # (T5)
        design = hold_design(
            scenario, additive_bound(scenario), period, measurement, position, scenario.uncertainty
        )
    except TerminalError as error:
        log.info(f"[terminal] no terminal controller designed before the funnels: {error}")
        return Targets(scenario=scenario)
    return core_targets(scenario, design, core)


def core_targets(scenario: Scenario, design: TerminalDesign, core: float = CORE) -> Targets:
    """``hold_targets`` for the terminal controller ``design``: Goal's extra bounds, per state,
    the box inside ``core`` of the level of the set the nominals arrive in
    (``TerminalDesign.arrives_in``) intersected with the scenario's own."""
    arrival = design.arrives_in
    half = target_of(arrival).core_box(core)
    bounds = dict(scenario.goal_bounds)
    for name, centre, h in zip(scenario.state_names, design.x_eq, half, strict=True):
        lower, upper = bounds.get(name, (-np.inf, np.inf))
        bounds[name] = (max(lower, float(centre - h)), min(upper, float(centre + h)))
    larger = (
        ""
        if design.arrival is None
        else f" (the funnels end in a larger set, (T6): level {design.check.level:.4g}, decay "
        f"{design.check.decay:.3g}/s, volume x"
        f"{np.exp((design.log_volume - arrival.log_volume) / 2):.3g})"
    )
    log.info(
        f"[terminal] {design.gain} gain at {np.round(design.x_eq, 3).tolist()}: invariant "
        f"ellipsoid certified (level {arrival.check.level:.4g}, decay "
        f"{arrival.check.decay:.3g}/s); the nominals end within +-{np.round(half, 3).tolist()} "
        f"of it{larger}"
    )
    return Targets(
        scenario=dataclasses.replace(scenario, goal_bounds=bounds),
        terminal=design,
        core=tuple(scenario.state_names),
        reserve=MappingProxyType(reserve_of(scenario, arrival)),
    )


def rest_targets(scenario: Scenario, period: float = 0.0) -> Targets:
    """Where a hold run's first optimization ends its nominals: ``hold_targets``, but with the
    position free over ``hover_box``, the positions where the set the nominals arrive in
    (``TerminalDesign.arrives_in``), designed at Goal's centre, still fits in Goal, so that each
    nominal comes to rest (the core box in the other states) wherever its flight is fastest
    (``Targets.placing``); ``placed_targets`` then moves the terminal controller to where they
    came to rest. Not a hold run: ``hold_targets``."""
    targets = hold_targets(scenario, period)
    box = None if targets.terminal is None else hover_box(scenario, targets.terminal.arrives_in)
    if box is None:
        return targets
    # the box lies inside the scenario's own Goal bounds on the position (hover_box)
    free = {
        scenario.state_names[i]: (float(lower), float(upper))
        for i, (lower, upper) in zip(scenario.position_index, box, strict=True)
    }
    moved = dataclasses.replace(
        targets.scenario, goal_bounds={**targets.scenario.goal_bounds, **free}
    )
    where = ", ".join(
        f"{name} in [{lower:.3g}, {upper:.3g}]" for name, (lower, upper) in free.items()
    )
    log.info(f"[terminal] first, the nominals come to rest anywhere with {where}")
    return dataclasses.replace(targets, scenario=moved, placing=True)


def placed_targets(
    scenario: Scenario, first: Targets, ends: Sequence[np.ndarray], period: float = 0.0
) -> Targets:
    """Where the nominals end after ``rest_targets``' optimization ended them at ``ends`` ((n,)
    each, its successful nominals'): ``hold_targets`` with the terminal equilibrium at the mean
    of their positions (where the fastest flights come to rest, as an uncertified minimum-time
    flight to rest chooses its own point of Goal), when the terminal controller designed there
    certifies a level no smaller than ``first``'s at Goal's centre (the room the funnels' ends
    need; the levels of the sets the nominals arrive in, ``TerminalDesign.arrives_in``); else
    ``first``'s controller at Goal's centre."""
    if first.terminal is None:
        return first
    if ends:
        position = np.mean([scenario.positions(end) for end in ends], axis=0)
        moved = hold_targets(scenario, period, position=position)
        level = first.terminal.arrives_in.check.level
        if moved.terminal is not None and moved.terminal.arrives_in.check.level >= level:
            return moved
        log.info(
            f"[terminal] kept at Goal's centre: at {np.round(position, 3).tolist()}, where the "
            "nominals came to rest, the terminal set certifies a smaller level"
        )
    return core_targets(scenario, first.terminal)


RESERVE = 2.0  # the reserve is this multiple of the terminal set's extents


def reserve_of(scenario: Scenario, design: TerminalDesign) -> dict[str, float]:
    """Name -> the half-width of the states and of the LQR law's inputs (at the equilibrium:
    the funnels' gains are first of the same weights, whichever gain the terminal law has) over
    ``{e^T P_T e <= 1}`` when ``P_T`` is shaped for a declared disturbance
    (``TerminalDesign.shaped``): about the smallest set the disturbance leaves, so the room the
    funnels' feedback needs about any nominal. Empty otherwise."""
    if not design.shaped:
        return {}
    Q = RESERVE**2 * np.linalg.inv(design.P)
    K = lqr_terminal(scenario, design.x_eq, design.u_eq)[0]
    states = np.sqrt(np.diag(Q))
    inputs = np.sqrt(np.einsum("ji,il,jl->j", K, Q, K))
    names = (*scenario.state_names, *scenario.input_names)
    return dict(zip(names, map(float, np.concatenate([states, inputs])), strict=True))
