"""The run's summary as typed, frozen data: the verdict, the claims with their kind, the numbers.

Built by ``pipeline.runtime.summary.summarise`` from the stage results, written to
``summary.json`` by ``to_json`` (non-finite numbers become ``null``, so the file is valid JSON)
and read back by ``Summary.from_json`` for the reports. Decoding is driven by these classes'
field types only: nothing in the file chooses what is built.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


class Verdict(enum.Enum):
    """The run's outcome; the value is the text printed and shown in the report."""

    CERTIFIED_AND_VALIDATED = "certified and validated"
    CERTIFIED_NOT_VALIDATED = "certified but not validated"
    NOT_CERTIFIED = "not certified"
    FAILED = "failed"

    @classmethod
    def of(cls, *, certified: bool, validated: bool) -> Verdict:
        """The verdict of a run that finished: certification first, then validation."""
        if not certified:
            return cls.NOT_CERTIFIED
        return cls.CERTIFIED_AND_VALIDATED if validated else cls.CERTIFIED_NOT_VALIDATED


class ClaimKind(enum.Enum):
    """How a claim was established."""

    CERTIFIED = "certified"  # proof (LMI, tube bounds), re-checked on the emitted file
    STATISTICALLY_VALIDATED = "statistically validated"  # i.i.d. sampling with a bound
    FALSIFICATION_SEARCHED = "falsification-searched"  # search; evidence, not a bound
    NOT_ESTABLISHED = "not established"


@dataclass(frozen=True, kw_only=True)
class Claim:
    claim: str
    kind: ClaimKind
    how: str


@dataclass(frozen=True, kw_only=True)
class DemoSummary:
    """One demonstration before and after optimization (times in s, clearances in m, radii in
    the P-norm; ``binding_*``: the constraint that sets the radius, and when)."""

    demo: str
    start: tuple[float, ...]
    T_demo: float
    T_optimized: float
    faster_percent: float
    optimized: bool
    message: str
    iterations: int
    horizons_tried: int
    seconds: float
    clearance_before: float
    clearance_after: float
    radius_before: float
    radius_after: float
    binding_before: str
    binding_after: str
    binding_time_before: float
    binding_time_after: float
    funnel_level: float | None = None  # the funnel certificate: rho of the optimized one
    funnel_binding: str | None = None  # the constraint that sets it (None: no funnel)
    funnel_seconds: float | None = None  # its synthesis wall time
    T_constant: float | None = None  # a funnel run: the constant certificate's optimized T


@dataclass(frozen=True, kw_only=True)
class FunnelSummary:
    """What controller.json guarantees along one shipped trajectory (a funnel run): every flight
    that starts in ``E_i(0)`` stays in ``E_i(t) = {x : ||x - x_ref_i(t)||_P_i(t) <= level}``
    until ``T`` (s). ``binding``: the constraint that sets the level ("design": the funnel's
    own LMI caps, i.e. at level 1 its cell of Init held whole; "dropped": no funnel ships);
    ``nearest``, ``nearest_level``: the tightest other constraint and the level it would allow.
    ``extent_at_T``: the largest position offset in ``E_i(T)`` from ``p_ref(T)``; ``clearance``:
    the smallest distance from Unsafe to the position projection of ``E_i(t)`` over the file's
    fine grid (both in the position unit; NaN for a dropped funnel). ``arrival``: ``x_ref(T)
    (n,)``; ``arrival_velocity``: ``d p_ref/dt`` at ``T`` (2,), ``arrival_speed`` its norm."""

    demo: str
    T: float
    level: float
    binding: str
    nearest: str
    nearest_level: float
    extent_at_T: float
    clearance: float
    arrival: tuple[float, ...]
    arrival_velocity: tuple[float, ...]
    arrival_speed: float

    @property
    def shipped(self) -> bool:
        """A certified funnel ships (not dropped)."""
        return self.binding != "dropped" and self.level > 0


@dataclass(frozen=True, kw_only=True)
class Headline:
    T_demo_mean: float
    T_optimized_mean: float
    faster_percent_mean: float
    min_clearance_before: float
    min_clearance_after: float
    required_clearance: float
    coverage_before: float
    coverage_after: float
    covered_before: bool
    covered_after: bool
    montecarlo_samples: int
    montecarlo_failures: int
    failure_bound_95: float


@dataclass(frozen=True, kw_only=True)
class FeedbackSummary:
    """The feedback and its tube footprint at ``r_d`` (``K (m, n)`` as nested tuples)."""

    gain: str
    K: tuple[tuple[float, ...], ...]
    P_eigenvalues: tuple[float, ...]
    rate: float
    region: dict[str, tuple[float, float]]
    required_radius: float
    covering_radius: float | None
    kept_radius: float
    input_margin_at_r_d: tuple[float, ...]
    region_extent_at_r_d: dict[str, float]
    vertices: int
    message: str


@dataclass(frozen=True, kw_only=True)
class Quantiles:
    median: float
    p95: float
    max: float


@dataclass(frozen=True, kw_only=True)
class FalsificationSummary:
    worst_x0: tuple[float, ...]
    worst_margin: float
    binding: str
    evaluations: int


@dataclass(frozen=True, kw_only=True)
class MonteCarloSummary:
    samples: int
    seed: int
    failures: dict[str, int]
    failure_bound_95: float
    min_clearance: float
    min_goal_margin: float
    max_tube_tightness: float
    tube_ratio_at_T: Quantiles | None
    falsification: FalsificationSummary
    message: str


@dataclass(frozen=True, kw_only=True)
class ControllerSummary:
    path: str
    trajectories: int
    interpolation_error_P: float


@dataclass(frozen=True, kw_only=True)
class CertificationSummary:
    """The final check of ``controller.json`` as written (stage ``certify``)."""

    certified: bool
    sha256: str
    metric_eigenvalue: float
    contraction_margin: float
    vertices: int
    covered_fraction: float
    message: str


@dataclass(frozen=True, kw_only=True)
class StressRunSummary:
    samples: int
    failures: dict[str, int]
    failed_fraction: float
    min_clearance: float
    min_goal_margin: float


@dataclass(frozen=True, kw_only=True)
class StressSummary:
    kind: str
    message: str
    with_feedback: StressRunSummary
    without_feedback: StressRunSummary


@dataclass(frozen=True, kw_only=True)
class Reproducibility:
    versions: dict[str, str]
    scenario_sha256: str
    montecarlo_seed: int
    command: tuple[str, ...]


@dataclass(frozen=True, kw_only=True)
class Summary:
    """Everything ``summary.json`` holds. ``reasons``: why the verdict is not "certified and
    validated" (empty otherwise); ``timings``: wall time per stage (0: reused); ``certificate``:
    what the verdict is for, ``"constant"`` (one metric and gain, ``safety-controller/1``) or
    ``"funnel"`` (a funnel per trajectory, ``safety-controller/2``); ``funnels``: a funnel
    run's shipped funnels, what controller.json guarantees per trajectory (empty otherwise)."""

    scenario: str
    verdict: Verdict
    reasons: tuple[str, ...]
    claims: tuple[Claim, ...]
    headline: Headline
    feedback: FeedbackSummary
    demos: tuple[DemoSummary, ...]
    montecarlo: MonteCarloSummary
    controller: ControllerSummary
    certification: CertificationSummary
    timings: dict[str, float]
    total_seconds: float
    reproducibility: Reproducibility
    stress: StressSummary | None = None
    certificate: str = "constant"
    funnels: tuple[FunnelSummary, ...] = ()

    @property
    def certified(self) -> bool:
        return self.verdict in (Verdict.CERTIFIED_AND_VALIDATED, Verdict.CERTIFIED_NOT_VALIDATED)

    @property
    def validated(self) -> bool:
        """Monte Carlo found no failure (also told for a run that is not certified)."""
        if self.verdict is Verdict.NOT_CERTIFIED:
            return self.headline.montecarlo_failures == 0
        return self.verdict is Verdict.CERTIFIED_AND_VALIDATED

    @property
    def text(self) -> str:
        """The verdict line: ``certified and validated``, or the verdict and its reasons."""
        if self.verdict is Verdict.CERTIFIED_AND_VALIDATED or not self.reasons:
            return self.verdict.value
        return f"{self.verdict.value}: " + "; ".join(self.reasons)

    def to_json(self) -> dict[str, Any]:
        """A JSON document (non-finite floats as null); the verdict is an object with
        ``kind``, ``certified``, ``validated``, ``text`` and ``reasons``."""
        document = _encode(self)
        document["verdict"] = {
            "kind": self.verdict.value,
            "certified": self.certified,
            "validated": self.validated,
            "text": self.text,
            "reasons": list(self.reasons),
        }
        del document["reasons"]
        return document

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> Summary:
        """The summary of a ``to_json`` document; a wrong or missing field raises ``ValueError``
        naming it."""
        if not isinstance(document, Mapping) or not isinstance(document.get("verdict"), Mapping):
            raise ValueError("verdict: missing; expected an object")
        verdict = document["verdict"]
        flat = {**document, "verdict": verdict.get("kind"), "reasons": verdict.get("reasons")}
        decoded: Summary = _decode(cls, flat, "")
        return decoded


def _encode(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _encode(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, Mapping):
        return {str(k): _encode(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_encode(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None  # JSON has no NaN or infinity
    return value


def _decode(kind: Any, value: Any, where: str) -> Any:
    """``value`` (decoded JSON) as the type ``kind``; ``where`` names the field for errors."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (kind,) = [a for a in args if a is not type(None)]
        return _decode(kind, value, where)
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):
        if not isinstance(value, Mapping):
            raise ValueError(f"{where or '(top level)'}: expected an object")
        hints = typing.get_type_hints(kind)
        fields = {}
        for f in dataclasses.fields(kind):
            name = f"{where}.{f.name}".lstrip(".")
            if f.name in value:
                fields[f.name] = _decode(hints[f.name], value[f.name], name)
            elif f.default is dataclasses.MISSING:
                raise ValueError(f"{name}: missing")
        return kind(**fields)
    if isinstance(kind, type) and issubclass(kind, enum.Enum):
        try:
            return kind(value)
        except ValueError:
            raise ValueError(
                f"{where}: {value!r} is not one of {[k.value for k in kind]}"
            ) from None
    if origin is tuple:
        if not isinstance(value, list):
            raise ValueError(f"{where}: expected a list")
        items = args[:1] * len(value) if args[-1] is Ellipsis else args
        if len(items) != len(value):
            raise ValueError(f"{where}: expected {len(items)} items")
        pairs = enumerate(zip(items, value, strict=True))
        return tuple(_decode(k, v, f"{where}[{i}]") for i, (k, v) in pairs)
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ValueError(f"{where}: expected an object")
        return {str(k): _decode(args[1], v, f"{where}.{k}") for k, v in value.items()}
    if kind is float:
        if value is None:  # written for a non-finite number
            return math.nan
        if type(value) not in (int, float):
            raise ValueError(f"{where}: expected a number")
        return float(value)
    if kind in (int, str, bool):
        if type(value) is not kind:
            raise ValueError(f"{where}: expected {kind.__name__}")
        return value
    raise TypeError(f"{where}: no decoder for {kind!r}")
