"""Compiled cost, gradients and closed-loop rollouts: numba kernels generated from the
scenario's sympy expressions.

The scalar functions ``f``, ``[f, f_x, f_u]`` (structural nonzeros only) and the vector-Jacobian
product ``lam -> (lam f_x, lam f_u)`` are printed from the same sympy expressions as
``pipeline.model.dynamics`` (common subexpressions eliminated, floats printed exactly), appended to
the loops of ``pipeline.numerics.kernels.loops`` (cost, gradients) and ``.rollout`` (closed
loop), and written to a cache folder under a name that hashes the source, so numba's
``cache=True`` compiles each scenario once per machine. Polygons become vertex arrays
(``PenaltyData``): shapely cannot run inside numba.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import importlib.util
import os
import sys
import tempfile
import threading
import weakref
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from types import ModuleType
from typing import IO, Any, NamedTuple

import numba
import numpy as np
import sympy
from numba.core.compiler_lock import global_compiler_lock
from numba.core.dispatcher import Dispatcher
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.base import BaseGeometry
from sympy.printing.pycode import PythonCodePrinter

from pipeline.model.dynamics import Dynamics, FloatArray
from pipeline.numerics.kernels import shared
from pipeline.numerics.optimize.penalties import Constraints, IntArray
from pipeline.numerics.optimize.sensitivity import SensitivityPattern

_TEMPLATES = tuple(Path(__file__).with_name(name) for name in ("loops.py", "rollout.py"))
_LOADED: dict[str, ModuleType] = {}
_BY_DYNAMICS: weakref.WeakKeyDictionary[Dynamics, ModuleType] = weakref.WeakKeyDictionary()
_LOADING = threading.Lock()  # e.g. the Monte Carlo stage's chunks and its side thread


def cache_folder() -> Path:
    """Where generated kernels live: ``$SAFETY_KERNEL_CACHE``, else ``~/.cache/...``."""
    configured = os.environ.get("SAFETY_KERNEL_CACHE")
    folder = (
        Path(configured) if configured else Path.home() / ".cache" / "safety-synthesis" / "kernels"
    )
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if os.access(folder, os.W_OK):
            return folder
    except OSError:
        pass
    fallback = Path(tempfile.gettempdir()) / "safety-synthesis-kernels"
    fallback.mkdir(parents=True, exist_ok=True)
    return fallback


class _Printer(PythonCodePrinter):
    """Python source with ``math`` functions; floats with all their digits."""

    def _print_Float(self, expr: sympy.Float) -> str:
        return repr(float(expr))


def _function(name: str, args: str, outputs: list[tuple[str, sympy.Expr]], unpack: str) -> str:
    printer = _Printer({"fully_qualified_modules": True})
    temporaries, reduced = sympy.cse(
        [expression for _, expression in outputs], symbols=sympy.numbered_symbols("c_")
    )
    lines = ["", "", "@njit(cache=True)", f"def {name}({args}):", *unpack.splitlines()]
    lines += [f"    {symbol} = {printer.doprint(value)}" for symbol, value in temporaries]
    for (target, _), value in zip(outputs, reduced, strict=True):
        lines.append(f"    {target} = {printer.doprint(value)}")
    return "\n".join(lines) + "\n"


def _is_unit(expression: sympy.Basic) -> bool:
    return bool(expression.is_Float) and abs(float(expression)) == 1.0  # type: ignore[arg-type]


def exact_units(expression: sympy.Expr) -> sympy.Expr:
    """``expression`` with ``1.0*a -> a``, ``-1.0*a -> -a`` and a bare ``+-1.0 -> +-1``: the
    same floating-point values (multiplying by +-1 is exact), and so the same kernel source as a
    scenario written without the factor (a parameter ``k: 1.0`` in ``k*aX``): its compiled
    kernels are shared. Exponents are left alone (``x**-1.0`` is ``pow``, not ``1/x``)."""
    if _is_unit(expression):
        return sympy.Integer(int(float(expression)))  # type: ignore[arg-type]

    def unit_factor(e: sympy.Basic) -> bool:
        return bool(e.is_Mul) and _is_unit(e.as_coeff_Mul()[0])  # type: ignore[attr-defined]

    def drop(e: sympy.Expr) -> sympy.Expr:
        coefficient, rest = e.as_coeff_Mul()
        return rest if float(coefficient) > 0 else -rest

    return expression.replace(unit_factor, drop)


def dynamics_source(dynamics: Dynamics) -> str:
    """Numba source of ``f_eval``, ``f_jac_eval`` and ``vjp_eval`` for ``dynamics``."""
    n, m = dynamics.n, dynamics.m
    x = [sympy.Symbol(f"x_{i}") for i in range(n)]
    u = [sympy.Symbol(f"u_{j}") for j in range(m)]
    lam = [sympy.Symbol(f"l_{i}") for i in range(n)]
    rename = dict(zip((*dynamics.state_symbols, *dynamics.input_symbols), (*x, *u), strict=True))
    f = [exact_units(sympy.sympify(e).xreplace(rename)) for e in dynamics.expressions]
    A = dynamics.jacobian_x.xreplace(rename).applyfunc(exact_units)
    B = dynamics.jacobian_u.xreplace(rename).applyfunc(exact_units)
    unpack = "\n".join(
        [f"    x_{i} = x[{i}]" for i in range(n)] + [f"    u_{j} = u[{j}]" for j in range(m)]
    )
    source = _function("f_eval", "x, u, out", [(f"out[{i}]", f[i]) for i in range(n)], unpack)
    outputs = [(f"out[{i}]", f[i]) for i in range(n)]
    outputs += [(f"A[{i * n + j}]", A[i, j]) for i in range(n) for j in range(n) if A[i, j] != 0]
    outputs += [(f"B[{i * m + j}]", B[i, j]) for i in range(n) for j in range(m) if B[i, j] != 0]
    source += _function("f_jac_eval", "x, u, out, A, B", outputs, unpack)
    vjp = [
        (f"out_x[{j}]", sum((lam[i] * A[i, j] for i in range(n)), sympy.S.Zero)) for j in range(n)
    ]
    vjp += [
        (f"out_u[{j}]", sum((lam[i] * B[i, j] for i in range(n)), sympy.S.Zero)) for j in range(m)
    ]
    unpack_lam = unpack + "\n" + "\n".join(f"    l_{i} = lam[{i}]" for i in range(n))
    source += _function("vjp_eval", "x, u, lam, out_x, out_u", vjp, unpack_lam)
    return source


def load_kernels(dynamics: Dynamics) -> ModuleType:
    """The compiled kernel module of ``dynamics`` (generated and imported once per process,
    also when several threads ask at once)."""
    if dynamics in _BY_DYNAMICS:
        return _BY_DYNAMICS[dynamics]
    with _LOADING:
        return _load_kernels(dynamics)


def _load_kernels(dynamics: Dynamics) -> ModuleType:
    if dynamics in _BY_DYNAMICS:
        return _BY_DYNAMICS[dynamics]
    source = "\n\n".join(template.read_text() for template in _TEMPLATES)
    source += "\n# ---- generated from the scenario's expressions ----\n"
    source += dynamics_source(dynamics)
    # numba's cache of a generated kernel holds the compiled shared functions it calls, and numba
    # checks only the generated file's own stamp: an edit of shared.py must give a new module
    # (keyed on the source this process runs), as must a change of PenaltyData's fields (numba
    # keys a named tuple on its field types, not their names)
    stamp = f"{numba.__version__} {sys.version}\n{shared.SOURCE}\n{PenaltyData._fields}\n{source}"
    key = hashlib.sha256(stamp.encode()).hexdigest()[:20]
    if key in _LOADED:
        _BY_DYNAMICS[dynamics] = _LOADED[key]
        return _LOADED[key]
    path = cache_folder() / f"kernels_{key}.py"
    if not path.is_file() or path.read_text() != source:
        partial = path.with_suffix(f".{os.getpid()}.tmp")
        partial.write_text(source)
        os.replace(partial, path)  # atomic: parallel workers never see a half-written file
    name = f"_safety_kernels_{key}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import the generated kernels {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    _share_compile_lock()
    _compile_one_at_a_time(module, path.with_suffix(".lock"))
    _LOADED[key] = _BY_DYNAMICS[dynamics] = module
    return module


class _CompileLock:
    """One process at a time compiles a kernel module's functions: an exclusive ``flock`` on
    ``path``, taken by a thread's outermost compile (a kernel compiles its callees inside it),
    released by the operating system if the process dies. A process that waited loads the
    other's result from numba's disk cache instead of compiling it again (parallel workers or
    pytest-xdist on a cold cache: each compiled every kernel it called first, ~10 s of CPU a
    scenario). A generated module's lock is taken outside numba's own compiler lock; ``shared``'s
    inside it (``outer``): a kernel compiling holds its module's lock and numba's, then takes
    ``shared``'s for its callees, and a direct call of a shared function takes numba's first too,
    so the locks are always taken in one order."""

    def __init__(self, path: Path, outer: AbstractContextManager[Any] | None = None) -> None:
        self.path = path
        self.outer = outer if outer is not None else nullcontext()
        self.thread = threading.RLock()  # also makes ``depth`` the owning thread's
        self.depth = 0
        self.handle: IO[bytes] | None = None

    def compile(self, original: Callable[[Any], Any], sig: Any) -> Any:
        with self.outer, self.thread:
            if self.depth == 0:
                self.handle = self._lock()
            self.depth += 1
            try:
                return original(sig)
            finally:
                self.depth -= 1
                if self.depth == 0 and self.handle is not None:
                    self.handle.close()  # releases the lock
                    self.handle = None

    def _lock(self) -> IO[bytes] | None:
        """The locked file, or None where it cannot be locked (e.g. a read-only cache folder):
        then this process compiles without waiting, as it would without the lock."""
        try:
            handle = self.path.open("ab")
        except OSError:
            return None
        try:
            fcntl.flock(handle, fcntl.LOCK_EX)
        except OSError:
            handle.close()
            return None
        return handle


def _compile_one_at_a_time(
    module: ModuleType, lock_path: Path, outer: AbstractContextManager[Any] | None = None
) -> None:
    """Route every compile of the dispatchers defined in ``module`` (not those it imports from
    ``shared``) through one ``_CompileLock``."""
    lock = _CompileLock(lock_path, outer)
    for value in vars(module).values():
        if isinstance(value, Dispatcher) and value.py_func.__module__ == module.__name__:
            value.compile = functools.partial(lock.compile, value.compile)  # type: ignore[method-assign]


@functools.cache
def _share_compile_lock() -> None:
    """The same for ``shared``, once per process (called under ``_LOADING``): its lock is taken
    inside a generated module's and inside numba's compiler lock, never the other way round, so
    neither two processes nor two threads can wait on each other."""
    _compile_one_at_a_time(shared, cache_folder() / "shared.lock", global_compiler_lock)


class PenaltyData(NamedTuple):
    """``Constraints`` on one grid as arrays for numba (see ``pipeline.numerics.kernels.loops``):
    ``unsafe_margin (N s + 1,)``, ``input_* (N, m)``, ``region_state_* (N s + 1, a)``,
    ``region_input_* (N, b)`` (``Constraints.grid``)."""

    position: IntArray
    unsafe_margin: FloatArray
    unsafe_vertices: FloatArray
    unsafe_ring_start: IntArray
    unsafe_set_rings: IntArray
    unsafe_box: FloatArray
    goal_vertices: FloatArray
    goal_ring_start: IntArray
    input_lower: FloatArray
    input_upper: FloatArray
    region_state_index: IntArray
    region_state_lower: FloatArray
    region_state_upper: FloatArray
    region_input_index: IntArray
    region_input_lower: FloatArray
    region_input_upper: FloatArray
    goal_index: IntArray
    goal_lower: FloatArray
    goal_upper: FloatArray


def rings(shape: BaseGeometry) -> list[FloatArray]:
    """Every ring (exterior and holes) of a polygon or multipolygon, without the closing vertex."""
    if isinstance(shape, Polygon):
        polygons = [shape]
    elif isinstance(shape, MultiPolygon):
        polygons = list(shape.geoms)
    else:
        raise TypeError(f"expected a polygon or multipolygon, got {shape.geom_type}")
    rings = []
    for polygon in polygons:
        for ring in (polygon.exterior, *polygon.interiors):
            rings.append(np.asarray(ring.coords, dtype=np.float64)[:-1])
    return rings


def ring_arrays(rings: list[FloatArray]) -> tuple[FloatArray, IntArray]:
    start = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
    return np.concatenate(rings, axis=0), start


def unsafe_ring_arrays(
    regions: list[BaseGeometry],
) -> tuple[FloatArray, IntArray, IntArray, FloatArray]:
    """The Unsafe sets as the kernels read them: ``vertices (v, 2)``, ``ring_start (rings + 1,)``,
    ``set_rings (sets + 1,)`` (set ``S`` owns rings ``set_rings[S]:set_rings[S+1]``) and bounding
    ``boxes (sets, 4)`` (xmin, ymin, xmax, ymax)."""
    unsafe_rings: list[FloatArray] = []
    set_rings = [0]
    for region in regions:
        region_rings = rings(region)
        unsafe_rings += region_rings
        set_rings.append(set_rings[-1] + len(region_rings))
    vertices, start = (
        ring_arrays(unsafe_rings) if unsafe_rings else (np.zeros((0, 2)), np.zeros(1, np.int64))
    )
    boxes = np.array([region.bounds for region in regions], dtype=np.float64).reshape(-1, 4)
    return vertices, start, np.array(set_rings, dtype=np.int64), boxes


def penalty_data(constraints: Constraints, N: int, substeps: int) -> PenaltyData:
    """Vertex arrays and bounds of ``constraints`` on the grid of ``N`` intervals and
    ``substeps`` RK4 steps each, for the kernels."""
    grid = constraints.grid(N, substeps)
    unsafe_vertices, unsafe_start, set_rings, boxes = unsafe_ring_arrays(
        list(constraints.unsafe.values())
    )
    goal_vertices, goal_start = ring_arrays(rings(constraints.goal_region))
    c = constraints
    return PenaltyData(
        position=np.array(c.position_index, dtype=np.int64),
        unsafe_margin=np.ascontiguousarray(grid.unsafe_margin),
        unsafe_vertices=unsafe_vertices,
        unsafe_ring_start=unsafe_start,
        unsafe_set_rings=set_rings,
        unsafe_box=boxes,
        goal_vertices=goal_vertices,
        goal_ring_start=goal_start,
        input_lower=np.ascontiguousarray(grid.input_lower),
        input_upper=np.ascontiguousarray(grid.input_upper),
        region_state_index=c.region_state_index,
        region_state_lower=np.ascontiguousarray(grid.region_state_lower),
        region_state_upper=np.ascontiguousarray(grid.region_state_upper),
        region_input_index=c.region_input_index,
        region_input_lower=np.ascontiguousarray(grid.region_input_lower),
        region_input_upper=np.ascontiguousarray(grid.region_input_upper),
        goal_index=c.goal_index,
        goal_lower=c.goal_lower,
        goal_upper=c.goal_upper,
    )


class PatternData(NamedTuple):
    """The pruned entries of ``Phi``/``Gamma`` and term lists of ``(A Phi)_P``, ``(A Gamma)_Q``."""

    phi_rows: IntArray
    phi_cols: IntArray
    gamma_rows: IntArray
    gamma_cols: IntArray
    terms: tuple[IntArray, IntArray, IntArray, IntArray, IntArray, IntArray, IntArray]


def pattern_data(pattern: SensitivityPattern, sparsity_x: np.ndarray) -> PatternData:
    """Index lists of the sparse products on the structural pattern (row-major entries)."""
    n, m = pattern.gamma.shape
    phi_rows, phi_cols = np.nonzero(pattern.phi)
    gamma_rows, gamma_cols = np.nonzero(pattern.gamma)
    phi_at = {(i, j): e for e, (i, j) in enumerate(zip(phi_rows, phi_cols, strict=True))}
    gamma_at = {(i, j): e for e, (i, j) in enumerate(zip(gamma_rows, gamma_cols, strict=True))}

    def terms(rows: IntArray, cols: IntArray, at: dict) -> tuple[IntArray, IntArray, IntArray]:
        ptr, a, src = [0], [], []
        for i, j in zip(rows, cols, strict=True):
            for k in np.flatnonzero(sparsity_x[i]):
                if (k, j) in at:
                    a.append(i * n + k)
                    src.append(at[(k, j)])
            ptr.append(len(a))
        return (
            np.array(ptr, dtype=np.int64),
            np.array(a, dtype=np.int64),
            np.array(src, dtype=np.int64),
        )

    phi_terms = terms(phi_rows, phi_cols, phi_at)
    gamma_terms = terms(gamma_rows, gamma_cols, gamma_at)
    gamma_b = (gamma_rows * m + gamma_cols).astype(np.int64)
    return PatternData(
        phi_rows=phi_rows.astype(np.int64),
        phi_cols=phi_cols.astype(np.int64),
        gamma_rows=gamma_rows.astype(np.int64),
        gamma_cols=gamma_cols.astype(np.int64),
        terms=(*phi_terms, *gamma_terms, gamma_b),
    )
