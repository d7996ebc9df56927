"""What an implicit method costs with its stage equations solved by fixed-point iteration
or by simplified Newton's method.

A (partitioned) Runge-Kutta step solves ``Q_i = q + h sum_j A_q[i, j] V_j``,
``P_i = p + h sum_j A_p[i, j] F_j`` with ``V_j = dH/dp(Q_j, P_j)`` and the forces
``F_j = -dH/dq(Q_j, P_j)``. Fixed-point iteration starts from ``Q_i = q``, ``P_i = p`` and
sweeps in Gauss-Seidel order, the positions first and the momenta from the forces at the
new positions:

    Q <- q + h A_q V(Q, P)
    F <- f(Q, P)                  (one force evaluation per stage that varies)
    P <- p + h A_p F

until the largest change of a stage value is at most ``tol`` times the largest stage
value (and 1). When the force depends on q only (a separable H), the forces of the last
sweep are those at the converged positions and the update ``p + h b_p F`` reuses them;
otherwise the step takes one more force evaluation per varying stage at the converged
stages. On the test models this is the linear iteration ``x_q <- e_q + z (K_qq x_q +
K_qp x_p)``, ``x_p <- e_p + z (K_pq x_q + K_pp x_p)`` (the new ``x_q``; ``K`` the stage
operator of :func:`stepsafe.core.transfer.stage_operator`), and the count below is that of
the algorithm above for the worse of the two unit states, not an estimate. On a separable
model ``K`` has zero diagonal blocks, the sweep's iteration matrix is ``z^2 K_pq K_qp`` on
the momenta, and its spectral radius is ``rho(z K)^2``: about half the passes of the
Jacobi order (every stage from the previous pass), with the same convergence limit
``z < 1 / rho(K)``. Beyond it fixed-point iteration diverges and the method needs Newton's
method.

Simplified Newton's method (``newton_cost``) iterates ``X <- X - J^-1 G(X)`` with the stage
system's Jacobian ``J`` taken once per step (one Hessian evaluation and one factorisation
per distinct substep). On the test models G is linear and J exact, so the first iteration
lands on the solution and the second sees a change at rounding level: 2 iterations at every
z, each evaluating the forces at the current stages, one more evaluation per stage for
the update, and no convergence limit (only the poles, where J is singular). Its cost in
force evaluations is those plus ``jacobian_cost`` per Jacobian (the Hessian and its
factorisation, in force evaluations: the caller's estimate).

Force evaluations per step: the stages whose ``A_q`` row is zero have ``Q_i = q`` for
good and cost one evaluation per step, none when the method reuses the previous step's
last force (first same as last: a stage whose ``A_q`` row is ``b_q`` ends at
``q_{n+1}``, as Lobatto IIIA's last; :func:`~stepsafe.methods.tableaux.step_end_stage`
decides it on the coefficients as written); every other stage costs one per iteration
(and, for Jacobi-order or Newton iterations, one for the update).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from stepsafe.comparison import compared
from stepsafe.core.sets import distinct
from stepsafe.core.transfer import blocks_of, stage_operator
from stepsafe.methods.protocol import Stages
from stepsafe.methods.tableaux import Method, PartitionedRK, step_end_stage

#: Default stopping tolerance (relative change of the stage values).
DEFAULT_TOL = 1e-14
#: Iterations beyond which the iteration counts as not converging.
MAX_ITERATIONS = 1000
#: Simplified Newton passes per step on a linear model: the solving one and the check.
NEWTON_ITERATIONS = 2


@compared
@dataclass(frozen=True, eq=False)
class SolverCost:
    """Fixed-point iterations and force evaluations of one step at ``z`` (None where the
    iteration diverges or needs more than :data:`MAX_ITERATIONS`), and ``limit`` =
    ``1 / rho(K)``, the z beyond which it diverges (inf for explicit methods)."""

    z: float
    iterations: int | None
    evaluations: int | None
    limit: float


def _implicit_blocks(method: Method) -> list[Stages]:
    """The blocks of a step that solve stage equations (one per implicit substep)."""
    if method.explicit:
        return []
    return [b for b in blocks_of(method, None) if isinstance(b, Stages)
            and not b.method.explicit]


def _prk_of(method: Method) -> tuple[PartitionedRK, int] | None:
    """The PRK tableau of an implicit method and its substeps per step (None: explicit)."""
    blocks = _implicit_blocks(method)
    if not blocks:
        return None
    prk = blocks[0].method.rk_form()
    assert prk is not None
    return prk, len(blocks)


def evaluation_pattern(prk: PartitionedRK) -> tuple[int, int]:
    """``(varying, fixed)``: stages evaluated every iteration, and force evaluations per
    step for the stages fixed at ``q`` (0 when the last one is reused)."""
    zero = ~np.any(prk.A_q != 0, axis=1)
    fsal = step_end_stage(prk) is not None
    return int((~zero).sum()), (0 if fsal else int(zero.any()))


def fixed_point_cost(method: Method, z: float, model: str = "oscillator",
                     tol: float = DEFAULT_TOL) -> SolverCost:
    """Gauss-Seidel fixed-point iterations and force evaluations per step at ``z = beta h``
    for the worse of the two unit states (see the module docstring); explicit methods cost
    their nominal evaluations and never diverge. A composition's substeps are all counted
    at its largest substep (an upper bound)."""
    found = _prk_of(method)
    if found is None:
        return SolverCost(z, 0, getattr(method, "evaluations", None), np.inf)
    prk, substeps = found
    g = _largest_weight(method)
    K, E, _ = stage_operator(prk, model)
    limit = fixed_point_limit(method, model)
    varying, fixed = evaluation_pattern(prk)
    counts = [_iterations(K, E[:, k], z * g, tol) for k in range(E.shape[1])]
    known = [c for c in counts if c is not None]
    if len(known) < len(counts):
        return SolverCost(z, None, None, limit)
    iterations = max(known)
    s = prk.stages
    separable = not (K[:s, :s].any() or K[s:, s:].any())  # the force depends on q only
    update = 0 if separable else varying  # else the forces again at the converged stages
    return SolverCost(z, iterations, (varying * iterations + update + fixed) * substeps,
                      limit)


def newton_cost(method: Method, z: float) -> SolverCost:
    """Iterations and force evaluations per step of simplified Newton's method at any z
    (see the module docstring; its Jacobians are :func:`factorizations`); ``limit`` is
    inf. Explicit methods cost their nominal evaluations."""
    found = _prk_of(method)
    if found is None:
        return SolverCost(z, 0, getattr(method, "evaluations", None), np.inf)
    prk, substeps = found
    varying, fixed = evaluation_pattern(prk)
    return SolverCost(z, NEWTON_ITERATIONS, (varying * (NEWTON_ITERATIONS + 1) + fixed)
                      * substeps, np.inf)


def factorizations(method: Method) -> int:
    """Jacobians factorised per step by simplified Newton's method: one per distinct
    substep size of an implicit method (0 for explicit methods)."""
    blocks = _implicit_blocks(method)
    if not blocks:
        return 0
    return int(distinct(np.abs([b.weight for b in blocks])).size)


def _largest_weight(method: Method) -> float:
    """The largest substep of a composition, in steps (1 otherwise): it binds."""
    blocks = _implicit_blocks(method)
    return float(np.abs([b.weight for b in blocks]).max()) if blocks else 1.0


def fixed_point_limit(method: Method, model: str = "oscillator") -> float:
    """``1 / rho(K)`` (over the largest substep): the z beyond which fixed-point iteration
    of the stages diverges on a separable model (oscillator, inverted: the Gauss-Seidel
    sweep's spectral radius is ``rho(z K)^2``); inf for explicit methods."""
    found = _prk_of(method)
    if found is None:
        return np.inf
    K, _, _ = stage_operator(found[0], model)
    rho = float(np.abs(np.linalg.eigvals(K)).max())
    return np.inf if rho == 0 else 1.0 / (rho * _largest_weight(method))


def step_limit(method: Method, betas: Mapping[str, np.ndarray]) -> float | None:
    """The largest h at which fixed-point iteration converges for every frequency of the
    vibration and barrier models (None: explicit, or no such frequency)."""
    models = [m for m in ("oscillator", "inverted") if m in betas]
    top = max((float(np.max(b)) for b in betas.values()), default=0.0)
    if not models or not top > 0:
        return None
    limit = min(fixed_point_limit(method, m) for m in models)
    return float(limit / top) if np.isfinite(limit) else None


def system_step_limit(method: Method, betas: Mapping[str, np.ndarray] | None,
                      hessians: list[np.ndarray]) -> float | None:
    """:func:`step_limit` for a whole system: its decoupled frequencies, and for each
    coupled piece (Hessian S) the largest |eigenvalue| of ``J S`` taken as a vibration and
    as a barrier of that rate (fixed-point iteration of the stages is the linear iteration
    ``X <- E + h (A x J S) X``, whose spectral radius grows with that of J S)."""
    limits = []
    if betas:
        limit = step_limit(method, betas)
        if limit is not None:
            limits.append(limit)
    for S in hessians:
        n = S.shape[0] // 2
        top = float(np.abs(np.linalg.eigvals(np.vstack([S[n:], -S[:n]]))).max())
        if top > 0:
            unit = min(fixed_point_limit(method, m) for m in ("oscillator", "inverted"))
            if np.isfinite(unit):
                limits.append(unit / top)
    return min(limits) if limits else None


def _iterations(K: np.ndarray, e: np.ndarray, z: float, tol: float) -> int | None:
    """Gauss-Seidel passes ``x_q <- e_q + z K_q x``, then ``x_p <- e_p + z K_p x`` (with the
    new ``x_q``) from ``x = e`` until the change is at most ``tol`` times ``max(1, |x|)``
    (max norms), as the solver runs them for the state ``e``."""
    s = K.shape[0] // 2
    K_q, K_p = K[:s], K[s:]
    x = e.copy()
    for iteration in range(1, MAX_ITERATIONS + 1):
        x_new = x.copy()
        x_new[:s] = e[:s] + z * (K_q @ x)
        x_new[s:] = e[s:] + z * (K_p @ x_new)  # (its p part is still the old one)
        change = float(np.abs(x_new - x).max())
        x = x_new
        if not np.isfinite(change):
            return None
        if change <= tol * max(1.0, float(np.abs(x).max())):
            return iteration
    return None
