"""Dynamics for the tests of the generated code: one that uses every allowed function, and the
oracle that evaluates expressions the way the batch code does."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import sympy

from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.model.expressions import ALLOWED_FUNCTIONS


def every_function_dynamics() -> Dynamics:
    """Three states, two inputs; every function a scenario may use, powers; damped, so that
    flights of a few seconds from the unit box stay bounded."""
    a, b, c = sympy.symbols("a b c", real=True)
    p, q = sympy.symbols("p q", real=True)
    F = ALLOWED_FUNCTIONS
    f = [
        -a + 0.2 * a**2 * F["sin"](b) * p + F["cos"](c) / (2 + b**2),
        -b + F["exp"](-(c**2)) + F["sqrt"](1 + a**2) * q - 0.1 * b**3 + 0.2 * F["tan"](0.3 * a),
        -c
        + F["tanh"](a * b)
        + F["atan"](c)
        + F["atan2"](b, a + 3)
        - F["log"](2 + c**2)
        + 0.1 * F["abs"](b) * b * p**2
        - 0.1 * sympy.pi * q,
    ]
    return Dynamics.from_expressions([a, b, c], [p, q], f)


def batch_code(
    dynamics: Dynamics, entries: Sequence[sympy.Expr] | None = None
) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """The oracle: ``entries`` (default ``f``'s) at one point as the batch code computes them
    (``np.moveaxis`` of ``x (n,)``, ``u (m,)`` into scalars, the values copied into an array)."""
    entries = list(dynamics.expressions if entries is None else entries)
    args = (*dynamics.state_symbols, *dynamics.input_symbols)
    compiled = sympy.lambdify(list(args), entries, modules="numpy", cse=True)

    def evaluate(x: FloatArray, u: FloatArray) -> FloatArray:
        out = np.empty(len(entries))
        for i, value in enumerate(compiled(*np.moveaxis(x, -1, 0), *np.moveaxis(u, -1, 0))):
            out[i] = value
        return out

    return evaluate
