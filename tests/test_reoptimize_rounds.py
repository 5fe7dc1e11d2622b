"""The re-optimize rounds' continuation (issue 16 part 4, ``funnels.reoptimize_rounds``):
per-trajectory acceptance of a round's new funnels on constructed funnel sets, the mixed set
they leave, the trust region on each step, and the floor on a round's horizon
(``optimize_from(..., N_min=...)``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from pipeline import load_scenario
from pipeline.numerics.optimize.footprint import ConstraintMargins
from stages.certificates import rounds
from stages.coverage import cover_balls
from stages.feedback import design_feedback
from stages.funnel import FunnelStageResult
from stages.optimize import (
    OptimizeOptions,
    TrajectoryOptimization,
    optimize_from,
    reoptimize_with_funnels,
)
from tests.helpers.funnels import make_funnel


def _stage(levels: list[float], usable: list[int], scale: float, n: int = 2) -> FunnelStageResult:
    """Funnels of ``n`` states with ``P[0] = scale * I`` and the given levels; the others are
    dropped (``rejected`` names them)."""
    N = 3
    funnels = tuple(
        make_funnel(np.zeros((N, 1, n)), np.broadcast_to(scale * np.eye(n), (N + 1, n, n)), rho)
        for rho in levels
    )
    names = tuple(f"demo_{i}" for i in range(len(levels)))
    return FunnelStageResult(
        names=names, funnels=funnels, initial_radii=np.ones(len(levels)), usable=tuple(usable),
        rejected=tuple(f"{names[i]} dropped: for the test" for i in range(len(levels))
                       if i not in usable),
        success=len(usable) == len(levels), message="",
    )  # fmt: skip


def test_a_new_funnel_is_kept_only_where_it_holds_what_the_kept_one_held():
    before = _stage([1.0, 1.0, 0.5, 0.3], usable=[0, 1, 2], scale=1.0)
    after = _stage([1.0 - 5e-4, 0.2, 0.6, 0.9], usable=[0, 1, 3], scale=4.0)
    # 0: within the tolerance; 1: shrank; 2: dropped now; 3: dropped before, certified now.
    assert rounds._accepted(before, after) == (0, 3)
    assert rounds._accepted(before, after, tolerance=1e-4) == (3,)


def test_a_lower_level_is_kept_only_while_the_round_still_covers_init():
    """``_kept``: with Init still covered by the mixed set of every certified new funnel, a
    funnel that shrank is kept too (never one dropped now, nor one that did not move); without
    that coverage only those holding what the kept one held (``_accepted``)."""
    before = _stage([1.0, 1.0, 0.5, 0.3], usable=[0, 1, 2], scale=1.0)
    after = _stage([1.0 - 5e-4, 0.95, 0.6, 0.9], usable=[0, 1, 3], scale=4.0)
    seen = []

    def coverage(covered):
        def cover(mixed):
            seen.append(mixed.levels.tolist())
            return SimpleNamespace(covered=covered)

        return cover

    kept, lowered = rounds._kept(before, after, [0, 1, 2, 3], coverage(True))
    assert kept == [0, 1, 3]
    assert seen == [[1.0 - 5e-4, 0.95, 0.5, 0.9]]  # 2 keeps its old funnel: dropped now
    assert lowered is not None and lowered[0].levels.tolist() == seen[0]  # the set covered
    assert rounds._kept(before, after, [0, 1, 2, 3], coverage(False)) == ([0, 3], None)
    assert rounds._kept(before, after, [0, 2, 3], coverage(True)) == ([0, 3], None)  # 1 unmoved
    assert len(seen) == 2  # nothing lower to try: coverage not computed again


def test_the_mixed_set_takes_each_trajectorys_funnel_from_where_it_was_kept():
    before = _stage([1.0, 1.0, 0.5], usable=[0, 1], scale=1.0)
    after = _stage([1.0, 0.2, 0.8], usable=[0, 1, 2], scale=4.0)
    mixed = rounds._mixed(before, after, kept=[0, 2])
    assert mixed.funnels[0] is after.funnels[0] and mixed.funnels[2] is after.funnels[2]
    assert mixed.funnels[1] is before.funnels[1]
    assert mixed.usable == (0, 1, 2) and mixed.success and not mixed.rejected
    np.testing.assert_array_equal(mixed.levels, [1.0, 1.0, 0.8])
    np.testing.assert_array_equal(mixed.starts[:, 0, 0], [4.0, 1.0, 4.0])
    # Keeping a funnel that is dropped: it stays dropped, and the reason comes with it.
    dropped = rounds._mixed(before, _stage([1.0, 1.0, 1.0], [0, 1], 1.0), kept=[2])
    assert dropped.usable == (0, 1) and not dropped.success
    assert dropped.rejected == ("demo_2 dropped: for the test",)


def test_the_mixed_set_covers_what_its_initial_ellipsoids_cover():
    """Coverage is re-checked on the mixed set: on the double integrator's Init, a mix whose
    one kept funnel shrank leaves a gap the unmixed set did not."""
    scenario = load_scenario("double_integrator", check_demos=False)
    lower, upper = np.asarray(scenario.init_lower), np.asarray(scenario.init_upper)
    center = (lower + upper) / 2
    wide = float(np.linalg.norm(upper - lower))  # a ball of this radius holds the whole box
    kept = _stage([wide, wide], usable=[0, 1], scale=1.0, n=scenario.n)
    narrow = _stage([0.1 * wide, 0.1 * wide], usable=[0, 1], scale=1.0, n=scenario.n)
    centers = np.stack([center, center])
    whole = cover_balls(scenario, kept.starts, centers, kept.levels)
    assert whole.covered_fraction == 1.0
    mixed = rounds._mixed(kept, narrow, kept=[0])
    assert cover_balls(scenario, mixed.starts, centers, mixed.levels).covered_fraction == 1.0
    both = rounds._mixed(kept, narrow, kept=[0, 1])
    assert cover_balls(scenario, both.starts, centers, both.levels).covered_fraction < 1.0


def test_a_rounds_horizon_stays_above_its_floor():
    """``N_min``: the continuation stops at the floor where it would otherwise go shorter."""
    scenario = load_scenario("double_integrator")
    feedback = design_feedback(scenario)
    margins = ConstraintMargins(input_margin=np.zeros(2), region_margin={}, gain=feedback.K)
    demo = scenario.demos[0]

    def shortest(N_min: int) -> TrajectoryOptimization:
        return optimize_from(
            scenario, demo.name, demo.x0, demo.us, margins, OptimizeOptions(),
            N_demo=len(demo.us), N_min=N_min,
        )  # fmt: skip

    free = shortest(1)
    assert free.success and free.N < free.N_demo
    floor = (free.N + free.N_demo) // 2
    bounded = shortest(floor)
    assert bounded.success and floor <= bounded.N < free.N_demo
    assert all(t.N >= floor for t in bounded.tries)


def test_one_floor_per_trajectory():
    scenario = load_scenario("double_integrator", check_demos=False)
    with pytest.raises(ValueError, match="1 shortest horizons for 0 trajectories"):
        reoptimize_with_funnels(scenario, [], [], OptimizeOptions(), shortest=[5])


def test_a_step_grows_after_a_kept_move_and_halves_after_one_that_was_not():
    step = rounds.FIRST_STEP
    grown = rounds._next_step(step, kept=True)
    assert grown == pytest.approx(rounds.GROW * step)
    assert rounds._next_step(grown, kept=False) == pytest.approx(grown / 2)
    assert rounds._next_step(rounds.MAX_STEP, kept=True) == rounds.MAX_STEP  # capped
    # halving settles a trajectory that keeps failing within a few rounds
    failing = [step]
    while failing[-1] >= rounds.SETTLED:
        failing.append(rounds._next_step(failing[-1], kept=False))
    assert len(failing) <= 4


def test_a_stopped_search_settles_a_trajectory_only_when_its_new_nominal_was_not_kept():
    """An optimizer that stopped above its floor settles its trajectory (step 0) unless the
    round kept its new nominal: then it is optimized again, against its new funnel."""
    step = rounds.FIRST_STEP
    assert rounds._stepped(step, stopped=True, kept=False) == 0.0
    assert rounds._stepped(step, stopped=True, kept=True) == rounds._next_step(step, True)
    assert rounds._stepped(step, stopped=False, kept=False) == rounds._next_step(step, False)
    assert rounds._stepped(step, stopped=False, kept=True) > step >= rounds.SETTLED


def test_a_search_is_stopped_only_where_the_halved_steps_floor_would_find_it_again():
    """From 40 samples with a step of 0.1 the floor is 36 and the halved step's 38: a search
    that reached 36 is not stopped; one at 37 is not either (a floor of 38 asks for a longer
    nominal); one at 38 or 39 would stop there again, so it is."""
    assert [rounds._stopped(found, 40, 0.1) for found in (36, 37, 38, 39)] == [
        False, False, True, True
    ]  # fmt: skip
    assert not rounds._stopped(40, 40, 0.0)  # no step: at its floor


def test_covering_as_well_reads_the_covered_flag_not_the_last_bits_of_the_volume():
    def coverage(covered: bool, fraction: float) -> SimpleNamespace:
        return SimpleNamespace(covered=covered, covered_fraction=fraction)

    assert rounds._covers_as_well(coverage(True, 1 - 1e-16), coverage(True, 1 + 2e-16))
    assert not rounds._covers_as_well(coverage(False, 0.999), coverage(True, 1.0))
    assert rounds._covers_as_well(coverage(False, 0.9), coverage(False, 0.8))
    assert not rounds._covers_as_well(coverage(False, 0.7), coverage(False, 0.8))


class _HeldStages:
    """``funnel_stages`` and ``reoptimize_rounds`` of ``stages.certificates.rounds`` replaced:
    each held funnel stage returns the next of ``results`` ((levels, usable, covered) per
    call) and records what it was asked; the rounds return their start, recording it."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, results: list[tuple]) -> None:
        self.results = list(results)
        self.stages: list[tuple[str, list, list | None]] = []
        self.rounds: list[tuple[str, tuple, tuple, list[float] | None]] = []
        monkeypatch.setattr(rounds, "funnel_stages", self.funnel_stages)
        monkeypatch.setattr(rounds, "reoptimize_rounds", self.reoptimize_rounds)

    def funnel_stages(self, run, trajectories, stage="funnel", reuse=None, earlier=()):
        self.stages.append((stage, list(trajectories), None if reuse is None else list(reuse)))
        levels, usable, covered = self.results.pop(0)
        coverage = SimpleNamespace(covered=covered, covered_fraction=1.0 if covered else 0.99)
        return _stage(levels, usable, scale=1.0), coverage

    def reoptimize_rounds(self, run, start, steps=None, label=""):
        steps = None if steps is None else list(steps)
        self.rounds.append((label, start.trajectories, start.optimized, steps))
        return start


class _Path(str):
    """A nominal trajectory named by a string, of one second (``Trajectory.duration``)."""

    duration = 1.0


def _paths(*names: str) -> tuple[_Path, ...]:
    return tuple(map(_Path, names))


def _searched(earlier: tuple) -> rounds.Rounds:
    """Where the continuous law's rounds left three trajectories (levels 1, Init covered)."""
    return rounds.Rounds(
        inputs=tuple(np.zeros((k, 1)) for k in (4, 4, 4)), trajectories=_paths("a2", "b2", "c2"),
        optimized=("A2", "B2", "C2"), funnels=_stage([1.0, 1.0, 1.0], [0, 1, 2], scale=1.0),
        coverage=SimpleNamespace(covered=True, covered_fraction=1.0), earlier=earlier,
    )  # fmt: skip


_CERTIFICATE = SimpleNamespace(
    trajectories=_paths("a0", "b0", "c0"), inputs=(np.zeros((6, 1)),) * 3,
    optimized=SimpleNamespace(trajectories=("A0", "B0", "C0")),
)  # fmt: skip


def test_the_held_laws_funnels_are_kept_around_the_searched_nominals_when_they_cover_as_well(
    monkeypatch,
):
    """``held_funnels``: one held stage around the nominals the continuous rounds chose, kept
    when Init is covered as well (a lower level included: coverage is the funnels' own)."""
    stages = _HeldStages(monkeypatch, [([1.0, 0.95, 1.0], [0, 1, 2], True)])
    held = rounds.held_funnels(SimpleNamespace(), _searched(((), (), ())), _CERTIFICATE)
    assert [stage for stage, _, _ in stages.stages] == ["funnel_held"]
    assert stages.stages[0][1] == ["a2", "b2", "c2"] and not stages.rounds
    assert held.trajectories == ("a2", "b2", "c2") and held.funnels.levels[1] == 0.95


def test_a_trajectory_whose_held_funnel_falls_short_steps_back_and_is_optimized_again(
    monkeypatch,
):
    """Init left uncovered: only the trajectory whose held funnel holds less than its
    continuous one steps back to the nominal it kept before (the others' funnels reused), and
    it alone is optimized again against its held funnel (the others settled: step 0)."""
    earlier = (
        ((np.zeros((5, 1)), _Path("a1"), "A1"),),
        ((np.zeros((5, 1)), _Path("b1"), "B1"),),
        (),
    )
    stages = _HeldStages(
        monkeypatch, [([1.0, 0.9, 1.0], [0, 1, 2], False), ([1.0, 1.0, 1.0], [0, 1, 2], True)]
    )
    held = rounds.held_funnels(SimpleNamespace(), _searched(earlier), _CERTIFICATE)
    (first, _, _), (back, trajectories, reuse) = stages.stages
    assert (first, back) == ("funnel_held", "funnel_held_back_1")
    assert trajectories == ["a2", "b1", "c2"]
    assert reuse is not None and reuse[1] is None and reuse[0] is not None and reuse[2] is not None
    assert stages.rounds == [
        ("_held", ("a2", "b1", "c2"), ("A2", "B1", "C2"), [0.0, rounds.FIRST_STEP, 0.0])
    ]
    assert held.optimized == ("A2", "B1", "C2") and held.inputs[1].shape == (5, 1)
    assert held.earlier[1] == ()  # the nominal it stepped back to is its current one


def test_with_no_earlier_nominal_to_step_back_to_the_rounds_run_again_with_the_held_law(
    monkeypatch,
):
    """A short trajectory with no earlier nominal and Init uncovered: the rounds again from the
    optimize stage's nominals, with the held law's funnels in every round (label ``_h``)."""
    stages = _HeldStages(
        monkeypatch, [([1.0, 1.0, 0.8], [0, 1, 2], False), ([1.0, 1.0, 1.0], [0, 1, 2], True)]
    )
    held = rounds.held_funnels(SimpleNamespace(), _searched(((), (), ())), _CERTIFICATE)
    assert [stage for stage, _, _ in stages.stages] == ["funnel_held", "funnel_h"]
    assert stages.stages[1][1] == ["a0", "b0", "c0"]
    assert stages.rounds == [("_h", ("a0", "b0", "c0"), ("A0", "B0", "C0"), None)]
    assert held.trajectories == ("a0", "b0", "c0")  # covers Init, the held stage did not


def test_a_trajectory_steps_back_one_kept_nominal_at_a_time_latest_first(monkeypatch):
    """With two step backs allowed (``STEP_BACKS``; ``funnel_held_back_1``, ``_2``), each to the
    nominal kept just before; still uncovered after both, the ``_h`` rounds run, and the better
    end is kept: here the step backs' (neither covers Init; the ``_h`` rounds dropped a
    funnel)."""
    monkeypatch.setattr(rounds, "STEP_BACKS", 2)
    earlier = (
        (),
        ((np.zeros((5, 1)), _Path("b1"), "B1"), (np.zeros((6, 1)), _Path("b0"), "B0")),
        (),
    )
    stages = _HeldStages(
        monkeypatch,
        [
            ([1.0, 0.5, 1.0], [0, 1, 2], False),
            ([1.0, 0.7, 1.0], [0, 1, 2], False),
            ([1.0, 0.9, 1.0], [0, 1, 2], False),
            ([1.0, 0.2, 1.0], [0, 2], False),
        ],
    )
    searched = _searched(earlier)
    held = rounds.held_funnels(SimpleNamespace(), searched, _CERTIFICATE)
    names = [stage for stage, _, _ in stages.stages]
    assert names == ["funnel_held", "funnel_held_back_1", "funnel_held_back_2", "funnel_h"]
    assert [trajectories[1] for _, trajectories, _ in stages.stages[1:3]] == ["b1", "b0"]
    assert held.trajectories == ("a2", "b0", "c2") and held.optimized[1] == "B0"
    assert held.funnels.levels[1] == 0.9 and held.earlier[1] == ()
    assert [label for label, *_ in stages.rounds] == ["_h"]  # no _held rounds: still uncovered


def test_when_many_held_funnels_fall_short_the_rounds_run_again_without_stepping_back(
    monkeypatch,
):
    """More than ``SHORT_SHARE`` of the trajectories short: no step back, the ``_h`` rounds."""
    earlier = tuple(((np.zeros((5, 1)), _Path(f"{name}1"), name.upper()),) for name in "abc")
    stages = _HeldStages(
        monkeypatch, [([0.5, 0.5, 1.0], [0, 1, 2], False), ([1.0, 1.0, 1.0], [0, 1, 2], True)]
    )
    held = rounds.held_funnels(SimpleNamespace(), _searched(earlier), _CERTIFICATE)
    assert [stage for stage, _, _ in stages.stages] == ["funnel_held", "funnel_h"]
    assert held.trajectories == ("a0", "b0", "c0")
