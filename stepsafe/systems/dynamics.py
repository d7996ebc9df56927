"""The equations of motion of a scene's system, for running methods on it
(:mod:`stepsafe.core.integrator`).

* a 1-dof Hamiltonian expression: its gradient by first-order forward automatic
  differentiation on numpy arrays (the same restricted expression language as
  :mod:`stepsafe.systems.nonlinear`, never ``eval``); separable when ``H_qp`` vanishes
  identically, which the expression's structure tells: ``H`` is a sum of terms each in q
  alone or p alone;
* a linear system ``H = p^T M^-1 p / 2 + q^T K q / 2`` (or ``x^T S x / 2``): the gradients
  are matrix products, and the exact flow is ``expm(J S t)``.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from stepsafe.core.integrator import System
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.nonlinear import Hamiltonian

_UNARY = {
    "sin": (np.sin, np.cos), "cos": (np.cos, lambda x: -np.sin(x)),
    "exp": (np.exp, np.exp), "log": (np.log, lambda x: 1.0 / x),
    "sqrt": (np.sqrt, lambda x: 0.5 / np.sqrt(x)), "cosh": (np.cosh, np.sinh),
    "sinh": (np.sinh, np.cosh), "tanh": (np.tanh, lambda x: 1.0 - np.tanh(x) ** 2),
}


class _Dual:
    """A value with its derivatives in q and p (arrays): first-order forward AD."""

    __slots__ = ("v", "dq", "dp")

    def __init__(self, v, dq=0.0, dp=0.0) -> None:
        self.v, self.dq, self.dp = v, dq, dp

    def __add__(self, o: _Dual) -> _Dual:
        return _Dual(self.v + o.v, self.dq + o.dq, self.dp + o.dp)

    def __sub__(self, o: _Dual) -> _Dual:
        return _Dual(self.v - o.v, self.dq - o.dq, self.dp - o.dp)

    def __mul__(self, o: _Dual) -> _Dual:
        return _Dual(self.v * o.v, self.v * o.dq + o.v * self.dq, self.v * o.dp + o.v * self.dp)

    def __truediv__(self, o: _Dual) -> _Dual:
        r = 1.0 / o.v
        return self * _Dual(r, -r * r * o.dq, -r * r * o.dp)

    def __neg__(self) -> _Dual:
        return _Dual(-self.v, -self.dq, -self.dp)

    def chain(self, f, df) -> _Dual:
        d = df(self.v)
        return _Dual(f(self.v), d * self.dq, d * self.dp)

    def power(self, o: _Dual, constant: bool) -> _Dual:
        if constant:
            n = o.v
            return _Dual(self.v ** n, n * self.v ** (n - 1) * self.dq,
                         n * self.v ** (n - 1) * self.dp)
        return (o * self.chain(np.log, lambda x: 1.0 / x)).chain(np.exp, np.exp)


def _constant(node: ast.AST) -> bool:
    return not any(isinstance(n, ast.Name) and n.id in ("q", "p") for n in ast.walk(node))


_BINARY = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b,
           ast.Mult: lambda a, b: a * b, ast.Div: lambda a, b: a / b}


def _compile(node: ast.AST, source: str, params: dict[str, _Dual]
             ) -> Callable[[dict[str, _Dual]], _Dual]:
    """The expression as nested closures of ``env`` (q and p): parsed once, evaluated on
    every step without walking the tree again."""
    if isinstance(node, ast.Constant):
        value = _Dual(float(ast.get_source_segment(source, node)))
        return lambda env: value
    if isinstance(node, ast.Name):
        if node.id in params:
            fixed = params[node.id]
            return lambda env: fixed
        name = node.id
        return lambda env: env[name]
    if isinstance(node, ast.UnaryOp):
        inner = _compile(node.operand, source, params)
        if isinstance(node.op, ast.USub):
            return lambda env: -inner(env)
        return inner
    if isinstance(node, ast.Call):
        f, df = _UNARY[node.func.id]
        arg = _compile(node.args[0], source, params)
        return lambda env: arg(env).chain(f, df)
    assert isinstance(node, ast.BinOp)
    left, right = _compile(node.left, source, params), _compile(node.right, source, params)
    if type(node.op) in _BINARY:
        op = _BINARY[type(node.op)]
        return lambda env: op(left(env), right(env))
    constant = _constant(node.right)
    return lambda env: left(env).power(right(env), constant)


def _terms(node: ast.AST) -> list[ast.AST]:
    """The terms of a sum (``a + b - c``)."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub)):
        return _terms(node.left) + _terms(node.right)
    if isinstance(node, ast.UnaryOp):
        return _terms(node.operand)
    return [node]


def separable_terms(tree: ast.AST) -> bool:
    """Whether every term of H involves q alone or p alone (then ``H_qp = 0``)."""
    for term in _terms(tree):
        names = {n.id for n in ast.walk(term) if isinstance(n, ast.Name)}
        if {"q", "p"} <= names:
            return False
    return True


def hamiltonian_system(H: Hamiltonian) -> System:
    """The 1-dof system of a Hamiltonian expression (arrays of shape (m, 1))."""
    tree, source = H.expression.tree, H.expression.text
    params = {k: _Dual(float(v)) for k, v in H.parameters.items()}
    params["pi"] = _Dual(math.pi)
    compiled = _compile(tree, source, params)

    def jet(q: np.ndarray, p: np.ndarray) -> _Dual:
        env = {"q": _Dual(q, 1.0, 0.0), "p": _Dual(p, 0.0, 1.0)}
        with np.errstate(all="ignore"):
            return compiled(env)

    def full(x: Any, like: np.ndarray) -> np.ndarray:
        if isinstance(x, np.ndarray) and x.shape == like.shape:
            return x
        return np.broadcast_to(np.asarray(x, dtype=float), like.shape).copy()

    def vector_field(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = jet(q, p)
        return full(d.dp, p), -full(d.dq, q)

    def hessian(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """Second derivatives by the second-order jets of stepsafe.systems.nonlinear."""
        blocks = np.empty((3, q.shape[0], 1, 1))
        for k in range(q.shape[0]):
            blocks[:, k, 0, 0] = H.jet(float(q[k, 0]), float(p[k, 0])).H
        return blocks[0], blocks[1], blocks[2]

    return System(dH_dq=lambda q, p: full(jet(q, p).dq, q),
                  dH_dp=lambda q, p: full(jet(q, p).dp, p),
                  energy=lambda q, p: full(jet(q, p).v, q)[:, 0], separable=separable_terms(tree),
                  dimension=1, vector_field=vector_field, hessian=hessian)


def linear_system(S: np.ndarray) -> System:
    """``H = x^T S x / 2``, ``x = (q, p)`` (S symmetric 2n x 2n)."""
    n = S.shape[0] // 2
    S_qq, S_qp, S_pq, S_pp = S[:n, :n], S[:n, n:], S[n:, :n], S[n:, n:]
    separable = not S_qp.any()

    def energy(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = np.hstack([q, p])
        return 0.5 * np.einsum("mi,mi->m", x @ S, x)  # (a matrix product: BLAS)

    def hessian(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        m = q.shape[0]
        return tuple(np.broadcast_to(B, (m, n, n)) for B in (S_qq, S_qp, S_pp))

    return System(dH_dq=lambda q, p: q @ S_qq.T + p @ S_pq.T,
                  dH_dp=lambda q, p: q @ S_qp.T + p @ S_pp.T,
                  energy=energy, separable=separable, dimension=n, hessian=hessian)


def stiffness_hessian(K: np.ndarray, M: np.ndarray | None) -> np.ndarray:
    """``S = blockdiag(K, M^-1)`` of ``H = p^T M^-1 p / 2 + q^T K q / 2``."""
    n = K.shape[0]
    Minv = np.eye(n) if M is None else np.linalg.inv(M)
    zero = np.zeros((n, n))
    return np.block([[K, zero], [zero, 0.5 * (Minv + Minv.T)]])


def exact_linear(S: np.ndarray, x0: np.ndarray, t: float) -> np.ndarray:
    """``expm(J S t) x0`` (rows of x0 are states)."""
    from scipy.linalg import expm

    n = S.shape[0] // 2
    J = np.block([[np.zeros((n, n)), np.eye(n)], [-np.eye(n), np.zeros((n, n))]])
    return x0 @ expm(J @ S * t).T


def check_finite_start(system: System, q: np.ndarray, p: np.ndarray) -> None:
    """The energy and gradients at the start must be finite numbers."""
    values = (system.energy(q, p), system.dH_dq(q, p), system.dH_dp(q, p))
    if not all(np.all(np.isfinite(v)) for v in values):
        raise StepsafeError("H or its gradient is not finite at the initial condition")
