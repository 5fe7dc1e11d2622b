"""Funnels that hold under a bounded disturbance (pipeline.numerics.funnel.robust (I5), funnel.lmi).

``xdot = f(x, u) + w`` with any ``|w_i| <= d_i``: the check bounds (F2)'s term and the
disturbance's together by the S-procedure; the synthesis imposes the same joint LMI at every
vertex, end and corner ``w_c``. Known answers for the check (where the S-procedure is exact), the
LMI against cvxpy, a double integrator's robust funnel flown from its boundary under the worst
disturbance, and the reduction to today's funnels without one.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from shapely.geometry import box

from pipeline.controller import inverse_linear
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel import synthesis
from pipeline.numerics.funnel.check import check_funnel, checked_margins, effective_margins
from pipeline.numerics.funnel.law import LMI_MARGIN, LawOffset, corners
from pipeline.numerics.funnel.lmi import FunnelProgram, codesign_gains, solve_clarabel, solve_cvxpy
from pipeline.numerics.funnel.robust import MULTIPLE_STEPS, RobustCheck, invariant_ellipsoid
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from tests.helpers.robust import DISTURBANCE, double_integrator_case, rk4_step


def _scalar_check(a: float, p: float, level: float) -> RobustCheck:
    """(I5) for ``edot = -a e + w`` over two intervals, metric ``P = p``, at ``level``."""
    Q = np.full((3, 1, 1), 1 / p)
    vertices = tuple(np.array([[[-a, 0.0]]]) for _ in range(2))
    return RobustCheck(Q, np.zeros((2, 1, 1)), vertices, 0.0, 0.1, level)


def test_the_s_procedure_is_exact_for_a_scalar_loop():
    """``edot = -a e + w``, ``|w| <= d``: the interval ``|e| <= d / a`` is the smallest invariant
    one. In the metric ``P = p`` at level rho the half-width is ``rho / sqrt(p)``, and (I5)
    holds exactly when ``rho / sqrt(p) > d / a`` (the S-procedure is lossless here); without a
    disturbance ``r = m / 2 = -a``; the multiple at level 2 is ``(2 / sqrt p) a / d``."""
    a, d, p = 0.7, 0.3, 4.0
    exact = d / a * np.sqrt(p)  # the level at which the interval is d / a wide
    for level, holds in ((exact * (1 + 1e-6), True), (exact * (1 - 1e-6), False)):
        r, _ = _scalar_check(a, p, level).margins(np.array([d]))
        assert bool(np.all(r < 0)) == holds
    assert np.allclose(_scalar_check(a, p, 1.0).margins(np.array([0.0]))[0], -a, atol=1e-8)
    multiple = _scalar_check(a, p, 2.0).multiple(np.array([d]), np.zeros(2))
    assert multiple == pytest.approx(2 / np.sqrt(p) * a / d, rel=1e-4)
    assert multiple <= 2 / np.sqrt(p) * a / d  # a lower bound: it holds at what is reported


def _multiple_by_full_searches(check: RobustCheck, bound: np.ndarray, lmi: np.ndarray) -> float:
    """``RobustCheck.multiple``'s bisection with a full (I5) search at every probe."""

    def holds(s: float) -> bool:
        return bool(np.all(2 * check.margins(s * bound)[0] + lmi < -LMI_MARGIN))

    low, high = 0.0, 1.0
    while holds(high):
        low, high = high, 2 * high
    for _ in range(MULTIPLE_STEPS):
        middle = (low + high) / 2
        low, high = (middle, high) if holds(middle) else (low, middle)
    return low * (1 - 1e-9)


def test_the_multiple_searches_only_where_the_last_multiplier_fails_and_finds_the_same():
    """``multiple`` tries the last certifying multipliers first and searches again only on the
    intervals they do not certify: on random stable funnels it reports what a full search at
    every bisection probe reports; ``enough`` is returned where it holds (certify needs no
    more), and does not change the multiple where it does not."""
    rng = np.random.default_rng(5)
    found = []
    for _ in range(6):
        N, n, m, V = 5, 3, 1, 4
        root = rng.normal(size=(n, n)) * 0.3 + np.eye(n) + 0.002 * rng.normal(size=(N + 1, n, n))
        Q = root @ np.swapaxes(root, 1, 2)  # slowly varying
        K = -np.abs(rng.normal(size=(N, m, n)))
        vertices = tuple(
            np.concatenate(
                [
                    -2 * np.eye(n) + 0.3 * rng.normal(size=(V, n, n)),
                    0.2 * rng.normal(size=(V, n, m)),
                ],
                axis=2,
            )
            for _ in range(N)
        )
        check = RobustCheck(Q, K, vertices, 0.1, 0.05, 1.0)
        bound = np.abs(rng.normal(size=n)) * 0.05
        lmi = -np.abs(rng.normal(size=N)) * 0.1
        reference = _multiple_by_full_searches(check, bound, lmi)
        assert check.multiple(bound, lmi) == pytest.approx(reference, rel=1e-9)
        if 0 < reference < 1e6:  # enough: returned where it holds, else the search's own
            assert check.holds_at(reference, bound, lmi)
            assert not check.holds_at(reference * 1.01, bound, lmi)
            assert check.multiple(bound, lmi, enough=reference / 2) == reference / 2
            more = check.multiple(bound, lmi, enough=2 * reference)
            assert more == pytest.approx(reference, rel=1e-9)
        found.append(reference)
    assert sum(0 < multiple < 1e6 for multiple in found) >= 4, found  # most hold some multiple


def test_the_invariant_ellipsoid_guess_is_the_best_lyapunov_solution_of_its_decays():
    """``invariant_ellipsoid`` (scipy's Bartels-Stewart per decay): on random stable loops the
    least-``tr(W Q)`` solution, positive semidefinite, of the 25 Lyapunov equations solved
    independently in Kronecker form, to rounding; an unstable loop gives None."""
    rng = np.random.default_rng(3)
    for _ in range(100):
        n = int(rng.integers(2, 7))
        A = rng.normal(size=(n, n))
        A -= (np.abs(np.linalg.eigvals(A).real).max() + 0.1) * np.eye(n)
        bound = np.abs(rng.normal(size=n)) * (rng.random(n) < 0.6)
        bound[0] = bound[0] or 1.0
        weight = np.diag(rng.random(n))
        acting = np.flatnonzero(bound > 0)
        E = np.zeros((n, len(acting)))
        E[acting, np.arange(len(acting))] = np.sqrt(len(acting)) * bound[acting]
        sigma = -np.linalg.eigvals(A).real.max()
        # an independent solution: each equation in Kronecker form on the row-major vec(Q),
        # (A (x) I + I (x) A + a I) vec(Q) = -vec(E E^T) / a
        solutions = [
            np.linalg.solve(
                np.kron(A, np.eye(n)) + np.kron(np.eye(n), A) + a * np.eye(n * n),
                -(E @ E.T).ravel() / a,
            ).reshape(n, n)
            for a in np.geomspace(0.02, 1.98, 25) * sigma
        ]
        best = min(solutions, key=lambda Q: float(np.trace(weight @ Q)))
        assert np.linalg.eigvalsh((best + best.T) / 2)[0] > -1e-9 * abs(best).max()
        guess = invariant_ellipsoid(A, bound, weight)
        assert guess is not None
        np.testing.assert_allclose(
            guess, (best + best.T) / 2, rtol=1e-8, atol=1e-12 * abs(best).max()
        )
    assert invariant_ellipsoid(np.eye(2), np.ones(2), np.eye(2)) is None


def test_the_joint_bound_beats_the_separate_one():
    """A lightly damped oscillator pushed on its speed: (I4)'s bound (``m + 2 max ||w||_P / rho``,
    the two terms at their own worst points) fails where (I5) holds, and (I5) is never looser."""
    A, K = np.array([[0.0, 1.0], [-1.0, -0.4]]), np.zeros((2, 1, 2))
    vertices = tuple(np.hstack([A, np.zeros((2, 1))])[None] for _ in range(2))
    Q = np.repeat(np.linalg.inv(np.array([[1.2, 0.2], [0.2, 1.0]]))[None], 3, 0)
    w = np.array([0.0, 0.05])
    separate = None
    for level in np.geomspace(0.05, 5, 40):
        check = RobustCheck(Q, K, vertices, 0.0, 0.1, level)
        joint = 2 * check.margins(w)[0].max()
        m = 2 * check.margins(np.zeros(2))[0].max()
        separate = m + 2 * np.sqrt(w @ np.linalg.solve(Q[0], w)) / level
        assert joint <= separate + 1e-9
        if joint < 0 < separate:
            break
    else:
        pytest.fail(f"no level where (I5) holds and (I4) fails (last: {separate})")


def test_corners_are_one_of_each_pair_over_the_disturbed_states():
    assert corners(np.zeros(3)).shape == (0, 3)
    w = corners(np.array([0.0, 0.2, 0.5]))
    assert w.shape == (2, 3) and np.all(w[:, 0] == 0)
    assert {tuple(np.abs(c)) for c in w} == {(0.0, 0.2, 0.5)}
    assert not np.allclose(w[0], -w[1])  # not both of a +- pair


def test_the_joint_constraint_is_the_same_program_in_cvxpy():
    """The Clarabel assembly of (I5)'s LMI ``[[M + alpha Q, w], [w^T, -(alpha - eps)]] <= 0``
    against cvxpy's statement, and what it imposes: the numpy check of the solution at level 1
    finds ``r <= -eps`` on every interval (to the solver's tolerance)."""
    A, B, K = np.array([[0, 1], [0, 0.0]]), np.array([[0], [1.0]]), np.array([[-1.0, -1.4]])
    N, w, alpha, eps = 5, np.array([0.0, 0.1]), 0.5, 0.05
    vertices = tuple(np.hstack([A, B])[None] for _ in range(N))
    program = FunnelProgram(
        Ts=0.1, K=np.repeat(K[None], N, 0), vertices=vertices, c=eps, Q_init=np.eye(2) * 0.01,
        floor=1e-6, caps=(), W=np.repeat(np.eye(2)[None], N + 1, 0), initial_weight=100.0,
        disturbance=corners(w), multiplier=alpha, margin=eps,
    )  # fmt: skip
    ours, reference = solve_clarabel(program), solve_cvxpy(program)
    assert not isinstance(ours, str) and not isinstance(reference, str)
    assert np.allclose(ours[0], reference[0], atol=1e-4) and ours[1] == pytest.approx(1.0)
    check = RobustCheck(ours[0], np.repeat(K[None], N, 0), vertices, 0.0, 0.1, 1.0)
    assert np.all(check.margins(w)[0] <= -eps + 1e-5)


def test_the_codesign_program_is_the_same_in_cvxpy():
    """(F6): the gains as unknowns ``Y = K Q`` with the input caps and the spread ``Z >= Y
    Q^-1 Y^T`` in Schur form, assembled for Clarabel against cvxpy's statement: the same optimal
    metric; the gains read back from both agree."""
    A, B = np.array([[0, 1], [0, 0.0]]), np.array([[0], [1.0]])
    N, w, alpha, eps = 4, np.array([0.0, 0.1]), 0.5, 0.05
    vertices = tuple(np.stack([np.hstack([A, B]), np.hstack([A, 1.2 * B])]) for _ in range(N))
    program = FunnelProgram(
        Ts=0.1, K=np.zeros((N, 1, 2)), vertices=vertices, c=eps, Q_init=np.eye(2) * 0.01,
        floor=1e-6, caps=(), W=np.repeat(np.eye(2)[None], N + 1, 0), initial_weight=100.0,
        disturbance=corners(w), multiplier=alpha, margin=eps, codesign=True,
        gain_caps=tuple((k, j, 0, 4.0) for j in range(N) for k in (j, j + 1)),
        gain_weight=np.eye(1) / 25,
    )  # fmt: skip
    ours, reference = codesign_gains(program), solve_cvxpy(program)
    assert not isinstance(ours, str) and not isinstance(reference, str) and len(reference) == 3
    K, Q, tau = ours
    Q_ref, tau_ref, Y_ref = reference
    assert tau == pytest.approx(1.0, abs=1e-6) and tau_ref == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(Q, Q_ref, atol=1e-4)
    Qbar = (Q_ref[:-1] + Q_ref[1:]) / 2
    K_ref = np.swapaxes(np.linalg.solve(Qbar, np.swapaxes(Y_ref, 1, 2)), 1, 2)
    assert np.allclose(K, K_ref, rtol=0.02)  # Q ~ 0.01: the solvers' tolerances, magnified
    assert np.all(K[:, 0, :] < 0)  # a stabilising gain for the double integrator (u = K e)


def test_codesigned_gains_hold_a_disturbance_the_lqr_gains_cannot():
    """On the double integrator, a disturbance eight times the tests' bound: the funnel with the
    LQR gains held is rejected (the co-design switched off), the one with the co-designed gains
    (F6) passes ``check_funnel``'s (I5) with the disturbance, whatever the program said."""
    scenario, trajectory, initial = double_integrator_case()
    bound = 8 * DISTURBANCE
    original = synthesis.codesign_gains
    try:
        synthesis.codesign_gains = lambda program: "switched off"
        lqr = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=bound)
    finally:
        synthesis.codesign_gains = original
    designed = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=bound)
    assert designed.success and "(F6)" in designed.message, designed.message
    assert not lqr.success and "rejected" in lqr.message, lqr.message
    assert not check_funnel(scenario, trajectory, designed, {}, _robust(designed, scenario, bound))


def test_each_gains_family_stops_searching_past_its_best_multiplier():
    """``MultiplierSearch``: a family searched upwards stops at the first multiplier infeasible
    or holding less after a feasible one (measured on quadrotor_hill: the LQR gains'
    taus infeasible, 0.58, infeasible, infeasible; (F6)'s 0.906, 0.668, infeasible,
    infeasible), never before a feasible one, and not while both hold the whole level."""
    search = synthesis.MultiplierSearch()
    for tau in (0.0, 0.58):
        search.record(False, tau)
        assert not search.past_best(False)
    search.record(False, 0.0)
    assert search.past_best(False)
    search.record(True, 0.906)
    assert not search.past_best(True)
    search.record(True, 0.668)
    assert search.past_best(True)
    whole = synthesis.MultiplierSearch()
    for tau in (1.4, 1.1, 0.99):  # capped at the design level 1: only the last holds less
        assert not whole.past_best(False)
        whole.record(False, tau)
    assert whole.past_best(False)


def test_a_family_past_its_best_multiplier_solves_no_more_programs():
    """The double integrator at twice the tests' bound, its LQR gains' programs scripted to
    hold half the design level at the first multiplier and less at the second: the LQR family
    stops there (the larger ones not solved), the (F6) family is searched next and the funnel it
    certifies (whole level) is kept; searching every multiplier solves the LQR programs
    skipped."""
    scenario, trajectory, initial = double_integrator_case()
    original, search = synthesis.solve_clarabel, synthesis.MultiplierSearch
    M = synthesis.ROBUST_MULTIPLIERS
    shrink = {M[0]: 0.5, M[1]: 0.3}  # tau of the LQR gains' programs, scaled to these (else 0.2)

    class Exhaustive(synthesis.MultiplierSearch):
        def past_best(self, codesign: bool) -> bool:
            return False

    def run(searching):
        solved = []

        def scripted(program):
            solution = original(program)
            gains = "F6" if "(F6)" in trace[-1] else "LQR"
            solved.append((gains, program.multiplier))
            if gains == "LQR" and not isinstance(solution, str):
                return solution[0], min(solution[1], 1.0) * shrink.get(program.multiplier, 0.2)
            return solution

        trace = ["LQR"]

        def designed(program):
            trace.append("(F6)")
            return codesign(program)

        synthesis.solve_clarabel, synthesis.MultiplierSearch = scripted, searching
        synthesis.codesign_gains = designed
        funnel = synthesize_funnel(
            scenario, trajectory, initial=initial, disturbance=2 * DISTURBANCE
        )
        return funnel, solved

    codesign = synthesis.codesign_gains
    try:
        stopped, stopped_solves = run(search)
        full, full_solves = run(Exhaustive)
    finally:
        synthesis.solve_clarabel, synthesis.MultiplierSearch = original, search
        synthesis.codesign_gains = codesign
    assert stopped_solves == [("LQR", M[0]), ("LQR", M[1]), ("F6", M[0])], stopped_solves
    lqr = [("LQR", alpha) for alpha in M]
    assert full_solves[: len(M) + 1] == [*lqr, ("F6", M[0])]
    assert stopped.success and "(F6)" in stopped.message and stopped.rho > 0.99
    assert stopped.rho == full.rho and np.array_equal(stopped.K, full.K)


def test_a_redesign_searches_from_the_first_design_s_multiplier_and_records_its_own():
    """``from_multiplier``: the search solves no program below it (the held law's redesign,
    ``stages.funnel``, starts where the first design's program was feasible), and a funnel
    records the multiplier of the program that designed it (0 without a disturbance)."""
    scenario, trajectory, initial = double_integrator_case()
    original = synthesis.solve_clarabel
    solved: list[float] = []

    def recorded(program):
        solved.append(program.multiplier)
        return original(program)

    synthesis.solve_clarabel = recorded
    try:
        first = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=DISTURBANCE)
        start = len(solved)
        later = synthesis.ROBUST_MULTIPLIERS[1]
        again = synthesize_funnel(
            scenario, trajectory, initial=initial, disturbance=DISTURBANCE, from_multiplier=later
        )
    finally:
        synthesis.solve_clarabel = original
    assert first.success and again.success, (first.message, again.message)
    assert solved[0] == synthesis.ROBUST_MULTIPLIERS[0] and first.multiplier in solved[:start]
    assert min(solved[start:]) == later and again.multiplier >= later
    assert synthesize_funnel(scenario, trajectory, initial=initial).multiplier == 0.0


@pytest.mark.parametrize(("short", "stops"), [(1e-7, True), (1e-5, False)])
def test_a_level_short_of_the_whole_by_rounding_ends_the_search(short, stops, monkeypatch):
    """Every program scripted to hold the design level ``1 - short``: within
    ``WHOLE_ROUNDING`` of the whole level the first funnel certified ends the search (one
    program solved); further below, the search goes on to the next multiplier."""
    scenario, trajectory, initial = double_integrator_case()
    solve = synthesis.solve_clarabel
    solved: list[float] = []

    def scripted(program):
        solved.append(program.multiplier)
        solution = solve(program)
        return solution if isinstance(solution, str) else (solution[0], (1 - short) ** 2)

    monkeypatch.setattr(synthesis, "solve_clarabel", scripted)
    funnel = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=DISTURBANCE)
    assert funnel.success and funnel.limits["design"] == pytest.approx(1 - short, abs=1e-12)
    assert short < synthesis.WHOLE_ROUNDING if stops else short > synthesis.WHOLE_ROUNDING
    assert (len(solved) == 1) == stops, solved


def _solves_by_family(monkeypatch, f6_share: float = 1.0, f6_gains: bool = True) -> list[str]:
    """Record each Clarabel solve of ``synthesize_funnel`` as ``"F6"`` (the program holding
    gains just co-designed) or ``"LQR"``, in order, into the list returned. ``f6_share``
    scales the (F6) programs' ``tau`` (capped at the whole level 1); with ``f6_gains`` False
    the (F6) program designs no gains."""
    solve, designer = synthesis.solve_clarabel, synthesis.codesign_gains
    solved: list[str] = []
    family = ["LQR"]

    def designed(program):
        if not f6_gains:
            return "no gains (scripted)"
        family[0] = "F6"
        return designer(program)

    def recorded(program):
        solved.append(family[0])
        solution = solve(program)
        if family[0] == "F6" and f6_share != 1.0 and not isinstance(solution, str):
            solution = (solution[0], f6_share * min(solution[1], 1.0))
        family[0] = "LQR"
        return solution

    monkeypatch.setattr(synthesis, "solve_clarabel", recorded)
    monkeypatch.setattr(synthesis, "codesign_gains", designed)
    return solved


@pytest.mark.parametrize("first", [False, True])
def test_a_nominal_whose_funnel_needed_codesigned_gains_searches_them_first(first, monkeypatch):
    """``codesign_first``: the (F6) gains' multipliers are solved before the LQR gains' (a
    re-optimize round's nominal whose kept funnel was co-designed); the funnel records which
    family designed it (``codesigned``). At eight times the tests' bound only (F6) holds."""
    scenario, trajectory, initial = double_integrator_case()
    solved = _solves_by_family(monkeypatch)
    funnel = synthesize_funnel(
        scenario, trajectory, initial=initial, disturbance=8 * DISTURBANCE, codesign_first=first
    )
    assert funnel.success and funnel.codesigned, funnel.message
    assert solved[0] == ("F6" if first else "LQR"), solved
    if first:  # the first whole funnel ends the search: no LQR program solved
        assert "LQR" not in solved, solved


@pytest.mark.parametrize("co_designed", ["short", "none"])
def test_with_codesigned_gains_first_the_lqr_gains_are_searched_only_where_they_certify_nothing(
    co_designed, monkeypatch
):
    """``codesign_first``: where the (F6) family certifies a funnel short of the whole level
    (its programs scripted to hold half the initial set), no LQR program is solved and that
    funnel is kept; where (F6) designs no gains at all, the LQR gains are searched."""
    scenario, trajectory, initial = double_integrator_case()
    solved = _solves_by_family(monkeypatch, f6_share=0.5, f6_gains=co_designed == "short")
    funnel = synthesize_funnel(
        scenario, trajectory, initial=initial, disturbance=2 * DISTURBANCE, codesign_first=True
    )
    assert funnel.success, funnel.message
    if co_designed == "short":
        assert solved and set(solved) == {"F6"}, solved
        assert funnel.codesigned and funnel.limits["design"] < 1.0
    else:
        assert solved and set(solved) == {"LQR"}, solved
        assert not funnel.codesigned


@pytest.mark.parametrize("widen", [True, False])
def test_capped_boxes_short_of_the_initial_set_are_widened_unless_asked_not_to(widen):
    """A quadrotor funnel (angle boxes capped first) whose program is scripted to hold half
    the initial set: the seed's uncapped boxes are tried after the capped ones, and only then
    (``widen=False``: the held law's redesign keeps the capped ones)."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us[:12], scenario.Ts)
    end = trajectory.xs[-1, :2]
    scenario = dataclasses.replace(scenario, goal=box(*(end - 1.5), *(end + 1.5)))
    hulls, solve = synthesis.piece_hulls, synthesis.solve_clarabel
    tight: list[bool] = []

    def recorded(*args):
        tight.append(args[-1])
        return hulls(*args)

    def half(program):
        solution = solve(program)
        return solution if isinstance(solution, str) else (solution[0], 0.5 * solution[1])

    synthesis.piece_hulls, synthesis.solve_clarabel = recorded, half
    try:
        funnel = synthesize_funnel(
            scenario, trajectory, state_bounds={"theta": (-0.8, 0.8)}, widen=widen
        )
    finally:
        synthesis.piece_hulls, synthesis.solve_clarabel = hulls, solve
    assert funnel.success and funnel.limits["design"] < 1.0, funnel.message
    assert tight == ([True, False] if widen else [True])


def _robust(funnel, scenario, bound):
    law = LawOffset.none(len(funnel.K), scenario.n, scenario.m, scenario.Ts)
    return law.with_disturbance(bound)


def test_a_robust_funnel_holds_under_the_worst_disturbance_from_its_boundary():
    """The robust funnel passes the check with the disturbance's term; flown from 40 boundary
    points with ``w = d sign(P e)`` (the disturbance pushing outward hardest in each state), RK4
    at Ts / 40, the state never leaves it. The nominal design fails that check, naming the
    term."""
    scenario, trajectory, initial = double_integrator_case()
    funnel = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=DISTURBANCE)
    assert funnel.success, funnel.message
    assert (
        check_funnel(scenario, trajectory, funnel, {}, _robust(funnel, scenario, DISTURBANCE))
        is None
    )
    nominal = synthesize_funnel(scenario, trajectory, initial=initial)
    failure = check_funnel(
        scenario, trajectory, nominal, {}, _robust(nominal, scenario, DISTURBANCE)
    )
    assert failure is not None and "under the disturbance" in failure

    rng = np.random.default_rng(3)
    Ts, h, N = scenario.Ts, scenario.Ts / 40, len(funnel.K)
    fine = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, 40)
    P_t = inverse_linear(funnel.P, Ts, fine.dense_ts)  # (M, n, n)
    v = rng.standard_normal((40, scenario.n))
    e = funnel.rho * v / np.sqrt(np.einsum("bi,ij,bj->b", v, funnel.P[0], v))[:, None]
    x, worst = fine.dense_xs[0] + e, 0.0
    for j in range(N * 40):
        k = j // 40
        u = trajectory.us[k] + (x - fine.dense_xs[j]) @ funnel.K[k].T

        def f(state, j=j, u=u):
            w = DISTURBANCE * np.sign((state - fine.dense_xs[j]) @ P_t[j])
            return scenario.dynamics.f(state, u) + w

        x = rk4_step(f, x, h)
        e = x - fine.dense_xs[j + 1]
        worst = max(worst, np.sqrt(np.einsum("bi,ij,bj->b", e, P_t[j + 1], e)).max() / funnel.rho)
    assert worst <= 1 + 1e-6, worst


def test_the_check_hands_back_the_margins_it_judged_by():
    """``checked_margins`` returns the failure ``check_funnel`` gives and the (N,) margins that
    ``effective_margins`` computes for the same funnel and law (the recheck reports them instead
    of searching (I5) again): for a funnel that holds and one that fails under the
    disturbance."""
    scenario, trajectory, initial = double_integrator_case()
    robust = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=DISTURBANCE)
    nominal = synthesize_funnel(scenario, trajectory, initial=initial)
    failures = []
    for funnel in (robust, nominal):
        law = _robust(funnel, scenario, DISTURBANCE)
        failure, margins = checked_margins(scenario, trajectory, funnel, {}, law)
        assert failure == check_funnel(scenario, trajectory, funnel, {}, law)
        failures.append(failure)
        Q = np.linalg.inv(funnel.P)
        expected = effective_margins(
            (Q + np.swapaxes(Q, 1, 2)) / 2, funnel.K, funnel, scenario.Ts, law
        )
        assert margins is not None and np.array_equal(margins, expected)
    assert failures[0] is None and "under the disturbance" in failures[1]


def test_no_disturbance_is_exactly_the_nominal_funnel():
    scenario, trajectory, initial = double_integrator_case()
    nominal = synthesize_funnel(scenario, trajectory, initial=initial)
    zero = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=np.zeros(4))
    assert np.array_equal(nominal.P, zero.P) and nominal.rho == zero.rho
    with pytest.raises(ValueError, match="expected 4 bounds >= 0"):
        synthesize_funnel(scenario, trajectory, initial=initial, disturbance=-DISTURBANCE)


def test_a_rejected_robust_funnel_says_each_reason_once():
    """A disturbance no funnel can hold (100x): every LMI margin fails, and the message names
    each distinct reason once, with the margins it applies to."""
    scenario, trajectory, initial = double_integrator_case()
    funnel = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=100 * DISTURBANCE)
    assert not funnel.success
    reasons = funnel.message.removeprefix("funnel rejected: ").split("; ")
    assert len(reasons) == len(set(r.partition(": ")[2] for r in reasons))
    assert all(r.startswith("margin") for r in reasons)


def _hover_case():
    """quadrotor_hill_flythrough hovering 3 s at (2, 2.5) with Goal a box around it, a 3% share of
    the declared bound of issue 29 (|w_vX| <= 0.033, |w_vY| <= 0.032 m/s^2): local hulls with
    several vertices (pitch, thrust)."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    x0, N = np.array([2.0, 2.5, 0, 0, 0, 0]), 30
    trajectory = simulate(scenario.dynamics, x0, np.tile([9.81, 0.0], (N, 1)), scenario.Ts)
    scenario = dataclasses.replace(scenario, goal=box(0.0, 1.0, 4.0, 4.0))
    bound = np.array([0, 0, 0, 0.033, 0.032, 0])
    return scenario, trajectory, np.diag([0.05, 0.05, 0, 0, 0, 0]) ** 2, bound


def _worst_boundary_rate(scenario, funnel, bound, rng) -> float:
    """The largest ``dV/dt`` found on ``funnel``'s boundary: on a 10x finer time grid inside
    every sample interval, at random points of the interval's hull, for random boundary states
    and the worst of the box's corners and 20 uniform draws of ``|w| <= bound``."""
    n, Ts, rho = scenario.n, scenario.Ts, funnel.rho
    Q = np.linalg.inv(funnel.P)
    w = np.vstack([corners(bound), -corners(bound), rng.uniform(-bound, bound, (20, n))])
    worst = -np.inf
    for k, vertices in enumerate(funnel.vertices):
        dQ = (Q[k + 1] - Q[k]) / Ts  # (F1)
        for s in np.arange(1, 10) / 10:
            P = np.linalg.inv((1 - s) * Q[k] + s * Q[k + 1])
            P = (P + P.T) / 2
            dP = -P @ dQ @ P
            mix = rng.dirichlet(np.ones(len(vertices)), size=8)  # random hull points
            for J in np.einsum("hv,vij->hij", mix, vertices):
                A_cl = J[:, :n] + J[:, n:] @ funnel.K[k]
                v = rng.standard_normal((16, n))
                e = rho * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P, v))[:, None]
                drift = np.einsum("bi,ij,bj->b", e, dP + 2 * P @ A_cl, e)
                push = 2 * (e @ P @ w.T).max(axis=1)
                worst = max(worst, float((drift + push).max()))
    return worst


@pytest.mark.parametrize("case", ["double_integrator", "quadrotor hover"])
def test_the_robust_funnel_holds_between_samples_at_random_hull_points_and_gusts(case):
    """The claim checked pointwise, independently of the LMIs: ``dV/dt = e^T P' e + 2 e^T P (A +
    B K) e + 2 e^T P w < 0`` on the boundary ``e^T P(t) e = rho^2`` at every sampled time, hull
    point and gust (``_worst_boundary_rate``): no flight crosses it outward. The funnel designed
    for the exact model, checked the same way, is crossed (the check can fail)."""
    if case == "double_integrator":
        scenario, trajectory, initial = double_integrator_case()
        bound = DISTURBANCE
    else:
        scenario, trajectory, initial, bound = _hover_case()
    bounds = dict(scenario.state_bounds)
    robust = synthesize_funnel(
        scenario, trajectory, initial=initial, disturbance=bound, state_bounds=bounds
    )
    exact = synthesize_funnel(scenario, trajectory, initial=initial, state_bounds=bounds)
    assert robust.success and exact.success, (robust.message, exact.message)
    rng = np.random.default_rng(7)
    assert _worst_boundary_rate(scenario, robust, bound, rng) < 0
    assert _worst_boundary_rate(scenario, exact, bound, rng) > 0


def test_a_robust_funnel_is_capped_by_every_input_bound():
    """The double integrator's inputs enter linearly (no hull variable, no hull box): with its
    input bounds 0.07 beyond the nominal's peak inputs, the robust funnel is shaped to them in
    the program (its level cannot shrink to fit them under the disturbance): the design binds,
    every input limit leaves room. (Before the caps its level was bound by 'uy' at 0.95.)"""
    scenario, trajectory, initial = double_integrator_case()
    peak = np.abs(trajectory.us).max(axis=0)
    tight = dataclasses.replace(scenario, input_lower=-(peak + 0.07), input_upper=peak + 0.07)
    robust = synthesize_funnel(tight, trajectory, initial=initial, disturbance=DISTURBANCE)
    assert robust.success, robust.message
    inputs = [v for k, v in robust.limits.items() if k.startswith("input")]
    assert robust.binding == "design" and min(inputs) > robust.rho
