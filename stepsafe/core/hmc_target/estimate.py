"""The acceptance of HMC on a target, estimated from draws with common random numbers.

For a method at nominal step h, L steps and jitter J, the expected acceptance of a proposal
from the stationary state is ``alpha = E[min(1, e^-Delta)]`` over ``q ~ pi`` and
``p ~ N(0, M)`` (``Delta`` the energy error of the method's own trajectory,
:mod:`stepsafe.core.hmc_target.trajectories`). It is estimated by the average of
``min(1, e^-Delta)`` over the draws, each with a fresh momentum (the Rao-Blackwellised
acceptance statistic: the probability, not the 0/1 outcome), with the Monte Carlo standard
error of a chain average (:mod:`stepsafe.core.hmc_target.statistics`: the draws of one
chain are correlated, the momenta are not). A proposal is divergent when ``Delta > 1000``
or its trajectory stopped being finite (BlackJAX's and Stan's rule); its acceptance
statistic is then ``e^-Delta`` (0 for a non-finite one).

Common random numbers. The momenta ``p = C z`` and jitter variates u are drawn once (from
the seed) and reused for every method and step, so that the estimate is a deterministic
function of h: a search for the step at target acceptance is a root search on one function,
and differences between methods or steps are not blurred by independent noise.

Step at target (:func:`target_step`). The largest h below ``h_hi`` with the estimated
acceptance at least the target at every step of a grid up to h (at least
:data:`TARGET_GRID` steps, more for a given L or integration time: the acceptance of a given
trajectory oscillates in h, :func:`stepsafe.core.hmc.target_grid`), then narrowed to
:data:`TARGET_RTOL` (regula falsi, :func:`narrowed`); its standard error is the
acceptance's standard error there divided by the slope of the estimate (a central
difference), none where the step is capped at ``h_hi``.

Divergence onset (:func:`divergence_onset`). On a grid of steps the first with a divergent
proposal among the n, bisected with the grid's previous step: below the lower end no
proposal of the n diverged (the divergence rate there is below ``3 / n`` with 95%
confidence, the rule of three), at the upper end at least one did.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stepsafe.core.hmc import Trajectory, target_grid
from stepsafe.core.hmc_target.draws import Draws
from stepsafe.core.hmc_target.potential import Target
from stepsafe.core.hmc_target.statistics import chain_mean, rate_bound
from stepsafe.core.hmc_target.trajectories import Scheme, energy_errors
from stepsafe.core.roots import narrowed
from stepsafe.exceptions import StepsafeError

#: The energy error beyond which a proposal counts as divergent (BlackJAX, Stan).
DIVERGENCE = 1000.0
#: At most this many steps per trajectory (L = floor(T / h) for a trajectory length T),
#: as the number of steps given is limited.
MAX_STEPS = 10**6
#: The target search: grid points up to the upper end (walked upwards) ...
TARGET_GRID = 16
#: ... then narrowed to this relative width (the estimate's noise is coarser).
TARGET_RTOL = 1e-3
#: The onset of divergences: grid points and bisections.
ONSET_GRID = 16
ONSET_RTOL = 1e-2


@dataclass(frozen=True)
class Estimate:
    """HMC figures of one method at one nominal step on the target.

    ``acceptance`` (with ``acceptance_se``) is the mean acceptance statistic,
    ``divergent`` the share of divergent proposals (``divergent_count`` of ``proposals``),
    ``expected_error`` the mean energy error (inf when a trajectory diverged to a
    non-finite state), ``gradients_per_proposal`` the gradient evaluations of one
    trajectory, ``effective_size`` that of the acceptance statistic."""

    method: str
    h: float
    steps: int
    jitter: float
    acceptance: float
    acceptance_se: float
    divergent: float
    divergent_count: int
    proposals: int
    expected_error: float
    expected_error_se: float
    gradients_per_proposal: float
    effective_size: float

    @property
    def divergent_bound(self) -> float:
        """The one-sided 95% upper bound on the divergence rate that ``divergent_count`` of
        ``proposals`` measures (:func:`~stepsafe.core.hmc_target.statistics.rate_bound`):
        about ``3 / proposals`` where none diverged, not 0."""
        return rate_bound(self.divergent_count, self.proposals)

    @property
    def gradients_per_accepted(self) -> float | None:
        """Gradient evaluations per accepted proposal (None at zero acceptance)."""
        return None if self.acceptance <= 0 else self.gradients_per_proposal / self.acceptance

    @property
    def gradients_per_time(self) -> float | None:
        """Gradient evaluations per accepted unit of simulated time ``L h`` (None at zero
        acceptance)."""
        if self.acceptance <= 0:
            return None
        return self.gradients_per_proposal / (self.acceptance * self.steps * self.h)


class Estimator:
    """The draws, their energies and gradients, and the common random numbers (module
    docstring) for estimates on one target.

    Parameters
    ----------
    target
        The potential and mass.
    draws
        Draws from the target.
    seed
        Seed of the momenta and jitter variates.
    scale
        Length scale of central differences where a method needs a Hessian: one for
        every coordinate, or one per coordinate (the draws' spread along each).
    """

    def __init__(self, target: Target, draws: Draws, seed: int = 0,
                 scale: float | np.ndarray = 1.0) -> None:
        self.target = target
        self.draws = draws
        self.seed = seed
        self.scale = scale
        self.q = draws.flat
        rng = np.random.default_rng(seed)
        self.p = target.mass.momenta(rng.standard_normal(self.q.shape))
        self.u = rng.uniform(-1.0, 1.0, size=self.q.shape[0])
        with np.errstate(all="ignore"):
            self.energy = target.potential.energy(self.q)
            self.gradient = target.potential.gradient(self.q)
        if not (np.isfinite(self.energy).all() and np.isfinite(self.gradient).all()):
            raise StepsafeError("the target's energy or gradient is not finite at a draw")

    @property
    def proposals(self) -> int:
        return int(self.q.shape[0])

    def deltas(self, run: Scheme, h: float, trajectory: Trajectory
               ) -> tuple[np.ndarray, int, float]:
        """The energy errors of every proposal at nominal step h, L and the gradients per
        proposal."""
        steps = trajectory.steps_at(h)
        if steps is None:
            raise StepsafeError("the acceptance on a target needs the number of steps or the "
                                "trajectory length")
        if trajectory.steps is None and steps > MAX_STEPS:
            raise StepsafeError(
                f"the trajectory length T = {trajectory.length:.6g} gives L = floor(T/h) "
                f"above {MAX_STEPS} steps per trajectory at h = {h:.6g} (at most {MAX_STEPS}, "
                "as for the number of steps): give a shorter length (--length T on the "
                "command line)", "length")
        hs = h * (1.0 + trajectory.jitter * self.u) if trajectory.jitter else h
        out = energy_errors(self.target, run, self.q, self.p, hs, steps, self.energy,
                            self.gradient, self.scale)
        cost = (run.gradients_per_step * steps + run.gradients_per_trajectory_extra
                if run.gradients_per_step is not None else out.gradients)
        return out.delta, steps, float(cost)

    def estimate(self, run: Scheme, h: float, trajectory: Trajectory) -> Estimate:
        """The :class:`Estimate` of ``run`` at nominal step h."""
        delta, steps, cost = self.deltas(run, h, trajectory)
        shape = (self.draws.chains, self.draws.per_chain)
        with np.errstate(over="ignore", invalid="ignore"):
            stat = np.where(np.isfinite(delta), np.exp(-np.maximum(delta, 0.0)), 0.0)
        acc = chain_mean(stat.reshape(shape))
        divergent = ~np.isfinite(delta) | (delta > DIVERGENCE)
        err = chain_mean(delta.reshape(shape))
        return Estimate(run.name, float(h), int(steps), trajectory.jitter, acc.value, acc.se,
                        float(divergent.mean()), int(divergent.sum()), delta.size,
                        err.value, err.se, cost, acc.effective_size)

    def acceptance(self, run: Scheme, h: float, trajectory: Trajectory) -> float:
        """The estimated acceptance alone (no standard error)."""
        delta, _, _ = self.deltas(run, h, trajectory)
        with np.errstate(over="ignore", invalid="ignore"):
            return float(np.mean(np.where(np.isfinite(delta),
                                          np.exp(-np.maximum(delta, 0.0)), 0.0)))

    def divergences(self, run: Scheme, h: float, trajectory: Trajectory) -> int:
        delta, _, _ = self.deltas(run, h, trajectory)
        return int((~np.isfinite(delta) | (delta > DIVERGENCE)).sum())


@dataclass(frozen=True)
class TargetStep:
    """The step at target acceptance on the target (module docstring): ``h`` with its
    standard error ``h_se`` (None where the slope is not resolved), the estimate there, and
    ``capped`` when the acceptance holds up to ``h_hi`` itself."""

    h: float
    h_se: float | None
    estimate: Estimate
    capped: bool


def target_step(estimator: Estimator, run: Scheme, target: float, h_hi: float,
                trajectory: Trajectory) -> TargetStep | None:
    """The largest step up to ``h_hi`` whose estimated acceptance reaches ``target`` at
    every grid step below it (module docstring); None when even ``h_hi / 2^30`` misses.

    The grid is walked upwards and stops at its first miss; the bracket it leaves is
    narrowed by :func:`narrowed` (regula falsi with a probe across each estimate).

    Parameters
    ----------
    estimator
        Draws and common random numbers.
    run
        The method.
    target
        The acceptance wanted, in (0, 1).
    h_hi
        The largest step considered (the stability limit over the draws, divided by
        ``1 + J`` unless unstable jittered steps are allowed).
    trajectory
        L (or the integration time) and the jitter.

    Returns
    -------
    TargetStep or None
    """
    def excess(h: float) -> float:
        return estimator.acceptance(run, h, trajectory) - target

    lo, f_lo = 0.0, 1.0 - target
    hi = f_hi = None
    for h in target_grid(trajectory, h_hi, TARGET_GRID):
        f = excess(float(h))
        if f < 0:
            hi, f_hi = float(h), f
            break
        lo, f_lo = float(h), f
    if hi is None:
        return _at(estimator, run, float(h_hi), trajectory, True)
    assert f_hi is not None
    if lo == 0.0:
        for _ in range(30):
            f = excess(hi / 2.0)
            if f >= 0:
                lo, f_lo = hi / 2.0, f
                break
            hi, f_hi = hi / 2.0, f
        else:
            return None
    lo = narrowed(excess, lo, f_lo, hi, f_hi, TARGET_RTOL)
    return _at(estimator, run, lo, trajectory, False)


def _at(estimator: Estimator, run: Scheme, h: float, trajectory: Trajectory,
        capped: bool) -> TargetStep:
    est = estimator.estimate(run, h, trajectory)
    dh = 0.02 * h
    slope = (estimator.acceptance(run, h + dh, trajectory)
             - estimator.acceptance(run, h - dh, trajectory)) / (2.0 * dh)
    h_se = est.acceptance_se / abs(slope) if (
        not capped and slope < 0 and math.isfinite(est.acceptance_se)) else None
    return TargetStep(h, h_se, est, capped)


@dataclass(frozen=True)
class Onset:
    """Where divergent proposals start: none of ``proposals`` diverged at ``h_clean`` (the
    rate there is below ``3 / proposals`` with 95% confidence), at least one did at
    ``h_divergent``; ``h_divergent`` is None where the scan found none up to its end
    (``h_clean`` is then that end), ``h_clean`` None where even the scan's first step had
    divergent proposals."""

    h_clean: float | None
    h_divergent: float | None
    proposals: int
    scanned_to: float

    @property
    def rate_bound_clean(self) -> float | None:
        """The 95% upper bound on the divergence rate at ``h_clean``, where none of the
        proposals diverged (:func:`~stepsafe.core.hmc_target.statistics.rate_bound`; None
        without ``h_clean``)."""
        return None if self.h_clean is None else rate_bound(0, self.proposals)


def divergence_onset(estimator: Estimator, run: Scheme, h_max: float,
                     trajectory: Trajectory) -> Onset:
    """The onset of divergent proposals up to ``h_max`` (module docstring).

    Parameters
    ----------
    estimator
        Draws and common random numbers.
    run
        The method.
    h_max
        The end of the scan.
    trajectory
        L (or the integration time) and the jitter.

    Returns
    -------
    Onset
    """
    n = estimator.proposals
    grid = h_max * np.arange(1, ONSET_GRID + 1) / ONSET_GRID
    lo = 0.0
    for h in grid:
        if estimator.divergences(run, float(h), trajectory):
            hi = float(h)
            break
        lo = float(h)
    else:
        return Onset(float(h_max), None, n, float(h_max))
    while hi - lo > ONSET_RTOL * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if estimator.divergences(run, mid, trajectory) else (mid, hi)
    return Onset(lo if lo > 0 else None, hi, n, float(h_max))
