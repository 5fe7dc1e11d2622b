"""Simulation speed, measured side by side in one run.

(a) One flight (the first shipped demo, else a 100-sample hover input): fixed-step RK4
    (``pipeline.model.simulate.simulate``) against ``solve_ivp`` (``simulate_reference``).
(b) 10,000 initial states simulated as one batch against 100 simulated one at a time, per state.
(c) The same flight as (a), one trajectory (``x0 (n,)``: RK4 on scalars) against a batch of one
    (``x0 (1, n)``: ``rk4_step`` on arrays, ``f`` through ``np.moveaxis``, the path every
    one-trajectory call took before), and whether their states are bitwise equal.
(d) ``Dynamics.f`` at one point ``x (n,)`` against the same point as a batch ``(1, n)``.
(e) The scalar RK4 of (c) on Python floats (``Dynamics.float_function``, what ``simulate`` runs)
    against the same steps on np.float64 scalars (its fallback), and whether they are bitwise
    equal.
"""

from __future__ import annotations

import numpy as np

from bench.timing import best_time
from pipeline.model.scenario import load_scenario
from pipeline.model.simulate import DEFAULT_SUBSTEPS, _rk4_loop, simulate, simulate_reference

BATCH = 10_000
ONE_AT_A_TIME = 100


def _flight(scenario) -> tuple[str, np.ndarray, np.ndarray]:
    """(label, x0 (n,), us (N, m)): the first demo, else 100 samples of hover."""
    if scenario.demos:
        demo = scenario.demos[0]
        return f"demo {demo.name}", demo.x0, demo.us
    x0 = 0.5 * (scenario.init_lower + scenario.init_upper)
    u = np.array(scenario.feedback.reference_input, dtype=np.float64)
    return "hover (no demos)", x0, np.tile(u, (100, 1))


def run() -> None:
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    D, Ts = scenario.dynamics, scenario.Ts
    label, x0, us = _flight(scenario)
    N = us.shape[0]

    rk4 = best_time(lambda: simulate(D, x0, us, Ts), repeat=5)
    reference = best_time(lambda: simulate_reference(D, x0, us, Ts), repeat=3)

    rng = np.random.default_rng(0)
    x0s = rng.uniform(scenario.init_lower, scenario.init_upper, (BATCH, scenario.n))
    batched = best_time(lambda: simulate(D, x0s, us, Ts), repeat=3) / BATCH
    single = (
        best_time(lambda: [simulate(D, x, us, Ts) for x in x0s[:ONE_AT_A_TIME]], repeat=2)
        / ONE_AT_A_TIME
    )

    one = best_time(lambda: simulate(D, x0, us, Ts), repeat=5)
    batch_of_one = best_time(lambda: simulate(D, x0[None], us[None], Ts), repeat=3)
    equal = np.array_equal(
        simulate(D, x0, us, Ts).dense_xs, simulate(D, x0[None], us[None], Ts).dense_xs[0]
    )
    loop, h = _rk4_loop(scenario.n), Ts / DEFAULT_SUBSTEPS

    def on_floats() -> list:
        return loop(D.float_function, x0.tolist(), us.tolist(), h, DEFAULT_SUBSTEPS)

    def on_numpy_scalars() -> list:
        return loop(D.scalar_function, list(x0), [list(u) for u in us], h, DEFAULT_SUBSTEPS)

    floats = best_time(on_floats, repeat=5)
    numpy_scalars = best_time(on_numpy_scalars, repeat=5)
    floats_equal = np.array_equal(np.array(on_floats()), np.array(on_numpy_scalars()))
    point, inputs = x0, us[0]
    f_point = best_time(lambda: D.f(point, inputs), repeat=5, number=2000)
    f_batch = best_time(lambda: D.f(point[None], inputs[None]), repeat=5, number=2000)

    print(
        f"quadrotor_hill_flythrough, {label}: N = {N} samples of Ts = {Ts:g} s, RK4 substeps = "
        f"{DEFAULT_SUBSTEPS}; best of repeated runs"
    )
    rows = [
        ("(a) one flight", "RK4 (simulate)", rk4, "solve_ivp DOP853 (reference)", reference),
        (
            "(b) per initial state",
            f"batch of {BATCH:,}",
            batched,
            f"{ONE_AT_A_TIME} one at a time",
            single,
        ),
        ("(c) one flight", "x0 (n,): scalars", one, "x0 (1, n): arrays, moveaxis", batch_of_one),
        ("(d) f at one point", "x (n,)", f_point, "x (1, n)", f_batch),
        ("(e) one flight", "Python floats", floats, "np.float64 scalars", numpy_scalars),
    ]
    print(
        f"{'measurement':<22} {'fast path':<16} {'time':>10}   {'slow path':<29} "
        f"{'time':>10}   {'speed-up':>8}"
    )
    for name, fast_label, fast, slow_label, slow in rows:
        print(
            f"{name:<22} {fast_label:<16} {_duration(fast):>10}   {slow_label:<29} "
            f"{_duration(slow):>10}   {slow / fast:>7.1f}x"
        )
    print(f"(c) states bitwise equal: {'yes' if equal else 'NO'}")
    print(f"(e) states bitwise equal: {'yes' if floats_equal else 'NO'}")


def _duration(seconds: float) -> str:
    return f"{seconds * 1e3:.3f} ms" if seconds >= 1e-3 else f"{seconds * 1e6:.2f} us"
