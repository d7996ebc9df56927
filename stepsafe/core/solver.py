"""What an implicit method costs with fixed-point iteration of its stage equations.

A (partitioned) Runge-Kutta step solves ``Q_i = q + h sum_j A_q[i, j] P_j``,
``P_i = p + h sum_j A_p[i, j] f(Q_j)``. Fixed-point iteration starts from ``Q_i = q``,
``P_i = p`` and repeats

    F = f(Q)                      (one force evaluation per stage that varies)
    Q, P = q + h A_q P, p + h A_p F

until the largest change of a stage value is at most ``tol`` times the largest stage
value (and 1); the step then takes one more force evaluation per stage for its update.
On the test models this is the linear iteration ``X <- E + z K X`` (``K`` the stage
operator of :func:`stepsafe.core.transfer.stage_operator`), whose changes are
``(z K)^j z K E`` exactly: the count below is that of the algorithm above for the worse of
the two unit states, not an estimate. It converges iff the spectral radius of ``z K`` is
below 1, i.e. for ``z < 1 / rho(K)``: beyond, fixed-point iteration diverges and the
method needs Newton's method.

Simplified Newton's method (``newton_cost``) iterates ``X <- X - J^-1 G(X)`` with the stage
system's Jacobian ``J`` taken once per step (one Hessian evaluation and one factorisation
per distinct substep). On the test models G is linear and J exact, so the first iteration
lands on the solution and the second sees a change at rounding level: 2 iterations at every
z, with the same stopping rule and evaluation count as fixed-point iteration, and no
convergence limit (only the poles, where J is singular).

Force evaluations per step: the stages whose ``A_q`` row is zero have ``Q_i = q`` for
good and cost one evaluation per step, none when the method reuses the previous step's
last force (first same as last: a stage with ``A_q`` row equal to ``b_q`` ends at
``q_{n+1}``, as in Lobatto IIIA-IIIB); every other stage costs one per iteration and one
for the update.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from stepsafe.core.sets import distinct
from stepsafe.methods.protocol import Stages
from stepsafe.methods.tableaux import Method, PartitionedRK

#: Default stopping tolerance (relative change of the stage values).
DEFAULT_TOL = 1e-14
#: Iterations beyond which the iteration counts as not converging.
MAX_ITERATIONS = 1000
#: Simplified Newton passes per step on a linear model: the solving one and the check.
NEWTON_ITERATIONS = 2


@dataclass(frozen=True)
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
    from stepsafe.core.transfer import blocks_of

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
    scale = max(float(np.abs(prk.b_q).max()), 1e-300)
    fsal = bool(np.any(np.all(np.abs(prk.A_q - prk.b_q[None, :]) <= 4e-16 * scale, axis=1)))
    return int((~zero).sum()), (0 if fsal else int(zero.any()))


def fixed_point_cost(method: Method, z: float, model: str = "oscillator",
                     tol: float = DEFAULT_TOL) -> SolverCost:
    """Iterations and force evaluations per step at ``z = beta h`` for the worse of the two
    unit states (see the module docstring); explicit methods cost their nominal
    evaluations and never diverge. A composition's substeps are all counted at its largest
    substep (an upper bound)."""
    from stepsafe.core.transfer import stage_operator

    found = _prk_of(method)
    if found is None:
        return SolverCost(z, 0, getattr(method, "evaluations", None), np.inf)
    prk, substeps = found
    g = _largest_weight(method)
    K, E, _ = stage_operator(prk, model)
    limit = fixed_point_limit(method, model)
    varying, fixed = evaluation_pattern(prk)
    counts = [_iterations(K, E[:, k], z * g, tol) for k in range(E.shape[1])]
    if any(c is None for c in counts):
        return SolverCost(z, None, None, limit)
    iterations = max(counts)
    return SolverCost(z, iterations, (varying * (iterations + 1) + fixed) * substeps, limit)


def newton_cost(method: Method, z: float) -> SolverCost:
    """Iterations and force evaluations per step of simplified Newton's method at any z
    (see the module docstring); ``limit`` is inf. Explicit methods cost their nominal
    evaluations."""
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
    of the stages diverges; inf for explicit methods."""
    from stepsafe.core.transfer import stage_operator

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
    """Passes of ``x <- e + z K x`` from ``x = e`` until the change is at most ``tol``
    times ``max(1, |x|)`` (max norms), as the solver runs them for the state ``e``."""
    x = e.copy()
    for iteration in range(1, MAX_ITERATIONS + 1):
        x_new = e + z * (K @ x)
        change = float(np.abs(x_new - x).max())
        x = x_new
        if not np.isfinite(change):
            return None
        if change <= tol * max(1.0, float(np.abs(x).max())):
            return iteration
    return None
