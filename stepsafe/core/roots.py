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
from typing import NamedTuple

import numpy as np

EPS = np.finfo(float).eps


def refine_brackets(fun: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray,
                    f_lo: np.ndarray, f_hi: np.ndarray, max_iter: int = 400,
                    slope: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                    level: np.ndarray | float = 0.0, start: np.ndarray | None = None
                    ) -> np.ndarray:
    """Solutions of ``fun(x) = level_i`` in each bracket ``[lo_i, hi_i]`` where
    ``f_lo_i * f_hi_i < 0`` (``f`` the values of ``fun - level`` at the ends).

    ``fun`` maps an array of points to an array of values; ``level`` (a scalar or one value
    per bracket) lets brackets for different levels advance together. With ``slope`` (a
    function returning ``(fun, dfun)``) the iteration takes safeguarded Newton steps
    instead, which converge quadratically; a Newton step that leaves the bracket is replaced
    by bisection, and ``start`` (e.g. :func:`hermite_root`) may give the first iterate
    (default: the secant point). Returns the point of each final bracket with the smaller
    ``|f|``.
    """
    level = np.broadcast_to(np.asarray(level, dtype=float), np.shape(lo))
    if slope is not None:
        return _newton_brackets(slope, lo, hi, f_lo, f_hi, max_iter, level, start)
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


class HermiteCubic(NamedTuple):
    """The cubic Hermite interpolant on a cell of width ``h``, in ``u = (z - z0)/h``:
    ``p(u) = f0 + m0 u + c2 u^2 + c3 u^3`` with ``p(1) = f0 + dv``, ``p'(0) = m0``,
    ``p'(1) = m1`` (slopes scaled by h). Arrays: one cell per entry."""

    f0: np.ndarray
    m0: np.ndarray
    m1: np.ndarray
    dv: np.ndarray
    c2: np.ndarray
    c3: np.ndarray

    @classmethod
    def on_cells(cls, z0, z1, f0, f1, d0, d1) -> HermiteCubic:
        h = z1 - z0
        m0, m1, dv = d0 * h, d1 * h, f1 - f0
        with np.errstate(over="ignore", invalid="ignore"):
            return cls(f0, m0, m1, dv, 3.0 * dv - 2.0 * m0 - m1, m0 + m1 - 2.0 * dv)

    def value(self, u):
        return self.f0 + u * (self.m0 + u * (self.c2 + u * self.c3))

    def slope(self, u):
        return self.m0 + u * (2.0 * self.c2 + 3.0 * u * self.c3)


def hermite_root(z0, z1, f0, f1, d0, d1, iterations: int = 8) -> np.ndarray:
    """Root in ``(z0, z1)`` of the cubic Hermite interpolant of ``f`` (values ``f0, f1``,
    slopes ``d0, d1``; ``f0 f1 < 0``): a starting point with error ``O(h^4)`` for Newton on
    ``f`` itself. Safeguarded Newton on the cubic in ``u``."""
    cubic = HermiteCubic.on_cells(z0, z1, f0, f1, d0, d1)
    lo, hi = np.zeros(np.shape(z0)), np.ones(np.shape(z0))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.clip(-f0 / cubic.dv, 0.0, 1.0)
        for _ in range(iterations):
            p = cubic.value(u)
            left = np.sign(p) == np.sign(f0)
            lo, hi = np.where(left, u, lo), np.where(left, hi, u)
            u = u - p / cubic.slope(u)
            u = np.where(np.isfinite(u) & (u >= lo) & (u <= hi), u, 0.5 * (lo + hi))
    return z0 + u * (z1 - z0)


def hermite_extremum(z0, z1, f0, f1, d0, d1) -> np.ndarray:
    """Where the cubic Hermite interpolant of ``f`` has zero slope in ``(z0, z1)`` (``d0 d1
    < 0``: exactly one such point), in closed form: the start for Newton on ``f'``."""
    cubic = HermiteCubic.on_cells(z0, z1, f0, f1, d0, d1)
    m0, m1 = cubic.m0, cubic.m1
    qa, qb = 3.0 * cubic.c3, 2.0 * cubic.c2  # p'(u) = m0 + qb u + qa u^2
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = np.sqrt(np.maximum(qb * qb - 4.0 * qa * m0, 0.0))
        # the root of the quadratic in (0, 1), in the cancellation-free form
        q = -0.5 * (qb + np.where(qb >= 0, disc, -disc))
        r1, r2 = q / qa, m0 / q
        u = np.where((r1 > 0) & (r1 < 1), r1, r2)
        u = np.where(np.isfinite(u) & (u > 0) & (u < 1), u, m0 / (m0 - m1))
    return z0 + u * (z1 - z0)


def _newton_brackets(slope, lo, hi, f_lo, f_hi, max_iter: int, level: np.ndarray,
                     start: np.ndarray | None = None) -> np.ndarray:
    """Safeguarded Newton (``rtsafe``) on many brackets at once, started at ``start`` or the
    secant point.

    A bracket is done when ``f`` is exactly zero, the bracket or the Newton correction
    (before safeguarding: a root found exactly sits on the bracket's end) is below the
    floating-point grid, or rounding noise in ``f`` has taken over: a correction below
    1e-9 relative that is no smaller than the previous one (in exact arithmetic Newton's
    corrections shrink near a root, quadratically for a simple one).
    """
    a = np.minimum(lo, hi).astype(float)
    b = np.maximum(lo, hi).astype(float)
    fa = np.where(lo <= hi, f_lo, f_hi).astype(float)
    fb = np.where(lo <= hi, f_hi, f_lo).astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = a - fa * (b - a) / (fb - fa) if start is None else np.asarray(start, dtype=float)
    x = np.where(np.isfinite(x) & (x > a) & (x < b), x, 0.5 * (a + b))
    best = x.copy()
    best_f = np.full(x.size, np.inf)
    prev_step = np.full(x.size, np.inf)
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
        noise = (step >= prev_step[idx]) & (step <= 1e-9 * np.maximum(np.abs(xi), 1.0))
        done = (f == 0) | (bi - ai <= tiny) | (step <= 0.5 * tiny) | noise
        prev_step[idx] = step
        x[idx] = np.where(ok, newton, 0.5 * (ai + bi))
        active[idx[done]] = False
    return best


def narrowed(f: Callable[[float], float], lo: float, f_lo: float, hi: float, f_hi: float,
             rtol: float) -> float:
    """The lower end of a bracket ``f(lo) >= 0 > f(hi)`` narrowed to ``hi - lo <= rtol
    hi``: each round takes the regula falsi point (kept a tenth of the bracket from its
    ends) and then probes ``rtol hi / 2`` beyond it on the side of the root, so that a good
    estimate closes the bracket in two evaluations; bisection after 40 rounds."""
    for round_ in range(200):
        if hi - lo <= rtol * hi:
            break
        width = hi - lo
        if round_ < 40 and f_lo > f_hi:
            x = lo + width * f_lo / (f_lo - f_hi)
            x = min(max(x, lo + 0.1 * width), hi - 0.1 * width)
        else:
            x = 0.5 * (lo + hi)
        fx = f(x)
        if fx >= 0:
            lo, f_lo = x, fx
        else:
            hi, f_hi = x, fx
        if hi - lo <= rtol * hi or round_ >= 40:
            continue
        y = x + 0.5 * rtol * hi if fx >= 0 else x - 0.5 * rtol * hi
        if lo < y < hi:
            fy = f(y)
            if fy >= 0:
                lo, f_lo = y, fy
            else:
                hi, f_hi = y, fy
    return lo
