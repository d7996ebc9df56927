"""The 2x2 one-step (transfer) matrix M(z) of any method on a test model, with dM/dz.

One place turns every method into ``M(z)``: the blocks of its step
(:func:`stepsafe.methods.protocol.linear_blocks`, the description the 2n x 2n map of
:mod:`stepsafe.systems.coupled` is built from too), each block's matrix at ``w z`` for its
weight w, multiplied in order:

* Stages (RK / PRK): with ``L`` the model generator, stack the stages as ``X = (Q; P)`` and solve
  ``(I - z K) X = E`` with ``K = [[A_q L_qq, A_q L_qp], [A_p L_pq, A_p L_pp]]`` and
  ``E = [[1, 0], [0, 1]]`` (blocks of ones); then ``M = I + z B X`` with
  ``B = [[b_q L_qq, b_q L_qp], [b_p L_pq, b_p L_pp]]``. Differentiating,
  ``dX/dz = (I - z K)^-1 K X``. The stage system is singular exactly at ``z = 1/lambda``
  for the real eigenvalues ``lambda`` of ``K`` (the poles).
* Shears (splitting), ``oscillator`` / ``inverted``: the product of drift ``[[1, a z], [0, 1]]`` and
  kick ``[[1, 0], [-+ b z, 1]]`` factors in the order applied; a force-gradient term
  (``p += c h^3 grad |V'|^2_{M^-1}``, :class:`Splitting`) is ``[[1, 0], [2 c z^3, 1]]`` on
  both (``V = +-beta^2 q^2 / 2``: ``|V'|^2 = beta^4 q^2`` whatever the sign), so an FG kick
  on the oscillator has the coefficient ``b - 2 c z^2`` (``p~ -= (b - 2 c z^2) z q``), on
  the barrier top ``b + 2 c z^2`` (``p~ += (b + 2 c z^2) z q``; the same as the oscillator's
  at ``z -> i z`` with ``p~ -> i p~``).
* Shears, ``saddle``: the product of the symplectic Euler factors of
  :meth:`Splitting.euler_factors` (diagonal: ``DK(c) = diag(1/(1-cz), 1-cz)``,
  ``KD(d) = diag(1+dz, 1/(1+dz))``).
* Friction (the Langevin O step, on the mean): ``diag(1, c)``, ``c = exp(-gamma w z)``
  (the friction per unit of the model's frequency: z = h when beta = 1).
* several blocks (a composition of an RK method, a Langevin splitting):
  ``M_k(w_k z) ... M_1(w_1 z)``; a composition of a splitting is one merged splitting, a
  processed method ``P^-1 K P`` the splitting of its full one-step map (the kernel's on
  the diagonal models, where every factor is diagonal and P commutes with K).

Everything is vectorised over an array of z. The jet carries ``dM/dz`` and, on request,
``d2M/dz2`` (the region finder locates extrema of ``tr M`` by Newton's method), and
``scale``, the magnitude of the terms that sum to ``tr M``, from which the region finder
bounds the rounding error of ``tr M``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from stepsafe.core.models import GENERATORS, KICK_SIGN, check_model
from stepsafe.methods.protocol import (
    DIAGONAL_MODELS,
    Block,
    Friction,
    MethodKind,
    Shears,
    Stages,
    linear_blocks,
)
from stepsafe.methods.tableaux import Method, PartitionedRK, RungeKutta, Splitting

EPS = float(np.finfo(float).eps)


class Jet(NamedTuple):
    """The one-step matrix and what the region finder needs of it, at each z.

    ``D = M - I`` is accumulated directly (never as ``M - I``), so ``dev = tr M - 2`` keeps
    its relative accuracy as z -> 0, where it behaves like ``-z^2`` while ``tr M`` rounds
    to 2; ``dev_m = tr M + 2`` likewise where ``M`` tends to ``-I``. ``sens`` bounds the
    first-order rounding error of each entry of ``D``: ``|computed D - D| <= eps * sens``
    entrywise, including the amplification by the
    conditioning of an implicit stage solve, and ``scale`` bounds that of ``dev``
    (``scale_m`` that of ``dev_m``). The region finder's tolerance is
    ``TOL_FACTOR * eps * scale``. Shapes: (n, 2, 2) for the
    matrices, (n,) for ``dev`` and ``scale``; derivatives not requested are NaN, ``sens``
    and ``scale`` zeros when not requested."""

    D: np.ndarray
    dM: np.ndarray
    d2M: np.ndarray
    dev: np.ndarray
    scale: np.ndarray
    sens: np.ndarray
    dev_m: np.ndarray  # tr M + 2 (accurate where M -> -I as z -> inf, see _prk_jet)
    scale_m: np.ndarray  # bounds the rounding of dev_m as scale does that of dev

    @property
    def M(self) -> np.ndarray:
        return self.D + np.eye(2)

    @property
    def trace(self) -> np.ndarray:
        return self.dev + 2.0

    @property
    def dtrace(self) -> np.ndarray:
        return self.dM[:, 0, 0] + self.dM[:, 1, 1]

    @property
    def d2trace(self) -> np.ndarray:
        return self.d2M[:, 0, 0] + self.d2M[:, 1, 1]


def _jet(D, dM, d2M, sens=None) -> Jet:
    """A :class:`Jet` with ``dev`` from ``D`` and ``scale`` the trace of ``sens``."""
    sens = np.zeros(D.shape) if sens is None else sens
    dev = D[:, 0, 0] + D[:, 1, 1]
    scale = sens[:, 0, 0] + sens[:, 1, 1]
    return Jet(D, dM, d2M, dev, scale, sens, dev + 4.0, scale + 4.0)


def has_form(method: Method, model: str) -> bool:
    """Whether ``method`` has a transfer matrix on ``model``: a force-gradient splitting
    (or a composition of one) needs ``T(p) + V(q)`` with quadratic T, so it has none on
    the saddles (``H = +-beta p q``); a method is analysed only on its ``models``."""
    check_model(model)
    if model not in method.models:
        return False
    return model not in DIAGONAL_MODELS or not method.force_gradient


_BLOCKS: dict[tuple[int, str], tuple[MethodKind, tuple[Block, ...]]] = {}


def blocks_of(method: MethodKind, model: str | None) -> tuple[Block, ...]:
    """:func:`~stepsafe.methods.protocol.linear_blocks` of ``method`` on ``model``, cached
    per method object (the region finder evaluates the same method many times)."""
    key = (id(method), str(model))
    hit = _BLOCKS.get(key)
    if hit is None or hit[0] is not method:
        if len(_BLOCKS) > 64:
            _BLOCKS.clear()
        hit = _BLOCKS[key] = (method, linear_blocks(method, model))
    return hit[1]


def transfer_matrix(method: Method, z, model: str = "oscillator") -> np.ndarray:
    """``M(z)`` for every z in ``z`` (array of shape (n, 2, 2); NaN where no unique step)."""
    return transfer_jet(method, z, model, scale=False, order=0).M


def transfer_jet(method: Method, z, model: str = "oscillator", scale: bool = True,
                 order: int = 1) -> Jet:
    """``M`` with its derivatives up to ``order`` (0, 1 or 2) and, unless ``scale=False``
    (then zeros), the rounding sensitivity. Derivatives above ``order`` are NaN; implicit
    methods pay one extra stage solve per order."""
    check_model(model)
    z = np.atleast_1d(np.asarray(z, dtype=float))
    blocks = blocks_of(method, model)
    if len(blocks) == 1 and blocks[0].weight == 1.0:
        return _block_jet(blocks[0], z, model, scale, order)
    return _product_jet(blocks, z, model, order, scale)


def _block_jet(block: Block, z: np.ndarray, model: str, scale: bool, order: int) -> Jet:
    """The jet of one block at weight 1."""
    if isinstance(block, Shears):
        if model == "saddle":
            return _euler_factor_jet(block.splitting, z)
        if model == "saddle-p":  # the saddle at -z: M(z) = M_saddle(-z), dM/dz = -dM_saddle
            jet = _euler_factor_jet(block.splitting, -z)
            return jet._replace(dM=-jet.dM)
        return _splitting_jet(block.splitting, z, model, scale, order)
    if isinstance(block, Stages):
        return _prk_jet(block.method, z, model, order, scale)
    if isinstance(block, Friction):
        return _friction_jet(block, z, model, order)
    raise TypeError(f"not a block: {type(block).__name__}")


def _friction_jet(block: Friction, z: np.ndarray, model: str, order: int) -> Jet:
    """The Langevin O step on the mean, ``M = diag(1, c)``, ``c = exp(-k z)`` with
    ``k = gamma w`` (the friction per unit of the model's frequency): ``D = diag(0,
    expm1(-k z))``, ``dM = diag(0, -k c)``, ``d2M = diag(0, k^2 c)``; each entry of D is
    one correctly rounded operation on ``k z`` (two roundings: ``sens = 2 |c - 1|``)."""
    if model != "oscillator":
        raise ValueError(f"the friction step is analysed on the oscillator, not on {model}")
    k = block.gamma * block.weight
    n = z.size
    with np.errstate(over="ignore", under="ignore"):
        c = np.exp(-k * z)
        D = np.zeros((n, 2, 2))
        D[:, 1, 1] = np.expm1(-k * z)
        dM = np.zeros((n, 2, 2))
        dM[:, 1, 1] = -k * c
        d2M = np.zeros((n, 2, 2))
        d2M[:, 1, 1] = k * k * c
    nan = np.full((n, 2, 2), np.nan)
    sens = np.zeros((n, 2, 2))
    sens[:, 1, 1] = 2.0 * np.abs(D[:, 1, 1])
    return _jet(D, dM if order >= 1 else nan, d2M if order >= 2 else nan, sens)


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
    """Solve ``S[i] x = rhs[i]``; NaN rows where ``S[i]`` is exactly singular (found by
    their zero LU determinant, replaced by the identity so the rest stays one batch)."""
    try:
        return np.linalg.solve(S, rhs)
    except np.linalg.LinAlgError:
        singular = np.linalg.det(S) == 0
        S = S.copy()
        S[singular] = np.eye(S.shape[-1])
        out = np.linalg.solve(S, rhs)
        out[singular] = np.nan
        return out


#: Work arrays per batch of z (stage matrices, per-factor rows): ~16 MB whatever the grid.
_BATCH_ELEMENTS = 2_000_000


def _in_batches(jet_of, z: np.ndarray, batch: int) -> Jet:
    """``jet_of`` applied to consecutive slices of ``z`` of at most ``batch`` points."""
    parts = [jet_of(z[i:i + batch]) for i in range(0, z.size, batch)]
    return Jet(*(np.concatenate(field) for field in zip(*parts)))


#: Safety factor of the region finder's rounding bound ``TOL_FACTOR * eps * scale`` over
#: the first-order bound ``eps * scale`` (second-order terms, LU pivot growth, and the
#: decimals of published coefficients).
TOL_FACTOR = 16.0


class FarForm(NamedTuple):
    """``M(z) = M_inf + B S^-1 V`` for an invertible stage operator (``V = K^-1 E``,
    ``M_inf = I - B V``, the limit as z -> inf), with ``tr M_inf -+ 2`` taken as exactly 0
    when within the rounding policy (:data:`TOL_FACTOR`) of 0: Gauss methods tend to
    ``M = (-1)^s I`` exactly, which float64 coefficients reproduce only to ~1e-16."""

    V: np.ndarray
    minus_2: float  # tr M_inf - 2
    plus_2: float  # tr M_inf + 2
    z_from: float  # used for z >= z_from, where ||(z K)^-1|| <= 1/4


@lru_cache(maxsize=64)
def far_form(method: RungeKutta | PartitionedRK, model: str) -> FarForm | None:
    """The :class:`FarForm` of ``method`` on ``model``, or None if K is (nearly) singular."""
    K, E, B = stage_operator(method, model)
    with np.errstate(all="ignore"):
        try:
            K_inv = np.linalg.inv(K)
            if not np.all(np.isfinite(K_inv)):
                return None
            norm_inv = np.linalg.norm(K_inv, 2)
        except np.linalg.LinAlgError:
            return None
    if not np.isfinite(norm_inv) or np.linalg.norm(K, 2) * norm_inv > 1e8:
        return None
    V = K_inv @ E
    trace = 2.0 - float(np.trace(B @ V))
    tol = TOL_FACTOR * EPS * K.shape[0] * float(np.trace(np.abs(B) @ np.abs(K_inv) @ E)) * (
        np.linalg.norm(K, 2) * norm_inv)
    minus_2, plus_2 = trace - 2.0, trace + 2.0
    if abs(minus_2) <= tol:
        minus_2, plus_2 = 0.0, 4.0
    elif abs(plus_2) <= tol:
        minus_2, plus_2 = -4.0, 0.0
    V.flags.writeable = False
    return FarForm(V, minus_2, plus_2, 4.0 * norm_inv)


def _prk_jet(prk: RungeKutta | PartitionedRK, z: np.ndarray, model: str, order: int = 1,
             with_scale: bool = True) -> Jet:
    """``M = I + z B X`` with the stage solve ``S X = E`` (``S = I - z K``), in whichever of
    three exact forms keeps ``dev = tr M - 2`` (and ``tr M + 2``) accurate:

    * small z (``z ||K|| <= 1``): ``D = z B E + z^2 B K X`` (since ``X = E + z K X``): the
      O(z) part is exact and the rest carries the factor z^2;
    * large z (:func:`far_form`, K invertible): ``M = M_inf + B S^-1 V``, the second part
      O(1/z) and accurate;
    * in between, ``D = z B X`` directly.

    Derivatives without cancellation: ``M' = B S^-2 E``, ``M'' = 2 B K S^-3 E`` (S and K
    commute), i.e. two more solves with the previous solution as right-hand side.

    Rounding: the LU solve returns X for some ``S + dS`` with ``|dS| <~ 2s eps |S|``, so X
    errs by ``S^-1 dS X``, and ``z B X`` by ``z B S^-1 dS X``, entrywise at most
    ``2s z |W| |S| |X|`` with ``W = B S^-1`` (a transposed solve; ``W = B K S^-1`` and
    ``z^2`` for the small-z form): the conditioning of the stage system enters through
    ``|W|``. The products add ``2s |B| ...`` terms of the same shape. Long grids are
    processed in batches (80-stage systems on 10^5 points would need gigabytes at once)."""
    K, E, B = stage_operator(prk, model)
    n2 = K.shape[0]
    batch = max(1, _BATCH_ELEMENTS // (n2 * n2))
    if z.size > batch:
        return _in_batches(lambda zb: _prk_jet(prk, zb, model, order, with_scale), z, batch)
    with np.errstate(over="ignore", invalid="ignore"):  # the form not chosen may overflow
        return _prk_forms(prk, z, model, order, with_scale)


def _prk_forms(prk: RungeKutta | PartitionedRK, z: np.ndarray, model: str, order: int,
               with_scale: bool) -> Jet:
    """The body of :func:`_prk_jet` for one batch."""
    K, E, B = stage_operator(prk, model)
    n2 = K.shape[0]
    far = far_form(prk, model)
    BK, BE = B @ K, B @ E
    zc = z[:, None, None]
    small = (np.abs(z) * np.abs(K).sum(axis=1).max() <= 1.0)[:, None, None]
    use_far = (np.abs(z) >= far.z_from)[:, None, None] if far else np.zeros_like(small)
    S = np.eye(n2)[None, :, :] - zc * K[None, :, :]
    rhs = E if far is None else np.hstack([E, far.V])
    Y = batched_solve(S, np.broadcast_to(rhs, (z.size, n2, rhs.shape[1])).copy())
    X = Y[:, :, :2]
    D = np.where(small, zc * BE[None, :, :] + (zc * zc) * (BK[None, :, :] @ X),
                 zc * (B[None, :, :] @ X))
    dev = D[:, 0, 0] + D[:, 1, 1]
    dev_m = dev + 4.0
    if far is not None:
        BSV = B[None, :, :] @ Y[:, :, 2:]
        tail = BSV[:, 0, 0] + BSV[:, 1, 1]
        D = np.where(use_far, BSV - (B @ far.V)[None, :, :], D)
        dev = np.where(use_far[:, 0, 0], far.minus_2 + tail, dev)
        dev_m = np.where(use_far[:, 0, 0], far.plus_2 + tail, dev_m)
    dM = np.full_like(D, np.nan)
    d2M = np.full_like(D, np.nan)
    if order >= 1:
        Y2 = batched_solve(S, X)
        dM = B[None, :, :] @ Y2
        if order >= 2:
            d2M = 2.0 * BK[None, :, :] @ batched_solve(S, Y2)
    if not with_scale:
        return Jet(D, dM, d2M, dev, np.zeros(z.size), np.zeros(D.shape), dev_m, np.zeros(z.size))
    W = batched_solve(S.transpose(0, 2, 1),
                      np.broadcast_to(np.hstack([BK.T, B.T]), (z.size, n2, 4)).copy())
    absW = np.abs(W).transpose(0, 2, 1)
    absY = np.abs(Y)
    absSY = absY + np.abs(zc) * (np.abs(K)[None, :, :] @ absY)  # |S| |Y|
    near = (zc * zc) * (absW[:, :2] @ absSY[:, :, :2]
                        + (np.abs(B) @ np.abs(K))[None, :, :] @ absY[:, :, :2])
    near = near + np.abs(zc) * (np.abs(B) @ E)[None, :, :] / n2
    direct = np.abs(zc) * (absW[:, 2:] @ absSY[:, :, :2] + np.abs(B)[None, :, :] @ absY[:, :, :2])
    sens = n2 * np.where(small, near, direct)
    scale = sens[:, 0, 0] + sens[:, 1, 1]
    scale_m = scale + 4.0
    if far is not None:
        tail = absW[:, 2:] @ absSY[:, :, 2:] + np.abs(B)[None, :, :] @ absY[:, :, 2:]
        sens = np.where(use_far, n2 * tail, sens)
        tail_scale = sens[:, 0, 0] + sens[:, 1, 1]
        far_scale = use_far[:, 0, 0]
        scale = np.where(far_scale, tail_scale + abs(far.minus_2), scale)
        scale_m = np.where(far_scale, tail_scale + abs(far.plus_2), scale_m)
    return Jet(D, dM, d2M, dev, scale, sens, dev_m, scale_m)


def _splitting_jet(method: Splitting, z: np.ndarray, model: str, with_scale: bool = True,
                   order: int = 1) -> Jet:
    """Product of drift/kick factors ``F = I + c z e_dst e_src^T`` applied as row updates.

    Held as Taylor coefficients ``T[k] = M^(k) / k!`` (shape (order+1, 2, 2, n)) except
    that ``T[0]`` holds ``D = M - I``: a factor adds ``c z`` times row ``src`` of ``M``
    (``= D[src] + e_src``) to row ``dst``, and ``(F R)_k = F R_k + c e_dst e_src^T
    R_(k-1)``, a few vector operations per factor whatever the order.

    Rounding, to first order: the update of row ``dst`` errs by at most
    ``3 eps (|D_new[dst]| + |c z| |M_old[src]|)`` entrywise (the product ``c z``, the
    multiplication and the addition), and the later factors ``L`` carry that error to the
    end as ``L e``, so ``sens = 3 sum_k |L_k[:, dst]| (|D_new[dst]| + |c z| |M_old[src]|)``
    (an outer product per factor). Changing a coefficient by a relative ``delta`` moves
    ``M`` by the same expression times ``delta / (3 eps)``.
    """
    ops = _row_ops(method, model)
    n = z.size
    batch = max(1, _BATCH_ELEMENTS // max(4 * len(ops), 1))
    if n > batch:
        return _in_batches(lambda zb: _splitting_jet(method, zb, model, with_scale, order),
                           z, batch)
    T = np.zeros((order + 1, 2, 2, n))
    # the factor's entry f(z) = c z^k with its Taylor coefficients f'(z) and f''(z) / 2
    # c z^k as ((c z) z) z: z^3 alone underflows at z = 1e-150 where c = 1e300 makes the
    # term O(z)
    cz = np.array([_scaled_power(c, z, k) for _, _, c, k in ops]).reshape(len(ops), n)
    rows = np.empty((len(ops), 2, n)) if with_scale else None
    for j, (src, dst, c, power) in enumerate(ops):
        old = T[0, src].copy()
        old[src] += 1.0  # row src of M = I + D
        f1 = c if power == 1 else power * _scaled_power(c, z, power - 1)
        if order >= 2:
            f2 = 0.0 if power == 1 else power * (power - 1) / 2 * _scaled_power(c, z, power - 2)
            T[2, dst] += cz[j] * T[2, src] + f1 * T[1, src] + f2 * old
        if order >= 1:
            T[1, dst] += cz[j] * T[1, src] + f1 * old
        T[0, dst] += cz[j] * old
        if rows is not None:
            rows[j] = np.abs(T[0, dst]) + np.abs(cz[j]) * np.abs(old)
    sens = None
    if rows is not None:
        sens = np.zeros((2, 2, n))
        L = np.zeros((2, 2, n))
        L[0, 0] = L[1, 1] = 1.0
        for k in range(len(ops) - 1, -1, -1):
            src, dst = ops[k][:2]
            sens += np.abs(L[:, dst])[:, None, :] * rows[k][None, :, :]
            L[:, src] += cz[k] * L[:, dst]
        sens = 3.0 * sens.transpose(2, 0, 1)
    jet = [T[k].transpose(2, 0, 1) * factorial for k, factorial in zip(range(order + 1), (1, 1, 2))]
    nan = np.full((n, 2, 2), np.nan)
    jet += [nan] * (3 - len(jet))
    return _jet(jet[0], jet[1], jet[2], sens)


def _scaled_power(c: float, z: np.ndarray, k: int) -> np.ndarray:
    """``c z^k`` multiplied out from c (no intermediate ``z^k`` to underflow or overflow
    while the product is representable)."""
    out = np.full(np.shape(z), c, dtype=float)
    with np.errstate(over="ignore", under="ignore"):
        for _ in range(k):
            out = out * z
    return out


def row_ops(method: Splitting, model: str) -> list[tuple[int, int, float, int]]:
    """``(src, dst, c, k)`` per factor ``I + c z^k e_dst e_src^T``: a drift adds ``a z`` times
    row p to row q, a kick ``-+ b z`` times row q to row p (``-`` for the oscillator, ``+``
    for the inverted), a force-gradient term ``+2 c z^3`` times row q to row p (either
    model: ``grad |V'|^2 = 2 beta^4 q``)."""
    sign = KICK_SIGN[model]
    out = []
    for kind, coef in method.operations:
        if kind == "drift":
            out.append((1, 0, coef, 1))
        elif kind == "kick":
            out.append((0, 1, sign * coef, 1))
        elif kind == "gradient":
            out.append((0, 1, 2.0 * coef, 3))
        else:
            raise ValueError(f"unknown operation {kind!r}")
    return out


_row_ops = row_ops


def _euler_factor_jet(method: Splitting, z: np.ndarray) -> Jet:
    """Saddle model: the diagonal product of the symplectic Euler factors

    ``DK(c) = diag(1/(1-cz), 1-cz)`` and ``KD(d) = diag(1+dz, 1/(1+dz))``, so
    ``M = diag(m, 1/m)``. With ``m = sigma e^lam`` (``lam = sum -+ log|f|`` over the linear
    factors ``f``, by ``log1p`` near 1): ``M_qq - 1 = sigma e^lam - 1`` and
    ``tr M - 2 = 4 sinh(lam/2)^2`` (``sigma = 1``) or ``-4 cosh(lam/2)^2`` (``sigma = -1``:
    a flip), all without cancellation. ``(log m)' = g = sum w/f``, ``g' = sum -+ (w/f)^2``
    (+ for DK), ``m'' = m (g^2 + g')``, ``(1/m)'' = (g^2 - g')/m``. Rounding: ``lam`` errs
    by at most ``2 eps sum (|log|f|| + |w z / f| + S |z / f|)``, the last term for the
    weights themselves (differences of partial sums of the coefficients, each wrong by up to
    ``2 eps S``, S the coefficients' total size: a weight that is 0 in exact arithmetic may
    be 1e-17, a factor 1 + 10 at z = 1e18), which moves ``tr M`` by ``2 |sinh lam|`` times
    that. Always computed to second order (it costs nothing).
    """
    n = z.size
    g, dg, lam, spread = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    sigma = np.ones(n)
    size = float(np.abs(method.drift).sum() + np.abs(method.kick).sum())
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for kind, w in method.euler_factors():
            wz = -w * z if kind == "DK" else w * z
            f = 1.0 + wz
            log_f = np.where(f > 0, np.log1p(np.maximum(wz, -1.0)), np.log(np.abs(f)))
            sigma = sigma * np.sign(f)
            lam += -log_f if kind == "DK" else log_f
            spread += np.abs(log_f) + np.abs(wz / f) + size * np.abs(z / f)
            r = w / f
            g += r
            dg += r * r if kind == "DK" else -r * r
        mq, mp = sigma * np.exp(lam), sigma * np.exp(-lam)
        D = np.zeros((n, 2, 2))
        D[:, 0, 0] = np.where(sigma > 0, np.expm1(lam), mq - 1.0)
        D[:, 1, 1] = np.where(sigma > 0, np.expm1(-lam), mp - 1.0)
        dev = np.where(sigma > 0, 4.0 * np.sinh(0.5 * lam) ** 2, -4.0 * np.cosh(0.5 * lam) ** 2)
        dM = np.zeros_like(D)
        dM[:, 0, 0] = mq * g
        dM[:, 1, 1] = -mp * g
        d2M = np.zeros_like(D)
        d2M[:, 0, 0] = mq * (g * g + dg)
        d2M[:, 1, 1] = mp * (g * g - dg)
        sens = np.zeros_like(D)
        sens[:, 0, 0] = 2.0 * np.abs(mq) * spread
        sens[:, 1, 1] = 2.0 * np.abs(mp) * spread
        scale = 4.0 * np.abs(np.sinh(lam)) * spread + 4.0 * EPS_FLOOR * np.abs(dev)
        bad = ~np.isfinite(mq) | ~np.isfinite(mp) | ~np.isfinite(lam)
        D[bad] = dM[bad] = d2M[bad] = np.nan
        dev[bad] = np.nan
    return Jet(D, dM, d2M, dev, scale, sens, dev + 4.0, scale + 4.0)


#: Relative rounding of the last operation that forms a value (in units of eps).
EPS_FLOOR = 1.0


def _block_jets(blocks: tuple[Block, ...], z: np.ndarray, model: str, with_scale: bool,
                order: int) -> tuple[np.ndarray, ...]:
    """``(D, dM, d2M, sens)`` of every block at ``w_k z``, each of shape (k, n, 2, 2); the
    blocks of one object (a composition's base) in one vectorised call at all their
    ``w z``."""
    n = z.size
    out = [np.empty((len(blocks), n, 2, 2)) for _ in range(4)]
    groups: dict[tuple, list[int]] = {}
    for k, b in enumerate(blocks):
        groups.setdefault(leaf_key(b), []).append(k)
    for members in groups.values():
        g = np.array([blocks[k].weight for k in members])
        jet = _block_jet(_at_unit_weight(blocks[members[0]]), np.outer(g, z).ravel(), model,
                         with_scale, order)
        for array, part in zip(out, (jet.D, jet.dM, jet.d2M, jet.sens)):
            array[members] = part.reshape(g.size, n, 2, 2)
    return tuple(out)


def leaf_key(block: Block) -> tuple:
    """What a block runs: blocks of one key differ only in their weight (a composition's
    substeps), so their matrices are one call at all their ``w z``."""
    if isinstance(block, Shears):
        return ("shears", id(block.splitting))
    if isinstance(block, Stages):
        return ("stages", id(block.method))
    return ("friction", block.gamma, block.kT)


def _at_unit_weight(block: Block) -> Block:
    from dataclasses import replace

    return block if block.weight == 1.0 else replace(block, weight=1.0)


def _product_jet(blocks: tuple[Block, ...], z: np.ndarray, model: str, order: int = 1,
                 with_scale: bool = True) -> Jet:
    """Product of the blocks' jets ``M = M_n(g_n z) ... M_1(g_1 z)``, accumulated as
    ``D <- D_k + D + D_k D`` (``M = I + D``), the derivatives by the product rule with the
    chain-rule factors ``g_k``, ``g_k^2``.

    Rounding, to first order: the error ``E_k`` of substep k's ``D_k`` (entrywise at most
    ``eps sens_k``) reaches the end as ``L_k E_k R_(k-1)`` (``L`` the later substeps, ``R``
    the earlier ones), and the update itself errs by ``2 eps (|D_new| + |D_k| |D|)``
    entrywise, carried by ``L_k``; ``sens`` sums these with absolute values."""
    g = np.array([b.weight for b in blocks])
    n = z.size
    Db, dMb, d2Mb, sb = _block_jets(blocks, z, model, with_scale, order)
    eye = np.eye(2)[None, :, :]
    D, dM, d2M = np.zeros((n, 2, 2)), np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
    right = np.empty((g.size, n, 2, 2)) if with_scale else None  # |M_{k-1} ... M_1|
    local = np.empty((g.size, n, 2, 2)) if with_scale else None
    for k in range(g.size):
        Mk, M = eye + Db[k], eye + D
        if order >= 2:
            d2M = (g[k] ** 2) * d2Mb[k] @ M + (2.0 * g[k]) * dMb[k] @ dM + Mk @ d2M
        if order >= 1:
            dM = g[k] * dMb[k] @ M + Mk @ dM
        new = Db[k] + D + Db[k] @ D
        if with_scale:
            right[k] = np.abs(M)
            local[k] = 2.0 * (np.abs(new) + np.abs(Db[k]) @ np.abs(D))
        D = new
    if order < 2:
        d2M = np.full_like(D, np.nan)
    if order < 1:
        dM = np.full_like(D, np.nan)
    if not with_scale:
        return _jet(D, dM, d2M)
    L = np.broadcast_to(eye, (n, 2, 2)).copy()
    sens = np.zeros((n, 2, 2))
    for k in range(g.size - 1, -1, -1):
        absL = np.abs(L)
        sens += absL @ (sb[k] @ right[k] + local[k])
        L = L @ (eye + Db[k])
    return _jet(D, dM, d2M, sens)


def signed_poles(method: Method, model: str) -> np.ndarray:
    """All real ``z != 0`` (either sign) where the step has no unique solution, sorted
    (see :func:`pole_locations`)."""
    return pole_locations(method, model)[0]


def pole_locations(method: Method, model: str) -> tuple[np.ndarray, np.ndarray]:
    """The real ``z != 0`` (either sign, sorted) where the step has no unique solution,
    and the float64 uncertainty of each.

    RK/PRK: ``z = 1/lambda`` for each real eigenvalue ``lambda`` of the stage operator K
    (an eigenvalue counts as real when its imaginary part is below 1e-7 of its modulus, so
    a near-double real pair is reported, conservatively, as a pole); ``lambda`` errs by
    about ``eps ||K|| kappa`` with ``kappa = |y| |x| / |y^H x|`` its condition number (left
    and right eigenvectors), and never by more than Elsner's bound
    ``(2 ||K||)^(1-1/n) (eps ||K||)^(1/n)`` (n the size of K), which holds for any K
    (finite where ``kappa`` is not: a defective eigenvalue); so ``z`` by ``z^2`` times the
    smaller (times a safety factor of 16).
    Splitting on the saddle: ``1/c`` for DK(c) factors and ``-1/d`` for KD(d), exact to
    rounding. Several blocks (a composition): each block's poles divided by its weight. The
    Langevin friction step has none.
    """
    check_model(model)
    blocks = method.decomposition(model)
    if len(blocks) == 1 and blocks[0].weight == 1.0:
        return _block_poles(blocks[0], model)
    groups: dict[tuple, tuple[Block, list[float]]] = {}
    for b in blocks:
        groups.setdefault(leaf_key(b), (b, []))[1].append(b.weight)
    zs_all, us_all = [], []
    for b, weights in groups.values():
        base, unc = _block_poles(_at_unit_weight(b), model)
        if not base.size:
            continue
        with np.errstate(over="ignore", divide="ignore"):  # a tiny weight: no pole in range
            zs_all += [base / g for g in weights]
            us_all += [unc / abs(g) for g in weights]
    if not zs_all:
        return np.empty(0), np.empty(0)
    return _unique_sorted(np.concatenate(zs_all), np.concatenate(us_all))


def _block_poles(block: Block, model: str) -> tuple[np.ndarray, np.ndarray]:
    """The poles of one block at weight 1 (see :func:`pole_locations`)."""
    if isinstance(block, Friction):
        return np.empty(0), np.empty(0)
    if isinstance(block, Shears):
        if model not in DIAGONAL_MODELS:
            return np.empty(0), np.empty(0)
        method = block.splitting
        zs = np.array([1.0 / w if kind == "DK" else -1.0 / w
                       for kind, w in method.euler_factors()])
        zs = zs if model == "saddle" else -zs
        # each factor weight w is a difference of partial sums of the coefficients, wrong
        # by up to 2 eps S (S their total size); the pole 1/w then by z^2 times that
        size = float(np.abs(method.drift).sum() + np.abs(method.kick).sum())
        with np.errstate(over="ignore"):  # a pole beyond 1e154: its band is unbounded
            unc = 2.0 * EPS * np.maximum(np.abs(zs), size * zs * zs)
        return _unique_sorted(zs, unc)
    assert isinstance(block, Stages)
    K, _, _ = stage_operator(block.method, model)
    lam, right = np.linalg.eig(K)
    real = (np.abs(lam.imag) <= 1e-7 * np.abs(lam)) & (np.abs(lam) > 1e-300)
    lam, right = lam.real[real], right[:, real].real
    # left eigenvectors: those of K^T, matched by eigenvalue (real ones are real vectors)
    lam_t, left = np.linalg.eig(K.T)
    match = np.abs(lam_t[None, :] - lam[:, None]).argmin(axis=1) if lam.size else []
    left = left[:, match].real
    norm = np.linalg.norm(K, 2)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        kappa = (np.linalg.norm(left, axis=0) * np.linalg.norm(right, axis=0)
                 / np.abs(np.einsum("ij,ij->j", left, right)))
        first_order = np.nan_to_num(16.0 * EPS * norm * kappa, nan=np.inf)
        n = K.shape[0]
        elsner = 16.0 * (2 * norm) ** (1 - 1 / n) * (EPS * norm) ** (1 / n)
        dlam = np.minimum(first_order, elsner)
        zs = 1.0 / lam
        unc = dlam * zs * zs
    return _unique_sorted(zs, np.maximum(unc, 2 * EPS * np.abs(zs)))


def poles(method: Method, model: str) -> np.ndarray:
    """The positive poles of :func:`signed_poles`."""
    zs = signed_poles(method, model)
    return zs[zs > 0]


def _unique_sorted(zs: np.ndarray, unc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    finite = np.isfinite(zs)
    order = np.argsort(zs[finite])
    zs, unc = zs[finite][order], unc[finite][order]
    if zs.size < 2:
        return zs, unc
    keep = np.concatenate([[True], np.diff(zs) > 1e-12 * np.abs(zs[1:])])
    return zs[keep], unc[keep]
