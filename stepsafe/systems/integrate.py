"""Initial conditions of ensembles of trajectories, and the distribution of their errors.

States are arrays of shape ``(N, 2n)`` (N trajectories of n degrees of freedom, q then p);
the trajectories themselves run through :func:`stepsafe.core.ensemble.integrate`.
Initial conditions (:func:`shell_states`, :func:`thermal_states`), seeded:

* on an energy shell near a centre ``x_e`` with Hessian ``S``: states whose quadratic
  energy ``(x - x_e)^T S (x - x_e) / 2`` is exactly ``E``, uniform on that ellipsoid's
  sphere in the normal coordinates (every phase of every mode and every split of the
  energy among the modes); the nonlinear energy differs by the anharmonic terms;
* at a temperature ``kT``: positions and momenta from the Boltzmann distribution of the
  quadratic model at the centre, ``x ~ N(x_e, kT S^-1)`` (S the centre's Hessian).

:func:`summary` gives the median, quartiles, 5 and 95 percent quantiles and maximum of
the trajectories' errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
