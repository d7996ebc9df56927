"""Root finding at the working mpmath precision, for the points float64 cannot decide
(:mod:`stepsafe.core.escalate`).

The core's own copy: the independent reference (:mod:`stepsafe.reference.highprec`) keeps
its own, so what verifies the core shares no code with it. Imports mpmath only when called.
"""

from __future__ import annotations

from collections.abc import Callable


def refine_root(f: Callable, lo, hi, tol=None):
    """Zero (or sign-changing pole) of f in [lo, hi], f(lo) f(hi) < 0.

    Illinois (modified regula falsi) safeguarded by a bisection step
    whenever three steps failed to halve the bracket; stops at a bracket
    width ~ 64 ulp (about mp.dps digits).  A point where f raises
    ZeroDivisionError is returned at once (an exact pole)."""
    from mpmath import mp

    a, b = mp.mpf(lo), mp.mpf(hi)
    fa, fb = f(a), f(b)
    if fa == 0 or fb == 0:
        return a if fa == 0 else b
    if (fa > 0) == (fb > 0):
        raise ValueError("refine_root: no sign change on [lo, hi]")
    tol = tol or mp.eps * 2 ** 6 * max(1, abs(a), abs(b))
    side, width, bisect = 0, b - a, False
    for it in range(1, 20 * mp.prec):
        if b - a <= tol:
            break
        c = (a + b) / 2 if bisect else (a * fb - b * fa) / (fb - fa)
        if not a < c < b:
            c = (a + b) / 2
        try:
            fc = f(c)
        except ZeroDivisionError:
            return c
        if fc == 0:
            return c
        if (fc > 0) == (fa > 0):
            a, fa = c, fc
            fb, side = (fb / 2 if side == -1 else fb), -1
        else:
            b, fb = c, fc
            fa, side = (fa / 2 if side == 1 else fa), 1
        bisect = False
        if it % 3 == 0:
            bisect, width = b - a > width / 2, b - a
    return (a + b) / 2


def locate_pole(inv: Callable, lo, hi, tol=None):
    """The pole of ``tr M`` in ``[lo, hi]`` given ``inv(z) = 1 / tr M(z)`` (0 where the stage
    system is exactly singular), or None.  An odd pole is a sign change of ``inv``, refined
    by :func:`refine_root`; an even one (a double eigenvalue of the stage operator) is a
    zero of ``|inv|`` without a sign change, found by golden-section search and accepted
    when ``|inv|`` there is below ``10^(-dps/2)`` of its value at the nearer end (near a
    double pole ``|inv|`` falls like the square of the distance; a finite peak of
    ``tr M`` does not take it to zero)."""
    from mpmath import mp

    a, b = mp.mpf(lo), mp.mpf(hi)
    fa, fb = inv(a), inv(b)
    if fa == 0 or fb == 0:
        return a if fa == 0 else b
    if (fa > 0) != (fb > 0):
        return refine_root(inv, a, b, tol)
    ratio = (mp.sqrt(5) - 1) / 2
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = abs(inv(c)), abs(inv(d))
    for _ in range(2 * mp.prec):
        if fc == 0 or fd == 0:
            return c if fc == 0 else d
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = abs(inv(c))
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = abs(inv(d))
        if b - a <= (tol or mp.eps * 2 ** 6 * max(1, abs(b))):
            break
    x, fx = (c, fc) if fc < fd else (d, fd)
    return x if fx <= mp.mpf(10) ** (-(mp.dps // 2)) * min(abs(fa), abs(fb)) else None
