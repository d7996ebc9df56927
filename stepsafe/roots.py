"""Vectorised refinement of many sign-change brackets at once.

All brackets advance together, one array evaluation of ``fun`` per iteration, so refining
every boundary of a method costs a few dozen vectorised evaluations instead of a scalar
``brentq`` per root (and avoids importing ``scipy.optimize`` at start-up, STYLE.md).

The iteration is the Illinois variant of regula falsi with a bisection step every fourth
iteration, which bounds the worst case by bisection's: the bracket ``[a, b]`` always holds
a sign change, and iteration stops when it is as narrow as the floating-point grid allows
(``|b - a| <= 2 eps max(|a|, |b|)``) or ``f`` is exactly zero.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

EPS = np.finfo(float).eps


def refine_brackets(fun: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray,
                    f_lo: np.ndarray, f_hi: np.ndarray, max_iter: int = 400,
                    slope: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                    level: np.ndarray | float = 0.0) -> np.ndarray:
    """Solutions of ``fun(x) = level_i`` in each bracket ``[lo_i, hi_i]`` where
    ``f_lo_i * f_hi_i < 0`` (``f`` the values of ``fun - level`` at the ends).

    ``fun`` maps an array of points to an array of values; ``level`` (a scalar or one value
    per bracket) lets brackets for different levels advance together. With ``slope`` (a
    function returning ``(fun, dfun)``) the iteration takes safeguarded Newton steps
    instead, which converge quadratically; a Newton step that leaves the bracket is replaced
    by bisection. Returns the point of each final bracket with the smaller ``|f|``.
    """
    level = np.broadcast_to(np.asarray(level, dtype=float), np.shape(lo))
    if slope is not None:
        return _newton_brackets(slope, lo, hi, f_lo, f_hi, max_iter, level)
    a = np.array(lo, dtype=float)
    b = np.array(hi, dtype=float)
    fa = np.array(f_lo, dtype=float)
    fb = np.array(f_hi, dtype=float)
    fa_true = fa.copy()  # fa is scaled by the Illinois step; keep the real value to report
    if a.size == 0:
        return a
    active = np.ones(a.size, dtype=bool)
    for it in range(max_iter):
        width = np.abs(b - a)
        active &= (width > 2.0 * EPS * np.maximum(np.abs(a), np.abs(b))) & (fa != 0) & (fb != 0)
        if not active.any():
            break
        idx = np.flatnonzero(active)
        ai, bi, fai, fbi = a[idx], b[idx], fa[idx], fb[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            c = bi - fbi * (bi - ai) / (fbi - fai)
        mid = 0.5 * (ai + bi)
        lo_i, hi_i = np.minimum(ai, bi), np.maximum(ai, bi)
        bad = ~np.isfinite(c) | (c <= lo_i) | (c >= hi_i) | (it % 4 == 3)
        c = np.where(bad, mid, c)
        fc = np.asarray(fun(c), dtype=float) - level[idx]
        fc = np.where(np.isnan(fc), fbi, fc)  # treat an undefined value as b's side
        same = np.sign(fc) == np.sign(fbi)
        # Illinois: keep a and halve fa when c lands on b's side; else a <- b
        new_a = np.where(same, ai, bi)
        new_fa = np.where(same, np.where(bad, fai, 0.5 * fai), fbi)
        fa_true[idx] = np.where(same, fa_true[idx], fbi)
        a[idx], fa[idx], b[idx], fb[idx] = new_a, new_fa, c, fc
    # report the end with the smaller residual
    return np.where(np.abs(fa_true) < np.abs(fb), a, b)


def _newton_brackets(slope, lo, hi, f_lo, f_hi, max_iter: int, level: np.ndarray) -> np.ndarray:
    """Safeguarded Newton (``rtsafe``) on many brackets at once, started at the secant point.

    A bracket is done when ``f`` is exactly zero or the bracket or the Newton correction
    (before safeguarding: a root found exactly sits on the bracket's end) is below the
    floating-point grid. Where rounding noise in ``f`` exceeds that, Newton steps land on
    both sides of the root and the bracket closes in on it by sign.
    """
    a = np.minimum(lo, hi).astype(float)
    b = np.maximum(lo, hi).astype(float)
    fa = np.where(lo <= hi, f_lo, f_hi).astype(float)
    fb = np.where(lo <= hi, f_hi, f_lo).astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = a - fa * (b - a) / (fb - fa)
    x = np.where(np.isfinite(x) & (x > a) & (x < b), x, 0.5 * (a + b))
    best = x.copy()
    best_f = np.full(x.size, np.inf)
    active = np.ones(x.size, dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        xi = x[idx]
        f, df = slope(xi)
        f = np.asarray(f, dtype=float) - level[idx]
        df = np.asarray(df, dtype=float)
        better = np.abs(f) < best_f[idx]
        best[idx] = np.where(better, xi, best[idx])
        best_f[idx] = np.where(better, np.abs(f), best_f[idx])
        left = np.sign(f) == np.sign(fa[idx])  # the root is to the right of x
        a[idx] = ai = np.where(left, xi, a[idx])
        fa[idx] = np.where(left, f, fa[idx])
        b[idx] = bi = np.where(left, b[idx], xi)
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = xi - f / df
        step = np.where(np.isfinite(newton), np.abs(newton - xi), np.inf)
        ok = np.isfinite(newton) & (newton > ai) & (newton < bi)
        tiny = 2.0 * EPS * np.maximum(np.abs(ai), np.abs(bi))
        done = (f == 0) | (bi - ai <= tiny) | (step <= 0.5 * tiny)
        x[idx] = np.where(ok, newton, 0.5 * (ai + bi))
        active[idx[done]] = False
    return best
