"""Langevin splittings on the harmonic oscillator: the mean, the covariance, the sampling.

Model: ``q'' = -omega^2 q`` for a mass m with friction gamma at thermal energy kT, in the
variables ``q~ = q omega sqrt(m / kT)``, ``p~ = p / sqrt(m kT)``, where the exact stationary
law (Boltzmann) is ``N(0, I)``. With ``z = omega h`` and the friction per unit of frequency
``g = gamma / omega``, one step of a splitting (:mod:`stepsafe.methods.langevin`) is
``x' = M x + N xi``: a drift or kick of fraction t is the oscillator's shear at ``t z``
(:func:`stepsafe.core.transfer.transfer_matrix`, the engine every method's step goes
through), an O step of fraction w is ``diag(1, c)``, ``c = exp(-g w z)``, plus a normal
noise of variance ``1 - c^2`` on ``p~``. So

* the mean follows ``M`` (stable iff its spectral radius is below 1, see
  :class:`~stepsafe.methods.langevin.Langevin` for where that holds at every friction);
* the covariance follows the Lyapunov recursion ``Sigma' = M Sigma M^T + Q``,
  ``Q = sum_k (1 - c_k^2) (L_k e_p)(L_k e_p)^T`` with ``L_k`` the substeps after the k-th
  O step, and the law the method samples in the long run is ``N(0, Sigma)`` with
  ``Sigma = M Sigma M^T + Q`` (a discrete Lyapunov equation: three linear equations for
  ``Sigma_qq, Sigma_qp, Sigma_pp``).

``Sigma_qq = <q^2> m omega^2 / kT`` is the configurational temperature over the true one,
``Sigma_pp = <p^2> / (m kT)`` the kinetic one, ``Sigma_qp = <q p> omega / kT``. Exact
sampling is ``Sigma = I``. For the library's splittings (x = z^2, every friction g > 0, for
``0 < z < 2``; derived from the recursion, tested against it at 50 digits and against a
simulation):

=======  ===================  ===================  ===========
word     Sigma_qq             Sigma_pp             Sigma_qp
=======  ===================  ===================  ===========
BAOAB    1                    1 - x/4              0
ABOBA    1                    1 / (1 - x/4)        0
OBABO    1 / (1 - x/4)        1                    0
BAOA     1                    1                    z / 2
=======  ===================  ===================  ===========

(BAOA is OpenMM's LangevinMiddleIntegrator: its state pairs the position with the velocity
half a step before it, hence the correlation.) None depends on the friction, and the mean
map of each is stable exactly for ``z < 2``: friction leaves the largest usable step where
Verlet has it, and the sampling error, not stability, is what a tolerance limits
(:func:`step_for_tolerance`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from stepsafe.core.records import json_ready
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import transfer_matrix
from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.methods.langevin import Langevin
from stepsafe.methods.library import resolve
from stepsafe.methods.protocol import Friction, Shears

#: Closed forms of the stationary covariance ``(Sigma_qq, Sigma_pp, Sigma_qp)`` at z (every
#: friction, ``0 < z < 2``), by the splitting's word (see the module docstring).
CLOSED_FORMS: dict[str, Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]] = {
    "BAOAB": lambda z: (np.ones_like(z), 1.0 - z * z / 4.0, np.zeros_like(z)),
    "ABOBA": lambda z: (np.ones_like(z), 1.0 / (1.0 - z * z / 4.0), np.zeros_like(z)),
    "OBABO": lambda z: (1.0 / (1.0 - z * z / 4.0), np.ones_like(z), np.zeros_like(z)),
    "BAOA": lambda z: (np.ones_like(z), np.ones_like(z), z / 2.0),
}


def _langevin(method: Any) -> Langevin:
    """``method`` as a :class:`Langevin`: a Langevin object, a name or path of a method file
    of kind langevin, or a :class:`stepsafe.Integrator` of one."""
    if isinstance(method, str):
        method = resolve(method)[0]
    method = getattr(method, "tableau", method)
    if not isinstance(method, Langevin):
        raise StepsafeError(f"{getattr(method, 'name', method)!r} is not a Langevin splitting "
                            "(a method file of kind langevin, e.g. baoab)")
    return method


def step_moments(method: Langevin, z: Any, friction: float) -> tuple[np.ndarray, np.ndarray]:
    """``(M, Q)`` of one step at each z (shapes (n, 2, 2)) in the scaled variables, at the
    friction per unit of frequency ``friction`` (``gamma / omega``)."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    M = np.broadcast_to(np.eye(2), (z.size, 2, 2)).copy()
    Q = np.zeros((z.size, 2, 2))
    for block in method.with_friction(friction).decomposition("oscillator"):
        if isinstance(block, Shears):
            F = transfer_matrix(block.splitting, block.weight * z, "oscillator")
            M, Q = F @ M, F @ Q @ np.swapaxes(F, 1, 2)
        else:
            assert isinstance(block, Friction)
            c = np.exp(-block.gamma * block.weight * z)
            M = M * np.stack([np.ones_like(c), c], axis=1)[:, :, None]
            Q = Q * np.stack([np.ones_like(c), c], axis=1)[:, :, None] \
                * np.stack([np.ones_like(c), c], axis=1)[:, None, :]
            Q[:, 1, 1] += -np.expm1(-2.0 * block.gamma * block.weight * z)  # 1 - c^2
    return M, Q


def spectral_radius(M: np.ndarray) -> np.ndarray:
    """Largest eigenvalue modulus of each 2x2 matrix."""
    return np.abs(np.linalg.eigvals(M)).max(axis=-1)


def stationary_covariance(M: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``Sigma = M Sigma M^T + Q`` for each pair (shape (n, 2, 2)); NaN where the mean map
    is not contracting (spectral radius >= 1: no stationary law). The three unknowns
    ``(s_qq, s_qp, s_pp)`` solve ``s - A s = (Q_qq, Q_qp, Q_pp)`` with A the action of
    ``Sigma -> M Sigma M^T`` on symmetric matrices."""
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    A = np.empty((M.shape[0], 3, 3))
    A[:, 0] = np.stack([a * a, 2 * a * b, b * b], axis=1)
    A[:, 1] = np.stack([a * c, a * d + b * c, b * d], axis=1)
    A[:, 2] = np.stack([c * c, 2 * c * d, d * d], axis=1)
    rhs = np.stack([Q[:, 0, 0], Q[:, 0, 1], Q[:, 1, 1]], axis=1)
    out = np.full((M.shape[0], 2, 2), np.nan)
    ok = spectral_radius(M) < 1.0
    if ok.any():
        s = np.linalg.solve(np.eye(3)[None] - A[ok], rhs[ok][:, :, None])[:, :, 0]
        out[ok] = np.stack([np.stack([s[:, 0], s[:, 1]], 1), np.stack([s[:, 1], s[:, 2]], 1)], 1)
    return out


@dataclass(frozen=True)
class ModeSampling:
    """One vibration of frequency ``beta`` under the splitting at step h."""

    beta: float
    z: float  # beta h
    decay: float  # spectral radius of the mean map (per step)
    stable: bool
    configurational: float | None  # <q^2> m beta^2 / kT (1 is exact); None: unstable
    kinetic: float | None  # <p^2> / (m kT)
    correlation: float | None  # <q p> beta / kT
    closed_form: tuple[float, float, float] | None  # the same from CLOSED_FORMS, if known

    def to_dict(self) -> dict[str, Any]:
        return {"beta": self.beta, "z": self.z, "decay_per_step": self.decay,
                "stable": self.stable, "configurational_temperature_ratio": self.configurational,
                "kinetic_temperature_ratio": self.kinetic, "correlation": self.correlation,
                "closed_form": None if self.closed_form is None else {
                    "configurational_temperature_ratio": self.closed_form[0],
                    "kinetic_temperature_ratio": self.closed_form[1],
                    "correlation": self.closed_form[2]}}


@dataclass(frozen=True)
class LangevinReport:
    """The sampling of each vibration, and the largest step whose mean map is stable for
    every friction (``h_stable``: the end of the region's interval from 0, which stops
    short of its first boundary by that point's uncertainty, over the largest beta; None
    when no boundary lies below the analysed range)."""

    method: str
    letters: str
    h: float
    friction: float
    kT: float
    modes: tuple[ModeSampling, ...]
    h_stable: float | None

    def to_dict(self) -> dict[str, Any]:
        return json_ready({"method": self.method, "letters": self.letters, "h": self.h,
                           "friction": self.friction, "kT": self.kT,
                           "h_stable": self.h_stable,
                           "modes": [m.to_dict() for m in self.modes]})


def sampling(method: Any, beta: Sequence[float] | float, h: float,
             friction: float | None = None) -> LangevinReport:
    """How the Langevin splitting ``method`` samples vibrations of angular frequencies
    ``beta`` at step ``h``: for each, the decay of the mean per step, the stationary
    configurational and kinetic temperature ratios and the correlation (from the Lyapunov
    equation, with the closed form where one is known), at the friction ``friction`` (per
    time unit; the method's own by default); and ``h_stable``, the largest step whose mean
    map is stable for every friction.

    Parameters
    ----------
    method : str, Integrator or Langevin
        A Langevin splitting: a name (``"baoab"``), a path, ``stepsafe.method("baoab")`` or
        its ``tableau``.
    beta : float or sequence of float
        Angular frequencies (rad per time unit), each > 0.
    h : float
        The step (time unit), > 0.
    friction : float, optional
        gamma per time unit (>= 0); the method's ``friction`` when None.

    Returns
    -------
    LangevinReport
    """
    m = _langevin(method)
    h = positive_finite(h, "h")
    betas = np.atleast_1d(np.asarray(beta, dtype=float))
    if betas.ndim != 1 or betas.size == 0 or not np.all(np.isfinite(betas)) \
            or not np.all(betas > 0):
        raise StepsafeError("beta must be one or more finite frequencies > 0")
    gamma = m.friction if friction is None else float(friction)
    if not (math.isfinite(gamma) and gamma >= 0):
        raise StepsafeError(f"friction must be a finite number >= 0, got {friction!r}")
    modes = []
    closed = CLOSED_FORMS.get(m.letters)
    for b in betas:
        z = float(b * h)
        M, Q = step_moments(m, [z], gamma / b)
        radius = float(spectral_radius(M)[0])
        S = stationary_covariance(M, Q)[0]
        stable = bool(radius < 1.0)
        known: tuple[float, float, float] | None = None
        if closed is not None and z < 2.0:
            qq, pp, qp = closed(np.array(z))
            known = (float(qq), float(pp), float(qp))
        modes.append(ModeSampling(float(b), z, radius, stable,
                                  float(S[0, 0]) if stable else None,
                                  float(S[1, 1]) if stable else None,
                                  float(S[0, 1]) if stable else None, known))
    first = find_region(m, "oscillator").first_interval  # (ends short of z* by its uncertainty)
    h_stable = 0.0 if first is None else None if first.hi is None else \
        float(first.hi / betas.max())
    return LangevinReport(m.name, m.letters, h, gamma, m.kT, tuple(modes), h_stable)


def step_for_tolerance(method: Any, tol: float, which: str = "configurational",
                       friction: float = 1.0, samples: int = 2000) -> float | None:
    """The largest ``z = omega h`` below the mean map's stability limit such that the
    stationary ``which`` temperature ratio (``configurational`` or ``kinetic``) is within
    ``tol`` of 1 at every smaller z, at the friction per unit of frequency ``friction``;
    None if it holds up to the limit (then stability binds). Found on a grid of ``samples``
    points and refined by bisection."""
    m = _langevin(method)
    tol = positive_finite(tol, "tol")
    if which not in ("configurational", "kinetic"):
        raise StepsafeError(f"which must be configurational or kinetic, got {which!r}")
    z_star = find_region(m, "oscillator").first_boundary
    limit = 10.0 if z_star is None else float(z_star)
    index = 0 if which == "configurational" else 1

    def excess(z: np.ndarray) -> np.ndarray:
        S = stationary_covariance(*step_moments(m, z, friction))
        return np.abs(S[:, index, index] - 1.0) - tol

    z = limit * np.arange(1, samples + 1) / (samples + 1)
    f = excess(z)
    over = np.flatnonzero(~(f <= 0))
    if not over.size:
        return None
    i = int(over[0])
    lo, hi = (0.0 if i == 0 else float(z[i - 1])), float(z[i])
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if not lo < mid < hi:
            break
        if excess(np.array([mid]))[0] <= 0:
            lo = mid
        else:
            hi = mid
    return lo
