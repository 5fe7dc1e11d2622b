"""The feedback design that tunes itself: a small search over what a user would edit by hand.

A contraction certificate ``(P, K, lambda)`` over an operating region ``R`` gives tubes
``||x - x_ref(t)||_P <= r e^{-lambda t}``; the run needs every optimized trajectory's tube at
the radius ``r_need = max(r_d, r_cover)`` (``r_d``: the clearance ``d``'s radius, ``r_cover``:
the smallest common radius whose balls around the demo starts cover Init). The constraints the
optimizer cannot move a trajectory away from are the structural ones (``pipeline.numerics.
tube.radius``): the tube's inputs within ``input_bounds`` and the region, its states within the
region and ``state_bounds``. So a design is scored by

    ratio = min_i r_struct_i / r_need,   r_struct_i = min over those constraints on demo i,

(``>= 1``: the demos' tubes fit at the radius the optimizer must keep; Unsafe and Goal are left
to the optimizer). The search tries, in order, until a design reaches ``ratio >= ENOUGH``:

1. the operating region narrowed around what the demos use (``REGION_PADS``: the demos' range
   on each variable the Jacobian depends on, widened by that fraction of the room to the
   file's interval; 1 is the file's region) at the first rate;
2. lower rates (``RATES``) at the best region so far, then the other regions at the best rate;
3. the LQR input weights scaled by ``WEIGHT_SCALES`` (smaller or larger LQR gains).

Fields the scenario file sets are not searched (``FeedbackSpec.given``); the region is only
narrowed inside the file's. Every design is certified by the caller's ``design`` (the LMI of
stage ``feedback``, re-checked with numpy); the search only chooses among certified ones, the
one with the largest ratio (the first reached at ``ENOUGH``), so soundness is the design's.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.tube.geometry import Tube
from pipeline.numerics.tube.radius import radius_limits
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS

log = logging.getLogger(__name__)

RATES = (0.5, 0.2, 0.1, 0.05)  # 1/s, tried from the file's (or the default) rate down
REGION_PADS = (1.0, 0.5, 0.2)  # fraction of the room between the demos' range and the file's
WEIGHT_SCALES = (10.0, 0.1)  # input weights x this (a smaller or larger LQR gain)
ENOUGH = 2.0  # ratio at which the search stops: the tubes fit twice over
GRID_POINTS = 4096  # over Init, for the covering radius's estimate


class Design(Protocol):
    """What the search reads from a design (``stages.feedback.FeedbackResult``)."""

    @property
    def success(self) -> bool: ...

    @property
    def tube(self) -> Tube | None: ...

    @property
    def message(self) -> str: ...


@dataclass(frozen=True, kw_only=True)
class Score:
    """How well a certified design's tubes fit (module docstring).

    Attributes:
      ratio: ``min_i r_struct_i / r_need``; radius: ``min_i r_struct_i``; needed: ``r_need``;
      required: ``r_d``; covering: ``r_cover`` as estimated by ``_covering``.
      binding: the structural constraint that sets ``radius``; binding_time (s); demo: whose.
    """

    ratio: float
    radius: float
    needed: float
    required: float
    covering: float
    binding: str
    binding_time: float
    demo: str


@dataclass(frozen=True, kw_only=True)
class FeedbackTuning:
    """What the search chose (stored with the feedback stage's result).

    Attributes:
      rate: lambda (1/s); state_weights (n,), input_weights (m,): the LQR weights used;
      region: the operating region used (inside the file's).
      ratio, radius, needed, binding, binding_time, demo: the chosen design's ``Score``.
      advice: what to edit if the fit is still short (one sentence), empty when it fits.
      tried: one line per design tried (the search's log).
    """

    rate: float
    state_weights: tuple[float, ...]
    input_weights: tuple[float, ...]
    region: Mapping[str, tuple[float, float]]
    ratio: float
    radius: float
    needed: float
    binding: str
    binding_time: float
    demo: str
    advice: str
    tried: tuple[str, ...] = field(repr=False)

    def summary(self, scenario: Scenario) -> str:
        """One line: what was chosen and which constraint binds."""
        spec = scenario.feedback
        changes = []
        if self.rate != spec.rate:
            changes.append(f"rate {self.rate:g} 1/s (from {spec.rate:g})")
        narrowed = [
            f"{name} [{lo:.3g}, {hi:.3g}]"
            for name, (lo, hi) in self.region.items()
            if (lo, hi) != tuple(scenario.operating_region[name])
        ]
        if narrowed:
            changes.append(f"operating_region narrowed to {', '.join(narrowed)}")
        if tuple(self.input_weights) != tuple(spec.input_weights):
            changes.append(f"input_weights {list(self.input_weights)}")
        chose = "; ".join(changes) if changes else "the file's settings"
        fit = (
            f"demo tubes fit {self.ratio:.2g}x the radius {self.needed:.3g} the run needs"
            if self.ratio >= 1
            else f"demo tubes reach only {self.ratio:.2g} of the radius {self.needed:.3g} the "
            "run needs"
        )
        return (
            f"tuned over {len(self.tried)} designs: {chose}; {fit}; radius limited by "
            f"{self.binding} at t = {self.binding_time:.1f} s ({self.demo})"
            + (f": {self.advice}" if self.advice else "")
        )


def tune_feedback(
    scenario: Scenario, design: Callable[[Scenario], Design]
) -> tuple[Design, FeedbackTuning | None]:
    """Search (module docstring) with ``design`` (a certified design of a scenario, from its
    ``operating_region`` and ``feedback``); returns the chosen design and what was chosen
    (None when no design was certified: the first design tried is returned, failed)."""
    spec = scenario.feedback
    trajectories = [
        simulate(scenario.dynamics, d.x0, d.us, scenario.Ts, substeps=VERIFY_SUBSTEPS)
        for d in scenario.demos
    ]
    pads, regions = zip(*_regions(scenario, trajectories), strict=True)
    rates = (spec.rate,) if "rate" in spec.given else _rates(spec.rate)
    weights_free = "input_weights" not in spec.given
    tried: list[str] = []
    results: dict[tuple[float, int, float], tuple[Design, Score | None]] = {}

    def attempt(rate: float, region: int, scale: float) -> Score | None:
        key = (rate, region, scale)
        if key in results:
            return results[key][1]
        started = time.perf_counter()
        candidate = dataclasses.replace(
            scenario,
            operating_region=regions[region],
            feedback=spec.model_copy(
                update={"rate": rate, "input_weights": [w * scale for w in spec.input_weights]}
            ),
        )
        result = design(candidate)
        score = None
        if result.success and result.tube is not None:
            score = _score(candidate, result.tube, trajectories)
        results[key] = (result, score)
        what = f"rate {rate:g}, region {pads[region]:g}" + (
            f", input weights x{scale:g}" if scale != 1.0 else ""
        )
        outcome = (
            "not certified"
            if score is None
            else f"ratio {score.ratio:.3g} (radius {score.radius:.3g}, needs {score.needed:.3g},"
            f" {score.binding})"
        )
        tried.append(f"{what}: {outcome}")
        log.info(f"[feedback search] {what}: {outcome} ({time.perf_counter() - started:.1f} s)")
        return score

    def best() -> tuple[float, int, float] | None:
        scored = [(k, s) for k, (_, s) in results.items() if s is not None]
        return max(scored, key=lambda ks: ks[1].ratio)[0] if scored else None

    def enough() -> bool:
        key = best()
        return key is not None and results[key][1] is not None and _ratio(results[key]) >= ENOUGH

    plan: list[tuple[str, float]] = [("region", i) for i in range(len(regions))]  # 1.
    plan += [("rate", rate) for rate in rates[1:]]  # 2. at the best region (the first if none)
    plan += [("region at the best rate", i) for i in range(len(regions))]
    plan += [("weights", scale) for scale in WEIGHT_SCALES] if weights_free else []  # 3.
    for kind, value in plan:
        found = best()
        rate, region = (found[0], found[1]) if found is not None else (rates[0], 0)
        if kind == "region":
            attempt(rates[0], int(value), 1.0)
        elif kind == "rate":
            attempt(value, region, 1.0)
        elif kind == "region at the best rate":
            attempt(rate, int(value), 1.0)
        elif kind == "weights":
            attempt(rate, region, value)
        else:
            raise ValueError(f"unknown search step {kind!r}")
        if enough():
            break
    key = best()
    if key is None:
        return next(iter(results.values()))[0], None
    chosen, score = results[key]
    assert score is not None
    rate, region, scale = key
    return chosen, FeedbackTuning(
        rate=rate,
        state_weights=tuple(float(w) for w in spec.state_weights),
        input_weights=tuple(float(w) * scale for w in spec.input_weights),
        region=regions[region],
        ratio=score.ratio,
        radius=score.radius,
        needed=score.needed,
        binding=score.binding,
        binding_time=score.binding_time,
        demo=score.demo,
        advice="" if score.ratio >= 1 else fix_for(scenario, score.binding),
        tried=tuple(tried),
    )


def _ratio(entry: tuple[Design, Score | None]) -> float:
    return -np.inf if entry[1] is None else entry[1].ratio


def _rates(first: float) -> tuple[float, ...]:
    """The file's (default) rate, then the lower of ``RATES``."""
    return (first, *(rate for rate in RATES if rate < first))


def _regions(
    scenario: Scenario, trajectories: Sequence[Trajectory]
) -> list[tuple[float, dict[str, tuple[float, float]]]]:
    """The operating region narrowed around the demos' use (module docstring, step 1), widest
    first, each with its pad; only the variables the Jacobian depends on are narrowed (narrowing
    any other only takes room from the tubes). Duplicates dropped."""
    states, inputs = scenario.state_names, scenario.input_names
    depends = set(scenario.dynamics.depends_on())
    regions: list[tuple[float, dict[str, tuple[float, float]]]] = []
    for pad in REGION_PADS:
        region = {}
        for name, (L, U) in scenario.operating_region.items():
            if name not in depends:
                region[name] = (float(L), float(U))
                continue
            if name in states:
                values = np.concatenate([t.dense_xs[:, states.index(name)] for t in trajectories])
            else:
                values = np.concatenate([t.us[:, inputs.index(name)] for t in trajectories])
            a, b = max(float(values.min()), L), min(float(values.max()), U)
            region[name] = (float(a - pad * (a - L)), float(b + pad * (U - b)))
        if all(region != other for _, other in regions):
            regions.append((pad, region))
    return regions


def _score(scenario: Scenario, tube: Tube, trajectories: Sequence[Trajectory]) -> Score:
    """The design's ``Score`` (module docstring) over the demos ``trajectories``."""
    radius, binding, when, demo = np.inf, "", 0.0, ""
    for d, trajectory in zip(scenario.demos, trajectories, strict=True):
        limits = radius_limits(scenario, tube, trajectory).limits
        for name, (r, t) in limits.items():
            if name.startswith(("unsafe", "goal")):
                continue
            if r < radius:
                radius, binding, when, demo = r, name, t, d.name
    required = tube.required_radius(scenario.clearance)
    covering = _covering(scenario, tube.P)
    needed = max(required, covering)
    return Score(
        ratio=float(radius / needed) if needed > 0 else np.inf,
        radius=float(radius),
        needed=float(needed),
        required=float(required),
        covering=float(covering),
        binding=binding,
        binding_time=float(when),
        demo=demo,
    )


def _covering(scenario: Scenario, P: FloatArray) -> float:
    """An estimate of the smallest common radius at which the balls around the demo starts cover
    Init: the largest P-distance from a point of a grid over Init (corners included, at most
    ``GRID_POINTS``) to its nearest start. A lower bound, for ranking designs only: the
    coverage stage certifies coverage soundly."""
    centers = np.array([d.x0 for d in scenario.demos])  # (k, n)
    lower, upper = scenario.init_lower, scenario.init_upper
    free = np.flatnonzero(upper > lower)
    per_axis = max(2, int(GRID_POINTS ** (1 / max(len(free), 1))))
    axes = [np.linspace(lower[i], upper[i], per_axis) for i in free]
    points = np.tile(lower, (per_axis ** len(free), 1))  # (G, n)
    if len(free):
        points[:, free] = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(
            -1, len(free)
        )
    e = points[:, None, :] - centers[None]  # (G, k, n)
    distance2 = np.einsum("gki,ij,gkj->gk", e, P, e).min(axis=1)
    return float(np.sqrt(max(float(distance2.max()), 0.0)))


def fix_for(scenario: Scenario, binding: str) -> str:
    """What to edit in the scenario file when ``binding`` (a ``radius_limits`` constraint name,
    e.g. "input 'v' upper") limits the tubes; names only fields the file has."""
    kind, _, rest = binding.partition(" ")
    name = rest.split("'")[1] if "'" in rest else ""
    narrow = [v for v in scenario.dynamics.depends_on() if v in scenario.operating_region]
    narrower = f" or narrow operating_region ({', '.join(narrow)})" if narrow else ""
    if kind == "input":
        return f"widen input_bounds.{name}{narrower} (a smaller feedback gain)"
    if kind == "region":
        return f"widen operating_region.{name}, or fly the demos further inside it"
    if kind == "state":
        return f"widen state_bounds.{name}, or fly the demos further inside it"
    return "fly the demos further from that limit"
