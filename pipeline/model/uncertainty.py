"""The uncertainty a scenario declares: what every certificate must hold against.

The scenario file's ``uncertainty:`` block (``pipeline.model.schema.UncertaintySpec``) declares

- ``disturbance``: a box ``|w_i| <= disturbance_i`` on an additive term in the named states'
  derivatives, ``x' = f(x, u) + w(t)``, acting at every instant: ``w`` is any measurable signal
  inside the box (a gust; states not named get 0);
- ``disturbance_ellipsoid``: semi-axes ``a_i > 0`` of an axis-aligned ellipsoid ``sum (w_i /
  a_i)^2 <= 1`` over the named states, a further additive term ``g`` (a gust of any
  direction) added to the box's ``d``. Every certificate holds the box ``|w_i| <= d_i + a_i``
  (``disturbance`` below, rounded up): each term ``(g_i / a_i)^2`` of the sum is at most 1, so
  ``|g_i| <= a_i`` and ``d + g`` lies in that box (sound; up to ``sqrt(k)`` wider than the
  ellipsoid along a diagonal of ``k`` states). The Monte Carlo draws from that box too;
- ``parameters``: an interval for any of the scenario's parameters. The true value is unknown
  and constant during a flight (or varying, the bound below does not use its rate). The nominals
  are flown with the file's (nominal) values ``p0``; a certificate holds the difference
  ``f(x, u, p) - f(x, u, p0)`` as a second additive term, bounded over its tube and the
  parameter box by outward-rounded interval arithmetic (``pipeline.numerics.uncertainty``).

- ``measurement``: a box ``|eta_i| <= measurement_i`` on the error of the state the feedback
  sees, ``x_meas = x + eta``, at every instant: ``eta`` is any measurable signal inside the box
  (states not named are measured exactly). The certificates are about the true state ``x``; the
  law sees ``x + eta`` (``pipeline.numerics.funnel.law`` (I7), ``pipeline.numerics.terminal.
  design`` (T5)). ``stress.measurement_noise`` (Gaussian, unbounded) stays uncertified.

An empty block (or none) is the exact model: every certificate reduces to its exact-model form.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.model.frozen import freeze_fields, reduce_fields


@dataclass(frozen=True, kw_only=True, eq=False)
class Uncertainty:
    """A scenario's declared uncertainty (``n`` states, ``q`` uncertain parameters).

    Attributes:
      disturbance: (n,) ``>= 0``, the box half-width of the additive term in each state's
        derivative (0 for states not named) that every certificate holds: the declared box
        plus ``ellipsoid``'s semi-axes (``held_box``).
      ellipsoid: (n,) ``>= 0``, the declared ellipsoid's semi-axes (0 for states outside it;
        omitted: zeros), already inside ``disturbance``.
      declared_box: (n,) ``>= 0``, the box as declared, for people (no certificate reads it):
        ``disturbance`` itself without an ellipsoid; given by the loader with one (omitted:
        ``disturbance - ellipsoid``, to the last bit of the subtraction).
      measurement: (n,) ``>= 0``, the box half-width of the error on each state as the feedback
        measures it (0 for states not named; omitted: zeros).
      parameter_names: (q,) the uncertain parameters, in the file's order.
      parameter_lower, parameter_upper: (q,) their intervals; parameter_nominal: (q,) the values
        the nominal model uses, inside the intervals.
      parametric: ``f(x, v)`` with ``v = (u, p)``: the scenario's dynamics with the ``q``
        uncertain parameters as trailing inputs (other parameters substituted); ``None`` when
        ``q = 0``.
    """

    disturbance: FloatArray
    parameter_names: tuple[str, ...] = ()
    parameter_lower: FloatArray = field(default_factory=lambda: np.zeros(0))
    parameter_upper: FloatArray = field(default_factory=lambda: np.zeros(0))
    parameter_nominal: FloatArray = field(default_factory=lambda: np.zeros(0))
    parametric: Dynamics | None = field(default=None, repr=False)
    measurement: FloatArray = field(default_factory=lambda: np.zeros(0))
    ellipsoid: FloatArray = field(default_factory=lambda: np.zeros(0))
    declared_box: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        disturbance = np.asarray(self.disturbance, dtype=np.float64)
        n = len(disturbance)
        if len(self.measurement) == 0:  # omitted: every state measured exactly
            object.__setattr__(self, "measurement", np.zeros(n))
        axes = np.zeros(n) if len(self.ellipsoid) == 0 else np.asarray(self.ellipsoid, float)
        object.__setattr__(self, "ellipsoid", axes)
        if not np.any(axes > 0):  # the box alone: as declared (``ellipsoidal`` False)
            object.__setattr__(self, "declared_box", disturbance)
        elif len(self.declared_box) == 0:
            object.__setattr__(self, "declared_box", np.maximum(disturbance - axes, 0.0))
        box = np.asarray(self.declared_box, dtype=np.float64)
        if axes.shape != disturbance.shape or box.shape != disturbance.shape:
            raise ValueError(
                f"Uncertainty: ellipsoid {axes.shape} and declared_box {box.shape} against "
                f"disturbance {disturbance.shape}; expected the same shape"
            )
        if np.any(axes > disturbance) or np.any(box > disturbance):
            raise ValueError("Uncertainty: disturbance must hold the declared box and ellipsoid")
        freeze_fields(self)

    def __reduce__(self) -> tuple[object, ...]:
        return reduce_fields(self)

    @classmethod
    def exact(cls, n: int) -> Uncertainty:
        """No uncertainty over ``n`` states: the exact model."""
        return cls(disturbance=np.zeros(n))

    @property
    def empty(self) -> bool:
        """Nothing declared: the exact model."""
        return (
            not self.parameter_names
            and not np.any(self.disturbance > 0)
            and not np.any(self.measurement > 0)
        )

    @property
    def ellipsoidal(self) -> bool:
        """An ellipsoid is declared (some ``ellipsoid_i > 0``)."""
        return bool(np.any(self.ellipsoid > 0))

    @property
    def measured(self) -> bool:
        """A measurement error is declared (some ``measurement_i > 0``)."""
        return bool(np.any(self.measurement > 0))

    @property
    def measurement_box(self) -> FloatArray | None:
        """(n,) ``measurement`` when an error is declared, else None (the state measured
        exactly), as the law's offset (I7) and the terminal check (T5) take it."""
        return self.measurement if self.measured else None

    @property
    def parameters(self) -> Mapping[str, tuple[float, float]]:
        """Parameter name -> (lower, upper)."""
        return {
            name: (float(lo), float(hi))
            for name, lo, hi in zip(
                self.parameter_names, self.parameter_lower, self.parameter_upper, strict=True
            )
        }

    def scaled(self, factor: float) -> Uncertainty:
        """The same declaration ``factor`` times as wide about the nominal (``--stress``)."""
        nominal = self.parameter_nominal
        return Uncertainty(
            disturbance=held_box(factor * self.declared_box, factor * self.ellipsoid),
            parameter_names=self.parameter_names,
            parameter_lower=nominal + factor * (self.parameter_lower - nominal),
            parameter_upper=nominal + factor * (self.parameter_upper - nominal),
            parameter_nominal=nominal,
            parametric=self.parametric,
            measurement=factor * self.measurement,
            ellipsoid=factor * self.ellipsoid,
            declared_box=factor * self.declared_box,
        )


def held_box(box: FloatArray, axes: FloatArray) -> FloatArray:
    """(n,) the box every certificate holds for the declared ``box (n,)`` plus an ellipsoid of
    semi-axes ``axes (n,)``: ``box + axes``, rounded up where both are positive (elsewhere the
    sum is one of them, exact: a declaration without an ellipsoid is held as written)."""
    total = box + axes
    return np.where((box > 0) & (axes > 0), np.nextafter(total, np.inf), total)
