"""The contraction inequality (C) has one evaluation (``pipeline.numerics.tube.contraction``): the
certifier, from the file's ``P``, ``K``, ``rate`` and a hull it rebuilds, finds the numbers the
designer found on its own hull, on every shipped scenario's feedback."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.model.scenario import load_scenario
from pipeline.numerics.hull import DEFAULT_SEGMENTS
from pipeline.numerics.tube.contraction import contraction_margin, contraction_rate
from stages.certify import contraction_check
from stages.feedback import design_feedback

SHIPPED = (
    "double_integrator",
    "double_integrator_hold",
    "quadrotor_hill_flythrough",
    "quadrotor_hill_gusty_flythrough",
    "unicycle_slalom",
)


@pytest.mark.parametrize("name", SHIPPED)
def test_the_certifier_finds_the_designers_vertices_and_margin(name: str) -> None:
    """Same vertices bit for bit; the designer's margin (in the metric's scale, ``L^-1 M L^-T``)
    to rounding; the certifier's own (``M`` as it is) negative and within ``[lambda_max(P),
    lambda_min(P)]`` times the designer's (Ostrowski: a congruence scales each eigenvalue by a
    factor between those of ``P``)."""
    feedback = design_feedback(load_scenario(name))
    assert feedback.success, feedback.message
    scenario = feedback.applied_to(load_scenario(name))  # the region and rate the file states
    P, K, rate = (  # as controller.json carries them
        np.array(json.loads(json.dumps(a.tolist())))
        for a in (feedback.P, feedback.K, np.array(feedback.rate))
    )
    margin, hull = contraction_check(scenario, P, K, float(rate), DEFAULT_SEGMENTS)
    assert np.array_equal(hull.vertices, feedback.vertices)
    designers = contraction_margin(P, K, hull.A, hull.B, float(rate), normalised=True)
    assert designers == pytest.approx(feedback.certified_margin, rel=1e-12, abs=1e-15)
    low, high = np.linalg.eigvalsh(P)[[0, -1]]
    assert margin < 0
    assert high * designers * (1 + 1e-9) <= margin <= low * designers * (1 - 1e-9)


def test_the_largest_rate_makes_the_margin_zero() -> None:
    """At ``contraction_rate`` (C) holds with no room: the metric-scale margin is 0 there, and
    negative below it."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 3, 3)) * 0.1 - np.eye(3)
    B = rng.normal(size=(5, 3, 1))
    K = np.zeros((1, 3))
    P = np.eye(3) + 0.1 * np.ones((3, 3))
    rate = contraction_rate(P, K, A, B)
    assert rate > 0
    assert contraction_margin(P, K, A, B, rate, normalised=True) == pytest.approx(0, abs=1e-12)
    assert contraction_margin(P, K, A, B, 0.9 * rate, normalised=True) < 0
    assert contraction_margin(P, K, A, B, 0.9 * rate) < 0
