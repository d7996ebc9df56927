"""Draws from the target: the mode and its Gaussian (Laplace) approximation, a short
adaptive HMC run of its own, or draws the user supplies.

Mode. ``U`` is minimised by BFGS (scipy) from the start given (the origin by default); the
Hessian there (the potential's own, else central differences of the gradient with steps
scaled by BFGS's inverse-Hessian estimate) gives the Laplace approximation
``N(mode, (nabla^2 U)^-1)`` when it is positive definite. Its mass-weighted eigenvalues
``lambda_k`` (:mod:`stepsafe.core.hmc_target.potential`) are the squared frequencies
``beta_k^2`` of the Gaussian analysis at the mode.

Warm-up sampler. ``chains`` chains of HMC with kick-drift-kick Verlet under the target's
own mass matrix, vectorised over chains, started from the Laplace approximation (or around
the start given when there is none). Each iteration draws the number of steps uniformly
from ``1 .. L_max`` and the step uniformly from ``h (0.9, 1.1)`` (both avoid periodic
orbits), accepts each chain with probability ``min(1, e^-Delta)`` and, during warm-up,
adapts h by dual averaging (Hoffman & Gelman, JMLR 15 (2014) 1593, algorithm 5: gamma =
0.05, t0 = 10, kappa = 0.75) so that the mean acceptance statistic over the chains
approaches :data:`WARMUP_ACCEPT`, a conservative 0.9: few divergent transitions and a
small bias from a still-adapting step. The integration time is ``pi/2`` times the largest
standard deviation of the mass-weighted target (Laplace's, re-estimated from the chains'
covariance at the end of each warm-up window), so that ``L_max = ceil(T / h)`` is capped at
:data:`MAX_WARMUP_STEPS`. After warm-up the step is frozen and every iteration of every
chain is kept; the Monte Carlo error of anything averaged over them comes from the chains'
autocorrelation (:mod:`stepsafe.core.hmc_target.statistics`). The seed is part of the
result.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import ClassVar

import numpy as np

from stepsafe.core.hmc_target.potential import Target, hessian_matrix
from stepsafe.exceptions import StepsafeError

#: The warm-up sampler's target for the mean acceptance statistic (conservative).
WARMUP_ACCEPT = 0.9
#: Cap on the warm-up sampler's steps per iteration.
MAX_WARMUP_STEPS = 256
#: Default chains, warm-up iterations and kept iterations per chain.
CHAINS = 32
WARMUP = 300
KEEP = 150
#: Default seed (stated in every result).
SEED = 20240611
#: Largest dimension for which the Laplace approximation's dense Hessian is formed.
LAPLACE_LIMIT = 2000


@dataclass(frozen=True)
class Laplace:
    """The mode of U and the Gaussian approximation there.

    ``hessian`` is ``nabla^2 U(mode)``; ``eigenvalues`` those of the mass-weighted Hessian
    (ascending); ``gradient_norm`` is ``|C^-1 grad U(mode)|`` (0 at an exact mode; compare
    with ``sqrt(d)``, its typical size at a draw)."""

    mode: np.ndarray
    hessian: np.ndarray
    eigenvalues: np.ndarray
    gradient_norm: float
    converged: bool

    @property
    def positive_definite(self) -> bool:
        return bool(self.eigenvalues.size and self.eigenvalues[0] > 0)

    @property
    def betas(self) -> np.ndarray:
        """The frequencies ``sqrt(lambda_k)`` of the Gaussian at the mode (only when the
        Hessian is positive definite)."""
        return np.sqrt(self.eigenvalues)


def find_mode(target: Target, start: np.ndarray | None = None) -> Laplace | None:
    """The mode of the target and its Laplace approximation (module docstring); None when
    the optimisation diverges or d exceeds :data:`LAPLACE_LIMIT`.

    Parameters
    ----------
    target
        The potential and mass.
    start
        Where the search starts (default: the origin).

    Returns
    -------
    Laplace or None
    """
    from scipy.optimize import minimize

    d = target.dimension
    if d > LAPLACE_LIMIT:
        return None
    x0 = np.zeros(d) if start is None else np.asarray(start, dtype=float).reshape(d)
    pot = target.potential

    def fun(x: np.ndarray) -> float:
        value = float(np.asarray(pot.energy(x[None, :]))[0])
        return value if math.isfinite(value) else math.inf

    def jac(x: np.ndarray) -> np.ndarray:
        return np.asarray(pot.gradient(x[None, :]), dtype=float)[0]

    with np.errstate(all="ignore"):
        found = minimize(fun, x0, jac=jac, method="BFGS",
                         options={"gtol": 1e-10, "maxiter": 200 * max(d, 10)})
        mode = np.asarray(found.x, dtype=float)
        if not np.isfinite(mode).all() or not math.isfinite(float(found.fun)):
            return None
        inv = np.asarray(getattr(found, "hess_inv", np.eye(d)), dtype=float)
        spread = np.sqrt(np.clip(np.diag(inv), 1e-300, None)) if inv.shape == (d, d) \
            else np.ones(d)
        H = hessian_matrix(pot, mode[None, :], spread)[0]
        if not np.isfinite(H).all():
            return None
        W = target.mass.weighted(H)
        lam = np.linalg.eigvalsh(0.5 * (W + W.T))
        g = target.mass.unweigh_gradient(jac(mode)[None, :])[0]
    return Laplace(mode, H, lam, float(np.linalg.norm(g)), bool(found.success))


@dataclass(frozen=True)
class Draws:
    """Positions from the target, shape (chains, n, d), with where they came from.

    ``source`` is ``"warm-up"`` (this module's sampler) or ``"given"``; for the sampler,
    ``step``, ``max_steps`` and ``acceptance`` (its mean acceptance statistic after
    warm-up), ``divergent`` (divergent transitions after warm-up) and ``seed``."""

    positions: np.ndarray
    source: str
    seed: int | None = None
    step: float | None = None
    max_steps: int | None = None
    acceptance: float | None = None
    divergent: int = 0

    #: the keys of ``hmc --json``'s ``draws`` record named after this sampler's attributes
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "sampler_step": "step", "sampler_max_steps": "max_steps",
        "sampler_acceptance": "acceptance", "sampler_divergent": "divergent"})

    @property
    def chains(self) -> int:
        """How many chains."""
        return int(self.positions.shape[0])

    @property
    def per_chain(self) -> int:
        """Draws per chain."""
        return int(self.positions.shape[1])

    @property
    def flat(self) -> np.ndarray:
        """The draws as (chains * n, d), chain by chain."""
        return self.positions.reshape(-1, self.positions.shape[-1])


def given_draws(positions: np.ndarray, dimension: int, where: str = "draws") -> Draws:
    """User-supplied draws: shape (n, d) (one chain, in the order drawn) or (chains, n, d);
    finite, at least 2 per chain.

    Parameters
    ----------
    positions
        The draws.
    dimension
        d of the target.
    where
        Names the draws in errors.

    Returns
    -------
    Draws
    """
    try:
        arr = np.array(positions, dtype=float)
    except (TypeError, ValueError):
        raise StepsafeError("draws must be an array of numbers", where) from None
    if arr.ndim == 1 and dimension == 1:
        arr = arr[:, None]
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[-1] != dimension:
        raise StepsafeError(f"draws must have shape (n, {dimension}) or (chains, n, "
                            f"{dimension}), got {np.shape(positions)}", where)
    if arr.shape[1] < 2:
        raise StepsafeError("draws need at least 2 per chain", where)
    if not np.isfinite(arr).all():
        raise StepsafeError("draws have a non-finite entry", where)
    return Draws(arr, "given")


def _leapfrog(target: Target, q: np.ndarray, p: np.ndarray, g: np.ndarray,
              h: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kick-drift-kick Verlet with a step and a number of steps per chain (rows stop
    moving after their own number of steps); non-finite rows are frozen."""
    pot, mass = target.potential, target.mass
    hcol = h[:, None]
    active = steps > 0
    q, p, g = q.copy(), p.copy(), g.copy()
    for k in range(int(steps.max(initial=0))):
        moving = active & (steps > k) & np.isfinite(q).all(axis=1) & np.isfinite(p).all(axis=1)
        if not moving.any():
            break
        idx = np.flatnonzero(moving)
        hk = hcol[idx]
        pk = p[idx] - 0.5 * hk * g[idx]
        qk = q[idx] + hk * mass.velocity(pk)
        gk = pot.gradient(qk)
        pk = pk - 0.5 * hk * gk
        q[idx], p[idx], g[idx] = qk, pk, gk
        bad = ~(np.isfinite(qk).all(axis=1) & np.isfinite(pk).all(axis=1) &
                np.isfinite(gk).all(axis=1))
        if bad.any():
            q[idx[bad]] = np.nan
    return q, p, g


def sample(target: Target, *, chains: int = CHAINS, warmup: int = WARMUP, keep: int = KEEP,
           seed: int = SEED, laplace: Laplace | None = None,
           start: np.ndarray | None = None) -> Draws:
    """Draws from the target by the warm-up sampler of the module docstring.

    Parameters
    ----------
    target
        The potential and mass.
    chains, warmup, keep
        Chains, warm-up iterations and kept iterations per chain.
    seed
        Seed of the random numbers (the result states it).
    laplace
        The Laplace approximation to start from (:func:`find_mode`), if any.
    start
        Where chains start when there is no (positive definite) Laplace approximation.

    Returns
    -------
    Draws
    """
    rng = np.random.default_rng(seed)
    d = target.dimension
    mass, pot = target.mass, target.potential
    if laplace is not None and laplace.positive_definite:
        # N(mode, H^-1): q = mode + C^-T V diag(lambda^-1/2) z with C^-1 H C^-T = V L V^T
        W = mass.weighted(laplace.hessian)
        lam, V = np.linalg.eigh(0.5 * (W + W.T))
        z = rng.standard_normal((chains, d)) / np.sqrt(lam)
        q = laplace.mode + mass.weigh_vector(z @ V.T)
        spread = float(1.0 / math.sqrt(lam[0]))
        h = 0.5 / math.sqrt(lam[-1])
    else:
        # the curvature where the chains start sets the first step and spread (its
        # magnitudes: the start need not be a minimum)
        centre = np.zeros(d) if start is None else np.asarray(start, float).reshape(d)
        with np.errstate(all="ignore"):
            lam = np.abs(np.linalg.eigvalsh(mass.weighted(
                hessian_matrix(pot, centre[None, :], 1e-3 * (np.abs(centre) + 1.0))[0])))
        lam = lam[np.isfinite(lam) & (lam > 0)]
        top = float(lam.max()) if lam.size else 1.0
        spread, h = 1.0 / math.sqrt(float(lam.min()) if lam.size else 1.0), 0.5 / math.sqrt(top)
        q = centre + 0.1 * spread * mass.weigh_vector(rng.standard_normal((chains, d)))
    with np.errstate(all="ignore"):
        u = pot.energy(q)
        g = pot.gradient(q)
    if not (np.isfinite(u).all() and np.isfinite(g).all()):
        raise StepsafeError("the target's energy or gradient is not finite where the chains "
                            "start (its mode, or the start given): give a start inside "
                            "the target's support")
    # dual averaging state
    mu, log_bar, s_bar, t0, gamma, kappa = math.log(10 * h), 0.0, 0.0, 10.0, 0.05, 0.75
    windows = {warmup // 4, warmup // 2, (3 * warmup) // 4}
    kept = np.empty((chains, keep, d))
    stats, divergent = [], 0
    for it in range(warmup + keep):
        adapting = it < warmup
        L_max = int(min(MAX_WARMUP_STEPS, max(1, math.ceil(0.5 * math.pi * spread / h))))
        steps = rng.integers(1, L_max + 1, size=chains)
        hs = h * rng.uniform(0.9, 1.1, size=chains)
        p = mass.momenta(rng.standard_normal((chains, d)))
        with np.errstate(all="ignore"):
            q1, p1, g1 = _leapfrog(target, q, p, g, hs, steps)
            finite = np.isfinite(q1).all(axis=1)
            u1 = np.full(chains, np.inf)
            if finite.any():
                u1[finite] = pot.energy(q1[finite])
            delta = (u1 - u) + (mass.kinetic(np.where(finite[:, None], p1, 0.0))
                                - mass.kinetic(p))
            delta = np.where(np.isfinite(delta), delta, np.inf)
            accept_prob = np.exp(-np.maximum(delta, 0.0))
        accept = rng.uniform(size=chains) < accept_prob
        q = np.where(accept[:, None], q1, q)
        g = np.where(accept[:, None], g1, g)
        u = np.where(accept, u1, u)
        if adapting:
            t = it + 1
            s_bar = (1 - 1 / (t + t0)) * s_bar + (WARMUP_ACCEPT - accept_prob.mean()) / (t + t0)
            log_h = mu - math.sqrt(t) / gamma * s_bar
            log_bar = t ** -kappa * log_h + (1 - t ** -kappa) * log_bar
            h = math.exp(log_h)
            if it + 1 in windows and it > 10:
                centred = q - q.mean(axis=0)
                white = mass.whiten(centred)  # C^T (q - mean): unit-mass coordinates
                cov = white.T @ white / max(chains - 1, 1)
                top = float(np.linalg.eigvalsh(cov)[-1]) if d > 1 else float(cov[0, 0])
                spread = max(spread, math.sqrt(max(top, 0.0)))
            if it + 1 == warmup:
                h = math.exp(log_bar)
        else:
            kept[:, it - warmup] = q
            stats.append(float(accept_prob.mean()))
            divergent += int((delta > 1000).sum())
    return Draws(kept, "warm-up", seed, h, L_max, float(np.mean(stats)) if stats else None,
                 divergent)
