"""What a synthesis returns: ``Synthesis``, a frozen result naming the verdict, the claims with
their kinds, the controller, the per-demo table and the files written (``Outputs``).

Built by ``pipeline.runtime.orchestrator``; the public entry point is ``pipeline.synthesize``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.controller import Controller
from pipeline.reporting.summary import Claim, DemoSummary, Summary, Verdict


@dataclass(frozen=True, kw_only=True)
class Outputs:
    """The files of a run, all under ``folder`` (``./reports/NAME`` unless ``out`` was given).

    Attributes:
      controller: ``controller.json`` when the run certified it, else ``None`` (a run that does
        not certify renames it ``controller.stale.json``).
      report_html, report_pdf: the reports (``None`` when the run failed before writing them).
      artifacts: the stage cache (one ``STAGE.json`` + ``.npz`` per stage).
    """

    folder: Path
    summary: Path
    controller: Path | None
    report_html: Path | None
    report_pdf: Path | None
    artifacts: Path

    @classmethod
    def of(cls, folder: Path) -> Outputs:
        """The files that exist in ``folder`` now."""

        def existing(name: str) -> Path | None:
            return folder / name if (folder / name).is_file() else None

        return cls(
            folder=folder,
            summary=folder / "summary.json",
            controller=existing("controller.json"),
            report_html=existing("report.html"),
            report_pdf=existing("report.pdf"),
            artifacts=folder / "artifacts",
        )


@dataclass(frozen=True, kw_only=True)
class Synthesis:
    """The result of ``pipeline.synthesize``.

    Attributes:
      verdict: ``Verdict.CERTIFIED_AND_VALIDATED`` when the certificate holds and Monte Carlo
        found no failure; ``success`` says exactly that.
      message: the verdict line with its reasons (or, for a failed run, the stage and error).
      claims: each claim with its kind (certified, statistically validated,
        falsification-searched, not established); empty for a failed run.
      controller: the certified controller (``pipeline.controller.Controller``, read back from
        ``controller.json`` as written), or ``None`` when the run did not certify one.
      demos: the per-demo table (duration, clearance, radius before and after optimization).
      summary: everything ``summary.json`` holds (``None`` for a failed run).
      outputs: the files written.
    """

    scenario: str
    verdict: Verdict
    success: bool
    message: str
    claims: tuple[Claim, ...]
    controller: Controller | None
    demos: tuple[DemoSummary, ...]
    summary: Summary | None
    outputs: Outputs

    @property
    def exit_code(self) -> int:
        """The command line's exit code: 0 certified and validated, 1 otherwise."""
        return 0 if self.success else 1
