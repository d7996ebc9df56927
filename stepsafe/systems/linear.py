"""Linear n-dof systems: which modes to analyse, and the coupled analysis when they do not
decouple (docs/theory.md#systems-beyond-the-test-models).

``H = x^T S x / 2`` with ``x = (q, p)`` and ``S = [[S_qq, S_qp], [S_pq, S_pp]]`` gives
``x' = J S x``. Use the cheapest analysis that is exact for the system in hand:

* **separable** (``S_qp = 0``, ``S_pp`` positive definite: ``H = p^T M^-1 p/2 + q^T K q/2``,
  K may be indefinite): every method decouples along the generalised eigenvectors of
  ``K v = w^2 M v``; ``w^2 > 0`` is an ``oscillator`` of rate ``w``, ``w^2 < 0`` an
  ``inverted`` barrier of rate ``sqrt(-w^2)``, ``w^2 = 0`` a free mode (no limit). A
  partitioned method commutes with ``q -> T q, p -> T^-T p``, which is what decouples it.
* **RK methods** (not partitioned) commute with every linear change of variables, so they
  decouple along the eigenvalues ``mu`` of ``J S``: ``mu = +-i w`` is an ``oscillator``,
  ``mu = +-lam`` real a saddle (for RK methods ``saddle`` and ``inverted`` coincide).
  Complex quadruplets ``+-a +-ib`` (loxodromic) have no 1-dof model and go to the coupled
  analysis.
* otherwise (**coupled**, :mod:`stepsafe.systems.coupled`): the full 2n x 2n one-step matrix, whose
  multipliers must have the types and Krein signatures of the eigenvalues of ``J S``. The
  orientation of hyperbolic directions is not checked in the coupled analysis.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from stepsafe.core.threads import blas_threads_for
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method

ZERO_TOL = 1e-10  # eigenvalues of J S below this times the largest are zero modes
EPS = float(np.finfo(float).eps)


class LinearMode(NamedTuple):
    beta: float
    model: str  # "oscillator", "inverted", "saddle", "free"
    eigenvalue: complex  # w^2 (separable) or mu (eigenvalues of J S)
    decided: bool = True  # False: within rounding of 0, analysed as both types
    rel_error: float = 0.0  # relative uncertainty of beta (from the eigenvalue's rounding)


class Decoupled(NamedTuple):
    modes: tuple[LinearMode, ...]
    analysis: str
    extremes_only: bool = False


class MatrixError(StepsafeError):
    """A system matrix is unusable; ``key`` names it (``stiffness``, ``mass``, ``hessian``)
    so that the scene-file error points at the right key."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def check_square(A: np.ndarray, name: str, symmetric: bool = True) -> np.ndarray:
    if isinstance(A, np.ndarray) and A.dtype.kind not in "fiu":
        raise MatrixError(name, f"{name} must hold real numbers, got dtype {A.dtype}")
    try:
        A = np.asarray(A, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise MatrixError(name, f"{name} must hold real numbers") from None
    if A.ndim != 2 or A.shape[0] != A.shape[1] or A.size == 0:
        raise MatrixError(name, f"{name} must be a non-empty square matrix, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise MatrixError(name, f"{name} has a non-finite entry")
    if symmetric and not np.allclose(A, A.T, rtol=1e-12, atol=1e-12 * np.abs(A).max()):
        raise MatrixError(name, f"{name} must be symmetric")
    return symmetric_part(A) if symmetric else A


def symmetric_part(A):
    """``(A + A^T) / 2``, what a quadratic form ``x^T A x / 2`` sees (dense or sparse): the
    entries that differ from their mirror replaced by their mean (halved first, so nothing
    overflows), the others kept exactly. Solvers that read one triangle, or a matrix
    product with A, then analyse the same matrix."""
    if not isinstance(A, np.ndarray):  # a scipy.sparse matrix
        A = A.tocsr()
        return A if (A != A.T).nnz == 0 else (0.5 * A + 0.5 * A.T).tocsr()
    differ = A != A.T
    if not differ.any():
        return A
    mean = 0.5 * A + 0.5 * A.T
    return np.where(differ, mean, A)


def is_positive_definite(M: np.ndarray) -> bool:
    """Whether the symmetric matrix M is positive definite, whatever its scaling.

    Decided by a Cholesky factorisation of ``D^-1/2 M D^-1/2`` (``D = diag M``, unit
    diagonal), not by an absolute eigenvalue threshold: ``diag(1e-300, 1e300)`` is positive
    definite. A positive definite M has ``M_ii > 0`` and ``|M_ij| < sqrt(M_ii M_jj)``, so the
    scaled entries are at most 1 and cannot overflow; an entry that overflows proves M
    indefinite.
    """
    d = np.diag(M)
    if not np.all(d > 0):
        return False
    s = np.sqrt(d)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        C = M / s[:, None] / s[None, :]
    if not np.all(np.isfinite(C)):
        return False
    np.fill_diagonal(C, 1.0)
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return False
    return True


def separable_modes(K, M=None) -> Decoupled:
    """Modes of ``H = p^T M^-1 p / 2 + q^T K q / 2`` (dense K and M)."""
    from scipy.linalg import eigh

    K = check_square(K, "stiffness")
    n = K.shape[0]
    if M is not None:
        M = check_square(M, "mass")
        if M.shape != K.shape:
            raise MatrixError("mass", f"mass is {M.shape[0]}x{M.shape[0]} but stiffness is "
                                      f"{n}x{n}")
        with blas_threads_for(n):
            if not is_positive_definite(M):
                raise MatrixError("mass", "mass must be positive definite")
    if is_diagonal(K) and (M is None or is_diagonal(M)):
        # decoupled already: w = sqrt|k_i| / sqrt(m_i), a rounding per operation (an
        # eigensolver's absolute bound, n eps |K|, would leave 1e-16 of a 1e16-conditioned
        # diagonal undecided); no w^2 is formed, so k = 1e-300 against m = 1e300 (w =
        # 1e-300) neither underflows nor overflows
        k = np.diagonal(K)
        m = np.ones(n) if M is None else np.diagonal(M)
        with np.errstate(all="ignore"):
            w = np.sqrt(np.abs(k)) / np.sqrt(m)
        if not np.all(np.isfinite(w)) or np.any((w == 0) & (k != 0)):
            raise MatrixError("stiffness", "a frequency sqrt(|k_i| / m_i) is beyond the "
                                           "float64 range; rescale the units of K or M")
        order = np.argsort(np.sign(k) * w, kind="stable")
        return Decoupled(_modes_from_rates(np.sign(k)[order], w[order]),
                         "decoupled: separable H, diagonal K and M (w^2 = k_i / m_i)")
    # K / 2^a and M / 2^b have entries of order 1 (exact: powers of two, a - b even): their
    # w^2 are those of K and M times 2^(b - a), and w times 2^((b - a) / 2), so the
    # eigenproblem is solved in range whatever the units (K = 1e-300 I against M = 1e300 I);
    # not where an entry would leave the normal range (a matrix spanning more than it)
    a = _exponent(K)
    b = 0 if M is None else _exponent(M)
    a += (a - b) % 2
    if _exact_scaling(K, a) and (M is None or _exact_scaling(M, b)):
        K = np.ldexp(K, -a)
        M = None if M is None else np.ldexp(M, -b)
    else:
        a = b = 0
    try:
        with np.errstate(all="ignore"), blas_threads_for(n):
            w2 = eigh(K, M, eigvals_only=True)  # M None: the standard problem
    except np.linalg.LinAlgError:
        raise MatrixError("mass", "the generalised eigenproblem K v = w^2 M v failed in "
                                  "float64 (mass too badly scaled); rescale the units") from None
    if not np.all(np.isfinite(w2)):
        raise MatrixError("stiffness", "the eigenvalues w^2 of K v = w^2 M v are beyond the "
                                       "float64 range; rescale the units of K or M")
    modes = _modes_from_w2(w2, _eigenvalue_error(w2, n) * _cond(M), (a - b) // 2)
    if any(m.model != "free" and not 0 < m.beta < np.inf for m in modes):
        raise MatrixError("stiffness", "a frequency of K v = w^2 M v is beyond the float64 "
                                       "range; rescale the units of K or M")
    return Decoupled(modes,
                     "decoupled: separable H, generalised eigenproblem K v = w^2 M v")


def gaussian_modes(C, M=None) -> Decoupled:
    """Modes of HMC on a Gaussian target of covariance ``C`` with mass (preconditioner)
    ``M``: ``H = p^T M^-1 p / 2 + q^T C^-1 q / 2``, so ``w^2`` are the eigenvalues of
    ``C^-1`` against M, i.e. ``1/mu`` for the eigenvalues ``mu`` of ``L^T C L`` (``M = L
    L^T``; ``C`` itself without a mass). Computed from C directly (no inverse): each
    ``mu`` is known to ``16 n eps mu_max`` (times the condition of M at unit diagonal), so
    ``beta = mu^-1/2`` to half that relative to ``mu``."""
    C = check_square(C, "covariance")
    n = C.shape[0]
    with blas_threads_for(n):
        if not is_positive_definite(C):
            raise MatrixError("covariance", "covariance must be positive definite")
        A = C
        if M is not None:
            M = check_square(M, "mass")
            if M.shape != C.shape:
                raise MatrixError("mass", f"mass is {M.shape[0]}x{M.shape[0]} but covariance "
                                          f"is {n}x{n}")
            if not is_positive_definite(M):
                raise MatrixError("mass", "mass must be positive definite")
            L = np.linalg.cholesky(M)
            A = L.T @ C @ L
        diagonal = not np.count_nonzero(A - np.diag(np.diagonal(A)))
        with np.errstate(all="ignore"):
            mu = np.diagonal(A).copy() if diagonal else np.linalg.eigvalsh(0.5 * (A + A.T))
    # a diagonal covariance (without a mass) holds its variances exactly
    error = 0.0 if diagonal and M is None else _eigenvalue_error(mu, n) * _cond(M)
    if not np.all(np.isfinite(mu)) or not np.all(mu > error):
        raise MatrixError("covariance", "a variance is within rounding of 0 (or beyond "
                                        "float64): the frequency 1/sigma is not decided")
    modes = tuple(LinearMode(float(1.0 / np.sqrt(m)), "oscillator", complex(1.0 / m), True,
                             0.5 * error / m + 2 * EPS) for m in mu)
    return Decoupled(modes, "decoupled: Gaussian target, frequencies 1/sqrt of the "
                            "eigenvalues of the (mass-preconditioned) covariance")


def _cond(M: np.ndarray | None) -> float:
    """Condition number of a positive definite mass scaled to unit diagonal (it amplifies
    K's rounding in the generalised eigenvalues; a diagonal scaling only changes units, so
    no mass or a diagonal one has 1)."""
    if M is None or not np.count_nonzero(M - np.diag(np.diagonal(M))):
        return 1.0
    d = 1.0 / np.sqrt(np.diag(M))
    with blas_threads_for(M.shape[0]):
        m = np.linalg.eigvalsh(M * np.outer(d, d))
    return float(m.max() / m.min())


def _exponent(A: np.ndarray) -> int:
    """The power of two ``e`` with ``max |A_ij|`` in ``[2^(e-1), 2^e)`` (0 for A = 0)."""
    top = float(np.abs(A).max(initial=0.0))
    return int(np.frexp(top)[1]) if top > 0 and np.isfinite(top) else 0


def _exact_scaling(A: np.ndarray, e: int) -> bool:
    """Whether ``A / 2^e`` keeps every normal entry of A normal (so it is exact)."""
    tiny = np.finfo(float).tiny
    with np.errstate(all="ignore"):
        scaled = np.ldexp(A, -e)
    return bool(np.all(np.isfinite(scaled))
                and not np.any((np.abs(A) >= tiny) & (np.abs(scaled) < tiny)))


def _modes_from_rates(signs: np.ndarray, w: np.ndarray) -> tuple[LinearMode, ...]:
    """Modes of exactly known type: ``sign > 0`` a vibration of rate ``w``, ``< 0`` a
    barrier, ``0`` free; each rate a few roundings from the truth."""
    out = []
    for sign, rate in zip(signs, w):
        with np.errstate(all="ignore"):
            value = complex(sign * rate * rate)
        if sign == 0:
            out.append(LinearMode(0.0, "free", 0j))
        else:
            out.append(LinearMode(float(rate), "oscillator" if sign > 0 else "inverted",
                                  value, True, 2 * EPS))
    return tuple(out)


def _modes_from_w2(w2: np.ndarray, error: float, exponent: int = 0) -> tuple[LinearMode, ...]:
    """Modes from the eigenvalues ``w^2``, each known to ``error`` (absolute), of a problem
    whose rates are ``2^exponent`` times smaller than the system's (each rate is scaled
    back exactly). An
    eigenvalue within ``error`` of 0 has no decided sign: it might be a slow vibration or
    a slow barrier of rate up to ``sqrt(error)``, so it is analysed as both at that rate
    (a free mode only when exactly 0 with no rounding: a diagonal K). A stiff system keeps
    its slow modes: in ``diag(1e12, -1)`` the barrier of rate 1 is far above the rounding
    (~1e-3)."""
    def rate(x: float) -> float:
        return float(np.ldexp(np.sqrt(x), exponent))

    def square(x: float) -> complex:
        with np.errstate(all="ignore"):
            return complex(np.ldexp(x, 2 * exponent))

    out = []
    for value in w2:
        rel = 0.5 * error / abs(value) + 2 * EPS if value else 0.0  # of sqrt|w^2|
        if value == 0 and error == 0:
            out.append(LinearMode(0.0, "free", square(value)))
        elif abs(value) <= error:  # (a computed 0 too: its sign is not decided either)
            top = rate(error)  # the rate is anywhere in [0, top]
            out += [LinearMode(top, "oscillator", square(value), False, 1.0),
                    LinearMode(top, "inverted", square(value), False, 1.0)]
        elif value > 0:
            out.append(LinearMode(rate(value), "oscillator", square(value), True, rel))
        else:
            out.append(LinearMode(rate(-value), "inverted", square(value), True, rel))
    return tuple(out)


def _eigenvalue_error(values: np.ndarray, n: int) -> float:
    """Absolute rounding bound of the eigenvalues of a symmetric (or symmetric-definite)
    problem of size n: a small multiple of ``n eps`` times the largest modulus."""
    return 16.0 * n * EPS * float(np.abs(values).max(initial=0.0))


def sparse_extreme_modes(K, M=None) -> Decoupled:
    """Only the extreme modes of a large separable system, sparse or dense (enough for
    ``h_max``).

    A diagonal (lumped) mass is folded in, ``M^-1/2 K M^-1/2``. The largest ``w^2`` is found
    by shift-invert Lanczos (``eigsh``) just above the Gershgorin upper bound, where it
    converges in a few iterations even when the top of the spectrum is clustered (a chain
    of 10^5 masses: gaps of 1e-9); the smallest likewise below the Gershgorin lower bound,
    only when that bound is negative (a barrier may exist). The eigenvalue nearest a shift
    above the whole spectrum is its largest, so no mode above it can be missed. A dense K
    is factorised once per shift (LU, ``2/3 n^3``) instead of reduced to tridiagonal form
    for every eigenvalue.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import ArpackNoConvergence, eigsh

    dense = isinstance(K, np.ndarray)
    K = np.asarray(K, dtype=float) if dense else sp.csr_matrix(K, dtype=float)
    n = K.shape[0]
    if K.shape[0] != K.shape[1]:
        raise MatrixError("stiffness", f"stiffness must be square, got shape {K.shape}")
    if not np.all(np.isfinite(K if dense else K.data)):
        raise MatrixError("stiffness", "stiffness has a non-finite entry")
    if n and abs(K - K.T).max() > 1e-12 * abs(K).max():
        raise MatrixError("stiffness", "stiffness must be symmetric")
    K = symmetric_part(K)
    if M is not None:
        M = sp.csr_matrix(M, dtype=float)
        if M.shape != K.shape:
            raise MatrixError("mass", f"mass is {M.shape} but stiffness is {K.shape}")
        if (M - sp.diags(M.diagonal())).count_nonzero():
            raise MatrixError("mass", "a large sparse system needs a diagonal (lumped) mass")
        m = M.diagonal()
        if not np.all(m > 0):
            raise MatrixError("mass", "mass must be positive definite")
        d = 1.0 / np.sqrt(m)
        K = K * np.outer(d, d) if dense else (sp.diags(d) @ K @ sp.diags(d)).tocsr()
    diag = np.diagonal(K) if dense else K.diagonal()
    off = np.asarray(abs(K).sum(axis=1)).ravel() - np.abs(diag)
    upper, lower = float((diag + off).max()), float((diag - off).min())
    scale = max(abs(upper), abs(lower), 1e-300)
    w2, bounded = [], False
    for bound, sign in ((upper, 1.0), (lower, -1.0)):
        if sign < 0 and (lower >= 0 or (_positive_definite(K) if dense
                                        else _sparse_positive_definite(K))):
            break  # no negative w^2: the smallest mode cannot limit h
        sigma = bound + sign * 1e-6 * scale
        try:
            with blas_threads_for(n):
                # a fixed start vector: ARPACK's own is drawn from a generator whose state
                # carries over between calls, so the answer would depend on the history
                # of the process (the budget can run out on one start and not another)
                start = np.random.default_rng(0).standard_normal(n)
                vals = eigsh(K if dense else K.tocsc(), k=1, sigma=sigma, which="LM",
                             v0=start, return_eigenvectors=False, tol=1e-13,
                             maxiter=int(min(500, max(3, EIGSH_WORK / (20 * max(n, 1))))))
            w2.append(float(vals[0]))
        except (ArpackNoConvergence, RuntimeError):
            # a clustered end of the spectrum (a long chain near w^2 = 0): the Gershgorin
            # bound itself, beyond every eigenvalue, is a frequency no mode exceeds
            w2.append(bound)
            bounded = True
    extremes = np.array(w2)
    how = ("shift-invert eigsh" if not bounded else
           "Gershgorin bounds where the eigensolver did not converge within its budget: "
           "conservative")
    return Decoupled(_modes_from_w2(extremes, 1e-12 * float(np.abs(extremes).max())),
                     "decoupled: separable H, extreme eigenvalues of K v = w^2 M v only "
                     f"({how}); islands not analysed", True)


#: Work of the Lanczos iteration for one extreme eigenvalue, in n x (solves with the
#: shift's factors; about 20 per restart): a few seconds at any size. A 10^6-dof chain whose
#: spectrum clusters at the shift took minutes unbounded; past the budget the Gershgorin
#: bound is used (conservative).
EIGSH_WORK = 1e8


def _positive_definite(K: np.ndarray) -> bool:
    """Whether a Cholesky factorisation of the dense symmetric K succeeds (``n^3/3``; a
    dense Gershgorin lower bound is usually far below the spectrum)."""
    try:
        np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        return False
    return True


def _sparse_positive_definite(K) -> bool:
    """Whether a sparse symmetric K factorises as ``P K P^T = L D L^T`` with every pivot
    of D positive (SuperLU with a symmetric fill-reducing order and diagonal pivots only,
    the sparse counterpart of a Cholesky factorisation; by Sylvester's law of inertia K
    then has no negative eigenvalue). False when the factorisation pivoted off the
    diagonal or failed: nothing is then ruled out."""
    from scipy.sparse.linalg import splu

    try:
        lu = splu(K.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except (RuntimeError, ValueError, MemoryError):
        return False
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return False
    pivots = lu.U.diagonal()
    return bool(np.all(np.isfinite(pivots)) and np.all(pivots > 0))


def is_diagonal(M) -> bool:
    """Whether a dense or sparse matrix has no off-diagonal entry."""
    if hasattr(M, "diagonal") and not isinstance(M, np.ndarray):
        import scipy.sparse as sp

        return not (M - sp.diags(M.diagonal())).count_nonzero()
    return not np.count_nonzero(M - np.diag(np.diagonal(M)))


def split_hessian(S) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    S = check_square(S, "hessian")
    if S.shape[0] % 2:
        raise MatrixError("hessian", f"hessian must be 2n x 2n for x = (q, p), got {S.shape[0]}")
    n = S.shape[0] // 2
    return S[:n, :n], S[:n, n:], S[n:, :n], S[n:, n:]


def normalised(S: np.ndarray) -> tuple[np.ndarray, int]:
    """``(S', e)``: ``S' = 2^-e T^T S T`` for the symplectic point transformation ``T =
    diag(d, 1/d)`` (``q -> d q``, ``p -> p / d``), ``d_i`` the power of two nearest
    ``|S_pp[i, i] / S_qq[i, i]|^(1/4)`` (each coordinate's two diagonal entries brought to
    one size; where one is 0, the blocks' norms stand in), and ``2^e`` the power of two
    that brings the largest entry into ``[1/2, 1)`` (a unit of time: the rates of ``S`` are
    ``2^e`` times those of ``S'``).

    Both are exact in floating point (multiplications by powers of two), so ``J S'`` has the
    eigenvalues of ``J S`` divided by ``2^e`` with the same types and Krein signatures, and
    every partitioned method commutes with ``T``: classifying ``S'`` classifies ``S``, in
    any units. The point transformation is skipped where a normal entry would leave the
    normal range (an entry spread of more than 1e300 within one matrix); entries far below
    the largest (subnormal ones, ``2^-1074`` of it) may lose digits or become 0, far below
    every rounding bound."""
    n = S.shape[0] // 2
    potential, kinetic = np.abs(np.diagonal(S)[:n]), np.abs(np.diagonal(S)[n:])
    with np.errstate(all="ignore"):
        blocks = 0.25 * (np.log2(np.linalg.norm(S[n:, n:])) - np.log2(np.linalg.norm(S[:n, :n])))
        target = np.where((potential > 0) & (kinetic > 0),
                          0.25 * (np.log2(kinetic) - np.log2(potential)),
                          blocks if np.isfinite(blocks) else 0.0)
    d = np.ldexp(1.0, np.round(np.where(np.isfinite(target), target, 0.0)).astype(int))
    scale = np.concatenate([d, 1.0 / d])
    with np.errstate(all="ignore"):
        scaled = S * np.outer(scale, scale)
    tiny = np.finfo(float).tiny
    if np.all(np.isfinite(scaled)) and not np.any((np.abs(S) >= tiny) & (np.abs(scaled) < tiny)):
        S = scaled  # (exact: no normal entry left the normal range)
    e = _exponent(S)
    return np.ldexp(S, -e), e


def hessian_modes(S, method: Method) -> Decoupled | None:
    """The decoupled modes of ``H = x^T S x / 2`` when they are exact for ``method``,
    else None (the coupled analysis is needed). Analysed as :func:`normalised` ``S'``, whose
    rates are scaled back exactly: any units from 1e-300 to 1e300, in q and p together or
    apart."""
    S = check_square(S, "hessian")
    split_hessian(S)
    S, exponent = normalised(S)
    S_qq, S_qp, _, S_pp = split_hessian(S)
    if not S_qp.any() and np.linalg.eigvalsh(S_pp).min() > 0:
        kinetic = np.linalg.inv(S_pp)
        if is_diagonal(S_pp):  # exact reciprocals of a diagonal: no inverse's rounding
            with np.errstate(all="ignore"):
                kinetic = np.diag(1.0 / np.diagonal(S_pp))
        d = separable_modes(S_qq, kinetic)
        return d._replace(modes=tuple(_scaled_mode(m, exponent, 2) for m in d.modes),
                          analysis="decoupled: separable Hessian, generalised eigenproblem")
    if method.partitioned:
        return None
    mu = np.linalg.eigvals(hamiltonian_matrix(S))
    mu = mu[(mu.imag > 0) | ((mu.imag == 0) & (mu.real >= 0))]
    # eigenvalues of J S carry an absolute error of a few n eps |J S| (|S| < 1 here): a
    # real or imaginary part within it is zero. A pair +-mu near 0 is the split of a
    # double eigenvalue: mu^2 moves by that error, so mu by error / |mu|, and a pair
    # within sqrt(error) of 0 is analysed as a vibration and a saddle of rate sqrt(error)
    # (its type and size are not decided; e.g. S = [[1, 3.16], [3.16, 10]], mu^2 = 1e-15)
    error = 1e3 * S.shape[0] * EPS * max(float(np.abs(S).max()),
                                         float(np.abs(mu).max(initial=0.0)))
    floor = float(np.sqrt(error))
    modes = []
    for m in mu:
        rel = error / abs(m) + error / abs(m) ** 2 + 2 * EPS if m else 0.0
        if m == 0:
            modes.append(LinearMode(0.0, "free", complex(m)))
        elif abs(m) <= floor:
            modes += [LinearMode(floor, "oscillator", complex(m), False, 1.0),
                      LinearMode(floor, "saddle", complex(m), False, 1.0)]
        elif abs(m.real) <= error:
            modes.append(LinearMode(float(abs(m.imag)), "oscillator", complex(m), True, rel))
        elif abs(m.imag) <= error:
            modes.append(LinearMode(float(abs(m.real)), "saddle", complex(m), True, rel))
        else:
            return None  # loxodromic: no 1-dof model
    return Decoupled(tuple(_scaled_mode(m, exponent, 1) for m in modes),
                     "decoupled: RK method, eigenvalues of J S")


def _scaled_mode(mode: LinearMode, exponent: int, power: int) -> LinearMode:
    """A mode of :func:`normalised` ``S'`` as one of S: its rate times ``2^exponent``
    (exact), its eigenvalue times ``2^(power exponent)`` (``power`` 2 for ``w^2``, 1 for an
    eigenvalue ``mu`` of ``J S``; it may leave float64's range, the rate does not)."""
    with np.errstate(all="ignore"):
        value = complex(np.ldexp(mode.eigenvalue.real, power * exponent),
                        np.ldexp(mode.eigenvalue.imag, power * exponent))
    return mode._replace(beta=float(np.ldexp(mode.beta, exponent)), eigenvalue=value)


def hamiltonian_matrix(S: np.ndarray) -> np.ndarray:
    """``J S`` with ``J = [[0, I], [-I, 0]]``: the generator of ``x' = J S x``."""
    n = S.shape[0] // 2
    return np.vstack([S[n:], -S[:n]])
