"""The smallest eigenvalue of a symmetric matrix, with positive definiteness certified.

The definite criterion of the coupled analysis (:mod:`stepsafe.systems.coupled`) asks of a
symmetric ``W`` two things: whether ``lambda_min(W) > b`` for a rounding bound ``b``
(the decision), and the value of ``lambda_min(W)`` (a continuous margin for the scan's dip
search and the boundary's root finder). An eigensolver reduces W to tridiagonal form for
the value; for large W that is most of the cost, so here:

* the **decision** is one Cholesky factorisation of ``A = W - tau I`` with
  ``tau = b + allowance``. If it completes in floating point, ``A + E = R^T R`` with
  ``|E| <= gamma_(N+1) |R^T| |R|`` (Higham, *Accuracy and Stability of Numerical
  Algorithms*, 2nd ed., Thm 10.3), so ``||E||_2 <= gamma_(N+1) trace(A) / (1 - gamma_(N+1))``,
  and forming ``A`` rounds its diagonal by at most ``u max |a_ii|``: ``allowance`` covers
  both, and a completed factorisation proves ``lambda_min(W) > b``.
* the **value** ``lambda_min(A)`` comes, where the factorisation completed and W is large,
  from Lanczos iterations on ``A^-1 = R^-1 R^-T`` (two triangular solves with one vector
  each; full reorthogonalisation), stopped when the Ritz value's error estimate
  ``min(r, r^2 / gap)`` is below :data:`LANCZOS_TOL` of it. A Ritz value of ``A^-1`` is
  below its largest eigenvalue, so the value is an upper bound on ``lambda_min(A)``, close
  to it at the tolerance. Elsewhere (small W, or no factorisation) a symmetric
  eigensolver gives it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UNIT_ROUNDOFF = 2.0**-53
#: From this size on the value is found by Lanczos iterations instead of an eigensolver
#: (measured with one BLAS thread: at N = 1600 the eigensolver takes 0.3 s, a Cholesky
#: factorisation 0.04 s and 40 Lanczos steps 0.05 s).
LANCZOS_FROM = 256
#: Relative error estimate at which a Lanczos Ritz value is accepted.
LANCZOS_TOL = 1e-10
#: Lanczos steps at most (the value is then the last Ritz value, still an upper bound).
LANCZOS_STEPS = 120


@dataclass(frozen=True)
class Smallest:
    """``lambda_min(W) - shift`` and whether ``lambda_min(W) > floor`` is proved."""

    value: float  #: lambda_min(W) - shift: eigensolver's, or a Lanczos upper bound
    certified: bool  #: a Cholesky factorisation of W - shift I completed
    shift: float  #: floor + the factorisation's allowance


def allowance(W: np.ndarray, floor: float = 0.0) -> float:
    """A bound on what a completed Cholesky factorisation of ``W - tau I`` (``tau`` the
    floor plus this, ``floor >= 0``) can hide: ``gamma_(N+1) trace^+ / (1 - gamma_(N+1))``
    plus the rounding of the shifted diagonal (see module); at least the eigensolver's
    ``4 N u ||W||_F``. For W of order 1 (:func:`smallest` scales it so): the bound
    assumes no underflow."""
    N = W.shape[0]
    diagonal = np.diagonal(W)
    gamma = (N + 1) * UNIT_ROUNDOFF / (1 - (N + 1) * UNIT_ROUNDOFF)
    trace = float(np.maximum(diagonal, 0.0).sum())
    factorisation = 1.01 * gamma / (1 - gamma) * trace
    shifted = 2 * UNIT_ROUNDOFF * (float(np.abs(diagonal).max(initial=0.0)) + floor)
    solver = 4 * N * UNIT_ROUNDOFF * float(np.linalg.norm(W))
    return max(factorisation + shifted, solver)


def smallest(W: np.ndarray, floor: float) -> Smallest:
    """``lambda_min(W) - shift`` (``shift = floor + allowance(W)``) and whether
    ``lambda_min(W) > floor`` is proved by a completed Cholesky factorisation of
    ``W - shift I``. W is first multiplied by the power of two that brings its largest
    entry to [1/2, 1) (exact, and the statement is the same for the scaled W and floor), so
    that nothing in the factorisation over- or underflows; the results are scaled back.
    W is not modified; a W that is not finite has value -inf."""
    if not np.all(np.isfinite(W)):
        return Smallest(-np.inf, False, floor)
    largest = max(float(W.max(initial=0.0)), -float(W.min(initial=0.0)))
    if largest == 0.0:  # (lambda_min = 0: nothing above a floor >= 0)
        return Smallest(-floor, False, floor)
    exponent = int(np.frexp(largest)[1])
    scaled = np.ldexp(W, -exponent)
    found = _smallest(scaled, float(np.ldexp(floor, -exponent)))
    return Smallest(float(np.ldexp(found.value, exponent)), found.certified,
                    float(np.ldexp(found.shift, exponent)))


def _smallest(W: np.ndarray, floor: float) -> Smallest:
    """:func:`smallest` of a W whose largest entry is in [1/2, 1)."""
    from scipy.linalg import lapack

    shift = floor + allowance(W, floor)
    A = np.array(W, order="F")  # (Fortran order: LAPACK and BLAS take it without a copy)
    A[np.diag_indices_from(A)] -= shift
    R, info = lapack.dpotrf(A, lower=0, clean=0, overwrite_a=1)
    certified = info == 0 and bool(np.all(np.isfinite(np.diagonal(R))))
    if certified and W.shape[0] >= LANCZOS_FROM:
        with np.errstate(over="ignore", invalid="ignore"):
            value = _lanczos(R)
        if np.isfinite(value):
            return Smallest(value, True, shift)
    return Smallest(extreme_eigenvalue(W) - shift, certified, shift)


def extreme_eigenvalue(A: np.ndarray, highest: bool = False) -> float:
    """The smallest (or largest) eigenvalue of the symmetric A: LAPACK's ``syevr`` for that
    one alone, or, where it fails (it can on a tight cluster, all eigenvalues within
    rounding of one another), every eigenvalue by divide and conquer."""
    import scipy.linalg as sla

    index = A.shape[0] - 1 if highest else 0
    try:
        return float(sla.eigh(A, eigvals_only=True, subset_by_index=[index, index],
                              check_finite=False)[0])
    except np.linalg.LinAlgError:
        return float(sla.eigh(A, eigvals_only=True, driver="evd", check_finite=False)[index])


def _lanczos(R: np.ndarray) -> float:
    """``1 / theta``, theta the largest Ritz value of ``(R^T R)^-1`` (R upper triangular,
    only its upper triangle read), from a fixed random start (a start taken from a nearby
    W's Ritz vector can lack the direction of a new lowest eigenvalue, and stop on the
    next one)."""
    import scipy.linalg as sla
    from scipy.linalg import blas

    N = R.shape[0]
    steps = min(LANCZOS_STEPS, N)
    basis = np.zeros((steps + 1, N))
    v = np.random.default_rng(0).standard_normal(N)
    basis[0] = v / np.linalg.norm(v)
    alpha, beta = np.zeros(steps), np.zeros(steps)
    theta = 0.0
    for k in range(steps):
        w = blas.dtrsv(R, basis[k], lower=0, trans=1)  # R^-T v
        w = blas.dtrsv(R, w, lower=0, trans=0, overwrite_x=1)  # R^-1 R^-T v
        alpha[k] = w @ basis[k]
        for _ in range(2):  # full reorthogonalisation, twice is enough
            w -= basis[:k + 1].T @ (basis[:k + 1] @ w)
        beta[k] = np.linalg.norm(w)
        if not (np.isfinite(alpha[k]) and np.isfinite(beta[k])):
            return np.nan  # (out of the float range: the caller's eigensolver decides)
        ritz, vectors = sla.eigh_tridiagonal(alpha[:k + 1], beta[:k])
        theta = float(ritz[-1])
        residual = beta[k] * abs(vectors[-1, -1])
        gap = theta - float(ritz[-2]) if k > 0 else theta
        if beta[k] == 0.0 or min(residual, residual**2 / max(gap, 1e-300)) \
                <= LANCZOS_TOL * theta:
            break
        basis[k + 1] = w / beta[k]
    return 1.0 / theta
