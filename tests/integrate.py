"""A small reference integrator for the tests, in mpmath arithmetic.

One step of a method on the pendulum-type problem H = p^2/2 + V(q), independent of
stepsafe's transfer matrices: splitting methods apply their drifts and kicks, compositions
apply the base with scaled steps, RK/PRK methods solve the nonlinear stage equations by
fixed-point iteration. Coefficients are read from the method files with the mpmath
backend of the expression evaluator (decimal literals exactly), so errors far below
float64 rounding can be measured: high-order methods need that to show their order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import mpmath as mp

from stepsafe.expressions import mpmath_backend
from stepsafe.families import lobatto3ab
from stepsafe.library import FAMILIES, _find_file, load_file


@dataclass
class MPMethod:
    kind: str
    order: int
    data: dict[str, Any]


def mp_method(name: str, stages: int | None = None) -> MPMethod:
    """The method ``name`` with coefficients in mpmath at the current precision."""
    if name in FAMILIES:
        import mpref

        def rows(A):
            return [[A[i, j] for j in range(A.cols)] for i in range(A.rows)] \
                if isinstance(A, mp.matrix) else [list(r) for r in A]

        if name == "gauss":
            A, b, _ = mpref.gauss_tableau(stages)
            A, b = rows(A), list(b)
            return MPMethod("prk", 2 * stages, {"A_q": A, "b_q": b, "A_p": A, "b_p": b})
        A, b, _ = mpref.lobatto_IIIA_tableau(stages)
        B, _, _ = mpref.lobatto_IIIB_tableau(stages)
        A, B, b = rows(A), rows(B), list(b)
        assert lobatto3ab(stages).stages == stages
        return MPMethod("prk", 2 * stages - 2, {"A_q": A, "b_q": b, "A_p": B, "b_p": b})
    data = load_file(_find_file(name), backend=mpmath_backend())
    co = dict(data.coefficients)
    if data.kind == "composition":
        base = mp_method(data.base if isinstance(data.base, str) else data.base["name"])
        if data.recipe:
            k = base.order + 1
            if data.recipe == "triple-jump":
                g1 = 1 / (2 - mp.root(2, k))
                co["weights"] = [g1, -mp.root(2, k) * g1, g1]
            else:
                p = 1 / (4 - mp.root(4, k))
                co["weights"] = [p, p, 1 - 4 * p, p, p]
        return MPMethod("composition", data.order, {"base": base, "weights": co["weights"]})
    if data.kind == "rk":
        co = {"A_q": co["A"], "b_q": co["b"], "A_p": co["A"], "b_p": co["b"]}
    return MPMethod("prk" if data.kind in ("rk", "prk") else data.kind, data.order, co)


def step(m: MPMethod, q, p, h, force: Callable):
    """(q, p) after one step of size h; ``force(q) = -V'(q)``."""
    if m.kind == "composition":
        for g in m.data["weights"]:
            q, p = step(m.data["base"], q, p, g * h, force)
        return q, p
    if m.kind == "splitting":
        drift, kick = m.data["drift"], m.data["kick"]
        for i, a in enumerate(drift):
            q = q + a * h * p
            if i < len(kick):
                p = p + kick[i] * h * force(q)
        return q, p
    A_q, b_q, A_p, b_p = (m.data[k] for k in ("A_q", "b_q", "A_p", "b_p"))
    s = len(b_q)
    Q, P = [q] * s, [p] * s
    tol = mp.mpf(10) ** (-mp.mp.dps + 3)
    for _ in range(500):
        F = [force(x) for x in Q]
        Qn = [q + h * mp.fsum(A_q[i][j] * P[j] for j in range(s)) for i in range(s)]
        Pn = [p + h * mp.fsum(A_p[i][j] * F[j] for j in range(s)) for i in range(s)]
        change = max(abs(x - y) for x, y in zip(Qn + Pn, Q + P))
        Q, P = Qn, Pn
        if change < tol:
            break
    F = [force(x) for x in Q]
    return (q + h * mp.fsum(b_q[j] * P[j] for j in range(s)),
            p + h * mp.fsum(b_p[j] * F[j] for j in range(s)))


def integrate(m: MPMethod, q0, p0, T, n: int, force: Callable):
    h = mp.mpf(T) / n
    q, p = mp.mpf(q0), mp.mpf(p0)
    for _ in range(n):
        q, p = step(m, q, p, h, force)
    return q, p
