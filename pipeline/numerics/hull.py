"""A sound polytope containing the Jacobians ``[f_x f_u]`` over a box (the operating region).

Problem: find matrices ``J_1 .. J_V`` (n, n+m) with ``[f_x f_u](z) in conv{J_i}`` for every ``z``
in the box ``Z = prod_k [lo_k, hi_k]`` over the variables the Jacobian depends on. Sampling ``Z``
is not sound; this construction is.

1. Features. Each (expanded) Jacobian entry is a sum ``c_0 + sum_k c_k phi_k(z)`` of numbers times
   products ``phi_k``, so ``J(z) = J_0 + sum_k phi_k(z) M_k`` is affine in the feature vector
   ``phi``. A feature that factors into single-variable parts ``phi = prod_z g_z(z)`` is
   *multilinear* in the coordinates ``g_z`` (one per variable); any other feature is its own
   coordinate.
2. Blocks. The coordinates of one variable ``z`` form a block ``G_z = {(g_1(z), .., g_p(z))}``
   over ``[lo, hi]``; each block is enclosed by a polytope with vertices ``V_z``:
   - one coordinate: the interval ``[min g, max g]`` (interval arithmetic, exact for ``g = z``);
   - ``(cos z, sin z)``: the arc circumscribed by tangents at ``k`` equally spaced angles (each
     arc piece lies in the triangle of its end points and the tangents' intersection);
   - anything else: the corners of interval boxes over ``k`` pieces of ``[lo, hi]``.
   A feature that does not factor gets the interval of its value over the whole box.
3. Vertices. ``phi`` is multilinear in the block coordinates, and a multilinear map sends a
   product of polytopes into the hull of the images of vertex tuples (fix all blocks but one:
   the map is affine in it). So ``J(Z) in conv{J_0 + sum_k phi_k(v) M_k : v in prod_z V_z}``.
   Linear dynamics have no features and give one vertex, the exact Jacobian.

Floating point. Interval bounds use outward-rounded interval arithmetic (``mpmath.iv``); their
end points are rounded outward again when converted to floats, so they hold exactly. The arc
polygon's vertices come from ``math.cos``/``math.sin``, whose error is below 1 ulp (< 2.3e-16 on
the unit circle). Scaling the tangent polygon by ``1 + PAD`` (``PAD = 1e-9``) moves the tangent
edges out by ``PAD``; widening the arc by ``PAD`` rad at each end puts the chord at least
``PAD sin(alpha / 2)`` beyond the arc's end points, alpha >= ``MIN_ARC = 1e-4`` rad its width
(narrower arcs are widened): >= 5e-14, over 200 times that error. (A degenerate interval,
``upper <= lower``, gives the rounded point ``(cos a, sin a)`` alone.) The
vertex sums ``J_0 + sum_k phi_k M_k`` are rounded to nearest (relative 1e-16 of the largest term);
the certificates that use the hull keep a margin (``EPS = 1e-3`` in their LMIs) far above that.

Speed. Steps 1-2 are symbolic and depend on the dynamics alone; they are computed once per
``Dynamics`` object (``_structure``, cached by identity: ``Dynamics`` is frozen, and a scenario
loaded again or modified is a new object with its own entry). Only the interval bounds of the
blocks over the given box and step 3 run per call, exactly as before, so caching changes no
number: every bound is still evaluated in outward-rounded ``mpmath.iv`` arithmetic over the box
it is asked for (``tests/test_hull_rounding.py``).

``abs``: the Jacobian of ``|h(z)|`` is ``sign(h) h_z`` with ``sign(0) = 0``. Its range over an
interval ``[a, b]`` of ``h`` is ``[sign a, sign b]`` (exact in the interval arithmetic above),
which holds the generalised (Clarke) derivative ``[-1, 1]`` at the kink whenever ``a < 0 < b``.
The certificate's argument integrates the Jacobian along the segment between two states; ``f`` is
Lipschitz there and the integral is exact with the a.e. Jacobian (where the segment runs inside
the kink, ``h`` is constant along it and the term is zero, as ``sign(0) = 0`` gives). So the hull
of these ranges is sound.
"""

from __future__ import annotations

import functools
import itertools
import math
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mpmath
import numpy as np
import sympy
from mpmath import iv

from pipeline.model.dynamics import Dynamics, FloatArray

PAD = 1e-9
DEFAULT_SEGMENTS = 8
MAX_SEGMENT_ANGLE = math.pi / 4
MARGIN = 1e-12  # outward margin of the compact arc polygon's edges
MIN_ARC = 1e-4  # narrower arcs are widened to this (rad), so that PAD's margin stays large
MAX_VERTICES = 4096


class HullError(ValueError):
    """The Jacobian cannot be enclosed over the given region (unbounded variable, bad function)."""


@dataclass(frozen=True, kw_only=True)
class JacobianHull:
    """Vertices of a polytope containing ``[f_x f_u]`` over ``region``.

    Attributes:
      vertices: (V, n, n+m) matrices ``[A_i B_i]``.
      region: variable name -> (lower, upper), the box it holds over.
      blocks: one line per block saying how it was enclosed (for reports).
    """

    vertices: FloatArray
    region: Mapping[str, tuple[float, float]]
    blocks: tuple[str, ...]

    @property
    def A(self) -> FloatArray:
        """(V, n, n) state Jacobian vertices."""
        n = self.vertices.shape[1]
        return self.vertices[:, :, :n]

    @property
    def B(self) -> FloatArray:
        """(V, n, m) input Jacobian vertices."""
        n = self.vertices.shape[1]
        return self.vertices[:, :, n:]


def arc_polygon(
    lower: float, upper: float, segments: int = DEFAULT_SEGMENTS, compact: bool = False
) -> FloatArray:
    """Vertices (segments+4, 2) of a polygon containing ``{(cos a, sin a) : a in [lower, upper]}``.

    The arc's end points and the intersections of the tangents at ``segments + 1`` equally spaced
    angles (at mid-angles, distance ``1 / cos(delta / 2)`` from the origin). Against rounding, the
    arc is widened by ``PAD`` radians at each end (margin along the chord) and the tangent polygon
    is scaled by ``1 + PAD`` (margin along the tangents; the unscaled end points keep the chord).

    ``compact``: ``segments + 2`` vertices instead (a triangle for one segment, as the local
    hulls of a funnel want): the polygon of the end points and tangent intersections, inflated
    about its centroid ``c`` by ``1 + max(PAD, MARGIN / min_edge dist(c, edge))``, which moves
    every edge outward by at least ``MARGIN = 1e-12``, over 1000 times the vertices' rounding.
    """
    if upper <= lower:
        return np.array([[math.cos(lower), math.sin(lower)]])
    middle, half = (lower + upper) / 2, max(upper - lower, MIN_ARC) / 2
    if compact:
        lower, upper = middle - half, middle + half
        segments = max(segments, math.ceil((upper - lower) / MAX_SEGMENT_ANGLE))
        delta = (upper - lower) / segments
        mids = lower + delta * (np.arange(segments) + 0.5)
        tangents = np.column_stack([np.cos(mids), np.sin(mids)]) / math.cos(delta / 2)
        ends = np.array([[math.cos(lower), math.sin(lower)], [math.cos(upper), math.sin(upper)]])
        polygon = np.vstack([ends[:1], tangents, ends[1:]])
        c = polygon.mean(axis=0)
        a, b = polygon, np.roll(polygon, -1, axis=0)
        edge = b - a
        cross = edge[:, 0] * (c - a)[:, 1] - edge[:, 1] * (c - a)[:, 0]
        distance = np.abs(cross) / np.linalg.norm(edge, axis=1)
        return c + (1.0 + max(PAD, MARGIN / distance.min())) * (polygon - c)
    lower, upper = middle - half - PAD, middle + half + PAD
    segments = max(segments, math.ceil((upper - lower) / MAX_SEGMENT_ANGLE))
    delta = (upper - lower) / segments
    mids = lower + delta * (np.arange(segments) + 0.5)
    tangents = np.column_stack([np.cos(mids), np.sin(mids)]) / math.cos(delta / 2)
    ends = np.array([[math.cos(lower), math.sin(lower)], [math.cos(upper), math.sin(upper)]])
    scaled = (1.0 + PAD) * np.vstack([ends[:1], tangents, ends[1:]])
    return np.vstack([ends[:1], scaled, ends[1:]])


def _monotone(function: str, x: mpmath.ctx_iv.ivmpf) -> mpmath.ctx_iv.ivmpf:
    """``function`` (increasing) of the interval ``x``: end points at 120 bits, widened by
    2^-100 relative (far above the 120-bit error), rounded outward to 53 bits by ``iv.mpf``."""
    with mpmath.workprec(120):
        ends = [getattr(mpmath, function)(end) for end in (x.a, x.b)]
        widen = mpmath.mpf(2) ** -100
        ends = [ends[0] - abs(ends[0]) * widen, ends[1] + abs(ends[1]) * widen]
    return iv.mpf(ends)


def _interval(expression: sympy.Expr, box: Mapping[sympy.Symbol, tuple[float, float]]):
    """``expression`` over ``box`` in outward-rounded interval arithmetic (``mpmath.iv``)."""
    args = [_interval(a, box) for a in expression.args]
    if expression.is_Symbol:
        return iv.mpf(list(box[expression]))
    if expression.is_Integer:
        return iv.mpf(int(expression))
    if expression.is_Rational:
        return iv.mpf(int(expression.p)) / iv.mpf(int(expression.q))
    if expression.is_Float:
        return iv.mpf(mpmath.mpf(expression._mpf_))  # the constant's exact binary value
    if expression in (sympy.pi, sympy.E):
        return iv.pi if expression == sympy.pi else iv.e
    if expression.is_Add:
        return functools.reduce(operator.add, args)
    if expression.is_Mul:
        return functools.reduce(operator.mul, args)
    if expression.is_Pow:
        base, exponent = expression.args
        if exponent.is_Integer:
            return args[0] ** int(exponent)  # even powers are nonnegative
        if exponent == sympy.Rational(1, 2):
            return iv.sqrt(args[0])
        return iv.exp(args[1] * iv.log(args[0]))
    if isinstance(expression, sympy.Abs):
        return abs(args[0])
    if isinstance(expression, sympy.sign):  # non-decreasing: [sign a, sign b]
        return iv.mpf([int(mpmath.sign(args[0].a)), int(mpmath.sign(args[0].b))])
    if isinstance(expression, (sympy.tanh, sympy.atan)):
        return _monotone(type(expression).__name__, args[0])
    name = type(expression).__name__
    if name in ("sin", "cos", "tan", "exp", "log", "atan2"):
        return getattr(iv, name)(*args)
    raise HullError(f"cannot bound '{expression}' by interval arithmetic ({name})")


def _bounds(expression: sympy.Expr, box: Mapping[sympy.Symbol, tuple[float, float]]) -> FloatArray:
    """Sound ``[lower, upper]`` of ``expression`` over ``box``: outward-rounded interval
    arithmetic (``mpmath.iv``, 53 bits), end points rounded outward again when made floats."""
    try:
        value = _interval(expression, {s: (float(b[0]), float(b[1])) for s, b in box.items()})
    except (ZeroDivisionError, ValueError) as error:
        if isinstance(error, HullError):
            raise
        raise HullError(f"cannot bound '{expression}' over {dict(box)}: {error}") from None
    lower, upper = float(value.a), float(value.b)
    if mpmath.mpf(lower) > value.a:
        lower = float(np.nextafter(lower, -np.inf))
    if mpmath.mpf(upper) < value.b:
        upper = float(np.nextafter(upper, np.inf))
    if not (math.isfinite(lower) and math.isfinite(upper)):
        raise HullError(f"'{expression}' is unbounded over {dict(box)}: [{lower}, {upper}]")
    return np.array([lower, upper])


def interval_of(
    expression: sympy.Expr, box: Mapping[sympy.Symbol, tuple[float, float]]
) -> tuple[float, float]:
    """Sound ``(lower, upper)`` floats of ``expression`` over ``box`` (``_bounds``)."""
    lower, upper = _bounds(expression, box)
    return float(lower), float(upper)


def unique_rows(array: FloatArray) -> FloatArray:
    """``np.unique(array, axis=0)`` for a finite float array ``(k, ...)`` with no ``-0.0``
    entry: its distinct rows in lexicographic order, by a lexsort of the flattened rows (~4x
    faster for the hulls' 6-24 vertices; ``np.unique`` sorts a structured view). The same array:
    rows equal as values are equal as bytes when no entry is ``-0.0`` (the hull's vertices are
    sums onto ``+0.0``, which never give ``-0.0``), so which of them is kept does not matter."""
    flat = array.reshape(len(array), -1)
    ordered = flat[np.lexsort(flat.T[::-1])]
    distinct = np.ones(len(ordered), dtype=bool)
    distinct[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    return ordered[distinct].reshape(-1, *array.shape[1:])


@functools.lru_cache(maxsize=256)
def _text(expression: sympy.Expr) -> str:
    """``str(expression)`` (sympy prints it anew on every call), for the blocks' descriptions."""
    return str(expression)


def _block_vertices(
    z: sympy.Symbol,
    functions: Sequence[sympy.Expr],
    lower: float,
    upper: float,
    segments: int,
    compact: bool,
) -> tuple[FloatArray, str]:
    """Vertices (k, p) of a polytope containing ``{(g_1(z), .., g_p(z)) : z in [lower, upper]}``."""
    if len(functions) == 1:
        interval = _bounds(functions[0], {z: (lower, upper)})
        return interval[:, None], f"{_text(functions[0])} in [{interval[0]:.6g}, {interval[1]:.6g}]"
    if set(functions) == {sympy.cos(z), sympy.sin(z)}:
        polygon = arc_polygon(lower, upper, segments, compact)
        if functions[0] == sympy.sin(z):
            polygon = polygon[:, ::-1]
        return polygon, f"(cos {z}, sin {z}) on [{lower:g}, {upper:g}]: {len(polygon)}-gon"
    edges = np.linspace(lower, upper, segments + 1)
    corners: list[tuple[float, ...]] = []
    for a, b in itertools.pairwise(edges):
        intervals = [_bounds(g, {z: (a, b)}) for g in functions]
        corners.extend(itertools.product(*intervals))
    return np.unique(np.array(corners), axis=0), (
        f"({', '.join(map(str, functions))}) on [{lower:g}, {upper:g}]: boxes over {segments}"
        " pieces"
    )


@dataclass(frozen=True, kw_only=True)
class _Structure:
    """Steps 1-2 of the module docstring for one ``Dynamics`` (symbolic; cached per object).

    Attributes:
      depends_on: names of the variables the Jacobian depends on; J0: (n, n+m) constant part.
      features: (feature, M (n, n+m), its factorisation: (variable or None, part) keys).
      parts: variable -> its single-variable parts g_z; whole: features that do not factor.
    """

    depends_on: tuple[str, ...]
    J0: FloatArray
    features: tuple[tuple[sympy.Expr, FloatArray, tuple[tuple[object, sympy.Expr], ...]], ...]
    parts: Mapping[sympy.Symbol, tuple[sympy.Expr, ...]]
    whole: tuple[sympy.Expr, ...]


@functools.lru_cache(maxsize=16)
def _structure(dynamics: Dynamics, inputs: int | None = None) -> _Structure:
    """The symbolic decomposition of ``[f_x f_u]``, of its first ``inputs`` input columns when
    given (``Dynamics`` is frozen and hashed by identity, so the cache holds one entry per
    loaded scenario and column count)."""
    n, m = dynamics.n, dynamics.m if inputs is None else inputs
    entries = sympy.Matrix.hstack(dynamics.jacobian_x, dynamics.jacobian_u[:, :m])
    variables = entries.free_symbols

    # 1. J(z) = J_0 + sum_k phi_k(z) M_k.
    J0 = np.zeros((n, n + m))
    features: dict[sympy.Expr, FloatArray] = {}
    for (i, j), entry in np.ndenumerate(np.array(entries.tolist(), dtype=object)):
        for term in sympy.Add.make_args(sympy.expand(entry)):
            coefficient, feature = term.as_coeff_Mul()
            if feature.is_number:
                J0[i, j] += float(coefficient * feature)
                continue
            features.setdefault(feature, np.zeros((n, n + m)))[i, j] += float(coefficient)

    # 2. Split each feature into single-variable parts g_z (or keep it whole).
    parts: dict[sympy.Symbol, list[sympy.Expr]] = {}
    whole: list[sympy.Expr] = []
    factorisation: list[tuple[tuple[object, sympy.Expr], ...]] = []
    for feature in features:
        by_variable: dict[sympy.Symbol, sympy.Expr] = {}
        separable = True
        for factor in sympy.Mul.make_args(feature):
            free = factor.free_symbols
            if len(free) != 1:
                separable = False
                break
            (z,) = free
            by_variable[z] = by_variable.get(z, sympy.Integer(1)) * factor
        if separable:
            factorisation.append(tuple(by_variable.items()))
            for z, g in by_variable.items():
                if g not in parts.setdefault(z, []):
                    parts[z].append(g)
        else:
            factorisation.append(((None, feature),))
            whole.append(feature)
    J0.flags.writeable = False
    for M in features.values():
        M.flags.writeable = False
    return _Structure(
        depends_on=tuple(
            z.name for z in (*dynamics.state_symbols, *dynamics.input_symbols) if z in variables
        ),
        J0=J0,
        features=tuple(
            (feature, M, keys)
            for (feature, M), keys in zip(features.items(), factorisation, strict=True)
        ),
        parts={z: tuple(functions) for z, functions in parts.items()},
        whole=tuple(whole),
    )


def arc_variables(dynamics: Dynamics) -> tuple[str, ...]:
    """Names of the variables whose block is ``(cos z, sin z)`` (enclosed by ``arc_polygon``:
    ``ceil(width / MAX_SEGMENT_ANGLE)`` segments at least, so a wider box costs vertices)."""
    return tuple(
        z.name
        for z, functions in _structure(dynamics, None).parts.items()
        if set(functions) == {sympy.cos(z), sympy.sin(z)}
    )


def jacobian_hull(
    dynamics: Dynamics,
    region: Mapping[str, tuple[float, float]],
    segments: int = DEFAULT_SEGMENTS,
    compact: bool = False,
    inputs: int | None = None,
) -> JacobianHull:
    """A sound polytope of ``[f_x f_u]`` over the box ``region`` (name -> (lower, upper)).

    Every variable the Jacobian depends on must be bounded by ``region``, by an interval
    (``lower <= upper``, else ``HullError``: an empty box has no hull); ``segments`` is the
    number of pieces per angle-like block (the arc polygon's tangents, or interval boxes);
    ``compact`` asks for the arc polygon with fewer vertices (``arc_polygon``). ``inputs``: only
    the first ``inputs`` columns of ``f_u`` (the rest, e.g. uncertain parameters appended as
    inputs, ``pipeline.model.uncertainty``, are then variables of the box alone): vertices
    ``(V, n, n + inputs)``; the projection of a hull of the whole Jacobian would hold the same
    matrices, at the cost of the dropped columns' features.
    """
    n, m = dynamics.n, dynamics.m if inputs is None else inputs
    structure = _structure(dynamics, inputs)
    symbols = {s.name: s for s in (*dynamics.state_symbols, *dynamics.input_symbols)}
    missing = [name for name in structure.depends_on if name not in region]
    if missing:
        raise HullError(
            f"the Jacobian depends on {missing} but the operating region does not bound them; "
            f"add them to operating_region (it has {sorted(region)})"
        )
    box = {
        symbols[name]: (float(region[name][0]), float(region[name][1]))
        for name in structure.depends_on
    }
    for z, (lower, upper) in box.items():  # mpmath's iv.mpf only asserts this (gone under -O)
        if not lower <= upper:
            raise HullError(
                f"{z} in [{lower:.6g}, {upper:.6g}]: not an interval (expected lower <= upper; "
                "a box clipped to bounds it lies outside of is empty)"
            )
    J0, parts, whole = structure.J0, structure.parts, structure.whole

    # Blocks: vertices (k_b, p_b) and the coordinate of each (variable, g) or whole feature.
    block_vertices: list[FloatArray] = []
    descriptions: list[str] = []
    coordinate: dict[tuple[object, sympy.Expr], tuple[int, int]] = {}
    for z, functions in parts.items():
        lower, upper = box[z]
        vertices, text = _block_vertices(z, functions, lower, upper, segments, compact)
        for p, g in enumerate(functions):
            coordinate[(z, g)] = (len(block_vertices), p)
        block_vertices.append(vertices)
        descriptions.append(text)
    for feature in whole:
        interval = _bounds(feature, {s: box[s] for s in feature.free_symbols})
        coordinate[(None, feature)] = (len(block_vertices), 0)
        block_vertices.append(interval[:, None])
        descriptions.append(f"{_text(feature)} in [{interval[0]:.6g}, {interval[1]:.6g}] (whole)")

    # 3. Vertices: every tuple of block vertices.
    count = math.prod(len(v) for v in block_vertices)
    if count > MAX_VERTICES:
        raise HullError(
            f"the Jacobian hull would have {count} vertices (> {MAX_VERTICES}); "
            "reduce segments or the number of variables in the operating region"
        )
    grids = np.meshgrid(*[np.arange(len(v)) for v in block_vertices], indexing="ij")
    choice = [g.ravel() for g in grids]  # block b -> (count,) vertex index
    vertices = np.broadcast_to(J0, (count, n, n + m)).copy()
    for _, M, parts_of in structure.features:
        value = np.ones(count)
        for key in parts_of:
            b, p = coordinate[key]
            value = value * block_vertices[b][choice[b], p]
        vertices += value[:, None, None] * M
    vertices = unique_rows(vertices)
    return JacobianHull(vertices=vertices, region=dict(region), blocks=tuple(descriptions))
