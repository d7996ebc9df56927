"""What a step buys: phase, energy and growth-rate errors of M(z), and their inverse.

Oscillator (docs/theory.md#accuracy-and-cost). A symplectic elliptic
``M = [[a, b], [c, d]]`` is conjugate to a rotation by ``theta`` with ``cos theta = tr M / 2``
and ``sin theta = sqrt(-bc - (a-d)^2/4)`` (no cancellation: ``-bc ~ z^2``). The flow rotates
by ``z``, so

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
loses ~1e-16 / |e| relative. Coefficients that vanish to rounding before the first that does
not are the order conditions, taken as exactly zero: for methods given by rounded decimals,
whose order conditions hold only to ~1e-17, this is the error of the ideal method (it
differs from the decimals' own by ~1e-17 / z^2 absolute). Later ones keep their rounding
bound; implicit (P)RK methods get theirs at high precision from their definition
(:func:`_hp_parts`). Every figure carries a float64 bound and is recomputed from the
high-precision transfer matrix where that bound exceeds :data:`RECOMPUTE_REL` of it.

The inverse problem (largest z meeting a tolerance) is the first crossing of ``|e| = tol``
from 0, never beyond the first boundary.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from stepsafe.core.engine import leaf_key
from stepsafe.core.escalate import DPS, MP_WORK_BUDGET, reference_of
from stepsafe.core.models import ELLIPTIC, GENERATORS
from stepsafe.core.roots import EPS, refine_brackets
from stepsafe.core.transfer import blocks_of, row_ops, stage_operator, transfer_matrix
from stepsafe.exceptions import StepsafeError
from stepsafe.lazy import lazy_module
from stepsafe.methods.protocol import Block, Friction, Shears
from stepsafe.methods.tableaux import Method, PartitionedRK, Splitting

if TYPE_CHECKING:
    from stepsafe.methods import exact
else:  # figures float64 cannot give to the printed digits
    exact = lazy_module("stepsafe.methods.exact")

SERIES_TERMS = 64
SERIES_Z = 0.5
#: A figure whose float64 error bound exceeds this (relative) is recomputed from the
#: method's high-precision transfer matrix (the printed 7 digits need < 5e-8).
RECOMPUTE_REL = 1e-9
#: Implicit (P)RK methods up to this many stages get their Taylor coefficients at high
#: precision from their definition (the family tableau at raised precision); larger ones
#: keep the float64 series, whose tiny coefficients carry their rounding bound.
HP_MAX_STAGES = 20


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
    """The :class:`Series` of M(z): ``M = I + sum_k z^(k+1) B K^k E``, over the blocks of
    the step (:func:`stepsafe.core.transfer.blocks_of`): the product of the blocks' series,
    each scaled to its weight."""
    blocks = blocks_of(method, model)
    if len(blocks) == 1 and blocks[0].weight == 1.0:
        return _block_series(blocks[0], model, terms)
    out = np.zeros((terms + 1, 2, 2))
    out[0] = np.eye(2)
    out_abs = out.copy()
    powers = np.arange(terms + 1)
    series: dict[tuple, Series] = {}
    z_valid = np.inf
    for b in blocks:
        leaf = leaf_key(b)
        if leaf not in series:
            from dataclasses import replace

            series[leaf] = _block_series(replace(b, weight=1.0), model, terms)
        base, base_abs, base_valid = series[leaf]
        g = b.weight
        scaled = base * (g ** powers)[:, None, None]
        scaled_abs = base_abs * (abs(g) ** powers)[:, None, None]
        out, out_abs = _series_product(scaled, out), _series_product(scaled_abs, out_abs)
        z_valid = min(z_valid, base_valid / abs(g))
    return Series(out, out_abs, z_valid)


def _friction_series(block: Friction, terms: int) -> Series:
    """``diag(1, exp(-k z))``, ``k = gamma w``: the coefficients ``(-k)^j / j!`` (an entire
    function: trusted where the terms left off are negligible, taken as ``|k z| <= 1``)."""
    k = block.gamma * block.weight
    out = np.zeros((terms + 1, 2, 2))
    out[0] = np.eye(2)
    term = 1.0
    for j in range(1, terms + 1):
        term = term * (-k) / j
        out[j, 1, 1] = term
    return Series(out, np.abs(out), 1.0 / k if k > 0 else np.inf)


def _block_series(block: Block, model: str, terms: int) -> Series:
    """The :class:`Series` of one block at weight 1."""
    if isinstance(block, Friction):
        return _friction_series(block, terms)
    if isinstance(block, Shears) and block.splitting.force_gradient:
        return _polynomial_series(block.splitting, model, terms)
    K, E, B = stage_operator(block.splitting.as_prk() if isinstance(block, Shears)
                             else block.method, model)
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
    """Zero the coefficients that vanish to rounding; return the values and each one's error
    bound. Those below rounding before the first that is not are the order conditions,
    exactly zero for the ideal method (error 0); a later one below rounding may be a
    genuinely tiny term (an implicit method's series has infinitely many) and keeps its
    rounding bound; a kept one carries ``(k + 1) eps`` times its absolute-value series."""
    k = np.arange(value.size)
    tol = 64 * EPS * bound * (k + 1)
    small = np.abs(value) <= tol
    kept = np.flatnonzero(~small)
    first = int(kept[0]) if kept.size else value.size
    err = np.where(small, np.where(k < first, 0.0, tol), EPS * bound * (k + 1))
    return np.where(small, 0.0, value), err


class Parts(NamedTuple):
    """Taylor coefficients (with error bounds) of ``delta = tr M / 2 - cos z`` (``cosh`` for
    hyperbolic models), ``b + c`` and ``a - d``, and the largest z where they are summed."""

    delta: np.ndarray
    delta_err: np.ndarray
    bc: np.ndarray
    bc_err: np.ndarray
    ad: np.ndarray
    ad_err: np.ndarray
    z_valid: float


def _reference_coefficients(model: str, n: int) -> np.ndarray:
    k = np.arange(n)
    fact = np.array([math.factorial(int(j)) for j in k], dtype=float)
    ref = np.where(k % 2 == 0, 1.0 / fact, 0.0)
    if ELLIPTIC[model]:
        ref = ref * np.where(k % 4 == 2, -1.0, 1.0)
    return ref


#: :func:`_parts` by method object (frozen, compared by identity) and model: the series
#: are rebuilt otherwise at every call, a fixed cost that dominates small arrays of z.
_PARTS: dict[tuple[int, str], tuple[Any, Parts]] = {}


def _parts(method: Method, model: str) -> Parts:
    hit = _PARTS.get((id(method), model))
    if hit is not None and hit[0] is method:
        return hit[1]
    if len(_PARTS) > 64:
        _PARTS.clear()
    parts = _parts_of(method, model)
    _PARTS[(id(method), model)] = (method, parts)
    return parts


def _parts_of(method: Method, model: str) -> Parts:
    series = taylor_series(method, model)
    hp = _hp_parts(method, model, series)
    if hp is not None:
        return hp
    c, a = series.coef, series.coef_abs
    ref = _reference_coefficients(model, c.shape[0])
    half_trace = 0.5 * (c[:, 0, 0] + c[:, 1, 1])
    bound = 0.5 * (a[:, 0, 0] + a[:, 1, 1])
    delta = _trim(half_trace - ref, bound + np.abs(ref))
    bc = _trim(c[:, 0, 1] + c[:, 1, 0], a[:, 0, 1] + a[:, 1, 0])
    ad = _trim(c[:, 0, 0] - c[:, 1, 1], a[:, 0, 0] + a[:, 1, 1])
    return Parts(*delta, *bc, *ad, series.z_valid)


_HP_CACHE: dict[Any, Parts] = {}


def _hp_parts(method: Method, model: str, series: Series) -> Parts | None:
    """:class:`Parts` of an implicit (P)RK method from its definition at high precision
    (the family tableau computed at raised precision, a file's decimals read exactly):
    every coefficient, however tiny, is then the ideal method's to float rounding. None for
    other methods (explicit ones have the exact polynomial) and for more than
    :data:`HP_MAX_STAGES` stages."""
    prk = method.rk_form()
    if prk is None or not np.isfinite(series.z_valid):
        return None
    if prk.stages > HP_MAX_STAGES:
        return None
    ex = prk.exact
    key = (model, series.coef.shape[0], prk.A_q.tobytes(), prk.b_q.tobytes(),
           prk.A_p.tobytes(), prk.b_p.tobytes(),
           ex)
    if key not in _HP_CACHE:
        if len(_HP_CACHE) > 32:
            _HP_CACHE.clear()
        _HP_CACHE[key] = _hp_series_parts(prk, model, series)
    return _HP_CACHE[key]


def _hp_series_parts(prk: PartitionedRK, model: str, series: Series) -> Parts:
    """``M_(k+1) = B K^k E`` summed at rising precision until every coefficient is either
    known to float accuracy or below the working precision's rounding bound (then 0 with
    that bound, negligible: at least 60 digits)."""
    import mpmath as mp

    L = [[int(x) for x in row] for row in GENERATORS[model]]
    n = series.coef.shape[0]
    a = series.coef_abs
    ref_abs = np.abs(_reference_coefficients(model, n))
    scales = (0.5 * (a[:, 0, 0] + a[:, 1, 1]) + ref_abs, a[:, 0, 1] + a[:, 1, 0],
              a[:, 0, 0] + a[:, 1, 1])
    k = np.arange(n)
    for dps in (60, 120, 240, 480):
        with mp.workdps(dps):
            Aq, bq, Ap, bp = exact.high_precision_tableaux(prk)
            s = len(bq)
            Xq = [[mp.mpf(1)] * s, [mp.mpf(0)] * s]  # stage vectors of the columns (q0, p0)
            Xp = [[mp.mpf(0)] * s, [mp.mpf(1)] * s]
            half, bc, ad = [mp.mpf(1)], [mp.mpf(0)], [mp.mpf(0)]
            for _ in range(n - 1):
                Yq = [[L[0][0] * x + L[0][1] * y for x, y in zip(Xq[col], Xp[col])]
                      for col in range(2)]
                Yp = [[L[1][0] * x + L[1][1] * y for x, y in zip(Xq[col], Xp[col])]
                      for col in range(2)]
                m00, m01 = mp.fdot(bq, Yq[0]), mp.fdot(bq, Yq[1])
                m10, m11 = mp.fdot(bp, Yp[0]), mp.fdot(bp, Yp[1])
                half.append((m00 + m11) / 2)
                bc.append(m01 + m10)
                ad.append(m00 - m11)
                Xq = [[mp.fdot(row, Yq[col]) for row in Aq] for col in range(2)]
                Xp = [[mp.fdot(row, Yp[col]) for row in Ap] for col in range(2)]
            exact_ref = []
            for j in range(n):
                r = 1 / mp.factorial(j) if j % 2 == 0 else mp.mpf(0)
                exact_ref.append(-r if ELLIPTIC[model] and j % 4 == 2 else r)
            delta = [h - r for h, r in zip(half, exact_ref)]
            out, settled = [], True
            for values, scale in zip((delta, bc, ad), scales):
                v = np.array([float(x) for x in values])
                bound = 10.0 ** (3 - dps) * scale * (k + 1)
                below = np.abs(v) <= bound
                if np.any(~below & (np.abs(v) * 1e-20 < bound)):
                    settled = False  # partly resolved: more digits needed
                v = np.where(below, 0.0, v)
                # those before the first resolved one are the order conditions: exactly 0
                first = int(np.argmax(~below)) if (~below).any() else n
                out += [v, np.where(below, np.where(k < first, 0.0, bound), EPS * np.abs(v))]
        if settled:
            break
    return Parts._make([*out, series.z_valid])


def _choose(coef, err, z_valid, z, direct, direct_err, shift: int = 0):
    """``(value / z^shift, bound / z^shift)``: the series where it is valid and its error
    bound beats the direct formula's (always at z <= SERIES_Z), else the direct value.
    Dividing the series by ``z^shift`` term by term keeps tiny z from underflowing."""
    k = np.arange(coef.size)
    az = np.abs(z)
    lead = [j for j in range(min(shift, coef.size)) if coef[j] != 0 or err[j] != 0]
    low = sum((coef[j] * z ** float(j - shift) for j in lead), np.zeros_like(z))
    low_err = sum((err[j] * az ** float(j - shift) for j in lead), np.zeros_like(z))
    series_val = low + _horner(coef[shift:], z)
    # the coefficients' bounds and the evaluation's rounding in one polynomial
    series_err = low_err + _horner((err + 4 * EPS * np.abs(coef) * (k + 1))[shift:], az)
    if np.isfinite(z_valid):  # the first terms left off, with room for the tail
        n = coef.size
        for j in (n - 2, n - 1):
            series_err = series_err + 4 * (np.abs(coef[j]) + err[j]) * az ** float(j - shift)
    scale = az ** float(shift)
    d_val, d_err = direct / scale, direct_err / scale
    use = (z <= z_valid) & ((series_err <= d_err) | (z <= SERIES_Z))
    return np.where(use, series_val, d_val), np.where(use, series_err, d_err)


def _horner(coef: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``sum_j coef[j] z^j`` (trailing zero coefficients, the padding of an explicit
    method's exact polynomial, skipped: they add exact zeros for finite z)."""
    out = np.zeros_like(z)
    nonzero = np.flatnonzero(coef)
    coef = coef[:nonzero[-1] + 1] if nonzero.size else coef[:0]
    for c in coef[::-1]:
        out = out * z + c
    return out


def _ratio_factor(r: np.ndarray, hyperbolic: bool) -> np.ndarray:
    """``arcsin(r) / r`` (``arcsinh`` when hyperbolic), 1 at r = 0."""
    r2 = r * r
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.arcsinh(r) / r if hyperbolic else np.arcsin(r) / r
    return np.where(np.abs(r) < 1e-4, 1.0 + (-r2 if hyperbolic else r2) / 6.0, f)


def errors(method: Method, z, model: str = "oscillator") -> Errors:
    """Phase (or growth-rate) and energy errors at each z (see the module docstring).

    A processed method ``P^-1 K P`` has its kernel's phase (growth-rate) error, a function
    of the trace, which conjugation keeps (taken from the kernel: fewer roundings), and the
    energy error of its own invariant ellipse, that of the full one-step map: the states
    it outputs, ``P^-1 K^n P x``, lie on that ellipse. :func:`kernel_errors` gives the
    kernel's own.

    Each figure carries a float64 error bound; where it exceeds :data:`RECOMPUTE_REL` of the
    figure, the figure is recomputed from the method's high-precision transfer matrix
    (:func:`stepsafe.core.escalate.reference_of`), within a work budget."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    hamiltonian_only(method)
    if method.processor_operations is not None:  # the kernel's phase, the full map's energy
        full = errors(method.one_step(), z, model)
        kernel = method.splitting()
        assert kernel is not None
        return Errors(z, errors(kernel, z, model).phase, full.energy)
    phase, phase_err, energy, energy_err = _float_errors(method, z, model)
    with np.errstate(invalid="ignore"):
        vague = (np.isfinite(phase) & ~(phase_err <= RECOMPUTE_REL * np.abs(phase))) | \
            (np.isfinite(energy) & ~(energy_err <= RECOMPUTE_REL * np.abs(energy)))
    vague &= np.abs(z) > 1e-100  # (there the series is exact to float rounding)
    # an explicit method's series is its exact polynomial, its bound a worst case: its
    # figures are the ideal method's (a reference from the float coefficients would give
    # those coefficients' own, off by their rounding: for blanes-casas-ros764's P^-1 K P,
    # 8.5e-17 against the ideal 2.17e-18 at z = 1e-4)
    if vague.any() and not method.explicit:
        phase, energy = phase.copy(), energy.copy()
        _escalate(method, model, z, np.flatnonzero(vague), phase, energy, phase_err,
                  energy_err)
    return Errors(z, phase, energy)


def _escalate(method: Method, model: str, z: np.ndarray, where: np.ndarray,
              phase: np.ndarray, energy: np.ndarray, phase_err: np.ndarray,
              energy_err: np.ndarray) -> None:
    """Recompute the figures at ``z[where]`` from the high-precision transfer matrix, as
    many as the work budget of :mod:`stepsafe.core.escalate` allows (the rest keep their
    float64 values), each kept only where its own bound (the reference's coefficients are
    good to about DPS digits) beats float64's: at tiny z the float series is the better."""
    import mpmath as mp

    limit = int(max(16, MP_WORK_BUDGET / method.sample_work))
    ref = reference_of(method)
    with mp.workdps(DPS):
        two_pi = 2 * mp.pi
        unit = mp.mpf(10) ** (8 - DPS)  # the reference's coefficients: ~DPS digits
        for i in where[:limit]:
            zz = mp.mpf(float(z[i]))
            try:
                M = ref(zz, model)
            except ZeroDivisionError:
                continue
            a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
            sin2 = -b * c - (a - d) ** 2 / 4
            half = (a + d) / 2
            size = abs(a) + abs(b) + abs(c) + abs(d) + 1
            if ELLIPTIC[model]:
                if not (sin2 > 0 and b > 0):
                    continue
                theta = mp.atan2(mp.sqrt(sin2), half)
                theta += two_pi * mp.nint((zz - theta) / two_pi)  # as in float64
                bound = unit * size / (zz * abs(mp.sin((theta + zz) / 2)))
                if bound < phase_err[i]:
                    phase[i] = float(theta / zz - 1)
                if np.isfinite(energy[i]):
                    spread = mp.sqrt((b + c) ** 2 + (a - d) ** 2)
                    lower = (b - c - spread) / 2
                    if unit * size * (1 + abs(spread / lower)) / lower < energy_err[i]:
                        energy[i] = float(spread / lower)
            elif sin2 < 0 and half > 0:
                mu = half + mp.sqrt(-sin2)
                lam = mp.log(mu)
                if unit * size / (zz * abs(mp.sinh((lam + zz) / 2))) < phase_err[i]:
                    phase[i] = float(lam / zz - 1)


def _float_errors(method: Method, z: np.ndarray, model: str):
    """Phase and energy errors with their float64 error bounds (absolute)."""
    M = transfer_matrix(method, z, model)
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    half_tr = 0.5 * (a + d)
    direct_err = 4 * EPS * (np.abs(M).sum(axis=(1, 2)) + 1.0)
    parts = _parts(method, model)
    nan = np.full(z.shape, np.nan)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore", under="ignore"):
        # sin^2(theta) / z^2 = (-bc - (a-d)^2/4) / z^2 when det M = 1: no cancellation,
        # and scaled by z^2 so that tiny z does not underflow
        bz, cz, adz = b / z, c / z, (a - d) / z
        s2 = -bz * cz - 0.25 * adz ** 2
        s2_err = 8 * EPS * (np.abs(bz * cz) + 0.25 * adz ** 2)
        if ELLIPTIC[model]:
            D, D_err = _choose(parts.delta, parts.delta_err, parts.z_valid, z,
                               half_tr - np.cos(z), direct_err, 2)  # delta / z^2
            y = z * np.sqrt(s2)
            theta = np.arctan2(y, half_tr)  # in (0, pi)
            # atan2's error from those of y (relative; s2 may cancel) and x = tr/2
            theta_err = 8 * EPS * np.abs(theta) + (
                direct_err * y + z * z * s2_err / (2 * y) * np.abs(half_tr)) / (
                y * y + half_tr * half_tr)
            # M^n sees its rotation only modulo 2 pi: of theta + 2 pi n, the phase error
            # is that of the branch nearest the flow's z (on the islands beyond 2 pi,
            # theta + 2 pi; the principal theta - z would be -0.9 at z = 7)
            theta = theta + 2 * np.pi * np.round((z - theta) / (2 * np.pi))
            half = 0.5 * (theta + z)
            sh = np.sin(half)
            # cos(theta) - cos(z) = -2 sin((theta+z)/2) sin((theta-z)/2): with
            # r = -delta / (2 sh), (theta - z) / z = 2 arcsin(r) / z = -D (z / sh) f(r)
            ratio = -(D * z) * (z / (2.0 * sh))
            lever = np.abs(z / sh)
            via_delta = -D * (z / sh) * _ratio_factor(ratio, False)
            err_delta = D_err * lever * 1.01 + np.abs(via_delta) * (
                theta_err * np.abs(np.cos(half) / sh) + 16 * EPS)
            fine = np.abs(ratio) <= 0.5
            phase = np.where(fine, via_delta, (theta - z) / z)
            phase_err = np.where(fine, err_delta, theta_err / z + 2 * EPS * np.abs(theta / z))
            ok = (s2 > 0) & (b > 0)
            phase = np.where(ok, phase, nan)
            # kappa - 1 = (l1 - l2) / l2, l1 - l2 = sqrt((s11 - s22)^2 + 4 s12^2) with
            # s11 - s22 = -(b + c) and s12 = (a - d)/2, both vanishing like powers of z
            # (all divided by z: tiny z neither underflows)
            if _energy_exact(method, model):
                energy, energy_err = np.where(ok, 0.0, nan), np.zeros(z.shape)
            else:
                BC, BC_err = _choose(parts.bc, parts.bc_err, parts.z_valid, z, b + c,
                                     direct_err, 1)
                AD, AD_err = _choose(parts.ad, parts.ad_err, parts.z_valid, z, a - d,
                                     direct_err, 1)
                spread = np.hypot(BC, AD)
                spread_err = np.maximum(BC_err, AD_err) + 4 * EPS * spread
                lower = 0.5 * (bz - cz - spread)
                energy = np.where(ok, spread / lower, nan)
                energy_err = (spread_err + np.abs(energy) * (
                    spread_err + 4 * EPS * (np.abs(bz) + np.abs(cz)) + direct_err / z)) / lower \
                    + 4 * EPS * np.abs(energy)
        else:
            D, D_err = _choose(parts.delta, parts.delta_err, parts.z_valid, z,
                               half_tr - np.cosh(z), direct_err, 2)
            delta = D * z * z
            # mu - 1 = (tr/2 - 1) + sqrt(tr^2/4 - 1), both parts without cancellation
            mu_minus_1 = delta + 2.0 * np.sinh(0.5 * z) ** 2 + z * np.sqrt(np.maximum(-s2, 0.0))
            lam = np.log1p(mu_minus_1)
            sh = np.sinh(0.5 * (lam + z))
            ratio = (D * z) * (z / (2.0 * sh))
            phase = 2.0 * D * (z / (2.0 * sh)) * _ratio_factor(ratio, True)
            root = z * np.sqrt(np.maximum(-s2, 0.0))
            lam_err = 8 * EPS * np.abs(lam) + (D_err * z * z + 8 * EPS * (
                np.abs(delta) + 2.0 * np.sinh(0.5 * z) ** 2 + root)
                + z * z * s2_err / (2 * root)) / (1 + mu_minus_1)
            phase_err = D_err * np.abs(z / sh) * 1.01 + np.abs(phase) * (
                lam_err * np.abs(np.cosh(0.5 * (lam + z)) / sh) + 16 * EPS)
            phase = np.where((s2 < 0) & (half_tr > 0), phase, nan)
            energy, energy_err = nan, np.zeros(z.shape)
    return phase, phase_err, energy, energy_err


def _energy_exact(method: Method, model: str) -> bool:
    """A Runge–Kutta method (not partitioned) maps the oscillator by ``R(z J)``, a
    multiple of a rotation plus one of the identity: ``a = d``, ``b = -c`` exactly, and its
    invariant ellipse is a circle (energy error 0)."""
    if model != "oscillator":
        return False
    prk = method.rk_form()
    return prk is not None and bool(np.array_equal(prk.A_q, prk.A_p) and
                                    np.array_equal(prk.b_q, prk.b_p))


def kernel_errors(method: Method, z, model: str = "oscillator") -> Errors | None:
    """The errors of a processed method's kernel run alone (its outputs taken without
    P^-1), None for any other method: the processor leaves the phase error as it is and
    changes the energy error (:func:`errors`)."""
    kernel = method.splitting() if method.processor_operations is not None else None
    if kernel is None:
        return None
    return errors(kernel, z, model)


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
    """:class:`Offsets` of the oscillator at each z (overflow gives inf or NaN entries, and
    no floating-point warning: the callers read them as unstable)."""
    z = np.atleast_1d(np.asarray(z, dtype=float))
    hamiltonian_only(method)
    with np.errstate(invalid="ignore", over="ignore"):
        M = transfer_matrix(method, z, "oscillator")
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        # |a| + |b| + |c| + |d| summed in numpy's order for axis=(1, 2), without its slow
        # reduction over the two short axes
        direct_err = 4 * EPS * (((np.abs(a) + np.abs(b)) + np.abs(c)) + np.abs(d) + 1.0)
        parts = _parts(method, "oscillator")
        b_plus_c = _choose(parts.bc, parts.bc_err, parts.z_valid, z, b + c, direct_err)[0]
        a_minus_d = _choose(parts.ad, parts.ad_err, parts.z_valid, z, a - d, direct_err)[0]
        return Offsets(M, b_plus_c, a_minus_d, -b * c - 0.25 * (a - d) ** 2)


def hamiltonian_only(method: Method) -> None:
    """A :class:`StepsafeError` for a method whose step is not a Hamiltonian map (phase,
    energy and HMC errors are those of one)."""
    if not method.hamiltonian:
        raise StepsafeError(f"phase, energy and acceptance errors are those of a Hamiltonian "
                            f"map: {method.analysis_note}")


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
