"""The typed run summary: the verdict table, summary.json as valid JSON, and the round trip."""

from __future__ import annotations

import dataclasses
import json

import pytest

from pipeline.reporting.summary import ClaimKind, Summary, Verdict


@pytest.mark.parametrize(
    ("certified", "validated", "verdict"),
    [
        (True, True, Verdict.CERTIFIED_AND_VALIDATED),
        (True, False, Verdict.CERTIFIED_NOT_VALIDATED),
        (False, True, Verdict.NOT_CERTIFIED),
        (False, False, Verdict.NOT_CERTIFIED),
    ],
)
def test_the_verdict_of_a_finished_run(certified, validated, verdict):
    assert Verdict.of(certified=certified, validated=validated) is verdict


@pytest.fixture
def summary(synthesized_constant) -> Summary:
    _, out = synthesized_constant
    return Summary.from_json(json.loads((out / "summary.json").read_text()))


def test_summary_json_round_trips_through_the_typed_summary(synthesized_constant, summary):
    _, out = synthesized_constant
    document = json.loads((out / "summary.json").read_text())
    assert summary.to_json() == document
    assert summary.verdict is Verdict.CERTIFIED_AND_VALIDATED and summary.certified
    assert summary.certificate == document["certificate"] == "constant"  # --certificate constant
    assert all(d.funnel_level is None for d in summary.demos)  # no funnel in a constant run
    assert summary.certification.certified and summary.certification.contraction_margin < 0
    assert {c.kind for c in summary.claims} >= {
        ClaimKind.CERTIFIED,
        ClaimKind.STATISTICALLY_VALIDATED,
        ClaimKind.FALSIFICATION_SEARCHED,
    }
    with pytest.raises(dataclasses.FrozenInstanceError):
        summary.verdict = Verdict.FAILED  # type: ignore[misc]


def test_the_shipped_quadrotor_run_is_a_funnel_run(synthesized):
    """quadrotor_hill_flythrough ships the funnel certificate: its summary round-trips and names a
    certified funnel level in (0, 1] for every demo."""
    _, out = synthesized
    document = json.loads((out / "summary.json").read_text())
    summary = Summary.from_json(document)
    assert summary.to_json() == document
    assert summary.certificate == "funnel" and summary.certified
    levels = [d.funnel_level for d in summary.demos]
    assert all(level is not None and 0 < level <= 1 for level in levels), levels


def test_non_finite_numbers_are_written_as_null(summary):
    montecarlo = dataclasses.replace(
        summary.montecarlo, min_clearance=float("-inf"), min_goal_margin=float("nan")
    )
    broken = dataclasses.replace(
        summary,
        montecarlo=montecarlo,
        verdict=Verdict.CERTIFIED_NOT_VALIDATED,
        reasons=("Monte Carlo failure: 1 of 1000 closed-loop runs failed: non_finite 1",),
    )
    text = json.dumps(broken.to_json(), allow_nan=False)  # strict JSON: raises on NaN/inf
    document = json.loads(text)
    assert document["montecarlo"]["min_clearance"] is None
    assert document["verdict"]["text"] == (
        "certified but not validated: Monte Carlo failure: 1 of 1000 closed-loop runs failed: "
        "non_finite 1"
    )
    assert document["verdict"]["certified"] and not document["verdict"]["validated"]
    back = Summary.from_json(document)
    assert back.montecarlo.min_clearance != back.montecarlo.min_clearance  # NaN: unknown


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["verdict"].update(kind="fine"), "verdict: 'fine' is not one of"),
        (lambda d: d["headline"].pop("montecarlo_samples"), "headline.montecarlo_samples: missing"),
        (lambda d: d["demos"][0].update(T_demo="3"), "demos[0].T_demo: expected a number"),
        (lambda d: d["claims"][1].update(kind="proved"), "claims[1].kind: 'proved'"),
        (lambda d: d.pop("verdict"), "verdict: missing"),
    ],
)
def test_a_wrong_summary_json_names_the_field(summary, change, message):
    document = summary.to_json()
    change(document)
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        Summary.from_json(document)


def test_a_summary_without_a_certificate_is_a_constant_ones(summary):
    """``summary.json`` written before the funnel certificate existed reads as ``constant``."""
    document = summary.to_json()
    del document["certificate"]
    for demo in document["demos"]:
        for name in ("funnel_level", "funnel_binding", "funnel_seconds"):
            del demo[name]
    assert Summary.from_json(document).certificate == "constant"


@pytest.mark.parametrize(
    ("margin", "bound", "kind"),
    [
        (-1e-3, -1e-9, ClaimKind.CERTIFIED),
        (-1e-12, -1e-9, ClaimKind.NOT_ESTABLISHED),  # below 0, not below certify's bound
        (0.0, -1e-9, ClaimKind.NOT_ESTABLISHED),
    ],
)
def test_the_contraction_claim_uses_certifys_own_bound(margin, bound, kind):
    """A /1 file whose contraction eigenvalue is negative but within rounding of 0 is not
    certified by certify; its contraction claim must not say "certified" either."""
    from types import SimpleNamespace

    from pipeline.runtime.verdict import certificate_kinds

    check = SimpleNamespace(contraction_margin=margin, contraction_bound=bound, success=False)
    evidence = SimpleNamespace(certification=check, certificate="constant")
    assert certificate_kinds(evidence, certified=False)[0] is kind  # type: ignore[arg-type]


def test_a_funnels_clearance_is_a_lower_bound_within_the_polygons_slack():
    """``funnel_clearance``: the distance from a box to ellipses, each replaced by a polygon
    of 64 sides that circumscribes it: never above the exact distance, below it by at most
    the polygon's overshoot (1/cos(pi/64) - 1 of the largest semi-axis)."""
    import types

    import numpy as np
    import shapely

    from pipeline.runtime.shipped import SIDES, funnel_clearance

    scene = types.SimpleNamespace(unsafe={"wall": shapely.box(3.0, -5.0, 4.0, 5.0)})
    slack = 1 / np.cos(np.pi / SIDES) - 1
    # a unit circle at the origin: 2 from the wall; an ellipse with semi-axes 2 (x) and 1 (y)
    for shape, exact, axis in ((np.eye(2), 2.0, 1.0), (np.diag([4.0, 1.0]), 1.0, 2.0)):
        found = funnel_clearance(scene, np.zeros((1, 2)), shape[None], np.array([1.0]))
        assert exact - axis * slack - 1e-12 <= found <= exact
    # several times: the closest one counts; one touching the wall: 0
    centres = np.array([[0.0, 0.0], [1.5, 0.0], [2.5, 0.0]])
    found = funnel_clearance(scene, centres, np.broadcast_to(np.eye(2), (3, 2, 2)), np.ones(3))
    assert found == 0.0
    found = funnel_clearance(scene, centres[:2], np.broadcast_to(np.eye(2), (2, 2, 2)), np.ones(2))
    assert 0.5 - slack <= found <= 0.5


def test_the_shipped_funnels_level_text_names_what_sets_it_and_the_next_constraint():
    from pipeline.reporting.shipped import binding_text, span
    from pipeline.reporting.summary import FunnelSummary

    funnel = FunnelSummary(
        demo="demo_01",
        T=2.8,
        level=0.9999,
        binding="design",
        nearest="goal",
        nearest_level=1.054,
        extent_at_T=0.3,
        clearance=0.7,
        arrival=(17.3, 3.7),
        arrival_velocity=(7.0, -3.8),
        arrival_speed=8.0,
    )
    assert binding_text(funnel) == "design: cell held whole (next: goal at 1.05)"
    dropped = dataclasses.replace(funnel, binding="dropped", level=0.0)
    assert not dropped.shipped and binding_text(dropped) == "dropped (no funnel ships)"
    assert span([2.64, 2.8, 2.7]) == "2.6-2.8" and span([2.71, 2.74]) == "2.7"
    assert span([float("nan")]) == "n/a (none shipped)"
