"""Parse the scenario's dynamics expressions into sympy, from a restricted grammar.

The text is parsed with Python's ``ast`` module and translated node by node: numbers, declared
names, ``+ - * / **``, unary minus, and calls of a fixed list of functions. Anything else
(attributes, subscripts, lambdas, strings, unknown names) is refused, so no user text is ever
evaluated as Python.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping

import sympy

ALLOWED_FUNCTIONS: Mapping[str, object] = {
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
ALLOWED_CONSTANTS: Mapping[str, sympy.Expr] = {"pi": sympy.pi}

_BINARY = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: a**b,
}


class ExpressionError(ValueError):
    """The expression uses something outside the restricted grammar; the message says what."""


def parse_expression(text: str, symbols: Mapping[str, sympy.Symbol]) -> sympy.Expr:
    """Translate ``text`` into a sympy expression over ``symbols`` (name -> Symbol)."""
    try:
        tree = ast.parse(str(text).strip(), mode="eval")
    except SyntaxError as error:
        raise ExpressionError(f"not a valid expression ({error.msg})") from None
    return _translate(tree.body, symbols)


def _translate(node: ast.AST, symbols: Mapping[str, sympy.Symbol]) -> sympy.Expr:
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
        if isinstance(node.value, bool):
            raise ExpressionError(f"boolean {node.value} is not allowed")
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
        args = [_translate(arg, symbols) for arg in node.args]
        return ALLOWED_FUNCTIONS[node.func.id](*args)  # type: ignore[operator]
    raise ExpressionError(
        f"'{ast.unparse(node)}' is not allowed (numbers, names, + - * / **, calls)"
    )
