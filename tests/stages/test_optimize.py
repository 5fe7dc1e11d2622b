"""Stage optimize: bisection, seeds, verified results, parallel equals serial; margins along the
trajectory and the re-optimization within a funnel."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline import load_scenario
from pipeline.io.executor import ProcessExecutor
from pipeline.model.simulate import simulate
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from pipeline.numerics.optimize.margins import MarginProfile
from pipeline.numerics.optimize.problem import make_problem
from stages.feedback import design_feedback
from stages.optimize import (
    ConstraintMargins,
    OptimizeOptions,
    end_unshrunk,
    optimize,
    optimize_demo,
    reoptimize_with_funnels,
    reseed,
    shortest_by_continuation,
    smallest_feasible,
)


@functools.cache
def _quadrotor():
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    feedback = design_feedback(scenario)
    r_d = feedback.required_radius(scenario.clearance)
    margins = ConstraintMargins.of_tube(feedback.certified_tube, r_d)
    return scenario, margins


@given(st.integers(1, 200), st.integers(0, 200))
def test_bisection_finds_what_a_linear_scan_finds(hi, threshold):
    threshold = min(threshold, hi)  # feasible from ``threshold`` on; ``hi`` is feasible
    calls = []

    def feasible(N):
        calls.append(N)
        return N >= threshold

    scan = next(N for N in range(1, hi + 1) if feasible(N))
    calls.clear()
    assert smallest_feasible(feasible, 0, hi) == scan
    assert len(calls) <= max(1, int(np.ceil(np.log2(hi))))


@given(st.integers(1, 200), st.integers(1, 200))
def test_continuation_finds_what_a_linear_scan_finds(start, threshold):
    threshold = min(threshold, start)
    assert shortest_by_continuation(lambda N: N >= threshold, start, 0.1) == threshold


def test_seeds_keep_the_start_or_the_whole_input():
    u = np.arange(20.0).reshape(10, 2)
    np.testing.assert_array_equal(reseed(u, 4, "truncate"), u[:4])
    compressed = reseed(u, 5, "compress")
    assert compressed.shape == (5, 2)
    assert compressed[0, 0] == pytest.approx(1.0) and compressed[-1, 0] == pytest.approx(17.0)
    with pytest.raises(ValueError, match="seed mode"):
        reseed(u, 4, "stretch")


def test_options_refuse_unknown_choices():
    with pytest.raises(ValueError, match="method"):
        OptimizeOptions(method="newton")
    with pytest.raises(ValueError, match="parameterization"):
        OptimizeOptions(parameterization="closed")
    with pytest.raises(ValueError, match="overshoot"):
        OptimizeOptions(overshoot=-0.1)


@pytest.mark.parametrize(
    ("method", "search"), [("gd", "continuation"), ("lbfgs", "continuation"), ("gd", "bisection")]
)
def test_the_closest_demo_becomes_faster_and_verified(method, search):
    scenario, margins = _quadrotor()
    demo = 3  # passes 0.54 m from the hill: infeasible for d = 1 as flown
    result = optimize_demo(scenario, demo, margins, OptimizeOptions(method=method, search=search))
    assert result.success, result.message
    assert result.N < result.N_demo
    assert result.verification.passed
    assert min(result.verification.clearance.values()) >= scenario.clearance
    # the search ended next to an infeasible try (or at 1 sample)
    tried = {t.N: t.feasible for t in result.tries}
    assert tried[result.N] and (result.N == 1 or tried.get(result.N - 1) is False)
    # every intermediate feasible input really has zero cost
    problem = make_problem(
        scenario,
        demo=demo,
        input_margin=margins.input_margin,
        region_margin={
            k: v + (0.01 if k in scenario.state_names else 0.0)
            for k, v in margins.region_margin.items()
        },
    )
    for u in result.feasible_inputs:
        assert problem.with_horizon(len(u), u).cost(u) == 0.0


def test_gradient_descent_log_is_monotone():
    scenario, margins = _quadrotor()
    result = optimize_demo(scenario, 7, margins, OptimizeOptions())
    assert np.all(np.diff(result.log.cost) <= 0)
    assert result.log.accepted[0]


def test_open_loop_descent_is_the_papers_literal_method():
    scenario, margins = _quadrotor()
    result = optimize_demo(
        scenario, 0, margins, OptimizeOptions(parameterization="open_loop", max_iterations=50)
    )
    # demo_01 already satisfies the margins: the paper's method keeps it feasible, never worse
    assert result.tries[0].feasible and result.N <= result.N_demo


def test_parallel_equals_serial():
    scenario, margins = _quadrotor()
    options = OptimizeOptions()
    serial = optimize(scenario, margins, options, demos=[1, 4])
    pool = ProcessExecutor(2)
    try:
        parallel = optimize(scenario, margins, options, demos=[1, 4], executor=pool)
    finally:
        pool.close()
    for a, b in zip(serial.trajectories, parallel.trajectories, strict=True):
        assert a.N == b.N
        np.testing.assert_array_equal(a.u, b.u)
        assert [t.N for t in a.tries] == [t.N for t in b.tries]


def test_a_wider_tube_is_kept_away_by_its_own_clearance():
    """``margins.clearance`` (a covering radius above ``r_d``) replaces ``d`` everywhere."""
    scenario, margins = _quadrotor()
    wider = dataclasses.replace(margins, clearance=1.2)
    result = optimize_demo(scenario, 7, wider, OptimizeOptions(method="lbfgs"))
    assert result.success, result.message
    assert min(result.verification.clearance.values()) >= 1.2
    problem = make_problem(
        scenario,
        demo=7,
        input_margin=margins.input_margin,
        region_margin={
            k: v + (0.01 if k in scenario.state_names else 0.0)
            for k, v in margins.region_margin.items()
        },
        clearance=1.2,
    )
    assert problem.with_horizon(result.N, result.u).cost(result.u) == 0.0


@functools.cache
def _double_integrator():
    """The double integrator, its demo 1 optimized with no tube (margins zero, clearance d) and
    with the constant certificate's tube, and the funnel around the latter."""
    scenario = load_scenario("double_integrator", check_demos=False)
    feedback = design_feedback(scenario)
    bare = ConstraintMargins(
        input_margin=np.zeros(scenario.m), region_margin={}, gain=feedback.K, clearance=None
    )
    tube = ConstraintMargins.of_tube(
        feedback.certified_tube, feedback.required_radius(scenario.clearance)
    )
    constant = optimize_demo(scenario, 0, tube, OptimizeOptions())
    trajectory = simulate(scenario.dynamics, constant.x0, constant.u, scenario.Ts)
    return (
        scenario,
        bare,
        optimize_demo(scenario, 0, bare, OptimizeOptions()),
        constant,
        (synthesize_funnel(scenario, trajectory)),
    )


def test_a_margin_along_the_trajectory_binds_where_it_is_and_nowhere_else():
    """Input extent 1.5 on 'ux' on one interval of the demo's grid only: the optimum without it
    breaks it there and nowhere else; with it, the optimum keeps |ux| <= 0.5 on the interval(s)
    that interval maps to (normalised time, window maximum) and uses more elsewhere."""
    scenario, bare, unconstrained, _, _ = _double_integrator()
    M = unconstrained.N_demo
    extent = np.zeros((M, scenario.m))
    extent[40, 0] = 1.5  # |ux| <= 0.5 on [4.0, 4.1] s of the demo, ~1/3 of the way
    profile = MarginProfile(
        clearance=np.zeros(M),
        input=extent,
        state=np.zeros((M, scenario.n)),
        final_clearance=0.0,
        final_state=np.zeros(scenario.n),
    )
    spiked = dataclasses.replace(bare, profile=profile)
    problem = make_problem(scenario, demo=0, input_margin=0.0, region_margin={}, profile=profile)
    # binding: the optimum without the margin violates it, on the mapped samples only
    N0, u0 = unconstrained.N, unconstrained.u
    mapped0 = np.flatnonzero(profile.on_grid(N0).input[:, 0] > 0)
    value, _ = problem.constraints.input_terms(u0, problem.constraints.grid(N0, problem.substeps))
    assert 1 <= len(mapped0) <= 2 and set(np.flatnonzero(value > 0)) <= set(mapped0)
    assert value.sum() > 0
    result = optimize_demo(scenario, 0, spiked, OptimizeOptions())
    assert result.success, result.message
    mapped = np.flatnonzero(profile.on_grid(result.N).input[:, 0] > 0)
    assert 1 <= len(mapped) <= 2
    assert np.all(np.abs(result.u[mapped, 0]) <= 0.5)
    assert np.abs(np.delete(result.u[:, 0], mapped)).max() > 1.5  # not applied elsewhere
    assert problem.with_horizon(result.N, result.u).cost(result.u) == 0.0


def test_reoptimizing_within_a_funnel_keeps_its_tube_inside_the_constraints():
    scenario, _, _, constant, funnel = _double_integrator()
    assert constant.success and funnel.success, funnel.message
    raw = ConstraintMargins.of_funnel(scenario, funnel).profile
    assert raw.clearance.max() < scenario.clearance  # the funnel is thinner than d here
    for at_least, expected in [(0.0, raw.clearance.max()), (None, scenario.clearance)]:
        again = reoptimize_with_funnels(
            scenario, [constant], [funnel], OptimizeOptions(), at_least=at_least
        )
        (new,) = again.trajectories
        assert again.success and new.success, new.message
        assert new.N <= constant.N and new.N_demo == constant.N_demo
        margins = ConstraintMargins.of_funnel(scenario, funnel, at_least=at_least or 0.0)
        profile = margins.profile.on_grid(new.N)
        # the new nominal's inputs keep the funnel's input extents from the bounds, per sample
        assert np.all(new.u - profile.input >= scenario.input_lower - 1e-12)
        assert np.all(new.u + profile.input <= scenario.input_upper + 1e-12)
        # verified against the tube's clearance per interval (at least d by default)
        assert new.verification.required_clearance == pytest.approx(expected)
        problem = make_problem(
            scenario,
            x0=new.x0,
            u_seed=new.u,
            clearance=0.0,
            region=dict(scenario.state_bounds),
            region_margin={},
            profile=margins.profile,
        )
        assert problem.cost(new.u) == 0.0


def test_reoptimizing_needs_one_certified_funnel_per_trajectory():
    scenario, _, _, constant, funnel = _double_integrator()
    with pytest.raises(ValueError, match="one funnel per trajectory"):
        reoptimize_with_funnels(scenario, [constant, constant], [funnel], OptimizeOptions())
    rejected = dataclasses.replace(funnel, success=False, message="LMIs infeasible")
    result = reoptimize_with_funnels(scenario, [constant], [rejected], OptimizeOptions())
    (kept,) = result.trajectories
    assert not result.success and "was not certified (LMIs infeasible)" in kept.message
    np.testing.assert_array_equal(kept.u, constant.u)


def test_an_unshrunk_end_bound_keeps_a_margin_entry_for_the_overshoot():
    """A hold run's core states bound the nominal's end itself (no tube extent), but their
    ``goal_margin`` stays in the mapping at 0: the descent's tightened problem adds its
    overshoot to every entry, so the tightened bound is strictly inside the real one (absent,
    both were the same and the descent stopped at J = 3e-22 > 0, short of feasible)."""
    scenario, margins = _quadrotor()
    core = ("vX", "vY")
    unshrunk = end_unshrunk(scenario, margins, core)
    assert {k: unshrunk.goal_margin[k] for k in core} == {"vX": 0.0, "vY": 0.0}
    others = set(margins.goal_margin) - set(core)
    assert {k: unshrunk.goal_margin[k] for k in others} == {
        k: margins.goal_margin[k] for k in others
    }
