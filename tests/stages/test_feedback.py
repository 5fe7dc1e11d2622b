"""Stage ``feedback``: the certificate re-checked independently of the code that made it.

- every vertex satisfies the contraction LMI (generalised eigenvalues by scipy);
- Jacobians at random points of the operating region lie in the hull (an LP per point), and a
  point outside the region does not (the test has teeth);
- simulated pairs of closed-loop trajectories inside the region obey
  ``||e(t)||_P <= exp(-lambda t) ||e(0)||_P``;
- the margins per unit radius are the maxima they claim to be.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import sympy
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog
from shapely.geometry import MultiPoint, Point

from pipeline.model.dynamics import Dynamics
from pipeline.model.scenario import load_scenario
from pipeline.numerics.hull import arc_polygon, jacobian_hull
from stages.feedback import FeedbackResult, design_feedback


@pytest.fixture(scope="module")
def quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


@pytest.fixture(scope="module")
def certified(quadrotor) -> FeedbackResult:
    return design_feedback(quadrotor)


def in_hull(vertices: np.ndarray, point: np.ndarray) -> bool:
    """Is ``point`` (d,) a convex combination of ``vertices`` (V, d)? (LP feasibility)."""
    V = vertices.reshape(len(vertices), -1)
    A_eq = np.vstack([V.T, np.ones(len(V))])
    b_eq = np.append(point.ravel(), 1.0)
    result = linprog(np.zeros(len(V)), A_eq=A_eq, b_eq=b_eq, bounds=(0, None), method="highs")
    return result.status == 0


def jacobians(dynamics: Dynamics, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    return np.concatenate([dynamics.f_x(x, u), dynamics.f_u(x, u)], axis=-1)


def region_samples(scenario, count: int, rng: np.random.Generator):
    """``count`` random (x, u) with the region's variables uniform in their box, plus its
    corners; other states/inputs random (the Jacobian does not depend on them)."""
    x = rng.normal(size=(count, scenario.n))
    u = rng.normal(size=(count, scenario.m))
    names = list(scenario.operating_region)
    corners = np.array(np.meshgrid(*[[0, 1]] * len(names))).reshape(len(names), -1).T
    x, u = x[: count - len(corners)], u[: count - len(corners)]
    x = np.vstack([x, np.zeros((len(corners), scenario.n))])
    u = np.vstack([u, np.zeros((len(corners), scenario.m))])
    for k, name in enumerate(names):
        lo, hi = scenario.operating_region[name]
        inner = rng.uniform(lo, hi, count - len(corners))
        value = np.concatenate([inner, lo + (hi - lo) * corners[:, k]])
        if name in scenario.state_names:
            x[:, scenario.state_names.index(name)] = value
        else:
            u[:, scenario.input_names.index(name)] = value
    return x, u


def test_quadrotor_is_certified_at_every_vertex(certified, quadrotor):
    assert certified.success, certified.message
    P, K, lam = certified.P, certified.K, certified.rate
    assert lam == quadrotor.feedback.rate
    np.testing.assert_array_equal(P, P.T)
    assert np.linalg.eigvalsh(P)[0] > 0
    n = quadrotor.n
    for vertex in certified.vertices:
        Acl = vertex[:, :n] + vertex[:, n:] @ K
        M = Acl.T @ P + P @ Acl + 2 * lam * P
        assert scipy.linalg.eigh((M + M.T) / 2, P, eigvals_only=True).max() < 0
    assert certified.certified_margin < 0


def test_jacobians_of_the_region_lie_in_the_hull(certified, quadrotor):
    x, u = region_samples(quadrotor, 60, np.random.default_rng(0))
    for J in jacobians(quadrotor.dynamics, x, u):
        assert in_hull(certified.vertices, J)
    # Teeth: pitch outside the certified region is outside the hull.
    x_out, u_out = x[:1].copy(), u[:1].copy()
    x_out[0, quadrotor.state_names.index("theta")] = 1.0
    u_out[0, quadrotor.input_names.index("u1")] = 14.9
    assert not in_hull(certified.vertices, jacobians(quadrotor.dynamics, x_out, u_out)[0])


def rk4_closed_loop(dynamics, K, x_ref0, x0, u_ref, Ts, substeps):
    """Reference (n,) and closed-loop states (B, n) under ``u = u_ref + K (x - x_ref)``, with the
    feedback evaluated continuously inside each RK4 step. Returns (steps+1, n), (steps+1, B, n),
    and the closed-loop inputs (steps, B, m) at the step starts."""

    def field(z_ref, z, u):
        return dynamics.f(z_ref, u), dynamics.f(z, u + (z - z_ref) @ K.T)

    h = Ts / substeps
    refs, xs, us = [x_ref0], [x0], []
    r, x = x_ref0, x0
    for u in u_ref:
        for _ in range(substeps):
            us.append(u + (x - r) @ K.T)
            a1, b1 = field(r, x, u)
            a2, b2 = field(r + h / 2 * a1, x + h / 2 * b1, u)
            a3, b3 = field(r + h / 2 * a2, x + h / 2 * b2, u)
            a4, b4 = field(r + h * a3, x + h * b3, u)
            r = r + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
            x = x + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
            refs.append(r)
            xs.append(x)
    return np.array(refs), np.array(xs), np.array(us)


def test_closed_loop_pairs_contract_at_the_certified_rate(certified, quadrotor):
    K, P, lam = certified.K, certified.P, certified.rate
    Ts, substeps = 0.1, 10
    t = Ts * np.arange(60)
    u_ref = np.column_stack([9.81 + 1.5 * np.sin(0.7 * t), 0.3 * np.cos(1.3 * t)])
    rng = np.random.default_rng(1)
    radius = certified.required_radius(quadrotor.clearance)
    w = rng.normal(size=(64, quadrotor.n))
    L = np.linalg.cholesky(P)
    e0 = scipy.linalg.solve_triangular(L.T, w.T, lower=False).T  # ||e0||_P = |w|
    e0 *= radius / np.linalg.norm(w, axis=1, keepdims=True)
    x_ref0 = np.zeros(quadrotor.n)
    refs, xs, us = rk4_closed_loop(quadrotor.dynamics, K, x_ref0, x_ref0 + e0, u_ref, Ts, substeps)
    # Precondition of the guarantee: both solutions stay in the operating region.
    theta = quadrotor.state_names.index("theta")
    lo, hi = quadrotor.operating_region["theta"]
    assert np.all((xs[..., theta] >= lo) & (xs[..., theta] <= hi))
    assert np.all((refs[..., theta] >= lo) & (refs[..., theta] <= hi))
    lo, hi = quadrotor.operating_region["u1"]
    assert np.all((us[..., 0] >= lo) & (us[..., 0] <= hi))
    e = xs - refs[:, None, :]
    norm = np.sqrt(np.einsum("tbi,ij,tbj->tb", e, P, e))
    times = Ts / substeps * np.arange(len(refs))
    ratio = norm * np.exp(lam * times)[:, None] / norm[0]
    assert ratio.max() <= 1 + 1e-6
    assert ratio[-1].max() < 0.9  # the errors do shrink (faster than the certified rate)


def test_margins_are_the_maxima_over_the_unit_ball(certified):
    P, K = certified.P, certified.K
    rng = np.random.default_rng(2)
    w = rng.normal(size=(20000, P.shape[0]))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    e = w @ np.linalg.inv(scipy.linalg.sqrtm(P).real)  # ||e||_P = 1
    for j in range(K.shape[0]):
        assert np.abs(e @ K[j]).max() <= certified.input_margin_per_radius[j] * (1 + 1e-9)
        assert np.abs(e @ K[j]).max() >= 0.95 * certified.input_margin_per_radius[j]
    assert np.all(np.abs(e).max(axis=0) <= certified.state_extent_per_radius * (1 + 1e-9))
    # r_d: the position projection of the r_d ball reaches exactly distance d.
    r_d = certified.required_radius(2.0)
    P_inv = np.linalg.inv(P)
    lam_max = np.linalg.eigvalsh(certified.position_shape)[-1]
    assert np.isclose(r_d, 2.0 / np.sqrt(lam_max))
    assert np.isclose(certified.position_extent(r_d), 2.0)
    np.testing.assert_allclose(certified.position_shape, P_inv[:2, :2])
    np.testing.assert_allclose(certified.input_margin(3.0), 3 * certified.input_margin_per_radius)
    assert set(certified.region_extent(1.0)) == set(certified.region)


def test_init_slice_and_margins_are_useful(certified, quadrotor):
    """The design objective: at r_d the Init slice is at least as large as the issue's LQR design
    (semi-axes 0.73 x 0.47 m at d = 1) and the thrust margin no larger (0.44 N)."""
    r_d = certified.required_radius(quadrotor.clearance)
    axes = certified.slice_semi_axes(r_d, quadrotor.position_index)
    assert axes[-1] >= 0.47 and np.prod(axes) >= 0.73 * 0.47
    assert certified.input_margin(r_d)[0] <= 0.45


@pytest.mark.parametrize("gain", ["lqr", "joint"])
def test_both_designs_certify_and_auto_keeps_the_better(quadrotor, certified, gain):
    result = design_feedback(quadrotor, gain=gain)
    assert result.success and result.gain == gain, result.message
    assert result.certified_margin < 0
    assert certified.objective <= result.objective + 1e-6


def test_too_fast_a_rate_fails_naming_rate_and_region(quadrotor):
    result = design_feedback(quadrotor, rate=20.0)
    assert not result.success and result.P is None
    assert "rate 20" in result.message and "theta in [-0.6, 0.6]" in result.message
    with pytest.raises(ValueError, match="not certified"):
        result.required_radius(1.0)


def test_linear_dynamics_give_one_exact_vertex(double_integrator):
    scenario = double_integrator()
    assert design_feedback(scenario).success  # linear: one exact vertex
    assert len(jacobian_hull(scenario.dynamics, {}).vertices) == 1


def test_missing_region_variable_is_named(quadrotor):
    with pytest.raises(ValueError, match="theta"):
        jacobian_hull(quadrotor.dynamics, {"u1": (5.0, 14.9)})


def test_bad_gain_option():
    with pytest.raises(ValueError, match="gain must be one of"):
        design_feedback(None, gain="pole-placement")  # type: ignore[arg-type]


def test_generic_hull_is_sound_for_other_nonlinearities():
    """Squares, products of functions of one variable, and a non-separable term."""
    a, b, u = sympy.symbols("a b u", real=True)
    dynamics = Dynamics.from_expressions(
        [a, b], [u], [b + sympy.sin(a) * sympy.cos(a), u * sympy.cos(a) - b**2 + sympy.sin(a + b)]
    )
    region = {"a": (-0.4, 0.9), "b": (-1.0, 2.0), "u": (1.0, 3.0)}
    hull = jacobian_hull(dynamics, region)
    rng = np.random.default_rng(3)
    z = np.column_stack([rng.uniform(*region[k], 40) for k in ("a", "b", "u")])
    for J in jacobians(dynamics, z[:, :2], z[:, 2:]):
        assert in_hull(hull.vertices, J)


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-3.0, 3.0),
    st.floats(0.01, 3.0),
    st.floats(0.0, 1.0),
    st.integers(1, 12),
)
def test_arc_polygon_contains_the_arc(lower, width, fraction, segments):
    polygon = MultiPoint(arc_polygon(lower, lower + width, segments)).convex_hull
    angle = lower + fraction * width
    assert polygon.covers(Point(np.cos(angle), np.sin(angle)))
