"""The stability function ``R = P/Q`` of a Runge–Kutta method and where ``|R(iy)| = 1``.

For an RK method ``(A, b)`` applied to ``y' = lambda y`` with ``w = h lambda``,
``R(w) = 1 + w b^T (I - w A)^-1 e = P(w) / Q(w)`` with

* ``Q(w) = det(I - w A) = sum_k c_k w^k``, ``c_k`` the characteristic-polynomial
  coefficients of ``A`` (``det(x I - A) = sum_k c_k x^(s-k)``; exactly 1 for explicit A);
* ``P(w) = Q(w) R(w)`` truncated at degree s, from the Taylor coefficients
  ``R(w) = 1 + sum_(j>=1) b^T A^(j-1) e w^j`` (P has degree <= s, so the product is exact).

On the harmonic oscillator the transfer matrix acts on ``q + i p`` as ``R(-i z)``, so its
spectral radius is ``|R(iz)|`` and the classical (imaginary-axis) stability condition is

    E(y^2) = |Q(iy)|^2 - |P(iy)|^2 >= 0,

a polynomial of degree <= s in ``x = y^2``. Its positive real roots are the only places the
condition can change, which :func:`imaginary_axis_crossings` returns (polished by Newton on
``|R(iy)|^2 - 1`` with ``R`` from stage solves, which keeps full accuracy where expanded
coefficients would not); the region code decides the status between
them from ``M(z)`` itself, so a root that is only rounding noise (``E`` vanishes
identically for Gauss and Lobatto IIIA) never becomes a boundary.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from stepsafe.core.engine import batched_solve
from stepsafe.core.sets import distinct
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import RungeKutta


def _too_large(method: RungeKutta) -> StepsafeError:
    return StepsafeError(f"method {method.name!r}: coefficients A, b too large to analyse "
                         "(its stability polynomial overflows float64)")


@lru_cache(maxsize=64)
def stability_polynomials(method: RungeKutta) -> tuple[np.ndarray, np.ndarray]:
    """Ascending coefficients ``(p, q)`` of ``P`` and ``Q`` (each of length s + 1; cached per
    method object, read-only). A tableau whose coefficients overflow float64 (entries like
    1e200: ``b^T A^j e`` is out of range) is refused with a :class:`StepsafeError`."""
    A, b = method.A, method.b
    s = b.size
    q = np.zeros(s + 1)
    q[0] = 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        if not method.explicit:
            q = np.real(np.poly(A))
        r = np.empty(s + 1)  # Taylor coefficients of R: 1, b^T e, b^T A e, ...
        r[0] = 1.0
        v = np.ones(s)
        for j in range(1, s + 1):
            r[j] = b @ v
            v = A @ v
        p = np.array([q[: k + 1] @ r[k::-1] for k in range(s + 1)])
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise _too_large(method)
    p.flags.writeable = q.flags.writeable = False
    return p, q


def stability_function(method: RungeKutta, w, derivative: bool = False):
    """``R(w) = 1 + w b^T X`` with ``(I - w A) X = e`` solved at every (complex) ``w``
    (batched s x s solves, NaN where singular: as accurate as the tableau allows, unlike
    expanded polynomials); for an explicit method ``R = P`` by Horner's rule.
    With ``derivative=True`` also ``R'(w) = b^T X + w b^T X'``, ``(I - w A) X' = A X``."""
    w = np.atleast_1d(np.asarray(w, dtype=complex))
    if method.explicit:  # R = P exactly, coefficients b^T A^(j-1) e: Horner
        p, _ = stability_polynomials(method)
        R, dR = np.full(w.shape, p[-1], dtype=complex), np.zeros(w.shape, dtype=complex)
        for c in p[-2::-1]:
            dR = dR * w + R
            R = R * w + c
        return (R, dR) if derivative else R
    A, b = method.A, method.b
    s = b.size
    S = np.eye(s)[None, :, :] - w[:, None, None] * A[None, :, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = batched_solve(S, np.ones((w.size, s, 1), dtype=complex))
        R = 1.0 + w * (b @ X)[:, 0]
        if not derivative:
            return R
        dX = batched_solve(S, A[None, :, :] @ X)
        return R, (b @ X)[:, 0] + w * (b @ dX)[:, 0]


def _modulus_squared_on_axis(f: np.ndarray) -> np.ndarray:
    """Ascending coefficients in ``x = y^2`` of ``|F(iy)|^2 = F(iy) F(-iy)``."""
    k = np.arange(f.size)
    g = np.convolve(f * 1j ** k, f * (-1j) ** k)
    return g.real[0::2]


def imaginary_axis_crossings(method: RungeKutta, ymax: float) -> np.ndarray:
    """Sorted ``y`` in ``(0, ymax]`` where ``E(y^2) = |Q(iy)|^2 - |P(iy)|^2`` may change sign:
    the positive real roots of ``E`` (numerically real: imaginary part below 1e-6 of the
    modulus; extra candidates are harmless, the caller classifies between them)."""
    p, q = stability_polynomials(method)
    with np.errstate(over="ignore", invalid="ignore"):
        e = _modulus_squared_on_axis(q) - _modulus_squared_on_axis(p)
    if not np.isfinite(e).all():
        raise _too_large(method)
    nz = np.flatnonzero(e)
    if nz.size == 0 or nz[-1] == nz[0]:
        return np.empty(0)  # E identically zero, or c x^k: no positive root
    x = np.roots(e[nz[-1]::-1][: nz[-1] - nz[0] + 1])
    x = x.real[(np.abs(x.imag) <= 1e-6 * np.abs(x)) & (x.real > 0)]
    y = np.sqrt(x)
    for _ in range(2 if y.size else 0):  # Newton on f(y) = |R(iy)|^2 - 1 (R from stage solves)
        R, dR = stability_function(method, 1j * y, derivative=True)
        f = np.abs(R) ** 2 - 1.0
        df = 2.0 * (np.conj(R) * 1j * dR).real
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(df != 0, f / df, 0.0)
        y = np.where(np.abs(step) < 1e-3 * y, y - step, y)
    return distinct(y[(y > 0) & (y <= ymax)])
