"""Instantaneous frequencies of the target over its draws.

At a configuration q the local frequencies are ``omega_k = sqrt(lambda_k)`` for the
eigenvalues of the mass-weighted Hessian ``W(q) = C^-1 nabla^2 U(q) C^-T`` (``M = C C^T``);
a negative ``lambda`` is a locally unstable (inverted) direction. A step h of a method
whose linear stability ends at ``z*`` (``|tr M(z)| <= 2`` for ``z < z*``) is stable at q
while ``h omega_max(q) < z*``: the chain meets the largest ``omega_max`` it visits, so the
limit is set by the stiffest region of the draws, not by the mode.

For d up to :data:`EXACT_LIMIT` every draw's W is formed (the potential's Hessian, else
central differences of the gradient) and its eigenvalues computed exactly (``eigvalsh``).
Beyond, the extreme eigenvalues come from :data:`LANCZOS_STEPS` steps of Lanczos on
Hessian-vector products (the potential's ``hvp``, else central differences), batched over
the draws, fully reorthogonalised, from a random start: the largest Ritz value is a lower
bound of ``lambda_max`` and an eigenvalue lies within its residual ``|beta_k s_k|`` of it
(stated as ``residual``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stepsafe.core.hmc_target.draws import Draws
from stepsafe.core.hmc_target.potential import Target, hessian_matrix, hessian_vector

#: Largest d whose Hessians are formed and diagonalised at every draw.
EXACT_LIMIT = 64
#: Lanczos steps beyond it (capped at d).
LANCZOS_STEPS = 40
#: At most this many draws (evenly spaced through the chains) are examined.
MAX_DRAWS = 2000
#: Quantiles of omega_max reported.
QUANTILES = (0.5, 0.9, 0.99, 1.0)


@dataclass(frozen=True)
class Spread:
    """``omega_max`` and ``lambda_min`` at each draw examined (``omega_max = sqrt(max(
    lambda_max, 0))``), how they were computed (``exact`` or ``lanczos``, with the
    residual bound of each ``lambda_max`` then), and the quantiles of ``omega_max``."""

    omega_max: np.ndarray
    lambda_min: np.ndarray
    how: str
    residual: np.ndarray | None = None

    @property
    def draws(self) -> int:
        return int(self.omega_max.size)

    @property
    def top(self) -> float:
        """The stiffest frequency met: the largest ``omega_max`` over the draws."""
        return float(self.omega_max.max())

    def quantiles(self) -> dict[float, float]:
        """``omega_max`` at each of :data:`QUANTILES`."""
        return {q: float(np.quantile(self.omega_max, q)) for q in QUANTILES}

    def inverted_share(self) -> float:
        """The share of draws where some direction is locally inverted (``lambda_min <
        0``)."""
        return float(np.mean(self.lambda_min < 0))


def _subset(draws: Draws, limit: int) -> np.ndarray:
    flat = draws.flat
    if flat.shape[0] <= limit:
        return flat
    index = np.linspace(0, flat.shape[0] - 1, limit).round().astype(int)
    return flat[index]


def spread(target: Target, draws: Draws, *, seed: int = 0, limit: int = MAX_DRAWS) -> Spread:
    """The frequencies over the draws (module docstring).

    Parameters
    ----------
    target
        The potential and mass.
    draws
        Draws from the target.
    seed
        Seed of Lanczos' random starts.
    limit
        At most this many draws are examined.

    Returns
    -------
    Spread
    """
    q = _subset(draws, limit)
    scale = coordinate_scales(draws.flat)
    d = target.dimension
    with np.errstate(all="ignore"):
        if d <= EXACT_LIMIT:
            # in pieces of draws: d central differences each way per draw
            rows = max(1, CHUNK_ELEMENTS // (d * d))
            lam = np.concatenate([_eigenvalues(target, q[i:i + rows], scale)
                                  for i in range(0, q.shape[0], rows)])
            return Spread(np.sqrt(np.maximum(lam[:, -1], 0.0)), lam[:, 0], "exact")
        top, bottom, residual = lanczos_extremes(target, q, scale, seed=seed)
    return Spread(np.sqrt(np.maximum(top, 0.0)), bottom, "lanczos", residual)


def _eigenvalues(target: Target, q: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The eigenvalues of W at each row of q, ascending."""
    W = target.mass.weighted(hessian_matrix(target.potential, q, scale))
    return np.linalg.eigvalsh(0.5 * (W + np.swapaxes(W, -1, -2)))


#: The exact path forms the Hessians of at most about this many entries at once.
CHUNK_ELEMENTS = 2**20


def coordinate_scales(flat: np.ndarray) -> np.ndarray:
    """The draws' spread along each axis (the length of central differences); where it is
    below 1e-8 of the mean absolute position (0, or the rounding of identical draws), that
    mean absolute position, else 1."""
    s = flat.std(axis=0) if flat.shape[0] > 1 else np.zeros(flat.shape[1])
    fallback = np.abs(flat).mean(axis=0)
    return np.where((s > 0) & (s > 1e-8 * fallback), s,
                    np.where(fallback > 0, fallback, 1.0))


def lanczos_extremes(target: Target, q: np.ndarray, scale: np.ndarray, *, seed: int = 0,
                     steps: int = LANCZOS_STEPS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Largest and smallest Ritz values of W at each row of q after ``min(steps, d)``
    Lanczos steps, and the residual bound of the largest (module docstring).

    Parameters
    ----------
    target
        The potential and mass.
    q
        Configurations, shape (n, d).
    scale
        Lengths per coordinate for central differences.
    seed
        Seed of the random starts.
    steps
        Lanczos steps.

    Returns
    -------
    tuple of arrays
        ``(lambda_max, lambda_min, residual)``, each of shape (n,).
    """
    n, d = q.shape
    k = min(steps, d)
    rng = np.random.default_rng(seed)
    mass, pot = target.mass, target.potential

    def apply(v: np.ndarray) -> np.ndarray:  # W v = C^-1 H C^-T v
        return mass.unweigh_gradient(hessian_vector(pot, q, mass.weigh_vector(v), scale))

    V = np.zeros((k + 1, n, d))
    alpha = np.zeros((n, k))
    beta = np.zeros((n, k + 1))
    v = rng.standard_normal((n, d))
    V[0] = v / np.linalg.norm(v, axis=1, keepdims=True)
    for j in range(k):
        w = apply(V[j])
        alpha[:, j] = np.einsum("nd,nd->n", w, V[j])
        w = w - alpha[:, j, None] * V[j] - (beta[:, j, None] * V[j - 1] if j else 0.0)
        for _ in range(2):  # full reorthogonalisation, twice
            w = w - np.einsum("jn,jnd->nd", np.einsum("jnd,nd->jn", V[:j + 1], w), V[:j + 1])
        b = np.linalg.norm(w, axis=1)
        size = np.abs(alpha[:, :j + 1]).max(axis=1) + 1e-300
        broken = b <= 1e-12 * size
        if broken.any():  # an invariant subspace: restart orthogonally (beta = 0)
            r = rng.standard_normal((int(broken.sum()), d))
            block = V[:j + 1][:, broken]
            for _ in range(2):
                r = r - np.einsum("jn,jnd->nd", np.einsum("jnd,nd->jn", block, r), block)
            w[broken] = r / np.linalg.norm(r, axis=1, keepdims=True)
            b = np.where(broken, 0.0, b)
            norm = np.where(broken, 1.0, b)
        else:
            norm = b
        beta[:, j + 1] = b
        V[j + 1] = w / norm[:, None]
    T = np.zeros((n, k, k))
    idx = np.arange(k)
    T[:, idx, idx] = alpha
    T[:, idx[:-1], idx[1:]] = beta[:, 1:k]
    T[:, idx[1:], idx[:-1]] = beta[:, 1:k]
    theta, S = np.linalg.eigh(T)
    residual = np.abs(beta[:, k] * S[:, -1, -1])
    return theta[:, -1], theta[:, 0], residual
