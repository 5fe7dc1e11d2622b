"""What a run settles before its stages: the certificate it ships, the feedback period checked
against it, the scenario's fields as a cache key, and the feedback's tube at the held law's rate.
No stage is imported here (only the orchestrator imports stages); stage results are read by
their fields.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import typing
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from pipeline.io.artifacts import inputs_key
from pipeline.io.errors import UserError
from pipeline.model.limits import MIN_FEEDBACK_PERIOD, divides, periods_allowed
from pipeline.model.scenario import CertificateName, Scenario
from pipeline.model.scenario_data import Unkeyable, plain, scenario_data
from pipeline.numerics.tube.sampled import HeldRate, held_rate
from pipeline.runtime.options import RunOptions

if TYPE_CHECKING:  # stage result types: only the orchestrator imports stages
    from pipeline.results.feedback import FeedbackResult


def held_feedback(
    scenario: Scenario, feedback: FeedbackResult, period: float
) -> tuple[FeedbackResult, HeldRate]:
    """The feedback with its tube at the held law's rate ``lambda_h`` (``--feedback-period``)."""
    n = len(scenario.state_names)
    A, B = feedback.vertices[:, :, :n], feedback.vertices[:, :, n:]
    tube = feedback.certified_tube
    held = held_rate(tube.P, tube.K, A, B, feedback.rate, period)
    if not held.success:
        return feedback, held
    held_tube = dataclasses.replace(tube, rate=held.held_rate)
    return dataclasses.replace(feedback, rate=held.held_rate, tube=held_tube), held


def check_period(
    scenario: Scenario,
    period: object,
    certificate: CertificateName,
    source: str = "--feedback-period",
) -> None:
    """The law's period (``source``: ``--feedback-period``, or the scenario's field) must be 0
    or at least ``MIN_FEEDBACK_PERIOD`` and divide the sampling time (``u_ref`` switches at
    samples, and a held law's windows must not straddle them), with either certificate (the
    constant one's held rate, ``pipeline.numerics.tube.sampled``; the funnel's (I6),
    ``funnel.law``). A scenario file's value was checked on loading; this also catches one set
    by ``dataclasses.replace``, of any type (a ``bool`` or text is refused, as by
    ``RunOptions``)."""
    expected = "expected " + periods_allowed(scenario.Ts, whose="the scenario's ")
    if isinstance(period, bool) or not isinstance(period, numbers.Real):
        raise UserError(f"{source}: found {period!r}; {expected}")
    try:
        seconds = float(period)
    except OverflowError:  # an int beyond float64
        seconds = math.inf
    if seconds == 0:
        return
    if not MIN_FEEDBACK_PERIOD <= seconds < math.inf or not divides(seconds, scenario.Ts):
        raise UserError(f"{source}: found {seconds:g} s; {expected}")


def period_source(scenario: Scenario, options: RunOptions) -> str:
    """Where this run's period comes from, for ``check_period``'s message: the option, the
    scenario file's field, or (a ``Scenario`` made by ``dataclasses.replace``) the object's."""
    if options.feedback_period is not None:
        return "--feedback-period"
    period, written = scenario.feedback_period, scenario.spec.feedback_period
    if isinstance(period, float) and period == written:
        return f"{scenario.path}: feedback_period"
    return f"the Scenario's feedback_period (set in Python; {scenario.path} says {written:g})"


def check_uncertainty(scenario: Scenario, certificate: str) -> None:
    """Every declared bound is held by the certificate that runs, or the run is refused: the
    constant certificate holds no uncertainty (its contraction is of the exact model); the
    funnel certificate holds it (``stages.funnel``, re-checked by certify)."""
    if scenario.uncertainty.empty:
        return
    if certificate == "constant":
        raise UserError(
            f"{scenario.path}: uncertainty: declared, but the constant certificate holds the exact "
            "model only; expected certificate: funnel (robust funnels hold the declared bounds) "
            "or no uncertainty block"
        )


def certificate_of(scenario: Scenario, options: RunOptions) -> CertificateName:
    """The certificate this run ships: ``--certificate``, else the scenario's."""
    name = options.certificate or scenario.certificate
    if name not in typing.get_args(CertificateName):
        raise UserError(
            f"--certificate: found {name!r}; expected one of "
            f"{', '.join(typing.get_args(CertificateName))}"
        )
    return typing.cast(CertificateName, name)


def period_of(scenario: Scenario, options: RunOptions) -> float:
    """The period ``h`` (s) the law is held for in this run (0: continuous feedback):
    ``--feedback-period``, else the scenario's ``feedback_period``."""
    if options.feedback_period is None:
        return scenario.feedback_period
    return options.feedback_period


def method_of(scenario: Scenario, options: RunOptions) -> str:
    """The optimizer this run uses: ``--method``, else the scenario's ``optimizer``."""
    return options.method or scenario.optimizer


# The scenario's fields that the numerical stages keyed on ``scenario_key(scenario,
# *NOT_NUMERICAL)`` do not read: the description and stress settings (the report, the stress
# test), the optimizer (optimize keys the one it runs: --method, else the scenario's) and the
# demos (the stages get their starts and inputs as arguments, which their keys carry; optimize,
# the one stage that reads scenario.demos, keys their names, starts and inputs too).
NOT_NUMERICAL = ("description", "stress", "optimizer", "demos")


def check_keyable(scenario: Scenario) -> None:
    """Every field of ``scenario`` has an exact encoding for the stages' cache keys
    (``scenario_data``, then ``inputs_key``): a value set by ``dataclasses.replace`` of another
    type (a ``fractions.Fraction``, a ``decimal.Decimal``, an array of objects, a float
    ``Enum``) is refused before any work, naming the field, instead of failing the first
    stage."""
    expected = "expected a float, an int, a string, an array of numbers or what load_scenario gives"
    try:
        data = scenario_data(scenario)
    except Unkeyable as error:
        raise UserError(
            f"scenario field {error.where}: found a {error.type_name}; {expected}"
        ) from None
    for name, value in data.items():
        try:
            inputs_key(value)
        except TypeError as error:  # plain data the exact encoding still refuses
            raise UserError(f"scenario field {name}: {error}; {expected}") from None


def scenario_key(scenario: Scenario, *exclude: str) -> str:
    """A hash of every field of the ``Scenario`` the stages read (``scenario_data``: arrays,
    polygons, the dynamics' expressions, the parsed file...), not of the file's bytes, without
    ``exclude`` (names of fields of the scenario or of its ``spec``). ``dataclasses.replace(
    scenario, clearance=0.25)`` has another key than ``scenario``."""
    return inputs_key(scenario_data(scenario, exclude))


def scenario_slice(scenario: Scenario, names: Sequence[str]) -> dict[str, Any]:
    """Field name -> plain data (``pipeline.model.scenario_data.plain``) for the fields
    ``names`` of ``scenario`` that a stage declares it reads (``StageInputs.scenario_fields``);
    a name that is no field of a ``Scenario`` raises ``ValueError``."""
    known = {f.name for f in dataclasses.fields(scenario)}
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ValueError(f"scenario_fields names no field of a Scenario: {unknown}")
    return {name: plain(getattr(scenario, name), name) for name in names}
