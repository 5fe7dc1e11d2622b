"""What the recorder's window shows, without pygame: the part of the plane to draw and the HUD.

**The view** fits the part of the scene that matters to a flight, not the polygons' whole
extents (quadrotor_hill_flythrough's hill and ceiling are 40 m wide; its flights use 20 m of it):

1. the *core*: Init's position box, Goal and the flights already recorded (the demos' sampled
   positions), the places a flight starts, ends and goes;
2. the *neighbourhood*: the core grown by ``reach = max(2 d, span / 4)`` (``d`` the clearance,
   ``span`` the core's larger side);
3. along each axis the view is the core plus a margin ``pad = max(d, span / 20)``, extended to
   the Unsafe sets that bound the free space around the core within the neighbourhood (a ground
   and a ceiling: the flight's corridor, drawn with a ``pad`` of Unsafe beyond its edge), and to
   the whole of every Unsafe set lying inside the neighbourhood (an obstacle to fly around).

**The HUD** shows the speed (the norm of the position's rate ``f(x, u)``, in the position unit
per second) and, when ``recorder.yaml`` names an ``angle_state``, the attitude in its unit (and
degrees for radians); each input is labelled with its name, human label and unit
(``Scenario.label``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import box

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import simulate

REACH = 0.25  # the neighbourhood: the core grown by this fraction of its larger side
PAD = 0.05  # the margin around what is shown, as a fraction of the core's larger side


@dataclass(frozen=True, kw_only=True)
class ViewBox:
    """The rectangle of the position plane drawn: ``lower (2,)``, ``upper (2,)``."""

    lower: FloatArray
    upper: FloatArray

    @property
    def span(self) -> FloatArray:
        """(2,) its width and height."""
        return self.upper - self.lower

    def contains(self, points: FloatArray) -> np.ndarray:
        """True where positions ``(..., 2)`` lie inside (boundary included). -> ``(...)``."""
        p = np.asarray(points, dtype=np.float64)
        return np.all((p >= self.lower) & (p <= self.upper), axis=-1)


def demo_paths(scenario: Scenario) -> list[FloatArray]:
    """The positions ``(N_i + 1, 2)`` of each demo at its sample times."""
    return [
        scenario.positions(simulate(scenario.dynamics, d.x0, d.us, scenario.Ts, substeps=1).xs)
        for d in scenario.demos
    ]


def view_box(scenario: Scenario, flights: Sequence[FloatArray] = ()) -> ViewBox:
    """The part of the position plane to draw (module docstring); ``flights``: paths
    ``(k_i, 2)`` already flown (``demo_paths``)."""
    i, j = scenario.position_index
    points = [
        scenario.init_lower[[i, j]][None, :],
        scenario.init_upper[[i, j]][None, :],
        np.reshape(scenario.goal.bounds, (2, 2)),
        *(np.reshape(path, (-1, 2)) for path in flights),
    ]
    stacked = np.concatenate(points)
    core_lower, core_upper = stacked.min(axis=0), stacked.max(axis=0)
    span = float(max(core_upper - core_lower))
    d = scenario.clearance
    reach, pad = max(2 * d, REACH * span), max(d, PAD * span)
    near_lower, near_upper = core_lower - reach, core_upper + reach
    near = box(*near_lower, *near_upper)
    lower, upper = core_lower - pad, core_upper + pad

    # the free space around the core: where it stops inside the neighbourhood, Unsafe bounds
    # the flight's corridor (ground, ceiling): show up to it and a pad of Unsafe beyond
    core = box(*core_lower, *core_upper)
    free = near.difference(shapely.union_all(list(scenario.unsafe.values())))
    parts = [part for part in getattr(free, "geoms", [free]) if part.intersects(core)]
    if parts:
        free_bounds = np.reshape(shapely.union_all(parts).bounds, (2, 2))
        tolerance = 1e-9 * max(span, 1.0)
        stops_below = free_bounds[0] > near_lower + tolerance
        stops_above = free_bounds[1] < near_upper - tolerance
        lower = np.where(stops_below, np.minimum(lower, free_bounds[0] - pad), lower)
        upper = np.where(stops_above, np.maximum(upper, free_bounds[1] + pad), upper)

    # obstacles wholly inside the neighbourhood are shown whole
    for region in scenario.unsafe.values():
        if near.covers(region):
            bounds = np.reshape(region.bounds, (2, 2))
            lower, upper = np.minimum(lower, bounds[0] - pad), np.maximum(upper, bounds[1] + pad)
    return ViewBox(lower=lower.astype(np.float64), upper=upper.astype(np.float64))


def _unit(scenario: Scenario, name: str) -> str:
    unit = scenario.unit(name)
    return f" {unit}" if unit else ""


def speed_unit(scenario: Scenario) -> str:
    """The position's unit per second (``"m/s"``; ``"position units/s"`` when undeclared)."""
    return f"{scenario.position_unit() or 'position units'}/s"


def hud_lines(
    scenario: Scenario, x: FloatArray, u: FloatArray | None, angle_index: int | None
) -> list[str]:
    """The HUD's lines for the state ``x (n,)`` under the input ``u (m,)`` (``None``: the
    middle of the input bounds): the speed, then the attitude of state ``angle_index``."""
    x = np.asarray(x, dtype=np.float64)
    if u is None:
        u = 0.5 * (scenario.input_lower + scenario.input_upper)
    rate = scenario.positions(scenario.dynamics.f(x, np.asarray(u, dtype=np.float64)))
    lines = [f"speed {float(np.linalg.norm(rate)):.2f} {speed_unit(scenario)}"]
    if angle_index is not None:
        name = scenario.state_names[angle_index]
        value = float(x[angle_index])
        degrees = f" ({np.degrees(value):+.1f} deg)" if scenario.unit(name) == "rad" else ""
        label = scenario.label(name, unit=False)
        lines.append(f"{label} {value:+.2f}{_unit(scenario, name)}{degrees}")
    return lines


def input_rows(scenario: Scenario, u: FloatArray | None) -> list[tuple[str, str]]:
    """Per input: its label (``"force (thrust) [N]"``) and its value with unit and bounds
    (``"+9.81 N   in [0, 14.9]"``; ``"-"`` for the value when ``u`` is ``None``)."""
    rows = []
    for k, name in enumerate(scenario.input_names):
        lower, upper = float(scenario.input_lower[k]), float(scenario.input_upper[k])
        value = "-" if u is None else f"{float(u[k]):+.2f}{_unit(scenario, name)}"
        rows.append((scenario.label(name), f"{value}   in [{lower:g}, {upper:g}]"))
    return rows
