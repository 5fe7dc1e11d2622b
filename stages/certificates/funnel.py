"""The funnel certificate (issue 16): the funnel stages around the optimized nominals
(``funnel_run``), then the re-optimize rounds against the funnels (``rounds``: part 4, a
trust-region continuation that keeps Init covered), and the funnel controller
(``safety-controller/2``). For a law held every ``h`` s the rounds choose the nominals with the
continuous law's funnels and the held law's are designed around the nominals chosen
(``rounds.held_funnels``). In a ``terminal: hold`` scenario the nominals end where
``targets`` says, and every funnel in the terminal controller's ellipsoid (issue 29 item 3).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from pipeline.model.scenario import CertificateName, Scenario
from stages.certificates import CertificateRun, Shipped, Targets
from stages.certificates.funnel_run import FunnelRun, funnel_stages
from stages.certificates.rounds import Rounds, held_funnels, reoptimize_rounds
from stages.certificates.targets import placed_targets, rest_targets
from stages.controller import FUNNEL_CONTROLLER, FunnelControllerInputs

log = logging.getLogger("pipeline.certificates")  # the run's logger: its lines are shown


@dataclasses.dataclass(frozen=True)
class FunnelCertificate:
    """A time-varying gain ``K_i[k]`` and metric ``P_i[k]`` per trajectory: the funnel stages,
    the re-optimize rounds, and the controller of the certified funnels."""

    name: CertificateName = "funnel"

    def targets(self, scenario: Scenario, period: float = 0.0) -> Targets:
        return rest_targets(scenario, period)

    def placed(
        self, scenario: Scenario, first: Targets, ends: Sequence[np.ndarray], period: float = 0.0
    ) -> Targets:
        return placed_targets(scenario, first, ends, period)

    def ship(self, run: CertificateRun) -> Shipped:
        # Each funnel is asked to hold its start's cell of Init (stage funnel); a start that
        # owns no cell asks for the constant ball's slice (I1), at the radius the optimizer kept
        # when its trajectory has no robustness radius.
        funnel_run = FunnelRun(
            scenario=run.scenario,
            runner=run.runner,
            executor=run.executor,
            feedback=run.feedback,
            starts=run.starts,
            initial_radii=[r.radius if r.radius > 0 else run.r_required for r in run.radii],
            options=run.options,
            quiet=run.quiet,
            describe_coverage=run.describe_coverage,
            targets=run.targets,
            feedback_period=run.feedback_period,
        )
        trajectories = list(run.trajectories)
        # a held law's funnels cost 2-3x the continuous law's (a held check that fails, then a
        # design with (I6')'s push): the rounds choose the nominals with the continuous law's
        # funnels, and the held law's are designed around the nominals chosen (``held_funnels``)
        held = funnel_run.feedback_period > 0
        search = funnel_run
        if held:
            search = dataclasses.replace(funnel_run, feedback_period=0.0)
            log.info(
                f"[funnel] the law is held every {funnel_run.feedback_period:g} s: the rounds "
                "choose the nominals with the continuous law's funnels, the held law's are then "
                "designed around them (funnel_held)"
            )
        funnels, coverage = funnel_stages(search, trajectories)
        if not funnels.usable:
            failure = f"no funnel certified: {funnels.message}"
            return Shipped(
                controller=None, trajectories=trajectories, failed_stage="funnel", failure=failure
            )
        rounds = reoptimize_rounds(
            search, Rounds.first(run.optimized, run.inputs, trajectories, funnels, coverage)
        )
        if held:
            rounds = held_funnels(funnel_run, rounds, run)
        final, funnels, coverage = list(rounds.trajectories), rounds.funnels, rounds.coverage
        if not funnels.usable:
            failure = f"no funnel certified for the held law: {funnels.message}"
            return Shipped(
                controller=None, trajectories=final, failed_stage="funnel_held", failure=failure
            )
        usable = funnels.usable
        controller = run.runner.run(
            FUNNEL_CONTROLLER,
            FunnelControllerInputs(
                scenario=run.scenario,
                names=tuple(run.names[i] for i in usable),
                trajectories=tuple(final[i] for i in usable),
                funnels=tuple(funnels.funnels[i] for i in usable),
                feedback_period=run.feedback_period,
                path=run.controller_path,
                terminal=None if run.targets is None else run.targets.terminal,
            ),
            rerun=True,  # always written from this run's certified results
            describe=lambda result: result.message,
            finish=run.publish,
        )
        return Shipped(
            controller=controller,
            trajectories=final,
            constant_trajectories=trajectories,
            funnels=funnels,
            funnel_coverage=coverage,
            report_stages=("funnel", "coverage_funnel", *(("funnel_held",) if held else ())),
        )
