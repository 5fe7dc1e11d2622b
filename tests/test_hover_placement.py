"""Where a hold run hovers: where its fastest nominals come to rest (stages.certificates.targets).

A ``terminal: hold`` run of the funnel certificate first optimizes its nominals to rest anywhere
the terminal set designed at Goal's centre still fits (``hover_box``), then designs the terminal
controller at the mean of their end positions (when it certifies no smaller a level there) and
optimizes again to its core. The box must hold the set at its corners and not beyond; the
placement must follow the ends, and fall back to Goal's centre where the set does not fit.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from pipeline.numerics.terminal.check import check_level
from pipeline.numerics.terminal.design import hover_box
from pipeline.numerics.terminal.equilibrium import equilibrium
from pipeline.numerics.uncertainty import additive_bound
from pipeline.reporting.summary import ClaimKind
from pipeline.runtime.runner import read_checked
from stages.certificates import nominals
from stages.certificates.targets import placed_targets, rest_targets

HOLD = "quadrotor_hill"  # robust funnels ending in the hover; its session synthesis is in make test


@pytest.fixture(scope="module")
def first():
    """``(scenario, rest_targets)``: the terminal controller at Goal's centre, position free."""
    scenario = load_scenario(HOLD, check_demos=False)
    return scenario, rest_targets(scenario)


def _level_at(scenario, design, position):
    x_eq, u_eq = equilibrium(scenario, np.asarray(position, dtype=np.float64))
    bound, measurement = additive_bound(scenario), scenario.uncertainty.measurement_box
    return check_level(
        scenario, x_eq, u_eq, design.K, design.P, design.check.level,
        disturbance=bound, measurement=measurement,
    )  # fmt: skip


def test_the_hover_box_holds_the_terminal_set_at_its_corners_and_not_beyond(first):
    scenario, targets = first
    design = targets.terminal
    box = hover_box(scenario, design)  # (2, 2): rows X, Y
    assert targets.placing and box is not None
    assert box[0, 0] <= design.x_eq[0] <= box[0, 1] and box[1, 0] <= design.x_eq[1] <= box[1, 1]
    inside = 1e-6 * (box[:, 1] - box[:, 0])
    for corner in ((0, 0), (0, 1), (1, 0), (1, 1)):
        position = [box[k, side] + (inside[k] if side == 0 else -inside[k]) for k, side in
                    enumerate(corner)]  # fmt: skip
        check = _level_at(scenario, design, position)
        assert check.success, (position, check.failures)
    for k in range(2):  # 1% of the box's width beyond each edge, the set leaves Goal
        for side, sign in ((0, -1.0), (1, 1.0)):
            position = np.mean(box, axis=1)
            position[k] = box[k, side] + sign * 0.01 * (box[k, 1] - box[k, 0])
            check = _level_at(scenario, design, position)
            assert any("leaves Goal" in failure for failure in check.failures), position
    # the first optimization's Goal: the position free over the box, the rest in the core
    bounds = targets.scenario.goal_bounds
    assert bounds["X"] == pytest.approx(tuple(box[0]))
    assert bounds["Y"] == pytest.approx(tuple(box[1]))
    assert bounds["vX"][1] - bounds["vX"][0] < 0.5


def test_the_hover_moves_to_where_the_nominals_rest_and_stays_where_the_set_does_not_fit(first):
    scenario, targets = first
    centre = targets.terminal.x_eq
    ends = [centre + np.array([0.0, d, 0, 0, 0, 0]) for d in (0.3, 0.4, 0.5)]  # mean 0.4 higher
    moved = placed_targets(scenario, targets, ends)
    assert not moved.placing
    assert moved.terminal.x_eq[:2] == pytest.approx(centre[:2] + [0.0, 0.4], abs=1e-9)
    assert moved.terminal.check.level >= targets.terminal.check.level
    half = moved.scenario.goal_bounds["Y"]  # the core box about the moved hover
    assert half[0] < centre[1] + 0.4 < half[1] and half[1] - half[0] < 0.5
    corner = [np.array([17.05, 1.05, 0, 0, 0, 0])]  # Goal's corner: no room for the set there
    kept = placed_targets(scenario, targets, corner)
    assert kept.terminal is targets.terminal
    assert kept.scenario.goal_bounds["X"][0] < centre[0] < kept.scenario.goal_bounds["X"][1]


@pytest.mark.xdist_group("synthesis-quadrotor_hill")  # with its session run (conftest)
def test_a_hold_run_hovers_at_the_mean_of_where_its_first_optimization_came_to_rest(synthesis):
    code, out = synthesis(HOLD)
    assert code == 0
    scenario = load_scenario(HOLD, check_demos=False)
    stored = read_checked(out / "artifacts" / "optimize_rest")
    assert stored is not None
    rested = [t for t in stored.result.trajectories if t.success]
    assert rested
    ends = [nominals(scenario, [t.x0], [t.u])[0].xs[-1] for t in rested]
    terminal = load(out / "controller.json").terminal
    assert terminal is not None
    assert terminal.x_eq[:2] == pytest.approx(np.mean(ends, axis=0)[:2], abs=1e-9)


@pytest.mark.xdist_group("synthesis-quadrotor_hill")  # with its session run (conftest)
def test_the_shipped_run_certifies_the_law_a_flight_computer_runs(synthesis_run):
    """Issue 29: ``make synthesize``'s claims cover the law evaluated every 5 ms and held in
    between, the funnels' and the hover's after T; the funnels shipped are the held law's
    (stage ``funnel_held``, around the nominals the continuous law's rounds chose)."""
    session = synthesis_run(HOLD)
    assert session.result.exit_code == 0
    controller = load(session.out / "controller.json")
    assert controller.feedback_period == 0.005
    summary = session.result.summary
    assert summary is not None
    claims = [claim.claim for claim in summary.claims if claim.kind is ClaimKind.CERTIFIED]
    held = "evaluated every 0.005 s and held in between"
    assert any(held in claim and "before T_i" in claim for claim in claims), claims
    assert any(held in claim and "stays in Goal for all time" in claim for claim in claims)
    assert any(record.getMessage().startswith("[funnel_held]") for record in session.records)
    # this run's held funnels cover Init at once: no step back, no held rounds, so they ship
    stored = read_checked(session.out / "artifacts" / "funnel_held")
    assert stored is not None and len(stored.result.usable) == len(controller.trajectories)
    for shipped, funnel in zip(controller.trajectories, stored.result.funnels, strict=True):
        np.testing.assert_array_equal(shipped.K, funnel.K)
