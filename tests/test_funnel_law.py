"""The funnel certificate covers the law as shipped (pipeline.numerics.funnel.law).

The shipped law tracks ``x_ref`` interpolated on the file's grid, not the exact nominal the funnel
is built around. These tests re-check the funnel inequality with the interpolation's term by
their own means (the interpolation error measured on a 10x finer grid, the metric evaluated at
every one of those times, (F2) at ten points of every interval), fly the shipped law from the
funnel's boundary with the exact dynamics, and check the bound (I1) and the grid it chooses.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.controller import load
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate, simulate_graded
from pipeline.numerics.funnel.law import (
    BASE_SUBSTEPS,
    LawOffset,
    grid_substeps,
    law_offset,
    law_substeps,
)
from pipeline.numerics.verify.recertify import ShippedFunnel, rebuild_funnel
from stages.certify import certify_controller

FUNNEL_SCENARIOS = ("quadrotor_hill_flythrough", "unicycle_slalom")
FINER = 10  # the re-check's time grid against the file's


def _rebuilt(scenario, tr, Ts):
    """The certificate's hull of each sample interval, rebuilt from the file (hulls only)."""
    nominal = simulate(scenario.dynamics, tr.x0, tr.u_ref, Ts, BASE_SUBSTEPS)
    shipped = ShippedFunnel(K=tr.K, P=tr.P, rho=tr.radius, rate=tr.rate)
    return rebuild_funnel(scenario, nominal, shipped, scenario.state_bounds, 1)


def _worst_inequality(scenario, controller, i):
    """Per sample interval: the largest (F2) eigenvalue (normalised by ``Q(s)``) at ten points
    of the interval plus ``2 max ||B_v K delta(t)||_P(t) / rho_t`` with ``delta`` the law's
    interpolation error measured on a grid ``FINER`` times the file's."""
    tr, Ts, n = controller.trajectories[i], controller.Ts, scenario.n
    N = len(tr.K)
    funnel = _rebuilt(scenario, tr, Ts)
    file_grid = grid_substeps(tr.t, N, Ts)
    exact = simulate_graded(scenario.dynamics, tr.x0, tr.u_ref, Ts, FINER * file_grid)
    _, interpolated = zip(*(controller.reference(t, i) for t in exact.dense_ts), strict=True)
    delta = exact.dense_xs - np.array(interpolated)  # (M, n): x_ref - what the law tracks
    k_of = np.minimum((exact.dense_ts / Ts + 1e-9).astype(int), N - 1)
    Q = np.linalg.inv(tr.P)
    worst = np.empty(N)
    for k in range(N):
        A, B = funnel.vertices[k][:, :, :n], funnel.vertices[k][:, :, n:]
        Acl = A + B @ tr.K[k]
        eigen = -np.inf
        for s in np.linspace(0.0, 1.0, 10):
            Qs = (1 - s) * Q[k] + s * Q[k + 1]
            L = -(Q[k + 1] - Q[k]) / Ts + Acl @ Qs + Qs @ np.swapaxes(Acl, 1, 2) + 2 * tr.rate * Qs
            C = np.linalg.inv(np.linalg.cholesky(Qs))
            M = C @ L @ C.T
            eigen = max(eigen, np.linalg.eigvalsh((M + np.swapaxes(M, 1, 2)) / 2).max())
        rows = k_of == k
        P_t = tr.metric(exact.dense_ts[rows], Ts)  # (M_k, n, n)
        w = np.einsum("vij,jl,tl->tvi", B, tr.K[k], delta[rows])  # (M_k, V, n)
        term = np.sqrt(np.einsum("tvi,tij,tvj->tv", w, P_t, w)).max()
        rho_t = tr.radius * np.exp(-tr.rate * Ts * (k + 1))
        worst[k] = eigen + 2 * term / rho_t
    return worst


@pytest.mark.parametrize("name", FUNNEL_SCENARIOS)
def test_the_funnel_inequality_holds_with_the_interpolated_reference(synthesis, name):
    """Fails on files that ship the reference on 20 RK4 steps everywhere:
    quadrotor_hill_flythrough's
    intervals 0-1 (eigenvalue about -0.01, the term up to 0.06)."""
    _, out = synthesis(name)
    scenario, controller = load_scenario(name), load(out / "controller.json")
    for i in range(len(controller.trajectories)):
        worst = _worst_inequality(scenario, controller, i)
        assert worst.max() < 0, (i, int(np.argmax(worst)), worst.max())


@pytest.mark.parametrize("name", FUNNEL_SCENARIOS)
def test_the_shipped_law_never_pushes_a_state_out_across_the_funnel_boundary(synthesis, name):
    """d/dt (e^T P e) + 2 rate e^T P e < 0 on the boundary ``e^T P(t) e = rho_t^2``, with the
    exact dynamics and the law as shipped (``controller(t, x, i)``: interpolated reference,
    clipping), at random boundary points of 40 times per trajectory."""
    _, out = synthesis(name)
    scenario, controller = load_scenario(name), load(out / "controller.json")
    rng = np.random.default_rng(7)
    Ts, n = controller.Ts, scenario.n
    for i, tr in enumerate(controller.trajectories):
        N = len(tr.K)
        exact = simulate(scenario.dynamics, tr.x0, tr.u_ref, Ts, 400)
        picks = np.concatenate([np.arange(0, 400 * 2, 20), rng.integers(0, 400 * N, 20)])
        for j in picks:
            t, x_ref = exact.dense_ts[j], exact.dense_xs[j]
            k = min(int(t / Ts + 1e-9), N - 1)
            P = tr.metric(t, Ts)
            Q = np.linalg.inv(tr.P)
            dP = -P @ ((Q[k + 1] - Q[k]) / Ts) @ P
            rho_t = tr.radius * np.exp(-tr.rate * t)
            v = rng.standard_normal((512, n))
            e = rho_t * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P, v))[:, None]
            x = x_ref + e
            u = controller(t, x, np.full(len(x), i))
            e_dot = scenario.dynamics.f(x, u) - scenario.dynamics.f(x_ref, tr.u_ref[k])
            dV = 2 * np.einsum("bi,ij,bj->b", e, P, e_dot) + np.einsum("bi,ij,bj->b", e, dP, e)
            assert (dV + 2 * tr.rate * rho_t**2).max() < 0, (i, t)


def test_a_file_on_the_old_uniform_grid_is_not_certified(synthesized, tmp_path):
    """quadrotor_hill_flythrough's funnels with their reference on 20 RK4 steps per sample
    everywhere (as
    files were written before the law's term was in the proof): not certified, naming it."""
    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough")
    document = json.loads((out / "controller.json").read_text())
    for item in document["trajectories"]:
        fine = simulate(scenario.dynamics, item["x0"], item["u_ref"], scenario.Ts, 20)
        item["t"], item["x_ref"] = fine.dense_ts.tolist(), fine.dense_xs.tolist()
    document["interpolation_error_P_norm"] = 7.8e-3  # what such a file measures (certify checks)
    path = tmp_path / "controller.json"
    path.write_text(json.dumps(document))
    result = certify_controller(scenario, path)
    assert not result.success
    assert "the interpolated reference's term" in result.message
    assert "interval 0 " in result.message


def test_the_interpolation_bound_holds_and_is_tight_on_a_double_integrator():
    """(I1) on ``x'' = u`` held: the position's interpolation error is exactly ``h^2 / 8 |u|``
    at the midpoints; the bound must hold and is within the a priori box's slack of it."""
    scenario = load_scenario("double_integrator", check_demos=False)
    demo = scenario.demos[0]
    us = demo.us[:5]
    nominal = simulate(scenario.dynamics, demo.x0, us, scenario.Ts, BASE_SUBSTEPS)
    N, n = len(us), scenario.n
    K = np.zeros((N, scenario.m, n))
    P = np.broadcast_to(np.eye(n), (N + 1, n, n))
    shipped = ShippedFunnel(K=K, P=np.array(P), rho=0.1, rate=0.0)
    # any hull over the nominal's box will do: the dynamics are linear
    funnel = rebuild_funnel(scenario, nominal, shipped, {}, 1)
    substeps = np.full(N, 4)
    offset = law_offset(
        funnel.vertices, funnel.enclosure.rate_bound, K, np.array(P), 0.1, 0.0, scenario.Ts,
        substeps,
    )  # fmt: skip
    grid = simulate_graded(scenario.dynamics, demo.x0, us, scenario.Ts, substeps)
    exact = simulate_graded(scenario.dynamics, demo.x0, us, scenario.Ts, 64 * substeps)
    xhat = np.stack(
        [np.interp(exact.dense_ts, grid.dense_ts, grid.dense_xs[:, j]) for j in range(n)], -1
    )
    measured = np.abs(exact.dense_xs - xhat)
    k_of = np.minimum((exact.dense_ts / scenario.Ts + 1e-9).astype(int), N - 1)
    h = scenario.Ts / 4
    for k in range(N):
        assert np.all(measured[k_of == k] <= offset.deviation[k] + 1e-12)  # rounding
        exact_position_error = h**2 / 8 * np.abs(us[k])  # x'' = u on each axis
        assert np.allclose(measured[k_of == k][:, :2].max(axis=0), exact_position_error, rtol=1e-3)
        assert np.all(offset.deviation[k, :2] <= 1.5 * exact_position_error + 1e-12)


def test_grid_substeps_reads_graded_grids_and_refuses_others():
    Ts, steps = 0.1, np.array([3, 1, 5])
    t = np.concatenate(
        [[0.0], *(k * Ts + Ts / s * np.arange(1, s + 1) for k, s in enumerate(steps))]
    )
    assert np.array_equal(grid_substeps(t, 3, Ts), steps)
    assert grid_substeps(np.delete(t, 3), 3, Ts) is None  # the sample time 0.1 is missing
    skewed = t.copy()
    skewed[6] += 1e-3  # unequal steps inside the third interval
    assert grid_substeps(skewed, 3, Ts) is None
    assert grid_substeps(t[:-1], 3, Ts) is None  # ends before T


def test_law_substeps_refines_where_the_term_does_not_fit():
    """Every term scales with h^2: a term 8x what SAFETY leaves of the room needs sqrt(8)x the
    steps, ``ceil(20 sqrt 8) = 57``."""
    Ts, room = 0.1, 1e-2
    offset = LawOffset(
        steps=np.full(3, Ts / BASE_SUBSTEPS),
        deviation=np.zeros((3, 2)),
        input_offset=np.array([[0.0], [0.0], [1e-3]]),
        lmi_term=np.array([room / 2, 4 * room, 0.0]),
        disturbance=np.zeros(2),
    )
    margins = np.full(3, -room - 1e-6)
    substeps = law_substeps(offset, margins, np.full((3, 1), 1e-2), Ts)
    assert substeps.tolist() == [BASE_SUBSTEPS, 57, BASE_SUBSTEPS]
    tight_input = law_substeps(offset, margins, np.array([[1.0], [1.0], [2.5e-4]]), Ts)
    assert tight_input.tolist() == [BASE_SUBSTEPS, 57, 57]  # 1e-3 against 2.5e-4 / 2: 8x


def test_the_centre_error_joins_the_interpolation_bound():
    """``law_offset``'s ``centre_error`` (the RK4 error of the nominal, a P-norm) is added to
    ``Delta`` as ``eps sqrt(Q_ii)`` in each state: the largest component a P-norm ``eps`` allows."""
    rng = np.random.default_rng(5)
    N, n, m = 3, 4, 2
    A = rng.standard_normal((N + 1, n, n))
    P = np.einsum("kij,klj->kil", A, A) + n * np.eye(n)
    K, vertices = (
        rng.standard_normal((N, m, n)),
        tuple(rng.standard_normal((2, n, n + m)) for _ in range(N)),
    )
    rate_bound = np.abs(rng.standard_normal((N, n)))
    substeps = np.full(N, 20)
    plain = law_offset(vertices, rate_bound, K, P, 1.0, 0.0, 0.1, substeps)
    shifted = law_offset(vertices, rate_bound, K, P, 1.0, 0.0, 0.1, substeps, centre_error=1e-3)
    Q_ii = np.diagonal(np.linalg.inv(P), axis1=1, axis2=2)
    expected = 1e-3 * np.sqrt(np.maximum(Q_ii[:-1], Q_ii[1:]))
    assert np.allclose(shifted.deviation - plain.deviation, expected, rtol=1e-12)
    assert np.all(shifted.lmi_term > plain.lmi_term) and np.all(
        shifted.input_offset > plain.input_offset
    )
