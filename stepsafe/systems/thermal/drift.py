"""Energy drift per unit time at a step, from a thermal ensemble.

The energy error ``dH_n = H(q_n, p_n) - H(q_0, p_0)`` of each trajectory is recorded at
every step (never a stride, which can alias with the map's rotation) and fitted by a line
in time ``t = n h``; the drift is the slope of the ensemble mean (the mean of the
trajectories' slopes, least squares being linear), its standard error the spread of the
slopes over ``sqrt(trajectories)`` (independent trajectories), the fluctuation the root
mean square over trajectories of the standard deviation of ``dH`` over time. Trajectories
that fail (:mod:`stepsafe.systems.thermal.trajectories`) are left out of the fit and
counted; an ensemble with a failed trajectory has no bounded energy, so its drift meets no
tolerance (:meth:`Drift.bound` is inf), whatever the survivors' slope.

A stable map's energy error oscillates without growing; a least-squares slope over a finite
run of N steps still picks up part of that oscillation (at most ``3 A / (N h)`` for an
amplitude A, and systematically where the rotation per step is a rational part of a turn):
a drift means something when its total over the run, ``rate N h``, stands well above the
fluctuation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.methods.tableaux import Method
from stepsafe.systems.thermal.potential import Potential
from stepsafe.systems.thermal.trajectories import DISTANCE, GROWTH, Outcome, Start, run


@dataclass(frozen=True)
class Drift:
    """The energy drift at one step.

    Attributes
    ----------
    h : float
    rate, error : float
        Drift (energy per unit time) and its standard error.
    fluctuation : float
        Energy fluctuation (root mean square of the standard deviation over time).
    kT : float
    dimension : int
        Degrees of freedom (for rates per degree of freedom).
    trajectories, failed, steps, seed : int
    """

    h: float
    rate: float
    error: float
    fluctuation: float
    kT: float
    dimension: int
    trajectories: int
    failed: int
    steps: int
    seed: int

    @property
    def per_dof(self) -> float:
        """``rate / dimension``."""
        return self.rate / self.dimension

    def bound(self, sigmas: float = 2.0) -> float:
        """``|rate| + sigmas * error``: what the drift may reach at that many standard
        errors; inf when a trajectory failed (the slope is fitted on the survivors, and an
        ensemble that loses trajectories has no bounded energy) or the rate is not
        finite."""
        b = abs(self.rate) + sigmas * self.error
        return b if self.failed == 0 and math.isfinite(b) else math.inf


def from_outcome(outcome: Outcome, kT: float, dimension: int, seed: int) -> Drift:
    """The drift record of one ensemble run."""
    return Drift(outcome.h, outcome.drift, outcome.drift_error, outcome.fluctuation, kT,
                 dimension, outcome.trajectories, outcome.failures, outcome.steps, seed)


def measure(method: Method, pot: Potential, start: Start, h: float, steps: int,
            rho: float = math.inf, growth: float = GROWTH,
            distance: float = DISTANCE) -> Drift:
    """The drift at h from the start's trajectories, ``steps`` steps each.

    Parameters
    ----------
    method : Method
    pot : Potential
    start : Start
        Thermal initial conditions.
    h : float
    steps : int
    rho : float
        The energy-ratio bound for the failure test (inf: only non-finite states and
        escapes fail).
    growth, distance : float
        Failure thresholds.

    Returns
    -------
    Drift
    """
    h = positive_finite(h, "h")
    out = run(method, pot, start, [h], steps, [rho], growth, distance)[0]
    if out.failures == out.trajectories:
        raise StepsafeError(f"every trajectory failed at h = {h:.6g}: no drift to measure")
    return from_outcome(out, start.kT, pot.dimension, start.seed)
