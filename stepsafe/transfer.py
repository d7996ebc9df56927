"""The 2x2 one-step (transfer) matrix M(z) of any method on a test model, with dM/dz.

One place turns every method kind into ``M(z)`` (DESIGN §1):

* RK / PRK: with ``L`` the model generator, stack the stages as ``X = (Q; P)`` and solve
  ``(I - z K) X = E`` with ``K = [[A_q L_qq, A_q L_qp], [A_p L_pq, A_p L_pp]]`` and
  ``E = [[1, 0], [0, 1]]`` (blocks of ones); then ``M = I + z B X`` with
  ``B = [[b_q L_qq, b_q L_qp], [b_p L_pq, b_p L_pp]]``. Differentiating,
  ``dX/dz = (I - z K)^-1 K X``. The stage system is singular exactly at ``z = 1/lambda``
  for the real eigenvalues ``lambda`` of ``K`` (the poles).
* splitting, ``oscillator`` / ``inverted``: the product of drift ``[[1, a z], [0, 1]]`` and
  kick ``[[1, 0], [-+ b z, 1]]`` factors in the order applied.
* splitting, ``saddle``: the product of the symplectic Euler factors of
  :meth:`Splitting.euler_factors` (diagonal: ``DK(c) = diag(1/(1-cz), 1-cz)``,
  ``KD(d) = diag(1+dz, 1/(1+dz))``).
* composition: ``M_base(g_k z) ... M_base(g_1 z)``.

Everything is vectorised over an array of z. The jet carries ``dM/dz`` and, on request,
``d2M/dz2`` (the region finder locates extrema of ``tr M`` by Newton's method), and
``scale``, the magnitude of the terms that sum to ``tr M``, from which the region finder
bounds the rounding error of ``tr M``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from .methods import Composition, Method, PartitionedRK, RungeKutta, Splitting
from .models import GENERATORS, KICK_SIGN, check_model


class Jet(NamedTuple):
    """``M(z)``, ``dM/dz``, the term magnitude ``scale`` and ``d2M/dz2`` at each z (shapes
    (n,2,2), (n,2,2), (n,), (n,2,2)); derivatives not requested are NaN, ``scale`` zeros."""

    M: np.ndarray
    dM: np.ndarray
    scale: np.ndarray
    d2M: np.ndarray

    @property
    def d2trace(self) -> np.ndarray:
        return self.d2M[:, 0, 0] + self.d2M[:, 1, 1]

    @property
    def trace(self) -> np.ndarray:
        return self.M[:, 0, 0] + self.M[:, 1, 1]

    @property
    def dtrace(self) -> np.ndarray:
        return self.dM[:, 0, 0] + self.dM[:, 1, 1]


def transfer_matrix(method: Method, z, model: str = "oscillator") -> np.ndarray:
    """``M(z)`` for every z in ``z`` (array of shape (n, 2, 2); NaN where no unique step)."""
    return transfer_jet(method, z, model, scale=False, order=0).M


def transfer_jet(method: Method, z, model: str = "oscillator", scale: bool = True,
                 order: int = 1) -> Jet:
    """``M`` with its derivatives up to ``order`` (0, 1 or 2) and, unless ``scale=False``
    (then zeros), the rounding scale. Derivatives above ``order`` are NaN; implicit methods
    pay one extra stage solve per order."""
    check_model(model)
    z = np.atleast_1d(np.asarray(z, dtype=float))
    if isinstance(method, Composition):
        flat = method.flattened()
        if isinstance(flat.base, Splitting):
            return transfer_jet(_as_splitting(flat), z, model, scale, order)
        return _composition_jet(flat, z, model, order, scale)
    if isinstance(method, Splitting):
        if model == "saddle":
            return _euler_factor_jet(method, z)
        if model == "saddle-p":  # the saddle at -z: M(z) = M_saddle(-z), dM/dz = -dM_saddle
            jet = _euler_factor_jet(method, -z)
            return Jet(jet.M, -jet.dM, jet.scale, jet.d2M)
        return _splitting_jet(method, z, model, scale, order)
    if isinstance(method, (RungeKutta, PartitionedRK)):
        return _prk_jet(method, z, model, order, scale)
    raise TypeError(f"not a method: {type(method).__name__}")


@lru_cache(maxsize=64)
def stage_operator(method: RungeKutta | PartitionedRK, model: str):
    """``(K, E, B)`` of the stage system ``(I - z K) X = E``, ``M = I + z B X`` (cached per
    method object and model: the region finder evaluates the same method many times)."""
    prk = method.as_prk()
    L = GENERATORS[model]
    s = prk.stages
    K = np.empty((2 * s, 2 * s))
    K[:s, :s], K[:s, s:] = prk.A_q * L[0, 0], prk.A_q * L[0, 1]
    K[s:, :s], K[s:, s:] = prk.A_p * L[1, 0], prk.A_p * L[1, 1]
    E = np.zeros((2 * s, 2))
    E[:s, 0] = 1.0
    E[s:, 1] = 1.0
    B = np.empty((2, 2 * s))
    B[0, :s], B[0, s:] = prk.b_q * L[0, 0], prk.b_q * L[0, 1]
    B[1, :s], B[1, s:] = prk.b_p * L[1, 0], prk.b_p * L[1, 1]
    for array in (K, E, B):
        array.flags.writeable = False
    return K, E, B


def batched_solve(S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``S[i] x = rhs[i]``; NaN rows where ``S[i]`` is exactly singular."""
    try:
        return np.linalg.solve(S, rhs)
    except np.linalg.LinAlgError:
        out = np.full(rhs.shape, np.nan, dtype=np.result_type(S, rhs))
        for i in range(S.shape[0]):
            try:
                out[i] = np.linalg.solve(S[i], rhs[i])
            except np.linalg.LinAlgError:
                pass
        return out


#: Work arrays per batch of z (stage matrices, per-factor rows): ~16 MB whatever the grid.
_BATCH_ELEMENTS = 2_000_000


def _in_batches(jet_of, z: np.ndarray, batch: int) -> Jet:
    """``jet_of`` applied to consecutive slices of ``z`` of at most ``batch`` points."""
    parts = [jet_of(z[i:i + batch]) for i in range(0, z.size, batch)]
    return Jet(*(np.concatenate(field) for field in zip(*parts)))


def _prk_jet(prk: RungeKutta | PartitionedRK, z: np.ndarray, model: str, order: int = 1,
             with_scale: bool = True) -> Jet:
    """Stage solves: ``S X = E``, ``S X' = K X``, ``S X'' = 2 K X'`` (``S = I - z K``);
    ``M = I + z B X``, ``M' = B X + z B X'``, ``M'' = 2 B X' + z B X''``. Long grids are
    processed in batches (80-stage systems on 10^5 points would need gigabytes at once)."""
    K, E, B = stage_operator(prk, model)
    n2 = K.shape[0]
    batch = max(1, _BATCH_ELEMENTS // (n2 * n2))
    if z.size > batch:
        return _in_batches(lambda zb: _prk_jet(prk, zb, model, order, with_scale), z, batch)
    zc = z[:, None, None]
    S = np.eye(n2)[None, :, :] - zc * K[None, :, :]
    X = batched_solve(S, np.broadcast_to(E, (z.size, n2, 2)).copy())
    BX = B[None, :, :] @ X
    M = np.eye(2)[None, :, :] + zc * BX
    dM = np.full_like(M, np.nan)
    d2M = np.full_like(M, np.nan)
    if order >= 1:
        dX = batched_solve(S, K[None, :, :] @ X)
        BdX = B[None, :, :] @ dX
        dM = BX + zc * BdX
        if order >= 2:
            d2X = batched_solve(S, 2.0 * (K[None, :, :] @ dX))
            d2M = 2.0 * BdX + zc * (B[None, :, :] @ d2X)
    scale = np.zeros(z.size)
    if with_scale:
        absterms = np.abs(z)[:, None, None] * (np.abs(B)[None, :, :] @ np.abs(X))
        scale = 2.0 + absterms[:, 0, 0] + absterms[:, 1, 1]
    return Jet(M, dM, scale, d2M)


def _identity(n: int) -> np.ndarray:
    M = np.zeros((n, 2, 2))
    M[:, 0, 0] = M[:, 1, 1] = 1.0
    return M


_FLAT: dict[int, tuple[Composition, Splitting]] = {}


def _as_splitting(method: Composition) -> Splitting:
    """Cached :meth:`Composition.as_splitting` (the region finder evaluates many times)."""
    hit = _FLAT.get(id(method))
    if hit is None or hit[0] is not method:
        if len(_FLAT) > 64:
            _FLAT.clear()
        hit = _FLAT[id(method)] = (method, method.as_splitting())
    return hit[1]


def _splitting_jet(method: Splitting, z: np.ndarray, model: str, with_scale: bool = True,
                   order: int = 1) -> Jet:
    """Product of drift/kick factors ``F = I + c z e_dst e_src^T`` applied as row updates.

    The jet is held as Taylor coefficients ``T[k] = M^(k) / k!``, shape (order+1, 2, 2, n);
    since ``F`` is linear in z, ``(F R)_k = F R_k + c e_dst e_src^T R_(k-1)``, so every
    factor costs a few vector operations whatever the order.
    The rounding scale is the first-order sandwich ``sum_k ||L_k|| ||F_k|| ||R_{k-1}||``
    (``R`` the product so far, ``L`` the product of the later factors, Frobenius norms).
    """
    ops = _row_ops(method, model)
    n = z.size
    batch = max(1, _BATCH_ELEMENTS // len(ops)) if ops else n
    if n > batch:
        return _in_batches(lambda zb: _splitting_jet(method, zb, model, with_scale, order),
                           z, batch)
    T = np.zeros((order + 1, 2, 2, n))
    T[0, 0, 0] = T[0, 1, 1] = 1.0
    cz = np.array([c for _, _, c in ops])[:, None] * z[None, :]
    right = np.empty((len(ops), n)) if with_scale else None
    for k, (src, dst, c) in enumerate(ops):
        if right is not None:
            right[k] = np.einsum("ijn,ijn->n", T[0], T[0])
        T[:, dst] += cz[k] * T[:, src]
        if order:
            T[1:, dst] += c * T[:-1, src]
    scale = np.zeros(n)
    if right is not None:
        L = np.zeros((2, 2, n))
        L[0, 0] = L[1, 1] = 1.0
        left = np.empty((len(ops), n))
        for k in range(len(ops) - 1, -1, -1):
            src, dst, _ = ops[k]
            left[k] = np.einsum("ijn,ijn->n", L, L)
            L[:, src] += cz[k] * L[:, dst]
        scale = np.sqrt(left * right * (2.0 + cz * cz)).sum(axis=0)
    jet = [T[k].transpose(2, 0, 1) * factorial for k, factorial in zip(range(order + 1), (1, 1, 2))]
    nan = np.full((n, 2, 2), np.nan)
    jet += [nan] * (3 - len(jet))
    return Jet(jet[0], jet[1], scale, jet[2])


def _row_ops(method: Splitting, model: str) -> list[tuple[int, int, float]]:
    """``(src, dst, c)`` per factor: drift adds ``c z`` times row p to row q, a kick adds
    ``-+ c z`` times row q to row p (``-`` for the oscillator, ``+`` for the inverted)."""
    sign = KICK_SIGN[model]
    return [(1, 0, coef) if kind == "drift" else (0, 1, sign * coef)
            for kind, coef in method.operations]


def _euler_factor_jet(method: Splitting, z: np.ndarray) -> Jet:
    """Saddle model: the diagonal product of the symplectic Euler factors

    ``DK(c) = diag(1/(1-cz), 1-cz)`` and ``KD(d) = diag(1+dz, 1/(1+dz))``, so
    ``M = diag(m, 1/m)`` with ``(log m)' = g = sum w/f`` over the factors (``f`` the linear
    factor), ``g' = sum -+ (w/f)^2`` (+ for DK), ``m'' = m (g^2 + g')``,
    ``(1/m)'' = (g^2 - g')/m``. Always computed to second order (it costs nothing).
    """
    g = np.zeros(z.size)
    dg = np.zeros(z.size)
    mq = np.ones(z.size)
    mp = np.ones(z.size)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for kind, w in method.euler_factors():
            f = 1.0 - w * z if kind == "DK" else 1.0 + w * z
            if kind == "DK":
                mq, mp = mq / f, mp * f
            else:
                mq, mp = mq * f, mp / f
            r = w / f
            g += r
            dg += r * r if kind == "DK" else -r * r
        M = np.zeros((z.size, 2, 2))
        M[:, 0, 0], M[:, 1, 1] = mq, mp
        dM = np.zeros_like(M)
        dM[:, 0, 0] = mq * g
        dM[:, 1, 1] = -mp * g
        d2M = np.zeros_like(M)
        d2M[:, 0, 0] = mq * (g * g + dg)
        d2M[:, 1, 1] = mp * (g * g - dg)
        bad = ~np.isfinite(mq) | ~np.isfinite(mp)
        M[bad] = dM[bad] = d2M[bad] = np.nan
    return Jet(M, dM, np.abs(mq) + np.abs(mp), d2M)


def _composition_jet(method: Composition, z: np.ndarray, model: str, order: int = 1,
                     with_scale: bool = True) -> Jet:
    """Product of base jets ``M = M_n(g_n z) ... M_1(g_1 z)`` (product rule for the
    derivatives, with the chain-rule factors ``g_k``, ``g_k^2``); the rounding scale is the
    first-order sandwich ``sum_k ||M_n..M_{k+1}|| scale_k ||M_{k-1}..M_1||`` (Frobenius
    norms), which keeps the cancellation that an entrywise absolute product would throw
    away."""
    g = method.weights
    base = transfer_jet(method.base, np.outer(g, z).ravel(), model, with_scale, order)
    n = z.size
    Mb = base.M.reshape(g.size, n, 2, 2)
    dMb = base.dM.reshape(g.size, n, 2, 2)
    d2Mb = base.d2M.reshape(g.size, n, 2, 2)
    sb = base.scale.reshape(g.size, n)
    M, dM, d2M = _identity(n), np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
    right_norms = np.empty((g.size, n))  # ||M_{k-1} ... M_1||
    for k in range(g.size):
        if with_scale:
            right_norms[k] = np.sqrt((M * M).sum(axis=(1, 2)))
        if order >= 2:
            d2M = (g[k] ** 2) * d2Mb[k] @ M + (2.0 * g[k]) * dMb[k] @ dM + Mb[k] @ d2M
        dM = g[k] * dMb[k] @ M + Mb[k] @ dM
        M = Mb[k] @ M
    L = _identity(n)
    scale = np.zeros(n)
    for k in range(g.size - 1, -1, -1) if with_scale else ():
        scale += np.sqrt((L * L).sum(axis=(1, 2))) * sb[k] * right_norms[k]
        L = L @ Mb[k]
    if order < 2:
        d2M = np.full_like(M, np.nan)
    return Jet(M, dM, scale, d2M)


def signed_poles(method: Method, model: str) -> np.ndarray:
    """All real ``z != 0`` (either sign) where the step has no unique solution, sorted.

    RK/PRK: ``z = 1/lambda`` for each real eigenvalue ``lambda`` of the stage operator K
    (an eigenvalue counts as real when its imaginary part is below 1e-7 of its modulus, so
    a near-double real pair is reported, conservatively, as a pole). Splitting on the
    saddle: ``1/c`` for DK(c) factors and ``-1/d`` for KD(d). Composition: the base's
    poles divided by each weight.
    """
    check_model(model)
    if isinstance(method, Composition):
        flat = method.flattened()
        base = signed_poles(flat.base, model)
        with np.errstate(over="ignore", divide="ignore"):  # a tiny weight: no pole in range
            zs = np.concatenate([base / g for g in flat.weights]) if base.size else base
        return _unique_sorted(zs)
    if isinstance(method, Splitting):
        if model not in ("saddle", "saddle-p"):
            return np.empty(0)
        zs = np.array([1.0 / w if kind == "DK" else -1.0 / w
                       for kind, w in method.euler_factors()])
        return _unique_sorted(zs if model == "saddle" else -zs)
    K, _, _ = stage_operator(method, model)
    lam = np.linalg.eigvals(K)
    real = np.abs(lam.imag) <= 1e-7 * np.abs(lam)
    lam = lam.real[real & (np.abs(lam) > 1e-300)]
    return _unique_sorted(1.0 / lam)


def poles(method: Method, model: str) -> np.ndarray:
    """The positive poles of :func:`signed_poles`."""
    zs = signed_poles(method, model)
    return zs[zs > 0]


def _unique_sorted(zs: np.ndarray) -> np.ndarray:
    zs = np.sort(zs[np.isfinite(zs)])
    if zs.size < 2:
        return zs
    keep = np.concatenate([[True], np.diff(zs) > 1e-12 * np.abs(zs[1:])])
    return zs[keep]
