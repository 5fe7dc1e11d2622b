"""Fly ``controller.json`` in its scenario's model and say what happened (any scenario).

Uses ``pipeline.fly``: the scenario's own dynamics (``load_scenario(name).dynamics.f``) by RK4 at
a fine step, the law evaluated continuously (``--period 0``, what the certificate assumes unless
the file says otherwise) or sampled every ``--period`` seconds and held in between (a flight
computer: certified only when it is the file's ``feedback_period``).

    python examples/fly_controller.py reports/quadrotor_hill/controller.json \
        --start 1.5 2.5 0 0 0 0 --period 0.01 --plot flight.png

The scenario is the file's (``--scenario NAME_OR_PATH`` for another copy of it); the start
defaults to the centre of Init. It prints whether the start is covered by the certificate
(coverage ratio < 1) and which trajectory it follows (``index: name``, the numbering of
``controller.trajectories``), the closest approach to each Unsafe region, and whether the
flight is in Goal at ``T`` (and at the end, when the file's terminal controller flies on);
the plot shows the flight over the nominal in the position plane with the position projection
of the certified tube at a few times. Both file formats fly the same way:
``safety-controller/1`` (one gain and metric) and ``/2`` (a funnel per trajectory, its metric
``controller.metric(t, index)`` varying along the flight).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

import pipeline
from pipeline.model import geometry


def plot(controller, scenario, flight, path: Path) -> None:
    """The flight ``flight.xs`` over trajectory ``flight.index`` and its tube, in the position
    plane, with Unsafe and Goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse, Polygon

    index, (a, b) = flight.index, scenario.position_index
    reference = controller.trajectories[index]
    figure, axes = plt.subplots(figsize=(8, 5), layout="constrained")
    for region in scenario.unsafe.values():
        axes.add_patch(Polygon(np.asarray(region.exterior.coords), color="0.6"))
    axes.add_patch(Polygon(np.asarray(scenario.goal.exterior.coords), color="tab:green",
                           alpha=0.3, label="Goal"))  # fmt: skip
    for t in np.linspace(0, reference.T, 12):
        # position projection of {e : e^T P(t) e <= radius^2 e^(-2 rate t)}
        Q = np.linalg.inv(controller.metric(t, index))[np.ix_([a, b], [a, b])]
        values, vectors = np.linalg.eigh(Q)
        angle = math.degrees(math.atan2(vectors[1, 1], vectors[0, 1]))
        centre = [np.interp(t, reference.t, reference.x_ref[:, j]) for j in (a, b)]
        scale = reference.radius * math.exp(-reference.rate * t)
        width, height = (2 * scale * math.sqrt(v) for v in values[::-1])
        axes.add_patch(Ellipse(centre, width, height, angle=angle, color="tab:orange", alpha=0.15))
    name = controller.label(index)
    axes.plot(reference.x_ref[:, a], reference.x_ref[:, b], "--", color="tab:orange",
              label=f"nominal {name} and its certified tube")  # fmt: skip
    axes.plot(flight.xs[:, a], flight.xs[:, b], color="tab:blue", label="flight")
    names = scenario.state_names
    axes.set(xlabel=names[a], ylabel=names[b], aspect="equal")
    axes.autoscale_view()
    axes.legend(loc="best", fontsize=8)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("controller", type=Path, help="path to controller.json")
    parser.add_argument("--scenario", default=None, help="name or path (default: the file's)")
    parser.add_argument("--start", type=float, nargs="+", default=None, help="x0 (n numbers)")
    parser.add_argument("--period", type=float, default=None,
                        help="feedback period (s); default the file's (0: continuous)")  # fmt: skip
    parser.add_argument("--until", type=float, default=None, help="end time (s)")
    parser.add_argument("--plot", type=Path, default=None, help="write the flight's figure here")
    args = parser.parse_args(argv)
    try:
        controller = pipeline.load_controller(args.controller)
        scenario = pipeline.load_scenario(args.scenario or controller.scenario)
    except (pipeline.ControllerFormatError, pipeline.UserError) as error:
        print(error, file=sys.stderr)
        return 2
    if args.start is None:
        x0 = (scenario.init_lower + scenario.init_upper) / 2  # the centre of Init
    else:
        x0 = np.array(args.start, dtype=float)
    period = controller.feedback_period if args.period is None else args.period
    try:
        flight = pipeline.fly(controller, scenario, x0, period=period, until=args.until)
    except ValueError as error:  # a start of the wrong length, an until past T, ...
        print(error, file=sys.stderr)
        return 2
    reference = controller.trajectories[flight.index]
    name = controller.label(flight.index)
    covered = "covered" if flight.covered else "NOT covered (outside the certificate)"
    kind = "funnel" if controller.funnel else "constant"
    print(
        f"start {x0.tolist()}: {covered}, coverage ratio {flight.ratio:.3f}, trajectory {name} "
        f"({kind} certificate)"
    )
    positions = scenario.positions(flight.xs)
    distances = ", ".join(
        f"'{region}' {geometry.distance(positions, shape).min():.3f} m"
        for region, shape in scenario.unsafe.items()
    )
    at_T = flight.xs[np.searchsorted(flight.ts, reference.T - 1e-9)]
    in_goal = "in" if scenario.in_goal(at_T) else "OUTSIDE"
    held = f"held {period:g} s" if period > 0 else "continuous"
    print(
        f"feedback {held}; flight of {flight.ts[-1]:.2f} s: closest to Unsafe {distances} "
        f"(clearance d = {scenario.clearance:g} m); at T = {reference.T:g} s {in_goal} Goal"
    )
    if flight.ts[-1] > reference.T + 1e-9:
        end = "in" if scenario.in_goal(flight.xs[-1]) else "OUTSIDE"
        print(f"terminal controller after T: {end} Goal at t = {flight.ts[-1]:.2f} s")
    if args.plot is not None:
        plot(controller, scenario, flight, args.plot)
        print(f"figure: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
