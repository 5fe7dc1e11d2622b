"""Margins that vary along the trajectory: a funnel's extents, the regridding rule, the penalties
that read them (pipeline.numerics.optimize.margins, .penalties)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline import load_scenario
from pipeline.numerics.funnel.bounds import Enclosure
from pipeline.numerics.optimize.margins import MarginProfile, funnel_margins, per_point
from pipeline.numerics.optimize.problem import make_problem
from pipeline.numerics.tube.geometry import Tube
from tests.helpers.funnels import make_funnel


@pytest.fixture(scope="module")
def quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


def test_a_constant_funnel_has_the_constant_tubes_margins(quadrotor):
    """K, P the same at every sample: every interval's extents are the constant tube's at rho."""
    rng = np.random.default_rng(3)
    n, m, N, rho = quadrotor.n, quadrotor.m, 12, 0.7
    A = rng.normal(size=(n, n))
    P = A @ A.T + n * np.eye(n)
    K = rng.normal(size=(m, n))
    profile = funnel_margins(
        quadrotor,
        make_funnel(np.broadcast_to(K, (N, m, n)), np.broadcast_to(P, (N + 1, n, n)), rho),
    )
    tube = Tube(
        K=K, P=P, rate=0.0, region={}, state_names=quadrotor.state_names,
        input_names=quadrotor.input_names, position_index=quadrotor.position_index,
    )  # fmt: skip
    assert profile.M == N
    np.testing.assert_allclose(profile.clearance, tube.position_extent(rho), rtol=1e-12)
    np.testing.assert_allclose(profile.input, np.tile(tube.input_margin(rho), (N, 1)), rtol=1e-12)
    np.testing.assert_allclose(profile.state, np.tile(tube.state_extent(rho), (N, 1)), rtol=1e-12)
    assert profile.final_clearance == pytest.approx(tube.position_extent(rho), rel=1e-12)
    np.testing.assert_allclose(profile.final_state, tube.state_extent(rho), rtol=1e-12)


def test_a_growing_funnel_takes_each_intervals_larger_end(quadrotor):
    """Q[k] = (1 + k) I: on interval k the extents are those at its end, t_k+1 (E3)."""
    n, m, N, rho = quadrotor.n, quadrotor.m, 5, 0.5
    Q = (1.0 + np.arange(N + 1))[:, None, None] * np.eye(n)
    K = np.zeros((N, m, n))
    K[:, 0, 0] = 2.0  # u1 = 2 e_X: its extent is 2 rho sqrt(Q_00)
    profile = funnel_margins(quadrotor, make_funnel(K, np.linalg.inv(Q), rho))
    end = rho * np.sqrt(2.0 + np.arange(N))  # rho sqrt(1 + (k + 1))
    np.testing.assert_allclose(profile.clearance, end, rtol=1e-12)
    np.testing.assert_allclose(profile.state, np.tile(end[:, None], (1, n)), rtol=1e-12)
    np.testing.assert_allclose(profile.input[:, 0], 2 * end, rtol=1e-12)
    np.testing.assert_allclose(profile.input[:, 1], 0.0, atol=1e-15)
    assert profile.final_clearance == pytest.approx(rho * np.sqrt(N + 1.0))
    assert funnel_margins(quadrotor, make_funnel(K, np.linalg.inv(Q), rho), level=1.0).clearance[
        0
    ] == pytest.approx(np.sqrt(2.0))


def test_the_nominals_enclosure_widens_the_state_margins(quadrotor):
    """Box = grid +- 0.1 (E1), range = grid +- (0.03, 0.04, 0.02, ...) (E2), tube extent
    ``rho sqrt(Q_ii)`` 0.05 on the first interval and 0.2 on the second: the state margin is the
    larger of the box and range + tube; the clearance gains the position's drift |(0.03, 0.04)|."""
    n, m, N, rho = quadrotor.n, quadrotor.m, 2, 0.5
    Q = np.array([0.01, 0.01, 0.16])[:, None, None] * np.eye(n)  # extents 0.05, 0.2
    grid = np.zeros((N, 2, n))
    drift = np.full(n, 0.02)
    drift[list(quadrotor.position_index)] = (0.03, 0.04)
    enclosure = Enclosure(
        box=grid + np.array([-0.1, 0.1])[None, :, None],
        rate_bound=np.zeros((N, n)),
        grid_range=grid,
        range=grid + np.stack([-drift, drift])[None],
    )
    funnel = make_funnel(np.zeros((N, m, n)), np.linalg.inv(Q), rho, enclosure=enclosure)
    plain = funnel_margins(quadrotor, funnel, enclosure=False)
    np.testing.assert_allclose(plain.state[:, 2], [0.05, 0.2])
    wide = funnel_margins(quadrotor, funnel)
    np.testing.assert_allclose(wide.state[:, 2], [0.1, 0.22])
    np.testing.assert_allclose(wide.clearance, plain.clearance + 0.05)
    assert wide.final_clearance == plain.final_clearance


def test_a_rejected_funnel_has_no_margins(quadrotor):
    n, m = quadrotor.n, quadrotor.m
    funnel = make_funnel(np.zeros((2, m, n)), np.broadcast_to(np.eye(n), (3, n, n)), 0.0, False)
    with pytest.raises(ValueError, match="not certified"):
        funnel_margins(quadrotor, funnel)


def _profile(values: np.ndarray) -> MarginProfile:
    return MarginProfile(
        clearance=values,
        input=np.stack([values, 2 * values], axis=1),
        state=values[:, None] * np.ones(3),
        final_clearance=0.1,
        final_state=np.zeros(3),
    )


def test_a_shorter_horizon_takes_the_windows_maximum():
    """M = 10 source intervals read on N = 4: windows [0, 3), [2, 5), [5, 8), [7, 10)."""
    profile = _profile(np.arange(10.0))
    on = profile.on_grid(4)
    np.testing.assert_array_equal(on.clearance, [2.0, 4.0, 7.0, 9.0])
    np.testing.assert_array_equal(on.input[:, 1], [4.0, 8.0, 14.0, 18.0])
    np.testing.assert_array_equal(profile.on_grid(10).clearance, profile.clearance)
    spike = np.zeros(10)
    spike[6] = 1.0
    np.testing.assert_array_equal(_profile(spike).on_grid(4).clearance, [0, 0, 1, 0])
    np.testing.assert_array_equal(_profile(spike).on_grid(20).clearance[11:15], [0, 1, 1, 0])


@given(
    st.lists(st.floats(0.0, 10.0), min_size=1, max_size=40),
    st.integers(1, 60),
)
def test_regridding_never_lowers_a_margin_at_the_same_fraction_of_the_flight(values, N):
    """Every new interval's margin is at least the source's on every source interval that
    shares part of the same fraction of the flight."""
    values = np.array(values)
    M = len(values)
    on = _profile(values).on_grid(N).clearance
    for k in range(N):
        for j in range(M):
            if j / M < (k + 1) / N and k / N < (j + 1) / M:  # the open intervals overlap
                assert on[k] >= values[j]
        assert on[k] in values


def test_a_grid_point_on_a_sample_boundary_takes_the_larger_margin():
    dense = per_point(np.array([1.0, 3.0, 2.0]), 2)
    np.testing.assert_array_equal(dense, [1, 1, 3, 3, 3, 2, 2])


def test_a_margin_at_one_sample_penalises_that_sample_only(quadrotor):
    """An input extent of 2 N on interval 3 of 8: thrust 13 N is allowed on every sample but 3."""
    m, n, N = quadrotor.m, quadrotor.n, 8
    input_extent = np.zeros((N, m))
    input_extent[3, 0] = 2.0  # u1 in [2, 12.9] on interval 3
    profile = MarginProfile(
        clearance=np.zeros(N),
        input=input_extent,
        state=np.zeros((N, n)),
        final_clearance=0.0,
        final_state=np.zeros(n),
    )
    u = np.tile([13.0, 0.0], (N, 1))
    problem = make_problem(  # no operating region: the input bounds alone
        quadrotor, x0=quadrotor.init_lower, u_seed=u, profile=profile, region={}, backend="numpy"
    )
    grid = problem.constraints.grid(N, problem.substeps)
    value, gradient = problem.constraints.input_terms(u, grid)
    np.testing.assert_allclose(value, np.where(np.arange(N) == 3, 0.1**2, 0.0), atol=1e-12)
    assert gradient[3, 0] == pytest.approx(0.2) and not np.delete(gradient, 3, axis=0).any()
    assert problem.input_upper[3, 0] == pytest.approx(12.9)
    assert problem.input_upper[2, 0] == quadrotor.input_upper[0]
    with pytest.raises(ValueError, match="pass the grid"):
        problem.constraints.input_terms(u)


def test_a_profile_that_empties_a_bound_is_refused(quadrotor):
    n, m = quadrotor.n, quadrotor.m
    profile = MarginProfile(
        clearance=np.zeros(2),
        input=np.array([[0.0, 0.0], [0.0, 10.5]]),
        state=np.zeros((2, n)),
        final_clearance=0.0,
        final_state=np.zeros(n),
    )
    with pytest.raises(ValueError, match="input bounds of 'u2' are empty"):
        make_problem(quadrotor, x0=quadrotor.init_lower, u_seed=np.zeros((2, m)), profile=profile)
    with pytest.raises(ValueError, match="must be finite and >= 0"):
        MarginProfile(
            clearance=np.array([-1.0]),
            input=np.zeros((1, m)),
            state=np.zeros((1, n)),
            final_clearance=0.0,
            final_state=np.zeros(n),
        )
