"""What ships, first: a funnel run's summary cards and per-demonstration table say what
controller.json guarantees per funnel (``Summary.funnels``: T, level, the constraint that sets
it, the extent at T, the funnel's clearance, the arrival state and speed).

The constant certificate (one ``K``, ``P``) seeds the funnels in such a run and is verified by
the stages but not shipped; it is shown once, in the section "Seed and comparison" built here
from the blocks that describe it (``certificates``, ``stage_sections``).
"""

from __future__ import annotations

import math

from pipeline.reporting.content import Headline, Paragraph, Table, fixed, number, percent
from pipeline.reporting.summary import FunnelSummary, Summary

SEED_TITLE = "Seed and comparison: the constant certificate"
LEVEL_HELD = 0.999  # a level this close to 1: the start's cell of Init held whole


def span(values: list[float], decimals: int = 1) -> str:
    """``low-high`` of ``values`` shown with ``decimals``; one number when they agree."""
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return fixed(math.nan, decimals, "none shipped")
    low, high = fixed(min(finite), decimals), fixed(max(finite), decimals)
    return low if low == high else f"{low}-{high}"


def binding_text(funnel: FunnelSummary) -> str:
    """The constraint that sets the level, in words, with the next one and the level it would
    allow: ``"design: cell held whole (next: goal at 1.05)"``."""
    if not funnel.shipped:
        return "dropped (no funnel ships)"
    if funnel.binding == "design":
        head = "design: cell held whole" if funnel.level >= LEVEL_HELD else "design"
    else:
        head = funnel.binding
    if not funnel.nearest or not math.isfinite(funnel.nearest_level):
        return head
    return f"{head} (next: {funnel.nearest} at {number(funnel.nearest_level, 3)})"


def speed_unit(length: str) -> str:
    return f"{length}/s" if length else "position units/s"


def shipped_items(summary: Summary, length: str = "m") -> tuple[Headline, ...]:
    """The cards of what controller.json guarantees (funnel run; none otherwise)."""
    funnels = [f for f in summary.funnels if f.shipped]
    if summary.certificate != "funnel" or not summary.funnels:
        return ()
    levels = [f.level for f in funnels]
    held = sum(1 for f in funnels if f.level >= LEVEL_HELD)
    unit = f" {length}" if length else ""
    return (
        Headline(
            "Shipped: controller.json",
            f"{len(funnels)} of {len(summary.funnels)} funnels, "
            f"T {span([f.T for f in summary.funnels])} s",
            "each flight from Init stays in its funnel E_i(t) until T, clear of Unsafe, then "
            f"lies in Goal; levels ρ {span(levels, 3)}"
            + (f" ({held} hold their cell of Init whole)" if held else ""),
        ),
        Headline(
            "Funnel clearance to Unsafe",
            f"≥ {fixed(min((f.clearance for f in funnels), default=math.nan), 2)}{unit}",
            "the closest of the shipped funnels E_i(t) to Unsafe over [0, T], on "
            "controller.json's time grid (a lower bound at each grid time)",
        ),
        Headline(
            "Arrival at T",
            f"{span([f.arrival_speed for f in funnels])} {speed_unit(length)}",
            "the shipped nominals' speed when they reach Goal; each funnel at T lies in Goal, "
            f"at most {fixed(max((f.extent_at_T for f in funnels), default=math.nan), 2)}{unit}"
            " from its nominal",
        ),
    )


def funnel_table(summary: Summary, starts: list[str], length: str = "m") -> Table:
    """Per demonstration, what ships (funnel run): ``starts`` the demos' start positions as
    shown."""
    funnels = {f.demo: f for f in summary.funnels}
    rows = []
    for d, start in zip(summary.demos, starts, strict=True):
        f = funnels.get(d.demo)
        shipped = f is not None and f.shipped
        rows.append(
            (
                d.demo,
                start,
                fixed(d.T_demo, 1),
                fixed(d.T_optimized, 1),
                f"{d.faster_percent:.0f}%",
                number(f.level, 3) if shipped and f else "dropped",
                binding_text(f) if f else "not shipped",
                fixed(f.extent_at_T if f else math.nan, 3, "dropped"),
                fixed(f.clearance if f else math.nan, 3, "dropped"),
                fixed(d.clearance_after, 3),
                fixed(f.arrival_speed if f else math.nan, 2, "not shipped"),
            )
        )
    unit = length or "position units"
    return Table(
        (
            "demo",
            f"start [{unit}]",
            "T demo (s)",
            "T shipped (s)",
            "faster",
            "funnel level ρ",
            "level set by",
            f"extent at T ({unit})",
            f"funnel clearance ({unit})",
            f"nominal clearance ({unit})",
            f"arrival speed ({speed_unit(length)})",
        ),
        tuple(rows),
        "Per demonstration: the shipped funnel of controller.json. Level set by: the constraint "
        "that sets ρ ('design': the funnel's own LMI caps; at 1 the start's cell of Init is held "
        "whole), with the next constraint and the level it would allow; extent at T: the "
        "funnel's largest position offset from the nominal at T (it lies in Goal); funnel "
        "clearance: the smallest distance from Unsafe to the funnel over [0, T]; arrival speed: "
        "the nominal's speed at T",
        numeric=(False, False, True, True, True, True, False, True, True, True, True),
        stack=True,
    )


def seed_paragraph(summary: Summary) -> Paragraph:
    """What the seed-and-comparison section is (funnel run)."""
    constant = [d.T_constant for d in summary.demos if d.T_constant is not None]
    T = f" (T {span(constant)} s)" if constant else ""
    return Paragraph(
        "Not shipped. The constant certificate (one gain K and metric P, robustness radii r_i) "
        f"seeds the funnels: its optimized nominals{T} and radii start the funnel rounds, "
        "which re-optimize the nominals against their funnels. The stages feedback, "
        "radius_optimized and coverage_optimized verify it; nothing of it is written to "
        "controller.json. It is shown here once, for comparison with what ships."
    )


def constant_demo_table(summary: Summary, extent: float) -> Table:
    """The constant certificate per demonstration (funnel run: the seed); ``extent``: the
    position offset (m) of its tube per unit of P-radius."""
    rows = tuple(
        (
            d.demo,
            fixed(d.T_constant if d.T_constant is not None else d.T_optimized, 1),
            fixed(d.radius_before, 3),
            fixed(d.radius_before * extent, 3),
            f"{d.binding_before} at {d.binding_time_before:.1f} s",
            fixed(d.radius_after, 3),
            fixed(d.radius_after * extent, 3),
            f"{d.binding_after} at {d.binding_time_after:.1f} s",
        )
        for d in summary.demos
    )
    return Table(
        (
            "demo",
            "T seed (s)",
            "radius before",
            "extent before (m)",
            "bound by",
            "radius seed",
            "extent seed (m)",
            "bound by",
        ),
        rows,
        "Constant certificate per demonstration (the seed, not shipped): its optimized T, the "
        "robustness radii in the P-norm (no unit) of the demonstration (before) and of the "
        "seed's optimum, their tubes' largest position offset, and the constraint each tube "
        "touches first",
        numeric=(False, True, True, True, False, True, True, False),
        stack=True,
    )


def coverage_row(summary: Summary) -> tuple[str, ...]:
    """The coverage table's row of the shipped funnels' ``E_i(0)`` (funnel run)."""
    h = summary.headline
    return (
        "shipped funnels E_i(0)",
        "yes" if h.covered_after else "no",
        percent(h.coverage_after),
        "",
        "",
        "",
        "certified by the certify stage on controller.json",
    )
