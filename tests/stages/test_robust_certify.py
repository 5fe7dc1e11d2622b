"""Certify holds a /2 file to the scenario's declared uncertainty (stages/certify.py).

One funnel of the double integrator, robust to a gust of 0.05 m/s^2 on both speeds, emitted by
the controller stage: certify re-checks it under the bound it derives from the scenario, never
under the file's word alone, and refuses a file that holds less than the scenario declares.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from stages.certify import certify_controller
from stages.controller import emit_funnel_controller
from tests.helpers.robust import DISTURBANCE, double_integrator_case

# one worker synthesizes the two funnels (``robust``, about 1 s of CPU), not each
pytestmark = pytest.mark.xdist_group("robust-certify")


def _declaring(scenario: Scenario, bound: np.ndarray) -> Scenario:
    return dataclasses.replace(scenario, uncertainty=Uncertainty(disturbance=bound))


def _funnel_failures(failures: tuple[str, ...]) -> list[str]:
    """The failures about the funnels and the uncertainty (one funnel cannot cover Init)."""
    return [f for f in failures if "funnel is not certified" in f or f.startswith("uncertainty")]


@pytest.fixture(scope="module")
def robust(tmp_path_factory: pytest.TempPathFactory) -> tuple[Scenario, Path, Path]:
    """The gusty scenario, its robust funnel's file and the exact-model funnel's file."""
    scenario, trajectory, initial = double_integrator_case()
    gusty = _declaring(scenario, DISTURBANCE)
    folder = tmp_path_factory.mktemp("robust")
    paths = []
    for declared, name in ((gusty, "robust.json"), (scenario, "exact.json")):
        disturbance = None if declared.uncertainty.empty else DISTURBANCE
        funnel = synthesize_funnel(declared, trajectory, initial=initial, disturbance=disturbance)
        assert funnel.success, funnel.message
        emit_funnel_controller(declared, [trajectory], [funnel], folder / name)
        paths.append(folder / name)
    return gusty, paths[0], paths[1]


def test_the_robust_file_states_its_bound_and_certifies_under_the_declaration(robust):
    gusty, path, _ = robust
    document = json.loads(path.read_text())
    assert document["uncertainty"]["additive_bound"] == DISTURBANCE.tolist()
    assert document["uncertainty"]["disturbance"] == {"x": 0, "y": 0, "vx": 0.05, "vy": 0.05}
    result = certify_controller(gusty, path)
    assert _funnel_failures(result.failures) == []


def test_a_file_holding_less_than_declared_is_refused(robust):
    gusty, path, exact = robust
    wider = _declaring(gusty, 4 * DISTURBANCE)
    failures = _funnel_failures(certify_controller(wider, path).failures)
    assert any("holds |w_vx| <= 0.05, the scenario declares 0.2" in f for f in failures)
    assert any("funnel is not certified" in f for f in failures)  # and fails the re-check
    exact_failures = _funnel_failures(certify_controller(gusty, exact).failures)
    assert any("holds |w_vx| <= 0, the scenario declares 0.05" in f for f in exact_failures)


def test_the_files_bound_is_verified_not_trusted(robust, tmp_path: Path):
    """A file claiming 20x the bound it was made for: certify checks the claim, and fails."""
    gusty, path, _ = robust
    document = json.loads(path.read_text())
    document["uncertainty"]["additive_bound"] = (20 * DISTURBANCE).tolist()
    tampered = tmp_path / "tampered.json"
    tampered.write_text(json.dumps(document))
    failures = _funnel_failures(certify_controller(gusty, tampered).failures)
    assert failures and all("funnel is not certified" in f for f in failures)
    assert "under the disturbance" in failures[0]


def test_an_exact_model_scenario_reads_the_exact_file_unchanged(robust):
    """No declaration and no ``uncertainty`` block: the exact-model certificate, as before."""
    gusty, _, exact = robust
    document = json.loads(exact.read_text())
    assert "uncertainty" not in document
    scenario = dataclasses.replace(gusty, uncertainty=Uncertainty.exact(gusty.n))
    assert _funnel_failures(certify_controller(scenario, exact).failures) == []


def test_certify_reports_the_largest_multiple_of_the_declared_bound(robust):
    """The multiple is what the re-check says: the funnel holds 0.999 of it and fails at 1.001
    of it (certify run again with the scenario declaring those multiples)."""
    gusty, path, _ = robust
    multiple = certify_controller(gusty, path).disturbance_multiple
    assert 1 <= multiple < 100
    inside = _declaring(gusty, 0.999 * multiple * DISTURBANCE)
    outside = _declaring(gusty, 1.001 * multiple * DISTURBANCE)
    assert not any(
        "funnel is not certified" in f for f in certify_controller(inside, path).failures
    )
    assert any("funnel is not certified" in f for f in certify_controller(outside, path).failures)


def test_the_multiple_is_the_smallest_over_the_funnels_in_either_order(robust, tmp_path: Path):
    """Certify searches each funnel's multiple no higher than the smallest found so far
    (``enough``): a file with the funnel and a copy at 90% of its level (a smaller multiple:
    (I5)'s term grows as the level shrinks) reports the copy's, in either order, as the copy
    alone does."""
    gusty, path, _ = robust
    document = json.loads(path.read_text())
    funnel = document["trajectories"][0]
    lower = {**funnel, "name": "lower", "radius": 0.9 * funnel["radius"]}
    found = {}
    for name, trajectories in (
        ("alone", [funnel]), ("lower", [lower]), ("first", [funnel, lower]),
        ("second", [lower, funnel]),
    ):  # fmt: skip
        variant = tmp_path / f"{name}.json"
        variant.write_text(json.dumps({**document, "trajectories": trajectories}))
        found[name] = certify_controller(gusty, variant).disturbance_multiple
    assert 0.5 < found["lower"] < found["alone"], found
    assert found["first"] == found["lower"] and found["second"] == found["lower"], found
