"""The 2x2 one-step (transfer) matrix M(z) of any method on a test model, with dM/dz.

The step engine (docs/theory.md#the-one-step-matrix; :func:`stepsafe.core.engine.step_jet`,
the one routine that also builds the 2n x 2n map of :mod:`stepsafe.systems.coupled`) turns
the blocks of a method's step (:func:`stepsafe.methods.tableaux.linear_blocks`) into
``M(z)``, each block's matrix at
``w z`` for its weight w, multiplied in order; a test model (:class:`TestModel`) gives the
matrix of each block:

* Stages (RK / PRK): the engine's stage system on the model's generator ``L``
  (:func:`stepsafe.core.engine.stage_operator`; for n = 1, with the stages stacked as
  ``X = (Q; P)``: ``(I - z K) X = E``, ``K = [[A_q L_qq, A_q L_qp], [A_p L_pq, A_p L_pp]]``,
  ``E = [[1, 0], [0, 1]]`` (blocks of ones), ``M = I + z B X``,
  ``B = [[b_q L_qq, b_q L_qp], [b_p L_pq, b_p L_pp]]``). Differentiating,
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

import numpy as np

from stepsafe.core.engine import (
    BATCH_ELEMENTS,
    EPS,
    FarForm,
    Jet,
    Rounding,
    StageOperator,
    at_unit_weight,
    in_batches,
    leaf_key,
    stage_jet,
    step_jet,
)
from stepsafe.core.engine import far_form as engine_far_form
from stepsafe.core.engine import jet as make_jet
from stepsafe.core.engine import stage_operator as engine_stage_operator
from stepsafe.core.models import GENERATORS, KICK_SIGN, check_model
from stepsafe.methods.protocol import (
    DIAGONAL_MODELS,
    Block,
    Friction,
    MethodKind,
    Shears,
    Stages,
)
from stepsafe.methods.tableaux import Method, PartitionedRK, RungeKutta, Splitting, linear_blocks


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
    """:func:`~stepsafe.methods.tableaux.linear_blocks` of ``method`` on ``model``, cached
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
    splitting = _as_plain_splitting(method, model)
    if splitting is not None:
        check_model(model)
        return _splitting_matrix(splitting, np.atleast_1d(np.asarray(z, dtype=float)), model)
    return transfer_jet(method, z, model, scale=False, order=0).M


def _as_plain_splitting(method: Method, model: str) -> Splitting | None:
    """The splitting whose product of factors is ``method``'s M on ``model`` (its one block
    of shears at weight 1, :func:`blocks_of`), None where :func:`transfer_jet` takes
    another route (the saddle models, Runge-Kutta and Langevin methods, several blocks)."""
    if model in ("saddle", "saddle-p"):
        return None
    blocks = blocks_of(method, model)
    if len(blocks) == 1 and blocks[0].weight == 1.0 and isinstance(blocks[0], Shears):
        return blocks[0].splitting
    return None


def _splitting_matrix(method: Splitting, z: np.ndarray, model: str) -> np.ndarray:
    """``M(z) = I + D`` of a splitting: :func:`_splitting_jet`'s ``D`` without derivatives
    or rounding bounds, the same operations in the same order on the four entries held
    apart (bit for bit its ``M``, at a fraction of the cost on large arrays of z)."""
    D = [[np.zeros(z.size), np.zeros(z.size)], [np.zeros(z.size), np.zeros(z.size)]]
    for src, dst, c, power in row_ops(method, model):
        cz = _scaled_power(c, z, power)
        old = [D[src][0], D[src][1]]
        old[src] = old[src] + 1.0
        D[dst][0] = D[dst][0] + cz * old[0]
        D[dst][1] = D[dst][1] + cz * old[1]
    M = np.empty((z.size, 2, 2))
    for i in range(2):
        for j in range(2):
            M[:, i, j] = D[i][j] + (1.0 if i == j else 0.0)
    return M


def transfer_jet(method: Method, z, model: str = "oscillator", scale: bool = True,
                 order: int = 1) -> Jet:
    """``M`` with its derivatives up to ``order`` (0, 1 or 2) and, unless ``scale=False``
    (then zeros), the entrywise rounding sensitivity. Derivatives above ``order`` are NaN;
    implicit methods pay one extra stage solve per order."""
    check_model(model)
    z = np.atleast_1d(np.asarray(z, dtype=float))
    return step_jet(blocks_of(method, model), _MODELS[model], z, order,
                    "entrywise" if scale else None)


class TestModel:
    """A 2x2 test model (:mod:`stepsafe.core.models`) as a
    :class:`~stepsafe.core.engine.LinearSystem` of the step engine, z = beta h: a
    splitting by the closed forms of its factors (:func:`_splitting_jet` on the kinetic +
    potential models, :func:`_euler_factor_jet` on the saddles), a Runge–Kutta step by the
    engine's stage system on the model's generator, the friction step on the oscillator."""

    __test__ = False  # not a pytest class

    def __init__(self, model: str) -> None:
        self.model = model

    def shears(self, splitting: Splitting, z: np.ndarray, order: int,
               rounding: Rounding) -> Jet:
        if self.model == "saddle":
            return _euler_factor_jet(splitting, z)
        if self.model == "saddle-p":  # the saddle at -z: M(z) = M_saddle(-z), dM = -dM_saddle
            out = _euler_factor_jet(splitting, -z)
            return out._replace(dM=-out.dM)
        return _splitting_jet(splitting, z, self.model, rounding == "entrywise", order)

    def stages(self, method: RungeKutta | PartitionedRK, z: np.ndarray, order: int,
               rounding: Rounding) -> Jet:
        return stage_jet(stage_operator(method, self.model), far_form(method, self.model), z,
                         order, rounding, norm_L=float(np.linalg.norm(GENERATORS[self.model])))

    def friction(self, block: Friction, z: np.ndarray, order: int,
                 rounding: Rounding) -> Jet:
        return _friction_jet(block, z, self.model, order)


_MODELS = {model: TestModel(model) for model in GENERATORS}


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
    return make_jet(D, dM if order >= 1 else nan, d2M if order >= 2 else nan, sens)


@lru_cache(maxsize=64)
def stage_operator(method: RungeKutta | PartitionedRK, model: str) -> StageOperator:
    """``(K, E, B)`` of the stage system ``(I - z K) X = E``, ``M = I + z B X`` on the
    model's generator (:func:`stepsafe.core.engine.stage_operator`; cached per method
    object and model: the region finder evaluates the same method many times)."""
    return engine_stage_operator(method, GENERATORS[model])


@lru_cache(maxsize=64)
def far_form(method: RungeKutta | PartitionedRK, model: str) -> FarForm | None:
    """The :class:`~stepsafe.core.engine.FarForm` of ``method`` on ``model`` (None if its
    K is nearly singular), cached as :func:`stage_operator`."""
    return engine_far_form(stage_operator(method, model))


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
    ops = row_ops(method, model)
    n = z.size
    batch = max(1, BATCH_ELEMENTS // max(4 * len(ops), 1))
    if n > batch:
        return in_batches(lambda zb: _splitting_jet(method, zb, model, with_scale, order),
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
    out = [T[k].transpose(2, 0, 1) * factorial for k, factorial in zip(range(order + 1), (1, 1, 2))]
    nan = np.full((n, 2, 2), np.nan)
    out += [nan] * (3 - len(out))
    return make_jet(out[0], out[1], out[2], sens)


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
        base, unc = _block_poles(at_unit_weight(b), model)
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
