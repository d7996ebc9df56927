"""The Hessian of an engine's potential by central differences of its forces, dense or as
Hessian-vector products, and the extreme eigenvalues of the mass-weighted Hessian.

Coordinates are the 3 Cartesian coordinates of every moving particle (positive mass,
:func:`~stepsafe.systems.md.engine.mobile_particles`), in the order ``x_0, y_0, z_0, x_1, ...``,
in nm. For a unit direction ``u`` (Euclidean norm 1 in nm) and a step ``eps`` in nm, with
``F_0 = F(x)`` and ``F_+- = F(x +- eps u)``,

    D(eps) u = -(F_+ - F_-) / (2 eps) = H u + O(eps^2) + O(rounding / eps),
    e(eps) u = |F_+ - 2 F_0 + F_-| / (2 eps)           (element-wise),

the central difference and its first-order error estimate, which costs nothing beyond the
force at x (computed once). For smooth forces e is (eps/2)|d^3U[u, u, .]|, first order in eps,
so it exceeds the second-order truncation error of D while eps is below the length over which
the curvature changes. A force that jumps by J between x - eps u and x + eps u (a pair crossing
a plain cutoff, as PME and reaction-field setups without a switching function have) makes D
wrong by J/(2 eps); the jump is on one side of x only, so e shows the same J/(2 eps). Such a
product is formed again with a step 16 times smaller (up to :data:`RETRIES` times), which
leaves the jump outside the stencil unless it sits within the smaller step. Rounding enters
twice and is added to e as a floor: the forces' own rounding S/eps (S measured by the step
control where rounding dominates), and the rounding of the displaced positions, which makes
the displacement ``x_+ - x_-`` differ from ``2 eps u`` (exactly known: along a single
coordinate the quotient uses the actual displacement, otherwise its relative size times the
largest ``|D u|`` met is added).

Step control (:func:`choose_step`): on a fixed pseudo-random direction (drawn in the
mass-weighted metric, so that light atoms move more, as in thermal motion) the relative
estimate ``|e(eps)| / |D(eps)|`` is computed on the ladder :data:`STEPS` (scaled by the median
nearest-neighbour distance over 0.1 nm, and extended by halving until rounding shows), and the
step 2^:data:`ABOVE_BALANCE` times the one with the smallest estimate is taken: at the smallest
the first-order term (falling with eps) and rounding (rising as 1/eps) balance; 8 times above
it the first-order term, a deterministic overestimate of the truncation, outweighs rounding 64
to 1. On OpenMM's Reference platform (double precision) that is 1e-7 to 1e-8 nm for molecular
systems with relative errors near 1e-8; single-precision forces (CPU platform) reach only
1e-3 to 1e-5.

Error bounds: an eigenvalue of the mass-weighted Hessian moves by at most ``||Delta W||_2 <=
rho(|Delta W|)`` (Weyl); with the element-wise estimate E for ``|Delta W|`` this is the bound
:data:`SAFETY` rho(E) (:attr:`Spectrum.bound`); each eigenvalue also gets the first-order
estimate :data:`SAFETY` ``|v|^T E |v|`` (:attr:`Spectrum.errors`, valid for an eigenvalue
separated from the others). Tested against exact Hessians of harmonic networks at lengths
from 1e-3 to 1e3 nm and stiffnesses over 8 decades.

The mass-weighted Hessian ``W = M^(-1/2) H M^(-1/2)`` (M the diagonal of masses, each repeated
3 times) has the squared angular frequencies as eigenvalues, in rad^2/ps^2 with the engine's
units (kJ/mol/nm^2/amu = 1/ps^2). Verlet's linear limit is ``h = 2 / omega_max``.

The dense Hessian costs 2 force evaluations per coordinate (6 N) and memory quadratic in N;
above a few thousand atoms use :class:`HessianVectorProduct` (2 evaluations per product,
memory linear in N) and :func:`extreme_eigenvalues` (Lanczos: ARPACK's implicitly restarted
Lanczos, ``scipy``'s ``eigsh``, on a ``LinearOperator``, started from a fixed pseudo-random
vector). Progress goes to an optional callback ``progress(stage, done, total)`` (``total``
None when unknown); nothing here prints.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.md.engine import ForceEngine, as_positions, mobile_particles

#: Candidate finite-difference steps for a system whose nearest neighbours are
#: :data:`REFERENCE_LENGTH` apart (nm; 1e-2 down to 3.7e-10 by factors of 2); other systems
#: scale them by their median nearest-neighbour distance over it (:func:`length_scale`).
STEPS = tuple(1e-2 * 0.5 ** k for k in range(25))
REFERENCE_LENGTH = 0.1
#: The ladder is extended past :data:`STEPS` (by halving) until the estimate has grown for 3
#: halvings, up to this many candidates in all.
MAX_HALVINGS = 60
#: Step control takes the step 2^ABOVE_BALANCE times the one with the smallest relative error
#: estimate (fewer halvings where a force jump shows at the larger steps).
ABOVE_BALANCE = 3
#: Step control refuses forces whose smallest relative error estimate exceeds this: they are
#: not smooth enough, or not precise enough, for finite differences.
MAX_RELATIVE_ERROR = 1e-2
#: A product whose relative error estimate exceeds both this many times the step control's and
#: :data:`RETRY_FLOOR` is formed again with a step 16 times smaller, at most :data:`RETRIES`
#: times. (A single coordinate's column has a larger first-order term than the spread-out
#: pilot direction, up to about 1e-6 relative on Reference; a force jump inside the stencil
#: gives relative estimates of order 1 and more.)
RETRY_FACTOR = 8.0
RETRY_FLOOR = 1e-5
RETRIES = 3
#: Reported error bounds are this multiple of the error estimates (whose elements are of the
#: size of the errors, not above them with certainty).
SAFETY = 2.0
#: Seed of the pilot direction and of Lanczos's start vector.
SEED = 20240601
#: The speed of light in cm/ps (exact), for wavenumbers omega / (2 pi c).
SPEED_OF_LIGHT_CM_PER_PS = 0.0299792458

Progress = Callable[[str, int, "int | None"], None]


def _silent(stage: str, done: int, total: int | None) -> None:
    return None


@dataclass(frozen=True)
class StepChoice:
    """The outcome of :func:`choose_step`.

    Attributes
    ----------
    step : float
        The chosen step eps in nm.
    steps : tuple of float
        The candidates tried (nm).
    errors : tuple of float
        The relative error estimate ``|e(eps)| / |D(eps)|`` at each candidate.
    noise : float
        The rounding scale S of the forces, kJ/mol/nm: the median of ``eps |e(eps)|`` at the
        three smallest candidates (where rounding dominates, ``eps |e|`` is constant,
        elsewhere it is larger) and at least ``2 u |F(x)|`` (u the unit roundoff), so that the
        rounding of ``D(eps) u`` has norm about ``S / eps`` or less.
    """

    step: float
    steps: tuple[float, ...]
    errors: tuple[float, ...]
    noise: float

    @property
    def relative_error(self) -> float:
        """The relative error estimate at the chosen step."""
        return self.errors[self.steps.index(self.step)]


class ForceDifferences:
    """Products ``H u`` of the Cartesian Hessian with vectors over the moving particles,
    by central differences of the engine's forces, with error estimates.

    Parameters
    ----------
    engine : ForceEngine
    positions : array_like, shape (N, 3), optional
        Where to differentiate (nm); the engine's positions by default.
    step : float, optional
        eps in nm; chosen by :func:`choose_step` on first use when omitted.
    progress : callable, optional
        ``progress("step control", candidates_tried, None)`` while the step is chosen.
    """

    def __init__(self, engine: ForceEngine, positions: np.ndarray | None = None,
                 step: float | None = None, progress: Progress | None = None) -> None:
        self.engine = engine
        self.x0 = as_positions(engine.positions if positions is None else positions,
                               engine.n_particles)
        self.particles = mobile_particles(engine.masses)
        if len(self.particles) == 0:
            raise StepsafeError("the system has no particle of positive mass")
        self.masses = np.asarray(engine.masses, dtype=float)[self.particles]
        #: The dimension 3 n of the space of moving coordinates.
        self.dim = 3 * len(self.particles)
        #: sqrt of the mass of each coordinate (amu^1/2), shape (dim,).
        self.sqrt_m = np.repeat(np.sqrt(self.masses), 3)
        #: Force evaluations so far, and products formed again with a smaller step.
        self.calls = 0
        self.retries = 0
        self._hnorm = 0.0
        self._progress = progress
        #: The forces at x0 on the moving coordinates (kJ/mol/nm).
        self.f0 = self.forces()
        self._choice: StepChoice | None = None
        if step is not None:
            if not (np.isfinite(step) and step > 0):
                raise StepsafeError(f"finite-difference step must be positive, got {step}")
            self._choice = choose_step(self, (float(step),), above_balance=0)

    def forces(self, u: np.ndarray | None = None, eps: float = 0.0) -> np.ndarray:
        """Forces on the moving coordinates (dim,) at ``x0 + eps u`` (u over moving coordinates)."""
        return self._forces_at(self._displaced(u, eps))

    def _displaced(self, u: np.ndarray | None, eps: float) -> np.ndarray:
        x = self.x0
        if u is not None:
            x = x.copy()
            x[self.particles] += eps * u.reshape(-1, 3)
        return x

    def _forces_at(self, x: np.ndarray) -> np.ndarray:
        self.calls += 1
        f = np.asarray(self.engine.forces(x), dtype=float)
        if f.shape != x.shape:
            raise StepsafeError(f"the engine returned forces of shape {f.shape} for positions "
                                f"of shape {x.shape}")
        f = f[self.particles].reshape(-1)
        if not np.all(np.isfinite(f)):
            raise StepsafeError("the engine returned non-finite forces near the configuration")
        return f

    def raw_difference(self, u: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray, float]:
        """``D(eps) u``, ``e(eps) u`` (kJ/mol/nm^2) and the displacement's rounding, for a
        direction u of Euclidean norm 1.

        The displaced positions are rounded to floating point, so the displacement actually
        made is ``delta = x_+ - x_-`` (exact: a difference of nearby numbers), not ``2 eps u``.
        Along a single coordinate the quotient uses delta itself (no error); otherwise the
        result is H applied to ``u + r/(2 eps)``, ``r = delta - 2 eps u``, and the third value
        is ``|r| / (2 eps)``.
        """
        xp, xm = self._displaced(u, eps), self._displaced(u, -eps)
        fp, fm = self._forces_at(xp), self._forces_at(xm)
        delta = (xp - xm)[self.particles].reshape(-1)
        e = np.abs(fp - 2.0 * self.f0 + fm) / (2.0 * eps)
        nz = np.flatnonzero(u)
        if len(nz) == 1 and delta[nz[0]] != 0.0:
            j = int(nz[0])
            return -(fp - fm) * (u[j] / delta[j]), e, 0.0
        shift = float(np.linalg.norm(delta - 2.0 * eps * u)) / (2.0 * eps)
        d = -(fp - fm) / (2.0 * eps)
        self._hnorm = max(self._hnorm, float(np.linalg.norm(d)))
        return d, e, shift

    def difference(self, u: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
        """``D(eps) u`` and its error estimate: ``e(eps) u`` plus, in every element, the
        rounding floor ``(S / eps + |r| / (2 eps) |H|) / sqrt(dim)`` (a vector of that norm
        times sqrt(dim)): S the force rounding from the step control, ``|r|/(2 eps)`` the
        displacement's rounding, |H| the largest ``|D u|`` met so far."""
        d, e, shift = self.raw_difference(u, eps)
        floor = self.choice.noise / eps + shift * self._hnorm
        return d, e + floor / math.sqrt(self.dim)

    @property
    def choice(self) -> StepChoice:
        """The step control's outcome (computed on first use)."""
        if self._choice is None:
            self._choice = choose_step(self, progress=self._progress)
        return self._choice

    @property
    def step(self) -> float:
        return self.choice.step

    def product(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``H v`` and its element-wise error estimate, for any vector ``v`` (dim,) over the
        moving coordinates (v is scaled to unit length for the differences and the result
        scaled back). A product whose relative error estimate exceeds :data:`RETRY_FACTOR`
        times the step control's and :data:`RETRY_FLOOR` (a force jump inside the stencil) is
        formed again with a step 16 times smaller while that lowers the estimate, up to
        :data:`RETRIES` times; the one with the smallest estimate is returned.

        Parameters
        ----------
        v : ndarray, shape (dim,)

        Returns
        -------
        (ndarray, ndarray)
            H v in kJ/mol/nm^2 times v's units, and the error estimate.
        """
        v = np.asarray(v, dtype=float).reshape(-1)
        norm = float(np.linalg.norm(v))
        if norm == 0.0:
            return np.zeros(self.dim), np.zeros(self.dim)
        u = v / norm
        eps = self.step
        ref = self.choice.relative_error
        accept = max(RETRY_FACTOR * ref, RETRY_FLOOR) if np.isfinite(ref) else RETRY_FLOOR
        d, e = self.difference(u, eps)
        best = (self._relative(d, e), d, e)
        for _ in range(RETRIES):
            if best[0] <= accept:
                break
            eps /= 16.0
            self.retries += 1
            d, e = self.difference(u, eps)
            rel = self._relative(d, e)
            if rel >= best[0]:
                break       # the estimate grows as the step shrinks: rounding, not a jump
            best = (rel, d, e)
        return norm * best[1], norm * best[2]

    @staticmethod
    def _relative(d: np.ndarray, e: np.ndarray) -> float:
        scale = float(np.linalg.norm(d))
        return float(np.linalg.norm(e)) / scale if scale > 0 else 0.0


def length_scale(positions: np.ndarray) -> float:
    """The median distance from a particle to its nearest neighbour (nm), or
    :data:`REFERENCE_LENGTH` when it is not positive (fewer than two particles, or all at one
    point). Periodic images are not considered."""
    from scipy.spatial import cKDTree

    x = np.asarray(positions, dtype=float).reshape(-1, 3)
    if len(x) < 2:
        return REFERENCE_LENGTH
    dist, _ = cKDTree(x).query(x, k=2)
    near = float(np.median(np.asarray(dist)[:, 1]))  # (k = 2: an array of pairs)
    return near if np.isfinite(near) and near > 0 else REFERENCE_LENGTH


def choose_step(differences: ForceDifferences, steps: tuple[float, ...] | None = None,
                seed: int = SEED, above_balance: int | None = None,
                progress: Progress | None = None) -> StepChoice:
    """The finite-difference step where the relative error estimate ``|e| / |D|`` is smallest,
    on a fixed pseudo-random direction ``u ~ M^(-1/2) xi`` (xi standard normal, u scaled to
    norm 1).

    Parameters
    ----------
    differences : ForceDifferences
    steps : tuple of float, optional
        Candidates in nm; :data:`STEPS` scaled by :func:`length_scale` of the moving particles
        over :data:`REFERENCE_LENGTH` when omitted.
    seed : int
        Of the direction.
    above_balance : int, optional
        Halvings above the smallest estimate to step back (:data:`ABOVE_BALANCE`).
    progress : callable, optional
        ``progress("step control", candidates_tried, None)`` after each candidate (two force
        evaluations).

    Returns
    -------
    StepChoice
    """
    above = ABOVE_BALANCE if above_balance is None else above_balance
    extend = steps is None
    if steps is None:
        scale = length_scale(differences.x0[differences.particles]) / REFERENCE_LENGTH
        steps = tuple(s * scale for s in STEPS)
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(differences.dim) / differences.sqrt_m
    u /= np.linalg.norm(u)
    rel: list[float] = []
    scaled: list[float] = []

    def measure(eps: float) -> None:
        d, e, shift = differences.raw_difference(u, eps)
        scale = float(np.linalg.norm(d))
        rel.append(float(np.linalg.norm(e)) / scale + shift if scale > 0 else float("inf"))
        scaled.append(eps * float(np.linalg.norm(e)))
        if progress is not None:
            progress("step control", len(rel), None)

    for eps in steps:
        measure(eps)
    # go on halving until the estimate has grown for 3 halvings (rounding dominates there)
    while extend and int(np.argmin(rel)) > len(rel) - 4 and len(rel) < MAX_HALVINGS:
        steps = steps + (steps[-1] / 2.0,)
        measure(steps[-1])
    # force rounding: eps |e| at the three smallest steps (where rounding dominates, and
    # larger where it does not), never below the rounding of the forces' own size
    noise = max(float(np.median(scaled[-3:])),
                2.0 * np.finfo(float).eps * float(np.linalg.norm(differences.f0)))
    best = int(np.argmin(rel))
    if not rel[best] <= MAX_RELATIVE_ERROR:
        raise StepsafeError(
            f"the forces are not smooth or precise enough for finite differences: relative "
            f"error {rel[best]:.1e} at best; use the Reference platform")
    # up to 8 times the balance point, where the first-order term dominates the estimate
    # (8 times, rounding an eighth: 64 to 1), unless a force jump shows there
    for up in range(above, 0, -1):
        if best - up >= 0 and steps[best - up] == steps[best] * 2.0 ** up and \
                rel[best - up] <= 2.0 ** up * rel[best]:
            best -= up
            break
    return StepChoice(float(steps[best]), tuple(float(s) for s in steps), tuple(rel), noise)


@dataclass(frozen=True)
class Hessian:
    """A dense Hessian by central differences.

    Attributes
    ----------
    matrix : ndarray, shape (d, d)
        ``d^2 U / dx dx`` in kJ/mol/nm^2 over the moving coordinates (central differences,
        symmetrised).
    error : ndarray, shape (d, d)
        Element-wise error estimate (the larger of the symmetrised estimate e and half the
        asymmetry of the differences).
    particles : ndarray of int
        The moving particles (d = 3 n).
    masses : ndarray, shape (n,)
        Their masses in amu.
    step : StepChoice
        The finite-difference step.
    calls : int
        Force evaluations used.
    positions : ndarray, shape (N, 3)
        Where the Hessian was taken (nm, all particles).
    forces : ndarray, shape (d,)
        The forces there on the moving coordinates (kJ/mol/nm).
    """

    matrix: np.ndarray
    error: np.ndarray
    particles: np.ndarray
    masses: np.ndarray
    step: StepChoice
    calls: int
    positions: np.ndarray
    forces: np.ndarray

    def mass_weighted(self) -> tuple[np.ndarray, np.ndarray]:
        """``W = M^(-1/2) H M^(-1/2)`` in 1/ps^2 and its element-wise error estimate."""
        s = 1.0 / np.repeat(np.sqrt(self.masses), 3)
        return s[:, None] * self.matrix * s[None, :], s[:, None] * self.error * s[None, :]


def hessian(engine: ForceEngine, positions: np.ndarray | None = None, *,
            step: float | None = None, progress: Progress | None = None) -> Hessian:
    """The dense Hessian of the engine's potential at ``positions`` by central differences of
    forces, one coordinate at a time, with the element-wise error estimate.

    Parameters
    ----------
    engine : ForceEngine
    positions : array_like, shape (N, 3), optional
        nm; the engine's positions by default.
    step : float, optional
        eps in nm; by step control when omitted.
    progress : callable, optional
        ``progress("hessian", done_columns, total_columns)`` (and ``"step control"``, see
        :func:`choose_step`).

    Returns
    -------
    Hessian
    """
    progress = progress or _silent
    fd = ForceDifferences(engine, positions, step, progress)
    d = fd.dim
    choice = fd.choice
    value = np.empty((d, d))
    err = np.empty((d, d))
    unit = np.zeros(d)
    for j in range(d):
        unit[j] = 1.0
        value[:, j], e = fd.product(unit)
        err[:, j] = e
        unit[j] = 0.0
        progress("hessian", j + 1, d)
    sym = 0.5 * (value + value.T)
    error = np.maximum(0.5 * (err + err.T), 0.5 * np.abs(value - value.T))
    return Hessian(sym, error, fd.particles, fd.masses, choice, fd.calls, fd.x0, fd.f0)


@dataclass(frozen=True)
class Spectrum:
    """Eigenvalues of a mass-weighted Hessian with their eigenvectors, fastest first.

    Attributes
    ----------
    eigenvalues : ndarray, shape (k,)
        omega^2 in rad^2/ps^2, descending (negative: an unstable direction).
    vectors : ndarray, shape (d, k)
        Orthonormal mass-weighted eigenvectors (columns); the Cartesian displacement of a
        mode is ``M^(-1/2) v``.
    errors : ndarray, shape (k,)
        Error estimate of each eigenvalue (rad^2/ps^2): finite differences, plus the
        residual ``|W v - lambda v|`` for Lanczos.
    particles : ndarray of int
        The moving particles the coordinates belong to.
    bound : float
        A bound on every eigenvalue's finite-difference error (Weyl's inequality with the
        spectral norm of the element-wise error estimate; ``nan`` when not computed).
    products : int
        Hessian-vector products (Lanczos) or 0 (dense).
    removed : int
        Degrees of freedom removed by constraints (0 without).
    """

    eigenvalues: np.ndarray
    vectors: np.ndarray
    errors: np.ndarray
    particles: np.ndarray
    bound: float = float("nan")
    products: int = 0
    removed: int = 0

    @property
    def omega(self) -> np.ndarray:
        """Angular frequencies sqrt(lambda) in rad/ps (negative for lambda < 0: -sqrt|lambda|)."""
        return np.sign(self.eigenvalues) * np.sqrt(np.abs(self.eigenvalues))

    @property
    def wavenumbers(self) -> np.ndarray:
        """omega / (2 pi c) in cm^-1 (signed as :attr:`omega`)."""
        return self.omega / (2.0 * np.pi * SPEED_OF_LIGHT_CM_PER_PS)

    def verlet_limit(self) -> float:
        """Verlet's linear stability limit 2/omega_max in ps, omega_max from the largest
        eigenvalue held (inf without a positive one)."""
        top = float(np.max(self.eigenvalues)) if len(self.eigenvalues) else 0.0
        return 2.0 / np.sqrt(top) if top > 0 else float("inf")

    def participation(self, mode: int = 0) -> np.ndarray:
        """The share of mode ``mode``'s kinetic energy carried by each moving particle:
        ``sum over x, y, z of v^2`` (sums to 1), shape (n,)."""
        v = self.vectors[:, mode]
        return (v.reshape(-1, 3) ** 2).sum(axis=1)


def spectral_radius_bound(e: np.ndarray, iterations: int = 30) -> float:
    """An upper bound on the spectral radius of a non-negative symmetric matrix: the
    Collatz-Wielandt bound ``max_i (E x)_i / x_i``, valid for every positive x, here x from a
    few power iterations started at the all-ones vector. For an element-wise error bound E
    of a symmetric matrix, ``||Delta||_2 <= rho(|Delta|) <= rho(E)``."""
    if e.size == 0 or not np.any(e > 0):
        return 0.0
    x = np.ones(len(e))
    for _ in range(iterations):
        y = e @ x + 1e-300
        x = y / y.max()
    y = e @ x
    return float(np.max(y / x))


def spectrum(h: Hessian, k: int | None = None) -> Spectrum:
    """All (or the ``k`` largest) eigenvalues of the mass-weighted dense Hessian, with
    first-order error estimates ``|v|^T E |v|`` (E the element-wise error estimate of W) and
    the global bound ``rho(E) >= ||Delta W||_2`` (Weyl: no eigenvalue moves by more).

    Parameters
    ----------
    h : Hessian
    k : int, optional
        How many of the largest to keep (all by default).

    Returns
    -------
    Spectrum
    """
    w, e = h.mass_weighted()
    lam, vec = np.linalg.eigh(w)
    lam, vec = lam[::-1], vec[:, ::-1]
    if k is not None:
        lam, vec = lam[:k], vec[:, :k]
    av = np.abs(vec)
    errors = SAFETY * np.einsum("ik,ij,jk->k", av, e, av)
    return Spectrum(lam, vec, errors, h.particles, SAFETY * spectral_radius_bound(e), 0)


class HessianVectorProduct:
    """``v -> W v``, the mass-weighted Hessian times a vector, by central differences of
    forces (2 evaluations; memory linear in N).

    Parameters
    ----------
    engine : ForceEngine
    positions : array_like, shape (N, 3), optional
    step : float, optional
        eps in nm; by step control when omitted.
    progress : callable, optional
        ``progress("products", done, None)`` after each product (each Lanczos iteration
        forms one), ``progress("step control", ...)`` before (:func:`choose_step`).
    """

    def __init__(self, engine: ForceEngine, positions: np.ndarray | None = None, *,
                 step: float | None = None, progress: Progress | None = None) -> None:
        self.fd = ForceDifferences(engine, positions, step, progress)
        self.dim = self.fd.dim
        self.particles = self.fd.particles
        self.products = 0
        self._progress = progress or _silent

    def __call__(self, v: np.ndarray) -> np.ndarray:
        return self.with_error(v)[0]

    def with_error(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``W v`` and its element-wise error estimate."""
        v = np.asarray(v, dtype=float).reshape(-1)
        out, err = self.fd.product(v / self.fd.sqrt_m)
        self.products += 1
        self._progress("products", self.products, None)
        return out / self.fd.sqrt_m, err / self.fd.sqrt_m


#: Lanczos defaults: relative accuracy of the Ritz values (ARPACK's ``tol``) and the
#: iteration cap in restarts.
LANCZOS_TOL = 1e-6
LANCZOS_MAXITER = 1000


def extreme_eigenvalues(operator: Callable[[np.ndarray], np.ndarray], dim: int, *, k: int = 1,
                        which: str = "largest", tol: float = LANCZOS_TOL,
                        ncv: int | None = None, maxiter: int = LANCZOS_MAXITER,
                        seed: int = SEED, with_error: Callable | None = None,
                        particles: np.ndarray | None = None) -> Spectrum:
    """The ``k`` largest (or smallest) eigenvalues of a symmetric operator by Lanczos
    (ARPACK through ``scipy.sparse.linalg.eigsh`` on a ``LinearOperator``), started from a
    fixed pseudo-random vector, so a run is reproducible.

    Each returned pair is checked by one more product: the residual ``|W v - lambda v|``
    bounds the distance from lambda to some eigenvalue of the operator (v has norm 1), and
    ``with_error`` (if given; e.g. :meth:`HessianVectorProduct.with_error`) adds the
    finite-difference estimate ``|v|^T |Delta W v|``. A Ritz value is the Rayleigh quotient of
    its vector, so the largest one never exceeds the largest eigenvalue of the operator.

    Parameters
    ----------
    operator : callable
        ``v -> W v`` on vectors of length ``dim``.
    dim : int
    k : int
        Eigenvalues wanted (``k < dim``).
    which : {"largest", "smallest", "magnitude"}
        Algebraically largest or smallest, or largest in absolute value (then every other
        eigenvalue lies within plus or minus the k-th's modulus).
    tol, ncv, maxiter :
        ARPACK's relative tolerance, Lanczos basis size (memory ``ncv * dim``; default
        ``max(2k + 1, 20)``) and iteration cap.
    seed : int
        Of the start vector.
    with_error : callable, optional
        ``v -> (W v, error estimate)``.
    particles : ndarray, optional
        Recorded in the result.

    Returns
    -------
    Spectrum
        Ordered fastest first (descending) for ``largest``, ascending for ``smallest``,
        by descending modulus for ``magnitude``.
    """
    from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

    if which not in ("largest", "smallest", "magnitude"):
        raise StepsafeError(f"which must be largest, smallest or magnitude, got {which!r}")
    if not 0 < k < dim:
        raise StepsafeError(f"k must be between 1 and {dim - 1}, got {k}")
    calls = [1]
    v0 = np.random.default_rng(seed).standard_normal(dim)
    v0 /= np.linalg.norm(v0)
    # ARPACK's tolerance turns absolute below |lambda| ~ 4e-11: work on W / sigma, sigma the
    # size of W on the start vector, so the tolerance is relative at every scale
    sigma = float(np.linalg.norm(operator(v0)))
    if not np.isfinite(sigma):
        raise StepsafeError("the operator returned non-finite values")
    if sigma == 0.0:
        sigma = 1.0

    def matvec(v: np.ndarray) -> np.ndarray:
        calls[0] += 1
        return operator(np.asarray(v, dtype=float).reshape(-1)) / sigma

    op: LinearOperator = LinearOperator((dim, dim), matvec=matvec, dtype=float)
    arpack: dict[str, Literal["LA", "SA", "LM"]] = {"largest": "LA", "smallest": "SA",
                                                    "magnitude": "LM"}
    try:
        lam, vec = eigsh(op, k=k, which=arpack[which], v0=v0, tol=tol, ncv=ncv,
                         maxiter=maxiter)
    except ArpackNoConvergence as exc:
        raise StepsafeError(f"Lanczos did not converge in {calls[0]} products "
                            f"({len(exc.eigenvalues)} of {k} eigenvalues)") from None
    lam = lam * sigma
    order = (np.argsort(lam)[::-1] if which == "largest" else np.argsort(lam)
             if which == "smallest" else np.argsort(np.abs(lam))[::-1])
    lam, vec = lam[order], vec[:, order]
    errors = np.empty(k)
    for i in range(k):
        v = vec[:, i]
        if with_error is not None:
            wv, e = with_error(v)
            fd = SAFETY * float(np.abs(v) @ e)
        else:
            wv, fd = operator(v), 0.0
        errors[i] = float(np.linalg.norm(wv - lam[i] * v)) + fd
    return Spectrum(lam, vec, errors,
                    np.arange(dim // 3) if particles is None else particles, float("nan"),
                    calls[0])


def largest_modes(engine: ForceEngine, positions: np.ndarray | None = None, *, k: int = 1,
                  step: float | None = None, tol: float = LANCZOS_TOL,
                  progress: Progress | None = None, which: str = "largest") -> Spectrum:
    """The ``k`` fastest modes of the mass-weighted Hessian by Lanczos on Hessian-vector
    products (no dense matrix: memory linear in the number of particles).

    Parameters
    ----------
    engine : ForceEngine
    positions : array_like, shape (N, 3), optional
    k : int
    step : float, optional
        eps in nm; by step control when omitted.
    tol : float
        ARPACK's relative tolerance.
    progress : callable, optional
        ``progress("products", done, None)``.
    which : {"largest", "magnitude"}
        As in :func:`extreme_eigenvalues`.

    Returns
    -------
    Spectrum
    """
    hvp = HessianVectorProduct(engine, positions, step=step, progress=progress)
    return extreme_eigenvalues(hvp, hvp.dim, k=k, tol=tol, which=which,
                               with_error=hvp.with_error,
                               particles=hvp.particles)


@dataclass(frozen=True)
class ModeReport:
    """One mode for a report: its frequency and the particles that carry it.

    Attributes
    ----------
    eigenvalue : float
        omega^2 in rad^2/ps^2.
    error : float
        Its error estimate.
    omega : float
        rad/ps (negative for an unstable direction: -sqrt|lambda|).
    wavenumber : float
        cm^-1.
    atoms : tuple of (int, str, float)
        ``(particle index, label, share of the mode's kinetic energy)``, largest share first,
        until the shares reach ``share`` or ``count`` particles.
    """

    eigenvalue: float
    error: float
    omega: float
    wavenumber: float
    atoms: tuple[tuple[int, str, float], ...]


def describe(spectrum: Spectrum, labels: tuple[str, ...] | list[str], *, modes: int = 5,
             count: int = 6, share: float = 0.9) -> tuple[ModeReport, ...]:
    """The first ``modes`` modes of ``spectrum`` (the fastest for a descending spectrum) with
    the particles that move in each.

    Parameters
    ----------
    spectrum : Spectrum
    labels : sequence of str
        Names of all N particles (indexed by particle number).
    modes : int
        How many modes.
    count : int
        At most this many particles per mode.
    share : float
        Stop listing particles once their shares add up to this.

    Returns
    -------
    tuple of ModeReport
    """
    out = []
    for m in range(min(modes, len(spectrum.eigenvalues))):
        p = spectrum.participation(m)
        order = np.argsort(p)[::-1]
        atoms: list[tuple[int, str, float]] = []
        total = 0.0
        for j in order[:count]:
            i = int(spectrum.particles[j])
            atoms.append((i, labels[i] if i < len(labels) else "", float(p[j])))
            total += float(p[j])
            if total >= share:
                break
        out.append(ModeReport(float(spectrum.eigenvalues[m]), float(spectrum.errors[m]),
                              float(spectrum.omega[m]), float(spectrum.wavenumbers[m]),
                              tuple(atoms)))
    return tuple(out)
