"""A potential energy ``U(q)`` with diagonal masses: what the thermal analysis needs of a
system ``H = p^T M^-1 p / 2 + U(q)``.

Conventions. Configurations are rows: ``q`` has shape ``(m, n)`` (m configurations of n
coordinates); ``energy(q)`` has shape ``(m,)``, ``gradient(q)`` ``(m, n)``, ``hessian(q)``
``(m, n, n)`` and ``hessian_vector(q, v)`` ``(m, n)`` (one vector per configuration). The
mass matrix is diagonal, ``M = diag(masses)``; frequencies are those of the mass-weighted
Hessian ``W = M^-1/2 grad^2 U M^-1/2``.

Without an analytic Hessian, Hessian-vector products are central differences of the
gradient, ``H v ~ (g(q + e v) - g(q - e v)) / 2e`` (:func:`fd_hessian_vector`): the error is
``e^2 |g'''[v, v]| / 6`` (truncation) plus ``r / e`` (the gradient's rounding r), smallest
at ``e = (3 r / |g'''[v, v]|)^(1/3)``; the third derivative is estimated from the difference
at ``e`` and ``2e``, and the error of the returned value is estimated alongside it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from stepsafe.core.integrator import System
from stepsafe.exceptions import StepsafeError

EPS = float(np.finfo(float).eps)
#: The gradient's rounding, relative to its size and to ``|H v| |q|`` (see
#: :func:`fd_hessian_vector`), unless the caller knows better.
GRADIENT_ROUNDING = 8 * EPS

Array = np.ndarray


class HessianVector(NamedTuple):
    """``H v`` at each configuration with an estimate of its absolute error (max-norm per
    row, 0 where the product is analytic) and the difference step used (0 if analytic)."""

    value: Array
    error: Array
    step: Array


@dataclass(frozen=True)
class Potential:
    """``U(q)`` and its derivatives on rows of configurations, with diagonal masses.

    Parameters
    ----------
    energy : callable
        ``U``: ``(m, n) -> (m,)``.
    gradient : callable
        ``grad U``: ``(m, n) -> (m, n)``.
    masses : array_like
        The n masses (positive, finite): ``M = diag(masses)``.
    hessian : callable, optional
        ``grad^2 U``: ``(m, n) -> (m, n, n)``.
    hessian_vector : callable, optional
        ``(q, v) -> grad^2 U(q) v``, both ``(m, n)``.
    minimum : array_like, optional
        A minimum ``q0`` of U (shape ``(n,)``): the 0 K configuration the analysis starts
        from.
    quadratic : bool
        U is exactly ``U(q0) + (q - q0)^T K (q - q0) / 2`` (then thermal configurations are
        drawn exactly).
    length : float, optional
        The length over which U's curvature changes, for difference steps (default: found
        by :func:`probe_length`).
    description : str
        What the potential is, for reports.
    """

    energy: Callable[[Array], Array]
    gradient: Callable[[Array], Array]
    masses: Array
    hessian: Callable[[Array], Array] | None = None
    hessian_vector: Callable[[Array, Array], Array] | None = None
    minimum: Array | None = None
    quadratic: bool = False
    length: float | None = None
    description: str = ""

    def __post_init__(self) -> None:
        masses = np.asarray(self.masses, dtype=float)
        if masses.ndim != 1 or masses.size == 0:
            raise StepsafeError(f"masses must be a non-empty list of numbers, got shape "
                                f"{masses.shape}")
        if not (np.all(np.isfinite(masses)) and np.all(masses > 0)):
            raise StepsafeError("masses must be positive finite numbers")
        object.__setattr__(self, "masses", masses)
        if self.minimum is not None:
            q0 = np.asarray(self.minimum, dtype=float).reshape(-1)
            if q0.size != masses.size or not np.all(np.isfinite(q0)):
                raise StepsafeError(f"the minimum must be {masses.size} finite numbers")
            object.__setattr__(self, "minimum", q0)
        if self.length is not None and not (np.isfinite(self.length) and self.length > 0):
            raise StepsafeError(f"length must be a positive finite number, got {self.length}")

    @property
    def dimension(self) -> int:
        """n, the number of coordinates."""
        return int(self.masses.size)

    @property
    def has_hessian(self) -> bool:
        """Whether Hessian(-vector) products are analytic."""
        return self.hessian is not None or self.hessian_vector is not None

    def product(self, q: Array, v: Array, scale: Array | float | None = None) -> HessianVector:
        """``grad^2 U(q) v`` row by row: analytic when the potential has it, else by
        :func:`fd_hessian_vector` with the length ``scale`` (default :meth:`scale_of`)."""
        q = np.asarray(q, dtype=float)
        v = np.asarray(v, dtype=float)
        zero = np.zeros(q.shape[0])
        if self.hessian_vector is not None:
            return HessianVector(np.asarray(self.hessian_vector(q, v), dtype=float), zero, zero)
        if self.hessian is not None:
            return HessianVector(np.einsum("mij,mj->mi", self.hessian(q), v), zero, zero)
        return fd_hessian_vector(self.gradient, q, v,
                                 self.scale_of(q) if scale is None else scale)

    def scale_of(self, q: Array) -> Array:
        """A length per configuration for difference steps: ``length`` when given, else
        :func:`probe_length` at the minimum (or 0), found once."""
        q = np.asarray(q, dtype=float)
        base = self.length
        if base is None:
            base = self.__dict__.get("_probed")
            if base is None:
                q0 = self.minimum if self.minimum is not None else np.zeros(self.dimension)
                base = probe_length(self.gradient, q0)
                self.__dict__["_probed"] = base  # (a cache: the instance stays frozen)
        return np.full(q.shape[0], float(base))

    def mass_weighted_hessian(self, q: Array) -> Array:
        """``W = M^-1/2 grad^2 U(q) M^-1/2`` of shape ``(m, n, n)`` from the analytic
        Hessian (symmetrised)."""
        if self.hessian is None:
            raise StepsafeError("this potential has no analytic Hessian")
        r = 1.0 / np.sqrt(self.masses)
        H = np.asarray(self.hessian(np.asarray(q, dtype=float)), dtype=float)
        W = H * r[None, :, None] * r[None, None, :]
        return 0.5 * (W + np.swapaxes(W, 1, 2))


def probe_length(gradient: Callable[[Array], Array], q0: Array) -> float:
    """A length over which U's curvature changes near ``q0``, for difference steps.

    Along a fixed direction u (seeded), ``d(e) = u . (g(q0 + e u) - g(q0))`` bends by
    ``r(e) = |d(2e) - 2 d(e)| / |2 d(e)|``: ``e / 2L`` for a cubic term of U on the length
    L, ``(e / L)^2`` for a quartic one. r is evaluated at ``e = 10^k`` (k = -300..300 in
    steps of 2, one batched call) from ``1e3 eps |q0|`` up (below, ``q0 + e u`` does not
    resolve e); in the longest run of steps with ``r <= 0.01`` (below it the rounding of g
    makes d jump, and short stretches there can look linear by chance) the end is refined
    in quarter decades and ``L = 20 e`` at the last e with ``r <= 0.01``. When d stays
    linear to the end of the range (a quadratic U) any step serves: the run's geometric
    middle; 1 when no e is linear."""
    q0 = np.asarray(q0, dtype=float).reshape(-1)
    n = q0.size
    u = np.random.default_rng(0).standard_normal(n)
    u /= np.linalg.norm(u)
    floor = 1e3 * EPS * float(np.max(np.abs(q0)))

    def bends(e: Array) -> tuple[Array, Array]:
        """``(r(e) <= 0.01, d(e) and d(2e) finite)``."""
        with np.errstate(all="ignore"):
            X = q0[None, :] + np.concatenate([e, 2 * e])[:, None] * u[None, :]
            g = np.asarray(gradient(np.concatenate([q0[None, :], X])), dtype=float) @ u
            d1, d2 = g[1:e.size + 1] - g[0], g[e.size + 1:] - g[0]
            finite = np.isfinite(d1) & np.isfinite(d2)
            return finite & (np.abs(d1) > 0) & (np.abs(d2 - 2 * d1) <= 0.02 * np.abs(d1)), \
                finite

    e = 10.0 ** np.arange(-300, 301, 2).astype(float)
    e = e[e >= floor]
    linear, finite = bends(e)
    if not linear.any():
        return 1.0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], linear.astype(int), [0]])))
    starts, ends = edges[::2], edges[1::2] - 1
    longest = int(np.argmax(ends - starts))
    first, end = int(starts[longest]), int(ends[longest])
    if end + 1 >= e.size or not finite[end + 1]:
        return float(np.sqrt(e[first]) * np.sqrt(e[end]))
    fine = e[end] * 10.0 ** (np.arange(1, 9) / 4.0)
    ok, _ = bends(fine)
    last = e[end] if not ok[0] else fine[int(np.argmin(ok)) - 1] if not ok.all() else fine[-1]
    return float(20.0 * last)


def fd_hessian_vector(gradient: Callable[[Array], Array], q: Array, v: Array,
                      scale: Array | float, rounding: float = GRADIENT_ROUNDING
                      ) -> HessianVector:
    """``grad^2 U(q) v`` by central differences of the gradient, with an error estimate.

    With ``u = v / |v|`` and ``D(e) = (g(q + e u) - g(q - e u)) / 2e``:
    ``D(e) = H u + e^2 t / 6 + O(e^4)`` (``t = g'''[u, u]``) plus rounding ``r / e``, where
    ``r = rounding * (|g|_inf + |D|_inf |q|_inf)`` stands for the gradient's absolute
    rounding (a gradient assembled from curvature times coordinates carries the rounding of
    those terms even where it is near 0). From the first step ``e1 = EPS^(1/3) scale`` the
    truncation ``|D(2 e1) - D(e1)| / 3`` estimates ``e1^2 |t| / 6``; where it is resolved
    above the rounding, the step moves to the optimum ``e = (r e1^2 / (2 trunc))^(1/3)``
    and both differences are taken again there. The error returned is the truncation
    estimate plus twice the rounding bound ``r / e``.

    Parameters
    ----------
    gradient : callable
        ``(k, n) -> (k, n)``.
    q, v : ndarray
        Configurations and directions, both ``(m, n)``.
    scale : float or ndarray
        A length typical of q (per row, or one for all).
    rounding : float
        The gradient's relative rounding.

    Returns
    -------
    HessianVector
        The products ``(m, n)``, their estimated absolute errors ``(m,)`` (max-norm) and the
        steps used ``(m,)``.
    """
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    m = q.shape[0]
    norm = np.linalg.norm(v, axis=1)
    safe = np.where(norm > 0, norm, 1.0)
    u = v / safe[:, None]
    e1 = EPS ** (1 / 3) * np.broadcast_to(np.asarray(scale, dtype=float), (m,))

    def differences(e: Array) -> tuple[Array, Array, Array]:
        d = e[:, None] * u
        g = np.asarray(gradient(np.concatenate([q + d, q - d, q + 2 * d, q - 2 * d])),
                       dtype=float)
        gp, gm, gp2, gm2 = np.split(g, 4)
        D1 = (gp - gm) / (2 * e[:, None])
        D2 = (gp2 - gm2) / (4 * e[:, None])
        size = np.max(np.abs(np.concatenate([gp, gm, gp2, gm2], axis=1)), axis=1)
        r = rounding * (size + np.max(np.abs(D1), axis=1) * np.max(np.abs(q), axis=1))
        return D1, np.max(np.abs(D2 - D1), axis=1) / 3.0, r

    D, trunc, r = differences(e1)
    e = e1
    with np.errstate(divide="ignore", invalid="ignore"):
        better = np.cbrt(r * e1 ** 2 / (2.0 * trunc))
    move = (trunc > r / e1) & np.isfinite(better) & (better < 0.5 * e1) & (better > 0)
    if move.any():
        e = np.where(move, better, e1)
        D2nd, trunc2, r2 = differences(e)
        D = np.where(move[:, None], D2nd, D)
        trunc = np.where(move, trunc2, trunc)
        r = np.where(move, r2, r)
    error = (trunc + 2.0 * r / e) * norm
    return HessianVector(D * norm[:, None], error, e)


def from_callables(energy: Callable[[Array], Array], gradient: Callable[[Array], Array],
                   masses, minimum=None, hessian=None, hessian_vector=None,
                   length: float | None = None, description: str = "") -> Potential:
    """A :class:`Potential` from plain functions, checked at the minimum (or at 0): shapes
    ``(m,)``, ``(m, n)``, ``(m, n, n)`` and finite values.

    Parameters
    ----------
    energy, gradient : callable
        ``U`` and ``grad U`` on rows ``(m, n)``.
    masses : array_like
        The n masses.
    minimum : array_like, optional
        A minimum ``q0`` of U.
    hessian, hessian_vector : callable, optional
        Analytic second derivatives.
    length : float, optional
        A typical length of the coordinates (for difference steps).
    description : str
        For reports.

    Returns
    -------
    Potential
    """
    pot = Potential(energy, gradient, masses, hessian, hessian_vector, minimum, False, length,
                    description)
    check_shapes(pot)
    return pot


def check_shapes(pot: Potential) -> None:
    """Evaluate U, its gradient and Hessian at ``q0`` (or 0) twice stacked: the shapes and
    finiteness the analysis relies on, else a :class:`StepsafeError`."""
    n = pot.dimension
    q0 = pot.minimum if pot.minimum is not None else np.zeros(n)
    q = np.stack([q0, q0])
    checks = [("energy", pot.energy(q), (2,)), ("gradient", pot.gradient(q), (2, n))]
    if pot.hessian is not None:
        checks.append(("hessian", pot.hessian(q), (2, n, n)))
    if pot.hessian_vector is not None:
        checks.append(("hessian_vector", pot.hessian_vector(q, q * 0 + 1), (2, n)))
    for name, value, shape in checks:
        value = np.asarray(value, dtype=float)
        if value.shape != shape:
            raise StepsafeError(f"the potential's {name} has shape {value.shape} on "
                                f"configurations of shape {q.shape}; expected {shape}")
        if not np.all(np.isfinite(value)):
            raise StepsafeError(f"the potential's {name} is not finite at "
                                f"{'the minimum' if pot.minimum is not None else 0}")


def quadratic(K, masses, minimum=None, energy_at_minimum: float = 0.0) -> Potential:
    """``U(q) = U0 + (q - q0)^T K (q - q0) / 2`` (K symmetric n x n).

    Parameters
    ----------
    K : array_like
        The stiffness (Hessian), symmetric.
    masses : array_like
        The n masses.
    minimum : array_like, optional
        ``q0`` (default 0).
    energy_at_minimum : float
        ``U0``.

    Returns
    -------
    Potential
        With ``quadratic=True`` and analytic Hessian.
    """
    K = np.asarray(K, dtype=float)
    n = K.shape[0]
    if K.shape != (n, n) or not np.all(np.isfinite(K)):
        raise StepsafeError(f"K must be a finite square matrix, got shape {K.shape}")
    if not np.allclose(K, K.T, rtol=1e-12, atol=0.0):
        raise StepsafeError("K must be symmetric")
    q0 = np.zeros(n) if minimum is None else np.asarray(minimum, dtype=float)
    U0 = float(energy_at_minimum)

    def energy(q: Array) -> Array:
        x = q - q0
        return U0 + 0.5 * np.einsum("mi,mi->m", x @ K, x)

    return Potential(energy=energy, gradient=lambda q: (q - q0) @ K,
                     masses=masses, hessian=lambda q: np.broadcast_to(K, (q.shape[0], n, n)),
                     minimum=q0, quadratic=True, description="quadratic")


def of_system(system: System, minimum=None, description: str = "") -> Potential:
    """The potential of a separable system ``H = p^T M^-1 p / 2 + U(q)`` with diagonal M.

    ``U(q) = H(q, 0)``, ``grad U(q) = dH/dq(q, 0)``, ``grad^2 U`` from the system's Hessian
    when it has one. The masses are read from ``dH/dp(q0, P)`` at ``P = I`` (the columns of
    ``M^-1``), which must be linear in P, symmetric, diagonal and positive; the kinetic
    energy must be ``H(q0, p) - H(q0, 0) = p^T M^-1 p / 2`` at a test momentum.

    Parameters
    ----------
    system : stepsafe.core.integrator.System
        A scene's equations of motion.
    minimum : array_like, optional
        A minimum ``q0`` of U (default 0 is only a probe point).
    description : str
        For reports.

    Returns
    -------
    Potential
    """
    if not system.separable:
        raise StepsafeError("the thermal analysis needs H = p^T M^-1 p / 2 + U(q); this H "
                            "mixes q and p")
    n = int(system.dimension)
    q0 = np.zeros(n) if minimum is None else np.asarray(minimum, dtype=float).reshape(-1)
    Q = np.broadcast_to(q0, (n, n)).copy()
    with np.errstate(all="ignore"):
        A = np.asarray(system.dH_dp(Q, np.eye(n)), dtype=float)
        A2 = np.asarray(system.dH_dp(Q, 2.0 * np.eye(n)), dtype=float)
    tol = 64 * EPS * max(float(np.max(np.abs(A))), np.finfo(float).tiny)
    if not (np.all(np.isfinite(A)) and np.all(np.abs(A2 - 2 * A) <= 2 * tol)
            and np.all(np.abs(A - A.T) <= tol)):
        raise StepsafeError("the kinetic energy is not p^T M^-1 p / 2 with a constant "
                            "symmetric M")
    off = A - np.diag(np.diag(A))
    if np.any(np.abs(off) > tol):
        raise StepsafeError("the thermal analysis needs a diagonal mass matrix; this one "
                            "couples the coordinates")
    inverse = np.diag(A)
    if not np.all(inverse > 0):
        raise StepsafeError("the masses must be positive")
    masses = 1.0 / inverse
    p = np.linspace(0.5, 1.5, n)[None, :] / np.sqrt(inverse)
    with np.errstate(all="ignore"):
        kinetic = float(system.energy(q0[None, :], p)[0] - system.energy(q0[None, :],
                                                                       0 * p)[0])
    expected = 0.5 * float(np.sum(p * p * inverse))
    if not abs(kinetic - expected) <= 1e-9 * expected:
        raise StepsafeError("the kinetic energy is not p^T M^-1 p / 2 with a constant M")

    def energy(q: Array) -> Array:
        return np.asarray(system.energy(q, np.zeros_like(q)), dtype=float)

    def gradient(q: Array) -> Array:
        return np.asarray(system.dH_dq(q, np.zeros_like(q)), dtype=float)

    hessian = None
    if system.hessian is not None:
        full = system.hessian

        def hessian(q: Array) -> Array:
            return np.asarray(full(q, np.zeros_like(q))[0], dtype=float)

    pot = Potential(energy, gradient, masses, hessian, None,
                    None if minimum is None else q0, False, None, description)
    check_shapes(pot)
    return pot


def system_of(pot: Potential) -> System:
    """The equations of motion ``q' = M^-1 p``, ``p' = -grad U(q)`` for
    :class:`stepsafe.core.integrator.Engine`."""
    inverse = 1.0 / pot.masses
    unit = bool(np.all(inverse == 1.0))  # (then M^-1 p is p itself: one pass fewer)

    def energy(q: Array, p: Array) -> Array:
        return pot.energy(q) + 0.5 * np.einsum("mi,mi->m", p if unit else p * inverse, p)

    hessian = None
    if pot.hessian is not None:
        full = pot.hessian
        n = pot.dimension

        def hessian(q: Array, p: Array) -> tuple[Array, ...]:
            m = q.shape[0]
            zero = np.zeros((m, n, n))
            return (np.asarray(full(q), dtype=float), zero,
                    np.broadcast_to(np.diag(inverse), (m, n, n)))

    return System(dH_dq=lambda q, p: pot.gradient(q),
                  dH_dp=(lambda q, p: p) if unit else (lambda q, p: p * inverse),
                  energy=energy, separable=True, dimension=pot.dimension, hessian=hessian)


def profile(pot: Potential, origin, direction, description: str = "") -> Potential:
    """The 1-D potential ``u(s) = U(q0 + s d)`` along a direction, with unit mass.

    ``d = M^-1/2 e`` for a unit vector e of the mass-weighted coordinates makes the kinetic
    energy ``s'^2 / 2``: pass ``direction = M^-1/2 e`` (see :func:`mode_direction`). Then
    ``u'(s) = d . grad U``, ``u''(s) = d^T grad^2 U d`` (analytic when U's Hessian is).

    Parameters
    ----------
    pot : Potential
    origin : array_like
        ``q0`` (n,).
    direction : array_like
        ``d`` (n,).
    description : str

    Returns
    -------
    Potential
        One coordinate s, mass 1, minimum 0 when ``q0`` is U's minimum.
    """
    q0 = np.asarray(origin, dtype=float).reshape(-1)
    d = np.asarray(direction, dtype=float).reshape(-1)

    def points(s: Array) -> Array:
        return q0[None, :] + np.asarray(s, dtype=float)[:, :1] * d[None, :]

    def energy(s: Array) -> Array:
        return pot.energy(points(s))

    def gradient(s: Array) -> Array:
        return (pot.gradient(points(s)) @ d)[:, None]

    hessian = None
    if pot.has_hessian:
        def hessian(s: Array) -> Array:
            x = points(s)
            Hd = pot.product(x, np.broadcast_to(d, x.shape)).value
            return (Hd @ d)[:, None, None]

    size = float(np.linalg.norm(d))
    if not (np.isfinite(size) and size > 0):
        raise StepsafeError("the profile's direction must be a finite nonzero vector")
    return Potential(energy, gradient, np.ones(1), hessian, None, np.zeros(1), False,
                     float(pot.scale_of(q0[None, :])[0]) / size, description or "1-D profile")


def mode_direction(pot: Potential, e) -> Array:
    """``M^-1/2 e`` for a mass-weighted direction e (normalised to |e| = 1)."""
    e = np.asarray(e, dtype=float).reshape(-1)
    return e / np.linalg.norm(e) / np.sqrt(pot.masses)


class Tabulated(NamedTuple):
    """A 1-D potential replaced by a cubic spline of its force on ``[lo, hi]``, with the
    largest deviation from the exact force found at the cell midpoints (absolute, and
    relative to the largest force on the table)."""

    potential: Potential
    lo: float
    hi: float
    error: float
    relative_error: float


def tabulate(pot: Potential, lo: float, hi: float, points: int = 20001) -> Tabulated:
    """A 1-D potential on ``[lo, hi]`` as a cubic spline of ``u'`` on a uniform grid of
    ``points`` (the energy as the spline's antiderivative, matched to ``u`` at 0 when the
    table holds 0, else at ``lo``), checked against the exact force at every cell midpoint.
    Outside ``[lo, hi]`` the force and energy are NaN: a trajectory that leaves the table is
    reported as failed by the callers.

    Iterating a method on the table costs a few array operations per step whatever the
    cost of U; the map differs from the exact one by at most ``error`` in the force.

    Parameters
    ----------
    pot : Potential
        One coordinate.
    lo, hi : float
        The table's range.
    points : int
        Grid points.

    Returns
    -------
    Tabulated
    """
    from scipy.interpolate import CubicSpline

    if pot.dimension != 1:
        raise StepsafeError("only a 1-D potential can be tabulated")
    s = np.linspace(lo, hi, points)
    f = pot.gradient(s[:, None])[:, 0]
    spline = CubicSpline(s, f)
    mid = 0.5 * (s[1:] + s[:-1])
    exact = pot.gradient(mid[:, None])[:, 0]
    error = float(np.max(np.abs(spline(mid) - exact)))
    scale = float(np.max(np.abs(f)))
    # the force's pieces c3 t^3 + c2 t^2 + c1 t + c0 (t from the cell's left node), the
    # energy's (the integral from lo) and the curvature's, evaluated on the uniform grid by
    # index arithmetic rather than a search
    c = spline.c  # (4, cells): c[0] t^3 + c[1] t^2 + c[2] t + c[3]
    width = float(s[1] - s[0])
    cells = c.shape[1]
    pieces = np.stack([c[0] / 4, c[1] / 3, c[2] / 2, c[3]])  # of the integral, over t^4..t
    ends = ((pieces[0] * width + pieces[1]) * width + pieces[2]) * width + pieces[3]
    start_energy = np.concatenate([[0.0], np.cumsum(ends * width)])[:-1]
    u_lo = float(pot.energy(np.array([[lo]]))[0])

    # the pieces' coefficients as contiguous rows, gathered with take (one call each)
    c0, c1, c2, c3 = (np.ascontiguousarray(c[j]) for j in range(4))
    e0, e1, e2, e3 = (np.ascontiguousarray(pieces[j]) for j in range(4))

    def locate(x: Array) -> tuple[Array, Array, Array | None]:
        """The cell i of each x, ``t = x - s_i``, and which x lie on the table (None: all;
        outside, x is taken at lo and its value replaced by NaN)."""
        x = np.asarray(x, dtype=float)[:, 0]
        inside = None
        if not (x.size and lo <= x.min() and x.max() <= hi):  # (a NaN fails both)
            with np.errstate(invalid="ignore"):
                inside = (x >= lo) & (x <= hi)
            x = np.where(inside, x, lo)
        i = ((x - lo) / width).astype(np.intp)
        np.minimum(i, cells - 1, out=i)
        return i, x - s.take(i), inside

    def horner(a: Array, b: Array, c_: Array, d: Array, i: Array, t: Array) -> Array:
        """``((a_i t + b_i) t + c_i) t + d_i``."""
        v = a.take(i)
        v *= t
        v += b.take(i)
        v *= t
        v += c_.take(i)
        v *= t
        v += d.take(i)
        return v

    def gradient(x: Array) -> Array:
        i, t, inside = locate(x)
        v = horner(c0, c1, c2, c3, i, t)
        return (v if inside is None else np.where(inside, v, np.nan))[:, None]

    def energy_from_lo(x: Array) -> Array:
        i, t, inside = locate(x)
        v = horner(e0, e1, e2, e3, i, t)
        v *= t
        w = start_energy.take(i)
        w += u_lo
        w += v
        return w if inside is None else np.where(inside, w, np.nan)

    def hessian(x: Array) -> Array:
        i, t, inside = locate(x)
        v = (3 * c0.take(i) * t + 2 * c1.take(i)) * t + c2.take(i)
        return (v if inside is None else np.where(inside, v, np.nan))[:, None, None]

    shift = 0.0
    if lo <= 0 <= hi:
        shift = float(pot.energy(np.zeros((1, 1)))[0]) - float(energy_from_lo(np.zeros((1, 1)))[0])

    def energy_shifted(x: Array) -> Array:
        return energy_from_lo(x) + shift

    table = Potential(energy_shifted, gradient, np.ones(1), hessian, None, pot.minimum, False,
                      pot.length, (pot.description or "1-D potential") + " (tabulated)")
    return Tabulated(table, float(lo), float(hi), error, error / scale if scale else 0.0)
