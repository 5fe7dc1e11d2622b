"""The funnel certificate (issue 16): the funnel stages around the optimized nominals, then the
re-optimize rounds against the funnels (part 4), a trust-region continuation that keeps Init
covered, and the funnel controller (``safety-controller/2``). For a law held every ``h`` s the
rounds choose the nominals with the continuous law's funnels and the held law's are designed
around the nominals chosen (``held_funnels``).

Arrive and stay (issue 29 item 3): in a ``terminal: hold`` scenario the terminal controller is
designed first (``terminal.hold_design``, robust to the declared uncertainty's additive bound),
the optimize stages end every nominal in the core of its ellipsoid (``Targets``: Goal's extra
bounds replaced by a box inside ``CORE`` of its level, checked at the box's corners), every
funnel must end inside the ellipsoid (stage funnel's ``terminal``) and ``controller.json``
carries that controller. Why the core (double_integrator_hold, measured): without it the
nominals ended at Goal's corner, ~0.9 m from its centre at 0.14-0.47 m/s, outside every terminal
ellipsoid centred in Goal, and no run with a terminal controller was certified. Why the box
fills the ellipsoid (``CORE`` 1, not half its level): a box inside a correlated ellipsoid is small
(its corners add the correlated states' worst signs), so the nominals' ends stay far inside it
anyway, and each funnel's own end check (T2) keeps the room its tube needs; on quadrotor_hill
the half-level box cost two demos a sample (their shorter nominals failed on its near edges).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Callable, Sequence
from types import MappingProxyType

import numpy as np

from pipeline.io.executor import Executor
from pipeline.io.progress import progress_bar
from pipeline.model.scenario import CertificateName, Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.check import EarlierDesign, Funnel
from pipeline.numerics.terminal.design import (
    TerminalDesign,
    TerminalError,
    hold_design,
    hover_box,
    lqr_terminal,
)
from pipeline.numerics.terminal.fit import TerminalTarget
from pipeline.numerics.uncertainty import additive_bound
from pipeline.results.coverage import CoverageResult
from pipeline.results.feedback import FeedbackResult
from pipeline.results.funnel import FunnelStageResult
from pipeline.results.optimize import OptimizeOptions, OptimizeResult, TrajectoryOptimization
from pipeline.results.stage import Runner
from stages.certificates import CertificateRun, Shipped, Targets, nominals
from stages.controller import FUNNEL_CONTROLLER, FunnelControllerInputs
from stages.coverage import COVERAGE, CoverageInputs
from stages.funnel import FUNNEL, FunnelInputs
from stages.optimize import REOPTIMIZE, ReoptimizeInputs

log = logging.getLogger("pipeline.certificates")  # the run's logger: its lines are shown
FUNNEL_ROUNDS = 10  # re-optimize rounds against the funnels at most (issue 16 part 4)
FIRST_STEP = 0.1  # round 1 shortens a nominal by at most this fraction of its samples
GROW, MAX_STEP = 1.5, 0.4  # a kept trajectory's next step grows by GROW, up to MAX_STEP
SETTLED = 0.025  # a trajectory whose step falls below this is not optimized again
LEVEL_TOLERANCE = 1e-3  # a new funnel's level may fall this far below the kept one's
CORE = 1.0  # a hold run's nominals end in a box inside this fraction of the terminal level
# held_funnels steps back at most this often, and only while at most this share of the
# trajectories falls short; beyond, the rounds again with the held law's funnels
# (quadrotor_hill_gusty at 5 ms: 4 of 9 held funnels certified in 127 s, then 7 step backs took
# 388 s more)
STEP_BACKS, SHORT_SHARE = 1, 1 / 3


@dataclasses.dataclass(frozen=True, kw_only=True)
class FunnelRun:
    """What every funnel stage of one run shares.

    Attributes:
      feedback: the constant certificate (its metric assigns Init's cells to the starts).
      starts: (n,) per trajectory, the demonstrations' starts, which every nominal keeps.
      initial_radii: per trajectory, the constant ball's radius (I1), for a start owning no cell.
      options: the optimizer of the re-optimize rounds; quiet: no progress bars.
      targets: where the re-optimize rounds end the nominals (their ``scenario``) and the
        terminal controller the funnels must end in.
      feedback_period: the law is held every ``h`` s (0: continuous); the funnels must hold it.
    """

    scenario: Scenario
    runner: Runner
    executor: Executor
    feedback: FeedbackResult
    starts: Sequence[np.ndarray]
    initial_radii: Sequence[float]
    options: OptimizeOptions
    quiet: bool
    describe_coverage: Callable[[CoverageResult], str]
    targets: Targets | None = None
    feedback_period: float = 0.0

    @property
    def terminal(self) -> TerminalTarget | None:
        """The ellipsoid every funnel must end in (None: none)."""
        design = None if self.targets is None else self.targets.terminal
        return None if design is None else target_of(design)

    @property
    def optimized_scenario(self) -> Scenario:
        """The scenario the re-optimize rounds read (``Targets.scenario``)."""
        return self.scenario if self.targets is None else self.targets.scenario


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


@dataclasses.dataclass(frozen=True)
class FunnelCertificate:
    """A time-varying gain ``K_i[k]`` and metric ``P_i[k]`` per trajectory: the funnel stages,
    the re-optimize rounds, and the controller of the certified funnels."""

    name: CertificateName = "funnel"

    def targets(self, scenario: Scenario, period: float = 0.0) -> Targets:
        return rest_targets(scenario, period)

    def placed(
        self, scenario: Scenario, first: Targets, ends: Sequence[np.ndarray], period: float = 0.0
    ) -> Targets:
        return placed_targets(scenario, first, ends, period)

    def ship(self, run: CertificateRun) -> Shipped:
        # Each funnel is asked to hold its start's cell of Init (stage funnel); a start that
        # owns no cell asks for the constant ball's slice (I1), at the radius the optimizer kept
        # when its trajectory has no robustness radius.
        funnel_run = FunnelRun(
            scenario=run.scenario,
            runner=run.runner,
            executor=run.executor,
            feedback=run.feedback,
            starts=run.starts,
            initial_radii=[r.radius if r.radius > 0 else run.r_required for r in run.radii],
            options=run.options,
            quiet=run.quiet,
            describe_coverage=run.describe_coverage,
            targets=run.targets,
            feedback_period=run.feedback_period,
        )
        trajectories = list(run.trajectories)
        # a held law's funnels cost 2-3x the continuous law's (a held check that fails, then a
        # design with (I6')'s push): the rounds choose the nominals with the continuous law's
        # funnels, and the held law's are designed around the nominals chosen (``held_funnels``)
        held = funnel_run.feedback_period > 0
        search = funnel_run
        if held:
            search = dataclasses.replace(funnel_run, feedback_period=0.0)
            log.info(
                f"[funnel] the law is held every {funnel_run.feedback_period:g} s: the rounds "
                "choose the nominals with the continuous law's funnels, the held law's are then "
                "designed around them (funnel_held)"
            )
        funnels, coverage = funnel_stages(search, trajectories)
        if not funnels.usable:
            failure = f"no funnel certified: {funnels.message}"
            return Shipped(
                controller=None, trajectories=trajectories, failed_stage="funnel", failure=failure
            )
        rounds = reoptimize_rounds(
            search, Rounds.first(run.optimized, run.inputs, trajectories, funnels, coverage)
        )
        if held:
            rounds = held_funnels(funnel_run, rounds, run)
        final, funnels, coverage = list(rounds.trajectories), rounds.funnels, rounds.coverage
        if not funnels.usable:
            failure = f"no funnel certified for the held law: {funnels.message}"
            return Shipped(
                controller=None, trajectories=final, failed_stage="funnel_held", failure=failure
            )
        usable = funnels.usable
        controller = run.runner.run(
            FUNNEL_CONTROLLER,
            FunnelControllerInputs(
                scenario=run.scenario,
                names=tuple(run.names[i] for i in usable),
                trajectories=tuple(final[i] for i in usable),
                funnels=tuple(funnels.funnels[i] for i in usable),
                feedback_period=run.feedback_period,
                path=run.controller_path,
                terminal=None if run.targets is None else run.targets.terminal,
            ),
            rerun=True,  # always written from this run's certified results
            describe=lambda result: result.message,
            finish=run.publish,
        )
        return Shipped(
            controller=controller,
            trajectories=final,
            constant_trajectories=trajectories,
            funnels=funnels,
            funnel_coverage=coverage,
            report_stages=("funnel", "coverage_funnel", *(("funnel_held",) if held else ())),
        )


def funnel_stages(
    run: FunnelRun,
    trajectories: Sequence[Trajectory],
    stage: str = "funnel",
    reuse: Sequence[tuple[Funnel, str | None] | None] | None = None,
    earlier: tuple[EarlierDesign, ...] = (),
) -> tuple[FunnelStageResult, CoverageResult]:
    """Stages ``stage`` (``funnel``, ``funnel_k`` in re-optimize round k, the held law's
    ``funnel_held...``, ``held_funnels``: one funnel per trajectory, on ``executor``;
    ``reuse[i]``, when given, is trajectory i's funnel from an earlier round around the same
    nominal, with its verdict then; ``earlier[i]``: how an earlier round designed its kept
    funnel, tried first) and ``coverage_<stage>`` (Init by the usable funnels' initial
    ellipsoids ``E_i(0)``, each in its own metric ``P_i[0]``)."""
    scenario = run.scenario
    with progress_bar(len(trajectories), "funnels", run.quiet) as advance:
        funnels: FunnelStageResult = run.runner.run(
            FUNNEL,
            FunnelInputs(
                scenario=scenario,
                names=tuple(d.name for d in scenario.demos),
                trajectories=tuple(trajectories),
                P=run.feedback.certified_tube.P,
                radii=np.asarray(run.initial_radii),
                terminal=run.terminal,
                feedback_period=run.feedback_period,
                earlier=earlier,
            ),
            name=stage,
            describe=lambda result: result.message,
            executor=run.executor,
            progress=advance,
            reuse=reuse,
        )
    return funnels, _funnel_coverage(run, f"coverage_{stage}", funnels)


def _funnel_coverage(run: FunnelRun, stage: str, funnels: FunnelStageResult) -> CoverageResult:
    """Stage ``stage``: Init covered by the usable funnels' initial ellipsoids ``E_i(0)``, each
    in its own metric ``P_i[0]`` at its level."""
    return run.runner.run(
        COVERAGE,
        CoverageInputs(
            scenario=run.scenario,
            metrics=funnels.starts,
            centers=np.array(run.starts),
            radii=funnels.levels,
            noun="funnel start",
        ),
        name=stage,
        describe=run.describe_coverage,
    )


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
        lower = functools.partial(_funnel_coverage, run, f"coverage_{stage}_lower")
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
                new_coverage = _funnel_coverage(run, f"coverage_{stage}_kept", new_funnels)
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
