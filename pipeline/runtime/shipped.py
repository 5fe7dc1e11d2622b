"""What a funnel run's controller.json guarantees, per trajectory, in the summary's terms.

For trajectory ``i`` of the file (``safety-controller/2``) the funnel is

    E_i(t) = {x : (x - x_ref_i(t))^T P_i(t) (x - x_ref_i(t)) <= rho_i(t)^2},
    rho_i(t) = rho_i e^(-rate_i t),  P_i(t)^-1 linear in t between samples,

and its position projection is the ellipse ``{p : (p - p_ref)^T S^-1 (p - p_ref) <= rho^2}``
with ``S = C P_i(t)^-1 C^T`` (``C`` picks the position states). From it, on the file's fine
grid ``t (r,)``:

- the extent at ``T``: ``rho_i(T) sqrt(lambda_max(S(T)))``, the largest position offset;
- the clearance: the smallest distance from Unsafe to the ellipse, measured on a polygon of
  ``SIDES`` sides that circumscribes it (the image of a polygon circumscribing the unit circle
  under ``p_ref + rho L z``, ``S = L L^T``), so each value is a lower bound at its grid time;
- the arrival: ``x_ref_i(T)`` and the nominal's position rate there, ``C f(x_ref(T), u_ref[N-1])``.

The level and the constraint that sets it are the funnel stage's (``FunnelStageResult``), the
rest is read from the file the run wrote, so the numbers describe what ships.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import shapely

from pipeline.controller import Controller, ReferenceTrajectory
from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.reporting.summary import FunnelSummary

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from stages.funnel import FunnelStageResult

SIDES = 64  # sides of the polygon circumscribing each funnel ellipse (clearance)


def funnel_clearance(
    scenario: Scenario, centres: FloatArray, shapes: FloatArray, radii: FloatArray
) -> float:
    """The smallest distance from Unsafe to the ellipses ``{p : (p - c_k)^T S_k^-1 (p - c_k) <=
    r_k^2}``, ``centres (k, 2)``, ``shapes S (k, 2, 2)``, ``radii (k,)``: a lower bound (each
    ellipse replaced by a circumscribing polygon of ``SIDES`` sides); 0 when one touches it."""
    angle = np.linspace(0.0, 2 * np.pi, SIDES, endpoint=False)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=1) / math.cos(np.pi / SIDES)
    L = np.linalg.cholesky(shapes)  # (k, 2, 2)
    corners = centres[:, None, :] + radii[:, None, None] * np.einsum("kij,aj->kai", L, circle)
    polygons = shapely.polygons(corners)
    unsafe = scenario.unsafe.values()
    return min(float(shapely.distance(polygons, region).min()) for region in unsafe)


def _one(
    scenario: Scenario, Ts: float, tr: ReferenceTrajectory, binding: str, limits: dict[str, float]
) -> FunnelSummary:
    c = list(scenario.position_index)
    radii = tr.radius * np.exp(-tr.rate * tr.t)  # (r,)
    shapes = np.linalg.inv(tr.metric(tr.t, Ts))[:, c][:, :, c]  # (r, 2, 2) C P(t)^-1 C^T
    shapes = (shapes + np.swapaxes(shapes, 1, 2)) / 2
    shipped = binding != "dropped" and tr.radius > 0
    extent = float(radii[-1] * np.sqrt(np.linalg.eigvalsh(shapes[-1]).max()))
    centres = scenario.positions(tr.x_ref)
    clearance = funnel_clearance(scenario, centres, shapes, radii) if shipped else math.nan
    end = tr.x_ref[-1]
    velocity = scenario.positions(scenario.dynamics.f(end, tr.u_ref[-1]))  # (2,)
    others = {name: level for name, level in limits.items() if name != binding}
    nearest = min(others, key=lambda name: others[name]) if others else ""
    return FunnelSummary(
        demo=tr.name or "",
        T=float(tr.T),
        level=float(tr.radius) if shipped else 0.0,
        binding=binding,
        nearest=nearest,
        nearest_level=float(others[nearest]) if nearest else math.nan,
        extent_at_T=extent if shipped else math.nan,
        clearance=clearance,
        arrival=tuple(float(v) for v in end),
        arrival_velocity=tuple(float(v) for v in velocity),
        arrival_speed=float(np.linalg.norm(velocity)),
    )


def funnel_summaries(
    scenario: Scenario, law: Controller, funnels: FunnelStageResult
) -> tuple[FunnelSummary, ...]:
    """One ``FunnelSummary`` per trajectory of ``law`` (controller.json as written), in the
    file's order; the level's constraint from ``funnels`` (matched by the trajectory's name)."""
    summaries = []
    for k, tr in enumerate(law.trajectories):
        i = funnels.names.index(tr.name) if tr.name in funnels.names else k
        funnel = funnels.funnels[i]
        usable = i in funnels.usable
        limits = {  # name -> level (or (level, time))
            str(name): float(v[0] if isinstance(v, tuple) else v)
            for name, v in dict(funnel.limits).items()
        }
        binding = funnel.binding if usable else "dropped"
        summaries.append(_one(scenario, law.Ts, tr, binding, limits))
    return tuple(summaries)
