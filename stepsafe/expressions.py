"""Restricted arithmetic expressions for coefficients (never Python ``eval``).

Grammar: decimal numbers (``2``, ``0.25``, ``1e-3``), ``+ - * / **``, parentheses, the
functions ``sqrt`` and ``cbrt``, the constant ``pi`` and names defined earlier in the same
file. The text is parsed with :mod:`ast` and every node is checked against that whitelist
before anything is evaluated; attribute access, calls of anything else, subscripts,
lambdas, comprehensions, strings, complex and boolean literals are refused.

An expression evaluates in two backends: ``float`` (the numeric core) and ``mpmath`` (the
high-precision reference used by ``--verify`` and the tests), where decimal literals are read
exactly from their text. The float evaluation runs first and guards the other: a result that
overflows (``9**9**9**9``), is complex or is not finite is an error.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Callable
from typing import Any, NamedTuple

MAX_LENGTH = 1000
MAX_NODES = 400
_NUMBER = re.compile(r"^(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?$")
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
FUNCTIONS = ("sqrt", "cbrt")
BUILTIN_NAMES = ("pi",)


class ExpressionError(ValueError):
    """The text is not an allowed expression, or it does not evaluate to a finite real."""


class Expression(NamedTuple):
    """A validated expression: its text and checked syntax tree."""

    text: str
    tree: ast.AST

    @property
    def names(self) -> set[str]:
        """Names used as values (not the called functions)."""
        called = {n.func.id for n in ast.walk(self.tree) if isinstance(n, ast.Call)}
        used = {n.id for n in ast.walk(self.tree) if isinstance(n, ast.Name)}
        return used - called


def parse(text: str, functions: tuple[str, ...] = FUNCTIONS) -> Expression:
    """Parse and whitelist-check ``text`` (calls only of ``functions``); raises
    :class:`ExpressionError`."""
    if not isinstance(text, str):
        raise ExpressionError("expected a number or an expression string, "
                              f"got {type(text).__name__}")
    source = text.strip()
    if not source:
        raise ExpressionError("empty expression")
    if len(source) > MAX_LENGTH:
        raise ExpressionError(f"expression longer than {MAX_LENGTH} characters")
    try:
        tree = ast.parse(source, mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        raise ExpressionError(f"not an arithmetic expression: {_clip(source)!r}") from None
    nodes = list(ast.walk(tree))
    if len(nodes) > MAX_NODES:
        raise ExpressionError(f"expression has more than {MAX_NODES} parts")
    for node in nodes:
        _check_node(node, source, functions)
    return Expression(source, tree.body)


def _clip(text: str, n: int = 40) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


_ALLOWED = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Constant, ast.Name, ast.Call,
            ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd, ast.Load)


def _check_node(node: ast.AST, source: str, functions: tuple[str, ...] = FUNCTIONS) -> None:
    if not isinstance(node, _ALLOWED):
        what = type(node).__name__
        raise ExpressionError(f"{what} is not allowed in an expression (only numbers, "
                              f"+ - * / **, parentheses, {', '.join(functions)}, pi, names)")
    if isinstance(node, ast.Constant):
        literal = ast.get_source_segment(source, node) or ""
        if type(node.value) not in (int, float) or not _NUMBER.match(literal):
            raise ExpressionError(f"{literal or repr(node.value)!r} is not a decimal number")
    elif isinstance(node, ast.Name):
        if not _NAME.match(node.id) or node.id.startswith("__"):
            raise ExpressionError(f"name {node.id!r} is not allowed")
    elif isinstance(node, ast.Call):
        if not isinstance(node.func, ast.Name) or node.func.id not in functions:
            raise ExpressionError(f"only {', '.join(f + '(...)' for f in functions)} may be "
                                  "called")
        if len(node.args) != 1 or node.keywords:
            raise ExpressionError(f"{node.func.id} takes exactly one argument")


class Backend(NamedTuple):
    """Arithmetic used to evaluate an expression."""

    number: Callable[[str], Any]
    sqrt: Callable[[Any], Any]
    cbrt: Callable[[Any], Any]
    pi: Any
    check: Callable[[Any], Any]


def _float_check(value: Any) -> float:
    if isinstance(value, complex) or not math.isfinite(value):
        raise ExpressionError("the value is not a finite real number")
    return float(value)


def _float_sqrt(x: float) -> float:
    if x < 0:
        raise ExpressionError("sqrt of a negative number")
    return math.sqrt(x)


FLOAT = Backend(number=float, sqrt=_float_sqrt, cbrt=math.cbrt, pi=math.pi, check=_float_check)


def mpmath_backend() -> Backend:
    """The mpmath backend (imports mpmath; precision is the caller's ``mp.dps``)."""
    import mpmath

    def check(value):
        if not isinstance(value, mpmath.mpf) or not mpmath.isfinite(value):
            raise ExpressionError("the value is not a finite real number")
        return value

    return Backend(number=mpmath.mpf, sqrt=mpmath.sqrt, cbrt=mpmath.cbrt, pi=mpmath.pi, check=check)


def evaluate(expr: Expression, names: dict[str, Any] | None = None,
             backend: Backend = FLOAT) -> Any:
    """Value of ``expr`` with ``names`` bound (values already in ``backend``'s type)."""
    env = dict(names or {})
    try:
        return backend.check(_eval(expr.tree, expr.text, env, backend))
    except ExpressionError:
        raise
    except (OverflowError, ZeroDivisionError, ValueError, TypeError, RecursionError,
            MemoryError) as exc:
        kind = "division by zero" if isinstance(exc, ZeroDivisionError) else "the value overflows"
        if isinstance(exc, (ValueError, TypeError)):
            kind = "the value is not a finite real number"
        raise ExpressionError(kind) from None


def _eval(node: ast.AST, source: str, env: dict[str, Any], bk: Backend) -> Any:
    if isinstance(node, ast.Constant):
        return bk.number(ast.get_source_segment(source, node))
    if isinstance(node, ast.Name):
        if node.id == "pi":
            return bk.pi
        if node.id not in env:
            raise ExpressionError(f"unknown name {node.id!r} (define it earlier under constants)")
        return env[node.id]
    if isinstance(node, ast.UnaryOp):
        value = _eval(node.operand, source, env, bk)
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.Call):
        arg = bk.check(_eval(node.args[0], source, env, bk))
        return bk.check(bk.sqrt(arg) if node.func.id == "sqrt" else bk.cbrt(arg))
    assert isinstance(node, ast.BinOp)
    left = bk.check(_eval(node.left, source, env, bk))
    right = bk.check(_eval(node.right, source, env, bk))
    op = node.op
    if isinstance(op, ast.Add):
        return left + right
    if isinstance(op, ast.Sub):
        return left - right
    if isinstance(op, ast.Mult):
        return left * right
    if isinstance(op, ast.Div):
        if right == 0:
            raise ZeroDivisionError
        return left / right
    if abs(right) > 1e6 or (left < 0 and right != int(right)):
        raise ExpressionError("power out of range (negative base with a fractional exponent, "
                              "or an exponent above 1e6)")
    return left ** right


def value_of(text: Any, names: dict[str, Any] | None = None, backend: Backend = FLOAT) -> Any:
    """Parse and evaluate in one step (``text`` a string, int or float)."""
    if isinstance(text, bool):
        raise ExpressionError("expected a number, got a boolean")
    if isinstance(text, (int, float)):
        text = repr(text)
    return evaluate(parse(text), names, backend)
