"""HMC advice on the user's own target: every method's step at target acceptance, its
acceptance, divergences and cost estimated on the target itself, beside the Gaussian
(Laplace) figures at the mode.

For each method:

* its linear stability limit ``z*`` (``|tr M| <= 2`` from 0, the rule for rounding gaps of
  :func:`stepsafe.core.regions.stable_run`) over the stiffest frequency the draws meet,
  ``h_stable = z* / omega_top`` (:mod:`stepsafe.core.hmc_target.frequencies`), and over
  the mode's, ``laplace_stability_h``;
* the step at target acceptance for the trajectory given (L steps, or an integration time
  T with ``L = floor(T / h)``) and jitter J, searched on the estimate with common random
  numbers (:mod:`stepsafe.core.hmc_target.estimate`) below ``h_stable / (1 + J)``, so that
  no jittered step passes the stiffest region's limit, unless ``allow_unstable_jitter``
  (then below ``h_stable``, and the share of jittered steps beyond it is stated); and
  below the divergence onset (the largest step of the scan below at which none of the
  proposals diverged; not with ``allow_unstable_jitter``, which accepts divergent jittered
  steps), since nonlinear instability can set in before the linear limit of
  the stiffest draw (a light tail such as U = x^4/4 has draws stiffer than any seen). The
  row's ``capped_by`` names the limit that bound the step (``"stability"``,
  ``"stability over 1 + J"``, ``"divergence onset"``; None where the acceptance falls to
  the target below every limit);
* at that step: the estimated acceptance with its standard error, the divergence rate, the
  mean energy error, gradient evaluations per proposal, per accepted proposal and per
  accepted unit of simulated time; and the Gaussian figures at the mode at the same step
  (``laplace_acceptance``, ``laplace_expected_error``, from
  :mod:`stepsafe.core.hmc`, exact for a Gaussian);
* where divergent proposals start (a scan of h on the estimate);
* the Laplace step at target, and the Laplace ranking.

Methods are ranked by gradient evaluations per accepted proposal at the L the sampler runs
(``ranked_by``, :data:`stepsafe.core.hmc.RANKINGS`; the trajectory is always given here):
``(L e + extra) / alpha`` with the estimated acceptance ``alpha`` at each method's step at
target. The Laplace ranking is the same criterion on the Gaussian at the mode (its own step
at target and exact acceptance), and the report lists the methods whose two ranks differ
(``ranking_differs``). Non-reversible (non-symmetric) methods are listed, not ranked;
non-symplectic ones are not run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from stepsafe.core import hmc as gaussian
from stepsafe.core.hmc import Trajectory
from stepsafe.core.hmc_target.draws import (
    DIVERGENT,
    ESS_LIMIT,
    RHAT_LIMIT,
    SEED,
    Draws,
    Laplace,
    find_mode,
    flat_direction,
    gradient_mismatch,
    sample,
    slow_direction,
)
from stepsafe.core.hmc_target.estimate import (
    Estimate,
    Estimator,
    Onset,
    divergence_onset,
    target_step,
)
from stepsafe.core.hmc_target.frequencies import Spread, coordinate_scales, spread
from stepsafe.core.hmc_target.modes import MODE_MASS, Survey, survey
from stepsafe.core.hmc_target.potential import Target
from stepsafe.core.hmc_target.statistics import rate_bound
from stepsafe.core.hmc_target.trajectories import scheme
from stepsafe.core.records import versioned
from stepsafe.core.regions import find_region, stable_run
from stepsafe.exceptions import NotConverged, StepsafeError
from stepsafe.methods.tableaux import Method

#: The divergence scan runs up to this multiple of the larger stability step (draws', mode's).
ONSET_REACH = 1.5


@dataclass(frozen=True)
class TargetRow:
    """One method's figures on the target (module docstring; steps in the target's time
    unit; None where a figure does not exist)."""

    method: str
    evaluations: int | None
    symmetric: bool
    z_star: float | None
    stability_h: float | None
    laplace_stability_h: float | None
    h_target: float | None
    h_target_se: float | None
    estimate: Estimate | None
    laplace_acceptance: float | None = None
    laplace_expected_error: float | None = None
    laplace_h_target: float | None = None
    laplace_gradients_per_time: float | None = None
    laplace_gradients_per_accepted: float | None = None
    onset: Onset | None = None
    at_step: Estimate | None = None
    laplace_at_step: float | None = None
    rank: int | None = None
    laplace_rank: int | None = None
    notes: tuple[str, ...] = ()
    capped_by: str | None = None

    #: the keys of this row in ``hmc --json`` held by :attr:`estimate` (the figures at
    #: ``h_target``) or named otherwise
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        **{key: f"estimate.{key}" for key in (
            "steps", "acceptance", "acceptance_se", "divergent", "divergent_bound",
            "expected_error",
            "expected_error_se", "gradients_per_proposal", "gradients_per_accepted",
            "gradients_per_time")},
        "divergence_onset": "onset", "at_step": "at_step_record"})

    @property
    def at_step_record(self) -> dict[str, Any] | None:
        """The figures at the step asked for (``hmc --step H``), with the Laplace
        acceptance there, as ``hmc --json`` gives them (None: no step asked for)."""
        if self.at_step is None:
            return None
        return {"h": self.at_step.h, "steps": self.at_step.steps,
                "acceptance": self.at_step.acceptance,
                "acceptance_se": self.at_step.acceptance_se,
                "divergent": self.at_step.divergent,
                "divergent_bound": self.at_step.divergent_bound,
                "expected_error": _finite(self.at_step.expected_error),
                "gradients_per_accepted": self.at_step.gradients_per_accepted,
                "laplace_acceptance": self.laplace_at_step}

    def to_dict(self) -> dict[str, Any]:
        """This method's row of ``hmc --json``."""
        e = self.estimate
        out: dict[str, Any] = {
            "method": self.method, "evaluations": self.evaluations,
            "symmetric": self.symmetric, "z_star": self.z_star,
            "stability_h": self.stability_h, "laplace_stability_h": self.laplace_stability_h,
            "h_target": self.h_target, "h_target_se": self.h_target_se,
            "capped_by": self.capped_by,
            "steps": None if e is None else e.steps,
            "acceptance": None if e is None else e.acceptance,
            "acceptance_se": None if e is None else e.acceptance_se,
            "divergent": None if e is None else e.divergent,
            "divergent_bound": None if e is None else e.divergent_bound,
            "expected_error": None if e is None else _finite(e.expected_error),
            "expected_error_se": None if e is None else _finite(e.expected_error_se),
            "gradients_per_proposal": None if e is None else e.gradients_per_proposal,
            "gradients_per_accepted": None if e is None else e.gradients_per_accepted,
            "gradients_per_time": None if e is None else e.gradients_per_time,
            "rank": self.rank,
            "laplace_acceptance": self.laplace_acceptance,
            "laplace_expected_error": _finite(self.laplace_expected_error),
            "laplace_h_target": self.laplace_h_target,
            "laplace_gradients_per_time": self.laplace_gradients_per_time,
            "laplace_gradients_per_accepted": self.laplace_gradients_per_accepted,
            "laplace_rank": self.laplace_rank,
            "divergence_onset": None if self.onset is None else {
                "h_clean": self.onset.h_clean, "h_divergent": self.onset.h_divergent,
                "proposals": self.onset.proposals, "scanned_to": self.onset.scanned_to,
                "rate_bound_clean": self.onset.rate_bound_clean},
            "at_step": self.at_step_record,
            "notes": list(self.notes)}
        return out


def _finite(x: float | None) -> float | None:
    """JSON has no inf: None for a non-finite figure."""
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass(frozen=True)
class TargetReport:
    """Methods ranked on the target (module docstring), with the draws, the spread of
    frequencies over them and the Laplace approximation they were compared with."""

    rows: tuple[TargetRow, ...]
    target_accept: float
    trajectory: Trajectory
    allow_unstable_jitter: bool
    dimension: int
    draws: Draws
    spread: Spread
    laplace: Laplace | None
    seed: int
    notes: tuple[str, ...] = field(default=())
    #: the search for other modes and the draws' visits to them (None: not searched)
    modes: Survey | None = None

    @property
    def unverified(self) -> str | None:
        """Why the estimates are not verified: the draws fail a convergence diagnostic or
        cannot be checked (:func:`unconverged`), or miss a mode the mode search found
        (:mod:`stepsafe.core.hmc_target.modes`), so they may not represent the target (a
        mode they missed changes the acceptance by more than its standard error, which
        assumes they do), or come from a sampler whose kept run had divergent transitions
        at every step it tried (:func:`diverged`), and h at target is not a
        recommendation; None only when the draws pass all three."""
        return unconverged(self.draws) or diverged(self.draws) or (
            None if self.modes is None else self.modes.missed_text())

    @property
    def verified(self) -> bool:
        """Whether the draws pass the convergence diagnostics, the divergence check and the
        mode search (:attr:`unverified`)."""
        return self.unverified is None

    #: what the gradient figures count
    COST_UNIT: ClassVar[str] = "gradient evaluations"
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "steps": "trajectory.steps", "length": "trajectory.length",
        "jitter": "trajectory.jitter", "cost_unit": "COST_UNIT",
        "laplace": "laplace_record", "methods": "rows", "mode_search": "modes"})

    @property
    def ranked_by(self) -> str:
        """The row key methods are ranked by (:data:`stepsafe.core.hmc.RANKINGS`)."""
        return gaussian.ranked_by(self.trajectory)

    @property
    def ranking_differs(self) -> list[dict[str, Any]]:
        """The methods ranked differently on the target and at the mode (Laplace), each
        with both ranks."""
        return [{"method": r.method, "rank": r.rank, "laplace_rank": r.laplace_rank}
                for r in self.rows if _differs(r)]

    @property
    def frequencies(self) -> dict[str, Any]:
        """The spread of the largest frequency over the draws, as ``hmc --json`` gives
        it: how it was found, over how many draws, ``omega_max`` (rad per time unit) and
        its quantiles, the share of draws with an inverted mode, the Lanczos residual."""
        return {"how": self.spread.how, "draws": self.spread.draws,
                "omega_max": self.spread.top,
                "omega_max_quantiles": {str(k): v for k, v in
                                        self.spread.quantiles().items()},
                "inverted_share": self.spread.inverted_share(),
                "lanczos_residual": (None if self.spread.residual is None else
                                     float(self.spread.residual.max()))}

    @property
    def laplace_record(self) -> dict[str, Any] | None:
        """The Gaussian (Laplace) approximation at the mode, as ``hmc --json`` gives it:
        whether its Hessian is positive definite, the search converged, the gradient norm
        there and its slowest and fastest beta (None: not found)."""
        lap = self.laplace
        if lap is None:
            return None
        return {"positive_definite": lap.positive_definite, "converged": lap.converged,
                "gradient_norm": lap.gradient_norm,
                "beta_min": float(lap.betas[0]) if lap.positive_definite else None,
                "beta_max": float(lap.betas[-1]) if lap.positive_definite else None}

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe hmc SCENE --json`` prints for a potential target."""
        d = self.draws
        return versioned({
            "target_accept": self.target_accept, "steps": self.trajectory.steps,
            "length": self.trajectory.length, "jitter": self.trajectory.jitter,
            "allow_unstable_jitter": self.allow_unstable_jitter,
            "dimension": self.dimension, "seed": self.seed,
            "cost_unit": self.COST_UNIT, "ranked_by": self.ranked_by,
            "ranking_differs": self.ranking_differs,
            "draws": {"source": d.source, "chains": d.chains, "per_chain": d.per_chain,
                      "seed": d.seed, "sampler_step": d.step, "sampler_max_steps": d.max_steps,
                      "sampler_acceptance": d.acceptance, "sampler_divergent": d.divergent,
                      "sampler_first_step": d.first_step,
                      "sampler_first_divergent": d.first_divergent,
                      "sampler_refit_steps": list(d.refit_steps),
                      "rhat": _finite(d.rhat), "effective_size":
                      _finite(d.effective_size), "stuck_chains": d.stuck,
                      "converged": d.converged},
            "verified": self.verified, "unverified": self.unverified,
            "mode_search": None if self.modes is None else self.modes.record(),
            "frequencies": self.frequencies, "laplace": self.laplace_record,
            "methods": [r.to_dict() for r in self.rows], "notes": list(self.notes)})


def _differs(row: TargetRow) -> bool:
    """Whether the method is ranked both on the target and at the mode, differently."""
    return row.rank is not None and row.laplace_rank is not None and \
        row.rank != row.laplace_rank


def _within(h: float, factor: float) -> float:
    """The largest float q <= h / factor with ``q * factor <= h`` in float64."""
    q = h / factor
    while q * factor > h:
        q = float(np.nextafter(q, 0.0))
    return q


def unconverged(draws: Draws) -> str | None:
    """Why ``draws`` do not count as converged, naming the diagnostic that fails and its
    limit (R-hat above :data:`RHAT_LIMIT`, effective sample size below
    :data:`ESS_LIMIT`, or none computed: too few draws per chain); None when they do."""
    if draws.stuck:
        return (f"the draws have not converged: {draws.stuck} of {draws.chains} chain(s) "
                "stay at one position throughout (every proposal rejected)")
    if draws.converged is None:
        return ("the draws' convergence cannot be checked: R-hat and the effective sample "
                "size need at least 4 draws per chain")
    failed = []
    if draws.rhat is not None and not draws.rhat <= RHAT_LIMIT:
        failed.append(f"R-hat {draws.rhat:.4f} is above {RHAT_LIMIT:g}")
    if draws.effective_size is not None and not draws.effective_size >= ESS_LIMIT:
        failed.append(f"the effective sample size {draws.effective_size:.4g} is below "
                      f"{ESS_LIMIT:g}")
    if not failed:
        return None
    return f"the draws have not converged: {' and '.join(failed)}"


def diverged(draws: Draws) -> str | None:
    """Why draws from the warm-up sampler whose kept run had divergent transitions (energy
    error above :data:`~stepsafe.core.hmc_target.draws.DIVERGENT`) at its own step and at
    every refit (:func:`~stepsafe.core.hmc_target.draws.sample`) do not count: a
    divergent transition is a trajectory the integrator could not follow, almost always
    through a region stiffer than the step allows (a funnel's neck); the chain rejects it
    and stays out, so the draws under-represent that region, R-hat and the effective
    sample size cannot tell, and the acceptance and divergence rate estimated on them are
    too optimistic there. None when the draws have none (or are given)."""
    if draws.source != "warm-up" or not draws.divergent:
        return None
    n = draws.chains * draws.per_chain
    tried = draws.refit_steps
    return (f"the warm-up sampler's kept run had {draws.divergent} divergent transitions of "
            f"{n} (energy error above {DIVERGENT:g}) at its step {draws.step:.4g}"
            + (f", and its refits at step{'s' if len(tried) > 1 else ''} "
               f"{', '.join(f'{h:.4g}' for h in tried)} diverged too" if tried else "")
            + ": its trajectories cannot follow the target somewhere, likely a region of "
            "high curvature (such as a funnel's neck), so the draws likely miss that region "
            "and the estimates may be off by more than their standard errors (give exact "
            "draws, or reparametrise the target)")


def hmc_on_target(target: Target, methods: Sequence[Method], trajectory: Trajectory, *,
                  target_accept: float = gaussian.DEFAULT_TARGET, step: float | None = None,
                  draws: Draws | None = None, laplace: Laplace | None = None,
                  seed: int = SEED, start: np.ndarray | None = None,
                  allow_unstable_jitter: bool = False, onset: bool = True,
                  zmax: float = 10.0, where: str | None = None,
                  require_converged: bool = False,
                  check_gradient: str | None = None) -> TargetReport:
    """HMC with each of ``methods`` on ``target`` (module docstring).

    Parameters
    ----------
    target
        The potential and mass.
    methods
        Methods of :mod:`stepsafe.methods.tableaux`.
    trajectory
        L (``steps``) or the integration time (``length``), and the jitter J; one of the
        first two is needed.
    target_accept
        The acceptance the step at target reaches.
    step
        Also estimate every method at this nominal step.
    draws
        Draws from the target (default: the warm-up sampler's, seeded by ``seed``).
    laplace
        The mode and its Gaussian approximation (default: found from ``start``).
    seed
        Seed of the warm-up sampler; the estimates' common random numbers use ``seed + 1``.
    start
        Where the mode search (and, without a mode, the chains) start.
    allow_unstable_jitter
        Search steps up to the stability limit itself rather than its quotient by 1 + J,
        and past the onset of divergent proposals.
    onset
        Scan for the step where divergent proposals start.
    zmax
        How far in z the methods' stability is analysed.
    where
        The scene file whose ``system:`` gives the target, named in refusals (None: the
        Python keywords).
    require_converged
        Refuse draws that have not converged (:func:`unconverged`), before any estimate.
    check_gradient
        The keyword of a gradient the user gave beside the energy: it is compared with
        central differences of the energy near the start and the mode, and refused, naming
        the keyword, where they disagree
        (:func:`stepsafe.core.hmc_target.draws.gradient_mismatch`); None: not checked (an
        exact or automatic gradient).

    Returns
    -------
    TargetReport
    """
    if not 0.0 < target_accept < 1.0:
        raise StepsafeError(f"target acceptance must be in (0, 1), got {target_accept!r}")
    if trajectory.steps is None and trajectory.length is None:
        raise StepsafeError("HMC on a target needs the number of steps per trajectory or the "
                            "trajectory length (the acceptance depends on it)")
    notes: list[str] = []
    if check_gradient is not None:
        at = (np.zeros(target.dimension) if start is None
              else np.asarray(start, dtype=float).reshape(target.dimension))
        mismatch = gradient_mismatch(target.potential, at)
        if mismatch is None and laplace is None:
            laplace = find_mode(target, start)
            if laplace is not None:
                mismatch = gradient_mismatch(target.potential, laplace.mode)
        if mismatch is not None:
            x = mismatch.position
            point = ", ".join(f"{v:.6g}" for v in x[:4]) + (", ..." if x.size > 4 else "")
            raise StepsafeError(
                f"component {mismatch.axis} of the gradient of log pi is "
                f"{-mismatch.gradient:.6g} at q = ({point}), where central differences of the "
                f"log-density give {-mismatch.difference:.6g}: the gradient given is not that "
                "of the log-density (check its sign, factor and coordinate order)",
                check_gradient)
    if laplace is None:
        laplace = find_mode(target, start)
    if laplace is None:
        notes.append("no mode found (or d too large for a dense Hessian): no Laplace figures")
    flat = None if laplace is None else flat_direction(target, laplace)
    if flat is not None:
        along = ("where its curvature is not positive" if not flat.curvature > 0 else
                 f"where its curvature is {flat.curvature:.3g} ({flat.scales:.3g} of its own "
                 "standard deviations)")
        raise StepsafeError(
            "the target is improper: U rises by less than 1 over a distance of "
            f"{flat.distance:.3g} from its mode along a direction {along}, so "
            "exp(-U) does not integrate (give a proper prior along it)",
            f"{where}::$.system.potential" if where else "logdensity")
    slow = None if laplace is None else slow_direction(target, laplace)
    if slow is not None:
        region = ("a tube around it, whose integral diverges for a power at most 1"
                  if slow.neighbourhood == "tube" else
                  f"a cone around it, whose integral diverges in {slow.dimension} dimensions "
                  f"for a power at most {slow.dimension}")
        raise StepsafeError(
            f"the target is improper: far from its mode U grows only like {slow.slope:.3g} "
            f"log r along a direction (r from {slow.inner:.3g} to {slow.outer:.3g}), so "
            f"exp(-U) decays like r^-{slow.slope:.3g} over {region} (give a proper prior, "
            "or a potential that grows faster)",
            f"{where}::$.system.potential" if where else "logdensity")
    if laplace is not None and not laplace.positive_definite:
        notes.append("the Hessian at the mode found is not positive definite: no Laplace "
                     "figures")
    modes = None if laplace is None else survey(target, laplace, seed + 3)
    if modes is None:
        notes.append("no search for other modes (it starts from a positive definite "
                     "Laplace approximation at the mode found): modes the draws do not "
                     "visit are not looked for")
    if draws is None:
        draws = sample(target, seed=seed, laplace=laplace, start=start, where=where)
    if modes is not None:
        modes = modes.visited_by(draws)
        notes.append(_survey_note(modes))
    if require_converged:
        refusal = unconverged(draws) or diverged(draws) or (
            None if modes is None else modes.missed_text())
        if refusal is not None:
            raise NotConverged(refusal + " (require_converged; --require-converged on the "
                               "command line)",
                               f"{where}::$.system.potential" if where else "draws")
    if draws.converged is False and not draws.stuck and draws.rhat is not None \
            and draws.effective_size is not None:
        notes.append(f"the draws have not converged (R-hat {draws.rhat:.4f}, limit "
                     f"{RHAT_LIMIT:g}; effective sample size {draws.effective_size:.4g}, limit "
                     f"{ESS_LIMIT:g}): they may not represent the target, the estimates may "
                     "be off by more than their standard errors, and h at target is not a "
                     "recommendation (unverified)")
    elif draws.converged is not True:
        notes.append(f"{unconverged(draws)}: they may not represent the target, the "
                     "estimates may be off by more than their standard errors, and h at "
                     "target is not a recommendation (unverified)")
    if draws.refit_steps and not draws.divergent:
        notes.append(f"the warm-up sampler's first kept run had {draws.first_divergent} "
                     f"divergent transition(s) at its step {draws.first_step:.4g}; the kept "
                     f"run was made afresh at step {draws.step:.4g}, where none of its "
                     f"{draws.chains * draws.per_chain} transitions diverged: these draws "
                     "are that run's")
    freq = spread(target, draws, seed=seed + 2)
    if not freq.top > 0:
        blame = ("draws" if draws.source == "given" else
                 f"{where}::$.system.potential" if where else "logdensity")
        if not (np.isfinite(freq.omega_max).all() and np.isfinite(freq.lambda_min).all()):
            raise StepsafeError("the curvature of the target at the draws is not finite in "
                                "float64 (it overflows there): rescale the target, its mass "
                                "or the draws", blame)
        raise StepsafeError("the target has no positive curvature at any draw, so there is no "
                            "linear stability limit to bound the step search (a density "
                            "whose curvature is nowhere positive, such as a Gamma of shape "
                            "below 1, is not analysed)", blame)
    estimator = Estimator(target, draws, seed=seed + 1,
                          scale=coordinate_scales(draws.flat))
    betas = laplace.betas if laplace is not None and laplace.positive_definite else None
    rows = []
    for m in methods:
        rows.append(_row(m, target_accept, trajectory, step, estimator, freq, betas,
                         allow_unstable_jitter, onset, zmax))
    rows = _ranked(rows)
    differ = [f"{r.method} (rank {r.rank}, Laplace {r.laplace_rank})" for r in rows
              if _differs(r)]
    if differ:
        notes.append("by gradients per accepted proposal, the ranking on the target differs "
                     "from the Gaussian (Laplace) one for " + ", ".join(differ))
    return TargetReport(tuple(rows), float(target_accept), trajectory,
                        bool(allow_unstable_jitter), target.dimension, draws, freq, laplace,
                        seed, tuple(notes), modes)


def _survey_note(modes: Survey) -> str:
    """What the mode search covered, what it found and what it does not cover."""
    n = len(modes.modes) - 1
    found = ("found no other mode" if not n else
             f"found {n} other mode(s), {len(modes.missed)} of them missed by the draws")
    return (f"mode search: {modes.starts} starts at each of "
            f"{', '.join(f'{s:g}' for s in modes.scales)} Laplace standard deviations from "
            f"the mode found, {modes.iterations} descent steps each, {found}"
            + (f" ({modes.stopped})" if modes.stopped else "")
            + "; a mode whose basin none of these starts reached, or with a Laplace share "
            f"below {MODE_MASS:g}, is not covered")


def _row(m: Method, target_accept: float, trajectory: Trajectory, step: float | None,
         estimator: Estimator, freq: Spread, betas: np.ndarray | None,
         allow_unstable_jitter: bool, onset: bool, zmax: float) -> TargetRow:
    run = scheme(m)
    region = find_region(m, "oscillator", zmax)
    notes: list[str] = []
    base = TargetRow(run.name, run.gradients_per_step, run.symmetric, None, None, None, None,
                     None, None)
    if not region.symplectic:
        return TargetRow(**{**base.__dict__, "notes": (
            "not symplectic: it does not preserve volume, so HMC with it does not sample "
            "the target",)})
    if not run.symmetric:
        notes.append("not symmetric: the HMC chain is not reversible with it (not ranked); "
                     "the acceptance shown is that of a proposal from the target")
    stable = stable_run(region)
    z_star = stable.first_unsafe if stable.first_unsafe is not None else region.zmax
    if stable.first_unsafe is None:
        notes.append(f"stable up to z = {region.zmax:g}, as far as analysed")
    h_stable = float(z_star / freq.top)
    laplace_h = None if betas is None else float(z_star / betas.max())
    jitter = trajectory.jitter
    h_hi = h_stable if (allow_unstable_jitter or not jitter) else _within(h_stable, 1 + jitter)
    cap = "stability" if h_hi == h_stable else "stability over 1 + J"
    # the onset of divergences on the same proposals bounds the search too (scanned up to
    # h_hi at least, so that the bound is known where it binds)
    reach = max(ONSET_REACH * max(h_stable, laplace_h or 0.0), h_hi) if onset else h_hi
    scan = divergence_onset(estimator, run, reach, trajectory)
    if not allow_unstable_jitter and scan.h_divergent is not None and (
            scan.h_clean is None or scan.h_clean < h_hi):
        h_hi, cap = scan.h_clean or 0.0, "divergence onset"
    found = None if h_hi <= 0 else target_step(estimator, run, target_accept, h_hi, trajectory)
    est = None if found is None else found.estimate
    h_target = None if found is None else found.h
    capped_by = None if found is None or not found.capped else cap
    if found is None:
        notes.append(f"no step up to h = {h_hi:.6g} reaches acceptance {target_accept:g} on "
                     "the target" + (" without divergent proposals"
                                     if cap == "divergence onset" else ""))
    elif capped_by == "divergence onset":
        notes.append(f"h at target is capped at h = {h_hi:.6g}, the largest step scanned "
                     f"at which none of the {scan.proposals} proposals diverged (a divergence "
                     f"rate below {rate_bound(0, scan.proposals):.2g} at 95% confidence "
                     "there, not shown to be 0; at least one diverged at "
                     f"h = {scan.h_divergent:.6g}), below the stiffest draw's stability limit "
                     f"{h_stable:.6g}" + (f" over 1 + J = {1 + jitter:g}" if jitter and not
                                          allow_unstable_jitter else ""))
    elif found.capped:
        notes.append(f"h at target is capped at h = {h_hi:.6g}: the stability limit of the "
                     "stiffest draw" + (f" over 1 + J = {1 + jitter:g}" if h_hi < h_stable
                                        else ""))
    if est is not None and jitter and allow_unstable_jitter and h_target is not None:
        share = min(max((1.0 + jitter - h_stable / h_target) / (2.0 * jitter), 0.0), 1.0)
        if share > 0:
            notes.append(f"{100 * share:.3g}% of the jittered steps h (1 +- {jitter:g}) pass "
                         f"the stiffest draw's stability limit {h_stable:.6g}")
    lap_acc = lap_err = lap_h = lap_cost = lap_accepted = lap_at = None
    if betas is not None:
        if h_target is not None:
            a = gaussian.acceptance_at(m, betas, h_target, trajectory)
            lap_acc, lap_err = a.rate, a.expected_error
        assert laplace_h is not None
        lap_hi = laplace_h if (allow_unstable_jitter or not jitter) else _within(
            laplace_h, 1 + jitter)
        lap_h = gaussian.target_step(m, betas, target_accept, lap_hi, trajectory)
        if lap_h is not None and run.gradients_per_step is not None:
            a = gaussian.acceptance_at(m, betas, lap_h, trajectory)
            L = trajectory.steps_at(lap_h)
            if a.rate > 0 and L:
                per_proposal = run.gradients_per_step * L + run.gradients_per_trajectory_extra
                lap_cost = per_proposal / (a.rate * L * lap_h)
                lap_accepted = per_proposal / a.rate
        if step is not None:
            lap_at = gaussian.acceptance_at(m, betas, step, trajectory).rate
    at_step = None if step is None else estimator.estimate(run, step, trajectory)
    if est is not None and est.divergent > 0:
        notes.append(f"{100 * est.divergent:.3g}% of the proposals at h at target diverge "
                     f"(energy error > 1000)")
    return TargetRow(run.name, run.gradients_per_step, run.symmetric, float(z_star), h_stable,
                     laplace_h, h_target, None if found is None else found.h_se, est,
                     lap_acc, lap_err, lap_h, lap_cost, lap_accepted,
                     scan if onset else None, at_step, lap_at, notes=tuple(notes),
                     capped_by=capped_by)


def _ranked(rows: list[TargetRow]) -> list[TargetRow]:
    """Rows sorted by gradients per accepted proposal on the target (symmetric ones
    ranked), each with its rank there and its rank by the Laplace figures."""
    def cost(r: TargetRow) -> float | None:
        return None if r.estimate is None else r.estimate.gradients_per_accepted

    index = range(len(rows))
    usable = sorted((k for k in index if rows[k].symmetric and cost(rows[k]) is not None),
                    key=lambda k: cost(rows[k]) or 0.0)
    rank = {k: n + 1 for n, k in enumerate(usable)}
    lap = sorted((k for k in index if rows[k].symmetric
                  and rows[k].laplace_gradients_per_accepted is not None),
                 key=lambda k: rows[k].laplace_gradients_per_accepted or 0.0)
    lap_rank = {k: n + 1 for n, k in enumerate(lap)}
    out = [TargetRow(**{**rows[k].__dict__, "rank": rank.get(k),
                        "laplace_rank": lap_rank.get(k)}) for k in index]
    return sorted(out, key=lambda r: (r.rank is None, r.rank or 0))
