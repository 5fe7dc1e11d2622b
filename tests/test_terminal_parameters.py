"""(T7): the declared parameter intervals in the terminal set's Jacobian hull.

On quadrotor_hill_flythrough with a declared wind, mass and gust: the hull of ``[f_x f_u]`` with
the parameters as interval variables holds the parametric model's Jacobian at sampled points, the
additive box at the equilibrium holds the parameters' shift there, a hover designed under (T7)
keeps ``V' < 0`` on its boundary for sampled parameters and gusts of the true parametric model,
and certify re-checks a block by (T7) only when it states less than the whole box's bound. At the
issue's own bound (wind [-1, 0], mass +-5%, gust 0.25) no hover holds the whole box's bound, and
one holds (T7)'s.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest
from scipy.optimize import linprog

from pipeline.controller import Controller, TerminalController
from pipeline.numerics.terminal import design as terminal_design
from pipeline.numerics.terminal.check import check_level, largest_level
from pipeline.numerics.terminal.design import TerminalDesign, hold_design
from pipeline.numerics.terminal.equilibrium import TerminalError, equilibrium, lqr_terminal
from pipeline.numerics.terminal.robust import robust_metric
from pipeline.numerics.uncertainty import additive_bound, equilibrium_bound, parametric_hull
from pipeline.numerics.verify.declared import terminal_claim
from pipeline.numerics.verify.terminal import recheck_terminal
from pipeline.results.certify import CertificationResult
from pipeline.runtime.verdict import Evidence, after_horizon
from stages.controller import terminal_block
from stages.montecarlo import claims_invariance
from tests.test_uncertainty import quadrotor

MODERATE = """
uncertainty:
  disturbance: {vX: 0.1, vY: 0.1}
  parameters: {wX: [-0.8, -0.2], m: [0.97, 1.03]}
"""


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return quadrotor(tmp_path_factory.mktemp("terminal_parameters"), MODERATE)


@pytest.fixture(scope="module")
def design(scenario):
    """A (T7) hover at Goal's centre: the LQR gain, (T3)'s metric and the largest level, each
    with the parameters in the hull and the box at the equilibrium."""
    u = scenario.uncertainty
    x_eq, u_eq = equilibrium(scenario)
    K = lqr_terminal(scenario, x_eq, u_eq)[0]
    box = equilibrium_bound(u, scenario, x_eq, u_eq)
    P = robust_metric(scenario, x_eq, u_eq, K, box, parameters=u)
    assert P is not None
    check = largest_level(scenario, x_eq, u_eq, K, P, disturbance=box, parameters=u)
    assert check.success
    return TerminalDesign(
        x_eq=x_eq, u_eq=u_eq, K=K, P=P, check=check, gain="lqr", fit=0.0, disturbance=box
    )


def parameter_samples(scenario, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, q) parameters drawn from their intervals, the box's corners first."""
    u = scenario.uncertainty
    p = rng.uniform(u.parameter_lower, u.parameter_upper, (count, len(u.parameter_names)))
    corners = list(itertools.product(*zip(u.parameter_lower, u.parameter_upper, strict=True)))
    p[: len(corners)] = corners
    return p


def test_the_hull_of_the_state_and_input_columns_holds_the_parametric_jacobian(scenario):
    """300 sampled ``(x, u, p)``: each ``[f_x f_u]`` is a convex combination of the vertices (an
    LP), and dropping the parameters' own columns keeps the hull small."""
    region = {"theta": (-0.3, 0.3), "u1": (7.0, 13.0), "u2": (-5.0, 5.0)}
    hull = parametric_hull(scenario, region, 4, scenario.uncertainty)
    n, m = scenario.n, scenario.m
    assert hull.vertices.shape[1:] == (n, n + m)
    dynamics = scenario.uncertainty.parametric
    rng = np.random.default_rng(1)
    p = parameter_samples(scenario, 300, rng)
    flat = hull.vertices.reshape(len(hull.vertices), -1).T  # (n (n + m), V)
    equality = np.vstack([flat, np.ones((1, flat.shape[1]))])
    for k in range(len(p)):
        x = np.zeros(n)
        x[2] = rng.uniform(*region["theta"])
        u = np.array([rng.uniform(*region["u1"]), rng.uniform(*region["u2"])])
        v = np.concatenate([u, p[k]])
        J = np.hstack([dynamics.f_x(x, v), dynamics.f_u(x, v)[:, :m]])
        found = linprog(
            np.zeros(flat.shape[1]), A_eq=equality, b_eq=np.append(J.ravel(), 1.0),
            bounds=(0, None), method="highs",
        )  # fmt: skip
        assert found.status == 0, f"sample {k}: {J} outside the hull"
    nominal = parametric_hull(scenario, region, 4)  # no parameters: the nominal model's hull
    assert len(nominal.vertices) < len(hull.vertices) <= 2 * len(nominal.vertices)


def test_the_box_at_the_equilibrium_holds_the_parameters_shift_there(scenario, design):
    """``equilibrium_bound`` against ``f(x_eq, u_eq, p) - f(x_eq, u_eq, p0)`` over sampled and
    corner parameters: above every one, within 5% of the largest (the mean-value form), and
    below the whole box's bound (U1)."""
    u = scenario.uncertainty
    x_eq, u_eq = design.x_eq, design.u_eq
    bound = equilibrium_bound(u, scenario, x_eq, u_eq)
    p = parameter_samples(scenario, 2000, np.random.default_rng(2))
    v = np.column_stack([np.broadcast_to(u_eq, (len(p), scenario.m)), p])
    v0 = np.concatenate([u_eq, u.parameter_nominal])
    shift = np.abs(
        u.parametric.f(np.broadcast_to(x_eq, (len(p), scenario.n)), v) - u.parametric.f(x_eq, v0)
    )
    largest = shift.max(axis=0) + u.disturbance
    assert np.all(largest <= bound)
    assert np.all(bound <= 1.05 * largest + 1e-12)
    assert np.all(bound <= additive_bound(scenario)) and np.any(bound < additive_bound(scenario))


def test_a_hover_under_t7_decreases_on_its_boundary_for_the_true_model(scenario, design):
    """``V' = 2 e^T P (f(x, u_eq + K e, p) + d) < 0`` at 4000 points of ``V = c``, with ``p``
    from the intervals (corners included) and ``d`` at the gust box's corners: the parametric
    model itself, not the certificate's hull."""
    assert check_level(
        scenario, design.x_eq, design.u_eq, design.K, design.P, design.check.level,
        disturbance=design.disturbance, parameters=scenario.uncertainty,
    ).success  # fmt: skip
    rng = np.random.default_rng(3)
    count, n = 4000, scenario.n
    L = np.linalg.cholesky(design.P)  # P = L L^T: e = sqrt(c) L^-T z, |z| = 1
    z = rng.normal(size=(count, n))
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    e = np.sqrt(design.check.level) * np.linalg.solve(L.T, z.T).T  # (count, n)
    u = design.u_eq + e @ design.K.T
    p = parameter_samples(scenario, count, rng)
    gust = scenario.uncertainty.disturbance * rng.choice([-1.0, 1.0], size=(count, n))
    f = scenario.uncertainty.parametric.f(design.x_eq + e, np.column_stack([u, p]))
    derivative = 2 * np.einsum("ki,ij,kj->k", e, design.P, f + gust)
    assert derivative.max() < 0


def test_certify_rechecks_by_t7_only_a_block_stating_less_than_the_whole_box(scenario, design):
    block = TerminalController(
        x_eq=design.x_eq, u_eq=design.u_eq, K=design.K, P=design.P, level=design.check.level,
        disturbance=design.disturbance,
    )  # fmt: skip
    bound, parameters, failures = terminal_claim(scenario, block)
    assert parameters is scenario.uncertainty and not failures
    assert np.array_equal(bound, design.disturbance)
    whole = TerminalController(
        x_eq=design.x_eq, u_eq=design.u_eq, K=design.K, P=design.P, level=design.check.level,
        disturbance=additive_bound(scenario),
    )  # fmt: skip
    bound, parameters, failures = terminal_claim(scenario, whole)
    assert parameters is None and not failures and np.array_equal(bound, additive_bound(scenario))
    short = design.disturbance.copy()
    short[4] *= 0.99  # vY's box below the parameters' shift at the equilibrium
    tampered = TerminalController(
        x_eq=design.x_eq, u_eq=design.u_eq, K=design.K, P=design.P, level=design.check.level,
        disturbance=short,
    )  # fmt: skip
    bound, parameters, failures = terminal_claim(scenario, tampered)
    assert parameters is scenario.uncertainty and np.array_equal(bound, design.disturbance)
    assert failures and "|w_vY| <=" in failures[0] and "(T7)" in failures[0]


def test_the_file_and_the_claim_state_the_box_t7_held(scenario, design):
    """The terminal block states the (T7) box, not the whole box's bound it was handed, and the
    after-T claim says what was proved: the parameters in the hull and that box."""
    block, fit, _ = terminal_block(
        scenario, design.K, design.P, [design.x_eq], [0.0], disturbance=additive_bound(scenario),
        design=design,
    )  # fmt: skip
    assert block is not None and fit == 0.0
    assert block["disturbance"] == design.disturbance.tolist()
    check = CertificationResult(
        path=Path("controller.json"), sha256="", metric_eigenvalue=1.0, contraction_margin=-1.0,
        vertices=1, radii=(), verified_radii=(), reference_error=0.0, covered_fraction=1.0,
        success=True, message="", terminal=True, terminal_decay=0.5, terminal_fit=0.5,
        terminal_box=tuple(design.disturbance),
    )  # fmt: skip

    def claim(certification: CertificationResult) -> str:
        evidence = SimpleNamespace(
            scenario=scenario, certification=certification, feedback_period=0
        )
        return after_horizon(cast(Evidence, evidence), certified=True).how

    local = claim(check)
    assert "(T7)" in local and "declared parameter value" in local
    assert f"|w_vY| <= {design.disturbance[4]:.3g}" in local
    whole = claim(dataclasses.replace(check, terminal_box=()))
    assert "(T7)" not in whole and "with w in that bound" in whole


def tried_holds(monkeypatch: pytest.MonkeyPatch) -> list[tuple[bool, str | None]]:
    """Each ``_hold`` that ``hold_design`` tries from now on, in order: whether with (T7)'s
    parameters, and its ``TerminalError`` (None: it designed a set)."""
    tried: list[tuple[bool, str | None]] = []
    hold = terminal_design._hold

    def recorded(scenario, x_eq, u_eq, demands):
        try:
            design = hold(scenario, x_eq, u_eq, demands)
        except TerminalError as error:
            tried.append((demands.parameters is not None, str(error)))
            raise
        tried.append((demands.parameters is not None, None))
        return design

    monkeypatch.setattr(terminal_design, "_hold", recorded)
    return tried


@pytest.mark.slow
def test_hold_design_keeps_the_whole_box_where_it_leaves_a_hover(scenario, monkeypatch):
    """(T7) is the fallback: where the whole box's bound certifies a set, that design stands
    and (T7) is not tried."""
    tried = tried_holds(monkeypatch)
    whole = hold_design(scenario, additive_bound(scenario), parameters=scenario.uncertainty)
    assert whole.disturbance is None and whole.check.success
    assert tried == [(False, None)]


def test_where_neither_box_leaves_a_hover_the_error_says_why_each_failed(scenario, monkeypatch):
    """The whole box's bound first, then (T7): when both fail, the one-line error names both."""
    tried: list[bool] = []

    def fails(scenario, x_eq, u_eq, demands):
        tried.append(demands.parameters is not None)
        raise TerminalError("(T7) failed" if tried[-1] else "the whole box failed")

    monkeypatch.setattr(terminal_design, "_hold", fails)
    message = r"^under the whole box's bound: the whole box failed; then \(T7\) failed$"
    with pytest.raises(TerminalError, match=message):
        hold_design(scenario, additive_bound(scenario), parameters=scenario.uncertainty)
    assert tried == [False, True]


@pytest.mark.slow
def test_at_the_issues_bound_only_t7_holds_a_hover(tmp_path: Path, monkeypatch):
    """Wind [-1, 0], mass +-5%, gust 0.25 (issue 29): the whole box's bound (vY 1.075) leaves
    no hover; (T7)'s (0.79 at the equilibrium) leaves one, certified from scratch."""
    scenario = quadrotor(tmp_path)
    tried = tried_holds(monkeypatch)
    design = hold_design(scenario, additive_bound(scenario), parameters=scenario.uncertainty)
    (whole, without), (local_box, failure) = tried
    assert not whole and without is not None and "does not decrease" in without
    assert local_box and failure is None
    local = equilibrium_bound(scenario.uncertainty, scenario, design.x_eq, design.u_eq)
    assert design.disturbance is not None and np.array_equal(design.disturbance, local)
    assert design.disturbance[4] < 0.8 < additive_bound(scenario)[4]
    assert check_level(
        scenario, design.x_eq, design.u_eq, design.K, design.P, design.check.level,
        disturbance=design.disturbance, parameters=scenario.uncertainty,
    ).success  # fmt: skip


def holding(block: TerminalController) -> Controller:
    """A funnel file with ``block`` as its terminal and one end tube of radius 0 at its
    equilibrium: what ``recheck_terminal`` and ``claims_invariance`` read of a file."""
    end = SimpleNamespace(x_ref=block.x_eq[None], radius=0.0, rate=0.0, T=1.0, P=np.eye(6)[None])
    file = SimpleNamespace(
        terminal=block, funnel=True, feedback_period=0.0, measurement_bound=None,
        trajectories=[end], source="controller.json",
    )  # fmt: skip
    return cast(Controller, file)


def test_certify_and_the_monte_carlo_read_a_t7_block_as_t7(scenario, design):
    """certify's re-check of a (T7) block passes and fails at four times its level; the Monte
    Carlo counts its exits, and those of a whole-box block, not those of a short one."""
    block = TerminalController(
        x_eq=design.x_eq, u_eq=design.u_eq, K=design.K, P=design.P, level=design.check.level,
        disturbance=design.disturbance,
    )  # fmt: skip
    decay, fit, failures = recheck_terminal(scenario, holding(block))
    assert not failures and decay > 0 and fit == 0.0
    raised = dataclasses.replace(block, level=4 * block.level)
    assert recheck_terminal(scenario, holding(raised))[2]
    assert claims_invariance(scenario, holding(block))
    whole = dataclasses.replace(block, disturbance=additive_bound(scenario))
    assert claims_invariance(scenario, holding(whole))
    short = block.disturbance.copy()
    short[3] *= 0.5
    assert not claims_invariance(scenario, holding(dataclasses.replace(block, disturbance=short)))
    assert not claims_invariance(scenario, holding(dataclasses.replace(block, disturbance=None)))
