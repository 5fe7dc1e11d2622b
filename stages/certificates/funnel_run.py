"""What every funnel stage of one run shares (``FunnelRun``), and the funnel stages themselves:
one funnel per trajectory (stage ``funnel``, ``stages.funnel``) and Init's coverage by their
initial ellipsoids (``coverage_funnel``, ``stages.coverage``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from pipeline.io.executor import Executor
from pipeline.io.progress import progress_bar
from pipeline.model.scenario import Scenario
from pipeline.model.simulate import Trajectory
from pipeline.numerics.funnel.check import EarlierDesign, Funnel
from pipeline.numerics.terminal.fit import TerminalTarget
from pipeline.results.coverage import CoverageResult
from pipeline.results.feedback import FeedbackResult
from pipeline.results.funnel import FunnelStageResult
from pipeline.results.optimize import OptimizeOptions
from pipeline.results.stage import Runner
from stages.certificates import Targets
from stages.certificates.targets import target_of
from stages.coverage import COVERAGE, CoverageInputs
from stages.funnel import FUNNEL, FunnelInputs


@dataclasses.dataclass(frozen=True, kw_only=True)
class FunnelRun:
    """What every funnel stage of one run shares.

    Attributes:
      feedback: the constant certificate (its metric assigns Init's cells to the starts).
      starts: (n,) per trajectory, the demonstrations' starts, which every nominal keeps.
      initial_radii: per trajectory, the constant ball's radius (I1), for a start owning no cell.
      options: the optimizer of the re-optimize rounds; quiet: no progress bars.
      targets: where the re-optimize rounds end the nominals (their ``scenario``) and the
        terminal controller the funnels must end in.
      feedback_period: the law is held every ``h`` s (0: continuous); the funnels must hold it.
    """

    scenario: Scenario
    runner: Runner
    executor: Executor
    feedback: FeedbackResult
    starts: Sequence[np.ndarray]
    initial_radii: Sequence[float]
    options: OptimizeOptions
    quiet: bool
    describe_coverage: Callable[[CoverageResult], str]
    targets: Targets | None = None
    feedback_period: float = 0.0

    @property
    def terminal(self) -> TerminalTarget | None:
        """The ellipsoid every funnel must end in (None: none)."""
        design = None if self.targets is None else self.targets.terminal
        return None if design is None else target_of(design)

    @property
    def optimized_scenario(self) -> Scenario:
        """The scenario the re-optimize rounds read (``Targets.scenario``)."""
        return self.scenario if self.targets is None else self.targets.scenario


def funnel_stages(
    run: FunnelRun,
    trajectories: Sequence[Trajectory],
    stage: str = "funnel",
    reuse: Sequence[tuple[Funnel, str | None] | None] | None = None,
    earlier: tuple[EarlierDesign, ...] = (),
) -> tuple[FunnelStageResult, CoverageResult]:
    """Stages ``stage`` (``funnel``, ``funnel_k`` in re-optimize round k, the held law's
    ``funnel_held...``, ``rounds.held_funnels``: one funnel per trajectory, on ``executor``;
    ``reuse[i]``, when given, is trajectory i's funnel from an earlier round around the same
    nominal, with its verdict then; ``earlier[i]``: how an earlier round designed its kept
    funnel, tried first) and ``coverage_<stage>`` (Init by the usable funnels' initial
    ellipsoids ``E_i(0)``, each in its own metric ``P_i[0]``)."""
    scenario = run.scenario
    with progress_bar(len(trajectories), "funnels", run.quiet) as advance:
        funnels: FunnelStageResult = run.runner.run(
            FUNNEL,
            FunnelInputs(
                scenario=scenario,
                names=tuple(d.name for d in scenario.demos),
                trajectories=tuple(trajectories),
                P=run.feedback.certified_tube.P,
                radii=np.asarray(run.initial_radii),
                terminal=run.terminal,
                feedback_period=run.feedback_period,
                earlier=earlier,
            ),
            name=stage,
            describe=lambda result: result.message,
            executor=run.executor,
            progress=advance,
            reuse=reuse,
        )
    return funnels, funnel_coverage(run, f"coverage_{stage}", funnels)


def funnel_coverage(run: FunnelRun, stage: str, funnels: FunnelStageResult) -> CoverageResult:
    """Stage ``stage``: Init covered by the usable funnels' initial ellipsoids ``E_i(0)``, each
    in its own metric ``P_i[0]`` at its level."""
    return run.runner.run(
        COVERAGE,
        CoverageInputs(
            scenario=run.scenario,
            metrics=funnels.starts,
            centers=np.array(run.starts),
            radii=funnels.levels,
            noun="funnel start",
        ),
        name=stage,
        describe=run.describe_coverage,
    )
