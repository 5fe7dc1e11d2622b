"""Continuous-time dynamics ``xdot = f(x, u)`` from symbolic expressions, with exact Jacobians.

Shapes: ``x (..., n)``, ``u (..., m)``; leading axes broadcast against each other.
``f -> (..., n)``, ``f_x -> (..., n, n)``, ``f_u -> (..., n, m)``. The Jacobians are derived
symbolically with sympy, so they are exact; their structural sparsity patterns (entries that
are identically zero) drive the pruned sensitivity system of the paper's Remark 3.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import sympy

from pipeline.model.frozen import frozen_array

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def _compiled(entries: Sequence[sympy.Expr], args: Sequence[sympy.Symbol]) -> Callable[..., list]:
    """The expressions as one NumPy function of the scalars ``(*x, *u)`` -> list of the values."""
    return sympy.lambdify(list(args), list(entries), modules="numpy", cse=True)


# NumPy's functions that lambdify prints for the scenario language's (pipeline.model.expressions)
FLOAT_FUNCTIONS = ("sin", "cos", "tan", "exp", "log", "sqrt", "tanh", "arctan", "arctan2", "abs")


def _returning_float(function: Callable[..., object]) -> Callable[..., float]:
    def call(*args: float) -> float:
        for arg in args:  # a loop, not any(generator): this runs millions of times a suite
            if isinstance(arg, complex):
                # a negative base's fractional power left the reals (NumPy: nan); abs or float()
                # of the function's result would make it real again: refuse, so the caller
                # falls back to np.float64
                raise TypeError("complex argument on the float path")
        return float(function(*args))  # type: ignore[arg-type]

    return call


_ON_FLOATS = {name: _returning_float(getattr(np, name)) for name in FLOAT_FUNCTIONS}


def _compiled_on_floats(
    entries: Sequence[sympy.Expr], args: Sequence[sympy.Symbol]
) -> Callable[..., list]:
    """``_compiled`` for Python floats: the same NumPy functions, their results as Python floats,
    so that the arithmetic between them runs on floats (the same IEEE operations as on
    np.float64, about twice as fast; but an error where NumPy's scalars give inf or nan)."""
    return sympy.lambdify(list(args), list(entries), modules=[_ON_FLOATS, "numpy"], cse=True)


def _vectorised(
    compiled: Callable[..., list], count: int
) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """NumPy function ``(x (..., n), u (..., m)) -> (..., count)`` of ``compiled``'s values."""

    def evaluate(x: FloatArray, u: FloatArray) -> FloatArray:
        x = np.asarray(x, dtype=np.float64)
        u = np.asarray(u, dtype=np.float64)
        if x.ndim == 1 and u.ndim == 1:
            # One point: the same np.float64 scalars as the batch path below passes for (n,)
            # and (m,), hence the same numbers, without its moveaxis and broadcast (~5x faster).
            return np.array(compiled(*x, *u), dtype=np.float64)
        batch = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        values = compiled(*np.moveaxis(x, -1, 0), *np.moveaxis(u, -1, 0))
        out = np.empty((*batch, count))
        for i, value in enumerate(values):
            out[..., i] = value
        return out

    return evaluate


@dataclass(frozen=True, eq=False)
class Dynamics:
    """``xdot = f(x, u)`` with named states and inputs; parameters already substituted.

    Attributes:
      state_names: (n,) names; input_names: (m,) names.
      expressions: (n,) sympy expressions of ``f``.
      jacobian_x: sympy (n, n) matrix ``df/dx``; jacobian_u: sympy (n, m) matrix ``df/du``.
      sparsity_x: (n, n) bool, True where ``df/dx`` is not identically zero; sparsity_u: (n, m).
    """

    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    expressions: tuple[sympy.Expr, ...]
    state_symbols: tuple[sympy.Symbol, ...]
    input_symbols: tuple[sympy.Symbol, ...]
    jacobian_x: sympy.Matrix = field(repr=False)
    jacobian_u: sympy.Matrix = field(repr=False)
    sparsity_x: BoolArray = field(repr=False)
    sparsity_u: BoolArray = field(repr=False)
    _f: Callable[[FloatArray, FloatArray], FloatArray] = field(repr=False)
    _f_x: Callable[[FloatArray, FloatArray], FloatArray] = field(repr=False)
    _f_u: Callable[[FloatArray, FloatArray], FloatArray] = field(repr=False)
    _f_scalars: Callable[..., list] = field(repr=False)
    _f_floats: Callable[..., list] = field(repr=False)

    def __post_init__(self) -> None:
        for name in ("sparsity_x", "sparsity_u"):
            object.__setattr__(self, name, frozen_array(getattr(self, name)))

    def __reduce__(self) -> tuple[object, ...]:
        """Pickled as the expressions it is built from (its compiled functions cannot be
        pickled): a worker process rebuilds it once per set of expressions (``_rebuilt``)."""
        return _rebuilt, (self.state_symbols, self.input_symbols, self.expressions)

    @classmethod
    def from_expressions(
        cls,
        state_symbols: Sequence[sympy.Symbol],
        input_symbols: Sequence[sympy.Symbol],
        expressions: Sequence[sympy.Expr],
    ) -> Dynamics:
        """Build from sympy expressions (one per state) in the given state and input symbols."""
        xs, us = tuple(state_symbols), tuple(input_symbols)
        n, m = len(xs), len(us)
        derived = _derived(xs, us, tuple(expressions))
        return cls(
            state_names=tuple(s.name for s in xs),
            input_names=tuple(s.name for s in us),
            expressions=derived.expressions,
            state_symbols=xs,
            input_symbols=us,
            jacobian_x=derived.jacobian_x.copy(),  # a mutable sympy Matrix: one per object
            jacobian_u=derived.jacobian_u.copy(),
            sparsity_x=np.array([[e != 0 for e in row] for row in derived.jacobian_x.tolist()]),
            sparsity_u=np.array(
                [[e != 0 for e in row] for row in derived.jacobian_u.tolist()]
            ).reshape(n, m),
            _f=_vectorised(derived.f_scalars, n),
            _f_x=_vectorised(derived.f_x, n * n),
            _f_u=_vectorised(derived.f_u, n * m),
            _f_scalars=derived.f_scalars,
            _f_floats=derived.f_floats,
        )

    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return len(self.input_names)

    def f(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """Vector field: ``x (..., n)``, ``u (..., m)`` -> ``(..., n)``."""
        return self._f(x, u)

    @property
    def scalar_function(self) -> Callable[..., list]:
        """``f_scalars`` taking the ``n + m`` scalars as separate arguments."""
        return self._f_scalars

    @property
    def float_function(self) -> Callable[..., list]:
        """``scalar_function`` on Python floats: the same values, bit for bit, where no
        operation overflows, divides by zero or leaves the reals; there Python raises (or turns
        complex, which the wrapped functions refuse and the caller's float conversion rejects)
        where NumPy's scalars give inf or nan."""
        return self._f_floats

    def f_scalars(self, x: Sequence[np.float64], u: Sequence[np.float64]) -> list:
        """The vector field at one point on scalars: ``n`` and ``m`` np.float64 -> ``n`` values,
        the numbers ``f`` returns for ``x (n,)``, ``u (m,)`` (RK4 along one trajectory runs it
        where ``float_function`` cannot)."""
        return self._f_scalars(*x, *u)

    def f_x(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """State Jacobian ``df/dx``: -> ``(..., n, n)``."""
        out = self._f_x(x, u)
        return out.reshape(*out.shape[:-1], self.n, self.n)

    def f_u(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """Input Jacobian ``df/du``: -> ``(..., n, m)``."""
        out = self._f_u(x, u)
        return out.reshape(*out.shape[:-1], self.n, self.m)

    @property
    def rate_states(self) -> tuple[int, ...]:
        """Indices of the states that are another state's derivative (``xdot_j = x_i``): they
        scale by ``T / T'`` when a trajectory of duration ``T`` is replayed in ``T'``."""
        return tuple(i for i, s in enumerate(self.state_symbols) if s in self.expressions)

    def depends_on(self) -> tuple[str, ...]:
        """Names of the states and inputs that the Jacobians depend on (the certified region)."""
        free = set().union(*(e.free_symbols for e in (*self.jacobian_x, *self.jacobian_u)))
        return tuple(s.name for s in (*self.state_symbols, *self.input_symbols) if s in free)


@dataclass(frozen=True)
class _Derived:
    """What ``Dynamics.from_expressions`` derives from the expressions: ``f`` (n,), its
    Jacobians (sympy (n, n) and (n, m)) and the functions lambdified from them."""

    expressions: tuple[sympy.Expr, ...]
    jacobian_x: sympy.Matrix
    jacobian_u: sympy.Matrix
    f_scalars: Callable[..., list]
    f_x: Callable[..., list]
    f_u: Callable[..., list]
    f_floats: Callable[..., list]


_DERIVED: dict[str, _Derived] = {}
_DERIVED_LOCK = threading.Lock()
DERIVED_KEPT = 32


def _derived(
    xs: tuple[sympy.Symbol, ...], us: tuple[sympy.Symbol, ...], expressions: tuple[sympy.Expr, ...]
) -> _Derived:
    """The Jacobians and lambdified functions of ``expressions``, derived once per process for
    each set of expressions (keyed on their ``srepr``, exact to the last bit of every Float, as
    ``_rebuilt``): each ``load_scenario`` of a scenario builds its own ``Dynamics`` from them
    (sympy's Jacobians and ``lambdify`` were ~40% of loading quadrotor_hill_flythrough without its
    demo checks). The lambdified functions are pure; they are shared."""
    key = sympy.srepr((xs, us, expressions))
    with _DERIVED_LOCK:
        if key in _DERIVED:
            return _DERIVED[key]
    f = sympy.Matrix(list(expressions))
    jac_x = f.jacobian(sympy.Matrix(xs))
    jac_u = f.jacobian(sympy.Matrix(us))
    args = (*xs, *us)
    derived = _Derived(
        expressions=tuple(f),
        jacobian_x=jac_x,
        jacobian_u=jac_u,
        f_scalars=_compiled(list(f), args),
        f_x=_compiled(list(jac_x), args),
        f_u=_compiled(list(jac_u), args),
        f_floats=_compiled_on_floats(list(f), args),
    )
    with _DERIVED_LOCK:
        if len(_DERIVED) >= DERIVED_KEPT:
            del _DERIVED[next(iter(_DERIVED))]
        return _DERIVED.setdefault(key, derived)


_REBUILT: dict[str, Dynamics] = {}
_REBUILT_LOCK = threading.Lock()
REBUILT_KEPT = 16


def _rebuilt(
    state_symbols: Sequence[sympy.Symbol],
    input_symbols: Sequence[sympy.Symbol],
    expressions: Sequence[sympy.Expr],
) -> Dynamics:
    """``Dynamics.from_expressions``, once per process for each set of expressions (their
    ``srepr``, exact to the last bit of every Float): the tasks of one run unpickle the same
    object, so the caches keyed on it (compiled kernels, the hull's structure) are shared."""
    key = sympy.srepr((tuple(state_symbols), tuple(input_symbols), tuple(expressions)))
    with _REBUILT_LOCK:
        if key not in _REBUILT:
            if len(_REBUILT) >= REBUILT_KEPT:
                del _REBUILT[next(iter(_REBUILT))]
            _REBUILT[key] = Dynamics.from_expressions(state_symbols, input_symbols, expressions)
        return _REBUILT[key]
