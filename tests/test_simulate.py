"""Simulation: fixed-step RK4 against ``solve_ivp``, batching, and the observed order of RK4.

Inputs are held on ``[k Ts, (k+1) Ts)``. RK4's global error is ``C h^4``, so halving the step
``h = Ts / substeps`` divides the error by 16: the observed order ``log2(e_h / e_{h/2})`` is ~4.
One trajectory (``x0 (n,)``, ``us (N, m)``) runs on scalars: bitwise the numbers of ``rk4_step``
on ``(n,)`` arrays with ``f`` through the batch code (``tests.test_dynamics.batch_code``).
"""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
import sympy

from pipeline import ScenarioError, available_scenarios, load_scenario
from pipeline.model.dynamics import Dynamics
from pipeline.model.simulate import (
    _rk4_loop,
    rk4_step,
    simulate,
    simulate_graded,
    simulate_reference,
)
from tests.helpers.dynamics import batch_code, every_function_dynamics


@cache
def quadrotor():
    return load_scenario("quadrotor_hill_flythrough", check_demos=False)


def hover_inputs(N: int, Ts: float, amplitude: float = 1.0) -> np.ndarray:
    """Hover-ish held inputs ``(N, 2)``: thrust ``9.81 + 0.5 a sin``, pitch accel. ``0.3 a sin``."""
    t = Ts * np.arange(N)
    return np.stack(
        [9.81 + amplitude * 0.5 * np.sin(0.7 * t), amplitude * 0.3 * np.sin(1.3 * t + 0.2)], -1
    )


X0 = np.array([2.0, 2.5, 0.0, 0.0, 0.0, 0.0])


def test_rk4_agrees_with_solve_ivp_on_a_10_s_flight() -> None:
    scenario = quadrotor()
    us = hover_inputs(100, scenario.Ts)
    trajectory = simulate(scenario.dynamics, X0, us, scenario.Ts)
    reference = simulate_reference(scenario.dynamics, X0, us, scenario.Ts)
    assert trajectory.duration == pytest.approx(10.0)
    assert reference.shape == trajectory.xs.shape == (101, 6)
    np.testing.assert_allclose(trajectory.xs, reference, rtol=0, atol=1e-6)
    # The flight actually moves (the test is not comparing two constants).
    assert np.ptp(trajectory.xs[:, 2]) > 0.05 and np.ptp(trajectory.xs[:, 0]) > 0.5


def _shipped_demos() -> list:
    try:
        return list(quadrotor().demos)
    except ScenarioError:  # reported by test_scenario.py::test_shipped_scenarios_load_...
        return []


@pytest.mark.parametrize(
    "index", [pytest.param(k, id=demo.name) for k, demo in enumerate(_shipped_demos())] or [None]
)
def test_rk4_agrees_with_solve_ivp_on_the_demos(index: int | None) -> None:
    if index is None:
        pytest.skip("no demos shipped in scenarios/quadrotor_hill_flythrough/demos")
    scenario = quadrotor()
    demo = scenario.demos[index]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    reference = simulate_reference(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    np.testing.assert_allclose(trajectory.xs, reference, rtol=0, atol=1e-6)


def test_batched_equals_one_at_a_time() -> None:
    scenario = quadrotor()
    rng = np.random.default_rng(0)
    B, N = 7, 30
    x0 = X0 + rng.uniform(-0.5, 0.5, (B, 6))
    us = hover_inputs(N, scenario.Ts) + rng.uniform(-1.0, 1.0, (B, N, 2))
    batched = simulate(scenario.dynamics, x0, us, scenario.Ts)
    assert batched.xs.shape == (B, N + 1, 6)
    assert batched.us.shape == (B, N, 2)
    for b in range(B):
        single = simulate(scenario.dynamics, x0[b], us[b], scenario.Ts)
        np.testing.assert_allclose(batched.xs[b], single.xs, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(batched.dense_xs[b], single.dense_xs, rtol=1e-14, atol=1e-14)


def test_broadcasting_initial_states_and_inputs() -> None:
    scenario = quadrotor()
    N = 5
    us = hover_inputs(N, scenario.Ts)
    many_x0 = np.tile(X0, (4, 1)) + np.arange(4)[:, None] * 0.1
    # Many initial states, one input sequence.
    trajectory = simulate(scenario.dynamics, many_x0, us, scenario.Ts)
    assert trajectory.xs.shape == (4, N + 1, 6)
    np.testing.assert_allclose(
        trajectory.xs[2], simulate(scenario.dynamics, many_x0[2], us, scenario.Ts).xs, atol=1e-14
    )
    # One initial state, many input sequences; and a (2, 3) grid of both.
    assert simulate(scenario.dynamics, X0, np.stack([us] * 3), scenario.Ts).xs.shape == (3, 6, 6)
    grid = simulate(scenario.dynamics, many_x0[:2, None], np.stack([us] * 3), scenario.Ts)
    assert grid.xs.shape == (2, 3, N + 1, 6)


def test_trajectory_grids() -> None:
    scenario = quadrotor()
    N, s = 8, 5
    trajectory = simulate(scenario.dynamics, X0, hover_inputs(N, scenario.Ts), scenario.Ts, s)
    np.testing.assert_allclose(trajectory.ts, scenario.Ts * np.arange(N + 1))
    np.testing.assert_allclose(trajectory.dense_ts, scenario.Ts / s * np.arange(N * s + 1))
    np.testing.assert_array_equal(trajectory.xs, trajectory.dense_xs[::s])
    np.testing.assert_array_equal(trajectory.xs[0], X0)
    np.testing.assert_array_equal(trajectory.final_state, trajectory.xs[-1])
    with pytest.raises(ValueError, match="substeps must be >= 1"):
        simulate(scenario.dynamics, X0, hover_inputs(N, scenario.Ts), scenario.Ts, 0)


def test_hover_at_rest_with_held_inputs_is_exact() -> None:
    """u = (m g, 0) with no relative wind: vX = wX drifts at constant speed, nothing else moves."""
    scenario = quadrotor()
    x0 = np.array([2.0, 2.5, 0.0, -0.5, 0.0, 0.0])
    us = np.tile([9.81, 0.0], (20, 1))
    trajectory = simulate(scenario.dynamics, x0, us, scenario.Ts)
    expected = x0 + np.outer(trajectory.ts, [-0.5, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(trajectory.xs, expected, atol=1e-12)


def test_rk4_observed_order_is_four() -> None:
    """Halving the RK4 step divides the error (against a tight ``solve_ivp``) by ~16."""
    scenario = quadrotor()
    Ts, N = 0.5, 8  # long steps, so the errors sit far above the reference's tolerance
    us = hover_inputs(N, Ts, amplitude=6.0)
    x0 = np.array([2.0, 2.5, 0.1, 0.5, -0.3, 0.2])
    reference = simulate_reference(scenario.dynamics, x0, us, Ts, rtol=1e-13, atol=1e-13)
    errors = np.array(
        [
            np.abs(simulate(scenario.dynamics, x0, us, Ts, substeps=s).xs - reference).max()
            for s in (2, 4, 8, 16)
        ]
    )
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all((orders > 3.5) & (orders < 4.5)), f"errors {errors}, observed orders {orders}"


def array_rk4(dynamics: Dynamics, x0: np.ndarray, us: np.ndarray, Ts: float, s: int) -> np.ndarray:
    """The oracle: ``rk4_step`` on ``(n,)`` arrays, ``f`` through the batch code; -> (N*s+1, n)."""
    D = dataclasses.replace(dynamics, _f=batch_code(dynamics))
    x, dense = np.array(x0, dtype=np.float64), [np.array(x0, dtype=np.float64)]
    for u in us:
        for _ in range(s):
            x = rk4_step(D, x, u, Ts / s)
            dense.append(x)
    return np.array(dense)


def _flights(name: str) -> tuple[Dynamics, float, list[tuple[np.ndarray, np.ndarray]]]:
    """A scenario's dynamics, Ts and flights: its shipped demos and two random input sequences
    (the every-function dynamics: four random flights)."""
    rng = np.random.default_rng(5)
    if name == "every_function":
        D, Ts = every_function_dynamics(), 0.05
        return D, Ts, [(rng.uniform(-1, 1, 3), rng.uniform(-1, 1, (40, 2))) for _ in range(4)]
    scenario = load_scenario(name)
    flights = [(d.x0, d.us) for d in scenario.demos]
    for _ in range(2):
        x0 = rng.uniform(scenario.init_lower, scenario.init_upper)
        flights.append((x0, rng.uniform(scenario.input_lower, scenario.input_upper, (60, 2))))
    return scenario.dynamics, scenario.Ts, flights


@pytest.mark.parametrize("name", [*available_scenarios(), "every_function"])
def test_one_trajectory_is_bitwise_rk4_step_on_arrays(name: str) -> None:
    """Every shipped demo (and random flights) at 1, 3 and 4 substeps: ``simulate``'s states on
    the whole RK4 grid equal the array RK4's bit for bit."""
    D, Ts, flights = _flights(name)
    assert len(flights) >= 4
    for x0, us in flights:
        for s in (1, 3, 4):
            trajectory = simulate(D, x0, us, Ts, substeps=s)
            expected = array_rk4(D, x0, us, Ts, s)
            assert trajectory.dense_xs.dtype == np.float64
            assert np.array_equal(trajectory.dense_xs, expected), np.abs(
                trajectory.dense_xs - expected
            ).max()
            np.testing.assert_array_equal(trajectory.xs, expected[::s])
            assert np.ptp(expected, axis=0).max() > 0.1  # the flight moves


@pytest.mark.parametrize(
    ("expression", "x0"),
    [
        ("1 / x", 0.0),
        ("x ** 0.5", -1.0),
        ("x ** 3", 1e120),
        ("sin(x ** 1.5)", -1.0),
    ],
    ids=["division by zero", "complex power", "overflow", "sin of a complex power"],
)
def test_where_python_floats_raise_the_trajectory_is_numpys(expression: str, x0: float) -> None:
    """One trajectory runs on Python floats, which raise (or turn complex) where NumPy's scalars
    give inf or nan: there it is run again on np.float64, so it still equals the array RK4."""
    from pipeline.model.expressions import parse_expression

    x, u = sympy.symbols("x u")
    f = parse_expression(expression, {"x": x, "u": u}) + u
    D = Dynamics.from_expressions([x], [u], [f])
    us = np.zeros((3, 1))
    with pytest.raises((ArithmeticError, TypeError)):  # what the fallback catches
        np.array(_rk4_loop(1)(D.float_function, [x0], us.tolist(), 0.05, 2), dtype=np.float64)
    with np.errstate(all="ignore"):
        trajectory = simulate(D, np.array([x0]), us, 0.1, substeps=2)
        expected = array_rk4(D, np.array([x0]), us, 0.1, 2)
    assert not np.all(np.isfinite(expected))  # the case is what it says
    np.testing.assert_array_equal(trajectory.dense_xs, expected)


def test_one_trajectory_edge_shapes() -> None:
    """No input samples: just ``x0``; a list ``x0`` counts as one trajectory."""
    scenario = quadrotor()
    empty = simulate(scenario.dynamics, X0, np.zeros((0, 2)), scenario.Ts)
    assert empty.xs.shape == empty.dense_xs.shape == (1, 6) and empty.us.shape == (0, 2)
    np.testing.assert_array_equal(empty.xs[0], X0)
    us = hover_inputs(3, scenario.Ts)
    listed = simulate(scenario.dynamics, X0.tolist(), us.tolist(), scenario.Ts)
    np.testing.assert_array_equal(
        listed.dense_xs, simulate(scenario.dynamics, X0, us, scenario.Ts).dense_xs
    )


def test_every_function_of_the_scenario_language_returns_a_float_on_the_float_path() -> None:
    """Each function a scenario may use is printed as a NumPy name that the float path wraps (an
    unwrapped one would still be exact, on np.float64, but slower)."""
    from pipeline.model.dynamics import FLOAT_FUNCTIONS, _returning_float
    from pipeline.model.expressions import ALLOWED_FUNCTIONS, ARITY

    x, y, u = sympy.symbols("x y u", real=True)
    for name, function in ALLOWED_FUNCTIONS.items():
        expression = function(x, y) if ARITY[name] == 2 else function(x)
        D = Dynamics.from_expressions([x, y], [u], [expression, y + u])
        value = D.float_function(0.3, 0.7, 0.0)[0]
        assert type(value) is float, (name, type(value))
        printed = sympy.printing.numpy.NumPyPrinter().doprint(expression).split("(")[0]
        assert printed.rsplit(".", 1)[-1] in FLOAT_FUNCTIONS, (name, printed)
    # a complex argument (a negative base's fractional power) is refused, not made real again
    # (abs would give its magnitude, float() of sin's result its real part)
    for name in FLOAT_FUNCTIONS:
        arguments = (-1.0) ** 1.5, *([1.0] if name == "arctan2" else [])
        with pytest.raises(TypeError, match="complex"):
            _returning_float(getattr(np, name))(*arguments)


def test_a_graded_grid_is_simulate_on_each_interval() -> None:
    """``simulate_graded``: equal steps everywhere is ``simulate`` bitwise (times too); another
    count on one interval changes only that interval's grid, and its states agree with a uniform
    fine simulation at the sample times to RK4's accuracy."""
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    demo = scenario.demos[0]
    us = demo.us[:6]
    uniform = simulate(scenario.dynamics, demo.x0, us, scenario.Ts, 20)
    same = simulate_graded(scenario.dynamics, demo.x0, us, scenario.Ts, np.full(6, 20))
    assert np.array_equal(same.dense_ts, uniform.dense_ts)
    assert np.array_equal(same.dense_xs, uniform.dense_xs) and np.array_equal(same.xs, uniform.xs)
    graded = simulate_graded(
        scenario.dynamics, demo.x0, us, scenario.Ts, np.array([80, 20, 20, 5, 20, 20])
    )
    assert len(graded.dense_ts) == 80 + 4 * 20 + 5 + 1
    assert np.allclose(graded.dense_ts[80:101], uniform.dense_ts[20:41], rtol=0, atol=1e-15)
    assert np.allclose(graded.xs, uniform.xs, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="6 whole numbers >= 1"):
        simulate_graded(
            scenario.dynamics, demo.x0, us, scenario.Ts, np.array([20, 20, 0, 20, 20, 20])
        )
