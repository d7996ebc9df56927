"""Restricted arithmetic expressions for coefficients (never Python ``eval``).

Grammar: decimal numbers (``2``, ``0.25``, ``1e-3``), ``+ - * / **``, parentheses, the
functions ``sqrt`` and ``cbrt``, the constant ``pi`` and names defined earlier in the same
file. The text is parsed with :mod:`ast` and every node is checked against that whitelist
before anything is evaluated; attribute access, calls of anything else, subscripts,
lambdas, comprehensions, strings, complex and boolean literals are refused.

An expression evaluates in two backends: ``float`` (the numeric core) and ``mpmath`` (the
high-precision reference used by ``--verify`` and the tests), where decimal literals are read
exactly from their text. The float evaluation runs first and guards the other: a result that
overflows (``9**9**9**9``), is complex or is not finite is an error. A float value whose
rounding bound (:func:`evaluate_with_bound`) exceeds a few ulps, as after cancellation, is
replaced by the correctly rounded value of an evaluation at 50 digits.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Callable
from typing import Any, NamedTuple

MAX_LENGTH = 1000
EPS = 2.0 ** -52
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
        called = {n.func.id for n in ast.walk(self.tree)
                  if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
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
        literal = ast.get_source_segment(source, node)
        assert literal is not None  # a node parsed from source has its segment
        return bk.number(literal)
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
        assert isinstance(node.func, ast.Name)  # (_check_node: only named functions)
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


#: A decimal literal with at least this many significant digits is taken as the rounding of
#: the value its author meant (see :func:`written_rounding`); a shorter one is exact.
ROUNDED_DIGITS = 10
#: ... to its last digit, or to this many ulps of float64, whichever is coarser: a float64
#: printed to 17 digits is within an ulp of the value it rounds, itself computed with a few
#: roundings.
ROUNDED_ULPS = 4


def significant_digits(literal: str) -> int:
    """Significant digits a decimal literal is written with: from its first nonzero digit
    to its last written one (``0.0250`` has 3, ``1e-12`` 1; an integer's trailing zeros do
    not count, ``1000`` has 1)."""
    mantissa = literal.lower().split("e")[0]
    if "." not in mantissa:
        mantissa = mantissa.rstrip("0")
    digits = mantissa.replace(".", "").lstrip("0")
    return max(len(digits), 1)


def written_rounding(literal: str) -> float:
    """How far the value a decimal literal was written for may lie from the literal: 0 for
    a literal of fewer than :data:`ROUNDED_DIGITS` significant digits (``0.5``, ``1e-12``,
    ``3``: exact as written), else half a unit of its last digit or
    :data:`ROUNDED_ULPS` ulps of float64, whichever is larger."""
    if significant_digits(literal) < ROUNDED_DIGITS:
        return 0.0
    value = abs(float(literal))
    mantissa, _, exponent = literal.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    last_digit = 10.0 ** (int(exponent or 0) - decimals)
    return max(0.5 * last_digit, ROUNDED_ULPS * EPS * value)


def evaluate_with_bound(expr: Expression, names: dict[str, float],
                        errors: dict[str, float], written: bool = False
                        ) -> tuple[float, float]:
    """Float value of ``expr`` and a first-order bound on its distance from the exact value
    of the decimal text (``errors`` bound the names' values alike). Cancellation shows up as
    a bound large against the value: ``((1e16 + 0.25) - 1e16) + 0.75`` is 0.75 in float64
    with a bound of about 2, the exact value being 1.

    With ``written``, the bound is instead on the distance of the exact value of the text
    from the value its author meant: each literal may be off by its
    :func:`written_rounding`, the arithmetic and ``pi`` are exact (the float value is only
    used to scale the bound)."""
    half = 0.0 if written else EPS / 2

    def go(node: ast.AST) -> tuple[float, float]:
        if isinstance(node, ast.Constant):
            text = ast.get_source_segment(expr.text, node) or repr(node.value)
            v = float(text)
            return v, (written_rounding(text) if written else half * abs(v))
        if isinstance(node, ast.Name):
            if node.id == "pi":
                return math.pi, half * math.pi
            return names[node.id], errors.get(node.id, 0.0)
        if isinstance(node, ast.UnaryOp):
            v, e = go(node.operand)
            return (-v if isinstance(node.op, ast.USub) else v), e
        if isinstance(node, ast.Call):
            assert isinstance(node.func, ast.Name)  # (_check_node: only named functions)
            x, e = go(node.args[0])
            if node.func.id == "sqrt":
                v = _float_sqrt(x)
                return v, (e / (2 * v) if v else math.sqrt(e)) + half * v
            v = math.cbrt(x)
            return v, (e / (3 * v * v) if v else abs(e) ** (1 / 3)) + half * abs(v)
        assert isinstance(node, ast.BinOp)
        (a, ea), (b, eb) = go(node.left), go(node.right)
        op = node.op
        if isinstance(op, (ast.Add, ast.Sub)):
            v = a + b if isinstance(op, ast.Add) else a - b
            return v, ea + eb + half * abs(v)
        if isinstance(op, ast.Mult):
            v = a * b
            return v, abs(a) * eb + abs(b) * ea + half * abs(v)
        if isinstance(op, ast.Div):
            if b == 0 or eb >= abs(b) / 2:
                return a / b if b else math.inf, math.inf
            v = a / b
            return v, (ea + abs(v) * eb) / abs(b) + half * abs(v)
        v = a ** b
        if not isinstance(v, float) or not math.isfinite(v):
            return float("nan"), math.inf
        log_a = math.log(abs(a)) if a else 0.0
        rel = (abs(b) * ea / abs(a) if a else (0.0 if ea == 0 else math.inf)) \
            + abs(log_a) * eb
        return v, abs(v) * (rel + (abs(b) + 1) * 2 * half)

    try:
        return go(expr.tree)
    except (OverflowError, ZeroDivisionError, ValueError, ExpressionError):
        return math.nan, math.inf


def value_of(text: Any, names: dict[str, Any] | None = None, backend: Backend = FLOAT) -> Any:
    """Parse and evaluate in one step (``text`` a string, int or float)."""
    if isinstance(text, bool):
        raise ExpressionError("expected a number, got a boolean")
    if isinstance(text, (int, float)):
        text = repr(text)
    return evaluate(parse(text), names, backend)
