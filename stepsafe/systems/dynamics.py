"""The equations of motion of a scene's system, for running methods on it
(:mod:`stepsafe.core.integrator`).

* a Hamiltonian expression (1 or n degrees of freedom): its gradient compiled from the
  expression graph (:mod:`stepsafe.systems.compiler`); separable when ``H_qp`` vanishes
  identically, which the expression's structure tells: ``H`` is a sum of terms each in q
  alone or p alone;
* a linear system ``H = p^T M^-1 p / 2 + q^T K q / 2`` (or ``x^T S x / 2``): the gradients
  are matrix products, and the exact flow is ``expm(J S t)``.
"""

from __future__ import annotations

import ast
from typing import Any

import numpy as np

from stepsafe.core.integrator import System
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.compiler import Compiled
from stepsafe.systems.nonlinear import Hamiltonian


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
    return compiled_system(H.compiled, 1, separable_terms(H.expression.tree))


def compiled_system(compiled: Compiled, n: int, separable: bool,
                    where: str | None = None) -> System:
    """The system of a compiled Hamiltonian of n degrees of freedom (variables q then p):
    ``dH/dq`` and ``dH/dp`` are compiled apart (a separable H's force reads q alone), the
    vector field from the whole gradient, the energy and Hessian from the same graph.
    States are arrays of shape (m, n); a non-finite value is left to the caller (the
    engine stops a run that leaves the finite numbers)."""
    grad = compiled.gradient_nodes
    force = compiled.function(grad[:n])
    velocity = compiled.function(grad[n:])
    both = compiled.function(grad)
    energy_of = compiled.function([compiled.H])

    def columns(q: np.ndarray, p: np.ndarray) -> list[np.ndarray]:
        return [*q.T, *p.T]

    def stack(values: Any, like: np.ndarray) -> np.ndarray:
        out = np.empty(like.shape)
        for i, v in enumerate(values):
            out[:, i] = v
        return out

    def dH_dq(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            return stack(force(*columns(q, p)), q)

    def dH_dp(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            return stack(velocity(*columns(q, p)), p)

    def vector_field(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(all="ignore"):
            g = both(*columns(q, p))
        return stack(g[n:], p), -stack(g[:n], q)

    def energy(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            (v,) = energy_of(*columns(q, p))
        return np.broadcast_to(np.asarray(v, dtype=float), (q.shape[0],)).copy()

    def hessian(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        S = compiled.hessian(np.hstack([q, p]))
        return S[:, :n, :n], S[:, :n, n:], S[:, n:, n:]

    return System(dH_dq=dH_dq, dH_dp=dH_dp, energy=energy, separable=separable,
                  dimension=n, vector_field=vector_field, hessian=hessian)


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
