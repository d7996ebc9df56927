"""Other modes of the target: a search from dispersed starts around the Laplace
approximation, and whether the draws visit the modes it finds.

R-hat and the effective sample size (:mod:`stepsafe.core.hmc_target.statistics`) see only
the modes some chain visits: chains started around one mode that never leave it read as
converged, however much mass lies elsewhere. The search looks for such modes.

Search. In the coordinates ``z`` of the Laplace approximation at the mode found
(``q = mode + L^-T z`` with ``nabla^2 U(mode) = L L^T``, where it is ``N(0, I)``),
:data:`STARTS` points are drawn from ``N(0, s^2 I)`` at each scale s of :data:`SCALES`
(fewer in high dimension: at most :data:`ELEMENTS` numbers in all) and each descends U by
gradient steps with its own step length (doubled after a step that lowers U by the Armijo
fraction :data:`ARMIJO` of its first-order decrease, quartered otherwise), for
:data:`ITERATIONS` iterations, batched over the points. A start outside the support (U or
its gradient not finite) is dropped. The end points more than :data:`SAME` from the mode
are taken by increasing U, at least 1 apart, at most :data:`REFINE` of them, and each is
polished by L-BFGS-B (in z); a polished point more than :data:`SAME` from the mode and from
every mode kept, whose Hessian is positive definite, is another mode.

Mass. Each mode m gets its Laplace mass ``exp(-U(m)) det(nabla^2 U(m))^-1/2`` (up to the
common constant), and its share ``w`` of the sum over the modes found (the mode found first
included).

Visits. A mode's ellipsoid is ``(q - m)^T nabla^2 U(m) (q - m) <= chi2_d(0.99)``, which holds
99% of its Laplace approximation; the draws visit it in proportion ``v``. A mode of share
``w >= MODE_MASS`` that the draws visit in proportion below ``MISSED * 0.99 w`` is
**missed**: the draws do not represent it (and the report is unverified).

Not covered: a mode whose basin of descent none of the starts reaches (narrow modes far
out, beyond the scales searched, or hidden in directions the starts rarely take); modes of
Laplace share below :data:`MODE_MASS`; and the shares are Laplace's, which a non-Gaussian
mode can miss by a factor (hence the margin :data:`MISSED`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from stepsafe.core.hmc_target.draws import Draws, Laplace, own_scale_hessian
from stepsafe.core.hmc_target.potential import Target
from stepsafe.exceptions import StepsafeError

#: Starts per scale (before the dimension limit) ...
STARTS = 256
#: ... at these multiples of the Laplace standard deviations ...
SCALES = (1.0, 2.0, 4.0, 8.0)
#: ... at most this many numbers (starts times d) in all, at least 16 starts per scale.
ELEMENTS = 2**18
#: Descent iterations per start, batched.
ITERATIONS = 50
#: A descent step is kept when U falls by at least this fraction of its first-order decrease.
ARMIJO = 1e-4
#: End points polished by L-BFGS-B, at most.
REFINE = 8
#: Points closer than this in the mode's Laplace coordinates are the same mode.
SAME = 0.01
#: Modes whose Laplace share is below this are not checked.
MODE_MASS = 1e-3
#: A mode is missed when the draws visit its ellipsoid in proportion below this fraction of
#: what its Laplace share implies.
MISSED = 0.1
#: Quantile of the ellipsoid of each mode.
ELLIPSOID = 0.99


@dataclass(frozen=True)
class Mode:
    """A mode: its position, U there, Laplace share (of the modes found), and the share of
    the draws in its ellipsoid (None before the draws are compared)."""

    position: tuple[float, ...]
    energy: float
    hessian: np.ndarray
    share: float
    visited: float | None = None

    #: the keys of ``hmc --json``'s records of modes named after other attributes
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "laplace_share": "share", "draws_within": "visited"})

    @property
    def missed(self) -> bool:
        """Share at least :data:`MODE_MASS` and visited in proportion below
        ``MISSED * ELLIPSOID * share``."""
        return bool(self.visited is not None and self.share >= MODE_MASS
                    and self.visited < MISSED * ELLIPSOID * self.share)

    def record(self) -> dict[str, Any]:
        """This mode as ``hmc --json`` gives it."""
        return {"position": list(self.position), "energy": self.energy,
                "laplace_share": self.share, "draws_within": self.visited,
                "missed": self.missed}


@dataclass(frozen=True)
class Survey:
    """What the search did and found: starts per scale, the scales (Laplace standard
    deviations), descent iterations, the modes (the mode found first, then the others by
    decreasing share), and why the search stopped early, if it did."""

    starts: int
    scales: tuple[float, ...]
    iterations: int
    modes: tuple[Mode, ...]
    stopped: str | None = None

    #: the share below which a mode is not checked (:data:`MODE_MASS`)
    MODE_MASS: ClassVar[float] = MODE_MASS
    #: what the search covers
    COVERS: ClassVar[str] = "modes whose basin of descent one of the starts reached"
    #: the keys of ``hmc --json``'s ``mode_search`` named after other attributes
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "starts_per_scale": "starts", "missed_count": "missed_count",
        "mode_mass": "MODE_MASS", "covers": "COVERS"})

    @property
    def missed_count(self) -> int:
        """How many modes the draws miss."""
        return len(self.missed)

    @property
    def missed(self) -> tuple[Mode, ...]:
        """The modes the draws miss (:attr:`Mode.missed`), the first never among them."""
        return tuple(m for m in self.modes[1:] if m.missed)

    def visited_by(self, draws: Draws) -> Survey:
        """The same survey with each mode's share of ``draws`` within its ellipsoid."""
        from scipy.stats import chi2

        flat = draws.flat
        d = flat.shape[1]
        radius = float(chi2.ppf(ELLIPSOID, d))
        modes = []
        for m in self.modes:
            x = flat - np.asarray(m.position)
            inside = np.einsum("ni,ij,nj->n", x, m.hessian, x) <= radius
            modes.append(Mode(m.position, m.energy, m.hessian, m.share,
                              float(inside.mean())))
        return Survey(self.starts, self.scales, self.iterations, tuple(modes), self.stopped)

    def record(self) -> dict[str, Any]:
        """The search as ``hmc --json`` gives it."""
        return {"starts_per_scale": self.starts, "scales": list(self.scales),
                "iterations": self.iterations, "stopped": self.stopped,
                "modes": [m.record() for m in self.modes],
                "missed_count": self.missed_count, "mode_mass": self.MODE_MASS,
                "covers": self.COVERS}

    def missed_text(self) -> str | None:
        """Why the draws do not represent the target, naming the modes they miss; None."""
        missed = self.missed
        if not missed:
            return None
        parts = [f"at q = ({', '.join(f'{x:.4g}' for x in m.position)}), Laplace share "
                 f"{m.share:.3g}, {100 * (m.visited or 0.0):.3g}% of the draws within its "
                 f"99% ellipsoid against about {100 * ELLIPSOID * m.share:.3g}%"
                 for m in missed[:3]]
        more = f" and {len(missed) - 3} more" if len(missed) > 3 else ""
        return (f"the draws miss {len(missed)} mode(s) the mode search found: "
                + "; ".join(parts) + more)


def survey(target: Target, laplace: Laplace, seed: int) -> Survey | None:
    """Search for other modes around the Laplace approximation (module docstring); None
    when it is not positive definite.

    Parameters
    ----------
    target
        The potential (the mass plays no part).
    laplace
        The mode found first and its Laplace approximation.
    seed
        Seed of the starts.

    Returns
    -------
    Survey or None
    """
    if not laplace.positive_definite:
        return None
    import scipy.linalg as sl

    pot = target.potential
    d = target.dimension
    H = 0.5 * (laplace.hessian + laplace.hessian.T)
    try:
        L = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return None
    per_scale = int(max(16, min(STARTS, ELEMENTS // (d * len(SCALES)))))
    mode = laplace.mode

    def to_q(z: np.ndarray) -> np.ndarray:
        return mode + sl.solve_triangular(L.T, z.T, lower=False).T

    def u_of(q: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.asarray(pot.energy(q), dtype=float)

    def g_of(q: np.ndarray) -> np.ndarray:
        # the gradient in z: L^-1 grad U
        with np.errstate(all="ignore"):
            g = np.asarray(pot.gradient(q), dtype=float)
        return sl.solve_triangular(L, g.T, lower=True).T

    u_mode = float(u_of(mode[None, :])[0])
    first = Mode(tuple(float(x) for x in mode), u_mode, H, 1.0)
    rng = np.random.default_rng(seed)
    z = np.concatenate([s * rng.standard_normal((per_scale, d)) for s in SCALES])
    stopped = None
    found = [first]
    try:
        q = to_q(z)
        u, g = u_of(q), g_of(q)
        ok = np.isfinite(u) & np.isfinite(g).all(axis=1)
        z, u, g = z[ok], u[ok], g[ok]
        alpha = np.ones(z.shape[0])
        for _ in range(ITERATIONS):
            if not z.shape[0]:
                break
            trial = z - alpha[:, None] * g
            qt = to_q(trial)
            ut = u_of(qt)
            gg = (g * g).sum(axis=1)
            better = np.isfinite(ut) & (ut <= u - ARMIJO * alpha * gg) & (gg > 0)
            if better.any():
                gt = g_of(qt[better])
                fine = np.isfinite(gt).all(axis=1)
                idx = np.flatnonzero(better)[fine]
                z[idx], u[idx], g[idx] = trial[idx], ut[idx], gt[fine]
                better[:] = False
                better[idx] = True
            alpha = np.where(better, np.minimum(2.0 * alpha, 1e6), 0.25 * alpha)
        far = np.linalg.norm(z, axis=1) > SAME
        order = np.flatnonzero(far)[np.argsort(u[far], kind="stable")]
        picked: list[np.ndarray] = []
        for k in order:
            if len(picked) >= REFINE:
                break
            if all(np.linalg.norm(z[k] - p) >= 1.0 for p in picked):
                picked.append(z[k])
        for z0 in picked:
            zm = _polish(u_of, g_of, to_q, z0)
            if zm is None or np.linalg.norm(zm) <= SAME:
                continue
            qm = to_q(zm[None, :])[0]
            if any(np.linalg.norm(L.T @ (qm - np.asarray(m.position))) <= SAME
                   for m in found[1:]):
                continue
            Hm = own_scale_hessian(pot, qm, np.sqrt(np.diag(np.linalg.inv(H))))
            if Hm is None:
                continue
            Hm = 0.5 * (Hm + Hm.T)
            if not np.linalg.eigvalsh(Hm)[0] > 0:
                continue
            found.append(Mode(tuple(float(x) for x in qm), float(u_of(qm[None, :])[0]), Hm,
                              0.0))
    except StepsafeError as exc:
        stopped = f"the search stopped: {exc}"
    # Laplace masses: exp(-U) det(H)^-1/2, as shares of their sum
    logs = np.array([-m.energy - 0.5 * np.linalg.slogdet(m.hessian)[1] for m in found])
    shares = np.exp(logs - logs.max())
    shares /= shares.sum()
    modes = [Mode(m.position, m.energy, m.hessian, float(w)) for m, w in zip(found, shares)]
    modes = [modes[0]] + sorted(modes[1:], key=lambda m: -m.share)
    return Survey(per_scale, SCALES, ITERATIONS, tuple(modes), stopped)


def _polish(u_of: Any, g_of: Any, to_q: Any, z0: np.ndarray) -> np.ndarray | None:
    """A local minimum of U in z from ``z0`` by L-BFGS-B; None where it fails."""
    from scipy.optimize import minimize

    def fun(z: np.ndarray) -> float:
        value = float(u_of(to_q(z[None, :]))[0])
        return value if math.isfinite(value) else math.inf

    def jac(z: np.ndarray) -> np.ndarray:
        return np.asarray(g_of(to_q(z[None, :]))[0], dtype=float)

    with np.errstate(all="ignore"):
        found = minimize(fun, z0, jac=jac, method="L-BFGS-B",
                         options={"gtol": 1e-9, "ftol": 1e-15, "maxiter": 2000})
    zm = np.asarray(found.x, dtype=float)
    if not np.isfinite(zm).all() or not math.isfinite(float(found.fun)):
        return None
    g = jac(zm)
    if not np.isfinite(g).all() or np.linalg.norm(g) > 1e-4 * max(1.0, math.sqrt(zm.size)):
        return None
    return zm
