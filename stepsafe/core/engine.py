"""The float one-step map of a linear system: a step's blocks applied to a batch of matrices.

One step of size h on ``x' = L x`` (x of size m = 2n, ``x = (q, p)``) is the product of
its blocks (:func:`stepsafe.methods.tableaux.linear_blocks`), block k run at ``w_k z``::

    M(z) = M_k(w_k z) ... M_2(w_2 z) M_1(w_1 z)

with z the step in the system's units (z = beta h on a 2x2 test model, z = h on a 2n x 2n
system). :func:`step_jet` is the one routine that evaluates it, vectorised over an array
of z: it asks a :class:`LinearSystem` for each block's matrix (the blocks of one object,
a composition's substeps, in one call at all their ``w z``), and multiplies them, carrying
on request the derivatives ``dM/dz``, ``d2M/dz2`` and a rounding bound. The two systems
are the 2x2 test models (:mod:`stepsafe.core.transfer`: closed forms of the drift/kick
products and of the saddles' diagonal factors) and the 2n x 2n systems
(:mod:`stepsafe.systems.coupled`: the symplectic Euler factors by n x n solves). The
stage system of a (partitioned) Runge–Kutta block is one routine for both,
:func:`stage_jet` over :func:`stage_operator`.

Every matrix is held as ``D = M - I`` (never formed as ``M - I``), so ``tr M - 2``
keeps its relative accuracy as z -> 0. Rounding, two bounds:

* ``"entrywise"`` (the region finder's): ``sens``, with ``|computed D - D| <= eps sens``
  entrywise to first order, and ``scale``, the bound of ``dev = tr D``;
* ``"norm"`` (the coupled criterion's): ``err``, a first-order bound on the Frobenius
  norm of D's rounding error.

The mpmath reference (:mod:`stepsafe.reference.highprec`) is a separate path sharing no
code with this one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Literal, NamedTuple, Protocol

import numpy as np

from stepsafe.methods.protocol import Block, Friction, Shears, Stages

if TYPE_CHECKING:  # pragma: no cover
    from stepsafe.methods.tableaux import PartitionedRK, RungeKutta, Splitting

EPS = float(np.finfo(float).eps)

#: The rounding bound a jet carries: none, entrywise (``sens``, ``scale``) or normwise
#: (``err``).
Rounding = Literal["entrywise", "norm"] | None

#: Safety factor of the region finder's rounding bound ``TOL_FACTOR * eps * scale`` over
#: the first-order bound ``eps * scale`` (second-order terms, LU pivot growth, and the
#: decimals of published coefficients).
TOL_FACTOR = 16.0

#: Work arrays per batch of z (stage matrices, per-factor rows): ~16 MB whatever the grid.
BATCH_ELEMENTS = 2_000_000


class Jet(NamedTuple):
    """The one-step matrix at each z and what the analyses need of it.

    ``D = M - I``; ``dev = tr D`` (``tr M - 2`` on a 2x2 model, accurate as z -> 0 where
    it behaves like ``-z^2`` while ``tr M`` rounds to 2) and ``dev_m = tr M + 2`` on a 2x2
    model (accurate where M tends to ``-I``). ``sens`` bounds the first-order rounding
    error of each entry of ``D``: ``|computed D - D| <= eps * sens`` entrywise, including
    the amplification by the conditioning of an implicit stage solve; ``scale`` bounds that
    of ``dev`` (``scale_m`` that of ``dev_m``); ``err`` bounds the Frobenius norm of D's
    rounding error. Shapes: (N, m, m) for the matrices, (N,) for the rest; derivatives not
    requested are NaN, ``sens`` and ``scale`` zeros and ``err`` None when not requested."""

    D: np.ndarray
    dM: np.ndarray
    d2M: np.ndarray
    dev: np.ndarray
    scale: np.ndarray
    sens: np.ndarray
    dev_m: np.ndarray
    scale_m: np.ndarray
    err: np.ndarray | None = None

    @property
    def M(self) -> np.ndarray:
        return self.D + np.eye(self.D.shape[-1])

    @property
    def trace(self) -> np.ndarray:
        return self.dev + 2.0

    @property
    def dtrace(self) -> np.ndarray:
        return _trace(self.dM)

    @property
    def d2trace(self) -> np.ndarray:
        return _trace(self.d2M)


def _trace(A: np.ndarray) -> np.ndarray:
    """The traces of a stack of matrices (two entries added for 2x2, the hot case)."""
    return A[:, 0, 0] + A[:, 1, 1] if A.shape[-1] == 2 else np.trace(A, axis1=1, axis2=2)


def jet(D: np.ndarray, dM: np.ndarray, d2M: np.ndarray, sens: np.ndarray | None = None,
        err: np.ndarray | None = None) -> Jet:
    """A :class:`Jet` with ``dev`` from ``D`` and ``scale`` the trace of ``sens``."""
    sens = np.zeros(D.shape) if sens is None else sens
    dev = _trace(D)
    scale = _trace(sens)
    return Jet(D, dM, d2M, dev, scale, sens, dev + 4.0, scale + 4.0, err)


def in_batches(jet_of: Callable[[np.ndarray], Jet], z: np.ndarray, batch: int) -> Jet:
    """``jet_of`` applied to consecutive slices of ``z`` of at most ``batch`` points."""
    parts = [jet_of(z[i:i + batch]) for i in range(0, z.size, batch)]
    return Jet._make(None if field[0] is None else np.concatenate(field)
                     for field in zip(*parts))


class LinearSystem(Protocol):
    """What each kind of block does on one linear system: its jet at unit weight for every
    z in ``z`` (shape (N,)), derivatives up to ``order`` (0, 1 or 2), with the rounding
    bound ``rounding`` asks for."""

    def shears(self, splitting: Splitting, z: np.ndarray, order: int,
               rounding: Rounding) -> Jet: ...

    def stages(self, method: RungeKutta | PartitionedRK, z: np.ndarray, order: int,
               rounding: Rounding) -> Jet: ...

    def friction(self, block: Friction, z: np.ndarray, order: int,
                 rounding: Rounding) -> Jet: ...


def step_jet(blocks: tuple[Block, ...], system: LinearSystem, z: np.ndarray, order: int = 1,
             rounding: Rounding = "entrywise") -> Jet:
    """The jet of the step made of ``blocks`` on ``system`` at every z in ``z`` (see the
    module docstring): one block at weight 1 is that block's jet; several are multiplied
    by :func:`product_jet`."""
    if len(blocks) == 1 and blocks[0].weight == 1.0:
        return block_jet(blocks[0], system, z, order, rounding)
    return product_jet(blocks, system, z, order, rounding)


def block_jet(block: Block, system: LinearSystem, z: np.ndarray, order: int,
              rounding: Rounding) -> Jet:
    """The jet of one block at weight 1 on ``system``."""
    if isinstance(block, Shears):
        return system.shears(block.splitting, z, order, rounding)
    if isinstance(block, Stages):
        return system.stages(block.method, z, order, rounding)
    if isinstance(block, Friction):
        return system.friction(block, z, order, rounding)
    raise TypeError(f"not a block: {type(block).__name__}")


def leaf_key(block: Block) -> tuple:
    """What a block runs: blocks of one key differ only in their weight (a composition's
    substeps), so their matrices are one call at all their ``w z``."""
    if isinstance(block, Shears):
        return ("shears", id(block.splitting))
    if isinstance(block, Stages):
        return ("stages", id(block.method))
    return ("friction", block.gamma, block.kT)


def at_unit_weight(block: Block) -> Block:
    """The block run at weight 1."""
    return block if block.weight == 1.0 else replace(block, weight=1.0)


def _block_jets(blocks: tuple[Block, ...], system: LinearSystem, z: np.ndarray, order: int,
                rounding: Rounding) -> list[Jet]:
    """The jet of every block at its ``w_k z``; the blocks of one key in one call at all
    their ``w z``."""
    n = z.size
    out: list[Jet | None] = [None] * len(blocks)
    groups: dict[tuple, list[int]] = {}
    for k, b in enumerate(blocks):
        groups.setdefault(leaf_key(b), []).append(k)
    for members in groups.values():
        g = np.array([blocks[k].weight for k in members])
        both = block_jet(at_unit_weight(blocks[members[0]]), system, np.outer(g, z).ravel(),
                         order, rounding)
        for i, k in enumerate(members):
            part = slice(i * n, (i + 1) * n)
            out[k] = Jet._make(None if f is None else f[part] for f in both)
    return [j for j in out if j is not None]


def product_jet(blocks: tuple[Block, ...], system: LinearSystem, z: np.ndarray,
                order: int = 1, rounding: Rounding = "entrywise") -> Jet:
    """Product of the blocks' jets ``M = M_n(g_n z) ... M_1(g_1 z)``, accumulated as
    ``D <- D_k + D + D_k D`` (``M = I + D``), the derivatives by the product rule with the
    chain-rule factors ``g_k``, ``g_k^2``.

    Rounding, to first order. Entrywise: the error ``E_k`` of substep k's ``D_k`` (at most
    ``eps sens_k``) reaches the end as ``L_k E_k R_(k-1)`` (``L`` the later substeps, ``R``
    the earlier ones), and the update itself errs by ``2 eps (|D_new| + |D_k| |D|)``,
    carried by ``L_k``; ``sens`` sums these with absolute values. Normwise: ``err`` sums
    ``err_k (1 + ||D||)`` over the substeps, D the product so far."""
    g = np.array([b.weight for b in blocks])
    n = z.size
    jets = _block_jets(blocks, system, z, order, rounding)
    m = jets[0].D.shape[-1]
    eye = np.eye(m)[None, :, :]
    D, dM, d2M = np.zeros((n, m, m)), np.zeros((n, m, m)), np.zeros((n, m, m))
    entrywise = rounding == "entrywise"
    right = np.empty((g.size, n, m, m)) if entrywise else None  # |M_{k-1} ... M_1|
    local = np.empty((g.size, n, m, m)) if entrywise else None
    err = np.zeros(n) if rounding == "norm" else None
    for k, jk in enumerate(jets):
        Mk, M = eye + jk.D, eye + D
        if order >= 2:
            d2M = (g[k] ** 2) * jk.d2M @ M + (2.0 * g[k]) * jk.dM @ dM + Mk @ d2M
        if order >= 1:
            dM = g[k] * jk.dM @ M + Mk @ dM
        new = jk.D + D + jk.D @ D
        if right is not None and local is not None:
            right[k] = np.abs(M)
            local[k] = 2.0 * (np.abs(new) + np.abs(jk.D) @ np.abs(D))
        D = new
        if err is not None:
            assert jk.err is not None
            err = err + jk.err * (1.0 + np.linalg.norm(D, axis=(1, 2)))
    if order < 2:
        d2M = np.full_like(D, np.nan)
    if order < 1:
        dM = np.full_like(D, np.nan)
    if right is None or local is None:
        return jet(D, dM, d2M, err=err)
    L = np.broadcast_to(eye, (n, m, m)).copy()
    sens = np.zeros((n, m, m))
    for k in range(g.size - 1, -1, -1):
        sens += np.abs(L) @ (jets[k].sens @ right[k] + local[k])
        L = L @ (eye + jets[k].D)
    return jet(D, dM, d2M, sens)


# ---------------------------------------------------------------- the stage system


class StageOperator(NamedTuple):
    """``(K, E, B)`` of the stage system ``(I - z K) X = E``, ``M = I + z B X``."""

    K: np.ndarray
    E: np.ndarray
    B: np.ndarray


def stage_operator(method: RungeKutta | PartitionedRK, L: np.ndarray) -> StageOperator:
    """The stage system of one (partitioned) Runge–Kutta step on ``x' = L x``
    (``L = [[L_qq, L_qp], [L_pq, L_pp]]``, n x n blocks): with the stages stacked as
    ``X = (Q_1 .. Q_s; P_1 .. P_s)``,

    ``K = [[A_q (x) L_qq, A_q (x) L_qp], [A_p (x) L_pq, A_p (x) L_pp]]``,
    ``E = [[1 (x) I, 0], [0, 1 (x) I]]`` (s stacked identities),
    ``B = [[b_q^T (x) L_qq, b_q^T (x) L_qp], [b_p^T (x) L_pq, b_p^T (x) L_pp]]``

    (``(x)``: the Kronecker product; for n = 1 the products of the tableaux with the
    model's scalars)."""
    prk = method.as_prk()
    s, n = prk.stages, L.shape[0] // 2
    L_qq, L_qp, L_pq, L_pp = L[:n, :n], L[:n, n:], L[n:, :n], L[n:, n:]
    K = np.block([[np.kron(prk.A_q, L_qq), np.kron(prk.A_q, L_qp)],
                  [np.kron(prk.A_p, L_pq), np.kron(prk.A_p, L_pp)]])
    E = np.zeros((2 * s * n, 2 * n))
    E[:s * n, :n] = np.tile(np.eye(n), (s, 1))
    E[s * n:, n:] = np.tile(np.eye(n), (s, 1))
    b_q, b_p = prk.b_q[None, :], prk.b_p[None, :]
    B = np.block([[np.kron(b_q, L_qq), np.kron(b_q, L_qp)],
                  [np.kron(b_p, L_pq), np.kron(b_p, L_pp)]])
    for array in (K, E, B):
        array.flags.writeable = False
    return StageOperator(K, E, B)


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


class FarForm(NamedTuple):
    """``M(z) = M_inf + B S^-1 V`` for an invertible stage operator (``V = K^-1 E``,
    ``M_inf = I - B V``, the limit as z -> inf), with ``tr M_inf -+ 2`` taken as exactly 0
    when within the rounding policy (:data:`TOL_FACTOR`) of 0: Gauss methods tend to
    ``M = (-1)^s I`` exactly, which float64 coefficients reproduce only to ~1e-16."""

    V: np.ndarray
    minus_2: float  # tr M_inf - 2
    plus_2: float  # tr M_inf + 2
    z_from: float  # used for z >= z_from, where ||(z K)^-1|| <= 1/4


def far_form(op: StageOperator) -> FarForm | None:
    """The :class:`FarForm` of the stage system ``op``, or None if K is (nearly)
    singular."""
    K, E, B = op.K, op.E, op.B
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
    trace = B.shape[0] - float(np.trace(B @ V))
    tol = TOL_FACTOR * EPS * K.shape[0] * float(np.trace(np.abs(B) @ np.abs(K_inv) @ E)) * (
        np.linalg.norm(K, 2) * norm_inv)
    minus_2, plus_2 = trace - 2.0, trace + 2.0
    if abs(minus_2) <= tol:
        minus_2, plus_2 = 0.0, 4.0
    elif abs(plus_2) <= tol:
        minus_2, plus_2 = -4.0, 0.0
    V.flags.writeable = False
    return FarForm(V, minus_2, plus_2, float(4.0 * norm_inv))


def stage_jet(op: StageOperator, far: FarForm | None, z: np.ndarray, order: int = 1,
              rounding: Rounding = "entrywise", norm_L: float = 0.0) -> Jet:
    """``M = I + z B X`` with the stage solve ``S X = E`` (``S = I - z K``), in whichever of
    three exact forms keeps ``dev = tr M - 2`` (and ``tr M + 2``) accurate:

    * small z (``z ||K|| <= 1``): ``D = z B E + z^2 B K X`` (since ``X = E + z K X``): the
      O(z) part is exact and the rest carries the factor z^2;
    * large z (``far``, K invertible): ``M = M_inf + B S^-1 V``, the second part O(1/z) and
      accurate;
    * in between, ``D = z B X`` directly.

    Derivatives without cancellation: ``M' = B S^-2 E``, ``M'' = 2 B K S^-3 E`` (S and K
    commute), i.e. two more solves with the previous solution as right-hand side.

    Rounding, entrywise: the LU solve returns X for some ``S + dS`` with
    ``|dS| <~ 2s eps |S|``, so X errs by ``S^-1 dS X``, and ``z B X`` by
    ``z B S^-1 dS X``, entrywise at most ``2s z |W| |S| |X|`` with ``W = B S^-1`` (a
    transposed solve; ``W = B K S^-1`` and ``z^2`` for the small-z form): the conditioning
    of the stage system enters through ``|W|``. The products add ``2s |B| ...`` terms of
    the same shape. Normwise: ``2 s n eps |z| ||L|| ||X||`` (Frobenius norms, ``norm_L``
    that of the generator L). Long grids
    are processed in batches (80-stage systems on 10^5 points would need gigabytes at
    once)."""
    n2 = op.K.shape[0]
    batch = max(1, BATCH_ELEMENTS // (n2 * n2))
    if z.size > batch:
        return in_batches(lambda zb: stage_jet(op, far, zb, order, rounding, norm_L), z,
                          batch)
    with np.errstate(over="ignore", invalid="ignore"):  # the form not chosen may overflow
        return _stage_forms(op, far, z, order, rounding, norm_L)


def _stage_forms(op: StageOperator, far: FarForm | None, z: np.ndarray, order: int,
                 rounding: Rounding, norm_L: float) -> Jet:
    """The body of :func:`stage_jet` for one batch."""
    K, E, B = op.K, op.E, op.B
    n2, m = K.shape[0], E.shape[1]
    BK, BE = B @ K, B @ E
    zc = z[:, None, None]
    small = (np.abs(z) * np.abs(K).sum(axis=1).max() <= 1.0)[:, None, None]
    use_far = (np.abs(z) >= far.z_from)[:, None, None] if far else np.zeros_like(small)
    S = np.eye(n2)[None, :, :] - zc * K[None, :, :]
    rhs = E if far is None else np.hstack([E, far.V])
    Y = batched_solve(S, np.broadcast_to(rhs, (z.size, n2, rhs.shape[1])).copy())
    X = Y[:, :, :m]
    D = np.where(small, zc * BE[None, :, :] + (zc * zc) * (BK[None, :, :] @ X),
                 zc * (B[None, :, :] @ X))
    dev = _trace(D)
    dev_m = dev + 4.0
    if far is not None:
        BSV = B[None, :, :] @ Y[:, :, m:]
        tail = _trace(BSV)
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
    if rounding != "entrywise":
        err = None
        if rounding == "norm":
            err = n2 * EPS * np.abs(z) * norm_L * np.linalg.norm(X, axis=(1, 2))
        return Jet(D, dM, d2M, dev, np.zeros(z.size), np.zeros(D.shape), dev_m,
                   np.zeros(z.size), err)
    W = batched_solve(S.transpose(0, 2, 1),
                      np.broadcast_to(np.hstack([BK.T, B.T]), (z.size, n2, 2 * m)).copy())
    absW = np.abs(W).transpose(0, 2, 1)
    absY = np.abs(Y)
    absSY = absY + np.abs(zc) * (np.abs(K)[None, :, :] @ absY)  # |S| |Y|
    near = (zc * zc) * (absW[:, :m] @ absSY[:, :, :m]
                        + (np.abs(B) @ np.abs(K))[None, :, :] @ absY[:, :, :m])
    near = near + np.abs(zc) * (np.abs(B) @ E)[None, :, :] / n2
    direct = np.abs(zc) * (absW[:, m:] @ absSY[:, :, :m] + np.abs(B)[None, :, :] @ absY[:, :, :m])
    sens = n2 * np.where(small, near, direct)
    scale = _trace(sens)
    scale_m = scale + 4.0
    if far is not None:
        tail = absW[:, m:] @ absSY[:, :, m:] + np.abs(B)[None, :, :] @ absY[:, :, m:]
        sens = np.where(use_far, n2 * tail, sens)
        tail_scale = _trace(sens)
        far_scale = use_far[:, 0, 0]
        scale = np.where(far_scale, tail_scale + abs(far.minus_2), scale)
        scale_m = np.where(far_scale, tail_scale + abs(far.plus_2), scale_m)
    return Jet(D, dM, d2M, dev, scale, sens, dev_m, scale_m)
