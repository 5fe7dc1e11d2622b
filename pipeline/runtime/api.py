"""The Python API: ``pipeline.synthesize`` (re-exported lazily by ``pipeline/__init__.py``)::

    import pipeline
    result = pipeline.synthesize("double_integrator", samples=1000)
    result.verdict, result.outputs.folder
    index, ratio = result.controller.select(x0)  # the certified controller

The library prints nothing: each stage logs one line on the ``pipeline`` logger (``logging``
INFO; the optimizer's iteration logs at DEBUG). ``logging.basicConfig(level=logging.INFO)``
shows them; the command line (``pipeline.runtime.cli``) is this function plus that.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.runtime.options import RunOptions
from pipeline.runtime.synthesis import Synthesis

if TYPE_CHECKING:
    from pipeline.model.scenario import Scenario


def synthesize(
    scenario: str | Path | Scenario,
    *,
    out: str | Path | None = None,
    certificate: str | None = RunOptions.certificate,
    samples: int = RunOptions.samples,
    seed: int = RunOptions.seed,
    executor: str | None = RunOptions.executor,
    jobs: int = RunOptions.jobs,
    method: str | None = RunOptions.method,
    search: str = RunOptions.search,
    stress: bool = RunOptions.stress,
    force: bool = RunOptions.force,
    feedback_period: float | None = RunOptions.feedback_period,
) -> Synthesis:
    """Synthesize and certify a safety controller for ``scenario``, then validate it.

    Args:
      scenario: a name (``./scenarios/NAME``, else the shipped scenario of that name), the
        path of a scenario folder or its ``scenario.yaml``, or a ``Scenario`` (from
        ``load_scenario``, or another one made from it by ``dataclasses.replace(scenario,
        clearance=0.5)``: a parameter sweep; each stage's key covers every field it reads, so a
        changed field recomputes what depends on it).
      out: the output folder (default ``./reports/NAME`` under the current directory); stages
        whose inputs did not change since the last run there are reused.
      certificate: ``"constant"`` (one contraction metric ``P`` and gain ``K`` for all of
        time, the paper's tube) or ``"funnel"`` (a time-varying gain ``K_i[k]`` and metric
        ``P_i[k]`` per trajectory, ``safety-controller/2``); default: the scenario's
        ``certificate``.
      samples, seed: the Monte Carlo closed-loop runs and their seed.
      executor, jobs: where parallel work runs (``None``/``"local"``, ``"dask-local"``,
        ``"dask://HOST:PORT"``) and with how many worker processes.
      method, search: the optimizer (``"gd"``, ``"lbfgs"``; default: the scenario's
        ``optimizer``) and horizon search.
      stress: also run the stress test (wind, noise; reported, never certified).
      force: rerun every stage.
      feedback_period: the period ``h`` (s) of a zero-order-hold feedback to certify (0: the
        feedback acts continuously); must divide the scenario's sampling time; default: the
        scenario's ``feedback_period``.

    Returns a ``Synthesis`` (verdict, claims, controller, per-demo table, files written). Bad
    input raises ``pipeline.UserError`` (``ScenarioError`` for the scenario) before any work;
    a stage that fails gives ``Verdict.FAILED`` with the stage and the error in ``message``.
    """
    options = RunOptions(
        certificate=certificate,
        samples=samples,
        seed=seed,
        executor=executor,
        jobs=jobs,
        method=method,
        search=search,
        stress=stress,
        force=force,
        feedback_period=feedback_period,
    )
    from pipeline.model.scenario import Scenario, load_scenario

    # a mistake in the scenario is reported before the heavy imports (~2 s: numerics, stages)
    loaded = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    from pipeline.runtime.orchestrator import run_synthesis

    return run_synthesis(loaded, out=None if out is None else Path(out), options=options)
