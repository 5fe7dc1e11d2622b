"""The funnel certificate in the report: the funnel figure, the table "constant vs funnel" and
the shipped gains, for a run with ``--certificate funnel`` (``ReportData.funnel``).

In such a run the constant certificate (one ``K``, ``P``) is still designed and verified by the
stages (``feedback``, ``radius_optimized``, ``coverage_optimized``) but neither written to a
file nor re-certified from one; what ships is controller.json (``safety-controller/2``): per
trajectory ``K_i[k] (N, m, n)``, ``P_i[k] (N+1, n, n)`` and a level ``rho_i``, the funnel

    E_i(t) = {x : (x - x_ref_i(t))^T P_i(t) (x - x_ref_i(t)) <= rho_i^2},

whose position projection is ``{p : (p - p_ref(t))^T (C P_i(t)^-1 C^T)^-1 (p - p_ref(t)) <=
rho_i^2}``. The run's verdict (certify on the shipped file, Monte Carlo) is the funnel's.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from shapely import LineString

from pipeline.io.artifacts import file_hash
from pipeline.model.dynamics import FloatArray
from pipeline.model.simulate import Trajectory
from pipeline.reporting import figures
from pipeline.reporting.content import Figure, Paragraph, Table, fixed, number, percent
from pipeline.reporting.data import ReportData
from pipeline.reporting.numbers import montecarlo_counts
from pipeline.reporting.plotting import FIGURE_WIDTH

CONSTANT_STATUS = "verified by the stages, not shipped"
FUNNEL_STATUS = "shipped: controller.json (safety-controller/2)"


def nominal_clearance(data: ReportData, paths: tuple[Trajectory, ...]) -> float:
    """The smallest distance (m) from Unsafe to the nominal positions of ``paths``, each path
    taken as the polyline through its fine grid ``dense_xs (r, n)``: exact for controller.json's
    ``x_ref``, which the law interpolates linearly."""
    s = data.scenario
    return min(
        float(LineString(s.positions(path.dense_xs)).distance(polygon))
        for path in paths
        for polygon in s.unsafe.values()
    )


def _span(values: FloatArray) -> str:
    """``min-max`` (s) of ``values (k,)``, one number when they agree to the shown digit."""
    low, high = fixed(float(np.min(values)), 1), fixed(float(np.max(values)), 1)
    return low if low == high else f"{low}-{high}"


def comparison(data: ReportData) -> tuple:
    """The table "constant vs funnel" (funnel run only; a constant run shows none)."""
    if not data.funnel:
        return ()
    summary = data.summary
    mc = summary.montecarlo
    kept = [k for k, r in enumerate(data.radius_optimized) if r.radius > 0]
    constant_paths = tuple(data.final_paths[k] for k in kept)
    coverage = data.coverage_optimized
    constant_verified = bool(kept) and coverage.covered
    constant_verdict = (
        "certified over the operating region by the stages feedback, radius_optimized and "
        "coverage_optimized; no controller written or re-certified from a file"
        if constant_verified
        else f"not verified: {len(kept)} of {len(data.final_paths)} radii positive, "
        f"Init {percent(coverage.covered_fraction)} covered (not shipped)"
    )
    counts = montecarlo_counts(mc.samples, summary.headline.montecarlo_failures, mc.failures)
    shipped = data.shipped_paths
    rows = (
        (
            "constant (one K, P)",
            CONSTANT_STATUS,
            str(len(constant_paths)),
            _span(np.array([p.duration for p in constant_paths])) if constant_paths else "n/a",
            fixed(nominal_clearance(data, constant_paths), 3) if constant_paths else "n/a",
            percent(coverage.covered_fraction),
            constant_verdict,
        ),
        (
            "funnel (K_i[k], P_i(t) per trajectory)",
            FUNNEL_STATUS,
            str(len(shipped)),
            _span(np.array([p.duration for p in shipped])),
            fixed(nominal_clearance(data, shipped), 3),
            percent(summary.headline.coverage_after),
            f"{summary.text}: certify re-checked controller.json "
            f"({'passed' if summary.certification.certified else 'failed'}); "
            f"Monte Carlo: {counts}",
        ),
    )
    return (
        Table(
            (
                "certificate",
                "status",
                "trajectories",
                "T (s, min-max)",
                "min nominal clearance (m)",
                "Init covered",
                "verdict",
            ),
            rows,
            "Constant vs funnel certificate in this run. T: the nominal horizons; clearance: "
            "the smallest distance from Unsafe to the nominal paths as polylines through their "
            "fine grids (for the shipped ones exactly the x_ref the controller follows; the "
            "Summary's per-demonstration nominal clearances are the smallest over those grids' "
            "points); "
            "coverage: certified by box subdivision (the constant balls, or the funnels' "
            "initial ellipsoids E_i(0))",
            numeric=(False, False, True, True, True, True, False),
        ),
    )


def funnel_figure(data: ReportData) -> tuple:
    """The shipped funnels over the scene (funnel run only)."""
    if not data.funnel:
        return ()
    return (
        Figure(
            "funnels",
            "The shipped funnels: for each trajectory of controller.json (orange, markers "
            f"{figures.MARKER_PERIOD:g} s apart) the position projection of its funnel E_i(t) = "
            "{x : (x - x_ref(t))^T P_i(t) (x - x_ref(t)) <= ρ_i²}, i.e. the ellipse with shape "
            f"C P_i(t)^-1 C^T and radius ρ_i, outlined in cyan every {figures.FUNNEL_PERIOD:g} s "
            "and at t = T, over Unsafe, Goal and Init; the arrows: each nominal's velocity when it "
            f"arrives ({figures.ARROW_SECONDS:g} s of travel).",
            partial(figures.draw_funnels, data=data),
            (FIGURE_WIDTH, figures.scene_height(data, data.shipped_paths, below=0.9)),
            data.fingerprint(file_hash(data.controller_path)),
        ),
    )


def _range(low: float, high: float, tiny: float) -> str:
    """``low .. high``, each ``0`` when below ``tiny`` in magnitude, one number when equal."""
    a, b = (number(v, 3) if abs(v) > tiny else "0" for v in (low, high))
    return a if a == b else f"{a} .. {b}"


def gain_range_table(data: ReportData) -> Table:
    """The shipped gains' range: entry ``(u_j, x_i)`` of every ``K_i[k]`` over all trajectories
    ``i`` and intervals ``k`` as ``min .. max``."""
    s = data.scenario
    K = np.concatenate([tr.K for tr in data.law.trajectories])  # (sum N_i, m, n)
    low, high = K.min(axis=0), K.max(axis=0)
    tiny = 1e-9 * float(np.abs(K).max()) if K.size else 0.0  # below: shown as 0
    return Table(
        ("K_i[k]", *(s.label(name) for name in s.state_names)),
        tuple(
            (
                s.label(name),
                *(_range(float(a), float(b), tiny) for a, b in zip(low[j], high[j], strict=True)),
            )
            for j, name in enumerate(s.input_names)
        ),
        "Shipped gains: the gains are per trajectory and per sample interval (K_i[k], held on "
        f"[t_k, t_k+1)); each entry's range over the {len(data.law.trajectories)} funnels and "
        f"{len(K)} intervals, in [unit of u_j] per [unit of x_i]",
        numeric=(False, *([True] * s.n)),
    )


def shipped_feedback(data: ReportData) -> tuple:
    """The feedback section's note on what is shipped (funnel run only): the gains are per
    trajectory; the constant K and P below are the constant certificate's, not shipped."""
    if not data.funnel:
        return ()
    levels = np.array([tr.radius for tr in data.law.trajectories])
    return (
        Paragraph(
            "This run ships the funnel certificate: controller.json has no feedback block; each "
            "trajectory carries its own gains K_i[k] and metrics P_i[k] (Q = P^-1 linear in t "
            "between samples) and a level ρ_i "
            f"({number(float(levels.min()), 3)} to {number(float(levels.max()), 3)}), and the "
            "controller is u = u_ref_i(t) + K_i[k] (x - x_ref_i(t)). The constant certificate's "
            f"gain K, metric P and rate ({CONSTANT_STATUS}) are in section 'Seed and comparison'."
        ),
        gain_range_table(data),
    )
