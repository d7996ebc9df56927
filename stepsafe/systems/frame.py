"""A symplectic point transformation that makes the coupled analysis cheap
(docs/theory.md#systems-beyond-the-test-models).

For ``x' = J S x`` with ``x = (q, p)`` and the kinetic block ``S_pp`` definite, the linear
point transformation ``q = R q~, p = R^-T p~`` (``T = diag(R, R^-T)``, symplectic) with
``R = L U P``, ``sigma S_pp = L L^T`` (Cholesky, ``sigma = +-1``), ``U`` the orthogonal
eigenvectors of ``L^T S_qq L`` (eigenvalues ``lambda``) and ``P`` the diagonal of powers of
two nearest ``|lambda_i|^(-1/4)`` (which balances each coordinate's two entries), gives

    S~ = T^T S T = [[diag(a), C], [C^T, diag(b)]],    C = R^T S_qp R^-T,

``a = lambda P^2``, ``b = sigma P^-2``, ``|a_i| / |b_i|`` within a factor 4 of 1.

Both diagonal blocks are diagonal; only the mixed block ``C`` is dense. Every symplectic
Euler factor (and every PRK step) commutes with linear point transformations, so the
one-step matrices in the new coordinates are ``M~(h) = T^-1 M(h) T``; the criteria of
:mod:`stepsafe.systems.coupled` are invariant under it (``Q~ = T^T Q T`` is congruent to Q,
``J S~`` similar to ``J S`` with the same Krein signatures). A factor then costs one
n x n solve and one n x n product (:func:`euler_deviation`) instead of a solve and four
products, which is what makes the analysis of a whole system a few eigendecompositions'
worth of work.

The transformation is only used when it is accurate: ``error`` estimates ``|S~ - T^T S T|_F``
for the float ``R``: the residual of the two diagonal blocks (measured), the rounding of
forming the blocks (``4 n eps`` times the products of absolute values, so a scaling of the
coordinates costs nothing) and the distance of the computed ``R^-T`` from the inverse of R
(``|R^T R^-T - I|``, measured); :func:`diagonal_frame` refuses (returns None) when it
exceeds :data:`MAX_RELATIVE_ERROR` of ``|S~|_F``. The coupled analysis adds ``error`` to its
rounding bound of every factor, so a decision it makes holds for ``T^T S T`` itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from stepsafe.systems.smallest import extreme_eigenvalue

EPS = float(np.finfo(float).eps)
#: The frame is refused when its error estimate exceeds this fraction of |S~|_F (the
#: estimate is a worst case growing with n: 7.6e-11 at n = 400, 2.9e-10 at n = 800 for a
#: random well-conditioned S); whether it leaves the margin room is decided by the coupled
#: analysis (``coupled._frame_pays``).
MAX_RELATIVE_ERROR = 1e-8
#: A factor's leftover product is folded into the next solve only when the weights'
#: ratio |c_prev / c| is at most this (the fold's rounding grows with it).
FOLD_RATIO = 4.0


@dataclass(frozen=True, eq=False)
class DiagonalFrame:
    """``S~ = T^T S T = [[diag(a), C], [C^T, diag(b)]]`` (see module)."""

    a: np.ndarray  #: diagonal of the potential block S~_qq
    b: np.ndarray  #: diagonal of the kinetic block S~_pp (all of the sign of S_pp)
    C: np.ndarray  #: the mixed block S~_qp (S~_pq is its transpose)
    error: float  #: bound on |S~ - T^T S T|_F for the float R
    R: np.ndarray  #: the point transformation q = R q~ (p = R^-T p~)

    @cached_property
    def C_norm(self) -> float:
        """A bound on ``||C||_2`` (the largest eigenvalue of ``C^T C``, widened by its
        rounding)."""
        return norm_2(self.C)

    @property
    def S(self) -> np.ndarray:
        """``S~`` as a dense 2n x 2n matrix."""
        return np.block([[np.diag(self.a), self.C], [self.C.T, np.diag(self.b)]])


def diagonal_frame(S: np.ndarray) -> DiagonalFrame | None:
    """The frame of the module docstring, or None when ``S_pp`` is not definite (by
    Cholesky) or the frame's error bound exceeds :data:`MAX_RELATIVE_ERROR`."""
    import scipy.linalg as sla

    n = S.shape[0] // 2
    S_qq, S_qp, S_pp = S[:n, :n], S[:n, n:], S[n:, n:]
    for sigma in (1.0, -1.0):
        try:
            L = np.linalg.cholesky(sigma * S_pp)
            break
        except np.linalg.LinAlgError:
            continue
    else:
        return None
    lam, U = np.linalg.eigh(_symmetric(L.T @ S_qq @ L))
    if not np.all(lam != 0):
        return None
    P = np.ldexp(1.0, np.round(-0.25 * np.log2(np.abs(lam))).astype(int))
    a, b = lam * P * P, sigma / (P * P)
    R = (L @ U) * P
    # R^-1 = P^-1 U^T L^-1 and R^-T = L^-T U P^-1
    R_invT = sla.solve_triangular(L, U, lower=True, trans="T") / P
    C = R.T @ S_qp @ R_invT
    # what the float R makes of the two diagonal blocks, against what is analysed
    residual = (np.linalg.norm(R.T @ S_qq @ R - np.diag(a))
                + np.linalg.norm(R_invT.T @ S_pp @ R_invT - np.diag(b)))
    # the rounding of forming each block, componentwise (scaled coordinates stay exact),
    # and how far the computed R^-T is from the inverse of R
    aR, aRi = np.abs(R), np.abs(R_invT)
    forming = 4 * n * EPS * (np.linalg.norm(aR.T @ np.abs(S_qq) @ aR)
                             + 2 * np.linalg.norm(aR.T @ np.abs(S_qp) @ aRi)
                             + np.linalg.norm(aRi.T @ np.abs(S_pp) @ aRi))
    norm_frame = float(np.sqrt(np.sum(a * a) + np.sum(b * b) + 2 * np.sum(C * C)))
    inverse = float(np.linalg.norm(R.T @ R_invT - np.eye(n)))
    error = float(residual + forming + 2 * inverse * norm_frame)
    if not np.isfinite(error) or error > MAX_RELATIVE_ERROR * norm_frame:
        return None
    return DiagonalFrame(a, b, C, error, R)


def equilibrated(S: np.ndarray, balance: bool = False) -> np.ndarray:
    """``T^T S T`` for ``T = diag(d, 1/d)`` with ``d_i`` a power of two: nearest
    ``|S_pp[i, i]|^(1/2)`` (so that ``S_pp`` has a diagonal of order 1), or with ``balance``
    nearest ``|S_pp[i, i] / S_qq[i, i]|^(1/4)`` (so that each coordinate's two diagonal
    entries agree). A symplectic point transformation (masses over decades brought to
    O(1)) that floating point applies exactly, so the result is the same system in other
    units of each coordinate, with no rounding. S itself where a diagonal entry needed is 0
    or the scaled matrix would leave the float range."""
    n = S.shape[0] // 2
    kinetic = np.abs(np.diagonal(S)[n:])
    potential = np.abs(np.diagonal(S)[:n])
    if n == 0 or not np.all(kinetic > 0) or (balance and not np.all(potential > 0)):
        return S
    with np.errstate(over="ignore"):
        target = 0.25 * np.log2(kinetic / potential) if balance else 0.5 * np.log2(kinetic)
    if not np.all(np.isfinite(target)):
        return S
    return _point_scaled(S, np.ldexp(1.0, np.round(target).astype(int)))


def _point_scaled(S: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``T^T S T`` for ``T = diag(d, 1/d)``, ``d`` powers of two: one multiplication by a
    power of two per entry, exact unless it leaves the normal range (then S itself)."""
    scale = np.concatenate([d, 1.0 / d])
    with np.errstate(over="ignore", under="ignore"):
        scaled = S * np.outer(scale, scale)
    exact = bool(np.all(np.isfinite(scaled))
                 and not np.any((S != 0) & (np.abs(scaled) < np.finfo(float).tiny)))
    return scaled if exact else S


#: :func:`balanced_blocks` rescales only blocks this far apart (a power of two).
BLOCK_RATIO = 2.0 ** 8


def balanced_blocks(S: np.ndarray) -> np.ndarray:
    """``T^T S T`` for ``T = diag(d I, I / d)``, ``d`` the power of two nearest
    ``(|S_pp|_F / |S_qq|_F)^(1/4)``, which brings the two diagonal blocks to one size (the
    same system with q in units d times larger and p d times smaller; applied exactly);
    S itself when they are within :data:`BLOCK_RATIO`, a block is 0, or the scaled matrix
    would leave the float range."""
    n = S.shape[0] // 2
    with np.errstate(over="ignore"):
        potential, kinetic = np.linalg.norm(S[:n, :n]), np.linalg.norm(S[n:, n:])
    if not (np.isfinite(potential) and np.isfinite(kinetic) and potential > 0 and kinetic > 0):
        return S
    if 1.0 / BLOCK_RATIO <= kinetic / potential <= BLOCK_RATIO:
        return S
    d = float(np.ldexp(1.0, round(0.25 * (np.log2(kinetic) - np.log2(potential)))))
    return _point_scaled(S, np.full(n, d))


def _symmetric(X: np.ndarray) -> np.ndarray:
    return 0.5 * (X + X.T)


def euler_deviation(frame: DiagonalFrame, factors: list[tuple[str, float]], h: float,
                    norm_S: float, fold_ratio: float = FOLD_RATIO
                    ) -> tuple[np.ndarray, float]:
    """``(D, err)``: ``D = M~(h) - I`` of the symplectic Euler factors ``("DK" | "KD", c)``
    (applied in order, weights ``c h``) in the frame, and a first-order bound on the
    Frobenius error of D (rounding, and the frame's ``error`` as a perturbation of S).

    With ``H = q^T A q / 2 + q^T C p + p^T B p / 2`` (A, B diagonal), ``f = C^T q + B p``
    (dH/dp) and ``g = -(A q + C p)``:

    * ``DK(c)``: ``(I - c C^T) y = f(q, p)`` gives ``y = f(q1, p)``, ``q1 = q + c y``, then
      ``p1 = p - c u``, ``u = A q1 + C p``; ``C^T q1 = y - B p`` comes free, ``C p1`` is
      ``C p - c C u``.
    * ``KD(c)``: ``(I + c C) w = A q + C p`` gives ``w = -g(q, p1)``, ``p1 = p - c w``,
      ``C p1 = w - A q`` free, then ``q1 = q + c v``, ``v = C^T q + B p1``; ``C^T q1`` is
      ``C^T q + c C^T v``.

    The product a factor leaves (``C u`` or ``C^T v``) is folded into the next factor's
    solve when that factor is of the other kind: with ``r = c_prev / c``,
    ``(I + c C)^-1 C = (I - (I + c C)^-1) / c`` turns the next right-hand side into
    ``(1 + r) u`` and its solution into ``(I + c C)^-1 (1 + r) u - r u`` (likewise
    ``(I - c C^T)^-1 (1 + r) v - r v``). Each factor then costs one n x n inverse and one
    product. The fold multiplies the rounding of that solution by about ``1 + 2 |r|``, so it
    is taken only for ``|r| <= fold_ratio`` (:data:`FOLD_RATIO`; else the product is formed) and the
    bound is widened by that factor.

    A step whose stage matrix is singular (no unique step) gives a NaN D. The increments
    are accumulated on D, never on ``I + D``.
    """
    a, b, C = frame.a[:, None], frame.b[:, None], frame.C
    n = C.shape[0]
    eye = np.eye(n)
    diag = np.arange(n)
    right = diag + n  # the p block's identity columns
    a0, b0 = a[:, 0], b[:, 0]
    # q = [I, 0] + Dq, p = [0, I] + Dp are never formed: the identity's contribution is
    # added on the diagonal of the block it sits in. Every update is made in place on
    # preallocated arrays (at n = 800 a temporary of n x 2n is 10 MB, and allocating one
    # per operation cost more than the operation).
    D = np.zeros((2 * n, 2 * n))
    Dq, Dp = D[:n], D[n:]
    Ctq = np.hstack([C.T, np.zeros((n, n))])  # C^T q
    Cp = np.hstack([np.zeros((n, n)), C])  # C p
    work = np.empty((n, 2 * n))  # the right-hand side of a factor
    y = np.empty((n, 2 * n))  # its solution, then a product
    err = 0.0
    size = float(np.sqrt(2 * n))  # |I + D|_F
    weights = [h * weight for _, weight in factors]
    r = 0.0  # c_prev / c when the previous factor's product is folded into this one
    for k, (label, _) in enumerate(factors):
        c = weights[k]
        following = weights[k + 1] if k + 1 < len(factors) else 0.0
        fold_next = (following != 0.0 and factors[k + 1][0] != label
                     and abs(c) <= fold_ratio * abs(following))
        carry = k + 1 < len(factors) and not fold_next
        solver = Solver.of(eye - c * C.T if label == "DK" else eye + c * C,
                           abs(c) * frame.C_norm)
        if solver is None:
            return np.full((2 * n, 2 * n), np.nan), np.inf
        if label == "DK":
            # work = f(q, p) = C^T q + B p; y = f(q1, p)
            np.multiply(b, Dp, out=work)
            work += Ctq
            work[diag, right] += b0
            solver.solve(work, r, y)
            np.multiply(b, Dp, out=Ctq)  # C^T q1 = y - B p
            np.subtract(y, Ctq, out=Ctq)
            Ctq[diag, right] -= b0
            y *= c  # dq
            Dq += y
            np.multiply(a, Dq, out=work)  # u = A q1 + C p
            work[diag, diag] += a0
            work += Cp
            if carry:
                np.matmul(C, work, out=y)
                y *= c
                Cp -= y
            work *= c
            Dp -= work
        else:
            np.multiply(a, Dq, out=work)  # A q + C p
            work[diag, diag] += a0
            work += Cp
            solver.solve(work, r, y)  # w = -g(q, p1)
            Cp -= work  # C p1 = w - A q
            Cp += y
            y *= c
            Dp -= y
            np.multiply(b, Dp, out=work)  # v = C^T q + B p1
            work += Ctq
            work[diag, right] += b0
            if carry:
                np.matmul(C.T, work, out=y)
                y *= c
                Ctq += y
            work *= c
            Dq += work
        # rounding of this factor and of the products carried into it, plus the frame; a
        # folded solve's rounding reaches D through c and the next factor's weight
        # (a solve's rounding grows with its matrix's condition times its inverse's size;
        # the frame's error, as a perturbation of the right-hand side, with the inverse's
        # size: both large only near a pole, where the stage matrix is singular. Its
        # second route, through the stage matrix, c ||A^-1||^2 ||dC|| ||y||, is not
        # carried: it matters only near such a pole)
        grow = solver.amplification
        err += abs(c) * ((4 * n + 2 * k) * EPS * norm_S * grow
                         + frame.error * solver.inverse_norm) * size
        if r:
            err += (abs(c) + abs(following)) * (1 + 2 * abs(r)) * n * EPS * norm_S * size \
                * grow
        r = c / following if fold_next else 0.0
        # |I + D|_F^2 = |D|_F^2 + 2 trace(D) + 2n
        trace = float(np.trace(Dq[:, :n]) + np.trace(Dp[:, n:]))
        size = float(np.sqrt(max(np.linalg.norm(D) ** 2 + 2 * trace + 2 * n, 0.0)))
    if not np.all(np.isfinite(D)):
        return np.full((2 * n, 2 * n), np.nan), np.inf
    return D, err


#: From this n on, a factor's stage matrix is applied through its LU factors rather than
#: its explicit inverse and one product: measured with one BLAS thread, the inverse is
#: 1.7x faster at n = 200, even at 400, and 1.3x slower at 800 (``getri`` scales worse).
SOLVE_FROM = 512
#: The LU factors are applied by block substitution with the inverses of diagonal blocks
#: of this size, so that nearly all the work is matrix products (at n = 800, 2n
#: right-hand sides and one BLAS thread: 0.7 of the time of LAPACK's ``getrs``).
SOLVE_BLOCK = 128
#: LAPACK's condition estimate (``gecon``, Hager-Higham) is a lower bound, usually within a
#: factor of 3 of the 1-norm condition: it is taken times this.
ESTIMATE_SAFETY = 10.0


@dataclass(frozen=True)
class Solver:
    """A factor's stage matrix ``A``, ready to apply ``A^-1``: its explicit inverse, or
    (n >= :data:`SOLVE_FROM`) ``P A = L U`` with the inverses of the diagonal blocks of
    L and U (:data:`SOLVE_BLOCK`)."""

    inverse: np.ndarray | None
    lu: np.ndarray | None = None
    rows: np.ndarray | None = None  #: P as a row order: (P x)_i = x[rows[i]]
    blocks: tuple[tuple[int, int, np.ndarray, np.ndarray], ...] = ()  #: (a, b, L^-1, U^-1)
    #: what the rounding of a solve is multiplied by (:func:`_amplification`)
    amplification: float = 1.0
    #: a bound on ``max(1, ||A^-1||_2)``
    inverse_norm: float = 1.0

    @staticmethod
    def of(A: np.ndarray, offset: float | None = None) -> Solver | None:
        """None if A is singular to working precision (no unique step). ``offset``: a bound
        on ``||A - I||_2`` (the stage matrices are ``I -+ c C``); below 1 it bounds A's
        condition rigorously and closely (Neumann: ``||A^-1|| <= 1 / (1 - offset)``)."""
        from scipy.linalg import lapack

        close = offset is not None and offset < 1.0
        neumann = neumann_inverse = np.inf
        if offset is not None and close:
            neumann = _amplification(1.0 + offset, 1.0 / (1.0 - offset))
            neumann_inverse = 1.0 / (1.0 - offset)
        if A.shape[0] < SOLVE_FROM:
            inverse = _inverse(A)
            if inverse is None:
                return None
            if close:  # (the norms below could only do better near offset = 1)
                return Solver(inverse, amplification=neumann, inverse_norm=neumann_inverse)
            absolute, inverse_absolute = np.abs(A), np.abs(inverse)
            size = float(np.sqrt(absolute.sum(axis=0).max() * absolute.sum(axis=1).max()))
            inverse_size = float(np.sqrt(inverse_absolute.sum(axis=0).max()
                                         * inverse_absolute.sum(axis=1).max()))
            return Solver(inverse, amplification=min(neumann,
                                                     _amplification(size, inverse_size)),
                          inverse_norm=max(1.0, min(neumann_inverse, inverse_size)))
        if not close:
            absolute = np.abs(A)
            norm_1 = float(absolute.sum(axis=0).max())
            norm_inf = float(absolute.sum(axis=1).max())
        lu, piv, info = lapack.dgetrf(A)
        if info != 0 or not np.all(np.isfinite(lu)):
            return None
        n = A.shape[0]
        rows = np.arange(n)
        for i, p in enumerate(piv):  # the interchanges, in order
            rows[i], rows[p] = rows[p], rows[i]
        blocks = []
        for a in range(0, n, SOLVE_BLOCK):
            b = min(a + SOLVE_BLOCK, n)
            lower, info_l = lapack.dtrtri(lu[a:b, a:b], lower=1, unitdiag=1)
            upper, info_u = lapack.dtrtri(lu[a:b, a:b], lower=0)
            if info_l != 0 or info_u != 0:
                return None
            blocks.append((a, b, np.tril(lower, -1) + np.eye(b - a), np.triu(upper)))
        if close:
            return Solver(None, lu, rows, tuple(blocks), neumann, neumann_inverse)
        estimates = [lapack.dgecon(lu, norm, norm=kind)
                     for norm, kind in ((norm_1, "1"), (norm_inf, "I"))]
        if any(info != 0 or not reciprocal > 0 for reciprocal, info in estimates):
            return None
        # kappa_2 <= sqrt(kappa_1 kappa_inf), ||A||_2 <= sqrt(||A||_1 ||A||_inf)
        size = float(np.sqrt(norm_1 * norm_inf))
        condition = 1.0 / float(np.sqrt(estimates[0][0] * estimates[1][0]))
        return Solver(None, lu, rows, tuple(blocks),
                      ESTIMATE_SAFETY * _amplification(size, condition / size),
                      max(1.0, ESTIMATE_SAFETY * condition / size))

    def solve(self, rhs: np.ndarray, r: float, out: np.ndarray) -> None:
        """``out = A^-1 rhs``, or with a folded product (``r != 0``, see
        :func:`euler_deviation`) ``A^-1 (1 + r) rhs - r rhs``; ``rhs`` is kept."""
        if self.inverse is not None:
            np.matmul(self.inverse, rhs, out=out)
        else:
            lu, rows = self.lu, self.rows  # a solver without the inverse holds P A = L U
            assert lu is not None and rows is not None
            for a, b, lower, _ in self.blocks:  # L y = P rhs, a block of rows at a time
                block = rhs[rows[a:b]]
                if a:
                    block -= lu[a:b, :a] @ out[:a]
                np.matmul(lower, block, out=out[a:b])
            for a, b, _, upper in reversed(self.blocks):  # U x = y
                if b < lu.shape[0]:
                    out[a:b] -= lu[a:b, b:] @ out[b:]
                out[a:b] = upper @ out[a:b]
        if r:
            out *= 1.0 + r
            out -= r * rhs


def norm_2(X: np.ndarray) -> float:
    """A bound on ``||X||_2``: the square root of the largest eigenvalue of ``X^T X``,
    widened by that eigenvalue's rounding (``4 n eps ||X^T X||_F``)."""
    if not X.size or not np.any(X):
        return 0.0
    gram = X.T @ X
    top = extreme_eigenvalue(gram, highest=True)
    top += 4 * X.shape[0] * EPS * float(np.linalg.norm(gram))
    return float(np.sqrt(max(top, 0.0)))


def _amplification(size: float, inverse_size: float) -> float:
    """``kappa(A) max(1, ||A^-1||)`` (2-norms, each bounded by ``sqrt(||.||_1 ||.||_inf)``):
    a solve's backward error relative to A becomes a forward error kappa times its size,
    and the right-hand side's own rounding is carried through A^-1; near a pole, where A
    turns singular, both grow. At least 1."""
    return max(1.0, size * inverse_size * max(1.0, inverse_size))


def _inverse(A: np.ndarray) -> np.ndarray | None:
    """``A^-1`` from its LU factors (``getri``; None if A is singular to working
    precision); any loss of symplecticity this costs is measured by the coupled analysis
    (the defect of M)."""
    from scipy.linalg import lapack

    lu, piv, info = lapack.dgetrf(A)
    if info != 0 or not np.all(np.isfinite(lu)):
        return None
    inverse, info = lapack.dgetri(lu, piv)
    if info != 0 or not np.all(np.isfinite(inverse)):
        return None
    return inverse
