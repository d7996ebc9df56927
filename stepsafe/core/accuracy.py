"""What a step buys: phase, energy and growth-rate errors of M(z), and their inverse.

Oscillator (DESIGN §3). A symplectic elliptic ``M = [[a, b], [c, d]]`` is conjugate to a
rotation by ``theta`` with ``cos theta = tr M / 2`` and ``sin theta = sqrt(-bc - (a-d)^2/4)``
(no cancellation: ``-bc ~ z^2``). The flow rotates by ``z``, so

* phase error ``e_phase = theta / z - 1``;
* energy error: orbits of M lie on the invariant ellipse ``x^T S x = const`` with
  ``S = [[-c, (a-d)/2], [(a-d)/2, b]]`` (``M^T S M = S``); the exact energy ``|x|^2 / 2``
  varies along it by the ratio of the eigenvalues of S, so ``e_energy = kappa(S) - 1``
  bounds the relative energy error (approached from the lowest-energy point of the ellipse
  when theta / 2 pi is irrational; a rotation by a rational part of a turn visits finitely
  many points and can stay below it).

Hyperbolic models: the flow grows by ``e^z`` per step, M by ``mu = tr/2 + sqrt(tr^2/4 - 1)``,
so ``e_rate = log(mu) / z - 1``.

Small z. ``theta - z`` can be 1e-30 while ``tr M / 2 - 1 ~ -z^2/2``: subtracting is hopeless.
Instead ``delta(z) = tr M / 2 - cos z`` (or ``- cosh z``) is summed from the Taylor series of
M, ``M = I + sum_k z^(k+1) B K^k E`` (the stage operator of :mod:`stepsafe.core.transfer`; for
explicit methods K is nilpotent and the series is the exact polynomial). Coefficients that
cancel to rounding are set to zero (their error bound is tracked with absolute values), and
the identity ``cos theta - cos z = -2 sin((theta+z)/2) sin((theta-z)/2)`` (``cosh`` alike)
turns ``delta`` into ``theta - z`` with full relative accuracy. The series is used where it is
valid (always for explicit methods, whose series is the exact polynomial; within half its
radius of convergence otherwise) and its rounding bound beats the direct formula's, which
loses ~1e-16 / |e| relative. Coefficients that vanish to rounding are taken as exactly zero:
for methods given by rounded decimals, whose order conditions hold only to ~1e-17, this is
the error of the ideal method (it differs from the decimals' own by ~1e-17 / z^2 absolute).

The inverse problem (largest z meeting a tolerance) is the first crossing of ``|e| = tol``
from 0, never beyond the first boundary.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from stepsafe.core.models import ELLIPTIC
from stepsafe.core.roots import EPS, refine_brackets
from stepsafe.core.transfer import stage_operator, transfer_matrix
from stepsafe.methods.tableaux import (
    Composition,
    Method,
    PartitionedRK,
    Processed,
    RungeKutta,
    Splitting,
)

SERIES_TERMS = 64
SERIES_Z = 0.5


class Errors(NamedTuple):
    """Error figures at each z (NaN where the type is not the flow's)."""

    z: np.ndarray
    phase: np.ndarray  # oscillator: theta/z - 1; hyperbolic: log(mu)/z - 1
    energy: np.ndarray  # oscillator only: kappa(S) - 1 (NaN for hyperbolic models)


class Series(NamedTuple):
    """Taylor coefficients ``M_k`` of M(z) (shape (terms+1, 2, 2)), the same series with
    absolute values (the rounding bound, times EPS), and the largest z where the truncated
    series is trusted (inf when it is an exact polynomial)."""

    coef: np.ndarray
    coef_abs: np.ndarray
    z_valid: float


def _polynomial_series(method: Splitting, model: str, terms: int) -> Series:
    """A force-gradient splitting (no PRK form) on the oscillator or the barrier top: M(z)
    is the exact matrix polynomial ``prod (I + c z^k e_dst e_src^T)`` of
    :func:`stepsafe.core.transfer.row_ops`, expanded (with absolute values alongside) and
    cut at ``terms``; it has no saddle form (a MethodError, as for the region)."""
    from stepsafe.core.transfer import row_ops

    if model not in ("oscillator", "inverted"):
        method.euler_factors()  # raises: no saddle form
    ops = row_ops(method, model)
    degree = max(terms, sum(k for _, _, _, k in ops))
    P = np.zeros((degree + 1, 2, 2))
    P[0] = np.eye(2)
    A = P.copy()
    for src, dst, c, k in ops:
        P[k:, dst, :] += c * P[:-k, src, :]
        A[k:, dst, :] += abs(c) * A[:-k, src, :]
    A = A * (4.0 * (len(ops) + 1))  # each coefficient's rounding, in units of EPS
    exact = not P[terms + 1:].any()  # higher powers are all zero: the series is M itself
    return Series(P[:terms + 1].copy(), A[:terms + 1].copy(), np.inf if exact else 0.0)


def taylor_series(method: Method, model: str, terms: int = SERIES_TERMS) -> Series:
    """The :class:`Series` of M(z): ``M = I + sum_k z^(k+1) B K^k E``."""
    if isinstance(method, Processed):  # the full one-step map P^-1 K P (the kernel's on
        # the diagonal saddle models, where P commutes with K)
        diagonal = model in ("saddle", "saddle-p")
        return taylor_series(method.kernel_splitting if diagonal else method.per_step(),
                             model, terms)
    if isinstance(method, Composition):
        flat = method.flattened()
        if isinstance(flat.base, Splitting):
            return taylor_series(flat.as_splitting(), model, terms)
        base, base_abs, base_valid = taylor_series(flat.base, model, terms)
        out = np.zeros_like(base)
        out[0] = np.eye(2)
        out_abs = out.copy()
        powers = np.arange(terms + 1)
        for g in flat.weights:
            scaled = base * (g ** powers)[:, None, None]
            scaled_abs = base_abs * (abs(g) ** powers)[:, None, None]
            out, out_abs = _series_product(scaled, out), _series_product(scaled_abs, out_abs)
        return Series(out, out_abs, base_valid / float(np.abs(flat.weights).max()))
    if isinstance(method, Splitting) and method.force_gradient:
        return _polynomial_series(method, model, terms)
    prk = method.as_prk() if isinstance(method, (RungeKutta, Splitting)) else method
    assert isinstance(prk, PartitionedRK)
    K, E, B = stage_operator(prk, model)
    out = np.zeros((terms + 1, 2, 2))
    out_abs = np.zeros((terms + 1, 2, 2))
    out[0] = out_abs[0] = np.eye(2)
    X, X_abs = E.copy(), E.copy()
    for k in range(terms):
        out[k + 1] = B @ X
        out_abs[k + 1] = np.abs(B) @ X_abs
        X, X_abs = K @ X, np.abs(K) @ X_abs
        if not X.any():  # K is nilpotent on E: the series is the exact polynomial
            return Series(out, out_abs, np.inf)
    rho = float(np.abs(np.linalg.eigvals(K)).max())
    return Series(out, out_abs, 0.5 / rho if rho > 0 else np.inf)


def _series_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Truncated product of matrix-valued series (a after b)."""
    n = a.shape[0]
    out = np.zeros_like(a)
    for k in range(n):
        out[k] = np.einsum("jab,jbc->ac", a[: k + 1], b[k::-1])
    return out


def _trim(value: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero the coefficients that vanish to rounding; return them with their bounds."""
    k = np.arange(value.size)
    tol = 64 * EPS * bound * (k + 1)
    return np.where(np.abs(value) <= tol, 0.0, value), tol


def _delta_series(method: Method, model: str):
    """Coefficients of ``tr M / 2 - cos z`` (oscillator) or ``- cosh z`` (hyperbolic), their
    rounding bounds and the series' range of validity."""
    series = taylor_series(method, model)
    half_trace = 0.5 * (series.coef[:, 0, 0] + series.coef[:, 1, 1])
    bound = 0.5 * (series.coef_abs[:, 0, 0] + series.coef_abs[:, 1, 1])
    k = np.arange(half_trace.size)
    fact = np.array([math.factorial(int(j)) for j in k], dtype=float)
    ref = np.where(k % 2 == 0, 1.0 / fact, 0.0)
    if ELLIPTIC[model]:
        ref = ref * np.where(k % 4 == 2, -1.0, 1.0)
    coef, tol = _trim(half_trace - ref, bound + np.abs(ref))
    return coef, tol, series.z_valid


def _choose(coef, tol, z_valid, z, direct, direct_err):
    """Series value where it is valid and its rounding bound beats the direct formula's."""
    series_val = _horner(coef, z)
    # coefficients trimmed to zero are exactly zero for the ideal method: no error from them;
    # the kept ones carry about eps times their absolute-value series (tol / (64 (k+1)))
    k = np.arange(coef.size)
    kept_tol = np.where(coef != 0, tol / (64.0 * (k + 1)), 0.0)
    series_err = _horner(kept_tol, np.abs(z)) + EPS * _horner(np.abs(coef), np.abs(z))
    use = (z <= z_valid) & ((series_err <= direct_err) | (z <= SERIES_Z))
    return np.where(use, series_val, direct)


def _horner(coef: np.ndarray, z: np.ndarray) -> np.ndarray:
    out = np.zeros_like(z)
    for c in coef[::-1]:
        out = out * z + c
    return out


def errors(method: Method, z, model: str = "oscillator") -> Errors:
    """Phase (or growth-rate) and energy errors at each z (see the module docstring).

    A processed method ``P^-1 K P`` has its kernel's phase (growth-rate) error, a function
    of the trace, which conjugation keeps (taken from the kernel: fewer roundings), and the
    energy error of its own invariant ellipse, that of the full one-step map: the states
    it outputs, ``P^-1 K^n P x``, lie on that ellipse. :func:`kernel_errors` gives the
    kernel's own."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    if isinstance(method, Processed):
        full = errors(method.per_step(), z, model)
        return Errors(z, errors(method.kernel_splitting, z, model).phase, full.energy)
    M = transfer_matrix(method, z, model)
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    half_tr = 0.5 * (a + d)
    direct_err = 4 * EPS * (np.abs(M).sum(axis=(1, 2)) + 1.0)
    coef, tol, z_valid = _delta_series(method, model)
    # sin^2(theta) = 1 - (tr/2)^2 = -bc - (a-d)^2/4 when det M = 1: no cancellation
    sin2 = -b * c - 0.25 * (a - d) ** 2
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if ELLIPTIC[model]:
            delta = _choose(coef, tol, z_valid, z, half_tr - np.cos(z), direct_err)
            theta = np.arctan2(np.sqrt(sin2), half_tr)
            # cos(theta) - cos(z) = -2 sin((theta+z)/2) sin((theta-z)/2)
            ratio = -delta / (2.0 * np.sin(0.5 * (theta + z)))
            diff = np.where(np.abs(ratio) <= 1, 2.0 * np.arcsin(ratio), theta - z)
            ok = (sin2 > 0) & (b > 0)
            phase = np.where(ok, diff / z, np.nan)
            # kappa - 1 = (l1 - l2) / l2, l1 - l2 = sqrt((s11 - s22)^2 + 4 s12^2) with
            # s11 - s22 = -(b + c) and s12 = (a - d)/2, both vanishing like powers of z
            b_plus_c, a_minus_d = _offsets(method, model, z, M, direct_err)
            spread = np.sqrt(b_plus_c ** 2 + a_minus_d ** 2)
            lower = 0.5 * (b - c - spread)
            energy = np.where(ok, spread / lower, np.nan)
        else:
            delta = _choose(coef, tol, z_valid, z, half_tr - np.cosh(z), direct_err)
            # mu - 1 = (tr/2 - 1) + sqrt(tr^2/4 - 1), both parts without cancellation
            mu_minus_1 = delta + 2.0 * np.sinh(0.5 * z) ** 2 + np.sqrt(np.maximum(-sin2, 0.0))
            lam = np.log1p(mu_minus_1)
            diff = 2.0 * np.arcsinh(delta / (2.0 * np.sinh(0.5 * (lam + z))))
            phase = np.where((sin2 < 0) & (half_tr > 0), diff / z, np.nan)
            energy = np.full(z.shape, np.nan)
    return Errors(z, phase, energy)


def kernel_errors(method: Method, z, model: str = "oscillator") -> Errors | None:
    """The errors of a processed method's kernel run alone (its outputs taken without
    P^-1), None for any other method: the processor leaves the phase error as it is and
    changes the energy error (:func:`errors`)."""
    if not isinstance(method, Processed):
        return None
    return errors(method.kernel_splitting, z, model)


class Offsets(NamedTuple):
    """The one-step matrix ``M = [[a, b], [c, d]]`` of the oscillator at each z with
    ``b + c`` and ``a - d`` (both vanish like powers of z; summed from the Taylor series
    where that is the more accurate) and ``sin2 = 1 - (tr M / 2)^2 = -bc - (a - d)^2 / 4``
    (no cancellation; negative where M is hyperbolic)."""

    M: np.ndarray
    b_plus_c: np.ndarray
    a_minus_d: np.ndarray
    sin2: np.ndarray


def offsets(method: Method, z) -> Offsets:
    """:class:`Offsets` of the oscillator at each z (overflow gives inf or NaN entries)."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    M = transfer_matrix(method, z, "oscillator")
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    with np.errstate(invalid="ignore", over="ignore"):
        direct_err = 4 * EPS * (np.abs(M).sum(axis=(1, 2)) + 1.0)
        b_plus_c, a_minus_d = _offsets(method, "oscillator", z, M, direct_err)
        return Offsets(M, b_plus_c, a_minus_d, -b * c - 0.25 * (a - d) ** 2)


def _offsets(method: Method, model: str, z: np.ndarray, M: np.ndarray,
             direct_err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    (bc_coef, bc_tol), (ad_coef, ad_tol), z_valid = _offset_series(method, model)
    return (_choose(bc_coef, bc_tol, z_valid, z, M[:, 0, 1] + M[:, 1, 0], direct_err),
            _choose(ad_coef, ad_tol, z_valid, z, M[:, 0, 0] - M[:, 1, 1], direct_err))


def _offset_series(method: Method, model: str):
    """Coefficients (with rounding bounds) of ``b + c = M_qp + M_pq`` and ``a - d =
    M_qq - M_pp``, which vanish like powers of z on the oscillator."""
    series = taylor_series(method, model)
    c, a = series.coef, series.coef_abs
    bc = _trim(c[:, 0, 1] + c[:, 1, 0], a[:, 0, 1] + a[:, 1, 0])
    ad = _trim(c[:, 0, 0] - c[:, 1, 1], a[:, 0, 0] + a[:, 1, 1])
    return bc, ad, series.z_valid


class ToleranceStep(NamedTuple):
    z: float | None  # largest z meeting the tolerance (None: none does)
    limited_by: str  # "tolerance", "boundary" (met up to z*), or "unreachable"


def z_for_tolerance(method: Method, tol: float, z_star: float, model: str = "oscillator",
                    kind: str = "phase", samples: int = 400) -> ToleranceStep:
    """The first z in (0, z*) where ``|error| = tol``; z* itself if the tolerance holds up to
    the boundary. ``kind`` is ``phase`` or ``energy``."""
    if not (tol > 0 and math.isfinite(tol)):
        raise ValueError("the tolerance must be a positive finite number")
    if z_star <= 0:
        return ToleranceStep(None, "unreachable")

    def excess(zz):
        e = errors(method, zz, model)
        return np.abs(e.phase if kind == "phase" else e.energy) - tol

    z = np.geomspace(z_star * 1e-6, z_star * (1 - 1e-9), samples)
    f = excess(z)
    f = np.where(np.isnan(f), np.inf, f)
    if f[0] > 0:
        # the error is already above tol at z*/1e6: shrink toward 0 geometrically
        tiny = np.geomspace(z_star * 1e-12, z_star * 1e-6, 60)
        g = excess(tiny)
        g = np.where(np.isnan(g), np.inf, g)
        if g[0] > 0:
            return ToleranceStep(None, "unreachable")
        z, f = np.concatenate([tiny, z]), np.concatenate([g, f])
    over = np.flatnonzero(f > 0)
    if over.size == 0:
        return ToleranceStep(float(z_star), "boundary")
    i = int(over[0])
    if i == 0:
        return ToleranceStep(None, "unreachable")
    root = refine_brackets(excess, z[i - 1:i], z[i:i + 1], f[i - 1:i],
                           np.minimum(f[i:i + 1], 1e300))
    return ToleranceStep(float(root[0]), "tolerance")
