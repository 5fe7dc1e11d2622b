"""``pipeline.fly``: a certified controller flown in its scenario's model (issue 31, item 5)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import pipeline
from pipeline.model import geometry
from pipeline.numerics.closed_loop.simulate import simulate_closed_loop

NAME = "double_integrator"


@pytest.fixture(scope="module")
def certified(synthesis):
    """The session's certified double_integrator controller and its scenario."""
    code, out = synthesis(NAME)
    assert code == 0
    return pipeline.load_controller(out / "controller.json"), pipeline.load_scenario(NAME)


@pytest.mark.xdist_group("synthesis-double_integrator")  # with its session run (conftest)
def test_a_covered_start_flies_into_goal_and_never_into_unsafe(certified):
    controller, scenario = certified
    rng = np.random.default_rng(3)
    starts = rng.uniform(scenario.init_lower, scenario.init_upper, size=(4, scenario.n))
    for x0 in [scenario.init_lower, scenario.init_upper, *starts]:  # Init's corners are worst
        flight = pipeline.fly(controller, NAME, x0)
        assert flight.covered and type(flight.index) is int and type(flight.ratio) is float
        reference = controller.trajectories[flight.index]
        assert flight.ts[0] == 0 and flight.ts[-1] == pytest.approx(reference.T)
        assert flight.xs.shape == (len(flight.ts), 4) and flight.us.shape == (len(flight.ts) - 1, 2)
        positions = scenario.positions(flight.xs)
        for region in scenario.unsafe.values():
            assert geometry.distance(positions, region).min() > 0
        assert scenario.in_goal(flight.xs[-1])
        assert np.all((controller.lower <= flight.us) & (flight.us <= controller.upper))


@pytest.mark.xdist_group("synthesis-double_integrator")
def test_fly_is_the_monte_carlo_integration_of_the_law(certified):
    """Continuous feedback at the same RK4 step as the validation's closed loop: the same
    states (so ``fly`` is the flight that was validated, not an approximation of it)."""
    controller, scenario = certified
    x0 = (scenario.init_lower + scenario.init_upper) / 2 + 0.05
    flight = pipeline.fly(controller, scenario, x0, step=controller.Ts / 20)
    run = simulate_closed_loop(scenario.dynamics, controller, x0[None], flight.index, 20)
    np.testing.assert_allclose(flight.ts, run.ts, atol=1e-12)
    np.testing.assert_allclose(flight.xs, run.xs[0], rtol=0, atol=1e-9)


@pytest.mark.xdist_group("synthesis-double_integrator")
def test_a_held_feedback_holds_its_input_for_each_period(certified):
    controller, scenario = certified
    x0 = scenario.init_lower
    flight = pipeline.fly(controller, scenario, x0, period=0.05, step=0.01)
    assert flight.period == 0.05 and len(flight.us) == len(flight.ts) - 1
    windows = np.floor(flight.ts[:-1] / 0.05 + 1e-9).astype(int)  # 5 steps each
    for k in np.unique(windows):
        held = flight.us[windows == k]
        assert len(held) == 5 and np.all(held == held[0])
    assert scenario.in_goal(flight.xs[-1])  # 20 Hz, close to the continuous law here


@pytest.mark.xdist_group("synthesis-double_integrator")
def test_fly_flies_the_law_the_file_certifies_unless_told_otherwise(certified):
    """Without ``period``, a file certified for a held law is flown held at its period, one
    for continuous feedback continuously."""
    controller, scenario = certified
    held = dataclasses.replace(controller, feedback_period=0.05)
    x0 = scenario.init_lower
    assert pipeline.fly(controller, scenario, x0, step=0.01).period == 0.0
    flight = pipeline.fly(held, scenario, x0, step=0.01)
    assert flight.period == 0.05
    given = pipeline.fly(controller, scenario, x0, period=0.05, step=0.01)
    np.testing.assert_array_equal(flight.us, given.us)
    assert pipeline.fly(held, scenario, x0, period=0.0, step=0.01).period == 0.0


@pytest.mark.xdist_group("synthesis-double_integrator")
def test_bad_arguments_are_value_errors_naming_them(certified):
    controller, scenario = certified
    T = controller.trajectories[controller.select(scenario.init_lower)[0]].T
    with pytest.raises(ValueError, match=r"x0 has shape \(3,\); expected \(4,\): one start"):
        pipeline.fly(controller, scenario, np.zeros(3))
    with pytest.raises(ValueError, match="period = -0.1; expected a finite number >= 0"):
        pipeline.fly(controller, scenario, scenario.init_lower, period=-0.1)
    if controller.terminal is None:
        with pytest.raises(ValueError, match=f"past the trajectory's T = {T:g} s"):
            pipeline.fly(controller, scenario, scenario.init_lower, until=T + 1)
    with pytest.raises(ValueError, match="scenario 'quadrotor_hill_flythrough' has states"):
        pipeline.fly(controller, "quadrotor_hill_flythrough", scenario.init_lower)
    short = pipeline.fly(controller, scenario, scenario.init_lower, until=0.5)
    assert short.ts[-1] == pytest.approx(0.5)
