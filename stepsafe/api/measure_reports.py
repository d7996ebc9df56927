"""The results of :func:`stepsafe.measure` and :func:`stepsafe.refine` (runs of the method on
the scene's own system): frozen objects whose ``to_dict()`` is the ``--json`` output of
``stepsafe measure`` (see :mod:`stepsafe.api.reports`)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

from stepsafe.comparison import compared
from stepsafe.core.records import unversioned, versioned


@compared
@dataclass(frozen=True, eq=False)
class InvariantRow:
    """A conserved quantity the scene declares, along one run: ``spread`` (max - min of
    ``(I(x_k) - I(x_0)) / |I(x_0)|``, absolute when ``I(x_0) = 0``), ``drift`` (the
    least-squares slope of that error against time, per time unit), ``r2`` (the share of
    its variance the line explains) and ``behaviour``: ``drift`` when that share is at
    least one half, else ``bounded``."""

    name: str
    spread: float
    drift: float | None
    r2: float | None
    behaviour: str | None

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "spread": self.spread, "drift": self.drift, "r2": self.r2,
                "behaviour": self.behaviour}


@compared
@dataclass(frozen=True, eq=False)
class MeasureRow:
    """What one step size h did on the system (None where not measured or predicted)."""

    h: float
    steps: int
    time: float
    status: str
    energy_error: float | None
    energy_drift: float | None
    trajectory_error: float | None
    evaluations_per_time: float | None
    iterations_per_step: float | None
    predicted_energy_error: float | None
    predicted_trajectory_error: float | None
    jacobians_per_time: float | None = None
    """Hessian evaluations (and stage-matrix factorisations) per unit time: simplified
    Newton's method takes one per implicit step, on top of the force evaluations"""
    gradients_per_time: float | None = None
    """force-gradient terms (Hessian-vector products) per unit time, on top of the forces"""
    reference_error: float | None = None
    """the reference's own error at ``time``, relative as ``trajectory_error`` (None: the
    exact flow); a trajectory error below it is not a number: ``trajectory_error`` is
    then None and ``below_reference`` True (the error is less than this floor)"""
    below_reference: bool = False
    energy_r2: float | None = None
    """the energy error against time: the share of its variance the least-squares line
    through every step explains, and ``drift`` (at least one half) or ``bounded``"""
    energy_behaviour: str | None = None
    invariants: tuple[InvariantRow, ...] = ()
    """the scene's declared invariants, measured like the energy"""
    seconds_per_time: float | None = None
    """wall-clock seconds per unit of simulated time of the run (monitoring included)"""

    @property
    def energy_ratio(self) -> float | None:
        """The measured energy error over the predicted one (None: either is missing, or
        the prediction is rounding of 0)."""
        return _ratio(self.energy_error, self.predicted_energy_error)

    @property
    def trajectory_ratio(self) -> float | None:
        """The measured trajectory error over the predicted one; None once the predicted
        phase drift reaches half a turn (the prediction is then the largest error, 2, not
        the error)."""
        if self.predicted_trajectory_error is not None and \
                self.predicted_trajectory_error >= 2.0:
            return None
        return _ratio(self.trajectory_error, self.predicted_trajectory_error)

    def to_dict(self) -> dict[str, Any]:
        """One row of the measurement, as JSON.

        Returns
        -------
        dict
            One entry of ``rows`` in ``stepsafe measure --json``.
        """
        return {"h": self.h, "steps": self.steps, "time": self.time, "status": self.status,
                "energy_error": self.energy_error, "energy_drift": self.energy_drift,
                "trajectory_error": self.trajectory_error,
                "evaluations_per_time": self.evaluations_per_time,
                "iterations_per_step": self.iterations_per_step,
                "predicted_energy_error": self.predicted_energy_error,
                "predicted_trajectory_error": self.predicted_trajectory_error,
                "energy_ratio": self.energy_ratio, "trajectory_ratio": self.trajectory_ratio,
                "jacobians_per_time": self.jacobians_per_time,
                "gradients_per_time": self.gradients_per_time,
                "reference_error": self.reference_error,
                "below_reference": self.below_reference,
                "energy_r2": self.energy_r2, "energy_behaviour": self.energy_behaviour,
                "invariants": [i.to_dict() for i in self.invariants],
                "seconds_per_time": self.seconds_per_time}


@compared
@dataclass(frozen=True, eq=False)
class MeasureReport:
    """Measured errors and cost of ``method`` on the system for each h (``rows``), from
    ``initial`` (q then p), with the linear predictions for the vibration of angular
    frequency ``beta`` the start orbits (None: no prediction)."""

    method: str
    system: str
    initial: tuple[float, ...]
    energy: float
    beta: float | None
    reference: str
    rows: tuple[MeasureRow, ...]
    time_unit: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe measure --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned(copy.deepcopy({"method": self.method, "system": self.system,
                              "initial": list(self.initial), "energy": self.energy,
                              "beta": self.beta, "reference": self.reference,
                              "time_unit": self.time_unit,
                              "rows": [r.to_dict() for r in self.rows]}))


@compared
@dataclass(frozen=True, eq=False)
class EnsembleRow:
    """One step ``h`` run for ``steps`` steps (up to ``time``) on every trajectory of an
    ensemble: the distribution of each trajectory's largest energy error
    ``max_k |H(x_k) - H(x_0)| / |H(x_0) - H_e|`` over every step (median, 90 and 99
    percent quantiles by linear interpolation, maximum; None where a trajectory that left
    the finite numbers makes it infinite), ``unstable`` the trajectories that left them
    or whose error exceeds :data:`stepsafe.systems.measurement.UNSTABLE`, and
    ``errors``, each trajectory's value in the order of the ensemble's states (``inf``
    for an unstable one; not in :meth:`to_dict`)."""

    h: float
    steps: int
    time: float
    median: float | None
    q90: float | None
    q99: float | None
    max: float | None
    unstable: int
    errors: tuple[float, ...] = field(repr=False, default=())

    def to_dict(self) -> dict[str, Any]:
        """One row of the ensemble, as JSON.

        Returns
        -------
        dict
            One entry of ``rows`` in ``stepsafe measure --ensemble N --json``.
        """
        return {"h": self.h, "steps": self.steps, "time": self.time, "median": self.median,
                "q90": self.q90, "q99": self.q99, "max": self.max, "unstable": self.unstable}


@compared
@dataclass(frozen=True, eq=False)
class EnsembleReport:
    """``method`` run on ``count`` trajectories at once for each h (``rows``): states
    drawn with ``seed`` either on the quadratic energy shell ``energy`` around the
    elliptic equilibrium ``centre`` (``draw`` ``shell``: every phase, every split of the
    energy among the modes) or from the Boltzmann distribution of its quadratic model at
    ``kT`` (``draw`` ``thermal``); ``centre_energy`` is H there. ``states`` holds the
    initial states (one row of q then p per trajectory; not in :meth:`to_dict`)."""

    method: str
    system: str
    count: int
    seed: int
    draw: str
    energy: float | None
    kT: float | None
    centre: tuple[float, ...]
    centre_energy: float
    rows: tuple[EnsembleRow, ...]
    time_unit: str | None = None
    states: tuple[tuple[float, ...], ...] = field(repr=False, default=())

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"ensemble": "count"})

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe measure --ensemble N --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"method": self.method, "system": self.system,
                          "ensemble": self.count, "seed": self.seed, "draw": self.draw,
                          "energy": self.energy, "kT": self.kT,
                          "centre": list(self.centre), "centre_energy": self.centre_energy,
                          "time_unit": self.time_unit,
                          "rows": [r.to_dict() for r in self.rows]})


#: Predicted errors below this are rounding of an exact 0 (a method that conserves every
#: quadratic invariant has no energy error on a linear model): no ratio is formed.
NEGLIGIBLE = 1e-13


def _ratio(measured: float | None, predicted: float | None) -> float | None:
    if measured is None or predicted is None or predicted <= NEGLIGIBLE:
        return None
    return measured / predicted


@compared
@dataclass(frozen=True, eq=False)
class Refinement:
    """The largest step ``h`` (within the safe steps for the vibration the start orbits)
    whose measured ``quantity`` (``energy``: the energy spread; ``trajectory``: the
    trajectory error at T) is at most ``tol``, found by bisection on measurements
    (``runs``: every run made, in order), beside ``predicted``, the h the linear model
    gives for the same tolerance (None when the start orbits no vibration: the search
    then starts from T / 1000). ``limited_by``: ``tolerance``, ``safety`` (met up to the
    safe limit), ``time`` (met up to the run time, with no vibration), ``unreachable``
    (not met down to the smallest h tried) or ``reference`` (the tolerance is below the
    reference's own error, so no run can show it met)."""

    quantity: str
    tol: float
    h: float | None
    error: float | None
    predicted: float | None
    h_safe: float | None
    limited_by: str
    runs: MeasureReport
    below_reference: bool = False
    """the trajectory error at ``h`` is below the reference's own error: ``error`` is that
    floor, an upper bound"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"predicted_h": "predicted"})

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe measure --tol-energy T --json`` (or ``--tol-trajectory``)
        prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"quantity": self.quantity, "tol": self.tol, "h": self.h,
                          "error": self.error, "below_reference": self.below_reference,
                          "predicted_h": self.predicted, "h_safe": self.h_safe,
                          "limited_by": self.limited_by,
                          "runs": unversioned(self.runs.to_dict())})
