"""The certificate as a type: one strategy per certificate (``CERTIFICATES``), each owning the
stages that certify the optimized nominals its way and the emission of ``controller.json``.

- ``constant`` (``ConstantCertificate``): the feedback's one ``P``, ``K`` and each usable
  trajectory's robustness radius, ``safety-controller/1``;
- ``funnel`` (``stages.certificates.funnel.FunnelCertificate``): a funnel per trajectory, the
  re-optimize rounds against them, ``safety-controller/2``.

Before the shared optimize stage the orchestrator asks ``CERTIFICATES[name].targets(scenario)``
where the nominals must end (``Targets``: the funnel certificate of a ``terminal: hold``
scenario designs its terminal controller first and ends each nominal in its core; it first lets
them come to rest anywhere the controller fits, ``Targets.placing``, and places the controller
where they did, ``placed``, before the optimization the run keeps).
The orchestrator runs ``CERTIFICATES[name].ship(run)`` after the shared stages (feedback, radii,
coverage, optimize) and gets a ``Shipped``: the controller stage's result (or why none could be
certified) and what the summary and report read of the certificate. A new certificate (a robust
funnel) is a new strategy here with its ``name`` added to ``pipeline.model.scenario.
CertificateName``. This package may run several stages (the stage modules never import each
other); it does so through a ``pipeline.results.stage.Runner``, so that each is cached.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from pipeline.io.executor import Executor
from pipeline.model.scenario import CertificateName, Scenario
from pipeline.model.simulate import Trajectory, simulate
from pipeline.numerics.optimize.footprint import ConstraintMargins
from pipeline.numerics.terminal.design import TerminalDesign
from pipeline.numerics.verify.nominal import VERIFY_SUBSTEPS
from pipeline.results.controller import ControllerResult
from pipeline.results.coverage import CoverageResult
from pipeline.results.feedback import FeedbackResult
from pipeline.results.funnel import FunnelStageResult
from pipeline.results.optimize import OptimizeOptions, OptimizeResult
from pipeline.results.radius import RadiusResult
from pipeline.results.stage import Runner
from stages.controller import CONSTANT_CONTROLLER, ConstantControllerInputs
from stages.optimize import end_unshrunk


@dataclass(frozen=True, kw_only=True)
class Targets:
    """Where the optimize stages end the nominals.

    Attributes:
      scenario: the scenario they read: the run's, or (a hold run of the funnel certificate) a
        copy whose ``goal_bounds`` are the terminal ellipsoid's core box (``core`` states).
      terminal: the terminal controller designed before the funnels (``hold_design``), which
        they must end in; None: none yet (one is designed for the ends at emission).
      core: the states whose end bound is the nominal's own: the constant tube's extent does
        not shrink it (the funnels, which certify the end, must end inside ``terminal``).
      reserve: state or input name -> the room the nominal keeps from its bounds (at least),
        under a declared disturbance: what the funnels' feedback needs to reject it.
      placing: the position is left free where ``terminal`` would still fit: the orchestrator
        optimizes once more, to ``Certificate.placed``'s targets for where the nominals ended.
    """

    scenario: Scenario
    terminal: TerminalDesign | None = None
    core: tuple[str, ...] = ()
    reserve: Mapping[str, float] = field(default_factory=dict)
    placing: bool = False

    def margins(self, margins: ConstraintMargins) -> ConstraintMargins:
        """``margins`` without the tube's extent at ``T`` along the ``core`` states, and at least
        ``reserve`` from every input bound and every bound of the region the nominal stays in."""
        margins = end_unshrunk(self.scenario, margins, self.core)
        if not self.reserve:
            return margins
        names = self.scenario.input_names
        inputs = np.array([self.reserve.get(name, 0.0) for name in names])

        def widened(extents: Mapping[str, float], names: Iterable[str]) -> dict[str, float]:
            keys = set(extents) | (set(self.reserve) & set(names))
            return {k: max(extents.get(k, 0.0), self.reserve.get(k, 0.0)) for k in sorted(keys)}

        return dataclasses.replace(
            margins,
            input_margin=np.maximum(margins.input_margin, inputs),
            region_margin=widened(margins.region_margin, self.scenario.operating_region),
            state_extent=widened(margins.state_extent, self.scenario.state_bounds),
        )


@dataclass(frozen=True, kw_only=True)
class CertificateRun:
    """What a certificate's strategy is given: the run's shared results and where it runs.

    Attributes:
      starts: (n,) per demo; inputs: (N_i, m) per demo, the optimized nominals (a demo whose
        optimization failed keeps its own); trajectories: their simulations (``nominals``);
        radii: their robustness radii; r_required: the radius the optimizer kept.
      controller_path: where ``controller.json`` is staged; publish: names a staged file by
        where it is published (applied to the controller stage's result before it is stored).
      describe_coverage: the one line a coverage stage logs.
      targets: where the optimize stages were asked to end the nominals (``targets``).
    """

    scenario: Scenario
    runner: Runner
    executor: Executor
    feedback: FeedbackResult
    starts: Sequence[np.ndarray]
    optimized: OptimizeResult
    inputs: Sequence[np.ndarray]
    trajectories: Sequence[Trajectory]
    radii: Sequence[RadiusResult]
    r_required: float
    options: OptimizeOptions
    feedback_period: float
    controller_path: Path
    quiet: bool
    publish: Callable[[ControllerResult], ControllerResult]
    describe_coverage: Callable[[CoverageResult], str]
    targets: Targets | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.scenario.demos)


@dataclass(frozen=True, kw_only=True)
class Shipped:
    """What a certificate shipped.

    Attributes:
      controller: the controller stage's result; None when nothing could be certified
        (``failed_stage`` and ``failure`` say where and why).
      trajectories: the nominals the controller follows (the funnel certificate's re-optimized
        ones); constant_trajectories: with the funnel certificate, those of the constant one.
      funnels, funnel_coverage: the funnel certificate's funnels and their coverage of Init.
      report_stages: the stages (artifact names) of this certificate that the report shows.
    """

    controller: ControllerResult | None
    trajectories: Sequence[Trajectory]
    constant_trajectories: Sequence[Trajectory] | None = None
    funnels: FunnelStageResult | None = None
    funnel_coverage: CoverageResult | None = None
    report_stages: tuple[str, ...] = ()
    failed_stage: str = ""
    failure: str = ""


class Certificate(Protocol):
    """A certificate's strategy."""

    @property
    def name(self) -> CertificateName:
        """What the scenario file and ``--certificate`` call it."""
        ...

    def targets(self, scenario: Scenario, period: float = 0.0) -> Targets:
        """Where the optimize stages must end the nominals (for the law held every ``period``
        s, 0: continuous)."""
        ...

    def placed(
        self, scenario: Scenario, first: Targets, ends: Sequence[np.ndarray], period: float = 0.0
    ) -> Targets:
        """The targets of the second optimization when ``first.placing``: ``ends`` ((n,) each)
        are where the first one's successful nominals ended."""
        ...

    def ship(self, run: CertificateRun) -> Shipped:
        """Run this certificate's stages and emit ``controller.json``."""
        ...


def nominals(
    scenario: Scenario, starts: Sequence[np.ndarray], inputs: Sequence[np.ndarray]
) -> list[Trajectory]:
    """The nominal of each start ``(n,)`` under its inputs ``(N_i, m)``, on the dense grid the
    radius and funnel stages bound between samples (``VERIFY_SUBSTEPS``)."""
    return [
        simulate(scenario.dynamics, x0, us, scenario.Ts, substeps=VERIFY_SUBSTEPS)
        for x0, us in zip(starts, inputs, strict=True)
    ]


@dataclass(frozen=True)
class ConstantCertificate:
    """One contraction metric ``P`` and gain ``K`` for all time: each trajectory with a
    positive robustness radius is shipped with it (``safety-controller/1``)."""

    name: CertificateName = "constant"

    def targets(self, scenario: Scenario, period: float = 0.0) -> Targets:
        return Targets(scenario=scenario)  # Goal as the scenario states it

    def placed(
        self, scenario: Scenario, first: Targets, ends: Sequence[np.ndarray], period: float = 0.0
    ) -> Targets:
        return first  # never placing

    def ship(self, run: CertificateRun) -> Shipped:
        usable = [i for i, r in enumerate(run.radii) if r.radius > 0]
        tube = run.feedback.certified_tube
        controller = run.runner.run(
            CONSTANT_CONTROLLER,
            ConstantControllerInputs(
                scenario=run.scenario,
                K=tube.K,
                P=tube.P,
                rate=run.feedback.rate,
                names=tuple(run.names[i] for i in usable),
                starts=tuple(run.starts[i] for i in usable),
                inputs=tuple(run.inputs[i] for i in usable),
                radii=tuple(run.radii[i].radius for i in usable),
                radius_floor=run.r_required,
                feedback_period=run.feedback_period,
                path=run.controller_path,
            ),
            rerun=True,  # always written from this run's certified results
            describe=lambda result: result.message,
            finish=run.publish,
        )
        return Shipped(controller=controller, trajectories=run.trajectories)


def _certificates() -> Mapping[CertificateName, Certificate]:
    from stages.certificates.funnel import FunnelCertificate

    return {"constant": ConstantCertificate(), "funnel": FunnelCertificate()}


CERTIFICATES: Mapping[CertificateName, Certificate] = _certificates()
