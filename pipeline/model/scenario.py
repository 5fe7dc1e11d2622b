"""Scenarios: load ``scenarios/NAME/scenario.yaml``, validate it, and build the frozen objects.

Validation happens in three layers, each ending in one ``ScenarioError`` that names the file, the
field path (or CSV row), what was found and what was expected:
1. YAML syntax (line and column; a key repeated in one mapping, a file above 1 MB and aliases
   that expand without bound are refused too: ``pipeline.model.safe_yaml``);
2. the schema (``pipeline.model.schema``: types, missing and extra keys, ordered bounds, ``Ts >
0``);
3. cross-field rules here: names that must match, symbols in the dynamics, valid polygons,
   Init and Goal clear of Unsafe, Init inside ``state_bounds``, demo files (inputs within
   bounds), and each demo's flight (avoids Unsafe, stays in ``state_bounds``, ends in Goal).
"""

from __future__ import annotations

import keyword
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
import sympy
from shapely.geometry import MultiPoint, Polygon
from shapely.validation import explain_validity

from pipeline.io.artifacts import file_hash
from pipeline.io.errors import ScenarioError
from pipeline.model import geometry
from pipeline.model.demos import Demo, read_demo_csv
from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.model.expressions import (
    ALLOWED_CONSTANTS,
    ALLOWED_FUNCTIONS,
    ExpressionError,
    parse_expression,
)
from pipeline.model.feedback_defaults import resolve_feedback
from pipeline.model.frozen import freeze_fields, reduce_fields
from pipeline.model.limits import MIN_FEEDBACK_PERIOD, divides, periods_allowed
from pipeline.model.scenario_file import LOCAL_SCENARIOS as LOCAL_SCENARIOS  # re-exported
from pipeline.model.scenario_file import SCENARIOS_ROOT as SCENARIOS_ROOT
from pipeline.model.scenario_file import available_scenarios as available_scenarios
from pipeline.model.scenario_file import parse_spec
from pipeline.model.scenario_file import resolve_scenario_path as resolve_scenario_path
from pipeline.model.schema import DEFAULT_RATE as DEFAULT_RATE
from pipeline.model.schema import CertificateName as CertificateName
from pipeline.model.schema import FeedbackSpec, ScenarioSpec
from pipeline.model.simulate import simulate
from pipeline.model.uncertainty import Uncertainty, held_box

# The largest lambda T of a demo: e^{lambda T} stays far below float64's limit e^709.78 (room for
# the factors it multiplies).
MAX_DECAY_EXPONENT = 600.0


@dataclass(frozen=True, eq=False)
class Scenario:
    """A validated scenario. Arrays: ``n`` states, ``m`` inputs.

    Attributes:
      input_lower, input_upper: (m,) input bounds.
      init_lower, init_upper: (n,) the Init box (degenerate intervals allowed).
      position_index: (2,) indices of the position states in the state vector.
      unsafe: name -> polygon over position; goal: polygon over position.
      goal_bounds: state name -> (lower, upper) extra bounds at the final time.
      operating_region: state or input name -> (lower, upper).
      terminal: "reach" (the paper's Goal) or "hold" (certified only with a terminal controller
        holding the state in Goal after ``T``).
      certificate: "constant" (one P, K over operating_region) or "funnel" (K[k], P[k] per
        trajectory).
      optimizer: "gd" (the paper's gradient descent) or "lbfgs": how nominals are optimized.
      feedback_period: ``h`` (s), the law is evaluated every ``h`` s and held in between (0:
        continuous feedback); 0 or at least ``MIN_FEEDBACK_PERIOD``, dividing ``Ts``.
      state_bounds: state name -> (lower, upper), the physical envelope (not a certificate region).
      units, labels: state or input name -> unit / human name (optional; see ``label``).
      uncertainty: the declared disturbance and parameter bounds (``pipeline.model.uncertainty``;
        empty for the exact model).

    Deeply frozen: every array is a read-only copy and every mapping a read-only view of a copy
    (``pipeline.model.frozen``), so ``dataclasses.replace(scenario, clearance=0.5)`` is the way to
    another scenario. Its cache key encodes these fields (``pipeline.model.scenario_data``).
    """

    name: str
    path: Path
    spec: ScenarioSpec = field(repr=False)
    dynamics: Dynamics = field(repr=False)
    Ts: float
    input_lower: FloatArray
    input_upper: FloatArray
    init_lower: FloatArray
    init_upper: FloatArray
    position_index: tuple[int, int]
    unsafe: Mapping[str, Polygon] = field(repr=False)
    goal: Polygon = field(repr=False)
    goal_bounds: Mapping[str, tuple[float, float]]
    clearance: float
    operating_region: Mapping[str, tuple[float, float]]
    feedback: FeedbackSpec = field(repr=False)
    demos: tuple[Demo, ...] = field(repr=False)
    source_hash: str = ""
    terminal: str = "reach"
    certificate: CertificateName = "constant"
    optimizer: str = "gd"
    feedback_period: float = 0.0
    state_bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    units: Mapping[str, str] = field(default_factory=dict)
    labels: Mapping[str, str] = field(default_factory=dict)
    uncertainty: Uncertainty = field(repr=False, kw_only=True)

    def __post_init__(self) -> None:
        freeze_fields(self)

    def __reduce__(self) -> tuple[object, ...]:
        """Pickled by its fields (an executor's worker gets the scenario it is given, also one
        made by ``dataclasses.replace``); unpickling constructs, hence freezes, it again."""
        return reduce_fields(self)

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.dynamics.state_names

    @property
    def input_names(self) -> tuple[str, ...]:
        return self.dynamics.input_names

    @property
    def n(self) -> int:
        return self.dynamics.n

    @property
    def m(self) -> int:
        return self.dynamics.m

    def label(self, name: str, *, unit: bool = True) -> str:
        """A state or input name for people: ``"force (thrust) [N]"``, or ``"force"`` when the
        scenario declares neither a label nor a unit for it."""
        text = name
        if name in self.labels:
            text += f" ({self.labels[name]})"
        if unit and name in self.units:
            text += f" [{self.units[name]}]"
        return text

    def unit(self, name: str) -> str:
        """The unit of a state or input (``""`` when undeclared)."""
        return self.units.get(name, "")

    def position_unit(self) -> str:
        """The position states' common unit: of clearances, distances and ``d`` (``""`` when
        undeclared or when the two differ)."""
        units = {self.unit(self.state_names[i]) for i in self.position_index}
        return units.pop() if len(units) == 1 else ""

    def positions(self, xs: FloatArray) -> FloatArray:
        """Position coordinates of states: ``(..., n)`` -> ``(..., 2)``."""
        return np.asarray(xs)[..., list(self.position_index)]

    def in_goal(self, x: FloatArray) -> np.ndarray:
        """True where a state ``(..., n)`` is in Goal (polygon and extra bounds). -> ``(...)``."""
        inside = geometry.contains(self.goal, self.positions(x))
        for name, (lower, upper) in self.goal_bounds.items():
            value = np.asarray(x)[..., self.state_names.index(name)]
            inside &= (value >= lower) & (value <= upper)
        return inside


def load_scenario(name_or_path: str | Path, check_demos: bool = True) -> Scenario:
    """Load and validate a scenario by name (``./scenarios/NAME``, else the shipped one) or by
    path (a folder holding ``scenario.yaml``, or the YAML file).

    With ``check_demos`` every demo is simulated and must avoid Unsafe, stay in ``state_bounds``
    and end in Goal.
    """
    path = resolve_scenario_path(name_or_path)
    spec = parse_spec(path)
    scenario = _build(path, spec)
    if check_demos:
        for demo in scenario.demos:
            check_demo_flight(scenario, demo)
    return scenario


def _require_names(
    path: Path, field_name: str, found: Sequence[str], expected: Sequence[str], exact: bool = True
) -> None:
    unknown = [name for name in found if name not in expected]
    if unknown:
        raise ScenarioError(
            f"unknown name '{unknown[0]}'",
            file=path,
            field=f"{field_name}",
            expected=f"names from {list(expected)}",
        )
    missing = [name for name in expected if name not in found]
    if exact and missing:
        raise ScenarioError(
            f"missing entry '{missing[0]}'",
            file=path,
            field=field_name,
            expected=f"one entry for every name in {list(expected)}",
        )


def _valid_polygon(path: Path, where: str, vertices: Sequence[Sequence[float]]) -> Polygon:
    shape = geometry.polygon(vertices)
    if not shape.is_valid or shape.area <= 0:
        reason = explain_validity(shape) if not shape.is_valid else "zero area"
        raise ScenarioError(
            f"invalid polygon ({reason})",
            file=path,
            field=where,
            expected="a simple polygon (no self-intersection, non-zero area)",
        )
    return shape


def _build(path: Path, spec: ScenarioSpec) -> Scenario:
    states, inputs = list(spec.states), list(spec.inputs)
    names = states + inputs + list(spec.parameters)
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise ScenarioError(
            f"name '{duplicates[0]}' declared twice",
            file=path,
            field="states/inputs/parameters",
            expected="distinct names",
        )
    reserved = [
        name
        for name in names
        if name in ALLOWED_FUNCTIONS or name in ALLOWED_CONSTANTS or keyword.iskeyword(name)
    ]
    if reserved:
        raise ScenarioError(
            f"name '{reserved[0]}' is reserved (a function, constant or Python keyword)",
            file=path,
            field="states/inputs/parameters",
            expected="another name",
        )
    if spec.position[0] == spec.position[1]:
        raise ScenarioError(
            "the same state twice",
            file=path,
            field="position",
            found=list(spec.position),
            expected="two different states",
        )
    _require_names(path, "dynamics", list(spec.dynamics), states)
    _require_names(path, "input_bounds", list(spec.input_bounds), inputs)
    _require_names(path, "init", list(spec.init), states)
    _require_names(path, "position", list(spec.position), states, exact=False)
    _require_names(path, "goal.bounds", list(spec.goal.bounds), states, exact=False)
    if spec.stress is not None:
        _require_names(
            path, "stress.disturbance", list(spec.stress.disturbance), states, exact=False
        )
        _require_names(
            path,
            "stress.measurement_noise",
            list(spec.stress.measurement_noise),
            states,
            exact=False,
        )
    _require_names(
        path, "operating_region", list(spec.operating_region), states + inputs, exact=False
    )
    _require_names(path, "state_bounds", list(spec.state_bounds), states, exact=False)
    _require_names(path, "units", list(spec.units), states + inputs, exact=False)
    _require_names(path, "labels", list(spec.labels), states + inputs, exact=False)
    for key, values, size in [
        ("feedback.reference_state", spec.feedback.reference_state, len(states)),
        ("feedback.reference_input", spec.feedback.reference_input, len(inputs)),
        ("feedback.state_weights", spec.feedback.state_weights, len(states)),
        ("feedback.input_weights", spec.feedback.input_weights, len(inputs)),
    ]:
        if values is not None and len(values) != size:
            raise ScenarioError(
                f"wrong length {len(values)}", file=path, field=key, expected=f"{size} values"
            )

    dynamics = _build_dynamics(path, spec)
    unsafe = {
        name: _valid_polygon(path, f"unsafe.{name}", vertices)
        for name, vertices in spec.unsafe.items()
    }
    if not spec.unsafe:
        raise ScenarioError(
            "no Unsafe set",
            file=path,
            field="unsafe",
            found={},
            expected="at least one named polygon: the certificate is a clearance d from Unsafe"
            " (for open space, name a polygon far from every flight)",
        )
    goal = _valid_polygon(path, "goal.polygon", spec.goal.polygon)
    if geometry.shrink(goal, spec.clearance).is_empty:
        room = geometry.inscribed_radius(goal)
        raise ScenarioError(
            f"does not fit in Goal (the largest disk inside goal.polygon has radius {room:.4g};"
            " every tube must end inside Goal, at least d from its boundary)",
            file=path,
            field="clearance",
            found=spec.clearance,
            expected=f"a clearance below {room:.4g}, or a larger goal.polygon",
        )
    position_index = (states.index(spec.position[0]), states.index(spec.position[1]))
    init_lower = np.array([spec.init[s][0] for s in states])
    init_upper = np.array([spec.init[s][1] for s in states])
    _check_init_in_bounds(path, spec, init_lower, init_upper)
    # The Init box projected on position; a point or a segment when an interval is degenerate.
    corners = [init_lower[list(position_index)], init_upper[list(position_index)]]
    init_box = MultiPoint(corners).envelope
    for name, region in unsafe.items():
        for label, other in [("init", init_box), ("goal.polygon", goal)]:
            if shapely.intersects(region, other):
                X, Y = shapely.intersection(region, other).representative_point().coords[0]
                raise ScenarioError(
                    f"overlaps Unsafe set '{name}' (for example at position ({X:g}, {Y:g}))",
                    file=path,
                    field=label,
                    found=shapely.to_wkt(other, rounding_precision=6),
                    expected=f"a set disjoint from unsafe.{name}",
                )
    Ts = float(spec.sampling_time)
    feedback = resolve_feedback(spec, states, inputs)
    demos = tuple(
        _load_demo(path, spec, index, dynamics, init_lower, init_upper, Ts)
        for index in range(len(spec.demos))
    )
    return Scenario(
        name=spec.name,
        path=path,
        spec=spec,
        dynamics=dynamics,
        Ts=Ts,
        input_lower=np.array([spec.input_bounds[u][0] for u in inputs]),
        input_upper=np.array([spec.input_bounds[u][1] for u in inputs]),
        init_lower=init_lower,
        init_upper=init_upper,
        position_index=position_index,
        unsafe=unsafe,
        goal=goal,
        goal_bounds=dict(spec.goal.bounds),
        clearance=float(spec.clearance),
        operating_region=dict(spec.operating_region),
        feedback=feedback,
        demos=demos,
        source_hash=file_hash(path),
        terminal=spec.terminal,
        certificate=spec.certificate,
        optimizer=spec.optimizer,
        feedback_period=_feedback_period(path, spec),
        state_bounds=dict(spec.state_bounds),
        units=dict(spec.units),
        labels=dict(spec.labels),
        uncertainty=_uncertainty(path, spec),
    )


def _feedback_period(path: Path, spec: ScenarioSpec) -> float:
    """``feedback_period``: 0, or at least ``MIN_FEEDBACK_PERIOD`` and dividing the sampling
    time (``u_ref`` switches at samples: a held window must not straddle one)."""
    period = float(spec.feedback_period)
    if period == 0:
        return 0.0
    if period < MIN_FEEDBACK_PERIOD or not divides(period, spec.sampling_time):
        raise ScenarioError(
            "is not a control period this scenario can be certified for",
            file=path,
            field="feedback_period",
            found=period,
            expected=periods_allowed(spec.sampling_time),
        )
    return period


def _check_init_in_bounds(
    path: Path, spec: ScenarioSpec, init_lower: FloatArray, init_upper: FloatArray
) -> None:
    """Every start must be admissible: the Init box inside ``state_bounds``."""
    for name, (lower, upper) in spec.state_bounds.items():
        i = list(spec.states).index(name)
        if init_lower[i] < lower or init_upper[i] > upper:
            raise ScenarioError(
                f"Init leaves state_bounds.{name} = [{lower:g}, {upper:g}]",
                file=path,
                field=f"init.{name}",
                found=[float(init_lower[i]), float(init_upper[i])],
                expected=f"an interval inside [{lower:g}, {upper:g}] (every start must lie in"
                " the state bounds)",
            )


def _build_dynamics(path: Path, spec: ScenarioSpec, keep: Sequence[str] = ()) -> Dynamics:
    """The scenario's dynamics with every parameter substituted but those named in ``keep``,
    which become trailing inputs (in that order): ``f(x, (u, p_keep))``."""
    state_symbols = [sympy.Symbol(name, real=True) for name in spec.states]
    input_symbols = [sympy.Symbol(name, real=True) for name in spec.inputs]
    parameter_symbols = {name: sympy.Symbol(name, real=True) for name in spec.parameters}
    symbols = {s.name: s for s in (*state_symbols, *input_symbols)} | parameter_symbols
    values = {
        parameter_symbols[k]: sympy.Float(v) for k, v in spec.parameters.items() if k not in keep
    }
    expressions = []
    for name in spec.states:
        try:
            expression = parse_expression(spec.dynamics[name], symbols)
        except ExpressionError as error:
            raise ScenarioError(
                str(error), file=path, field=f"dynamics.{name}", found=spec.dynamics[name]
            ) from None
        expression = sympy.sympify(expression.subs(values))
        if expression.has(sympy.zoo, sympy.oo, -sympy.oo, sympy.nan, sympy.I):
            raise ScenarioError(
                f"not a finite real expression after substituting the parameters ({expression})",
                file=path,
                field=f"dynamics.{name}",
                found=spec.dynamics[name],
                expected="no division by zero and no complex values",
            )
        expressions.append(expression)
    kept = [parameter_symbols[k] for k in keep]
    return Dynamics.from_expressions(state_symbols, [*input_symbols, *kept], expressions)


def _uncertainty(path: Path, spec: ScenarioSpec) -> Uncertainty:
    """The declared ``uncertainty:`` block, checked against the states and parameters."""
    declared = spec.uncertainty
    states = list(spec.states)
    _require_names(path, "uncertainty.disturbance", list(declared.disturbance), states, exact=False)
    _require_names(
        path,
        "uncertainty.disturbance_ellipsoid",
        list(declared.disturbance_ellipsoid),
        states,
        exact=False,
    )
    _require_names(path, "uncertainty.measurement", list(declared.measurement), states, exact=False)
    _require_names(
        path,
        "uncertainty.parameters",
        list(declared.parameters),
        list(spec.parameters),
        exact=False,
    )
    names = tuple(declared.parameters)
    for name, (lower, upper) in declared.parameters.items():
        nominal = spec.parameters[name]
        if not lower <= nominal <= upper:
            raise ScenarioError(
                f"excludes the nominal value {nominal:g} (parameters.{name})",
                file=path,
                field=f"uncertainty.parameters.{name}",
                found=[lower, upper],
                expected=f"an interval holding {nominal:g}: the nominals are flown with it",
            )
    box = np.array([float(declared.disturbance.get(s, 0.0)) for s in states])
    axes = np.array([float(declared.disturbance_ellipsoid.get(s, 0.0)) for s in states])
    return Uncertainty(
        disturbance=held_box(box, axes),  # the ellipsoid held by its bounding box
        ellipsoid=axes,
        declared_box=box,
        measurement=np.array([float(declared.measurement.get(s, 0.0)) for s in states]),
        parameter_names=names,
        parameter_lower=np.array([declared.parameters[k][0] for k in names], dtype=float),
        parameter_upper=np.array([declared.parameters[k][1] for k in names], dtype=float),
        parameter_nominal=np.array([spec.parameters[k] for k in names], dtype=float),
        parametric=_build_dynamics(path, spec, keep=names) if names else None,
    )


def _load_demo(
    path: Path,
    spec: ScenarioSpec,
    index: int,
    dynamics: Dynamics,
    init_lower: FloatArray,
    init_upper: FloatArray,
    Ts: float,
) -> Demo:
    entry = spec.demos[index]
    where = f"demos.{index}.x0"
    x0 = np.array(entry.x0, dtype=np.float64)
    if x0.shape != (dynamics.n,):
        raise ScenarioError(
            f"wrong length {x0.size}",
            file=path,
            field=where,
            expected=f"{dynamics.n} values ({', '.join(dynamics.state_names)})",
        )
    outside = np.flatnonzero((x0 < init_lower - 1e-12) | (x0 > init_upper + 1e-12))
    if outside.size:
        i = outside[0]
        raise ScenarioError(
            f"initial state outside Init in '{dynamics.state_names[i]}'",
            file=path,
            field=where,
            found=float(x0[i]),
            expected=f"a value in [{init_lower[i]:g}, {init_upper[i]:g}]",
        )
    demo_path = _demo_path(path, index, entry.file)
    bounds = np.array([spec.input_bounds[name] for name in dynamics.input_names])
    us = read_demo_csv(demo_path, dynamics.input_names, Ts, bounds=bounds)
    T, rate = len(us) * Ts, spec.feedback.rate or DEFAULT_RATE
    if rate * T > MAX_DECAY_EXPONENT:  # the tube's e^{-lambda t} would underflow
        raise ScenarioError(
            f"demo lasts {T:g} s: its tube shrinks by e^-(rate T) = e^-{rate * T:.0f}, beyond"
            " float64 (overflow in every stage that scales by e^(rate t))",
            file=demo_path,
            expected=f"a flight of at most {MAX_DECAY_EXPONENT / rate:g} s at feedback.rate"
            f" = {rate:g} 1/s ({MAX_DECAY_EXPONENT:g} / rate)",
        )
    return Demo(name=Path(entry.file).stem, file=demo_path, x0=x0, us=us)


def _demo_path(path: Path, index: int, file: str) -> Path:
    """``file`` inside the scenario's folder; an absolute path, or one leading out of the folder
    (``..``, a symbolic link), is refused: a scenario may only read its own files."""
    folder = path.parent.resolve()
    try:
        target = (folder / file).resolve()
    except (RuntimeError, OSError):  # a symbolic-link loop (RuntimeError before Python 3.13)
        raise ScenarioError(
            "demo file is a symbolic-link loop",
            file=path,
            field=f"demos.{index}.file",
            found=file,
            expected="a CSV file inside the scenario folder",
        ) from None
    if Path(file).is_absolute() or not target.is_relative_to(folder):
        raise ScenarioError(
            "demo file outside the scenario folder",
            file=path,
            field=f"demos.{index}.file",
            found=file,
            expected=f"a path relative to {folder}, inside it (copy the CSV there)",
        )
    return path.parent / file


def check_demo_flight(scenario: Scenario, demo: Demo) -> None:
    """Simulate ``demo`` and raise if it enters Unsafe, leaves ``state_bounds`` or ends outside
    Goal (saying where/when)."""
    with np.errstate(over="ignore", invalid="ignore"):
        trajectory = simulate(scenario.dynamics, demo.x0, demo.us, scenario.Ts)
    if not np.all(np.isfinite(trajectory.dense_xs)):
        k = int(np.argmax(~np.all(np.isfinite(trajectory.dense_xs), axis=-1)))
        raise ScenarioError(
            f"demo '{demo.name}' diverges (non-finite state) at t = {trajectory.dense_ts[k]:.2f} s",
            file=demo.file,
        )
    positions = scenario.positions(trajectory.dense_xs)
    for name, region in scenario.unsafe.items():
        hits = np.flatnonzero(geometry.contains(region, positions))
        if hits.size:
            k = hits[0]
            X, Y = positions[k]
            raise ScenarioError(
                f"demo '{demo.name}' enters Unsafe set '{name}'"
                f" at t = {trajectory.dense_ts[k]:.2f} s,"
                f" position ({X:.3f}, {Y:.3f})",
                file=demo.file,
                expected="a flight that never touches Unsafe",
            )
    for name, (lower, upper) in scenario.state_bounds.items():
        values = trajectory.dense_xs[:, scenario.state_names.index(name)]
        outside = np.flatnonzero((values < lower) | (values > upper))
        if outside.size:
            k = outside[0]
            raise ScenarioError(
                f"demo '{demo.name}' leaves state_bounds.{name} = [{lower:g}, {upper:g}]"
                f" at t = {trajectory.dense_ts[k]:.2f} s ({name} = {values[k]:.4g})",
                file=demo.file,
                expected="a flight inside the state bounds",
            )
    if not scenario.in_goal(trajectory.final_state):
        X, Y = positions[-1]
        raise ScenarioError(
            f"demo '{demo.name}' does not end in Goal: at t = {trajectory.duration:.2f} s it is at"
            f" position ({X:.3f}, {Y:.3f}), state {np.round(trajectory.final_state, 3).tolist()}",
            file=demo.file,
            expected="a final state inside Goal",
        )
