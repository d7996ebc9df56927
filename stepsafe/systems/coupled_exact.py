"""The definite criterion of the coupled analysis at high precision, for the small systems
whose boundary float64 cannot place (docs/theory.md#systems-beyond-the-test-models).

On a nearly semidefinite S (condition 1e12 and beyond: a strong magnetic field, a slow
drift mode) the rounding bound of ``Q(h) = sign(S) (M^T J - J M)`` reaches its smallest
eigenvalue before the structure is lost: float64 certifies the steps below some h_max and
the loss above some h_lost, and decides nothing in between. For ``2n <=``
:data:`EXACT_SIZE` the one-step matrix is then formed from the exact floats of S at
:data:`PRECISION` significant digits (mpmath: the method's symplectic Euler factors solved
directly) and Q is tested by a Cholesky factorisation at that precision. A factorisation
with a pivot within :data:`PIVOT_FLOOR` units of the precision of the rounding of Q is
redone at twice the digits, and if it is still that close the step is not certified.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from stepsafe.core.transfer import blocks_of
from stepsafe.methods.protocol import Shears
from stepsafe.methods.tableaux import Method

#: Largest 2n decided at high precision (one step costs about 1.5 ms per Euler factor at
#: 2n = 8: 1 to 5 s for the about 100 steps of a boundary).
EXACT_SIZE = 8
#: Significant digits of the high-precision criterion.
PRECISION = 40
#: A Cholesky pivot of Q is trusted when it exceeds this many units of the working
#: precision times ``2n max |M|^2`` (the size of the rounding of Q, formed from M).
PIVOT_FLOOR = 1e6
#: Uniform samples of the undecided band before the bisection (a narrow island of loss in
#: the band is found when it spans one of them).
BAND_SAMPLES = 16
#: Bisection steps at most (from a band starting at 0, each halves the step).
MAX_BISECTIONS = 200


def euler_factors(method: Method | None) -> list[tuple[str, float]] | None:
    """The method's symplectic Euler factors ``("DK" | "KD", weight)`` (a splitting or a
    composition of splittings without force gradients), or None."""
    if method is None:
        return None
    blocks = blocks_of(method, None)
    if len(blocks) == 1 and isinstance(blocks[0], Shears) and blocks[0].weight == 1.0 \
            and not blocks[0].splitting.force_gradient:
        return blocks[0].splitting.euler_factors()
    return None


def exact_capable(method: Method | None, S: np.ndarray) -> bool:
    """Whether :func:`kept_exactly` applies (a splitting, ``2n <= EXACT_SIZE``)."""
    return S.shape[0] <= EXACT_SIZE and euler_factors(method) is not None


def definite_sign(S: np.ndarray) -> int:
    """``+1`` or ``-1`` if the exact floats of S form a definite matrix of that sign
    (Cholesky at :data:`PRECISION` digits, pivots beyond their rounding), else 0."""
    import mpmath as mp

    size = S.shape[0]
    with mp.workdps(PRECISION):
        matrix = mp.matrix([[mp.mpf(float(S[i, j])) for j in range(size)]
                            for i in range(size)])
        largest = max(abs(matrix[i, j]) for i in range(size) for j in range(size))
        floor = PIVOT_FLOOR * mp.eps * size * largest
        for sign in (1, -1):
            if _positive_definite(sign * matrix, floor):
                return sign
    return 0


def kept_exactly(factors: list[tuple[str, float]], S: np.ndarray, sign: int, h: float
                 ) -> bool:
    """Whether ``sign (M^T J - J M)`` is positive definite for the step ``h`` of the Euler
    ``factors`` on ``x' = J S x`` (S definite of sign ``sign``), decided at
    :data:`PRECISION` digits, or twice that where a pivot is too small to trust; False
    where even that cannot decide, or where the step is not unique."""
    for digits in (PRECISION, 2 * PRECISION):
        verdict = _kept(factors, S, sign, h, digits)
        if verdict is not None:
            return verdict
    return False


def _kept(factors, S, sign, h, digits) -> bool | None:
    import mpmath as mp

    n = S.shape[0] // 2
    with mp.workdps(digits):
        def block(rows, cols):
            return mp.matrix([[mp.mpf(float(S[i, j])) for j in cols] for i in rows])

        qs, ps = range(n), range(n, 2 * n)
        S_qq, S_qp, S_pq, S_pp = block(qs, qs), block(qs, ps), block(ps, qs), block(ps, ps)
        eye = mp.eye(n)
        q = mp.matrix(n, 2 * n)
        p = mp.matrix(n, 2 * n)
        for i in range(n):
            q[i, i] = p[i, n + i] = 1
        try:
            for label, weight in factors:
                c = mp.mpf(weight) * mp.mpf(h)
                if label == "DK":  # q1 = q + c (S_pq q1 + S_pp p), p1 = p - c (S_qq q1 + S_qp p)
                    q = mp.inverse(eye - c * S_pq) * (q + c * S_pp * p)
                    p = p - c * (S_qq * q + S_qp * p)
                else:  # p1 = p - c (S_qq q + S_qp p1), q1 = q + c (S_pq q + S_pp p1)
                    p = mp.inverse(eye + c * S_qp) * (p - c * S_qq * q)
                    q = q + c * (S_pq * q + S_pp * p)
        except ZeroDivisionError:
            return False  # a singular stage matrix: no unique step
        M = mp.matrix(2 * n, 2 * n)
        for i in range(n):
            for j in range(2 * n):
                M[i, j], M[n + i, j] = q[i, j], p[i, j]
        # Q = sign (M^T J - J M), J = [[0, I], [-I, 0]]
        Q = mp.matrix(2 * n, 2 * n)
        for i in range(2 * n):
            for j in range(2 * n):
                mtj = -M[n + j, i] if j < n else M[j - n, i]  # (M^T J)_ij
                jm = M[n + i, j] if i < n else -M[i - n, j]  # (J M)_ij
                Q[i, j] = sign * (mtj - jm)
        largest = max(abs(M[i, j]) for i in range(2 * n) for j in range(2 * n))
        floor = PIVOT_FLOOR * mp.eps * 2 * n * largest ** 2
        return _positive_definite(Q, floor)


def _positive_definite(Q, floor) -> bool | None:
    """Cholesky at the working precision: True, False, or None when a pivot is within
    ``floor`` of 0 (its sign not trusted)."""
    import mpmath as mp

    size = Q.rows
    L = mp.matrix(size, size)
    for j in range(size):
        pivot = Q[j, j] - mp.fsum(L[j, k] ** 2 for k in range(j))
        if abs(pivot) <= floor:
            return None
        if pivot < 0:
            return False
        L[j, j] = mp.sqrt(pivot)
        for i in range(j + 1, size):
            L[i, j] = (Q[i, j] - mp.fsum(L[i, k] * L[j, k] for k in range(j))) / L[j, j]
    return True


def exact_boundary(factors: list[tuple[str, float]], S: np.ndarray, sign: int, good: float,
                   lost: float, rel_tol: float, steps: np.ndarray | None = None,
                   progress: Callable[[float], None] | None = None) -> float:
    """The last step kept at high precision in ``[good, lost]`` before the first loss,
    ``good`` being certified and ``lost`` lost: the ``steps`` inside (the float64 scan's)
    and :data:`BAND_SAMPLES` uniform samples in order, then bisection of the first change
    to ``rel_tol`` (relative); ends on a kept step. ``progress(h / lost)`` after each
    sample (a 35-factor method on 8 rows takes up to 13 s)."""
    uniform = good + (lost - good) * np.arange(1, BAND_SAMPLES + 1) / BAND_SAMPLES
    inside = np.empty(0) if steps is None else steps[(steps > good) & (steps < lost)]
    previous = good
    for h in np.union1d(uniform, inside):
        h = float(h)
        if progress:
            progress(h / lost)
        if kept_exactly(factors, S, sign, h):
            previous = h
            continue
        lo, hi = previous, h
        for _ in range(MAX_BISECTIONS):
            if hi - lo <= rel_tol * hi or (lo == 0.0 and hi <= rel_tol * h):
                break  # (from 0: no step above rel_tol of the first sample is kept)
            mid = 0.5 * (lo + hi)
            if kept_exactly(factors, S, sign, mid):
                lo = mid
            else:
                hi = mid
        return lo
    return previous
