"""Parse the scenario's dynamics expressions into sympy, from a restricted grammar.

The text is parsed with Python's ``ast`` module and translated node by node: numbers, declared
names, ``+ - * / **``, unary minus, and calls of a fixed list of functions. Anything else
(attributes, subscripts, lambdas, strings, unknown names, keyword arguments) is refused, so no
user text is ever evaluated as Python. Powers of two numbers are computed in floating point, so a
text such as ``10**10**10`` cannot make sympy build a huge exact integer.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Mapping

import sympy

ALLOWED_FUNCTIONS: Mapping[str, Callable[..., sympy.Expr]] = {
    "sin": sympy.sin,
    "cos": sympy.cos,
    "tan": sympy.tan,
    "exp": sympy.exp,
    "log": sympy.log,
    "sqrt": sympy.sqrt,
    "tanh": sympy.tanh,
    "atan": sympy.atan,
    "atan2": sympy.atan2,
    "abs": sympy.Abs,
}
ARITY: Mapping[str, int] = {name: 2 if name == "atan2" else 1 for name in ALLOWED_FUNCTIONS}
ALLOWED_CONSTANTS: Mapping[str, sympy.Expr] = {"pi": sympy.pi}
MAX_LENGTH = 10_000

_BINARY = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: _power(a, b),
}


class ExpressionError(ValueError):
    """The expression uses something outside the restricted grammar; the message says what."""


def parse_expression(text: str, symbols: Mapping[str, sympy.Symbol]) -> sympy.Expr:
    """Translate ``text`` into a sympy expression over ``symbols`` (name -> Symbol)."""
    text = str(text).strip()
    if len(text) > MAX_LENGTH:
        raise ExpressionError(f"expression is {len(text)} characters long (at most {MAX_LENGTH})")
    try:
        tree = ast.parse(text, mode="eval")
        return _translate(tree.body, symbols)
    except SyntaxError as error:
        raise ExpressionError(f"not a valid expression ({error.msg})") from None
    except (RecursionError, MemoryError):
        raise ExpressionError("expression is nested too deeply") from None


def _power(base: sympy.Expr, exponent: sympy.Expr) -> sympy.Expr:
    """``base**exponent``; between two numbers (``pi`` too): in float64, and it must be finite."""
    if not (base.is_number and exponent.is_number):
        return base**exponent
    try:
        a, b = float(base), float(exponent)
        value = a**b
    except TypeError:  # a complex operand
        raise ExpressionError(f"({base})**({exponent}) is not a finite real number") from None
    except (OverflowError, ZeroDivisionError):
        value = math.inf
    if not isinstance(value, float) or not math.isfinite(value):
        raise ExpressionError(f"({a:g})**({b:g}) is not a finite real number")
    return sympy.Float(value)


def _translate(node: ast.AST, symbols: Mapping[str, sympy.Symbol]) -> sympy.Expr:
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
        if isinstance(node.value, bool):
            raise ExpressionError(f"boolean {node.value} is not allowed")
        if not math.isfinite(node.value):
            raise ExpressionError(f"number '{ast.unparse(node)}' is not finite")
        return (
            sympy.Float(node.value) if isinstance(node.value, float) else sympy.Integer(node.value)
        )
    if isinstance(node, ast.Name):
        if node.id in symbols:
            return symbols[node.id]
        if node.id in ALLOWED_CONSTANTS:
            return ALLOWED_CONSTANTS[node.id]
        known = ", ".join(sorted(symbols))
        raise ExpressionError(f"unknown symbol '{node.id}' (known: {known}, pi)")
    if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
        return _BINARY[type(node.op)](
            _translate(node.left, symbols), _translate(node.right, symbols)
        )
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        operand = _translate(node.operand, symbols)
        return -operand if isinstance(node.op, ast.USub) else operand
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
        if node.func.id not in ALLOWED_FUNCTIONS:
            allowed = ", ".join(ALLOWED_FUNCTIONS)
            raise ExpressionError(f"unknown function '{node.func.id}' (allowed: {allowed})")
        arity = ARITY[node.func.id]
        if len(node.args) != arity:
            raise ExpressionError(
                f"'{ast.unparse(node)}': {node.func.id} takes {arity} argument"
                f"{'s' if arity > 1 else ''}, got {len(node.args)}"
            )
        args = [_translate(arg, symbols) for arg in node.args]
        return ALLOWED_FUNCTIONS[node.func.id](*args)
    raise ExpressionError(
        f"'{ast.unparse(node)}' is not allowed (numbers, names, + - * / **, calls)"
    )
