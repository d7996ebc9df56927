"""HMC advice for Gaussian targets: the public :func:`hmc` behind ``stepsafe hmc``.

For each method: the stability limit of the fastest mode (and the structure limit where it
differs), the predicted acceptance rate as a function of h (:mod:`stepsafe.core.hmc`), the
largest step whose acceptance reaches the target (default 0.8, Stan's ``adapt_delta``), and
the cost in gradient evaluations per proposal, per accepted proposal and per accepted unit
of simulated time. Methods are ranked by the report's ``ranked_by``
(:data:`stepsafe.core.hmc.RANKINGS`): with the trajectory given (L steps, or an integration
time T, L = floor(T / h)) by gradient evaluations per accepted proposal at the L the sampler
runs, ``(L e + overhead) / acceptance``; without one by gradient evaluations per accepted unit
of simulated time (there is no L to count a proposal by).

Jitter. A sampler with jitter J draws each step from ``h (1 - J, 1 + J)``: the step at
target is searched below ``limit / (1 + J)`` (rounded down so that ``h (1 + J)`` computed in
float64 stays within it), ``limit`` the criterion's step limit of the fastest mode, so that
no jittered step is unstable. A step whose longest draws pass the stability limit makes the
trajectories that draw them grow without bound (Stan's divergent transitions), while the
acceptance averaged over the jitter can still look fine. ``allow_unstable_jitter`` searches
up to ``limit`` itself, as for a fixed step; the fraction of unstable draws,
``(h (1 + J) - limit) / (2 J h)``, is then stated wherever it is not 0: wherever the longest
draw as float64 computes it, ``h * (1 + J)``, passes the stability limit.

A processed method ``P^-1 K P`` proposes ``x -> P^-1 K^L P x``: its one-step matrix is the
full map ``P^-1 M_K P`` (:mod:`stepsafe.core.transfer`), whose L-th power is the proposal,
so the energy errors and acceptance of :mod:`stepsafe.core.hmc` are the processed
trajectory's. Each proposal pays P and P^-1 once: ``2 n_P`` gradient evaluations on top of
``L`` kernel steps (per accepted unit of time too, when L is known). With the momentum
flip ``S`` and a palindromic kernel (``S K S = K^-1``), ``S (P^-1 K^L P) S`` is the
inverse of the proposal only when ``S P S = P``; a drift/kick processor has
``S P_h S = P_-h``, so the proposal is reversible only for a processor even in h, and an
HMC chain with any other does not satisfy detailed balance: it drifts away from the
target, and the predicted acceptance is only that of a proposal from the target. Such
methods are listed but not ranked. ``P* K^L P`` with ``P* = S P^-1 S`` (the processor's
adjoint) would be reversible for every P; it is not the L-th power of one map and is not
offered here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from stepsafe.api.hmc_reports import DesignReport, HmcReport, HmcRow
from stepsafe.api.hmc_target import on_target, target_of
from stepsafe.api.inputs import (
    ArrayLike,
    Integrator,
    Problem,
    UnitValues,
    compared_methods,
    problem_of,
    step_cost,
)
from stepsafe.api.keywords import shared_keywords
from stepsafe.arguments import public
from stepsafe.core import hmc as core
from stepsafe.core.advice import SHRINK, Modes, first_unsafe_z
from stepsafe.core.design import OBJECTIVES, PARAMETERS, STABLE_LIMIT, family_member, minimax
from stepsafe.core.design import design as core_design
from stepsafe.core.hmc import MAX_EXACT_MODES, Trajectory
from stepsafe.core.hmc_target.advice import TargetReport
from stepsafe.core.hmc_target.draws import SEED as TARGET_SEED
from stepsafe.core.regions import find_region, stable_run, validate_criterion
from stepsafe.core.roots import EPS
from stepsafe.core.solver import fixed_point_cost, step_limit
from stepsafe.core.tradeoff import SOLVER_REACH
from stepsafe.exceptions import StepsafeError, finite_real, positive_finite
from stepsafe.methods.families import is_symmetric
from stepsafe.methods.tableaux import validate_gradient_cost
from stepsafe.systems.loader import DENSE_LIMIT
from stepsafe.systems.scene import Scene, scene_time_unit
from stepsafe.units import duration

#: Stall steps (L theta = 2 pi m) are reported within this relative distance of the target
#: step (or within the jitter, if wider).
STALL_WINDOW = 0.1
#: A row's note when its acceptance at h at target is approximate (the report's
#: ``approximate`` says whether any row has it).
APPROXIMATE_NOTE = ("the acceptance at h at target is approximate (more distinct modes than "
                    "a checked rule of the spectrum stands for, turns of L theta across the "
                    "jitter, or steps L than float64 integrates exactly: above 1e6 steps "
                    "L theta carries an error of eps L pi)")
#: Significant digits of a ranking's cost that order the methods (fewer than the search for
#: h at target resolves).
RANK_DIGITS = 5
#: Methods compared when none are named: the integrators HMC codes ship.
HMC_DEFAULT = ("verlet", "mclachlan2-min", "bcss2", "bcss3", "yoshida4", "pefrl")


class TargetError(StepsafeError):
    """The frequencies given are not those of a Gaussian target HMC can sample."""


def _validated(target: float, steps: int | None, length: float | None,
               jitter: float) -> tuple[float, int | None, float | None, float]:
    if not 0.0 < finite_real(target, "target acceptance") < 1.0:
        raise StepsafeError(f"target acceptance must be a number in (0, 1), got {target!r}")
    if steps is not None and length is not None:
        raise StepsafeError("give the number of steps or the trajectory length, not both")
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not (
                1 <= steps <= 10**6):
            raise StepsafeError(f"trajectory_steps must be an integer from 1 to 1000000 (--steps "
                                f"on the command line), got {steps!r}")
        steps = int(steps)
    if length is not None:
        length = positive_finite(length, "trajectory length")
    if not 0.0 <= finite_real(jitter, "jitter") < 1.0:
        raise StepsafeError(f"jitter must be a number in [0, 1), got {jitter!r}")
    return float(target), steps, length, float(jitter)


@public()
@shared_keywords
def hmc(methods: Sequence[Integrator | str] | str | None = None, *,
        beta: ArrayLike | None = None, sigma: ArrayLike | None = None,
        saddle_beta: ArrayLike | None = None, inverted_beta: ArrayLike | None = None,
        modes: Mapping[str, ArrayLike] | None = None,
        ordinary_frequency: UnitValues | None = None,
        wavenumber: UnitValues | None = None, period: UnitValues | None = None,
        time_unit: str | None = None,
        labels: Mapping[str, Sequence[str | None]] | None = None,
        system: Mapping[str, Any] | None = None, scene: str | Path | Scene | None = None,
        zmax: float | None = None, budget: float | None = None,
        progress: Callable[[float], None] | None = None, problem: Problem | None = None,
        trajectory_steps: int | None = None, length: float | str | None = None,
        jitter: float = 0.0, target_accept: float = 0.8, step: float | str | None = None,
        criterion: str = "stability", curve: int = 0, gradient_cost: float = 1.0,
        allow_unstable_jitter: bool = False, target_for_every_length: bool = False,
        logdensity: Callable[..., Any] | None = None,
        gradient: Callable[..., Any] | None = None, start: ArrayLike | None = None,
        mass: ArrayLike | None = None, draws: ArrayLike | str | Path | None = None,
        seed: int | None = None, require_converged: bool = False
        ) -> HmcReport | TargetReport:
    """HMC on a target with each of ``methods``: the step at target, the acceptance and
    the cost, methods ranked by gradient evaluations per accepted proposal at the L run (L
    or T given), else per accepted unit of simulated time (the report's ``ranked_by``).

    With L (``trajectory_steps``) or T (``length``) given, the step at target is the
    largest whose acceptance for that trajectory reaches ``target_accept`` at every step up
    to it; without, or with ``target_for_every_length=True``, the largest whose acceptance
    reaches it for every trajectory length (each mode's energy error at its bound over L,
    rho(h) of Blanes, Casas & Sanz-Serna 2014; the acceptance for one L oscillates with h
    like sin^2(L theta)). The acceptance is reported for the trajectory given.

    A target that is not Gaussian, ``logdensity`` with ``start`` or a scene or ``system``
    with ``potential:`` (:mod:`stepsafe.systems.potential`), is never analysed as a
    Gaussian: the acceptance is estimated on ``draws`` from the target with each method's
    own trajectories, beside the Laplace figures at the mode, and a
    :class:`~stepsafe.core.hmc_target.advice.TargetReport` is returned
    (:mod:`stepsafe.api.hmc_target`). It needs L or T.

    Parameters
    ----------
    methods : list of Integrator or str, or "all", optional
        The methods (names, ``family:N``, paths, Integrators); None: :data:`HMC_DEFAULT`.
    <keywords: target>
    progress : callable, optional
        Called with the fraction of methods done.
    problem : Problem, optional
        A :func:`~stepsafe.problem` built beforehand, given instead of the target's
        keywords above.
    trajectory_steps : int, optional
        L, the number of steps per trajectory (a count, not a time).
    length : float or str, optional
        The trajectory length T in the time unit (or a text with a time unit): L =
        floor(T / h), as Stan. Neither L nor T: the acceptance is the bound over every L.
    jitter : float
        j in [0, 1): each step is drawn from ``h (1 +- j)``; the step at target keeps
        ``h (1 + j)`` within the criterion's step limit (no jittered step unstable) unless
        ``allow_unstable_jitter`` (see the module docstring).
    target_accept : float
        The acceptance rate to reach, in (0, 1) (Stan's ``adapt_delta``).
    step : float or str, optional
        A step h to evaluate too, in the time unit (or a text with a time unit).
    criterion : str
        What bounds the search for h: ``stability`` (|tr M| <= 2, the default here) or
        ``structure`` (type and orientation).
    curve : int
        N: add the predicted acceptance at N steps up to that limit to each row.
    gradient_cost : float
        Gradient evaluations one force-gradient term costs.
    allow_unstable_jitter : bool
        Search up to the limit itself, as for a fixed step (the fraction of unstable
        draws is then stated).
    target_for_every_length : bool
        Reach ``target_accept`` for every trajectory length (the bound over L), not only
        for the L or T given (Gaussian targets).
    logdensity : callable, optional
        ``log pi(q)`` of a target that is not Gaussian: with ``gradient``, a numpy function
        batched over leading axes (``(..., d) -> (...)``); without, a JAX function of one
        position (``(d,) -> ()``), differentiated by JAX.
    gradient : callable, optional
        ``grad log pi(q)``, ``(..., d) -> (..., d)``.
    start : array_like, optional
        A position of shape (d,) inside the support of ``logdensity`` (sets d; the mode
        search starts there).
    mass : array_like, optional
        The mass matrix M of ``logdensity``'s kinetic energy ``p^T M^-1 p / 2``: a number,
        d masses or a d x d SPD matrix (default: unit masses).
    draws : array_like or str, optional
        Draws from a target that is not Gaussian, shape (n, d) or (chains, n, d), or a
        file (:func:`stepsafe.systems.potential.read_draws`); default: a short adaptive
        HMC run of stepsafe's own.
    seed : int, optional
        Seed of that run and of the estimate's momenta (stated in the report; default
        :data:`~stepsafe.core.hmc_target.draws.SEED`). A target that is not Gaussian only: a
        Gaussian target's figures are exact and draw no random numbers (the jitter average
        is a quadrature), so a seed given with one is refused rather than ignored.
    require_converged : bool
        Refuse (:class:`~stepsafe.exceptions.NotConverged`, a StepsafeError naming the
        diagnostic that fails) draws that have not converged: the largest rank-normalised
        split R-hat over the coordinates and U above 1.01, or the smallest effective sample
        size below 400 (or too few draws per chain to compute them), a warm-up whose kept
        run and its refits at smaller steps all had divergent transitions, or a mode the
        mode search found that the draws miss, checked before any estimate. A target that
        is not Gaussian only, as ``seed``. Without it, such draws still give a report,
        marked ``verified`` False with the reason in ``unverified``: its estimates may be
        off by more than their standard errors and its h at target is not a recommendation
        (the command line prints it and exits 1;
        ``--require-converged`` there refuses before the estimates, as this keyword).

    Returns
    -------
    HmcReport or TargetReport
        One row per method, ranked; ``to_dict()`` is ``stepsafe hmc --json``.

    >>> rows = hmc(["verlet", "bcss2"], sigma=list(np.linspace(0.5, 1.0, 20)), length=5.0).rows
    >>> [(r.method, r.rank) for r in rows]   # bcss2: fewer gradients per accepted proposal
    [('bcss2', 1), ('verlet', 2)]
    """
    steps = trajectory_steps
    _validated(target_accept, steps, None, jitter)  # the unit-free ones, before any work
    validate_gradient_cost(gradient_cost)  # a bad value fails before any work
    criterion = validate_criterion(criterion)
    if not isinstance(allow_unstable_jitter, (bool, np.bool_)):
        raise StepsafeError("allow_unstable_jitter must be True or False, got "
                            f"{str(allow_unstable_jitter)[:20]!r}")
    if isinstance(curve, bool) or not isinstance(curve, int) or not 0 <= curve <= 10_000:
        raise StepsafeError(f"curve must be an integer from 0 to 10000, got {curve!r}")
    if not isinstance(target_for_every_length, (bool, np.bool_)):
        raise StepsafeError("target_for_every_length must be True or False, got "
                            f"{str(target_for_every_length)[:20]!r}")
    if not isinstance(require_converged, (bool, np.bool_)):
        raise StepsafeError("require_converged must be True or False, got "
                            f"{str(require_converged)[:20]!r}")
    integrators = compared_methods(HMC_DEFAULT if methods is None else methods)
    inputs = {"sigma": sigma, "saddle_beta": saddle_beta, "inverted_beta": inverted_beta,
              "modes": modes, "ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
              "period": period, "time_unit": time_unit, "labels": labels, "system": system,
              "scene": scene, "zmax": zmax, "budget": budget, "problem": problem}
    found = target_of(logdensity, gradient, start, mass, scene, system)
    if found is not None:
        return _non_gaussian(found, integrators, {**inputs, "beta": beta,
                                                  "progress": progress},
                             steps=steps, length=length, jitter=jitter,
                             target_accept=target_accept, step=step, criterion=criterion,
                             curve=curve, draws=draws,
                             seed=TARGET_SEED if seed is None else seed,
                             allow_unstable_jitter=bool(allow_unstable_jitter),
                             target_for_every_length=bool(target_for_every_length),
                             require_converged=bool(require_converged))
    if draws is not None:
        raise StepsafeError("draws= go with a target that is not Gaussian (logdensity= or a "
                            "potential:); a Gaussian target's acceptance is exact")
    if seed is not None:
        raise StepsafeError("seed= (--seed) goes with a target that is not Gaussian "
                            "(logdensity= or a potential:): a Gaussian target's figures are "
                            "exact and deterministic, no random numbers are drawn (the "
                            "jitter average is a quadrature)")
    if require_converged:
        raise StepsafeError("require_converged= (--require-converged) goes with a target "
                            "that is not Gaussian (logdensity= or a potential:): a Gaussian "
                            "target's figures are exact, no draws are made")
    p = problem_of(integrators[0], beta, inputs, times=(step, length))
    if length is not None:
        length = duration(length, "length", p.time_unit)
    target, steps, length, jitter = _validated(target_accept, steps, length, jitter)
    if step is not None:
        step = positive_finite(duration(step, "step", p.time_unit), "step")
    betas, errors = _gaussian_betas(p)
    trajectory = Trajectory(steps, length, jitter)
    rows = []
    for k, integrator in enumerate(integrators):
        rows.append(_row(integrator, betas, errors, trajectory, target, step, criterion,
                         p.zmax, curve, gradient_cost, bool(allow_unstable_jitter),
                         bool(target_for_every_length)))
        if progress is not None:
            progress((k + 1) / len(integrators))
    # a method that is not reversible does not sample the target: listed, not ranked
    key = core.ranked_by(trajectory)

    def cost(row: HmcRow) -> float | None:
        value = getattr(row, key)
        return None if value is None else float(value)

    other = next(name for name in core.RANKINGS if name != key)

    def figure(value: float | None) -> float:
        # costs that agree to RANK_DIGITS digits tie (h at target is found to a relative
        # 1e-6, so further digits are the search's, not the method's): the other ranking,
        # then the order given, decides
        return math.inf if value is None else float(f"{float(value):.{RANK_DIGITS}g}")

    usable = [cost(r) is not None and r.symmetric for r in rows]
    order = sorted(range(len(rows)), key=lambda k: (
        not usable[k], figure(cost(rows[k])), figure(getattr(rows[k], other)), k))
    out, rank = [], 0
    for k in order:
        rank += usable[k]
        out.append(HmcRow(**{**rows[k].__dict__, "rank": rank if usable[k] else None}))
    positive = betas[betas > 0]
    return HmcReport(tuple(out), target, steps, length, jitter, criterion, int(betas.size),
                     (float(positive.min()), float(positive.max())), p.time_unit,
                     any(APPROXIMATE_NOTE in r.notes for r in rows),
                     bool(allow_unstable_jitter),
                     bool(target_for_every_length or trajectory.steps is None
                          and trajectory.length is None
                          or not _given_length_searched(betas, jitter)), key)


def _non_gaussian(found: Any, integrators: list[Integrator], inputs: dict[str, Any], *,
                  steps: int | None, length: Any, jitter: float, target_accept: float,
                  step: Any, criterion: str, curve: int, draws: Any, seed: Any,
                  allow_unstable_jitter: bool, target_for_every_length: bool,
                  require_converged: bool = False) -> TargetReport:
    """``hmc`` on a target that is not Gaussian (:mod:`stepsafe.api.hmc_target`)."""
    others = sorted(k for k, v in inputs.items()
                    if v is not None and k not in ("scene", "system", "time_unit", "zmax",
                                                   "progress"))
    if others:
        raise StepsafeError(f"give the target once: {others[0]}= beside a log-density or a "
                            "potential (on the command line: --sigma, --beta, --modes or "
                            "another frequency option beside a potential scene)")
    if criterion != "stability":
        raise StepsafeError("a target that is not Gaussian is searched below the stability "
                            "limit of the stiffest draw: criterion structure applies to "
                            "Gaussian targets only")
    if curve:
        raise StepsafeError("curve= (--plot) draws the exact acceptance of a Gaussian target; "
                            "for this target the acceptance is estimated at the steps "
                            "searched only")
    if target_for_every_length:
        raise StepsafeError("the bound over every trajectory length is a Gaussian figure: for "
                            "this target the acceptance is estimated for the L (or T) given")
    time_unit = inputs.get("time_unit")
    scene = inputs.get("scene")
    if time_unit is None and scene is not None and hasattr(scene, "time_unit"):
        time_unit = scene.time_unit
    elif time_unit is None and isinstance(scene, (str, Path)):
        time_unit = scene_time_unit(scene)
    if length is not None:
        length = duration(length, "length", time_unit)
    target, steps, length, jitter = _validated(target_accept, steps, length, jitter)
    if step is not None:
        step = positive_finite(duration(step, "step", time_unit), "step")
    report = on_target(found, integrators, steps=steps, length=length, jitter=jitter,
                       target_accept=target, step=step, draws=draws, seed=seed,
                       allow_unstable_jitter=allow_unstable_jitter,
                       zmax=inputs.get("zmax"), require_converged=require_converged)
    progress = inputs.get("progress")
    if progress is not None:
        progress(1.0)
    return report


def _quotient_below(z: float, beta: float) -> float:
    """``z / beta`` taken :data:`stepsafe.core.advice.SHRINK` lower, as advise and check
    take a gap's start in h: below it ``beta h < z`` exactly and as check computes it."""
    return float(z / beta * SHRINK)


def _quotient_within(h: float, factor: float) -> float:
    """The largest float q <= h / factor with ``q * factor <= h`` in float64: a step whose
    longest jittered draw, as a sampler computes it, stays within ``h``."""
    q = h / factor
    while q * factor > h:
        q = float(np.nextafter(q, 0.0))
    return q


def unstable_fraction(h: float, jitter: float, limit: float) -> float:
    """The fraction of steps drawn uniformly from ``h (1 - jitter, 1 + jitter)`` that pass
    ``limit``: ``(h (1 + jitter) - limit) / (2 jitter h)`` clipped to [0, 1] (0 or 1 without
    jitter, as h is within the limit or not).

    It is 0 exactly when the longest draw as a sampler computes it, ``h * (1 + jitter)`` in
    float64 (no draw ``h * (1 + jitter u)`` computes larger, rounding being monotone), is
    within ``limit``, and 1 exactly when the shortest, ``h * (1 - jitter)``, is past it: the
    rule the step at target keeps. Between the two the share is strictly between 0 and 1
    (a draw on each side), the difference ``h (1 + jitter) - limit`` taken from the computed
    longest draw (exact when the two are within a factor 2, so a share of one rounding is
    not lost to the cancellation in ``1 + jitter - limit / h``)."""
    if jitter == 0.0:
        return 0.0 if h <= limit else 1.0
    longest = h * (1.0 + jitter)
    if longest <= limit:
        return 0.0
    if h * (1.0 - jitter) > limit:
        return 1.0
    share = ((longest - limit) / (2.0 * jitter * h) if np.isfinite(longest) else
             (1.0 + jitter - limit / h) / (2.0 * jitter))  # h near float64's largest
    return float(min(max(share, float(np.nextafter(0.0, 1.0))), float(np.nextafter(1.0, 0.0))))


def _given_length_searched(betas: np.ndarray, jitter: float) -> bool:
    """Whether the step at target is searched for the L given (else the bound over every L
    stands for it): always without jitter; with jitter up to
    :data:`stepsafe.core.hmc.MAX_EXACT_MODES` distinct frequencies, beyond which each step
    of that search costs seconds to minutes."""
    return not jitter or np.unique(betas).size <= MAX_EXACT_MODES


def _row(integrator: Integrator, betas: np.ndarray, errors: np.ndarray, trajectory: Any,
         target: float, step: float | None, criterion: str, zmax: float, curve: int = 0,
         gradient_cost: float = 1.0, allow_unstable_jitter: bool = False,
         every_length: bool = False) -> HmcRow:
    m = integrator.tableau
    top = float(betas.max())
    with integrator.naming_its_file():
        region = find_region(m, "oscillator", zmax)
    symmetric = is_symmetric(m)
    notes: list[str] = []
    empty = HmcRow(integrator.name, integrator.evaluations, symmetric, None, None, (), None,
                   None, None, None, None, None, None)
    if not region.symplectic:
        return HmcRow(**{**empty.__dict__, "notes": (
            "not symplectic: it does not preserve volume, so HMC with it does not sample "
            "the target",)})
    if not symmetric and getattr(m, "kind", "") == "processed":
        notes.append("not reversible: with the momentum flip S, S P^-1 K^L P S is not the "
                     "inverse of the proposal unless S P S = P, so an HMC chain with it does "
                     "not satisfy detailed balance and drifts away from the target; the "
                     "acceptance shown is that of a proposal from the target (not ranked)")
    elif not symmetric:
        notes.append("not symmetric: the HMC chain is not reversible with it and drifts away "
                     "from the target (alternate it with its adjoint); the acceptance shown "
                     "is that of a proposal from the target (not ranked)")
    # the stable steps, resonances (rounding gaps) excluded but not ending them: the rule
    # design uses too (stepsafe.core.regions.stable_run)
    run = stable_run(region)
    if run.end is None:
        notes.append(f"stable up to z = {region.zmax:g}, as far as analysed: the stability h "
                     "shown is that end, not the method's limit (--zmax analyses further)")
    # the limits as advise computes them: each boundary less its float64 uncertainty, over
    # the largest beta (1 + r) the rounding of a computed eigenvalue allows, rounded down
    stab_lo = run.first_unsafe if run.first_unsafe is not None else region.zmax
    struct_lo = (first_unsafe_z(region) if region.first_boundary is not None
                 else region.zmax)
    widest = float((betas * (1.0 + errors)).max())
    stability_h, structure_h = _quotient_below(stab_lo, widest), _quotient_below(
        struct_lo, widest)
    if not (np.isfinite(stability_h) and np.isfinite(structure_h)):
        raise StepsafeError(f"the step limit z / beta = {stab_lo:.6g} / {widest:.3g} "
                            "overflows float64: give sigma, the frequencies or the "
                            "covariance in units nearer 1")
    h_hi = stability_h if criterion == "stability" else structure_h
    solver_limit = None if integrator.explicit else step_limit(m, {"oscillator": betas})
    if solver_limit is not None and SOLVER_REACH * solver_limit < h_hi:
        h_hi = SOLVER_REACH * solver_limit
        notes.append(f"the step is kept below 0.9 of the fixed-point iteration's "
                     f"convergence limit h = {solver_limit:.6g}")
    jitter = trajectory.jitter
    h_fixed = h_hi  # the limit for a fixed step
    if jitter and not allow_unstable_jitter:
        h_hi = _quotient_within(h_hi, 1.0 + jitter)  # every draw h (1 + jitter u) within it
    resonances = tuple(r.z / top for r in run.resonances)

    def gradients(h: float) -> float | None:
        if integrator.explicit:
            per_step = step_cost(integrator, gradient_cost)
            return None if per_step is None else float(per_step)
        cost = fixed_point_cost(m, h * top)
        return None if cost.evaluations is None else float(cost.evaluations)

    # a processed method runs P and P^-1 once per trajectory
    overhead = 2.0 * (m.processor_evaluations or 0)
    if overhead:
        notes.append(f"processed: P and P^-1 cost {overhead:g} gradient evaluations per "
                     "proposal besides the kernel's steps (included in the costs when the "
                     "trajectory is given)")

    def figures(h: float) -> dict[str, Any]:
        acc = core.acceptance_at(m, betas, h, trajectory)
        L = trajectory.steps_at(h)
        e = gradients(h)
        per_step = None if e is None else e
        per_proposal = None if (L is None or e is None) else L * e + overhead
        if per_proposal is not None and L:
            per_step = per_proposal / L
        return {"h": h, "steps": L, "acceptance": acc.rate,
                "approximate": acc.approximate, "expected_error": acc.expected_error,
                "gradients_per_proposal": per_proposal,
                "gradients_per_accepted": (None if per_proposal is None or acc.rate == 0
                                           else per_proposal / acc.rate),
                "gradients_per_time": (None if per_step is None or acc.rate == 0
                                       else per_step / (acc.rate * h))}

    # the step reaching the target for the trajectory given (at every step up to it: the
    # acceptance for a given L oscillates with h like sin^2(L theta)), or for every
    # trajectory length (the bound rho of each mode) when asked or when L is not given
    bound = core.Trajectory(jitter=jitter)
    given = trajectory.steps is not None or trajectory.length is not None
    h_target = core.target_step(m, betas, target, h_hi, bound)
    if given and not every_length and h_target is not None and h_target < h_hi:
        if _given_length_searched(betas, jitter):
            # the given L's acceptance is at least the bound's: its search starts there
            h_target = core.target_step(m, betas, target, h_hi, trajectory, h_lo=h_target)
        else:
            notes.append(f"h at target reaches the target for every trajectory length, so for "
                         f"the one given too: with jitter, the search for the L given is not "
                         f"made on more than {core.MAX_EXACT_MODES} distinct frequencies (each "
                         "of its steps averages every mode over the turns of L theta across "
                         "the jitter); the acceptance shown is for the L given")
    at_target = figures(h_target) if h_target else {}
    if jitter and h_target is not None and h_target == h_hi and not allow_unstable_jitter:
        notes.append(f"h at target is capped at h = {h_hi:.6g}, the {criterion} limit "
                     f"{h_fixed:.6g} over 1 + J = {1.0 + jitter:g}, so that no jittered step "
                     "passes it (--allow-unstable-jitter, allow_unstable_jitter=True in "
                     "Python, searches up to the limit itself)")
    for where, h in (("the step at target", h_target), ("the step asked for", step)):
        unstable = (unstable_fraction(h, jitter, stability_h)
                    if h and jitter and run.end is not None else 0.0)
        if unstable > 0.0:
            share = ("every jittered step h (1 +- {j:g}) passes" if unstable == 1.0 else
                     f"{100 * unstable:.3g}% of the jittered steps h (1 +- {{j:g}}) pass"
                     ).format(j=jitter)
            notes.append(f"at {where} h = {h:.6g}, {share} the "
                         f"stability limit {stability_h:.6g}: the trajectories that draw them "
                         "grow without bound (divergent transitions)"
                         + (", which the acceptance averaged over the jitter hides"
                            if unstable < 1.0 else ""))
    if at_target.get("approximate"):
        notes.append(APPROXIMATE_NOTE)
    for where, h in (("h at target", h_target), ("the step asked for", step)):
        wanted = trajectory.capped(h) if h else None
        if wanted is not None:
            notes.append(f"L = floor(T/h) = {wanted:.3g} at {where} is capped at "
                         f"{core.MAX_TRAJECTORY_STEPS:.0e} steps: the acceptance and costs "
                         f"shown there are for L = {core.MAX_TRAJECTORY_STEPS:.0e} (no "
                         "sampler runs more)")
    at_step: Mapping[str, Any] | None = None
    if step is not None:
        figures_at_step = figures(step)
        figures_at_step["largest_errors"] = tuple(
            MappingProxyType(asdict(e))
            for e in core.largest_errors(m, betas, step, trajectory.steps_at(step)))
        at_step = MappingProxyType(figures_at_step)
    stalls: list[Mapping[str, Any]] = []
    L = trajectory.steps_at(h_target) if h_target else None
    if L is not None and h_target:
        window = max(STALL_WINDOW, trajectory.jitter)
        for beta in sorted({float(betas[betas > 0].min()), top}):
            near = [(abs(h / h_target - 1.0), turns, h) for turns, h in
                    core.stall_steps(m, region, beta, L, h_target, window)]
            stalls += [MappingProxyType({"beta": beta, "steps": L, "turns": turns, "h": h,
                                         "from_target": gap})
                       for gap, turns, h in sorted(near)[:1]]
    points: tuple[tuple[float, float, float], ...] = ()
    if curve:
        hs = h_hi * (np.arange(1, curve + 1) / curve)
        points = tuple((float(h), a.rate, b.rate) for h, a, b in zip(
            hs, core.acceptance_curve(m, betas, hs, trajectory),
            core.acceptance_curve(m, betas, hs, bound)))
    per_step = step_cost(integrator, gradient_cost) if integrator.explicit else None
    return HmcRow(integrator.name, per_step, symmetric, stability_h, structure_h,
                  resonances, h_target, at_target.get("steps"), at_target.get("acceptance"),
                  at_target.get("expected_error"), at_target.get("gradients_per_proposal"),
                  at_target.get("gradients_per_accepted"), at_target.get("gradients_per_time"),
                  None, at_step, tuple(stalls), tuple(notes), points)


# --------------------------------------------------------------------------- design

#: The fixed integrators a designed one is compared with.
DESIGN_REFERENCES = ("verlet", "bcss2", "bcss3", "mclachlan2-min")


@public()
@shared_keywords
def design(*, step: float | str, stages: int = 2, jitter: float = 0.0,
           name: str | None = None, beta: ArrayLike | None = None, sigma: ArrayLike | None = None,
           saddle_beta: ArrayLike | None = None, inverted_beta: ArrayLike | None = None,
           modes: Mapping[str, ArrayLike] | None = None,
           ordinary_frequency: UnitValues | None = None,
           wavenumber: UnitValues | None = None, period: UnitValues | None = None,
           time_unit: str | None = None,
           labels: Mapping[str, Sequence[str | None]] | None = None,
           system: Mapping[str, Any] | None = None, scene: str | Path | Scene | None = None,
           zmax: float | None = None, budget: float | None = None,
           problem: Problem | None = None, trajectory_steps: int | None = None,
           length: float | str | None = None,
           objective: str = "error-bound") -> DesignReport:
    """Design the palindromic ``stages``-stage splitting (2: parameter b; 3: b and a; see
    :mod:`stepsafe.core.design`) that minimises the expected energy error summed over the
    target's modes at ``step``, averaged over ``step (1 +- jitter)``, every mode stable up
    to ``step (1 + jitter)`` (an M = +-I resonance does not end the stable steps: the rule
    ``hmc`` uses, :func:`stepsafe.core.regions.stable_run`).

    ``objective="acceptance"`` minimises instead what ``hmc`` ranks by: the gradient
    evaluations per accepted proposal for the trajectory given (``trajectory_steps`` L or
    ``length`` T, L = floor(T / step); neither: each mode at its bound over L) and the jitter, at
    ``step`` the reciprocal of the predicted acceptance; the comparison then also lists
    the minimax member (``aia-minimax``: the smallest worst rho over (0, beta_max step
    (1 + jitter)], the adaptive integrators' choice; the report's ``aia_params``), which is
    also a starting point of the design, so that the designed member's objective is at most
    the minimax member's; and gives every row's acceptance for that trajectory.
    ``trajectory_steps`` or ``length`` alone (the default objective) only sets the
    trajectory of the comparison.

    Parameters
    ----------
    step : float or str
        The step h to design for, in the time unit (or a text with a time unit).
    stages : int
        2 or 3 force evaluations per step.
    jitter : float
        j in [0, 1): the design averages over ``step (1 +- j)``.
    name : str, optional
        The designed method's name (default ``designed-2stage`` / ``designed-3stage``).
    <keywords: target>
    problem : Problem, optional
        A :func:`~stepsafe.problem` built beforehand, given instead of the target's
        keywords above.
    trajectory_steps : int, optional
        L, the number of steps per trajectory (a count, not a time).
    length : float or str, optional
        The trajectory length T in the time unit (or a text with a time unit).
    objective : str
        ``error-bound`` (the default) or ``acceptance`` (see above).

    Returns
    -------
    DesignReport
        The parameters, the method file and the comparison; ``to_dict()`` is ``stepsafe
        design --json``.

    Examples
    --------
    >>> report = design(sigma=[1.0, 0.5, 0.2], step=0.5)
    >>> [(c["method"], round(c["acceptance"], 2)) for c in report.comparison[:3]]
    [('designed-2stage', 0.98), ('verlet', 0.84), ('bcss2', 0.77)]
    """
    if isinstance(stages, bool) or not isinstance(stages, (int, np.integer)) or \
            stages not in PARAMETERS:
        raise StepsafeError(f"stages must be 2 or 3, got {stages!r}")
    if objective not in OBJECTIVES:
        raise StepsafeError(f"objective must be one of {', '.join(OBJECTIVES)}, got "
                            f"{str(objective)[:40]!r}")
    name = f"designed-{stages}stage" if name is None else name
    if not isinstance(name, str) or not name or not all(
            c.isascii() and (c.isalnum() or c == "-") for c in name) or len(name) > 60:
        raise StepsafeError(f"name must be 1 to 60 letters, digits and '-' (as method files "
                            f"require), got {str(name)[:40]!r}")
    inputs = {"sigma": sigma, "saddle_beta": saddle_beta, "inverted_beta": inverted_beta,
              "modes": modes, "ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
              "period": period, "time_unit": time_unit, "labels": labels, "system": system,
              "scene": scene, "zmax": zmax, "budget": budget, "problem": problem}
    p = problem_of("verlet", beta, inputs, times=(step, length))
    step = positive_finite(duration(step, "step", p.time_unit), "step")
    if length is not None:
        length = duration(length, "length", p.time_unit)
    _, steps, length, jitter = _validated(0.5, trajectory_steps, length, jitter)
    betas, errors = _gaussian_betas(p)
    # designed for each frequency at the largest it may be (the rounding of the
    # eigenvalues it came from), as hmc and advise limit the step
    widest = betas * (1.0 + errors)
    values, counts = np.unique(widest[betas > 0], return_counts=True)
    given = core.Trajectory(steps, length, jitter)
    # the AIA-style minimax member: compared with, and a start of the acceptance design
    # (so that the design beats or ties it on its own objective)
    params_aia = (minimax(stages, float(widest.max()) * step * (1.0 + jitter))
                  if objective == "acceptance" else None)
    found = core_design(stages, values, counts.astype(float), step, jitter, objective,
                        given.steps_at(step), () if params_aia is None else (params_aia,))
    if found is None:
        top = values.max()
        past = (f"; past h = {3.0 / top:g} only members with an M = -I point are, of which "
                "the design tries bcss3 and (1/6, 1/3)" if stages == 3 else "")
        raise StepsafeError(f"no {stages}-stage member keeps every mode stable up to h = "
                            f"{step * (1.0 + jitter):g} (the family's stable steps end at "
                            f"h = {STABLE_LIMIT[stages] / top:g}{past}): take a smaller step")
    designed = family_member(stages, found.params, name)
    params = dict(zip(PARAMETERS[stages], found.params))
    rows = []
    # the trajectory given, else the bound over L; averaged over the jitter
    over = given if (steps is not None or length is not None) else core.Trajectory(
        jitter=jitter)
    extra = []
    if params_aia is not None:
        extra = [("aia-minimax", family_member(stages, params_aia, "aia-minimax"), stages)]
    for label, tableau, evals in [(name, designed, stages)] + extra + [
            (ref, (i := compared_methods([ref])[0]).tableau, int(i.evaluations or 0))
            for ref in DESIGN_REFERENCES]:  # the references are explicit: evaluations known
        h = step * evals / stages
        if h == 0:
            raise StepsafeError(f"step: {step:g} is so small that {label}'s step at equal "
                                "cost, step * evaluations / stages, underflows to 0: give "
                                "sigma and the step in units nearer 1")
        acc = core.acceptance_at(tableau, betas, h, over)
        reach = float(widest.max()) * h * (1.0 + jitter)
        run = stable_run(find_region(tableau, "oscillator", max(reach * 1.001, 10.0)))
        L = over.steps_at(h)
        row = {"method": label, "evaluations": evals, "h": h,
               "resonance_h": tuple(r.z / float(betas.max()) for r in run.resonances
                                    if r.z <= reach),
               "error_bound": (None if not np.isfinite(acc.expected_error)
                               else acc.expected_error),
               "acceptance": acc.rate,
               "gradients_per_time": (None if acc.rate == 0 else evals / acc.rate / h)}
        if objective == "acceptance":
            row["steps"] = L
            row["gradients_per_accepted"] = (None if acc.rate == 0 or L is None
                                             else evals * L / acc.rate)
        rows.append(MappingProxyType(row))
    return DesignReport(name, stages, MappingProxyType(params), step,
                        _method_file(name, stages, params, step, jitter, betas.size,
                                     objective, given.steps_at(step)),
                        tuple(rows), int(betas.size), found.binned, p.time_unit, objective,
                        steps, length, jitter,
                        None if params_aia is None else MappingProxyType(
                            dict(zip(PARAMETERS[stages], params_aia))))


def _gaussian_betas(p: Any) -> tuple[np.ndarray, np.ndarray]:
    """The vibration frequencies of a Gaussian target (refusing anything else) and the
    relative uncertainty of each (2 eps for frequencies given, the rounding of 1/sigma or of
    a unit's conversion; the rounding bound of the eigenvalue for those computed from a
    covariance or precision, as advise widens them).

    A precision eigenvalue that float64 cannot tell from 0 (within its rounding bound
    ``16 n eps |P|``, :mod:`stepsafe.systems.linear`) is refused as undecided, naming the
    file and key; only a certainly negative one is called negative."""
    source = (p.system.source or None) if p.system is not None else \
        (f"{p.scene}::$.modes" if p.scene is not None else None)
    if p.system is not None and p.system.modes is None:
        raise TargetError("the target's modes do not decouple: a Gaussian target needs a "
                            "symmetric positive definite precision (or covariance)", source)
    if p.system is not None and p.system.primary_only:
        raise TargetError(f"HMC's acceptance depends on every mode, and a matrix of more "
                            f"than {DENSE_LIMIT} rows is reduced to its extreme eigenvalues: "
                            "give the standard deviations of its modes (--modes FILE with a "
                            "sigma column) or a smaller matrix", source)
    if p.system is not None and any(item.get("type") == "free" for item in p.system.items):
        raise TargetError("the precision is singular (a direction of zero precision): the "
                            "target is not a proper Gaussian", source)
    if p.system is not None and any(item.get("type") == "undecided"
                                    for item in p.system.items):
        raise TargetError("an eigenvalue of the precision is within rounding of 0 (its "
                            "condition number is beyond what float64 resolves), so its sign "
                            "is not decided and the target is not certainly a Gaussian: give "
                            "the covariance, or a better-conditioned precision (a mass matrix "
                            "as preconditioner)", source)
    others = [m for m in p.modes.betas if m != "oscillator"]
    if others:
        if p.system is None:
            why = (f"{others[0]} modes (given as such) are not modes of a Gaussian "
                   "target")
        elif "inverted" in others:
            why = "the precision has a negative eigenvalue (an inverted mode)"
        else:
            why = f"{others[0]} modes have no place in HMC"
        raise TargetError("a Gaussian target has only vibrations (sigma, covariance, "
                            f"positive definite precision): {why}", source)
    betas = np.asarray(p.modes.betas["oscillator"], dtype=float)
    modes = p.system.modes if p.system is not None else p.modes
    errors = (modes.error("oscillator") if isinstance(modes, Modes) else
              np.zeros(betas.size))
    errors = np.asarray(errors, dtype=float)
    if errors.shape != betas.shape:
        errors = np.zeros(betas.size)
    # at least the rounding of 1/sigma (or of a unit's conversion), so that a step whose
    # z = h / sigma is the family's limit within an ulp is not designed for
    errors = np.maximum(errors, 2 * EPS)
    if not betas.max() > 0:
        raise TargetError("every frequency is 0: a flat target has no step limit", source)
    if np.any(betas == 0):
        raise TargetError("a frequency is 0 (sigma = inf): a flat direction, so the target is "
                          "not a proper Gaussian", source)
    tiny = float(np.finfo(float).tiny)
    positive = betas[betas > 0]
    if positive.min() < tiny:
        # 1/beta overflows past the stability limit, and beta h loses digits (subnormal)
        raise TargetError(f"a frequency 1/sigma = {positive.min():.3g} is below float64's "
                            f"normal range ({tiny:.3g}; sigma above {1 / tiny:.3g}): its "
                            "steps overflow. Give sigma, the frequencies or the covariance "
                            "in units nearer 1", source)
    return betas, errors

def _method_file(name: str, stages: int, params: Mapping[str, float], step: float,
                 jitter: float, modes: int, objective: str = "error-bound",
                 steps: int | None = None) -> str:
    family = ("K(b h) D(h/2) K((1-2b) h) D(h/2) K(b h)" if stages == 2 else
              "K(b h) D(a h) K((1/2-b) h) D((1-2a) h) K((1/2-b) h) D(a h) K(b h)")
    constants = "\n".join(f'  {k}: "{v!r}"' for k, v in params.items())
    shape = ('drift: [0, "1/2"]\nkick: [b, "1 - 2*b"]' if stages == 2 else
             'drift: [0, a, "1 - 2*a"]\nkick: [b, "1/2 - b"]')
    return (f"name: {name}\n"
            f'title: "Palindromic {stages}-stage splitting designed for a Gaussian target"\n'
            "kind: splitting\norder: 2\n"
            f"evaluations: {stages}\n"
            f'source: "stepsafe design: the {stages}-stage palindromic family {family} of '
            "Blanes, Casas & Sanz-Serna, SIAM J. Sci. Comput. 36 (2014) A1556, with "
            + (f"{', '.join(params)} minimising the sum over {modes} mode(s) of the "
               f"expected energy error bound rho(beta h) at h = {step!r}"
               if objective == "error-bound" else
               f"{', '.join(params)} maximising the predicted HMC acceptance on {modes} "
               f"mode(s) at h = {step!r}"
               + (f" after L = {steps} steps" if steps is not None else
                  " (each mode at its error bound over L)"))
            + (f" (averaged over h (1 +- {jitter!r}))" if jitter else "") + '"\n'
            f"constants:\n{constants}\n"
            f"symmetric: true\n{shape}\n")
