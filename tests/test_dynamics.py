"""Dynamics: exact Jacobians against central finite differences, batching, sparsity patterns.

For every shipped scenario, ``f_x`` and ``f_u`` at random points must match
``(f(x + h e_j, u) - f(x - h e_j, u)) / 2h`` (error O(h^2)), on batches of points at once.
At one point (``x (n,)``, ``u (m,)``) ``f``, ``f_x``, ``f_u`` and ``f_scalars`` take a short path
that must give bitwise the numbers of the batch code (``np.moveaxis`` of the point into scalars).
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
import sympy
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline import available_scenarios, load_scenario
from pipeline.model.dynamics import Dynamics, FloatArray
from tests.helpers.dynamics import batch_code, every_function_dynamics

SCENARIOS = available_scenarios()


@pytest.fixture(scope="module", params=SCENARIOS)
def scenario(request: pytest.FixtureRequest):
    return load_scenario(request.param, check_demos=False)


@cache
def _quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


@pytest.fixture(scope="module")
def quadrotor():
    return _quadrotor()


def random_points(scenario, count: int, seed: int = 0) -> tuple[FloatArray, FloatArray]:
    """``x (count, n)`` in the Init box widened by 1 on each side, ``u (count, m)`` in bounds."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(scenario.init_lower - 1.0, scenario.init_upper + 1.0, (count, scenario.n))
    u = rng.uniform(scenario.input_lower, scenario.input_upper, (count, scenario.m))
    return x, u


def central_differences(
    dynamics: Dynamics, x: FloatArray, u: FloatArray, h: float = 1e-6
) -> tuple[FloatArray, FloatArray]:
    """Finite-difference Jacobians of a batch: ``x (B, n)``, ``u (B, m)`` -> ``(B, n, n)``,
    ``(B, n, m)``; column ``j`` is ``(f(. + h e_j) - f(. - h e_j)) / 2h``."""
    E_x, E_u = h * np.eye(x.shape[-1]), h * np.eye(u.shape[-1])
    # Perturbed copies on a new axis: (B, j, n); f over them -> (B, j, n); transpose to (B, n, j).
    A = (dynamics.f(x[:, None] + E_x, u[:, None]) - dynamics.f(x[:, None] - E_x, u[:, None])) / (
        2 * h
    )
    B = (dynamics.f(x[:, None], u[:, None] + E_u) - dynamics.f(x[:, None], u[:, None] - E_u)) / (
        2 * h
    )
    return np.swapaxes(A, -1, -2), np.swapaxes(B, -1, -2)


def test_some_scenario_is_shipped() -> None:
    assert "quadrotor_hill_flythrough" in SCENARIOS


def test_jacobians_match_central_differences(scenario) -> None:
    x, u = random_points(scenario, 200)
    A_fd, B_fd = central_differences(scenario.dynamics, x, u)
    np.testing.assert_allclose(scenario.dynamics.f_x(x, u), A_fd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(scenario.dynamics.f_u(x, u), B_fd, rtol=1e-6, atol=1e-6)


def test_batch_shapes_and_broadcasting(scenario) -> None:
    D, n, m = scenario.dynamics, scenario.n, scenario.m
    x, u = random_points(scenario, 12, seed=1)
    assert D.f(x[0], u[0]).shape == (n,)
    assert D.f_x(x[0], u[0]).shape == (n, n)
    assert D.f_u(x[0], u[0]).shape == (n, m)
    X, U = x.reshape(3, 4, n), u.reshape(3, 4, m)
    assert D.f(X, U).shape == (3, 4, n)
    assert D.f_x(X, U).shape == (3, 4, n, n)
    assert D.f_u(X, U).shape == (3, 4, n, m)
    # x (3, 1, n) against u (4, m) broadcasts to (3, 4).
    assert D.f(X[:, :1], U[0]).shape == (3, 4, n)
    assert D.f_x(X[:, :1], U[0]).shape == (3, 4, n, n)
    assert D.f_u(x[:1], u).shape == (12, n, m)
    # A batch equals the points one at a time.
    for function in (D.f, D.f_x, D.f_u):
        batched = function(X, U)
        single = np.array([function(a, b) for a, b in zip(x, u, strict=True)])
        np.testing.assert_allclose(batched.reshape(single.shape), single, rtol=1e-14, atol=0)
        assert batched.dtype == np.float64


def test_sparsity_is_the_symbolic_nonzero_pattern(scenario) -> None:
    D = scenario.dynamics
    symbolic_x = np.array([[not e.is_zero for e in row] for row in D.jacobian_x.tolist()])
    symbolic_u = np.array([[not e.is_zero for e in row] for row in D.jacobian_u.tolist()])
    np.testing.assert_array_equal(D.sparsity_x, symbolic_x)
    np.testing.assert_array_equal(D.sparsity_u, symbolic_u.reshape(D.n, D.m))
    # Numerically: zero wherever the pattern says so, and each structural entry nonzero somewhere.
    x, u = random_points(scenario, 50, seed=2)
    for values, pattern in [(D.f_x(x, u), D.sparsity_x), (D.f_u(x, u), D.sparsity_u)]:
        assert np.all(values[:, ~pattern] == 0)
        assert np.all(np.any(values[:, pattern] != 0, axis=0))


def test_quadrotor_structure(quadrotor) -> None:
    D = quadrotor.dynamics
    assert D.state_names == ("X", "Y", "theta", "vX", "vY", "omega")
    assert D.input_names == ("u1", "u2")
    assert int(D.sparsity_x.sum()) == 7
    assert int(D.sparsity_u.sum()) == 3
    i = {name: k for k, name in enumerate(D.state_names)}
    expected_x = {
        ("X", "vX"),
        ("Y", "vY"),
        ("theta", "omega"),
        ("vX", "theta"),
        ("vX", "vX"),
        ("vY", "theta"),
        ("vY", "vY"),
    }
    assert {(a, b) for a in i for b in i if D.sparsity_x[i[a], i[b]]} == expected_x
    assert {(a, j) for a in i for j in range(2) if D.sparsity_u[i[a], j]} == {
        ("vX", 0),
        ("vY", 0),
        ("omega", 1),
    }
    assert D.depends_on() == ("theta", "u1")
    assert set(D.depends_on()) == set(quadrotor.operating_region)


def test_quadrotor_vector_field_known_values(quadrotor) -> None:
    """Hover: thrust m g at theta = 0, no wind relative velocity -> only the drag term."""
    D = quadrotor.dynamics
    x = np.array([2.0, 2.5, 0.0, -0.5, 0.0, 0.0])  # moving with the wind (wX = -0.5)
    np.testing.assert_allclose(D.f(x, [9.81, 0.0]), [-0.5, 0.0, 0.0, 0.0, 0.0, 0.0], atol=1e-15)
    x = np.array([0.0, 0.0, np.pi / 2, 0.0, 0.0, 0.3])
    # mu (wX - vX) - (u1/m) sin(theta) = 0.5 * -0.5 - 2 = -2.25; vY: 0 + 0 - 9.81.
    np.testing.assert_allclose(D.f(x, [2.0, 1.5]), [0, 0, 0.3, -2.25, -9.81, 1.5], atol=1e-14)


finite = st.floats(min_value=-3.0, max_value=3.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(
    x=st.lists(finite, min_size=6, max_size=6),
    u=st.tuples(st.floats(0.0, 14.9), st.floats(-10.0, 10.0)),
)
def test_quadrotor_jacobians_property(x: list[float], u: tuple[float, float]) -> None:
    """At any point, f_x and f_u equal central differences (hypothesis draws the points)."""
    D = _quadrotor().dynamics
    X, U = np.array([x]), np.array([u])
    A_fd, B_fd = central_differences(D, X, U)
    np.testing.assert_allclose(D.f_x(X, U), A_fd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(D.f_u(X, U), B_fd, rtol=1e-6, atol=1e-6)


def test_constant_expressions_broadcast() -> None:
    """A vector field with constant entries (zero Jacobians) still returns full batch shapes."""
    a, b, c = sympy.symbols("a b c", real=True)
    D = Dynamics.from_expressions([a, b], [c], [sympy.Integer(1), a * c])
    x, u = np.zeros((5, 2)), np.ones((5, 1))
    np.testing.assert_array_equal(D.f(x, u), np.tile([1.0, 0.0], (5, 1)))
    assert D.f_x(x, u).shape == (5, 2, 2) and D.f_u(x, u).shape == (5, 2, 1)
    np.testing.assert_array_equal(D.sparsity_x, [[False, False], [True, False]])
    np.testing.assert_array_equal(D.sparsity_u, [[False], [True]])


def test_every_function_dynamics_is_what_it_says() -> None:
    D = every_function_dynamics()
    names = {type(e).__name__.lower() for f in D.expressions for e in sympy.preorder_traversal(f)}
    assert {"sin", "cos", "tan", "exp", "log", "tanh", "atan", "atan2", "abs", "pow"} <= names
    assert D.f(np.zeros(3), np.zeros(2)).shape == (3,)


@pytest.mark.parametrize("name", [*SCENARIOS, "every_function"])
def test_one_point_is_bitwise_the_batch_code(name: str) -> None:
    """``f``, ``f_x``, ``f_u`` and ``f_scalars`` at 300 single points: exactly the numbers of
    the batch code (the oracle) at each."""
    if name == "every_function":
        D = every_function_dynamics()
        rng = np.random.default_rng(3)
        x, u = rng.uniform(-2.0, 2.0, (300, D.n)), rng.uniform(-2.0, 2.0, (300, D.m))
    else:
        D = load_scenario(name, check_demos=False).dynamics
        x, u = random_points(load_scenario(name, check_demos=False), 300, seed=3)
    f, f_x, f_u = batch_code(D), batch_code(D, D.jacobian_x), batch_code(D, D.jacobian_u)
    for a, b in zip(x, u, strict=True):
        expected = f(a, b)
        assert np.array_equal(D.f(a, b), expected), (a, b, D.f(a, b) - expected)
        assert np.array_equal(np.array(D.f_scalars(list(a), list(b)), dtype=np.float64), expected)
        assert np.array_equal(D.f_x(a, b), f_x(a, b).reshape(D.n, D.n))
        assert np.array_equal(D.f_u(a, b), f_u(a, b).reshape(D.n, D.m))
        assert D.f(a, b).dtype == np.float64 and D.f(a, b).shape == (D.n,)
    # The points are not all alike (the comparison is not between constants).
    assert np.ptp(D.f(x, u), axis=0).max() > 0.1


def test_one_point_constant_entries() -> None:
    """Constant entries come back from the one-point path as float64 (lambdify returns ints)."""
    a, b, c = sympy.symbols("a b c", real=True)
    D = Dynamics.from_expressions([a, b], [c], [sympy.Integer(1), a * c])
    x, u = np.array([2.0, 0.0]), np.array([3.0])
    assert D.f(x, u).dtype == np.float64
    np.testing.assert_array_equal(D.f(x, u), [1.0, 6.0])
    np.testing.assert_array_equal(D.f_x(x, u), [[0.0, 0.0], [3.0, 0.0]])
    np.testing.assert_array_equal(D.f_u(x, u), [[0.0], [2.0]])
