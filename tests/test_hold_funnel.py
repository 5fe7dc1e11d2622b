"""Arrive and stay under a declared gust (issue 29 item 3): a funnel run of a ``terminal: hold``
scenario designs its terminal controller first, ends every nominal in the core of its ellipsoid
and every funnel inside it, and ships that controller, robust to the declared bound.

double_integrator_hold with ``certificate: funnel`` and a gust of 0.02 m/s^2 on vx' and vy' is
synthesized end to end (before this item its nominals ended at Goal's corner, outside every
terminal ellipsoid, and the run was not certified); certify refuses the same file when the
scenario declares four times the gust.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import pipeline
from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from stages.certificates.targets import CORE
from stages.certify import certify_controller
from tests.helpers.robust import GUST, gusty_hold_scenario


@pytest.mark.slow
@pytest.mark.xdist_group("hold-funnel-gusty")
def test_a_gusty_hold_run_arrives_and_stays_and_four_times_the_gust_is_refused(tmp_path):
    path = gusty_hold_scenario(tmp_path / "gusty", GUST)
    result = pipeline.synthesize(path, out=tmp_path / "out", samples=300)
    assert result.success, result.message
    claims = {c.claim: c.kind.value for c in result.claims}
    after = [c for c in claims if c.startswith("after T")]
    assert after == [
        "after T every covered start stays in Goal for all time under the declared uncertainty "
        f"(|w_vx| <= {GUST:g}, |w_vy| <= {GUST:g}) (terminal controller)"
    ]
    assert claims[after[0]] == "certified"
    controller = load(tmp_path / "out" / "controller.json")
    block = controller.terminal
    assert block is not None
    document = json.loads((tmp_path / "out" / "controller.json").read_text())
    assert document["terminal"]["disturbance"] == [0.0, 0.0, GUST, GUST]
    # every nominal ends in the core: inside CORE of the terminal level
    P_T, x_eq = np.asarray(block.P), np.asarray(block.x_eq)
    for tr in controller.trajectories:
        d = tr.x_ref[-1] - x_eq
        assert d @ P_T @ d <= CORE * block.level * (1 + 1e-3)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["montecarlo"]["failures"]["after_T"] == 0
    # the same file against a scenario declaring 4x the gust: not certified
    stronger = load_scenario(gusty_hold_scenario(tmp_path / "stronger", 4 * GUST))
    refused = certify_controller(stronger, tmp_path / "out" / "controller.json")
    assert not refused.success
    assert any("uncertainty: the file holds |w_vx| <= 0.02" in f for f in refused.failures)


def test_the_reserve_keeps_the_nominal_off_its_bounds():
    """Under a declared disturbance a hold run's first optimization keeps at least the terminal
    set's extents (``Targets.reserve``) from every input bound and every bound of the region:
    the larger of the tube's margin and the reserve, per name; none without a reserve."""
    from pipeline.numerics.optimize.footprint import ConstraintMargins
    from stages.certificates import Targets

    scenario = load_scenario("quadrotor_hill_hold", check_demos=False)
    margins = ConstraintMargins(
        input_margin=np.array([0.2, 0.2]), region_margin={"theta": 0.05, "u1": 0.3},
        gain=np.zeros((2, 6)), state_extent={"theta": 0.02},
    )  # fmt: skip
    assert Targets(scenario=scenario).margins(margins) == margins
    reserve = {"u1": 1.0, "theta": 0.1, "X": 0.7}
    kept = Targets(scenario=scenario, reserve=reserve).margins(margins)
    assert kept.input_margin.tolist() == [1.0, 0.2]
    assert kept.region_margin == {"theta": 0.1, "u1": 1.0}  # X: not in the operating region
    assert kept.state_extent == {"theta": 0.1}  # X: not in state_bounds


def test_the_end_box_fills_the_terminal_ellipsoid():
    """A hold run's nominals end in Goal's bounds replaced by a box about ``x_eq`` whose worst
    corner lies on the terminal ellipsoid (``CORE`` 1: the whole level, not half), every other
    corner inside (quadrotor_hill: Goal's own bounds cut no side of it)."""
    import itertools

    from stages.certificates.targets import hold_targets, target_of

    scenario = load_scenario("quadrotor_hill", check_demos=False)
    targets = hold_targets(scenario)
    assert targets.terminal is not None
    target = target_of(targets.terminal)
    lower = np.array([targets.scenario.goal_bounds[k][0] for k in scenario.state_names])
    upper = np.array([targets.scenario.goal_bounds[k][1] for k in scenario.state_names])
    half = target.core_box(CORE)
    np.testing.assert_allclose(upper - lower, 2 * half, rtol=1e-12)  # Goal's bounds cut nothing
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=len(half))))
    shares = np.einsum("ki,ij,kj->k", signs * half, target.P, signs * half) / target.level
    assert shares.max() == pytest.approx(1.0, rel=1e-9)
