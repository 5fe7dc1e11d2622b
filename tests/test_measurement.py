"""A declared measurement error (``uncertainty.measurement``): the law sees ``x + eta``,
``|eta| <= E`` (``funnel.law`` (I7), ``terminal.check`` (T5)).

Checked: without ``E`` every number of the law's offset is as before; with it the offset gains
``E``, its push ``max_v |B_v K| E`` joins (I5)'s box; a robust double-integrator funnel holds a
small ``E`` and is refused, naming the measurement, at a large one; brute force: the law flown
from the funnel's boundary with worst-case (outward-pushing) measurement errors and
disturbances never leaves the funnel, and with 30x the error it does; certify refuses a file
whose measurement bound was edited below the scenario's. The slow test synthesizes the gusty
double_integrator_hold copy with a small measurement bound (certified, the claims name it) and
a large one (refused).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import pipeline
from pipeline.controller import inverse_linear, load
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import simulate, simulate_graded
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.funnel.law import BASE_SUBSTEPS, law_offset
from pipeline.numerics.terminal.check import check_level
from pipeline.numerics.terminal.equilibrium import equilibrium, lqr_terminal
from pipeline.numerics.verify.recertify import (
    rebuild_funnel,
    recheck_as_shipped,
    reference_substeps,
)
from stages.certify import certify_controller
from tests.helpers.robust import DISTURBANCE, gusty_hold_scenario, robust_double_integrator

SMALL = np.full(4, 1e-3)  # certified on the robust double-integrator funnel
LARGE = np.full(4, 3e-2)  # refused there


@pytest.fixture(scope="module")
def robust_case():
    scenario, trajectory, shipped = robust_double_integrator()
    nominal = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, scenario.Ts)
    rebuilt = rebuild_funnel(scenario, nominal, shipped, {}, 1)
    return scenario, trajectory, shipped, rebuilt


def _offset(case, measurement=None, period=0.0):
    scenario, _, shipped, funnel = case
    grid = np.full(len(shipped.K), 4)
    return law_offset(
        funnel.vertices, funnel.enclosure.rate_bound, shipped.K, shipped.P, shipped.rho,
        shipped.rate, scenario.Ts, grid, 0.0, period, DISTURBANCE, measurement,
    )  # fmt: skip


@pytest.mark.parametrize("period", [0.0, 0.01])
def test_without_a_measurement_every_number_is_as_before(robust_case, period):
    plain, zero = _offset(robust_case, None, period), _offset(robust_case, np.zeros(4), period)
    for field in dataclasses.fields(plain):
        a, b = getattr(plain, field.name), getattr(zero, field.name)
        assert (a is None and b is None) or np.array_equal(a, b), field.name
    assert plain.measurement is None
    assert (plain.hold is None) == (period == 0)


def test_the_measurement_joins_the_offset_and_the_box(robust_case):
    plain, measured = _offset(robust_case), _offset(robust_case, SMALL)
    _, _, shipped, funnel = robust_case
    assert np.allclose(measured.deviation, plain.deviation + SMALL, rtol=0, atol=1e-15)
    assert np.array_equal(measured.lmi_term, plain.lmi_term)  # (I2) keeps (I1)'s Delta alone
    for k, vertices in enumerate(funnel.vertices):
        B = vertices[:, :, 4:]
        box = (np.abs(B @ shipped.K[k]) @ SMALL).max(axis=0)
        assert np.allclose(measured.hold[k], box, rtol=1e-15)
        assert np.allclose(measured.held_input[k], np.abs(shipped.K[k]) @ SMALL, rtol=1e-15)
    assert np.all(measured.input_offset > plain.input_offset)
    robust = measured.with_disturbance(DISTURBANCE)
    assert robust.disturbed and np.all(robust.box >= DISTURBANCE + robust.hold - 1e-15)
    held = _offset(robust_case, SMALL, 0.01)
    held_plain = _offset(robust_case, None, 0.01)
    assert np.all(held.hold >= held_plain.hold) and np.all(held.deviation > held_plain.deviation)


def test_a_small_error_is_certified_and_a_large_one_refused_naming_it(robust_case):
    scenario, trajectory, shipped, _ = robust_case
    exact = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE)
    small = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE, 0.0, SMALL)
    assert exact.failure is None and small.failure is None, small.failure
    assert small.margin > exact.margin  # the error costs room
    large = recheck_as_shipped(scenario, trajectory, shipped, {}, DISTURBANCE, 0.0, LARGE)
    assert large.failure is not None and "the measurement's term (I7)" in large.failure


def _fly(case, measurement, starts=(0, 10, 20), runs=48, seed=3):
    """The largest ``V / rho_t^2`` over flights of ``u = u_ref + K (x + eta - xhat)`` from the
    funnel's boundary (``xhat`` on the grid ``reference_substeps`` ships), with ``eta`` at the
    corner of its box that pushes ``V`` up (``sign(K^T B^T P e)``) for half the runs and at
    random corners for the others, and the disturbance pushing outward, RK4 steps of Ts / 50."""
    scenario, trajectory, shipped, _ = case
    Ts, n, N = scenario.Ts, scenario.n, len(shipped.K)
    nominal = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, BASE_SUBSTEPS)
    grid = reference_substeps(scenario, nominal, shipped, {}, DISTURBANCE, 0.0, SMALL)
    fine = 50
    exact = simulate(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, fine)
    coarse = simulate_graded(scenario.dynamics, trajectory.xs[0], trajectory.us, Ts, grid)
    xhat = np.stack(
        [np.interp(exact.dense_ts, coarse.dense_ts, coarse.dense_xs[:, i]) for i in range(n)], -1
    )
    P_t = inverse_linear(shipped.P, Ts, exact.dense_ts)
    B = scenario.dynamics.f_u(trajectory.xs[0], trajectory.us[0])  # constant: a double integrator
    rng = np.random.default_rng(seed)
    dt, worst = Ts / fine, 0.0
    for start in starts:
        v = rng.standard_normal((runs, n))
        j0 = start * fine
        rho_t = shipped.rho * np.exp(-shipped.rate * exact.dense_ts[j0])
        x = (
            exact.dense_xs[j0]
            + 0.999 * rho_t * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P_t[j0], v))[:, None]
        )
        outward = np.arange(runs) % 2 == 0
        for j in range(j0, N * fine):
            k = j // fine
            signs = rng.choice([-1.0, 1.0], size=(runs, n))

            def field(state, t_index, k=k, signs=signs, outward=outward):
                e = state - exact.dense_xs[t_index]
                push = np.sign(e @ P_t[t_index] @ B @ shipped.K[k])  # sign((B K)^T P e)
                eta = measurement * np.where(outward[:, None], push, signs)
                u = trajectory.us[k] + (state + eta - xhat[t_index]) @ shipped.K[k].T
                w = DISTURBANCE * np.sign(e @ P_t[t_index])
                return scenario.dynamics.f(state, u) + w

            # the stages at the step's start and end use those times' references (the midpoint
            # stages the start's: a coarser but admissible eta and delta)
            k1 = field(x, j)
            k2 = field(x + dt / 2 * k1, j)
            k3 = field(x + dt / 2 * k2, j)
            k4 = field(x + dt * k3, j + 1 if (j + 1) % fine else j)
            x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            e = x - exact.dense_xs[j + 1]
            rho_t = shipped.rho * np.exp(-shipped.rate * exact.dense_ts[j + 1])
            worst = max(worst, float((np.einsum("bi,ij,bj->b", e, P_t[j + 1], e) / rho_t**2).max()))
    return worst


def test_worst_case_errors_flown_from_the_boundary_stay_in_the_funnel(robust_case):
    held = _fly(robust_case, SMALL)
    assert held <= 1.0 + 1e-6, held
    assert held > 0.99  # the flights start on the boundary: the check is not vacuous
    assert _fly(robust_case, 30 * SMALL, starts=(0,), runs=16) > 1.0  # the test can fail


def test_the_terminal_check_holds_the_measurement_as_a_box(robust_case):
    scenario = robust_case[0]
    x_eq, u_eq = equilibrium(scenario)
    K, P = lqr_terminal(scenario, x_eq, u_eq)
    plain = check_level(scenario, x_eq, u_eq, K, P, 0.01, disturbance=DISTURBANCE)
    zero = check_level(
        scenario, x_eq, u_eq, K, P, 0.01, disturbance=DISTURBANCE, measurement=np.zeros(4)
    )
    assert plain == zero
    measured = check_level(
        scenario, x_eq, u_eq, K, P, 0.01, disturbance=DISTURBANCE, measurement=SMALL
    )
    assert measured.disturbance > plain.disturbance  # (T5)'s push joins the box
    assert measured.input_slack < plain.input_slack  # |K_T| E on the inputs


def test_the_uncertainty_parses_and_scales():
    exact = Uncertainty.exact(4)
    assert exact.empty and not exact.measured and exact.measurement.tolist() == [0.0] * 4
    declared = Uncertainty(disturbance=np.zeros(4), measurement=np.array([0.01, 0, 0, 0]))
    assert not declared.empty and declared.measured
    assert declared.scaled(2.0).measurement.tolist() == [0.02, 0, 0, 0]


MEASURED = "  measurement: {x: 0.002, y: 0.002, vx: 0.002, vy: 0.002}\n"


def _measured(folder: Path, block: str = MEASURED) -> Path:
    path = gusty_hold_scenario(folder, 0.02)
    path.write_text(path.read_text().replace("\nterminal: hold", "\n" + block + "terminal: hold"))
    return path


@pytest.mark.slow
@pytest.mark.xdist_group("measurement")
def test_a_gusty_hold_run_holds_a_small_measurement_error_and_certify_checks_it(tmp_path):
    path = _measured(tmp_path / "measured")
    out = tmp_path / "out"
    result = pipeline.synthesize(path, out=out, samples=300)
    assert result.success, result.message
    declared = "|w_vx| <= 0.02, |w_vy| <= 0.02, |eta_x| <= 0.002, |eta_y| <= 0.002"
    claims = [c.claim for c in result.claims]
    assert sum(f"under the declared uncertainty ({declared}" in c for c in claims) == 2, claims
    controller = load(out / "controller.json")
    assert controller.measurement_bound.tolist() == [0.002] * 4
    scenario = load_scenario(path)
    assert certify_controller(scenario, out / "controller.json").success
    document = json.loads((out / "controller.json").read_text())
    document["uncertainty"]["measurement_bound"][2] = 0.001
    edited = tmp_path / "edited.json"
    edited.write_text(json.dumps(document))
    refused = certify_controller(scenario, edited)
    assert not refused.success
    assert "the file holds |eta_vx| <= 0.001, the scenario declares 0.002" in refused.message
    del document["uncertainty"]["measurement_bound"]
    edited.write_text(json.dumps(document))
    assert "|eta_x| <= 0, the scenario" in certify_controller(scenario, edited).message
    large = _measured(tmp_path / "large", MEASURED.replace("0.002", "0.05"))
    assert not certify_controller(load_scenario(large), out / "controller.json").success
    wide = pipeline.synthesize(large, out=tmp_path / "out_large", samples=300)
    assert not wide.success
    assert "no funnel certified" in wide.message
    assert "the funnel does not hold the measurement error" in wide.message


def test_the_monte_carlo_draws_the_error_in_its_box_and_nothing_else_changes():
    from pipeline.numerics.closed_loop.gusts import sample

    exact = Uncertainty(disturbance=np.array([0.0, 0.0, 0.05, 0.05]))
    measured = dataclasses.replace(exact, measurement=SMALL)
    a = sample(exact, np.random.default_rng(1), 200, 3.0)
    b = sample(measured, np.random.default_rng(1), 200, 3.0)
    assert a.errors is None
    assert np.array_equal(a.gusts, b.gusts) and np.array_equal(a.parameters, b.parameters)
    assert b.errors.shape == b.gusts.shape and np.all(np.abs(b.errors) <= SMALL)
    corners = np.all(np.abs(b.errors) == SMALL, axis=(1, 2))
    assert 0.1 < corners.mean() < 0.9  # some runs at corners, the others uniform
    assert np.array_equal(b.rows(np.arange(3)).error(0.6), b.errors[:3, 1])
