"""Ensembles of trajectories: many initial conditions advanced together by a splitting
method on a compiled Hamiltonian, and the distribution of their energy errors.

States are arrays of shape ``(N, 2n)`` (N trajectories of n degrees of freedom, q then p).
One step of a splitting method ``drift(a_1 h) kick(b_1 h) drift(a_2 h) ...`` on a
separable ``H = T(p) + V(q)`` is :func:`splitting_step`: ``drift(c)`` is
``q += c dH/dp(p)``, ``kick(c)`` is ``p -= c dH/dq(q)``, each on the whole batch at once;
the method enters only through its coefficient arrays and the Hamiltonian only through
its batched gradients (any callables of shape ``(N, n) -> (N, n)``), so the same function
serves every splitting method and every system.

Initial conditions (:func:`shell_states`, :func:`thermal_states`), seeded:

* on an energy shell near a centre ``x_e`` with Hessian ``S``: states whose quadratic
  energy ``(x - x_e)^T S (x - x_e) / 2`` is exactly ``E``, uniform on that ellipsoid's
  sphere in the normal coordinates (every phase of every mode and every split of the
  energy among the modes); the nonlinear energy differs by the anharmonic terms;
* at a temperature ``kT``: positions and momenta from the Boltzmann distribution of the
  quadratic model at the centre, ``x ~ N(x_e, kT S^-1)`` (S the centre's Hessian).

:func:`energy_errors` runs the batch for a number of steps and returns each trajectory's
largest ``|H(x_k) - H(x_0)|`` over every step, relative to its ``|H(x_0) - H_e|``;
:func:`summary` its median, quartiles, 5 and 95 percent quantiles and maximum.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Gradient = Callable[[np.ndarray], np.ndarray]


def splitting_step(drift: np.ndarray, kick: np.ndarray, dV: Gradient, dT: Gradient,
                   q: np.ndarray, p: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """One step of the splitting ``drift(a_1 h) kick(b_1 h) drift(a_2 h) ...``.

    Parameters
    ----------
    drift, kick : ndarray
        The coefficients ``a_i`` and ``b_i`` (``drift`` as long as ``kick`` or one
        longer; zeros are skipped).
    dV, dT : callable
        ``dH/dq`` as a function of q alone and ``dH/dp`` of p alone, on arrays of shape
        ``(N, n)``.
    q, p : ndarray
        The states, shape ``(N, n)`` each (not modified).
    h : float
        The step.

    Returns
    -------
    q, p : ndarray
        The states after the step.
    """
    for i, a in enumerate(drift):
        if a:
            q = q + (a * h) * dT(p)
        if i < len(kick) and kick[i]:
            p = p - (kick[i] * h) * dV(q)
    return q, p


def shell_states(centre: np.ndarray, hessian: np.ndarray, energy: float, count: int,
                 rng: np.random.Generator) -> np.ndarray:
    """``count`` states ``(count, 2n)`` of quadratic energy ``energy`` above the centre,
    every phase: in the normal coordinates of the Hessian ``S`` (positive definite,
    ``S = L L^T``), ``x - x_e = L^-T y`` with ``y`` uniform on the sphere of radius
    ``sqrt(2 energy)``, so ``(x - x_e)^T S (x - x_e) / 2 = energy`` for each."""
    S = 0.5 * (hessian + hessian.T)
    L = np.linalg.cholesky(S)
    y = rng.standard_normal((count, S.shape[0]))
    y *= np.sqrt(2 * energy) / np.linalg.norm(y, axis=1, keepdims=True)
    return centre + np.linalg.solve(L.T, y.T).T


def thermal_states(centre: np.ndarray, hessian: np.ndarray, kT: float, count: int,
                   rng: np.random.Generator) -> np.ndarray:
    """``count`` states from ``N(x_e, kT S^-1)``, the Boltzmann distribution
    ``exp(-(x - x_e)^T S (x - x_e) / (2 kT))`` of the quadratic model."""
    S = 0.5 * (hessian + hessian.T)
    L = np.linalg.cholesky(S)
    y = rng.standard_normal((count, S.shape[0])) * np.sqrt(kT)
    return centre + np.linalg.solve(L.T, y.T).T


def energy_errors(drift: np.ndarray, kick: np.ndarray, energy: Gradient, dV: Gradient,
                  dT: Gradient, X0: np.ndarray, h: float, steps: int,
                  reference_energy: float = 0.0) -> np.ndarray:
    """For each trajectory from the rows of ``X0`` (shape ``(N, 2n)``), the largest
    ``|H(x_k) - H(x_0)|`` over the steps ``k = 1 .. steps``, relative to
    ``|H(x_0) - reference_energy|``; ``inf`` for a trajectory that left the finite
    numbers. ``energy`` maps states ``(N, 2n)`` to ``(N,)``."""
    n = X0.shape[1] // 2
    q, p = X0[:, :n].copy(), X0[:, n:].copy()
    e0 = energy(X0)
    worst = np.zeros(X0.shape[0])
    with np.errstate(all="ignore"):
        for _ in range(steps):
            q, p = splitting_step(drift, kick, dV, dT, q, p, h)
            e = energy(np.hstack([q, p]))
            worst = np.fmax(worst, np.where(np.isfinite(e), np.abs(e - e0), np.inf))
        scale = np.abs(e0 - reference_energy)
        return worst / np.where(scale > 0, scale, 1.0)


@dataclass(frozen=True)
class Distribution:
    """Quantiles of an ensemble's errors (``count`` trajectories, ``seed`` of the draw)."""

    count: int
    seed: int
    median: float
    q05: float
    q25: float
    q75: float
    q95: float
    max: float


def summary(errors: np.ndarray, seed: int) -> Distribution:
    """The median, the 5, 25, 75 and 95 percent quantiles and the maximum of ``errors``."""
    q05, q25, median, q75, q95 = np.quantile(errors, [0.05, 0.25, 0.5, 0.75, 0.95])
    return Distribution(int(errors.size), int(seed), float(median), float(q05), float(q25),
                        float(q75), float(q95), float(np.max(errors)))
