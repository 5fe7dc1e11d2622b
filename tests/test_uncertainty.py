"""The declared uncertainty (``uncertainty:``) and its additive bound (U1)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

import pipeline
from pipeline import load_scenario
from pipeline.io.errors import UserError
from pipeline.model.scenario import Scenario
from pipeline.numerics.hull import HullError
from pipeline.numerics.uncertainty import additive_bound, certified_box, parameter_bound
from pipeline.reporting.uncertainty import declared_table
from pipeline.runtime.run_inputs import scenario_key
from stages.controller import uncertainty_block
from tests.helpers.scenario_files import write_scenario, yaml_replace

REPO = Path(__file__).resolve().parents[1]
DECLARED = """
uncertainty:
  disturbance: {vX: 0.25, vY: 0.25}
  parameters: {wX: [-1.0, 0.0], m: [0.95, 1.05]}
"""


def quadrotor(tmp_path: Path, block: str = DECLARED) -> Scenario:
    folder = tmp_path / "quad"
    shutil.copytree(REPO / "scenarios" / "quadrotor_hill_flythrough", folder)
    path = folder / "scenario.yaml"
    path.write_text(path.read_text() + block)
    return load_scenario(path)


def test_declared_block_is_parsed(tmp_path: Path) -> None:
    uncertainty = quadrotor(tmp_path).uncertainty
    assert not uncertainty.empty
    assert uncertainty.disturbance.tolist() == [0, 0, 0, 0.25, 0.25, 0]
    assert dict(uncertainty.parameters) == {"wX": (-1.0, 0.0), "m": (0.95, 1.05)}
    assert uncertainty.parameter_nominal.tolist() == [-0.5, 1.0]
    with pytest.raises(ValueError, match="read-only"):
        uncertainty.disturbance[3] = 0.0


def test_no_block_is_the_exact_model() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough")
    assert scenario.uncertainty.empty
    assert scenario.uncertainty.parametric is None
    assert additive_bound(scenario).tolist() == [0.0] * 6


def test_the_key_changes_with_the_declared_bound(tmp_path: Path) -> None:
    scenario = quadrotor(tmp_path)
    wider = dataclasses.replace(scenario, uncertainty=scenario.uncertainty.scaled(2.0))
    assert scenario_key(wider) != scenario_key(scenario)


def test_parameter_bound_holds_every_sampled_model_and_is_tight(tmp_path: Path) -> None:
    """(U1) against the true difference ``f(x, u, p) - f(x, u, p0)`` at 20,000 random points of
    the certified box and the parameter box, corners included; and within 10% of its exact
    supremum (worked by hand below)."""
    scenario = quadrotor(tmp_path)
    uncertainty = scenario.uncertainty
    box = certified_box(scenario)
    bound = parameter_bound(uncertainty, box)
    rng = np.random.default_rng(0)
    count = 20_000
    x = np.zeros((count, 6))
    x[:, 2] = rng.uniform(*box["theta"], count)
    x[:, 3:5] = rng.uniform(-5, 5, (count, 2))  # the speeds cancel in the difference
    u = np.column_stack([rng.uniform(*box["u1"], count), rng.uniform(*box["u2"], count)])
    p = rng.uniform(uncertainty.parameter_lower, uncertainty.parameter_upper, (count, 2))
    x[:4, 2], u[:4, 0], p[:4] = 0.8, 14.9, [[-1, 0.95], [0, 0.95], [-1, 1.05], [0, 1.05]]
    p0 = np.broadcast_to(uncertainty.parameter_nominal, p.shape)
    dynamics = uncertainty.parametric
    assert dynamics is not None
    difference = dynamics.f(x, np.hstack([u, p])) - dynamics.f(x, np.hstack([u, p0]))
    assert np.all(np.abs(difference) <= bound)
    # sup |mu (wX - wX0)| + sup |u1 sin(theta) (1/m - 1/m0)|, and sup |u1 cos(theta) (1/m - 1)|
    exact = [0.5 * 0.5 + 14.9 * np.sin(0.8) * (1 / 0.95 - 1), 14.9 * (1 / 0.95 - 1)]
    assert bound[[0, 1, 2, 5]].tolist() == [0.0] * 4
    assert np.all(bound[3:5] <= 1.1 * np.array(exact))


def test_additive_bound_adds_the_disturbance(tmp_path: Path) -> None:
    scenario = quadrotor(tmp_path)
    parameters = parameter_bound(scenario.uncertainty, certified_box(scenario))
    total = additive_bound(scenario)
    assert np.all(total >= parameters + scenario.uncertainty.disturbance)
    assert np.allclose(total, parameters + scenario.uncertainty.disturbance, rtol=1e-15)


ELLIPSOID = """
uncertainty:
  disturbance: {vX: 0.05}
  disturbance_ellipsoid: {vX: 0.2, vY: 0.1}
  parameters: {wX: [-1.0, 0.0], m: [0.95, 1.05]}
"""
BOUNDING_BOX = """
uncertainty:
  disturbance: {vX: 0.25, vY: 0.1}
  parameters: {wX: [-1.0, 0.0], m: [0.95, 1.05]}
"""


def test_a_declared_ellipsoid_is_held_by_its_bounding_box(tmp_path: Path) -> None:
    """The ellipsoid's semi-axes join the declared box: the additive bound is the bounding box
    file's, every point of box plus ellipsoid lies in it, and the file, the report and
    ``--stress`` keep what was declared."""
    ellipsoid = quadrotor(tmp_path / "ellipsoid", ELLIPSOID)
    box = quadrotor(tmp_path / "box", BOUNDING_BOX)
    u = ellipsoid.uncertainty
    assert np.allclose(u.disturbance, [0, 0, 0, 0.25, 0.1, 0], rtol=1e-15, atol=0)
    assert u.ellipsoid.tolist() == [0, 0, 0, 0.2, 0.1, 0]
    assert u.declared_box.tolist() == [0, 0, 0, 0.05, 0, 0]
    assert np.all(u.disturbance >= box.uncertainty.disturbance)  # 0.05 + 0.2 rounded up
    assert np.all(additive_bound(ellipsoid) >= additive_bound(box))
    assert np.allclose(additive_bound(ellipsoid), additive_bound(box), rtol=1e-15, atol=0)
    assert scenario_key(ellipsoid) != scenario_key(box)  # the report and the file differ
    rng = np.random.default_rng(3)
    v = rng.normal(size=(10_000, 2))
    v *= rng.random((10_000, 1)) ** 0.5 / np.linalg.norm(v, axis=1, keepdims=True)  # in the disk
    w = np.zeros((10_000, 6))
    w[:, 3:5] = v * [0.2, 0.1]
    w[:, 3] += rng.choice([-0.05, 0.05], size=10_000)
    assert np.all(np.abs(w) <= u.disturbance)
    block = uncertainty_block(ellipsoid, additive_bound(ellipsoid))
    assert block["disturbance"]["vX"] == 0.05 and block["disturbance"]["vY"] == 0.0
    assert block["disturbance_ellipsoid"] == {"vX": 0.2, "vY": 0.1}
    assert "disturbance_ellipsoid" not in uncertainty_block(box, additive_bound(box))
    declared = [row[1] for row in declared_table(ellipsoid, None).rows]
    assert "(g_vX / 0.2 m/s^2)^2 + (g_vY / 0.1 m/s^2)^2 <= 1" in declared
    assert "|d_vX| <= 0.05 m/s^2" in declared and not any("|d_vY|" in row for row in declared)
    wider = u.scaled(2.0)
    assert wider.ellipsoid.tolist() == [0, 0, 0, 0.4, 0.2, 0]
    assert np.all(wider.disturbance >= [0, 0, 0, 0.5, 0.2, 0])
    assert np.allclose(wider.disturbance, [0, 0, 0, 0.5, 0.2, 0], rtol=1e-15, atol=0)
    assert wider.declared_box.tolist() == [0, 0, 0, 0.1, 0, 0]


def test_a_sensitivity_over_an_unbounded_state_names_it(tmp_path: Path) -> None:
    path = write_scenario(tmp_path)
    yaml_replace("X: vX\n", "X: k*vX\n")(path)
    yaml_replace(
        "clearance: 0.25\n", "clearance: 0.25\nuncertainty: {parameters: {k: [0.9, 1.1]}}\n"
    )(path)
    scenario = load_scenario(path)
    with pytest.raises(HullError, match="depends on 'vX'.*declare state_bounds.vX"):
        additive_bound(scenario)


def test_the_constant_certificate_refuses_a_declaration(tmp_path: Path) -> None:
    """Exit 2 in one line, before any stage runs (no folder written): the constant certificate
    is of the exact model."""
    scenario = quadrotor(tmp_path)
    out = tmp_path / "out"
    with pytest.raises(UserError, match="uncertainty: declared.*expected certificate: funnel"):
        pipeline.synthesize(scenario, out=out, certificate="constant")
    assert not out.exists()


def test_a_robust_funnel_keeps_its_tube_where_the_bound_holds():
    """The additive bound holds over ``certified_box`` only: under a declared uncertainty a
    state the operating region bounds (and state_bounds does not) joins the funnel's state
    bounds; without one, the scenario's state_bounds alone."""
    from pipeline.model.uncertainty import Uncertainty
    from pipeline.numerics.uncertainty import held_state_bounds

    scenario = load_scenario("quadrotor_hill", check_demos=False)
    assert held_state_bounds(scenario) == {"theta": (-0.8, 0.8)}
    unbounded = dataclasses.replace(scenario, state_bounds={})
    assert held_state_bounds(unbounded) == {"theta": (-0.6, 0.6)}  # the operating region's
    exact = dataclasses.replace(unbounded, uncertainty=Uncertainty.exact(scenario.n))
    assert held_state_bounds(exact) == {}
