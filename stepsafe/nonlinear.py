"""Nonlinear 1-dof systems (paper Sec. 3): equilibria of H(q, p), their type, and the
linear model each one gives.

``H`` is a restricted expression in ``q``, ``p`` and named parameters (numbers, + - * / **,
sin, cos, exp, log, sqrt, cosh, sinh, tanh, pi; checked by :mod:`stepsafe.expressions`,
never ``eval``). Derivatives are exact: H is evaluated on second-order jets (value,
gradient, Hessian), i.e. forward-mode automatic differentiation, not finite differences.

Equilibria solve ``grad H = 0`` inside a box: Newton from a grid of starts, deduplicated.
Each is classified by ``D = H_qp^2 - H_qq H_pp`` (the paper's ``f_q g_p - f_p g_q``):
``D < 0`` elliptic, ``D > 0`` hyperbolic, ``D = 0`` degenerate (no linear model). Its exact
linearisation ``x' = L x``, ``L = [[H_pq, H_pp], [-H_qq, -H_qp]]``, maps to a test model
when a partition-preserving scaling ``q -> a q, p -> b p`` brings it there (which every
partitioned method commutes with):

* ``H_qp = 0``: ``oscillator`` with ``beta = sqrt(H_qq H_pp)`` if ``H_qq H_pp > 0``, else
  ``inverted`` with ``beta = sqrt(-H_qq H_pp)``;
* ``H_qq = H_pp = 0``: ``saddle`` (q expands) if ``H_qp > 0`` or ``saddle-p`` if ``H_qp < 0``,
  ``beta = |H_qp|``;
* otherwise the linearisation is analysed as a 2x2 Hessian (:mod:`stepsafe.systems`:
  decoupled for RK methods, coupled for partitioned ones).
"""

from __future__ import annotations

import ast
import math
from typing import NamedTuple

import numpy as np

from .errors import StepsafeError
from .expressions import Expression, ExpressionError, parse

FUNCTIONS = ("sin", "cos", "exp", "log", "sqrt", "cosh", "sinh", "tanh")


class Jet2:
    """A value with its gradient and Hessian in (q, p): second-order forward AD."""

    __slots__ = ("v", "g", "H")

    def __init__(self, v: float, g=None, H=None) -> None:
        self.v = float(v)
        self.g = np.zeros(2) if g is None else g
        self.H = np.zeros((2, 2)) if H is None else H

    @staticmethod
    def lift(x) -> Jet2:
        return x if isinstance(x, Jet2) else Jet2(x)

    def _chain(self, f0: float, f1: float, f2: float) -> Jet2:
        """``f(self)`` from f, f', f'' at self.v."""
        return Jet2(f0, f1 * self.g, f1 * self.H + f2 * np.outer(self.g, self.g))

    def __add__(self, o):
        o = Jet2.lift(o)
        return Jet2(self.v + o.v, self.g + o.g, self.H + o.H)

    __radd__ = __add__

    def __neg__(self):
        return Jet2(-self.v, -self.g, -self.H)

    def __sub__(self, o):
        return self + (-Jet2.lift(o))

    def __rsub__(self, o):
        return Jet2.lift(o) - self

    def __mul__(self, o):
        o = Jet2.lift(o)
        return Jet2(self.v * o.v, self.v * o.g + o.v * self.g,
                    self.v * o.H + o.v * self.H + np.outer(self.g, o.g) + np.outer(o.g, self.g))

    __rmul__ = __mul__

    def reciprocal(self):
        if self.v == 0:
            raise ZeroDivisionError
        return self._chain(1 / self.v, -1 / self.v**2, 2 / self.v**3)

    def __truediv__(self, o):
        return self * Jet2.lift(o).reciprocal()

    def __rtruediv__(self, o):
        return Jet2.lift(o) * self.reciprocal()

    def __pow__(self, o):
        o = Jet2.lift(o)
        if not o.g.any() and not o.H.any():  # constant exponent
            n, x = o.v, self.v
            if x == 0 and n == int(n) and n >= 0:
                k = int(n)
                return self._chain(0.0 if k else 1.0, 1.0 if k == 1 else 0.0,
                                   2.0 if k == 2 else 0.0)
            if x <= 0 and n != int(n):
                raise ValueError("power of a non-positive base")
            return self._chain(x**n, n * x ** (n - 1), n * (n - 1) * x ** (n - 2))
        return (o * self.log()).exp()

    def __rpow__(self, o):
        return Jet2.lift(o) ** self

    def exp(self):
        e = math.exp(self.v)
        return self._chain(e, e, e)

    def log(self):
        if self.v <= 0:
            raise ValueError("log of a non-positive number")
        return self._chain(math.log(self.v), 1 / self.v, -1 / self.v**2)

    def sqrt(self):
        if self.v <= 0:
            raise ValueError("sqrt at a non-positive number (not differentiable)")
        r = math.sqrt(self.v)
        return self._chain(r, 0.5 / r, -0.25 / (r * self.v))

    def sin(self):
        return self._chain(math.sin(self.v), math.cos(self.v), -math.sin(self.v))

    def cos(self):
        return self._chain(math.cos(self.v), -math.sin(self.v), -math.cos(self.v))

    def sinh(self):
        return self._chain(math.sinh(self.v), math.cosh(self.v), math.sinh(self.v))

    def cosh(self):
        return self._chain(math.cosh(self.v), math.sinh(self.v), math.cosh(self.v))

    def tanh(self):
        t = math.tanh(self.v)
        return self._chain(t, 1 - t * t, -2 * t * (1 - t * t))


class Hamiltonian(NamedTuple):
    expression: Expression
    parameters: dict[str, float]

    def jet(self, q: float, p: float) -> Jet2:
        env = {"q": Jet2(q, np.array([1.0, 0.0])), "p": Jet2(p, np.array([0.0, 1.0])),
               **{k: Jet2(v) for k, v in self.parameters.items()}, "pi": Jet2(math.pi)}
        try:
            out = _eval(self.expression.tree, self.expression.text, env)
        except (ZeroDivisionError, ValueError, OverflowError) as exc:
            raise ExpressionError(str(exc) or type(exc).__name__) from None
        return Jet2.lift(out)


def parse_hamiltonian(text: str, parameters: dict[str, float] | None = None) -> Hamiltonian:
    """A whitelisted H(q, p); unknown names are an error."""
    parameters = dict(parameters or {})
    for name in parameters:
        if name in ("q", "p", "pi") or name in FUNCTIONS or not name.isidentifier():
            raise ExpressionError(f"parameter name {name!r} is not allowed")
    expr = parse(text, FUNCTIONS)
    unknown = expr.names - {"q", "p", "pi"} - set(parameters)
    if unknown:
        raise ExpressionError(f"unknown name {sorted(unknown)[0]!r} (use q, p, pi and the "
                              "parameters)")
    return Hamiltonian(expr, parameters)


def _eval(node: ast.AST, source: str, env: dict[str, Jet2]):
    if isinstance(node, ast.Constant):
        return float(ast.get_source_segment(source, node))
    if isinstance(node, ast.Name):
        return env[node.id]
    if isinstance(node, ast.UnaryOp):
        value = _eval(node.operand, source, env)
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.Call):
        return getattr(Jet2.lift(_eval(node.args[0], source, env)), node.func.id)()
    assert isinstance(node, ast.BinOp)
    a, b = _eval(node.left, source, env), _eval(node.right, source, env)
    if isinstance(node.op, ast.Add):
        return Jet2.lift(a) + b
    if isinstance(node.op, ast.Sub):
        return Jet2.lift(a) - b
    if isinstance(node.op, ast.Mult):
        return Jet2.lift(a) * b
    if isinstance(node.op, ast.Div):
        return Jet2.lift(a) / b
    bv = b.v if isinstance(b, Jet2) else b
    if isinstance(b, (int, float)) or (not b.g.any() and not b.H.any()):
        if abs(bv) > 64:
            raise ValueError("exponent above 64")
    return Jet2.lift(a) ** b


class Equilibrium(NamedTuple):
    q: float
    p: float
    D: float
    kind: str  # "elliptic", "hyperbolic", "degenerate"
    hessian: np.ndarray  # [[H_qq, H_qp], [H_pq, H_pp]]
    beta: float | None
    model: str | None  # a test model, "coupled" (needs the 2x2 Hessian analysis) or None


def find_equilibria(H: Hamiltonian, box_q: tuple[float, float], box_p: tuple[float, float],
                    grid: int = 13) -> list[Equilibrium]:
    """All zeros of grad H in the box: Newton from a grid of starts, deduplicated."""
    (q0, q1), (p0, p1) = box_q, box_p
    if not (q0 < q1 and p0 < p1) or not all(map(math.isfinite, (q0, q1, p0, p1))):
        raise StepsafeError("the box needs finite q: [lo, hi] and p: [lo, hi] with lo < hi")
    size = max(q1 - q0, p1 - p0)
    found: list[np.ndarray] = []
    for qs in np.linspace(q0, q1, grid):
        for ps in np.linspace(p0, p1, grid):
            x = np.array([qs, ps])
            for _ in range(60):
                try:
                    j = H.jet(*x)
                except ExpressionError:
                    break
                try:
                    step = np.linalg.lstsq(j.H, j.g, rcond=1e-14)[0]
                except np.linalg.LinAlgError:
                    break
                x = x - step
                if not np.all(np.isfinite(x)) or np.abs(x).max() > 1e3 * (1 + size):
                    break
                if np.abs(step).max() <= 1e-15 * (1 + np.abs(x).max()):
                    break
            try:
                g = H.jet(*x).g
            except ExpressionError:
                continue
            inside = (q0 - 1e-9 * size <= x[0] <= q1 + 1e-9 * size and
                      p0 - 1e-9 * size <= x[1] <= p1 + 1e-9 * size)
            if inside and np.abs(g).max() <= 1e-10 * (1 + _grad_scale(H, x)) and not any(
                    np.abs(x - y).max() <= 1e-7 * (1 + size) for y in found):
                found.append(x)
    return [classify_equilibrium(H, x) for x in sorted(found, key=lambda v: (v[0], v[1]))]


def _grad_scale(H: Hamiltonian, x: np.ndarray) -> float:
    return float(np.abs(H.jet(*x).H).max())


def classify_equilibrium(H: Hamiltonian, x: np.ndarray) -> Equilibrium:
    j = H.jet(*x)
    Hqq, Hqp, Hpp = j.H[0, 0], j.H[0, 1], j.H[1, 1]
    D = Hqp * Hqp - Hqq * Hpp
    scale = max(abs(Hqq), abs(Hqp), abs(Hpp), 1e-300)
    tol = 1e-12 * scale * scale
    q, p = float(x[0]), float(x[1])
    if abs(D) <= tol:
        return Equilibrium(q, p, 0.0, "degenerate", j.H, None, None)
    kind = "elliptic" if D < 0 else "hyperbolic"
    if abs(Hqp) <= 1e-12 * scale:
        prod = Hqq * Hpp
        model = "oscillator" if prod > 0 else "inverted"
        return Equilibrium(q, p, D, kind, j.H, float(math.sqrt(abs(prod))), model)
    if abs(Hqq) <= 1e-12 * scale and abs(Hpp) <= 1e-12 * scale:
        return Equilibrium(q, p, D, kind, j.H, float(abs(Hqp)),
                           "saddle" if Hqp > 0 else "saddle-p")
    return Equilibrium(q, p, D, kind, j.H, float(math.sqrt(abs(D))), "coupled")
