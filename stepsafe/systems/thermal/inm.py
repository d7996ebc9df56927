"""Instantaneous normal modes: the extreme frequencies of a potential at given
configurations.

At a configuration q (an equilibrium or not) the local frequencies are ``sqrt(lambda)`` for
the eigenvalues lambda of the mass-weighted Hessian ``W = M^-1/2 grad^2 U(q) M^-1/2``. A
negative lambda is an unstable direction there (an imaginary frequency
``i sqrt(-lambda)``): thermal configurations visit regions where U curves downward.

Two ways, chosen by the dimension n:

* ``n <= exact_up_to``: W is built (from the analytic Hessian, or column by column from
  Hessian-vector products) and all its eigenvalues are computed by ``numpy.linalg.eigvalsh``,
  vectorised over configurations. Error bound: ``4 n eps max|lambda|`` (the symmetric
  eigensolver's backward error) plus, for a difference Hessian, the Frobenius norm of the
  columns' estimated errors (Weyl: an eigenvalue moves by at most the perturbation's
  2-norm).
* larger n: Lanczos (``scipy.sparse.linalg.eigsh``) on the operator ``x -> W x`` from a
  fixed start vector (standard normal, seed stated), for the largest and the smallest
  eigenvalue. For a symmetric W the Ritz pair ``(theta, x)`` with ``|x| = 1`` has an
  eigenvalue within the residual ``|W x - theta x|`` of theta, which is added to the error
  (with the product's difference error where W is applied by differences).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.potential import EPS, Potential, fd_hessian_vector

#: Largest n for which W is built and fully diagonalised.
EXACT_UP_TO = 256
#: Relative tolerance passed to eigsh.
LANCZOS_TOL = 1e-10
#: Seed of the fixed Lanczos start vector.
START_SEED = 0
#: Elements of W (configurations x n x n) built at once.
CHUNK_ELEMENTS = 2 ** 22


@dataclass(frozen=True)
class Frequencies:
    """The extreme eigenvalues of W at m configurations.

    Attributes
    ----------
    lambda_max, lambda_min : ndarray
        Largest and smallest eigenvalue of W at each configuration, shape ``(m,)``.
    error : ndarray
        An absolute bound (estimate, for difference Hessians) on the error of both, ``(m,)``.
    how : str
        ``"eigvalsh (analytic Hessian)"``, ``"eigvalsh (difference Hessian)"`` or
        ``"Lanczos (eigsh) on Hessian-vector products"``.
    start_seed : int or None
        The seed of the Lanczos start vector (None for eigvalsh).
    """

    lambda_max: np.ndarray
    lambda_min: np.ndarray
    error: np.ndarray
    how: str
    start_seed: int | None = None

    @property
    def omega_max(self) -> np.ndarray:
        """``sqrt(lambda_max)`` (0 where lambda_max <= 0)."""
        return np.sqrt(np.maximum(self.lambda_max, 0.0))

    @property
    def omega_max_upper(self) -> np.ndarray:
        """``sqrt(lambda_max + error)``: an upper bound on the largest frequency."""
        return np.sqrt(np.maximum(self.lambda_max + self.error, 0.0))

    @property
    def imaginary(self) -> np.ndarray:
        """``sqrt(-lambda_min)`` where lambda_min < 0 (the growth rate of the most
        unstable direction), else 0."""
        return np.sqrt(np.maximum(-self.lambda_min, 0.0))

    @property
    def unstable(self) -> np.ndarray:
        """Configurations with a direction of negative curvature beyond the error."""
        return self.lambda_min < -self.error


def frequencies(pot: Potential, q, exact_up_to: int = EXACT_UP_TO,
                tol: float = LANCZOS_TOL, seed: int = START_SEED) -> Frequencies:
    """The largest and smallest eigenvalue of ``W(q)`` at each configuration.

    Parameters
    ----------
    pot : Potential
    q : array_like
        Configurations ``(m, n)``.
    exact_up_to : int
        Build and diagonalise W up to this n; Lanczos beyond.
    tol : float
        eigsh's relative tolerance.
    seed : int
        The Lanczos start vector's seed.

    Returns
    -------
    Frequencies
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = pot.dimension
    if q.shape[1] != n:
        raise StepsafeError(f"configurations must have {n} coordinates, got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise StepsafeError("configurations must be finite")
    if n <= exact_up_to:
        values, error, how = _exact(pot, q)
        return Frequencies(values[:, -1], values[:, 0], error, how)
    top = np.empty(q.shape[0])
    low = np.empty(q.shape[0])
    err = np.empty(q.shape[0])
    for i, row in enumerate(q):
        top[i], low[i], err[i] = _lanczos(pot, row, tol, seed)
    return Frequencies(top, low, err, "Lanczos (eigsh) on Hessian-vector products", seed)


def mass_weighted(pot: Potential, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """W at each configuration ``(m, n, n)``, symmetrised, with the 2-norm error bound of
    its construction ``(m,)`` (0 for an analytic Hessian)."""
    m, n = q.shape
    if pot.hessian is not None:
        return pot.mass_weighted_hessian(q), np.zeros(m), "eigvalsh (analytic Hessian)"
    r = 1.0 / np.sqrt(pot.masses)
    Q = np.repeat(q, n, axis=0)  # (m n, n): configuration k, column j at row k n + j
    V = np.tile(np.diag(r), (m, 1))
    prod = pot.product(Q, V)
    W = prod.value.reshape(m, n, n) * r[None, None, :]  # [k, j, :] = column j of W
    W = np.swapaxes(W, 1, 2)
    col = prod.error.reshape(m, n) * float(np.max(r)) * np.sqrt(n)  # 2-norm of each column
    error = np.sqrt(np.sum(col ** 2, axis=1))
    how = ("eigvalsh (analytic Hessian)" if pot.has_hessian
           else "eigvalsh (difference Hessian)")
    return 0.5 * (W + np.swapaxes(W, 1, 2)), error, how


def _exact(pot: Potential, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    m, n = q.shape
    chunk = max(1, CHUNK_ELEMENTS // (4 * n * n))
    values = np.empty((m, n))
    error = np.empty(m)
    how = ""
    for a in range(0, m, chunk):
        W, err, how = mass_weighted(pot, q[a:a + chunk])
        if not np.all(np.isfinite(W)):
            raise StepsafeError("the Hessian is not finite at a configuration")
        lam = np.linalg.eigvalsh(W)
        values[a:a + chunk] = lam
        error[a:a + chunk] = err + 4 * n * EPS * np.max(np.abs(lam), axis=1)
    return values, error, how


def _operator(pot: Potential, q: np.ndarray):
    """``x -> W x`` at one configuration, and the estimated error of one product with a
    unit vector (0 when analytic). A difference product keeps the step chosen once at a
    probe vector, so that the operator is the same on every call."""
    n = pot.dimension
    r = 1.0 / np.sqrt(pot.masses)
    row = q[None, :]
    if pot.has_hessian:
        def apply(x: np.ndarray) -> np.ndarray:
            x = np.asarray(x, dtype=float).reshape(-1)
            return r * pot.product(row, (r * x)[None, :]).value[0]

        return apply, 0.0
    probe = np.random.default_rng(START_SEED + 1).standard_normal(n)
    probe /= np.linalg.norm(probe)
    first = fd_hessian_vector(pot.gradient, row, (r * probe)[None, :], pot.scale_of(row))
    step = float(first.step[0])
    unit_error = float(first.error[0]) / float(np.linalg.norm(r * probe)) * np.sqrt(n)

    def apply_fd(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float).reshape(-1)
        v = r * x
        size = float(np.linalg.norm(v))
        if size == 0:
            return np.zeros(n)
        d = (step / size) * v
        g = pot.gradient(np.stack([q + d, q - d]))
        return r * (g[0] - g[1]) * (size / (2 * step))

    return apply_fd, unit_error * float(np.max(r))


def _lanczos(pot: Potential, q: np.ndarray, tol: float, seed: int
             ) -> tuple[float, float, float]:
    from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

    n = pot.dimension
    apply, unit_error = _operator(pot, q)
    op = LinearOperator((n, n), matvec=apply, dtype=float)
    v0 = np.random.default_rng(seed).standard_normal(n)
    out = []
    for which in ("LA", "SA"):
        try:
            lam, vec = eigsh(op, k=1, which=which, v0=v0, tol=tol, maxiter=20 * n)
        except ArpackNoConvergence:
            end = "largest" if which == "LA" else "smallest"
            raise StepsafeError(f"Lanczos did not converge to the {end} eigenvalue of the "
                                f"mass-weighted Hessian (n = {n})") from None
        x = vec[:, 0] / np.linalg.norm(vec[:, 0])
        residual = float(np.linalg.norm(apply(x) - lam[0] * x))
        out.append((float(lam[0]), residual))
    (top, r_top), (low, r_low) = out
    scale = max(abs(top), abs(low))
    return top, low, max(r_top, r_low) + unit_error + 4 * n * EPS * scale


@dataclass(frozen=True)
class Modes:
    """The normal modes of W at one configuration: eigenvalues ascending ``(k,)``, unit
    eigenvectors in mass-weighted coordinates as columns ``(n, k)``, and the eigenvalues'
    error bound."""

    eigenvalues: np.ndarray
    vectors: np.ndarray
    error: float

    @property
    def omegas(self) -> np.ndarray:
        """``sqrt(max(lambda, 0))``."""
        return np.sqrt(np.maximum(self.eigenvalues, 0.0))


def modes(pot: Potential, q0, count: int | None = None, exact_up_to: int = EXACT_UP_TO,
          tol: float = LANCZOS_TOL, seed: int = START_SEED) -> Modes:
    """The ``count`` fastest normal modes of W at ``q0`` (all of them by default for
    ``n <= exact_up_to``), eigenvalues ascending.

    Parameters
    ----------
    pot : Potential
    q0 : array_like
        One configuration (n,).
    count : int, optional
        How many of the largest eigenvalues (default: all for small n, 1 for large n).
    exact_up_to, tol, seed
        As for :func:`frequencies`.

    Returns
    -------
    Modes
    """
    q0 = np.asarray(q0, dtype=float).reshape(1, -1)
    n = pot.dimension
    if n <= exact_up_to:
        W, err, _ = mass_weighted(pot, q0)
        if not np.all(np.isfinite(W)):
            raise StepsafeError("the Hessian is not finite at the configuration")
        lam, vec = np.linalg.eigh(W[0])
        k = n if count is None else min(int(count), n)
        error = float(err[0]) + 4 * n * EPS * float(np.max(np.abs(lam)))
        return Modes(lam[n - k:], vec[:, n - k:], error)
    from scipy.sparse.linalg import LinearOperator, eigsh

    apply, unit_error = _operator(pot, q0[0])
    op = LinearOperator((n, n), matvec=apply, dtype=float)
    k = 1 if count is None else min(int(count), n - 1)
    v0 = np.random.default_rng(seed).standard_normal(n)
    lam, vec = eigsh(op, k=k, which="LA", v0=v0, tol=tol, maxiter=20 * n)
    order = np.argsort(lam)
    lam, vec = lam[order], vec[:, order]
    residual = max(float(np.linalg.norm(apply(vec[:, j]) - lam[j] * vec[:, j]))
                   for j in range(k))
    return Modes(lam, vec, residual + unit_error + 4 * n * EPS * float(np.max(np.abs(lam))))
