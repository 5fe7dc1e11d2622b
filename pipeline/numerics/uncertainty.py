"""The declared uncertainty as one additive bound: ``x' = f(x, u) + w``, ``|w_i| <= b_i``.

A scenario declares a disturbance box ``|d_i| <= D_i`` and parameter intervals ``p in [p_lo,
p_hi]`` around the nominal ``p0`` (``pipeline.model.uncertainty``). The true system is
``x' = f(x, u, p) + d``; the certificates design around ``f(x, u) = f(x, u, p0)``, so

    x' = f(x, u) + w,   w = f(x, u, p) - f(x, u, p0) + d.

Bound (U1). By the mean value theorem on the segment from ``p0`` to ``p`` (for each component
``i`` separately), ``f_i(x, u, p) - f_i(x, u, p0) = sum_j (df_i/dp_j)(x, u, xi) (p_j - p0_j)``
for some ``xi`` on the segment, which lies in the parameter box. So with the interval enclosure
``[df_i/dp_j]`` over the box ``Z`` of ``(x, u)`` and the parameter box (outward-rounded interval
arithmetic, ``pipeline.numerics.hull``),

    |w_i| <= D_i + max |sum_j [df_i/dp_j] * [p_lo_j - p0_j, p_hi_j - p0_j]| =: b_i,

the interval product and sum in outward-rounded arithmetic too, and the sum ``D_i + ...``
rounded up. The mean-value form avoids interval arithmetic's dependency problem on the
difference itself (a thrust over an uncertain mass, ``u/m - u/m0``, bounded term by term is
~40x wider on quadrotor_hill).

Which box ``Z``. Every certificate that holds uncertainty keeps its tube inside ``state_bounds``
and its inputs inside ``input_bounds`` (a funnel's caps, ``pipeline.numerics.funnel.synthesis``), so
``Z`` is the state bounds (else the operating region) for each state ``df/dp`` depends on, and the
input bounds for each input. A state that neither declares is a ``HullError`` naming it.
"""

from __future__ import annotations

from collections.abc import Mapping

import mpmath
import numpy as np
import sympy
from mpmath import iv

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.hull import HullError, interval_of


def certified_box(scenario: Scenario) -> dict[str, tuple[float, float]]:
    """Variable name -> interval every uncertainty-holding certificate keeps its tube in: the
    input bounds, the state bounds, and the operating region for states without bounds."""
    box = {
        name: interval
        for name, interval in scenario.operating_region.items()
        if name in scenario.state_names
    }
    box.update(scenario.state_bounds)
    for j, name in enumerate(scenario.input_names):
        box[name] = (float(scenario.input_lower[j]), float(scenario.input_upper[j]))
    return box


def parameter_bound(uncertainty: Uncertainty, box: Mapping[str, tuple[float, float]]) -> FloatArray:
    """(n,) the bound (U1) on ``|f(x, u, p) - f(x, u, p0)|`` over ``box`` (variable name ->
    interval) and the declared parameter intervals; zeros without uncertain parameters."""
    n = len(uncertainty.disturbance)
    dynamics = uncertainty.parametric
    if dynamics is None:
        return np.zeros(n)
    q = len(uncertainty.parameter_names)
    m = dynamics.m - q
    parameters = dynamics.input_symbols[m:]
    ranges = {
        symbol: (float(lo), float(hi))
        for symbol, lo, hi in zip(
            parameters, uncertainty.parameter_lower, uncertainty.parameter_upper, strict=True
        )
    }
    steps = [
        iv.mpf([float(lo), float(hi)]) - iv.mpf(float(p0))
        for lo, hi, p0 in zip(
            uncertainty.parameter_lower,
            uncertainty.parameter_upper,
            uncertainty.parameter_nominal,
            strict=True,
        )
    ]
    bound = np.zeros(n)
    for i, expression in enumerate(dynamics.expressions):
        total = iv.mpf(0)
        for j, symbol in enumerate(parameters):
            derivative = sympy.diff(expression, symbol)
            if derivative == 0:
                continue
            variables = {}
            for free in derivative.free_symbols - set(parameters):
                if free.name not in box:
                    raise HullError(
                        f"the dynamics' sensitivity to parameter '{symbol.name}' depends on "
                        f"'{free.name}', which has no bound: declare state_bounds.{free.name}"
                    )
                variables[free] = box[free.name]
            lower, upper = interval_of(derivative, {**variables, **ranges})
            total += iv.mpf([lower, upper]) * steps[j]
        largest = max(abs(total.a), abs(total.b))
        bound[i] = _up(largest)
    return bound


def additive_bound(scenario: Scenario, uncertainty: Uncertainty | None = None) -> FloatArray:
    """(n,) ``b`` of (U1): the declared disturbance plus the parameters' term over
    ``certified_box``, rounded up; ``uncertainty`` defaults to the scenario's."""
    uncertainty = scenario.uncertainty if uncertainty is None else uncertainty
    parameter = parameter_bound(uncertainty, certified_box(scenario))
    return np.array(
        [
            _up(iv.mpf(float(d)) + iv.mpf(float(p)))
            for d, p in zip(uncertainty.disturbance, parameter, strict=True)
        ]
    )


def _up(value: object) -> float:
    """An interval's (or number's) upper end as a float rounded up."""
    upper = value.b if isinstance(value, iv.mpf) else mpmath.mpf(value)  # type: ignore[attr-defined]
    result = float(upper)
    if mpmath.mpf(result) < upper:
        result = float(np.nextafter(result, np.inf))
    return result
