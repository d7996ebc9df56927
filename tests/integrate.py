"""A small reference integrator for the tests, in mpmath arithmetic.

One step of a method on the pendulum-type problem H = p^2/2 + V(q), independent of
stepsafe's transfer matrices: splitting methods apply their drifts and kicks, compositions
apply the base with scaled steps, processed methods ``P^-1 K P`` apply the processor once,
the kernel every step and the inverse processor at the end, RK/PRK methods solve the
nonlinear stage equations by fixed-point iteration. Coefficients come from
:func:`stepsafe.reference.verify.mp_method` (method files read with the mpmath backend,
decimal literals exactly), so errors far below float64 rounding can be measured: high-order
methods need that to show their order.
"""

from __future__ import annotations

from collections.abc import Callable

import mpmath as mp

from stepsafe.reference.verify import MPMethod, mp_method

__all__ = ["MPMethod", "integrate", "mp_method", "step"]


def step(m: MPMethod, q, p, h, force: Callable):
    """(q, p) after one step of size h; ``force(q) = -V'(q)``."""
    if m.kind == "processed":  # the full one-step map P^-1 K P
        q, p = step(m.data["processor"], q, p, h, force)
        q, p = step(m.data["kernel"], q, p, h, force)
        return unprocess(m, q, p, h, force)
    if m.kind == "composition":
        for g in m.data["weights"]:
            q, p = step(m.data["base"], q, p, g * h, force)
        return q, p
    if m.kind == "splitting":
        drift, kick = m.data["drift"], m.data["kick"]
        gradient = m.data.get("gradient") or [0] * len(kick)
        for i, a in enumerate(drift):
            q = q + a * h * p
            if i < len(kick) and gradient[i] and m.data.get("displaced"):
                # Hessian-free: the force at q + (2 c h^2 / b) F(q) (unit mass)
                shifted = q + 2 * gradient[i] * h ** 2 / kick[i] * force(q)
                p = p + kick[i] * h * force(shifted)
            elif i < len(kick):
                # force-gradient kick: p += b h F + c h^3 d/dq (F^2), F^2' = 2 F F'
                fg = 2 * force(q) * mp.diff(force, q) if gradient[i] else 0
                p = p + kick[i] * h * force(q) + gradient[i] * h ** 3 * fg
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


def unprocess(m: MPMethod, q, p, h, force: Callable):
    """``P^-1`` of a processed method: P's drifts and kicks undone in reverse order."""
    proc = m.data["processor"].data
    drift, kick = proc["drift"], proc["kick"]
    for i in reversed(range(len(drift))):
        if i < len(kick):
            p = p - kick[i] * h * force(q)
        q = q - drift[i] * h * p
    return q, p


def integrate(m: MPMethod, q0, p0, T, n: int, force: Callable):
    h = mp.mpf(T) / n
    q, p = mp.mpf(q0), mp.mpf(p0)
    processed = m.kind == "processed"
    if processed:  # P once, the kernel every step, P^-1 at the output
        q, p = step(m.data["processor"], q, p, h, force)
        m, kernel = m, m.data["kernel"]
    for _ in range(n):
        q, p = step(kernel if processed else m, q, p, h, force)
    return unprocess(m, q, p, h, force) if processed else (q, p)
