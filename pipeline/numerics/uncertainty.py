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

evaluated as one expression in that arithmetic (``hull.interval_of``: every sum and product
rounded outward, the float end rounded up). The mean-value form avoids interval arithmetic's
dependency problem on the difference itself (on quadrotor_hill_flythrough, a thrust times the sine
of the pitch over an uncertain mass, bounded term by term: 21.9 m/s^2 against 0.59 in the mean-value
form).

(T7) Parameters in the hull. Near one point ``(x_eq, u_eq)`` (a terminal set) the bound (U1) over
a box is wasteful: most of the parameters' term is the shift of ``f`` at the point itself, the
rest varies with ``(x, u)``. Split ``f(x, u, p) - f(x_eq, u_eq, p0)`` as ``[f(x, u, p) - f(x_eq,
u_eq, p)] + [f(x_eq, u_eq, p) - f(x_eq, u_eq, p0)] + r``: the first is ``J(xi, p) (x - x_eq, u -
u_eq)`` by the mean value theorem at fixed ``p`` (per component), with ``J(xi, p)`` in the hull of
``[f_x f_u]`` over the box and the parameter intervals (``parametric_hull``); the second is (U1)
at the point alone (``equilibrium_bound``), added to the declared disturbance. The certificates
that use it (``terminal.check`` (T7)) hold every hull point and every additive term in that box,
so they hold for every parameter in its interval, constant or not.

Which box ``Z``. Every certificate that holds uncertainty keeps its tube inside ``state_bounds``
and its inputs inside ``input_bounds`` (a funnel's caps, ``pipeline.numerics.funnel.synthesis``), so
``Z`` is the state bounds (else the operating region) for each state ``df/dp`` depends on, and the
input bounds for each input. A state that neither declares is a ``HullError`` naming it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import sympy

from pipeline.model.dynamics import FloatArray
from pipeline.model.scenario import Scenario
from pipeline.model.uncertainty import Uncertainty
from pipeline.numerics.hull import HullError, JacobianHull, interval_of, jacobian_hull


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


def held_state_bounds(scenario: Scenario) -> dict[str, tuple[float, float]]:
    """State name -> the interval a funnel keeps its tube in: the scenario's ``state_bounds``,
    and under a declared uncertainty also the operating region of the states without bounds
    (``certified_box``'s states: the additive bound (U1) holds only there)."""
    if scenario.uncertainty.empty:
        return dict(scenario.state_bounds)
    box = certified_box(scenario)
    return {name: box[name] for name in scenario.state_names if name in box}


def parameter_bound(uncertainty: Uncertainty, box: Mapping[str, tuple[float, float]]) -> FloatArray:
    """(n,) the bound (U1) on ``|f(x, u, p) - f(x, u, p0)|`` over ``box`` (variable name ->
    interval) and the declared parameter intervals; zeros without uncertain parameters."""
    return _bound(uncertainty, box, with_disturbance=False)


def additive_bound(scenario: Scenario, uncertainty: Uncertainty | None = None) -> FloatArray:
    """(n,) ``b`` of (U1): the declared disturbance plus the parameters' term over
    ``certified_box``, rounded up; ``uncertainty`` defaults to the scenario's."""
    uncertainty = scenario.uncertainty if uncertainty is None else uncertainty
    return _bound(uncertainty, certified_box(scenario), with_disturbance=True)


def declared_bound(scenario: Scenario) -> FloatArray | None:
    """``additive_bound(scenario)``, or None when the scenario declares no uncertainty (the
    exact model: every certificate then takes its exact-model form)."""
    return None if scenario.uncertainty.empty else additive_bound(scenario)


def equilibrium_bound(
    uncertainty: Uncertainty, scenario: Scenario, x_eq: FloatArray, u_eq: FloatArray
) -> FloatArray:
    """(n,) (T7)'s additive box at the point ``(x_eq (n,), u_eq (m,))``: the declared disturbance
    plus the parameters' term (U1) there alone, rounded up."""
    names = (*scenario.state_names, *scenario.input_names)
    point = {k: (float(v), float(v)) for k, v in zip(names, [*x_eq, *u_eq], strict=True)}
    return _bound(uncertainty, point, with_disturbance=True)


def parametric_hull(
    scenario: Scenario,
    region: Mapping[str, tuple[float, float]],
    segments: int,
    parameters: Uncertainty | None = None,
) -> JacobianHull:
    """``jacobian_hull`` of ``[f_x f_u]`` (``(V, n, n + m)`` vertices) over ``region`` and, when
    ``parameters`` declares any, over their intervals too (T7): the parametric dynamics'
    Jacobian in the states and the ``m`` inputs. ``HullError`` as ``jacobian_hull``'s."""
    if parameters is None or parameters.parametric is None:
        return jacobian_hull(scenario.dynamics, region, segments)
    box = {**region, **parameters.parameters}
    return jacobian_hull(parameters.parametric, box, segments, inputs=scenario.m)


def _bound(
    uncertainty: Uncertainty, box: Mapping[str, tuple[float, float]], *, with_disturbance: bool
) -> FloatArray:
    """(n,) per state the upper end of ``[D_i +] |sum_j df_i/dp_j (x, u, xi) (s_j - p0_j)|`` in
    the outward-rounded interval arithmetic of ``pipeline.numerics.hull`` (``interval_of``),
    with ``xi`` (the parameters' own symbols) and ``s`` (fresh ones) over the parameter box, the
    other variables over ``box``: (U1) as one expression, so that every sum, product and the
    final float are rounded by the hull's arithmetic."""
    n = len(uncertainty.disturbance)
    disturbance = uncertainty.disturbance if with_disturbance else np.zeros(n)
    dynamics = uncertainty.parametric
    if dynamics is None:
        return np.array(disturbance, dtype=np.float64)
    parameters = dynamics.input_symbols[dynamics.m - len(uncertainty.parameter_names) :]
    values = [sympy.Symbol(f"{p.name}__value", real=True) for p in parameters]
    ranges: dict[sympy.Symbol, tuple[float, float]] = {}
    for p, s, lo, hi in zip(
        parameters, values, uncertainty.parameter_lower, uncertainty.parameter_upper, strict=True
    ):
        ranges[p] = ranges[s] = (float(lo), float(hi))
    bound = np.zeros(n)
    for i, expression in enumerate(dynamics.expressions):
        difference = sympy.Add(
            *(
                sympy.diff(expression, p) * (s - sympy.Float(float(p0)))
                for p, s, p0 in zip(parameters, values, uncertainty.parameter_nominal, strict=True)
            )
        )
        if difference == 0:
            bound[i] = disturbance[i]
            continue
        variables = {}
        for free in difference.free_symbols - set(ranges):
            if free.name not in box:
                named = [p.name for p in parameters if sympy.diff(expression, p).has(free)]
                raise HullError(
                    f"the dynamics' sensitivity to parameter '{named[0]}' depends on "
                    f"'{free.name}', which has no bound: declare state_bounds.{free.name}"
                )
            variables[free] = box[free.name]
        total = sympy.Float(float(disturbance[i])) + sympy.Abs(difference)
        bound[i] = interval_of(total, {**variables, **ranges})[1]
    return bound
