"""The target of HMC as a potential: ``U(q) = -log pi(q)`` (up to a constant) with its
gradient, and the mass matrix of the kinetic energy ``T(p) = p^T M^-1 p / 2``.

Conventions. Positions are arrays of shape ``(..., d)``: every function here is batched over
the leading axes, as the user's callables must be (a numpy function of ``q[..., j]``). The
momenta of HMC are drawn from ``N(0, M)``: ``p = C z`` with ``M = C C^T`` (Cholesky) and
``z ~ N(0, I)``. The local frequencies of the target at q are ``omega_k = sqrt(lambda_k)``
for the eigenvalues ``lambda_k`` of the mass-weighted Hessian
``W = M^-1/2 nabla^2 U(q) M^-1/2``, computed as the similar ``C^-1 nabla^2 U C^-T`` (the
same eigenvalues as ``M^-1 nabla^2 U``).

Anything with ``dimension``, ``energy(q)`` and ``gradient(q)`` (shapes ``(..., d) ->
(...)`` and ``(..., d) -> (..., d)``) is a :class:`Potential`; ``hessian(q)`` (``(..., d,
d)``) and ``hvp(q, v)`` (``(..., d)``) are used where present, else the Hessian is taken
by central differences of the gradient (:func:`hessian_vector`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from stepsafe.exceptions import StepsafeError


@runtime_checkable
class Potential(Protocol):
    """``U(q) = -log pi(q)`` and its gradient, batched over leading axes."""

    @property
    def dimension(self) -> int: ...

    def energy(self, q: np.ndarray) -> np.ndarray: ...

    def gradient(self, q: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class CallablePotential:
    """A :class:`Potential` from numpy callables.

    Parameters
    ----------
    energy_fn, gradient_fn
        ``U(q)`` and ``grad U(q)`` on arrays of shape ``(..., d)``.
    dimension
        d.
    hessian, hvp
        Optional ``nabla^2 U(q)`` (``(..., d, d)``) and Hessian-vector product
        ``nabla^2 U(q) v`` (``(..., d)``).
    """

    energy_fn: Callable[[np.ndarray], np.ndarray]
    gradient_fn: Callable[[np.ndarray], np.ndarray]
    dimension: int
    #: ``nabla^2 U(q)``, shape ``(..., d, d)``, or None
    hessian: Callable[[np.ndarray], np.ndarray] | None = None
    #: ``nabla^2 U(q) v``, shape ``(..., d)``, or None
    hvp: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None

    def energy(self, q: np.ndarray) -> np.ndarray:
        return np.asarray(self.energy_fn(q), dtype=float)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return np.asarray(self.gradient_fn(q), dtype=float)


class Guarded:
    """A user's potential (numpy or JAX callables) with their failures and wrong shapes
    turned into a :class:`StepsafeError` naming the keyword (never a traceback): ``names``
    are the keywords of the energy's and the gradient's functions."""

    def __init__(self, inner: CallablePotential, names: tuple[str, str]) -> None:
        self.inner, self.names = inner, names
        self.dimension = inner.dimension
        hessian, hvp = getattr(inner, "hessian", None), getattr(inner, "hvp", None)
        d = self.dimension
        self.hessian = None if hessian is None else (
            lambda q: self._call(hessian, q, names[1], q.shape + (d,)))
        self.hvp = None if hvp is None else (
            lambda q, v: self._call(lambda x: hvp(x, v), q, names[1], q.shape))

    def _call(self, fn: Callable[[np.ndarray], np.ndarray], q: np.ndarray, key: str,
              shape: tuple[int, ...]) -> np.ndarray:
        try:
            out = np.asarray(fn(q), dtype=float)
        except StepsafeError:
            raise
        except Exception as exc:  # the user's code: reported, not a crash
            raise StepsafeError(f"{key} raised {type(exc).__name__}: {str(exc)[:120]}",
                                key) from None
        if out.shape != shape:
            raise StepsafeError(f"{key} returned shape {out.shape} for positions of shape "
                                f"{q.shape}; expected {shape} (batched over leading axes)",
                                key)
        return out

    def energy(self, q: np.ndarray) -> np.ndarray:
        return self._call(self.inner.energy, q, self.names[0], q.shape[:-1])

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return self._call(self.inner.gradient, q, self.names[1], q.shape)


def from_logdensity(logdensity: Callable[[np.ndarray], np.ndarray],
                    gradient: Callable[[np.ndarray], np.ndarray], dimension: int,
                    hessian: Callable[[np.ndarray], np.ndarray] | None = None
                    ) -> CallablePotential:
    """The potential ``U = -log pi`` of a log-density and its gradient (numpy callables
    batched over leading axes; ``hessian`` optional, of ``log pi``).

    Parameters
    ----------
    logdensity, gradient
        ``log pi(q)`` and ``grad log pi(q)``, q of shape ``(..., d)``.
    dimension
        d, an integer >= 1.
    hessian
        Optional ``nabla^2 log pi(q)`` of shape ``(..., d, d)``.

    Returns
    -------
    CallablePotential
        ``U = -log pi``, ``grad U = -grad log pi``.
    """
    d = _dimension(dimension)
    return CallablePotential(lambda q: -np.asarray(logdensity(q), dtype=float),
                             lambda q: -np.asarray(gradient(q), dtype=float), d,
                             None if hessian is None else
                             (lambda q: -np.asarray(hessian(q), dtype=float)))


def _dimension(d: Any) -> int:
    if isinstance(d, bool) or not isinstance(d, (int, np.integer)) or not 1 <= d <= 10**7:
        raise StepsafeError(f"dimension must be an integer from 1 to 10^7, got {d!r}")
    return int(d)


@dataclass(frozen=True)
class Mass:
    """The mass matrix M of ``T(p) = p^T M^-1 p / 2``: diagonal (``matrix`` of shape (d,))
    or dense ((d, d), symmetric positive definite); ``factor`` is C with ``M = C C^T``
    (lower Cholesky; the square root of the diagonal)."""

    matrix: np.ndarray
    factor: np.ndarray = field(repr=False)

    @property
    def diagonal(self) -> bool:
        return self.matrix.ndim == 1

    @property
    def dimension(self) -> int:
        return int(self.matrix.shape[0])

    def velocity(self, p: np.ndarray) -> np.ndarray:
        """``M^-1 p`` (rows of p: momenta); a non-finite row gives a non-finite row (a
        diverging trajectory, frozen by its integrator), not an error."""
        if self.diagonal:
            return p / self.matrix
        import scipy.linalg as sl

        flat = p.reshape(-1, self.dimension).T
        out = sl.cho_solve((self.factor, True), flat, check_finite=False)
        return out.T.reshape(p.shape)

    def kinetic(self, p: np.ndarray) -> np.ndarray:
        """``p^T M^-1 p / 2``."""
        return 0.5 * np.einsum("...i,...i->...", p, self.velocity(p))

    def momenta(self, z: np.ndarray) -> np.ndarray:
        """``p = C z``: from standard normals z, momenta distributed as ``N(0, M)``."""
        if self.diagonal:
            return z * self.factor
        return z @ self.factor.T

    def weighted(self, hessian: np.ndarray) -> np.ndarray:
        """``C^-1 H C^-T`` (batched over leading axes): similar to ``M^-1 H``, symmetric
        when H is."""
        if self.diagonal:
            s = 1.0 / self.factor
            return hessian * s[:, None] * s[None, :]
        import scipy.linalg as sl

        d = self.dimension
        inv = sl.solve_triangular(self.factor, np.eye(d), lower=True)
        return inv @ hessian @ inv.T

    def weigh_vector(self, v: np.ndarray) -> np.ndarray:
        """``C^-T v``: the direction in q whose Hessian product, premultiplied by ``C^-1``,
        is ``W v`` (``W = C^-1 H C^-T``)."""
        if self.diagonal:
            return v / self.factor
        import scipy.linalg as sl

        flat = v.reshape(-1, self.dimension).T
        return sl.solve_triangular(self.factor.T, flat, lower=False,
                                   check_finite=False).T.reshape(v.shape)

    def whiten(self, q: np.ndarray) -> np.ndarray:
        """``C^T q``: positions in the coordinates where the mass is the identity (the
        Hessian there is ``C^-1 H C^-T``)."""
        if self.diagonal:
            return q * self.factor
        return q @ self.factor

    def unweigh_gradient(self, g: np.ndarray) -> np.ndarray:
        """``C^-1 g``."""
        if self.diagonal:
            return g / self.factor
        import scipy.linalg as sl

        flat = g.reshape(-1, self.dimension).T
        return sl.solve_triangular(self.factor, flat, lower=True,
                                   check_finite=False).T.reshape(g.shape)


def mass_matrix(mass: Any, dimension: int, where: str = "mass") -> Mass:
    """A :class:`Mass` from None (unit masses), a scalar, a vector of d positive masses or a
    symmetric positive definite d x d matrix; a :class:`StepsafeError` naming ``where``
    otherwise."""
    d = _dimension(dimension)
    if mass is None:
        arr = np.ones(d)
    else:
        try:
            arr = np.array(mass, dtype=float)
        except (TypeError, ValueError):
            raise StepsafeError("the mass must be a number, a vector of d masses or a d x d "
                                "matrix", where) from None
        if arr.ndim == 0:
            arr = np.full(d, float(arr))
    if not np.isfinite(arr).all():
        raise StepsafeError("the mass has a non-finite entry", where)
    if arr.shape == (d,):
        if not (arr > 0).all():
            raise StepsafeError("every mass must be positive", where)
        return Mass(arr, np.sqrt(arr))
    if arr.shape != (d, d):
        raise StepsafeError(f"the mass must have shape ({d},) or ({d}, {d}) for a target of "
                            f"dimension {d}, got {arr.shape}", where)
    scale = float(np.abs(arr).max())
    if not np.allclose(arr, arr.T, rtol=0.0, atol=8 * np.finfo(float).eps * scale):
        raise StepsafeError("the mass matrix must be symmetric", where)
    arr = 0.5 * (arr + arr.T)
    try:
        factor = np.linalg.cholesky(arr)
    except np.linalg.LinAlgError:
        raise StepsafeError("the mass matrix must be positive definite", where) from None
    return Mass(arr, factor)


@dataclass(frozen=True)
class Target:
    """A potential with the mass matrix HMC runs it with."""

    potential: Potential
    mass: Mass

    @property
    def dimension(self) -> int:
        return int(self.potential.dimension)

    def hamiltonian(self, q: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``H = U(q) + p^T M^-1 p / 2``."""
        return self.potential.energy(q) + self.mass.kinetic(p)


def target(potential: Potential, mass: Any = None, where: str = "mass") -> Target:
    """A :class:`Target` from a potential and a mass (see :func:`mass_matrix`).

    Parameters
    ----------
    potential
        A :class:`Potential`.
    mass
        None (unit masses), a scalar, d masses or a d x d SPD matrix.
    where
        Names the mass in errors.

    Returns
    -------
    Target
    """
    if not isinstance(potential, Potential):
        raise StepsafeError("the target needs dimension, energy(q) and gradient(q)")
    return Target(potential, mass_matrix(mass, potential.dimension, where))


#: Central differences of the gradient take ``e = FD_STEP * scale`` (the cube root of
#: float64's epsilon balances the truncation error e^2 U''' against rounding eps_64 / e).
FD_STEP = float(np.cbrt(np.finfo(float).eps))


def hessian_vector(potential: Potential, q: np.ndarray, v: np.ndarray,
                   scale: float | np.ndarray = 1.0) -> np.ndarray:
    """``nabla^2 U(q) v`` (batched): the potential's ``hvp`` if it has one, else
    ``(grad U(q + e v) - grad U(q - e v)) / 2e`` with ``e |v|`` equal to ``FD_STEP`` times
    the length over which U's curvature changes along v, ``|s * v| / |v|`` for the
    per-coordinate lengths ``scale`` (the spread of the draws along each axis)."""
    hvp = getattr(potential, "hvp", None)
    if hvp is not None:
        return np.asarray(hvp(q, v), dtype=float)
    s = np.broadcast_to(np.asarray(scale, dtype=float), v.shape[-1:])
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    norm = np.where(norm > 0, norm, 1.0)
    length = np.linalg.norm(v * s, axis=-1, keepdims=True) / norm
    e = FD_STEP * length / norm
    return (potential.gradient(q + e * v) - potential.gradient(q - e * v)) / (2.0 * e)


def hessian_matrix(potential: Potential, q: np.ndarray,
                   scale: float | np.ndarray = 1.0) -> np.ndarray:
    """``nabla^2 U(q)`` of shape ``(..., d, d)``: the potential's ``hessian`` if it has one,
    else central differences of the gradient along each axis j with step
    ``FD_STEP * scale_j`` (``scale``: a length per coordinate, or one for all), in one
    batched call each way, symmetrised."""
    hessian = getattr(potential, "hessian", None)
    if hessian is not None:
        return np.asarray(hessian(q), dtype=float)
    d = q.shape[-1]
    e = FD_STEP * np.broadcast_to(np.asarray(scale, dtype=float), (d,))
    shifts = np.diag(e)
    plus = potential.gradient(q[..., None, :] + shifts)  # (..., d, d): row j at q + e_j
    minus = potential.gradient(q[..., None, :] - shifts)
    H = (plus - minus) / (2.0 * e[:, None])
    return 0.5 * (H + np.swapaxes(H, -1, -2))
