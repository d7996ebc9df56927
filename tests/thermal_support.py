"""Test systems and independent references for the thermal analysis: plain-numpy potentials
(Morse, cubic, quartic, an FPU-alpha chain), integrators written out step by step (velocity
Verlet and PEFRL with their published coefficients), exact 1-D Boltzmann draws by quadrature
and a random-walk Metropolis sampler. Nothing here calls stepsafe's engine or samplers."""

from __future__ import annotations

import numpy as np

from stepsafe.systems.thermal.potential import Potential, from_callables

# PEFRL (Omelyan, Mryglod, Folk 2002): drift xi, kick (1-2 lam)/2, drift chi, kick lam,
# drift 1-2(chi+xi), kick lam, drift chi, kick (1-2 lam)/2, drift xi
XI, LAM, CHI = 0.1786178958448091, -0.2123418310626054, -0.06626458266981849
PEFRL_DRIFTS = (XI, CHI, 1 - 2 * (CHI + XI), CHI, XI)
PEFRL_KICKS = ((1 - 2 * LAM) / 2, LAM, LAM, (1 - 2 * LAM) / 2)


def morse() -> Potential:
    """``U = (1 - e^-q)^2 / 2`` (D = 1/2, omega_0 = 1), unit mass."""
    def energy(q):
        return 0.5 * (1 - np.exp(-q[:, 0])) ** 2

    def gradient(q):
        e = np.exp(-q)
        return (1 - e) * e

    def hessian(q):
        e = np.exp(-q)
        return (2 * e * e - e)[:, :, None]

    return from_callables(energy, gradient, [1.0], minimum=[0.0], hessian=hessian,
                          description="Morse")


def morse_force(q):
    e = np.exp(-q)
    return -(1 - e) * e


def morse_energy(q):
    return 0.5 * (1 - np.exp(-q)) ** 2


def cubic(a: float) -> Potential:
    """``U = q^2/2 + a q^3/3`` (a barrier at q = -1/a of height 1/(6 a^2))."""
    return from_callables(lambda q: q[:, 0] ** 2 / 2 + a * q[:, 0] ** 3 / 3,
                          lambda q: q + a * q * q, [1.0], minimum=[0.0],
                          hessian=lambda q: (1 + 2 * a * q)[:, :, None],
                          description=f"cubic a = {a}")


def quartic(b: float) -> Potential:
    """``U = q^2/2 + b q^4/4``."""
    return from_callables(lambda q: q[:, 0] ** 2 / 2 + b * q[:, 0] ** 4 / 4,
                          lambda q: q + b * q ** 3, [1.0], minimum=[0.0],
                          hessian=lambda q: (1 + 3 * b * q * q)[:, :, None],
                          description=f"quartic b = {b}")


def fpu_bonds(q):
    z = np.zeros((q.shape[0], 1))
    return np.diff(np.hstack([z, q, z]), axis=1)


def fpu_energy(q, alpha):
    d = fpu_bonds(q)
    return np.sum(d * d * (0.5 + d * (alpha / 3)), axis=1)


def fpu_force(q, alpha):
    d = fpu_bonds(q)
    f = d * (1 + alpha * d)
    return f[:, 1:] - f[:, :-1]


def fpu_hessian(q, alpha):
    """The tridiagonal Hessian, written out entry by entry."""
    d = fpu_bonds(q)
    k = 1 + 2 * alpha * d
    m, n = q.shape
    out = np.zeros((m, n, n))
    for i in range(n):
        out[:, i, i] = k[:, i] + k[:, i + 1]
        if i + 1 < n:
            out[:, i, i + 1] = out[:, i + 1, i] = -k[:, i + 1]
    return out


def fpu(n: int, alpha: float = 0.25, masses=None, analytic: bool = True) -> Potential:
    """An FPU-alpha chain of n masses between fixed walls: bonds ``d^2/2 + alpha d^3/3``."""
    return from_callables(lambda q: fpu_energy(q, alpha), lambda q: -fpu_force(q, alpha),
                          np.ones(n) if masses is None else masses, minimum=np.zeros(n),
                          hessian=(lambda q: fpu_hessian(q, alpha)) if analytic else None,
                          description=f"FPU-alpha {n}")


def boltzmann_1d(energy, kT, count, rng, lo, hi, points=400001):
    """Exact draws of exp(-U/kT) on [lo, hi] by a tabulated distribution function."""
    s = np.linspace(lo, hi, points)
    w = np.exp(-(energy(s) - np.min(energy(s))) / kT)
    c = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    return np.interp(rng.random(count), c / c[-1], s)


def boltzmann_quantile(energy, kT, level, lo, hi, points=400001):
    """The ``level`` quantile of q under exp(-U/kT) on [lo, hi] (trapezoid rule)."""
    s = np.linspace(lo, hi, points)
    w = np.exp(-(energy(s) - np.min(energy(s))) / kT)
    c = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    return float(np.interp(level, c / c[-1], s))


def verlet(force, q, p, h, steps, fail):
    """Velocity Verlet (kick h/2, drift h, kick h/2) on arrays; ``fail(q, p)`` marks rows
    that failed at a step; returns the mask of rows that ever failed."""
    dead = np.zeros(q.shape[0], dtype=bool)
    f = force(q)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            p = p + 0.5 * h * f
            q = q + h * p
            f = force(q)
            p = p + 0.5 * h * f
            dead |= fail(q, p)
    return dead


def pefrl(force, q, p, h, steps, fail):
    """PEFRL, drift first, on arrays (as :func:`verlet`)."""
    dead = np.zeros(q.shape[0], dtype=bool)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            for a, b in zip(PEFRL_DRIFTS, PEFRL_KICKS):
                q = q + a * h * p
                p = p + b * h * force(q)
            q = q + PEFRL_DRIFTS[-1] * h * p
            dead |= fail(q, p)
    return dead


def metropolis(energy, kT, q0, chains, steps, step, rng, thin):
    """Random-walk Metropolis with Gaussian proposals of size ``step``, ``chains`` chains
    from q0; returns every ``thin``-th state after the first half (rows: samples)."""
    q = np.repeat(np.asarray(q0, dtype=float)[None, :], chains, axis=0)
    u = energy(q)
    out = []
    accepted = 0
    for k in range(steps):
        trial = q + step * rng.standard_normal(q.shape)
        ut = energy(trial)
        ok = np.log(rng.random(chains)) < -(ut - u) / kT
        q = np.where(ok[:, None], trial, q)
        u = np.where(ok, ut, u)
        accepted += int(ok.sum())
        if k >= steps // 2 and (k - steps // 2) % thin == 0:
            out.append(q.copy())
    return np.concatenate(out), accepted / (chains * steps)
