"""Inputs for every declared stage on a small double integrator (two demos), each stage's
result computed once, and a ``Scenario`` that refuses (or records) reads of its fields, for
``tests/test_stage_conformance.py``."""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.artifacts import file_hash
from pipeline.model.scenario import Scenario, load_scenario
from pipeline.model.schema import StressSpec
from pipeline.numerics.terminal.design import hold_design
from pipeline.numerics.terminal.fit import TerminalTarget
from pipeline.results.stage import FileInput, Stage, StageInputs
from stages.certificates import nominals
from stages.controller import (
    CONSTANT_CONTROLLER,
    FUNNEL_CONTROLLER,
    ConstantControllerInputs,
    FunnelControllerInputs,
)
from stages.coverage import COVERAGE, COVERING_RADIUS, CoverageInputs, CoveringRadiusInputs
from stages.feedback import FEEDBACK, FeedbackInputs
from stages.funnel import FUNNEL, FunnelInputs
from stages.montecarlo import MONTECARLO, MonteCarloInputs
from stages.optimize import (
    OPTIMIZE,
    REOPTIMIZE,
    ConstraintMargins,
    OptimizeInputs,
    OptimizeOptions,
    ReoptimizeInputs,
)
from stages.radius import RADIUS, RadiusInputs
from stages.stress import STRESS, StressInputs

SCENARIO_FIELDS = frozenset(f.name for f in dataclasses.fields(Scenario))


class UndeclaredRead(AssertionError):
    """A stage read a field of the scenario that its inputs type does not declare."""


def guarded(scenario: Scenario, allowed: Collection[str], seen: set[str] | None = None) -> Scenario:
    """A copy of ``scenario`` whose fields outside ``allowed`` raise ``UndeclaredRead`` when read
    (directly, or through a property or method such as ``n`` or ``in_goal``); with ``seen``,
    every field read is recorded there instead."""
    allowed = frozenset(allowed)

    def __getattribute__(self: Any, name: str) -> Any:
        if name in SCENARIO_FIELDS:
            if seen is not None:
                seen.add(name)
            elif name not in allowed:
                raise UndeclaredRead(f"the stage read scenario.{name}, which it does not declare")
        return object.__getattribute__(self, name)

    cls = type("GuardedScenario", (Scenario,), {"__getattribute__": __getattribute__})
    copy = object.__new__(cls)
    for name in SCENARIO_FIELDS:
        object.__setattr__(copy, name, getattr(scenario, name))
    return copy


def with_scenario(inputs: StageInputs, scenario: Scenario) -> StageInputs:
    return dataclasses.replace(inputs, scenario=scenario)  # type: ignore[call-arg]


@dataclasses.dataclass
class StageCase:
    """A stage, its inputs, its result on them, what its function was called with and what it
    read of the scenario without declaring it."""

    stage: Stage[Any, Any]
    inputs: StageInputs
    result: Any
    context: dict[str, Any]
    undeclared: str | None  # the first undeclared read of the scenario, if any

    @property
    def id(self) -> str:
        return f"{self.stage.name}:{self.stage.inputs.__name__}"


def small_scenario() -> Scenario:
    """double_integrator with two demos and a stress section (the shipped one has none)."""
    scenario = load_scenario("double_integrator", check_demos=False)
    stress = StressSpec(disturbance={"vX": 0.05}, measurement_noise={"X": 0.001})
    return dataclasses.replace(
        scenario,
        demos=scenario.demos[:2],
        spec=scenario.spec.model_copy(update={"stress": stress}),
    )


def stage_cases(folder: Path) -> Iterator[StageCase]:
    """Every declared stage but ``report`` (``tests/test_stage_conformance.py`` builds that one
    from a finished run), in the order of a run, each run once on the small scenario; files
    are written in ``folder``."""
    scenario = small_scenario()

    def case(stage: Stage[Any, Any], inputs: StageInputs, **context: Any) -> StageCase:
        """Run once, on a scenario that refuses the fields the inputs do not declare."""
        declared = type(inputs).scenario_fields
        try:
            result = stage(with_scenario(inputs, guarded(scenario, declared)), **context)
            undeclared = None
        except UndeclaredRead as error:  # the test names it; the other checks go on
            result, undeclared = stage(inputs, **context), str(error)
        return StageCase(stage, inputs, result, context, undeclared)

    feedback = case(FEEDBACK, FeedbackInputs(scenario=scenario))
    yield feedback
    tube = feedback.result.certified_tube
    starts = tuple(d.x0 for d in scenario.demos)
    demo_trajectories = tuple(nominals(scenario, starts, [d.us for d in scenario.demos]))
    radius = case(
        RADIUS, RadiusInputs(scenario=scenario, tube=tube, trajectories=demo_trajectories)
    )
    yield radius
    radii = np.array([max(r.radius, 0.0) for r in radius.result])
    centers = np.array(starts)
    yield case(
        COVERAGE, CoverageInputs(scenario=scenario, metrics=tube.P, centers=centers, radii=radii)
    )
    r_d = feedback.result.required_radius(scenario.clearance)
    yield case(
        COVERING_RADIUS,
        CoveringRadiusInputs(
            scenario=scenario, P=tube.P, centers=centers, upper=float(radii.max())
        ),
    )
    options = OptimizeOptions(method="lbfgs")
    margins = ConstraintMargins.of_tube(tube, r_d)
    optimize = case(OPTIMIZE, OptimizeInputs(scenario=scenario, margins=margins, options=options))
    yield optimize
    inputs = tuple(t.u for t in optimize.result.trajectories)
    final = tuple(nominals(scenario, starts, inputs))
    names = tuple(d.name for d in scenario.demos)
    design = hold_design(scenario)  # a hold run's terminal controller, designed first
    everywhere = TerminalTarget(x_eq=design.x_eq, P=design.P, level=1e6)  # holds any end
    funnel = case(
        FUNNEL,
        FunnelInputs(
            scenario=scenario,
            names=names,
            trajectories=final,
            P=tube.P,
            radii=np.full(2, r_d),
            terminal=everywhere,
        ),
    )
    yield funnel
    yield case(
        COVERAGE,
        CoverageInputs(
            scenario=scenario,
            metrics=funnel.result.starts,
            centers=centers,
            radii=funnel.result.levels,
            noun="funnel start",
        ),
    )
    yield case(
        REOPTIMIZE,
        ReoptimizeInputs(
            scenario=scenario,
            trajectories=optimize.result.trajectories,
            funnels=funnel.result.funnels,
            options=options,
            shortest=tuple(int(0.9 * len(u)) for u in inputs),
        ),
    )
    yield case(
        FUNNEL_CONTROLLER,
        FunnelControllerInputs(
            scenario=scenario,
            names=names,
            trajectories=final,
            funnels=funnel.result.funnels,
            feedback_period=0.0,
            path=folder / "funnel" / "controller.json",
            terminal=design,
        ),
    )
    path = folder / "controller.json"
    yield case(
        CONSTANT_CONTROLLER,
        ConstantControllerInputs(
            scenario=scenario,
            K=tube.K,
            P=tube.P,
            rate=feedback.result.rate,
            names=names,
            starts=starts,
            inputs=inputs,
            radii=(r_d, r_d),
            radius_floor=r_d,
            feedback_period=0.0,
            path=path,
        ),
    )
    controller = FileInput(path=path, sha256=file_hash(path))
    yield case(
        MONTECARLO, MonteCarloInputs(scenario=scenario, controller=controller, samples=40, seed=1)
    )
    yield case(STRESS, StressInputs(scenario=scenario, controller=controller, seed=1))
