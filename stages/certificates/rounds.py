"""The re-optimize rounds against the funnels (issue 16 part 4): a trust-region continuation that
shortens the nominals while their funnels keep Init covered (``reoptimize_rounds``), and for a law
held every ``h`` s the held law's funnels around the nominals the continuous law's rounds chose
(``held_funnels``)."""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Callable, Sequence

import numpy as np

from pipeline.io.progress import progress_bar
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.check import EarlierDesign
from pipeline.results.coverage import CoverageResult
from pipeline.results.funnel import FunnelStageResult
from pipeline.results.optimize import OptimizeResult, TrajectoryOptimization
from stages.certificates import CertificateRun, nominals
from stages.certificates.funnel_run import FunnelRun, funnel_coverage, funnel_stages
from stages.optimize import REOPTIMIZE, ReoptimizeInputs

log = logging.getLogger("pipeline.certificates")  # the run's logger: its lines are shown
FUNNEL_ROUNDS = 10  # re-optimize rounds against the funnels at most (issue 16 part 4)
FIRST_STEP = 0.1  # round 1 shortens a nominal by at most this fraction of its samples
GROW, MAX_STEP = 1.5, 0.4  # a kept trajectory's next step grows by GROW, up to MAX_STEP
SETTLED = 0.025  # a trajectory whose step falls below this is not optimized again
LEVEL_TOLERANCE = 1e-3  # a new funnel's level may fall this far below the kept one's
# held_funnels steps back at most this often, and only while at most this share of the
# trajectories falls short; beyond, the rounds again with the held law's funnels
# (quadrotor_hill_gusty at 5 ms: 4 of 9 held funnels certified in 127 s, then 7 step backs took
# 388 s more)
STEP_BACKS, SHORT_SHARE = 1, 1 / 3


# a kept nominal: its inputs (N, m), its simulation, the optimizer's result it came from
Nominal = tuple[np.ndarray, Trajectory, TrajectoryOptimization]


@dataclasses.dataclass(frozen=True, kw_only=True)
class Rounds:
    """Where the re-optimize rounds stand: per trajectory the kept nominal's inputs ``(N_i,
    m)``, its simulation and the optimizer's result it came from (the next round starts
    there), the kept funnels and their coverage of Init, and ``earlier[i]``, trajectory i's
    nominals kept before its current one (``Nominal``s, latest first)."""

    inputs: tuple[np.ndarray, ...]
    trajectories: tuple[Trajectory, ...]
    optimized: tuple[TrajectoryOptimization, ...]
    funnels: FunnelStageResult
    coverage: CoverageResult
    earlier: tuple[tuple[Nominal, ...], ...]

    @classmethod
    def first(
        cls,
        optimized: OptimizeResult,
        inputs: Sequence[np.ndarray],
        trajectories: Sequence[Trajectory],
        funnels: FunnelStageResult,
        coverage: CoverageResult,
    ) -> Rounds:
        """Before round 1: the optimize stage's nominals and the first funnels."""
        return cls(
            inputs=tuple(inputs), trajectories=tuple(trajectories),
            optimized=tuple(optimized.trajectories), funnels=funnels, coverage=coverage,
            earlier=((),) * len(inputs),
        )  # fmt: skip


def reoptimize_rounds(
    run: FunnelRun, start: Rounds, steps: Sequence[float] | None = None, label: str = ""
) -> Rounds:
    """The alternation of issue 16 part 4, as a continuation that keeps Init covered.

    Round k optimizes each nominal again against its current funnel's time-varying extents
    (stage ``reoptimize_k``), but to no fewer than ``ceil((1 - step_i) N_i)`` samples, and
    synthesizes and checks new funnels around the new nominals (``funnel_k``,
    ``coverage_funnel_k``; one whose kept funnel has co-designed gains (F6) is searched with
    them first, one whose kept funnel was designed again for a held law with that design
    first); a trajectory that did not move keeps its funnel.
    Trajectory i's new nominal and funnel are kept when that funnel is certified and its
    level holds at least what the kept one held (``_accepted``: both levels are fractions of
    the same required set, the start's cell of Init), or, at any certified level, when the
    round's certified funnels together still cover Init (``_kept``, ``coverage_funnel_k_lower``:
    a funnel holding 95% of its cell where its neighbours hold the rest); the mixed set is
    covered again (``coverage_funnel_k_kept``) and the round is kept only when it covers Init at
    least as well (``_covers_as_well``) and shortens the total T.
    A trust region on each step (``_next_step``): ``FIRST_STEP`` in round 1, ``GROW`` times
    longer after a kept move (at most ``MAX_STEP``), half as long after one not kept (or for
    every trajectory, when the round is not kept); a trajectory whose step falls below
    ``SETTLED``, or whose optimizer stopped above its floor while its new nominal was not kept
    (no shorter horizon is feasible against the funnel it keeps; ``_stepped``) and at or above
    the floor the halved step would set (the same search would stop there again), is not
    optimized again. Stop when every trajectory is settled,
    when no trajectory could be optimized again, or after ``FUNNEL_ROUNDS``. Returns where the
    rounds left ``start`` (a round is never kept unverified: its funnels passed ``check_funnel``
    and the certify-style rebuild in their stage). ``steps``: each trajectory's first step
    (default ``FIRST_STEP``; 0: not optimized again); ``label``: in the stages' names
    (``reoptimize<label>_k``, ``funnel<label>_k``) and the log's.

    Why (measured on quadrotor_hill_gusty_flythrough, ``--samples 2000``): one unbounded round
    shortened T from 11.8 s to ~3 s, but the new funnels, bound by their own LMI caps ('design': the
    local hull at the new nominal's high thrust and pitch) or by Goal, held only 11-21% of
    their required sets and Init went uncovered, so the round was discarded. Shorter steps
    keep each new nominal within reach of the funnel that was certified around the previous.
    With each funnel asked for its start's cell of Init (``stages.funnel``), measured with
    ``--method lbfgs --samples 2000 --jobs 2``: a 40% first step gave funnels holding 56-68%
    of their cells (Init 36% covered, round discarded); 10% steps are held whole. The old
    schedule (40% first, then only halved) ran out of rounds while every round still
    shortened (6 rounds, T 3.7-5.1 s, 1.37-1.89x the uncertified minimum time); this trust
    region kept all 10 rounds: T 2.7-3.3 s, 1.08-1.23x, certified. On quadrotor_hill_flythrough
    (``--certificate funnel --method lbfgs --samples 10000``) T 2.6-2.8 s, certified, 23 s wall
    at load ~1 (the previous schedule: 53 s); settling a trajectory whose optimizer stopped
    above its floor took that run from 232 s to 131 s wall at load ~6: three rounds in which
    no nominal could be shortened cost 36-46 s each. One whose new nominal was kept is not
    settled: its next search runs against the new funnel, which may allow a shorter horizon
    (on quadrotor_hill_gusty the four slowest demos' T then fell 0.1-0.4 s more).
    """
    scenario, runner, starts = run.scenario, run.runner, run.starts
    inputs, trajectories = list(start.inputs), list(start.trajectories)
    funnels, coverage, previous = start.funnels, start.coverage, list(start.optimized)
    superseded = list(start.earlier)
    step = [FIRST_STEP] * len(trajectories) if steps is None else list(steps)
    for k in range(1, FUNNEL_ROUNDS + 1):
        stage = _round_stage(k, label)
        active = [i for i in funnels.usable if step[i] >= SETTLED]
        if not active:
            log.info(f"[round{label} {k}] every trajectory settled: the previous funnels are kept")
            break
        previous = [
            dataclasses.replace(t, u=u, N=len(u)) for t, u in zip(previous, inputs, strict=True)
        ]
        shortest = [
            _floor(len(u), step[i]) if i in active else len(u) for i, u in enumerate(inputs)
        ]
        with progress_bar(len(previous), f"round {k}: optimized again", run.quiet) as advance:
            again: OptimizeResult = runner.run(
                REOPTIMIZE,
                ReoptimizeInputs(
                    scenario=run.optimized_scenario,
                    trajectories=tuple(previous),
                    funnels=funnels.funnels,
                    options=run.options,
                    shortest=tuple(shortest),
                    core=() if run.targets is None else run.targets.core,
                ),
                name=f"reoptimize{label}_{k}",
                describe=_describe_round,
                executor=run.executor,
                progress=advance,
            )
        moved = [
            i
            for i in active
            if again.trajectories[i].success and again.trajectories[i].N < len(inputs[i])
        ]
        stopped = [
            i
            for i in active
            if i not in moved or _stopped(again.trajectories[i].N, len(inputs[i]), step[i])
        ]
        if not moved:
            log.info(
                f"[round{label} {k}] no trajectory optimized again: the previous funnels are kept"
            )
            break
        new_inputs = [again.trajectories[i].u if i in moved else u for i, u in enumerate(inputs)]
        simulated = nominals(
            scenario, [starts[i] for i in moved], [new_inputs[i] for i in moved]
        )  # the others keep their nominal
        new_trajectories = list(trajectories)
        for i, trajectory in zip(moved, simulated, strict=True):
            new_trajectories[i] = trajectory
        new_funnels, new_coverage = funnel_stages(
            run, new_trajectories, stage=stage,
            reuse=[
                None if i in moved else (funnels.funnels[i], funnels.failure(i))
                for i in range(len(inputs))
            ],
            # a nominal whose kept funnel needed (F6) gains is searched with them first, and
            # one whose kept funnel was designed again for a held law with that design first
            earlier=tuple(EarlierDesign.of(f) for f in funnels.funnels),
        )  # fmt: skip
        lower = functools.partial(funnel_coverage, run, f"coverage_{stage}_lower")
        kept, lowered = _kept(funnels, new_funnels, moved, lower)
        tried = new_funnels  # the round's own funnels (new_funnels may become the mixed set)
        if kept != moved:  # unmoved trajectories already carry their kept funnels
            new_inputs = [new_inputs[i] if i in kept else u for i, u in enumerate(inputs)]
            new_trajectories = [
                new_trajectories[i] if i in kept else t for i, t in enumerate(trajectories)
            ]
            if lowered is not None:  # that mixed set is covered already
                new_funnels, new_coverage = lowered
            else:
                new_funnels = _mixed(funnels, new_funnels, kept)
                new_coverage = funnel_coverage(run, f"coverage_{stage}_kept", new_funnels)
        before = _total_T(trajectories, funnels.usable)
        after = _total_T(new_trajectories, new_funnels.usable)
        shorter = after < before and len(new_funnels.usable) >= len(funnels.usable)
        if not (shorter and _covers_as_well(new_coverage, coverage)):
            why = (
                f"total T {after:.2f} s against {before:.2f} s, Init "
                f"{100 * new_coverage.covered_fraction:.1f}% covered against "
                f"{100 * coverage.covered_fraction:.1f}%"
            )
            if not kept:  # every new funnel fell short of its cell with Init left uncovered
                levels = ", ".join(f"{tried.names[i]} {tried.funnels[i].rho:.3g}" for i in moved)
                why = f"no new funnel holds what the kept one did ({levels})"
            log.info(f"[round{label} {k}] not kept: {why}; the previous funnels are kept")
            kept = []
        for i in active:
            step[i] = _stepped(step[i], stopped=i in stopped, kept=i in kept)
        if not kept:
            continue
        log.info(
            f"[round{label} {k}] kept: total T {before:.2f} s -> {after:.2f} s, new nominals "
            f"kept for {len(kept)} of {len(active)} trajectories optimized again"
        )
        for i in kept:
            superseded[i] = ((inputs[i], trajectories[i], previous[i]), *superseded[i])
        inputs, trajectories, funnels, coverage = (
            new_inputs, new_trajectories, new_funnels, new_coverage
        )  # fmt: skip
        previous = [again.trajectories[i] if i in kept else t for i, t in enumerate(previous)]
    return Rounds(
        inputs=tuple(inputs), trajectories=tuple(trajectories), optimized=tuple(previous),
        funnels=funnels, coverage=coverage, earlier=tuple(superseded),
    )  # fmt: skip


def held_funnels(run: FunnelRun, searched: Rounds, certificate: CertificateRun) -> Rounds:
    """The funnels of the law held every ``run.feedback_period`` s around the nominals that
    the continuous law's rounds chose (``searched``; stage ``funnel_held``).

    Where a funnel the search certified is dropped or Init is covered less than the search
    covered it, each trajectory whose held funnel holds less than its continuous one did steps
    back to the nominal it kept before (``Rounds.earlier``, stages ``funnel_held_back_j``) until
    neither happens, none has an earlier nominal, more than ``SHORT_SHARE`` of them fall short
    or after ``STEP_BACKS`` steps; those that stepped back are then optimized again against
    their held funnels (``reoptimize_rounds``, label ``_held``, the others settled). Where one
    still happens, the rounds again from the optimize stage's nominals with the held law's
    funnels in every round (label ``_h``), and the better of the two is kept: the one covering
    Init as well as the other, then with fewer funnels dropped, then shorter. A design choice,
    nothing proven depends on it: the continuous law's funnels only choose the nominals, and
    every funnel shipped is one of the held law's, checked for it (``stages.funnel``) and by
    certify. It saves the held law's costlier funnels in every round: quadrotor_hill at 5 ms,
    the same nominals as the continuous law's (T 3.5-3.7 s), funnel stages 64 -> 40 s."""
    funnels, coverage = funnel_stages(run, searched.trajectories, stage="funnel_held")
    inputs, trajectories = list(searched.inputs), list(searched.trajectories)
    optimized, earlier = list(searched.optimized), [list(e) for e in searched.earlier]
    stepped: set[int] = set()
    back = 0

    def as_well() -> bool:
        return set(searched.funnels.usable) <= set(funnels.usable) and _covers_as_well(
            coverage, searched.coverage
        )

    while not as_well() and back < STEP_BACKS:
        held = _accepted(searched.funnels, funnels)
        short = [i for i in searched.funnels.usable if i not in held and earlier[i]]
        if not short or len(short) > SHORT_SHARE * len(trajectories):
            break
        back += 1
        for i in short:
            inputs[i], trajectories[i], optimized[i] = earlier[i].pop(0)
        stepped.update(short)
        log.info(
            f"[funnel_held] {', '.join(searched.funnels.names[i] for i in short)} back to the "
            "nominal kept before: its held law's funnel holds less than the continuous law's"
        )
        funnels, coverage = funnel_stages(
            run, trajectories, stage=f"funnel_held_back_{back}",
            reuse=[None if i in short else (funnels.funnels[i], funnels.failure(i))
                   for i in range(len(trajectories))],
        )  # fmt: skip
    held_rounds = Rounds(
        inputs=tuple(inputs), trajectories=tuple(trajectories), optimized=tuple(optimized),
        funnels=funnels, coverage=coverage, earlier=tuple(map(tuple, earlier)),
    )  # fmt: skip
    if not as_well():
        log.info(
            f"[funnel_held] {len(funnels.usable)} funnels certified against "
            f"{len(searched.funnels.usable)}, Init {100 * coverage.covered_fraction:.1f}% "
            f"covered against {100 * searched.coverage.covered_fraction:.1f}%: the rounds again "
            "with the held law's funnels in every round"
        )
        first = list(certificate.trajectories)
        funnels, coverage = funnel_stages(run, first, stage="funnel_h")
        again = reoptimize_rounds(
            run, Rounds.first(certificate.optimized, certificate.inputs, first, funnels, coverage),
            label="_h",
        )  # fmt: skip
        return min(again, held_rounds, key=_shortfall)
    if not stepped:
        return held_rounds
    steps = [FIRST_STEP if i in stepped else 0.0 for i in range(len(trajectories))]
    return reoptimize_rounds(run, held_rounds, steps, label="_held")


def _shortfall(rounds: Rounds) -> tuple[bool, float, int, float]:
    """What ``held_funnels`` minimises between two ends of the rounds: Init not covered, the
    part of it left uncovered, the funnels dropped, the total T of the certified nominals."""
    usable, covered = rounds.funnels.usable, rounds.coverage.covered
    return (
        not covered,
        0.0 if covered else -rounds.coverage.covered_fraction,  # not its last bits (Init covered)
        len(rounds.trajectories) - len(usable),
        _total_T(rounds.trajectories, usable),
    )


def _total_T(trajectories: Sequence[Trajectory], usable: Sequence[int]) -> float:
    """The summed horizon (s) of the trajectories whose funnels are certified (``usable``)."""
    return sum(trajectories[i].duration for i in usable)


def _kept(
    before: FunnelStageResult,
    after: FunnelStageResult,
    moved: Sequence[int],
    coverage: Callable[[FunnelStageResult], CoverageResult],
) -> tuple[list[int], tuple[FunnelStageResult, CoverageResult] | None]:
    """The trajectories of ``moved`` whose new nominal and funnel a round keeps: every one
    certified (usable) when the mixed set with all of them (``coverage`` of it) still covers
    Init, with that set and its coverage; else those whose level holds at least what the kept
    one held (``_accepted``), and None. A lower level is sound where Init stays covered:
    coverage is computed from the funnels themselves, each certified at its own level."""
    held = [i for i in _accepted(before, after) if i in moved]
    certified = [i for i in after.usable if i in moved]
    if held != certified:
        mixed = _mixed(before, after, certified)
        covered = coverage(mixed)
        if covered.covered:
            return certified, (mixed, covered)
    return held, None


def _covers_as_well(new: CoverageResult, old: CoverageResult) -> bool:
    """``new`` covers Init whenever ``old`` does (the covered flag, not the volume fraction,
    whose sum of box volumes may differ in the last bits), else at least as large a part."""
    return new.covered or (not old.covered and new.covered_fraction >= old.covered_fraction)


def _floor(samples: int, step: float) -> int:
    """The fewest samples a round's search from ``samples`` may reach with ``step``."""
    return math.ceil((1 - step) * samples)


def _stopped(found: int, samples: int, step: float) -> bool:
    """Whether the search from ``samples`` with ``step`` stopped at ``found`` samples above its
    ``_floor``, the limit against the funnel it ran against, and at or above the floor the
    halved step sets: searched again, it would stop there again, while a floor above ``found``
    asks for a longer nominal, whose funnel may hold what it must."""
    return found > _floor(samples, step) and found >= _floor(samples, step / 2)


def _stepped(step: float, *, stopped: bool, kept: bool) -> float:
    """A trajectory's step after a round: 0 (settled) when its search ``stopped`` (``_stopped``:
    above its floor, and at or above the halved step's) and its new nominal was not kept (no
    shorter horizon is feasible against the funnel it keeps), else ``_next_step`` (a kept
    nominal is optimized next against its new funnel)."""
    return 0.0 if stopped and not kept else _next_step(step, kept)


def _next_step(step: float, kept: bool) -> float:
    """The fraction of its samples a trajectory may lose next round: ``GROW`` times ``step``
    after a kept move (at most ``MAX_STEP``), half of it after one that was not kept."""
    return min(GROW * step, MAX_STEP) if kept else step / 2


def _accepted(
    before: FunnelStageResult, after: FunnelStageResult, tolerance: float = LEVEL_TOLERANCE
) -> tuple[int, ...]:
    """Indices i whose new funnel is usable and whose level holds at least what the kept one
    held: ``rho_after_i >= rho_before_i - tolerance`` (both fractions of the same required set,
    0 for a dropped funnel)."""
    old, new = before.levels, after.levels
    return tuple(i for i in after.usable if new[i] >= old[i] - tolerance)


def _mixed(
    before: FunnelStageResult, after: FunnelStageResult, kept: Sequence[int]
) -> FunnelStageResult:
    """The funnels of ``after`` for the trajectories in ``kept``, those of ``before`` for the
    others (each certified around its own nominal, which the caller keeps with it)."""
    source = [after if i in kept else before for i in range(len(before.funnels))]
    usable = tuple(i for i, result in enumerate(source) if i in result.usable)
    rejected = tuple(
        f"{result.names[i]} dropped: {result.failure(i)}"
        for i, result in enumerate(source)
        if i not in result.usable
    )
    levels = [source[i].funnels[i].rho for i in usable]
    return dataclasses.replace(
        before,
        funnels=tuple(result.funnels[i] for i, result in enumerate(source)),
        usable=usable,
        rejected=rejected,
        success=len(usable) == len(source),
        message=f"new funnels kept for {len(kept)} of {len(source)} trajectories; "
        f"{len(usable)} certified"
        + (f", levels {min(levels):.3f} to {max(levels):.3f}" if levels else ""),
    )


def _round_stage(k: int, label: str = "") -> str:
    """The funnel stage of re-optimize round ``k`` (0: the first funnels) of the rounds
    ``label`` names (``reoptimize_rounds``)."""
    return f"funnel{label}" if k == 0 else f"funnel{label}_{k}"


def _describe_round(result: OptimizeResult) -> str:
    """A funnel round's line: the trajectories optimized again, and those already settled (at
    their shortest allowed horizon) named on one line, not one sentence each."""
    if result.success:
        return result.message
    settled = [
        t.demo for t in result.trajectories if not t.success and "may not be shortened" in t.message
    ]
    failed = [
        t.message
        for t in result.trajectories
        if not t.success and "may not be shortened" not in t.message
    ]
    again = sum(1 for t in result.trajectories if t.success)
    parts = [f"searched again for {again} of {len(result.trajectories)} trajectories"]
    if settled:
        parts.append(f"{len(settled)} already at their shortest horizon ({', '.join(settled)})")
    return "; ".join(parts + failed)
