"""The result types of stage ``feedback`` (``stages/feedback.py``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.numerics.tube.feedback_search import FeedbackTuning
from pipeline.numerics.tube.geometry import Tube
from pipeline.results.base import Result


@dataclass(frozen=True, kw_only=True)
class FeedbackResult(Result):
    """The certified feedback and its tube (``pipeline.numerics.tube.geometry``).

    Attributes:
      K: (m, n) gain of ``u = u_ref + K (x - x_ref)``; None if no gain could be designed.
      P: (n, n) contraction metric; None unless ``success``.
      rate: lambda (1/s): ``||e(t)||_P <= exp(-lambda t) ||e(0)||_P`` inside ``region``.
      vertices: (V, n, n+m) the Jacobian hull's vertices ``[A_i B_i]``.
      solver_status: cvxpy status of the chosen design (or of each try on failure).
      region: name -> (lower, upper) box of states/inputs where the certificate holds.
      tube: the certified tube's geometry (None unless ``success``); the per-radius quantities
        and the methods below read it.
      gain: "lqr" or "joint", the design that was kept.
      certified_margin: largest eigenvalue of ``P^-1/2 (A_cl^T P + P A_cl + 2 lambda P) P^-1/2``
        over the vertices (< 0 for a certificate).
      objective: the design objective's value.
      hull: how each block of the Jacobian hull was enclosed.
      tuning: what the search chose (``pipeline.numerics.tube.feedback_search``) when the scenario's
        ``feedback.tune`` is set: the design is for ``applied_to(scenario)``; None otherwise.
    """

    K: FloatArray | None
    P: FloatArray | None
    rate: float
    vertices: FloatArray = field(repr=False)
    solver_status: str
    region: Mapping[str, tuple[float, float]]
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    tube: Tube | None = field(default=None, repr=False)
    success: bool
    message: str
    gain: str = ""
    certified_margin: float = float("nan")
    objective: float = float("nan")
    hull: tuple[str, ...] = ()
    tuning: FeedbackTuning | None = None

    def applied_to(self, scenario: Scenario) -> Scenario:
        """The scenario this design is for: ``scenario`` itself, or with the tuned operating
        region, rate and weights (every later stage and the final check read them there)."""
        if self.tuning is None:
            return scenario
        return dataclasses.replace(
            scenario,
            operating_region=dict(self.tuning.region),
            feedback=scenario.feedback.model_copy(
                update={
                    "rate": self.tuning.rate,
                    "state_weights": list(self.tuning.state_weights),
                    "input_weights": list(self.tuning.input_weights),
                }
            ),
        )

    @property
    def certified_tube(self) -> Tube:
        """The tube; raises if the feedback was not certified."""
        if not self.success or self.tube is None:
            raise ValueError(f"the feedback was not certified: {self.message}")
        return self.tube

    @property
    def input_margin_per_radius(self) -> FloatArray:
        """(m,) ``||K_j P^-1/2||``: ``|K_j e| <= r`` times this."""
        return self.certified_tube.input_margin_per_radius

    @property
    def state_extent_per_radius(self) -> FloatArray:
        """(n,) ``sqrt((P^-1)_ii)``: ``|e_i| <= r`` times this."""
        return self.certified_tube.state_extent_per_radius

    @property
    def position_shape(self) -> FloatArray:
        """(2, 2) ``C P^-1 C^T``: the position projection of the unit ball."""
        return self.certified_tube.position_shape

    def required_radius(self, clearance: float) -> float:
        """``r_d``: see ``Tube.required_radius``."""
        return self.certified_tube.required_radius(clearance)

    def position_extent(self, radius: float) -> float:
        """See ``Tube.position_extent``."""
        return self.certified_tube.position_extent(radius)

    def input_margin(self, radius: float) -> FloatArray:
        """(m,) see ``Tube.input_margin``."""
        return self.certified_tube.input_margin(radius)

    def region_extent(self, radius: float) -> dict[str, float]:
        """See ``Tube.region_extent``."""
        return self.certified_tube.region_extent(radius)

    def slice_semi_axes(self, radius: float, index: tuple[int, ...]) -> FloatArray:
        """See ``Tube.slice_semi_axes``."""
        return self.certified_tube.slice_semi_axes(radius, index)
