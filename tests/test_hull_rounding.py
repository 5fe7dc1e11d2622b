"""Interval bounds in pipeline.numerics.hull are rounded outward: they hold for the exact values.

Each case compares against exact rationals (``fractions.Fraction`` of the floats involved) or
120-bit mpmath, and is one where rounding to nearest would land inside the true range.
"""

from __future__ import annotations

import re
from fractions import Fraction

import mpmath
import numpy as np
import pytest
import sympy

from pipeline.numerics.hull import HullError, _bounds, arc_polygon

x = sympy.Symbol("x")


def test_product_with_a_constant_contains_the_exact_value() -> None:
    # float(3 * 0.1) = 0.30000000000000004 lies above 3 * Fraction(0.1): round-to-nearest would
    # give a lower bound above the true value.
    lower, upper = _bounds(3 * x, {x: (0.1, 0.1)})
    exact = 3 * Fraction(0.1)
    assert Fraction(lower) <= exact <= Fraction(upper)
    assert Fraction(3 * 0.1) > exact and lower < 3 * 0.1
    assert upper - lower <= 4 * np.spacing(0.3)  # and tight


def test_rational_constants_are_enclosed() -> None:
    lower, upper = _bounds(x + sympy.Rational(1, 3), {x: (0.0, 0.0)})
    assert Fraction(lower) < Fraction(1, 3) < Fraction(upper)


@pytest.mark.parametrize(
    ("function", "reference"),
    [(sympy.sin, mpmath.sin), (sympy.tanh, mpmath.tanh), (sympy.atan, mpmath.atan),
     (sympy.exp, mpmath.exp)],
)  # fmt: skip
def test_functions_contain_high_precision_values(function, reference) -> None:
    lower, upper = _bounds(function(x) * sympy.Float(0.7), {x: (0.5, 0.6)})
    with mpmath.workprec(120):
        values = [reference(mpmath.mpf(a)) * mpmath.mpf(0.7) for a in np.linspace(0.5, 0.6, 11)]
        assert mpmath.mpf(lower) <= min(values) and max(values) <= mpmath.mpf(upper)
        assert upper - lower <= float(max(values) - min(values)) + 1e-12  # and tight


def test_unbounded_expression_is_refused() -> None:
    with pytest.raises(HullError, match="unbounded"):
        _bounds(1 / x, {x: (-1.0, 1.0)})


@pytest.mark.parametrize(
    ("lower", "width", "segments"),
    [(0.1, 0.05, 1), (-0.8, 0.0001, 1), (0.3, 1e-7, 1), (-3.0, 2.5, 2), (1.0, 0.3, 3)],
)
def test_compact_arc_polygon_contains_the_arc_exactly(lower, width, segments) -> None:
    polygon = arc_polygon(lower, lower + width, segments, compact=True)
    assert len(polygon) == max(segments, int(np.ceil(max(width, 1e-4) / (np.pi / 4)))) + 2
    with mpmath.workprec(200):
        vertices = [(mpmath.mpf(float(a)), mpmath.mpf(float(b))) for a, b in polygon]
        angles = [mpmath.mpf(lower) + mpmath.mpf(width) * f for f in np.linspace(0, 1, 41)]
        for (ax, ay), (bx, by) in zip(vertices, vertices[1:] + vertices[:1], strict=True):
            for angle in angles:  # every arc point on the inner side of every edge (CCW)
                px, py = mpmath.cos(angle), mpmath.sin(angle)
                assert (bx - ax) * (py - ay) - (by - ay) * (px - ax) > 0


@pytest.mark.parametrize(
    ("region", "message"),
    [
        ({"theta": (-0.6, 0.6), "u1": (15.8, 14.9)}, "u1 in [15.8, 14.9]: not an interval"),
        ({"theta": (0.6, -0.6), "u1": (5.0, 14.9)}, "theta in [0.6, -0.6]: not an interval"),
        ({"theta": (-0.6, 0.6), "u1": (np.nan, 14.9)}, "u1 in [nan, 14.9]: not an interval"),
    ],
    ids=["interval block", "arc block", "nan"],
)
def test_a_box_that_is_not_an_interval_is_refused_by_name(region, message) -> None:
    """Issue 27, item 10: an empty box (an input box clipped to bounds it lies beyond) stopped
    on mpmath's ``assert`` (gone under ``python -O``), or for an angle gave the hull of a single
    point; either way it is now a ``HullError`` naming the variable."""
    from pipeline.model.scenario import load_scenario
    from pipeline.numerics.hull import jacobian_hull

    dynamics = load_scenario("quadrotor_hill_flythrough", check_demos=False).dynamics
    with pytest.raises(HullError, match=re.escape(message)):
        jacobian_hull(dynamics, region)
