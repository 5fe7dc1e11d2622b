"""Fly ``controller.json`` in your own simulation loop: the quadrotor_hill example.

Needs only NumPy, matplotlib and ``pipeline/controller.py`` (copy that one file next to this one
if the pipeline is not installed). The vehicle model is written out by hand below, as a user of
the controller would, and the feedback is sampled every ``--period`` seconds and held in between
(a real flight computer), while the plant is integrated by RK4 with a finer step.

    python examples/fly_controller.py reports/quadrotor_hill/controller.json \
        --start 1.5 2.5 0 0 0 0 --period 0.01 --plot flight.png

It prints whether the start is covered by the certificate (coverage ratio < 1), the closest
approach to the hill and the ceiling, and whether the flight ends in Goal; the plot shows the
flight over the nominal trajectory, the position projection of the certified tube
``||x - x_ref(t)||_P(t) <= e^(-rate t) radius`` (filled) and of the flight's own bound
``e^(-rate t) ||x0 - x_ref(0)||_P(0)`` (outlined) at a few times. Both file formats fly the same
way: ``safety-controller/1`` (one gain ``K`` and metric ``P``) and ``/2`` (a funnel per
trajectory: ``K[k]`` per sample interval, a metric ``P(t)`` that varies along the flight,
``controller.metric(t, index)``).

Note: the certificate assumes continuous-time feedback; a held feedback is not certified here,
so a long period is flown at your own risk (the printout says which one was flown).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

try:
    from pipeline.controller import ControllerFormatError, load
except ImportError:  # the copied-file layout: controller.py beside this script
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from controller import ControllerFormatError, load  # type: ignore[no-redef]

# quadrotor_hill's model and sets, written out by hand (scenarios/quadrotor_hill/scenario.yaml)
MASS, GRAVITY, DRAG, WIND_X, WIND_Y = 1.0, 9.81, 0.5, -0.5, 0.0
HILL = [(-5, -5), (35, -5), (35, 0), (15, 0), (12, 3.5), (10, 4.5), (8, 3.5), (5, 0), (-5, 0)]
CEILING = [(-5, 8), (35, 8), (35, 13), (-5, 13)]
GOAL = (17.0, 21.0, 1.0, 4.0)  # x from, x to, y from, y to


def quadrotor(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``xdot (6,)`` for state ``(X, Y, theta, vX, vY, omega)``, input ``(thrust, pitch acc)``."""
    X, Y, theta, vX, vY, omega = x
    thrust, pitch = u
    return np.array(
        [
            vX,
            vY,
            omega,
            DRAG * (WIND_X - vX) - thrust / MASS * math.sin(theta),
            DRAG * (WIND_Y - vY) + thrust / MASS * math.cos(theta) - GRAVITY,
            pitch,
        ]
    )


def fly(controller, x0: np.ndarray, period: float, step: float = 0.0025):
    """Sampled feedback held for ``period`` s, plant by RK4 with step ``<= step``.

    Returns ``(index, ratio, ts (K+1,), xs (K+1, n))``.
    """
    index, ratio = controller.select(x0)
    T = controller.trajectories[int(index)].T
    substeps = max(1, math.ceil(period / step))
    h = period / substeps
    ts, xs, x, t = [0.0], [x0.copy()], x0.copy(), 0.0
    while t < T - 1e-12:
        u = controller(t, x, index)  # sampled now, held for one period
        for _ in range(substeps):
            k1 = quadrotor(x, u)
            k2 = quadrotor(x + h / 2 * k1, u)
            k3 = quadrotor(x + h / 2 * k2, u)
            k4 = quadrotor(x + h * k3, u)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            t += h
            ts.append(t)
            xs.append(x.copy())
    return int(index), float(ratio), np.array(ts), np.array(xs)


def _distance_to_polygon(points: np.ndarray, polygon: list[tuple[float, float]]) -> np.ndarray:
    """Distance from ``points (k, 2)`` to a polygon's boundary, 0 inside (even-odd rule)."""
    V = np.array(polygon, dtype=float)
    A, B = V, np.roll(V, -1, axis=0)
    d = B - A
    t = np.clip(np.einsum("kvi,vi->kv", points[:, None] - A, d) / np.einsum("vi,vi->v", d, d), 0, 1)
    nearest = A + t[..., None] * d
    distance = np.linalg.norm(points[:, None] - nearest, axis=-1).min(axis=1)
    crosses = (A[:, 1] > points[:, None, 1]) != (B[:, 1] > points[:, None, 1])
    x_cross = A[:, 0] + (points[:, None, 1] - A[:, 1]) * d[:, 0] / np.where(
        d[:, 1] == 0, 1, d[:, 1]
    )
    inside = np.sum(crosses & (points[:, None, 0] < x_cross), axis=1) % 2 == 1
    return np.where(inside, 0.0, distance)


def plot(controller, index: int, ts, xs, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse, Polygon

    reference = controller.trajectories[index]
    e0 = xs[0] - reference.x_ref[0]
    level = math.sqrt(e0 @ controller.metric(0.0, index) @ e0)
    figure, axes = plt.subplots(figsize=(8, 4), layout="constrained")
    for shape, colour in ((HILL, "0.6"), (CEILING, "0.6")):
        axes.add_patch(Polygon(shape, color=colour))
    x_from, x_to, y_from, y_to = GOAL
    axes.add_patch(Polygon([(x_from, y_from), (x_to, y_from), (x_to, y_to), (x_from, y_to)],
                           color="tab:green", alpha=0.3, label="Goal"))  # fmt: skip
    for t in np.linspace(0, reference.T, 12):
        # position projection of {e : e^T P(t) e <= 1}
        Q = np.linalg.inv(controller.metric(t, index))[:2, :2]
        values, vectors = np.linalg.eigh(Q)
        angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
        centre = [np.interp(t, reference.t, reference.x_ref[:, j]) for j in (0, 1)]
        decay = math.exp(-reference.rate * t)
        for scale, style in ((reference.radius, {"color": "tab:orange", "alpha": 0.15}),
                             (level, {"fill": False, "color": "tab:blue", "lw": 0.8})):  # fmt: skip
            width, height = (2 * scale * decay * math.sqrt(v) for v in values[::-1])
            axes.add_patch(Ellipse(centre, width, height, angle=angle, **style))
    label = f"nominal {index} and its certified tube (radius {reference.radius:.2f})"
    axes.plot(reference.x_ref[:, 0], reference.x_ref[:, 1], "--", color="tab:orange", label=label)
    axes.plot(xs[:, 0], xs[:, 1], color="tab:blue", label="flight and its own tube bound")
    axes.set(xlim=(-2, 25), ylim=(-1, 9), xlabel="X (m)", ylabel="Y (m)", aspect="equal")
    axes.legend(loc="upper right", fontsize=8)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("controller", type=Path, help="path to controller.json")
    parser.add_argument("--start", type=float, nargs=6, default=[1.5, 2.5, 0, 0, 0, 0])
    parser.add_argument("--period", type=float, default=0.01, help="feedback period (s)")
    parser.add_argument("--plot", type=Path, default=None, help="write the flight's figure here")
    args = parser.parse_args(argv)
    try:
        controller = load(args.controller)
    except ControllerFormatError as error:
        print(error, file=sys.stderr)
        return 2
    x0 = np.array(args.start, dtype=float)
    index, ratio, ts, xs = fly(controller, x0, args.period)
    covered = "covered" if ratio < 1 else "NOT covered (outside the certificate)"
    kind = "funnel" if controller.funnel else "constant"
    print(
        f"start {x0.tolist()}: {covered}, coverage ratio {ratio:.3f}, trajectory {index} "
        f"({kind} certificate)"
    )
    positions = xs[:, :2]
    hill = _distance_to_polygon(positions, HILL).min()
    ceiling = _distance_to_polygon(positions, CEILING).min()
    X, Y = positions[-1]
    x_from, x_to, y_from, y_to = GOAL
    in_goal = x_from <= X <= x_to and y_from <= Y <= y_to
    print(
        f"feedback held {args.period:g} s; flight of {ts[-1]:.2f} s: closest to the hill "
        f"{hill:.3f} m, to the ceiling {ceiling:.3f} m; ends at ({X:.2f}, {Y:.2f}) "
        f"{'in' if in_goal else 'OUTSIDE'} Goal"
    )
    if args.plot is not None:
        plot(controller, index, ts, xs, args.plot)
        print(f"figure: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
