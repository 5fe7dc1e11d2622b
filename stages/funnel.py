"""Stage ``funnel``: a time-varying funnel around each final trajectory (the funnel certificate).

For trajectory ``i`` (``pipeline.numerics.funnel.synthesis``): gains ``K_i[k] (m, n)`` held on
``[t_k, t_k+1)``, metrics ``P_i[k] (n, n)`` at ``t_k`` and a level ``rho_i``, certifying that
every state starting in

    E_i(0) = {x : (x - x0_i)^T P_i[0] (x - x0_i) <= rho_i^2}

stays in the tube ``E_i(t)`` around the nominal, clear of Unsafe, inside the input bounds and
the scenario's ``state_bounds``, and ends in Goal; for every disturbance and parameter the
scenario declares (``uncertainty:``, held as one additive bound, ``pipeline.numerics.uncertainty``
(U1), by the funnel's (I5)). Each funnel is asked to hold its start's
cell of Init (``pipeline.numerics.funnel.cells``: Init cut into equal boxes, each given to the start
nearest its centre in the constant certificate's metric ``P``; funnel ``i`` must hold the corners
of the hull of its boxes), so that the funnels together hold Init when every level reaches 1.
A start that owns no box is asked for the part of Init that the constant certificate's ball of
radius ``r_i`` holds: its slice along Init's free directions ``S (n, D)``,

    Q_init_i = r_i^2 S (S^T P S)^-1 S^T.                                                    (I1)

Why cells (quadrotor_hill_gusty_flythrough, measured): the ball slice (I1) reached +-0.30 rad in
pitch and +-0.95 m/s in horizontal speed from every start, 4-6x what Init spans; on the same
nominals (T 3.3-3.7 s) funnels asked for (I1) held 57-70% of it, funnels asked for their cells held
all of it.

With a terminal ellipsoid (``terminal``, a ``terminal: hold`` run: ``terminal.hold_design``),
each funnel must also end inside it (``synthesize_funnel(terminal=...)``: (T2) in the program,
the exact containment level after the check); a nominal that ends outside has no funnel.

A funnel that ``pipeline.numerics.funnel.check`` rejects (re-checked here with numpy alone,
independently of the solver) or whose level is not positive is dropped, as a trajectory
without a robustness radius is in the constant certificate.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from pipeline.io.executor import Executor, SerialExecutor, preload_in_workers
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.cells import init_cells
from pipeline.numerics.funnel.check import EarlierDesign, Funnel, HeldDesign, check_funnel
from pipeline.numerics.funnel.law import LawOffset
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from pipeline.numerics.terminal.fit import TerminalTarget
from pipeline.numerics.uncertainty import declared_bound, held_state_bounds
from pipeline.numerics.verify.recertify import ShippedFunnel, held_law_bounds, recheck_as_shipped
from pipeline.results.funnel import FunnelStageResult as FunnelStageResult
from pipeline.results.stage import Stage, StageInputs

preload_in_workers(__name__)  # its chunks run in worker processes
# a funnel that does not hold the law held every h s is designed again for this multiple of the
# hold's box (funnel.law (I6)) added to the declared disturbance: the box is found on the first
# funnel, and the second funnel's own box is what certify checks (the multiple is its room)
HOLD_DESIGN = 1.25
PUSH_ATTEMPTS = 2  # designs with (I6')'s rows on the failing intervals only, before every piece


def initial_sets(scenario: Scenario, P: FloatArray, radii: FloatArray) -> FloatArray:
    """(k, n, n) ``Q_init_i`` of (I1): the slice of the ball ``||e||_P <= r_i`` along Init's
    free directions, for the metric ``P (n, n)`` and radii ``(k,)``."""
    P = np.asarray(P, dtype=np.float64)
    free = np.flatnonzero(np.asarray(scenario.init_upper) > np.asarray(scenario.init_lower))
    S = np.eye(P.shape[0])[:, free]  # (n, D)
    Q_slice = S @ np.linalg.solve(S.T @ P @ S, S.T)  # eq. (I1) with r = 1
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    return radii[:, None, None] ** 2 * Q_slice[None]


def required_sets(
    scenario: Scenario, starts: Sequence[FloatArray], P: FloatArray, radii: FloatArray
) -> list[FloatArray]:
    """Per start ``(n,)``, the ``Q_init (p, n, n)`` its funnel must hold: ``v v^T`` for each
    corner offset ``v`` of its cell of Init (``pipeline.numerics.funnel.cells``, assigned in the
    metric ``P (n, n)``), or the ball slice (I1) of radius ``radii[i]`` if it owns no cell."""
    corners = init_cells(
        scenario.init_lower, scenario.init_upper, np.asarray(starts, dtype=np.float64), P
    )
    balls = initial_sets(scenario, P, radii)
    return [
        np.einsum("pi,pj->pij", v, v) if len(v) else ball[None]
        for v, ball in zip(corners, balls, strict=True)
    ]


@dataclass(frozen=True, kw_only=True)
class _Task:
    """One funnel for a worker: the scenario (pickled to a worker process), the nominal,
    ``Q_init (p, n, n)`` (``v v^T`` per corner of its cell, or the ball slice (I1)) and the
    additive bound ``(n,)`` of the declared uncertainty (None: the exact model); the terminal
    ellipsoid it must end in (None: none); the period the law is held for (0: continuous); the
    box ``(n,)`` of the error on the state the law sees (``funnel.law`` (I7); None: exact);
    how an earlier round designed the trajectory's kept funnel, tried first (the default:
    nothing earlier)."""

    scenario: Scenario
    trajectory: Trajectory
    initial: FloatArray
    rate: float
    disturbance: FloatArray | None
    terminal: TerminalTarget | None = None
    period: float = 0.0
    measurement: FloatArray | None = None
    earlier: EarlierDesign = EarlierDesign()


def _accepted(
    scenario: Scenario,
    trajectory: Trajectory,
    funnel: Funnel,
    state_bounds: Mapping[str, tuple[float, float]],
    disturbance: FloatArray | None = None,
    period: float = 0.0,
    measurement: FloatArray | None = None,
) -> tuple[str | None, tuple[int, ...]]:
    """``(None, ())`` if ``funnel`` certifies its trajectory (for ``x' = f(x, u) + w``, ``|w| <=
    disturbance (n,)`` when given, the law held every ``period`` s when it is > 0 and seeing the
    state within ``measurement (n,)`` when given), else why it is dropped and the sample
    intervals where the certify-style rebuild found (F2) failing (none when something else
    failed first)."""
    if not funnel.success:
        return funnel.message, ()
    if not funnel.rho > 0:
        return f"funnel level {funnel.rho:.3g} is not positive", ()
    law = LawOffset.none(len(funnel.K), scenario.n, scenario.m, scenario.Ts)
    if disturbance is not None:
        law = law.with_disturbance(disturbance)
    failure = check_funnel(scenario, trajectory, funnel, state_bounds, law)
    if failure is not None:
        return f"rejected by the independent check: {failure}", ()
    # as the certify stage will see it: rebuilt from K, P and rho alone (its own enclosure), the
    # law tracking the reference interpolated on the grid the controller stage ships
    shipped = ShippedFunnel(K=funnel.K, P=funnel.P, rho=funnel.rho, rate=funnel.rate)
    again = recheck_as_shipped(
        scenario, trajectory, shipped, state_bounds, disturbance, period, measurement,
        multiple=False,
    )  # fmt: skip
    if not again.failure:
        return None, ()
    return f"rejected when rebuilt as certify does: {again.failure}", again.failing


def _ends_outside(scenario: Scenario, trajectory: Trajectory, why: str) -> Funnel:
    """The funnel of a nominal that ends outside the terminal ellipsoid: none (level 0)."""
    N, n, m = len(trajectory.us), scenario.n, scenario.m
    return Funnel(
        K=np.zeros((N, m, n)), P=np.tile(np.eye(n), (N + 1, 1, 1)), rho=0.0, rate=0.0,
        margins=np.full((N, 2), np.nan), boxes=np.zeros((N, 2, 0)), variables=(), vertices=(),
        enclosure=None, limits={}, binding="", seconds=0.0, success=False, message=why,
    )  # fmt: skip


def _funnel_in_worker(task: _Task) -> tuple[Funnel, str | None]:
    """The funnel of one task and why it is dropped (None: certified); its ``seconds``: the
    task's whole wall time (synthesis, the certify-style checks and a redesign for a held or
    measured law)."""
    start = time.perf_counter()
    funnel, failure = _designed(task)
    return replace(funnel, seconds=time.perf_counter() - start), failure


def _designed(task: _Task) -> tuple[Funnel, str | None]:
    scenario, terminal, end = task.scenario, task.terminal, task.trajectory.dense_xs[-1]
    if terminal is not None and not terminal.share(end) < 1:
        why = (
            f"the nominal ends at {np.round(end, 3).tolist()}, outside the terminal ellipsoid "
            f"({terminal.share(end):.3g} of its radius from its centre)"
        )
        return _ends_outside(scenario, task.trajectory, why), why
    bounds = held_state_bounds(scenario)
    measurement = task.measurement

    def verdict(funnel: Funnel) -> tuple[str | None, tuple[int, ...]]:
        """``_accepted`` for the task's own law and declaration (the scenario's bounds)."""
        return _accepted(
            scenario, task.trajectory, funnel, bounds, task.disturbance, task.period, measurement
        )

    if task.earlier.held is not None and task.period > 0:
        # an earlier round's redesign, around a nearby nominal of this trajectory, first: kept
        # when it holds the held law, else the search below as for any nominal
        again = _redesign(task, task.earlier.held, bounds)
        if verdict(again)[0] is None:
            return again, None
    # a held law keeps the LQR gains: (F6)'s program cannot see its own gains' push (I6)
    codesign = task.period <= 0
    funnel = synthesize_funnel(
        scenario, task.trajectory, state_bounds=bounds, initial=task.initial, rate=task.rate,
        disturbance=task.disturbance, terminal=terminal, codesign=codesign,
        codesign_first=task.earlier.codesigned,
    )  # fmt: skip
    failure, failing = verdict(funnel)
    boxed = task.period > 0 or measurement is not None
    if failure is None or not (boxed and funnel.success and funnel.rho > 0):
        return funnel, failure
    # (I6), (I7): the held law's and the measurement's terms are a box joined to the
    # disturbance; design for both (HOLD_DESIGN); a held law first with its push to first order
    # in the program and only (I6')'s remainder in the box (funnel.sampled)
    shipped = ShippedFunnel(K=funnel.K, P=funnel.P, rho=funnel.rho, rate=funnel.rate)
    held = held_law_bounds(
        scenario, task.trajectory, shipped, bounds, task.disturbance, task.period, measurement
    )
    if held is None:
        return funnel, failure
    declared = np.zeros(scenario.n) if task.disturbance is None else task.disturbance
    # the hold's input offset does not shrink with the grid: the design keeps room for it (its
    # input bounds narrowed by HOLD_DESIGN times the first funnel's; certify uses the true ones)
    lower = scenario.input_lower + HOLD_DESIGN * held.held_input
    upper = scenario.input_upper - HOLD_DESIGN * held.held_input
    if not np.all(lower < upper):
        lower, upper = scenario.input_lower, scenario.input_upper
    whose = "the hold's" if measurement is None else "the law's (hold and measurement)"

    def design(box: FloatArray, period: float, pushed: tuple[int, ...] | None) -> HeldDesign:
        return HeldDesign(
            disturbance=design_disturbance(declared, box, period, measurement is not None),
            input_lower=lower, input_upper=upper, period=period, pushed=pushed,
            from_multiplier=funnel.multiplier,
        )  # fmt: skip

    # (I6')'s rows first on the intervals where the held law's check failed (none when another
    # check did: the narrowed inputs and the remainder box may be all it needs), adding those
    # each such design fails on, while they are fewer than half; then on every piece (a piece's
    # rows double its LMIs, and the solve time grows faster); then (I6)'s box
    few = len(task.trajectory.us) / 2
    designs: list[tuple[str, FloatArray, HeldDesign]] = []
    if held.remainder is not None:
        push = f"{whose} push to first order, remainder |w_r| <= "
        if len(failing) < few:
            designs.append((push, held.remainder, design(held.remainder, task.period, failing)))
        designs.append((push, held.remainder, design(held.remainder, task.period, None)))
    designs.append((f"{whose} box |w_h| <= ", held.hold, design(held.hold, 0.0, None)))
    reasons = []
    attempts = 0
    while designs:
        what, box, asked = designs.pop(0)
        again = _redesign(task, asked, bounds)
        second, failing = verdict(again)
        if second is None:
            return again, None
        if asked.pushed is not None:
            attempts += 1
            more = tuple(sorted({*asked.pushed, *failing}))
            if attempts < PUSH_ATTEMPTS and len(asked.pushed) < len(more) < few:
                designs.insert(0, (what, box, replace(asked, pushed=more)))
            continue  # not reported: the design on every piece follows
        reasons.append(
            f"designed again for {what}{np.round(HOLD_DESIGN * box, 4).tolist()} on top of the "
            f"disturbance: {second}"
        )
    return funnel, "; ".join([failure, *reasons])


def design_disturbance(
    declared: FloatArray, box: FloatArray, period: float, measured: bool
) -> FloatArray:
    """(n,) the disturbance a held or measured law's redesign asks its program for: the declared
    ``(n,)`` plus ``HOLD_DESIGN`` times the law's ``box (n,)``, with the push to first order
    (``period > 0``) (I6')'s remainder only on the states the declaration pushes (when it pushes
    any and nothing is measured). A design choice, nothing proven depends on it (the held law's
    check, certify's, holds the whole remainder): a remainder on another state (quadrotor_hill:
    ~0.006 rad/s^2 on the pitch rate's derivative against 0.15 and 0.13 m/s^2 declared on the
    speeds') puts a third state under the S-procedure's corners and doubles the program
    (quadrotor_hill at 5 ms, when its rounds designed held funnels: the funnel stages 104 -> 87
    s, the rounds' levels as high or higher)."""
    if period > 0 and not measured and np.any(declared > 0):
        box = np.where(declared > 0, box, 0.0)
    return np.asarray(declared + HOLD_DESIGN * box, dtype=np.float64)


def _redesign(
    task: _Task, asked: HeldDesign, state_bounds: Mapping[str, tuple[float, float]]
) -> Funnel:
    """The funnel of ``task`` designed for a held or measured law as ``asked`` (its bound, input
    bounds, period, pushed intervals and first multiplier), on the capped boxes, with the LQR
    gains for a held law, recording ``asked`` (``Funnel.held``) with the multiplier that
    designed it as the first (where a round's next search for the trajectory starts: upwards
    from there, so a later round tries no smaller multiplier unless that first try fails)."""
    scenario = task.scenario
    if not (
        np.array_equal(asked.input_lower, scenario.input_lower)
        and np.array_equal(asked.input_upper, scenario.input_upper)
    ):
        scenario = replace(scenario, input_lower=asked.input_lower, input_upper=asked.input_upper)
    funnel = synthesize_funnel(
        scenario, task.trajectory, state_bounds=state_bounds,
        initial=task.initial, rate=task.rate, disturbance=asked.disturbance,
        terminal=task.terminal, period=asked.period, codesign=task.period <= 0, widen=False,
        from_multiplier=asked.from_multiplier,
        pushed=None if asked.pushed is None else frozenset(asked.pushed),
    )  # fmt: skip
    # a round's next try for this trajectory starts at the multiplier that designed this one
    start = funnel.multiplier if funnel.success and funnel.rho > 0 else asked.from_multiplier
    return replace(funnel, held=replace(asked, from_multiplier=start))


def _reused(earlier: tuple[Funnel, str | None]) -> tuple[Funnel, str | None]:
    """An earlier round's funnel and its verdict then (None: certified), kept for a nominal that
    did not move: no synthesis time spent now; dropped again (with the reason) if it was
    dropped then or is not certified (``success``, ``rho > 0``)."""
    funnel, failure = earlier
    if failure is None and not (funnel.success and funnel.rho > 0):
        failure = f"the reused funnel was not certified ({funnel.message})"
    return replace(funnel, seconds=0.0), failure


def synthesize_funnels(
    scenario: Scenario,
    names: Sequence[str],
    trajectories: Sequence[Trajectory],
    P: FloatArray,
    radii: FloatArray,
    *,
    rate: float = 0.0,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
    reuse: Sequence[tuple[Funnel, str | None] | None] | None = None,
    terminal: TerminalTarget | None = None,
    period: float = 0.0,
    earlier: Sequence[EarlierDesign] = (),
) -> FunnelStageResult:
    """The funnel of every trajectory on ``executor`` (default: here, in order; the result does
    not depend on it), each asked to hold its start's cell of Init (``required_sets``).

    Args:
      names: one per trajectory; trajectories: the final nominals (``xs (N_i+1, n)``,
        ``us (N_i, m)``, their dense grids).
      P: (n, n) the constant certificate's metric (it assigns the cells); radii: (k,) its ball
        radius per trajectory (I1), for a start that owns no cell.
      rate: lambda (1/s) of the funnels' decay (``synthesize_funnel``).
      reuse: per trajectory, None or a funnel made earlier around the same nominal with the
        same request and its verdict then (None: certified, else why it was dropped; an earlier
        round's, for a nominal that did not move): kept as it is, without a new synthesis and
        its checks (the result would be the same), its synthesis time counted as 0; one dropped
        then, or not certified (``success``, ``rho > 0``), is dropped again.
      terminal: the ellipsoid every funnel must end in (None: none); a nominal ending outside
        it is dropped, saying so.
      period: the law is held every ``period`` s (0: continuous): a funnel is kept only when
        it holds that law (``funnel.law`` (I6)) as certify will rebuild it.
      earlier: per trajectory, how an earlier round designed its kept funnel (``EarlierDesign``:
        co-designed gains (F6) searched before the LQR gains, a held law's redesign tried
        first; empty: nothing earlier): tried first, kept when it passes (checked as any other
        funnel; it may differ from the one the full search would find).
    """
    if not (len(names) == len(trajectories) == len(radii)):
        raise ValueError(
            f"funnel: {len(names)} names, {len(trajectories)} trajectories and {len(radii)} "
            "radii; expected one of each per trajectory"
        )
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    initial = required_sets(scenario, [t.xs[0] for t in trajectories], P, radii)
    reuse = [None] * len(trajectories) if reuse is None else list(reuse)
    earlier = list(earlier) or [EarlierDesign()] * len(trajectories)
    if len(earlier) != len(trajectories):
        raise ValueError(
            f"funnel: {len(earlier)} earlier designs for {len(trajectories)} trajectories; "
            "expected one per trajectory (or none)"
        )
    if len(reuse) != len(trajectories):
        raise ValueError(
            f"funnel: {len(reuse)} funnels to reuse for {len(trajectories)} trajectories; "
            "expected one (or None) per trajectory"
        )
    disturbance = declared_bound(scenario)
    measurement = scenario.uncertainty.measurement_box  # funnel.law (I7)
    tasks = {
        i: _Task(
            scenario=scenario,
            trajectory=trajectory,
            initial=Q_init,
            rate=rate,
            disturbance=disturbance,
            terminal=terminal,
            period=period,
            measurement=measurement,
            earlier=earlier[i],
        )
        for i, (trajectory, Q_init) in enumerate(zip(trajectories, initial, strict=True))
        if reuse[i] is None
    }
    executor = executor or SerialExecutor()
    done = executor.map(
        _funnel_in_worker,
        list(tasks.values()),
        done=None if progress is None else lambda _i: progress(1),
    )
    computed = dict(zip(tasks, done, strict=True))
    outcomes = [
        computed[i] if earlier is None else _reused(earlier) for i, earlier in enumerate(reuse)
    ]
    if progress is not None and len(tasks) < len(trajectories):
        progress(len(trajectories) - len(tasks))
    funnels = tuple(funnel for funnel, _ in outcomes)
    usable = tuple(i for i, (_, failure) in enumerate(outcomes) if failure is None)
    rejected = tuple(
        f"{names[i]} dropped: {failure}" for i, (_, failure) in enumerate(outcomes) if failure
    )
    return FunnelStageResult(
        names=tuple(names),
        funnels=funnels,
        initial_radii=radii,
        usable=usable,
        rejected=rejected,
        success=len(usable) == len(funnels),
        message=_describe(funnels, usable, rejected),
    )


def _describe(funnels: Sequence[Funnel], usable: Sequence[int], rejected: Sequence[str]) -> str:
    """One line: how many funnels are certified, their levels and times, who was dropped."""
    seconds = np.array([f.seconds for f in funnels])
    timing = (
        f"{seconds.min():.1f} to {seconds.max():.1f} s each ({seconds.sum():.1f} s of work)"
        if len(seconds)
        else "none"
    )
    if usable:
        levels = [funnels[i].rho for i in usable]
        found = (
            f"funnels certified for {len(usable)} of {len(funnels)} trajectories, levels "
            f"{min(levels):.3f} to {max(levels):.3f} (1: the start's cell of Init held whole)"
            f"; {timing}"
        )
    else:
        found = f"no funnel certified for any of the {len(funnels)} trajectories; {timing}"
    return "; ".join([found, *rejected])


@dataclass(frozen=True, kw_only=True)
class FunnelInputs(StageInputs):
    """What stage ``funnel`` reads: the trajectories' names and final nominals, the constant
    certificate's metric ``P (n, n)`` and ball radius per trajectory ``radii (k,)``, the
    terminal ellipsoid the funnels must end in (None: none), the period the law is held for
    (0: continuous feedback) and per trajectory how an earlier round designed its kept funnel
    (``EarlierDesign``, tried first; empty: nothing earlier)."""

    scenario_fields: ClassVar = (
        "Ts",
        "clearance",
        "dynamics",
        "feedback",
        "goal",
        "goal_bounds",
        "init_lower",
        "init_upper",
        "input_lower",
        "input_upper",
        "operating_region",
        "position_index",
        "state_bounds",
        "uncertainty",
        "unsafe",
    )
    scenario: Scenario
    names: tuple[str, ...]
    trajectories: tuple[Trajectory, ...]
    P: FloatArray
    radii: FloatArray
    terminal: TerminalTarget | None = None
    feedback_period: float = 0.0
    earlier: tuple[EarlierDesign, ...] = ()


def _funnel_stage(
    inputs: FunnelInputs,
    *,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
    reuse: Sequence[tuple[Funnel, str | None] | None] | None = None,
) -> FunnelStageResult:
    return synthesize_funnels(
        inputs.scenario,
        inputs.names,
        inputs.trajectories,
        inputs.P,
        inputs.radii,
        executor=executor,
        progress=progress,
        reuse=reuse,
        terminal=inputs.terminal,
        period=inputs.feedback_period,
        earlier=inputs.earlier,
    )


FUNNEL = Stage("funnel", _funnel_stage, FunnelInputs, FunnelStageResult)
