"""A double integrator's first demo with a small initial set, its robust funnel, and a gusty copy
of double_integrator_hold, for the robust-funnel tests."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
from scipy.linalg import solve_continuous_lyapunov
from shapely.geometry import box

from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.funnel.synthesis import synthesize_funnel
from pipeline.numerics.verify.recertify import ShippedFunnel

DISTURBANCE = np.array([0.0, 0.0, 0.05, 0.05])  # m/s^2 on both speeds of the double integrator
HOLD = "double_integrator_hold"
GUST = 0.02  # m/s^2 on vx' and vy' of the gusty double_integrator_hold runs


def rk4_step(field, x: np.ndarray, dt: float) -> np.ndarray:
    """One classical RK4 step of ``x' = field(x)`` (states stacked in rows)."""
    k1 = field(x)
    k2 = field(x + dt / 2 * k1)
    k3 = field(x + dt / 2 * k2)
    k4 = field(x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def held_hover_flights(
    scenario: Scenario,
    x_eq: np.ndarray,
    u_eq: np.ndarray,
    K: np.ndarray,
    P: np.ndarray,
    level: float,
    bound: np.ndarray,
    period: float,
    *,
    substeps: int,
    seed: int,
    seconds: float = 6.0,
    flights: int = 64,
):
    """Yields ``(e_j, x)``, both ``(flights, n)``, after every RK4 step of ``flights`` flights of
    the hover law ``u = u_eq + K e_j`` held every ``period`` s (``substeps`` RK4 steps each; ``e_j =
    x(t_j) - x_eq`` at the last evaluation), from just inside ``{V = level}`` (``V = e^T P e``),
    half under the gust ``bound (n,)`` pushing outward hardest, half under bang-bang gusts that
    switch at random, for ``seconds``."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal((flights, scenario.n))
    r = np.sqrt(level)
    x = x_eq + 0.999 * r * v / np.sqrt(np.einsum("bi,ij,bj->b", v, P, v))[:, None]
    dt = period / substeps
    outward = np.arange(flights) % 2 == 0
    signs = rng.choice([-1.0, 1.0], size=(flights, scenario.n))
    for j in range(int(seconds / dt)):
        if j % substeps == 0:
            e_j = x - x_eq
            u = u_eq + e_j @ K.T
        if rng.random() < 0.2:
            signs = rng.choice([-1.0, 1.0], size=(flights, scenario.n))

        def field(state, u=u, signs=signs):
            w = bound * np.where(outward[:, None], np.sign((state - x_eq) @ P), signs)
            return scenario.dynamics.f(state, u) + w

        x = rk4_step(field, x, dt)
        yield e_j, x


def stiff_hull(
    rng: np.random.Generator, V: int = 4
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random hull about two stiff double integrators (``n = 4``, ``m = 2``, poles at -3), the
    tests of a held law's push: ``A (V, n, n)``, ``B (V, n, m)``, the gain ``K (m, n)`` and ``Q
    (n, n)`` of the nominal loop's Lyapunov equation, scaled to largest eigenvalue 1."""
    eye = np.eye(2)
    A0 = np.block([[0 * eye, eye], [0 * eye, -0.1 * eye]])
    B0 = np.vstack([0 * eye, eye])
    K = -np.hstack([9 * eye, 6 * eye])
    A = A0 + 0.05 * rng.standard_normal((V, 4, 4))
    B = B0 + 0.05 * rng.standard_normal((V, 4, 2))
    Q = solve_continuous_lyapunov(A0 + B0 @ K, -np.eye(4))
    return A, B, K, Q / np.linalg.eigvalsh(Q).max()


def double_integrator_case() -> tuple[Scenario, Trajectory, np.ndarray]:
    """The double integrator's first demo over 3 s, Goal around where it ends, and a small
    initial set ``Q_init (4, 4)`` (as tests/conftest.py's ``funnel_artifact``)."""
    scenario = load_scenario("double_integrator", check_demos=False)
    demo = scenario.demos[0]
    trajectory = simulate(scenario.dynamics, demo.x0, demo.us[:30], scenario.Ts)
    end = trajectory.xs[-1, :2]
    scenario = dataclasses.replace(scenario, goal=box(*(end - 1.0), *(end + 1.0)))
    return scenario, trajectory, 2 * np.diag([0.05, 0.05, 0.0, 0.0]) ** 2


def robust_double_integrator() -> tuple[Scenario, Trajectory, ShippedFunnel]:
    """``double_integrator_case``'s robust funnel under ``DISTURBANCE``, as a file ships it."""
    scenario, trajectory, initial = double_integrator_case()
    funnel = synthesize_funnel(scenario, trajectory, initial=initial, disturbance=DISTURBANCE)
    assert funnel.success, funnel.message
    shipped = ShippedFunnel(K=funnel.K, P=funnel.P, rho=funnel.rho, rate=funnel.rate)
    return scenario, trajectory, shipped


# the gusty copies keep Init's lower-left 2 x 2 of its 3 x 3 demo cells (a third as many
# funnels to design as the whole box: the runs test the robust hold, not the coverage of more)
GUSTY_INIT = ("  x: [0.0, 1.0]\n  y: [0.0, 1.0]\n", "  x: [0.0, 0.667]\n  y: [0.0, 0.667]\n")
GUSTY_DROPPED = ("demo_03", "demo_06", "demo_07", "demo_08", "demo_09")


def gusty_hold_scenario(folder: Path, gust: float) -> Path:
    """A copy of double_integrator_hold in ``folder`` with the funnel certificate and ``gust``
    declared on both speeds, Init ``[0, 0.667]^2`` at rest and its four demos (``GUSTY_INIT``);
    its scenario.yaml."""
    source = load_scenario(HOLD, check_demos=False).path.parent
    shutil.copytree(source, folder)
    path = folder / "scenario.yaml"
    text = path.read_text()
    assert GUSTY_INIT[0] in text, "double_integrator_hold's Init changed: update GUSTY_INIT"
    text = text.replace(*GUSTY_INIT).replace(
        "\nterminal: hold",
        f"\ncertificate: funnel\nuncertainty:\n  disturbance: {{vx: {gust}, vy: {gust}}}\n"
        "terminal: hold",
    )
    kept = [line for line in text.splitlines() if not any(d in line for d in GUSTY_DROPPED)]
    path.write_text("\n".join(kept) + "\n")
    return path
