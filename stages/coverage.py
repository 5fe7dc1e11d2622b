"""Stage ``coverage``: is Init inside the union of the balls ``{x : ||x - x0_i||_P_i <= r_i}``?

Each ball has its own metric ``P_i``: the funnel certificate's balls are its initial ellipsoids
``E_i(0)`` (``P_i = P_i[0]``, ``r_i = rho_i``; ``cover_balls``); the constant certificate's are the
same code with the feedback's one ``P`` repeated (``cover_init``).

Init is a box, covered by sound recursive subdivision (``pipeline.numerics.verify.cover``, which the
final certificate check, stage ``certify``, uses as well): a box is covered when all its
vertices lie in one ball; boxes no ball can cover yet are halved up to ``max_depth`` times.
What remains is reported as uncovered (sound, not complete). The covered boxes with their
ball indices form the controller's lookup table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.verify.cover import DEFAULT_DEPTH, subdivide
from pipeline.results.coverage import CoverageResult as CoverageResult
from pipeline.results.coverage import CoveringRadius as CoveringRadius
from pipeline.results.stage import Stage, StageInputs

MAX_BISECTIONS = 200  # covering_radius: tries of a radius (about 10 suffice in practice)


class Metric(Protocol):
    """What this stage reads from the feedback stage's result."""

    @property
    def P(self) -> FloatArray | None:  # (n, n)
        ...


def cover_init(
    scenario: Scenario,
    feedback: Metric,
    centers: FloatArray,
    radii: FloatArray,
    max_depth: int = DEFAULT_DEPTH,
) -> CoverageResult:
    """Certify that Init (``scenario.init_lower/upper (n,)``) lies in the union of the balls
    with ``centers (k, n)``, ``radii (k,)`` in the metric ``feedback.P (n, n)`` (the constant
    certificate: ``cover_balls`` with that one ``P`` for every ball)."""
    if feedback.P is None:
        raise ValueError("coverage: the feedback has no certified P; run the feedback stage")
    P = np.asarray(feedback.P, dtype=np.float64)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, P.shape[0])
    return cover_balls(scenario, P, centers, radii, max_depth)


def cover_balls(
    scenario: Scenario,
    metrics: FloatArray,
    centers: FloatArray,
    radii: FloatArray,
    max_depth: int = DEFAULT_DEPTH,
    *,
    noun: str = "ball",
) -> CoverageResult:
    """Certify that Init (``scenario.init_lower/upper (n,)``) lies in the union of the balls
    ``(x - centers[i])^T metrics[i] (x - centers[i]) <= radii[i]^2`` with ``metrics (k, n, n)``
    (or ``(n, n)``, one for every ball), ``centers (k, n)``, ``radii (k,)`` (radii <= 0 cover
    nothing); ``noun`` names a ball in the message (e.g. ``"funnel start"``)."""
    cover = subdivide(
        np.asarray(metrics, dtype=np.float64),
        scenario.init_lower,
        scenario.init_upper,
        centers,
        radii,
        max_depth,
    )
    gaps, free_index, depth = cover.uncovered, list(cover.free), cover.depth
    fraction, covered = cover.fraction, cover.covered
    if covered:
        used = len(np.unique(cover.assignment))
        message = f"Init is covered by {used} {noun}{'s' if used > 1 else ''}"
    else:
        names = [scenario.state_names[i] for i in free_index]
        widths = gaps[:, 1, free_index] - gaps[:, 0, free_index]
        big = gaps[int(np.argmax(np.prod(widths, axis=1)))][:, free_index]
        where = ", ".join(
            f"{name} in [{lo:.4g}, {hi:.4g}]" for name, lo, hi in zip(names, *big, strict=True)
        )
        message = (
            f"Init is not covered: {len(gaps)} boxes ({100 * (1 - fraction):.3g}% of Init by "
            f"volume) are not certified at depth {depth}; the largest: {where}"
        )
    return CoverageResult(
        covered=covered,
        covered_fraction=float(fraction),
        boxes=cover.boxes,
        assignment=cover.assignment,
        uncovered_boxes=gaps,
        free=cover.free,
        depth=depth,
        success=covered,
        message=message,
    )


def covering_radius(
    scenario: Scenario,
    feedback: Metric,
    centers: FloatArray,
    upper: float,
    tolerance: float = 0.01,
    max_depth: int = DEFAULT_DEPTH,
) -> CoveringRadius:
    """Bisection on a common radius ``r`` in ``(0, upper]`` for the balls around ``centers
    (k, n)``; coverage by ``cover_init`` is monotone in ``r``, and the radius returned is one
    at which it was certified, at most ``(1 + tolerance)`` times the smallest such."""
    centers = np.asarray(centers, dtype=np.float64)
    lower0 = np.asarray(scenario.init_lower, dtype=np.float64)
    upper0 = np.asarray(scenario.init_upper, dtype=np.float64)
    if np.all(upper0 == lower0):
        return _point_covering_radius(feedback, centers, lower0)

    def covers(radius: float) -> bool:
        radii = np.full(len(centers), radius)
        return cover_init(scenario, feedback, centers, radii, max_depth).covered

    tries = 1
    if not (np.isfinite(upper) and upper > 0 and covers(upper)):
        return CoveringRadius(
            radius=np.inf,
            covered=False,
            tries=tries,
            success=False,
            message=f"balls of radius {upper:.4g} do not cover Init",
        )
    # Init has a free direction, so the smallest covering radius is positive and each halving
    # while lo = 0 brings hi closer to it: the loop ends after about log2(upper / radius) +
    # log2(1 / tolerance) tries. MAX_BISECTIONS bounds it whatever the numbers.
    lo, hi = 0.0, float(upper)
    while hi - lo > tolerance * hi and tries <= MAX_BISECTIONS:
        middle = (lo + hi) / 2
        tries += 1
        if covers(middle):
            hi = middle
        else:
            lo = middle
    converged = hi - lo <= tolerance * hi
    note = "" if converged else f" (bisection stopped after {MAX_BISECTIONS} tries)"
    return CoveringRadius(
        radius=hi,
        covered=True,
        tries=tries,
        success=True,
        message=f"balls of radius {hi:.4g} around the {len(centers)} starts cover Init{note}",
    )


def _point_covering_radius(
    feedback: Metric, centers: FloatArray, point: FloatArray
) -> CoveringRadius:
    """Init is the single state ``point (n,)``: the smallest common radius is exactly the
    distance ``min_i ||point - centers[i]||_P`` (0 when a demo starts there; every tube then
    covers Init and the optimizer keeps ``r_d``)."""
    if feedback.P is None:
        raise ValueError("coverage: the feedback has no certified P; run the feedback stage")
    P = np.asarray(feedback.P, dtype=np.float64)
    e = point[None] - centers.reshape(-1, point.shape[0])  # (k, n)
    distance = float(np.sqrt(max(np.min(np.einsum("ki,ij,kj->k", e, P, e)), 0.0)))
    # One ulp-scale step up, so that cover_init (q <= r^2) certifies this radius too.
    radius = distance * (1.0 + 1e-12)
    return CoveringRadius(
        radius=radius,
        covered=True,
        tries=0,
        success=True,
        message=(
            "Init is a single state; "
            + (
                "a demo starts there, so any tube covers it"
                if radius == 0.0
                else f"the nearest start is at P-distance {distance:.4g}"
            )
        ),
    )


@dataclass(frozen=True, kw_only=True)
class CoverageInputs(StageInputs):
    """What stage ``coverage`` reads: Init, and the balls ``(x - centers[i])^T metrics[i]
    (x - centers[i]) <= radii[i]^2`` (``metrics (n, n)`` or ``(k, n, n)``, ``centers (k, n)``,
    ``radii (k,)``); ``noun`` names a ball in its message."""

    scenario_fields: ClassVar = (
        "dynamics",
        "init_lower",
        "init_upper",
    )
    scenario: Scenario
    metrics: FloatArray
    centers: FloatArray
    radii: FloatArray
    noun: str = "ball"


def _coverage_stage(inputs: CoverageInputs) -> CoverageResult:
    return cover_balls(
        inputs.scenario, inputs.metrics, inputs.centers, inputs.radii, noun=inputs.noun
    )


@dataclass(frozen=True, kw_only=True)
class CoveringRadiusInputs(StageInputs):
    """What stage ``covering_radius`` reads: Init, the metric ``P (n, n)``, the demo starts
    ``centers (k, n)`` and the largest radius tried ``upper``."""

    scenario_fields: ClassVar = (
        "dynamics",
        "init_lower",
        "init_upper",
    )
    scenario: Scenario
    P: FloatArray
    centers: FloatArray
    upper: float


@dataclass(frozen=True, kw_only=True)
class _Metric:
    P: FloatArray


def _covering_radius_stage(inputs: CoveringRadiusInputs) -> CoveringRadius:
    return covering_radius(inputs.scenario, _Metric(P=inputs.P), inputs.centers, inputs.upper)


COVERAGE = Stage("coverage", _coverage_stage, CoverageInputs, CoverageResult)
COVERING_RADIUS = Stage(
    "covering_radius", _covering_radius_stage, CoveringRadiusInputs, CoveringRadius
)
