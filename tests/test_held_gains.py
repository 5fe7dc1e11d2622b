"""A held law's funnels keep the LQR gains (``stages.funnel``, ``synthesize_funnel(codesign=...)``).

(F6) co-designs the gains with the metric for the continuous law; its program cannot see the push
its own gains give a held law ((I6) is bilinear in them), so a co-designed funnel's push is what
the design never saw. On quadrotor_hill at 5 ms (round 1's nominals) the co-designed funnels'
push on the pitch rate was 10-30x the LQR gains' and none of them held the held law, after up to
32 solves each. So a held law is designed with the LQR gains only, first design and redesigns;
the continuous law keeps (F6). The order of the redesigns (``stages.funnel._designed``): an
earlier round's redesign first, then (I6')'s rows where the held check failed, on every piece,
and (I6)'s box.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import stages.funnel as stage
from pipeline.numerics.funnel import synthesis
from pipeline.numerics.funnel.check import EarlierDesign, HeldDesign
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from pipeline.numerics.verify.recertify import HeldLawBounds
from tests.helpers.robust import DISTURBANCE, double_integrator_case


def test_without_codesign_no_gains_are_codesigned(monkeypatch):
    """At eight times the tests' bound the LQR gains' funnel is rejected and (F6)'s passes
    (``test_robust_funnel``); with ``codesign=False`` (F6)'s program is never solved and the
    funnel returned is the LQR gains' (rejected, the (F6) family not named)."""
    scenario, trajectory, initial = double_integrator_case()
    bound = 8 * DISTURBANCE
    calls = []
    original = synthesis.codesign_gains

    def counted(program):
        calls.append(program.multiplier)
        return original(program)

    monkeypatch.setattr(synthesis, "codesign_gains", counted)
    lqr = synthesize_funnel(
        scenario, trajectory, initial=initial, disturbance=bound, codesign=False
    )
    assert calls == [] and "(F6)" not in lqr.message and not lqr.success, lqr.message
    designed = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=bound)
    assert calls and designed.success and "(F6)" in designed.message, designed.message


def _designs(
    monkeypatch,
    period: float,
    verdicts: list[tuple[str | None, tuple[int, ...]]],
    earlier_held: HeldDesign | None = None,
    returned: list | None = None,
) -> list[dict]:
    """The keyword arguments of every ``synthesize_funnel`` call of the stage's design of one
    funnel (``earlier_held``: the task's ``EarlierDesign.held``), each design's held-law check
    scripted by ``verdicts`` in order (then rejected with no failing interval); ``returned``
    gets the funnel and verdict the stage returns."""
    scenario, trajectory, initial = double_integrator_case()
    seen: list[dict] = []
    found = dataclasses.replace(
        stage._ends_outside(scenario, trajectory, "scripted"),
        rho=0.5,
        success=True,
        multiplier=3.0,
    )

    def designed(designed_for, *args, **kwargs):
        seen.append({**kwargs, "scenario": designed_for})
        return found

    script = iter(verdicts)
    box = np.full(scenario.n, 0.01)
    monkeypatch.setattr(stage, "synthesize_funnel", designed)
    monkeypatch.setattr(
        stage, "_accepted", lambda *args, **kwargs: next(script, ("scripted: not held", ()))
    )
    monkeypatch.setattr(
        stage,
        "held_law_bounds",
        lambda *args, **kwargs: HeldLawBounds(
            hold=box, held_input=np.zeros(scenario.m), remainder=box
        ),
    )
    task = stage._Task(
        scenario=scenario, trajectory=trajectory, initial=initial[None], rate=0.0,
        disturbance=DISTURBANCE, period=period, earlier=EarlierDesign(held=earlier_held),
    )  # fmt: skip
    result = stage._designed(task)
    if returned is not None:
        returned.append(result)
    return seen


def test_a_held_law_is_designed_with_the_lqr_gains_only(monkeypatch):
    """Held every 5 ms: the first design and every redesign ((I6')'s pushed rows with the
    remainder box, on the failing intervals and then on every piece, then (I6)'s box) without
    (F6); the continuous law: one design, with it."""
    held = _designs(monkeypatch, 0.005, [])
    assert [kwargs["codesign"] for kwargs in held] == [False] * 4
    assert [kwargs["codesign"] for kwargs in _designs(monkeypatch, 0.0, [])] == [True]


def test_the_pushed_rows_go_first_where_the_held_check_failed(monkeypatch):
    """The held law's check fails on interval 3: the first redesign pushes interval 3 only; it
    fails on interval 5 too: the next pushes both; after ``PUSH_ATTEMPTS`` such designs, every
    piece, then (I6)'s box (no period); a design that passes ends the search."""
    failing = [("scripted: (F2) fails", (3,)), ("scripted: (F2) fails", (3, 5))]
    tried = [(kwargs.get("period", 0.0), kwargs.get("pushed")) for kwargs in
             _designs(monkeypatch, 0.005, failing)]  # fmt: skip
    assert stage.PUSH_ATTEMPTS == 2
    assert tried == [(0.0, None), (0.005, {3}), (0.005, {3, 5}), (0.005, None), (0.0, None)]
    passed = _designs(monkeypatch, 0.005, [("scripted: (F2) fails", (3,)), (None, ())])
    assert [kwargs.get("pushed") for kwargs in passed] == [None, {3}]


def test_an_earlier_rounds_redesign_is_tried_first_and_recorded(monkeypatch):
    """A task with an earlier round's redesign (``EarlierDesign.held``) designs with it first
    (its bound, input bounds, period, pushed intervals and first multiplier) and keeps that
    funnel when it holds the held law, recording what it was designed for with the multiplier that
    designed it as the next search's first; when it does not, the search runs as for any
    nominal. A redesign found that way is recorded too."""
    earlier = HeldDesign(
        disturbance=np.full(4, 0.07), input_lower=np.full(2, -0.9), input_upper=np.full(2, 0.9),
        period=0.005, pushed=(0, 2), from_multiplier=0.5,
    )  # fmt: skip
    returned: list = []
    kept = _designs(monkeypatch, 0.005, [(None, ())], earlier_held=earlier, returned=returned)
    assert len(kept) == 1 and kept[0]["pushed"] == {0, 2} and kept[0]["period"] == 0.005
    assert kept[0]["from_multiplier"] == 0.5 and kept[0]["codesign"] is False
    assert np.array_equal(kept[0]["disturbance"], earlier.disturbance)
    assert np.array_equal(kept[0]["scenario"].input_upper, earlier.input_upper)
    funnel, failure = returned[-1]
    assert failure is None and funnel.held == dataclasses.replace(earlier, from_multiplier=3.0)
    failing = [("scripted: not held", ()), ("scripted: (F2) fails", (3,)), (None, ())]
    tried = _designs(monkeypatch, 0.005, failing, earlier_held=earlier, returned=returned)
    assert [(kwargs.get("period", 0.0), kwargs.get("pushed")) for kwargs in tried] == [
        (0.005, {0, 2}), (0.0, None), (0.005, {3}),
    ]  # fmt: skip
    funnel, failure = returned[-1]
    assert failure is None and funnel.held is not None and funnel.held.pushed == (3,)
    continuous = _designs(monkeypatch, 0.0, [], earlier_held=earlier)
    assert len(continuous) == 1 and continuous[0].get("period", 0.0) == 0.0  # not held: unused
