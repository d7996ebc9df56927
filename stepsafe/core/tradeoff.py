"""Speed against accuracy for a set of frequencies: what each method costs
(docs/theory.md#accuracy-and-cost).

For a method and modes, the usable step is ``h = min(h_safe, h_tol)``: ``h_safe`` from
:mod:`stepsafe.core.advice`, ``h_tol`` the largest step whose error stays within tolerance for
the largest frequency of each model (errors depend on z = beta h only and grow from 0, so
the largest beta binds). The cost per unit of simulated time is ``evaluations / h``
(= evaluations * beta / z): force evaluations per step as listed in the method file; for
implicit methods, by default, those of fixed-point iteration of the stage equations to
1e-14 at the largest beta h (:mod:`stepsafe.core.solver`), whose convergence limit also
bounds h (``bound_by = "solver"``); ``solver="newton"`` counts simplified Newton's
method (2 iterations on the test models, any h), its cost being its force evaluations plus
``jacobian_cost`` per Jacobian; ``solver="best"`` takes whichever of the two costs less per
unit time at the step it allows (``Tradeoff.solver`` says which);
``solver="nominal"`` counts one per stage.

A processed method ``P^-1 K P`` costs its kernel's evaluations per step plus a one-off
``processor_evaluations``: P once before the first step and P^-1 for each output (each as
many forces as P has kicks). Over a run of T with outputs every ``T_out`` it adds
``2 n_P / T`` at most per unit time when ``T_out = T``, ``n_P / T_out`` per output otherwise;
the cost column stays the per-step cost and the one-off part is reported beside it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from stepsafe.core.accuracy import errors, z_for_tolerance
from stepsafe.core.advice import Advice, Modes, advise
from stepsafe.core.models import ELLIPTIC
from stepsafe.core.solver import factorizations, fixed_point_cost, newton_cost, step_limit
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method


def energy_exact(method: Method) -> bool:
    """Whether the method's energy error on the oscillator is 0 at every step (to rounding,
    checked at z = 0.1, 0.5, 1): symplectic Runge-Kutta methods such as Gauss conserve
    every quadratic invariant, the linear model's energy among them."""
    with np.errstate(all="ignore"):
        energy = np.asarray(errors(method, np.array([0.1, 0.5, 1.0])).energy, dtype=float)
    return bool(np.all(np.isfinite(energy)) and np.all(np.abs(energy) <= 1e-13))


class Tolerance(NamedTuple):
    kind: str  # "phase" (growth rate for hyperbolic models) or "energy"
    value: float


class ToleranceLimit(NamedTuple):
    model: str
    kind: str
    tol: float
    beta: float
    z: float | None
    h: float | None  # None when no step meets it, or every float step does
    limited_by: str  # "tolerance", "boundary" (met up to z*), "unreachable", or
    #                  "beyond-float" (its step is past the largest float: no limit)


class Tradeoff(NamedTuple):
    method: str
    advice: Advice
    limits: tuple[ToleranceLimit, ...]
    h: float | None  # the step to use: min(h_safe, h_tol); None if unbounded
    bound_by: str  # "safety", "accuracy", "horizon" (the analysed range) or "nothing"
    evaluations: float | None
    cost: float | None  # evaluations per unit time at h
    iterations: int | None = None  # fixed-point iterations per step (implicit methods)
    #: processed methods: forces of P (once) and of P^-1 (each output); None otherwise
    processor_evaluations: int | None = None
    #: implicit methods: the stage solver counted (``fixed-point`` or ``newton``) and,
    #: for Newton, its Jacobians per step (their cost is in ``cost``)
    solver: str | None = None
    jacobians: int | None = None


#: How an implicit method's cost is counted: its stages solved by fixed-point iteration or
#: by simplified Newton's method (:mod:`stepsafe.core.solver`; Newton adds a Jacobian and
#: its factorisation per step, at ``jacobian_cost`` force evaluations each), the cheaper
#: of the two at the step each allows (``best``), or the nominal count of one per stage.
SOLVERS = ("fixed-point", "newton", "best", "nominal")
#: A Jacobian (the Hessian at the step's start and the factorisation of the stage
#: system) in force evaluations, by default: a few degrees of freedom, where a Hessian
#: costs about one gradient by automatic differentiation and the factorisation of a
#: matrix of 2 s d rows is negligible.
JACOBIAN_COST = 1.0
#: Fixed-point iteration is used up to this fraction of its convergence limit (beyond, its
#: iteration count grows without bound).
SOLVER_REACH = 0.9


def tradeoff(method: Method, modes: Modes, tolerances: tuple[Tolerance, ...] = (),
             margin: float = 1.0, name: str | None = None,
             evaluations: float | None = None, zmax: float | None = None,
             resonance_order: int | None = None, solver: str = "fixed-point",
             criterion: str = "structure", jacobian_cost: float = JACOBIAN_COST
             ) -> Tradeoff:
    kinds = {t.kind for t in tolerances}
    if "energy" in kinds and "phase" not in kinds and energy_exact(method):
        raise StepsafeError(
            f"{name or method.name} keeps the energy of every linear model exactly (it "
            "conserves quadratic invariants), so --tol-energy alone would recommend the "
            "largest safe step, which says nothing about a nonlinear system: give "
            "--tol-phase as well")
    extent: dict[str, Any] = {} if zmax is None else {"zmax": zmax}
    adv = advise(method, modes, margin, name=name, resonance_order=resonance_order,
                 criterion=criterion, **extent)
    limits: list[ToleranceLimit] = []
    for tol in tolerances:
        if not (tol.value > 0):
            raise ValueError(f"--tol-{tol.kind} must be positive, got {tol.value}")
        for lim in adv.models:
            if tol.kind == "energy" and not ELLIPTIC[lim.model]:
                continue
            if lim.beta_max == 0:
                continue
            region = adv.regions[lim.model]
            z_star = region.first_boundary if region.first_boundary is not None else region.zmax
            step = z_for_tolerance(method, tol.value, z_star, lim.model, tol.kind)
            h = None if step.z is None else margin * step.z / lim.beta_max
            limited_by = step.limited_by
            if h is not None and not np.isfinite(h):  # beta ~ 1e-310: past every float
                h, limited_by = None, "beyond-float"
            limits.append(ToleranceLimit(lim.model, tol.kind, tol.value, lim.beta_max, step.z,
                                         h, limited_by))
    # the safe interval is open: a step to use lies strictly inside it
    h_safe = None if adv.h_max is None else float(np.nextafter(adv.h_max, 0.0))
    h_tol = min((lim.h for lim in limits if lim.h is not None), default=None)
    if any(lim.limited_by == "unreachable" for lim in limits):
        h_tol = 0.0
    candidates: list[tuple[float, str]] = [
        (h, why) for h, why in ((h_safe, "safety"), (h_tol, "accuracy")) if h is not None]
    if not candidates:
        h, bound = None, "nothing"
    else:
        h, bound = min(candidates, key=lambda pair: pair[0])
        if h_tol is not None and h_safe is not None and h_tol >= h_safe:
            bound = "safety"
        if bound == "safety" and adv.h_max_is_horizon:
            bound = "horizon"  # no boundary below the analysed range: not a safety limit
    evals = evaluations if evaluations is not None else getattr(method, "evaluations", None)
    iterations, used, jacobians = None, None, None
    cost = None if (h is None or h == 0 or evals is None) else evals / h
    if solver in ("fixed-point", "newton", "best") and not method.explicit and h:
        options = []
        if solver in ("fixed-point", "best"):
            option = _fixed_point(method, modes, h, bound)
            if option is not None:
                options.append(option)
            elif solver == "fixed-point":  # (no count: the nominal one, as before)
                options.append(_Solved("fixed-point", h, bound, evals, None, 0, cost))
        if solver in ("newton", "best"):
            options.append(_newton(method, h, bound, jacobian_cost))
        if options:
            best = min(options, key=lambda o: (o.cost is None, o.cost or 0.0))
            h, bound, evals, iterations, cost = (best.h, best.bound, best.evaluations,
                                                 best.iterations, best.cost)
            used, jacobians = best.solver, best.jacobians or None
    processor = method.processor_evaluations
    return Tradeoff(adv.method, adv, tuple(limits), h, bound, evals, cost, iterations,
                    processor, used, jacobians)


class _Solved(NamedTuple):
    """An implicit method's step, cost and counts with one stage solver."""

    solver: str
    h: float
    bound: str
    evaluations: float | None
    iterations: int | None
    jacobians: int
    cost: float | None  # (evaluations + jacobian_cost * jacobians) / h


def _fixed_point(method: Method, modes: Modes, h: float, bound: str) -> _Solved | None:
    """Fixed-point iteration at h, h capped at :data:`SOLVER_REACH` of its convergence
    limit (None: it does not converge there)."""
    top = max(float(b.max()) for b in modes.betas.values())
    models = [m for m in modes.betas if m in ("oscillator", "inverted")] or ["oscillator"]
    h_limit = step_limit(method, modes.betas)
    if h_limit is not None and h > SOLVER_REACH * h_limit:
        h, bound = SOLVER_REACH * h_limit, "solver"
    costs = [fixed_point_cost(method, h * top, m) for m in models]
    if any(c.evaluations is None for c in costs):
        return None
    evals = max(c.evaluations for c in costs if c.evaluations is not None)
    iterations = max(c.iterations for c in costs if c.iterations is not None)
    return _Solved("fixed-point", h, bound, evals, iterations, 0, evals / h)


def _newton(method: Method, h: float, bound: str, jacobian_cost: float) -> _Solved:
    """Simplified Newton's method at h: its force evaluations and ``jacobian_cost`` per
    Jacobian (evaluated and factorised once per distinct substep)."""
    cost_n = newton_cost(method, h)
    jacobians = factorizations(method)
    evals = cost_n.evaluations
    cost = None if evals is None else (evals + jacobian_cost * jacobians) / h
    return _Solved("newton", h, bound, evals, cost_n.iterations, jacobians, cost)
