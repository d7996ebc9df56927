"""The results of :func:`stepsafe.hmc` and :func:`stepsafe.design` (HMC on a Gaussian
target): frozen objects whose ``to_dict()`` is the ``--json`` output of ``stepsafe hmc``
and ``stepsafe design`` (see :mod:`stepsafe.api.reports`)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import Any, ClassVar

from stepsafe.comparison import compared
from stepsafe.core.records import json_ready, versioned
from stepsafe.core.regions import ROUNDING_GAP_RULE


@compared
@dataclass(frozen=True, eq=False)
class HmcRow:
    """One method's HMC figures (steps in the time unit of 1/beta; None where a figure
    does not exist, e.g. no step reaches the target)."""

    method: str
    evaluations: float | None
    """gradient evaluations per step (first same as last merged; a force gradient counted
    at ``gradient_cost``; None for an implicit method, whose count depends on h)"""
    symmetric: bool
    stability_h: float | None  # end of |tr M| <= 2 from 0 for the fastest mode
    structure_h: float | None  # end of the structure-preserving interval from 0
    resonance_h: tuple[float, ...]  # M = +-I points below stability_h (excluded steps)
    h_target: float | None  # largest h whose acceptance reaches the target for every L
    steps: int | None  # L at h_target (None: trajectory length not given)
    acceptance: float | None  # at h_target, for the trajectory given (>= the target)
    expected_error: float | None  # E[Delta] at h_target
    gradients_per_proposal: float | None
    gradients_per_accepted: float | None
    gradients_per_time: float | None  # per accepted unit of simulated time
    rank: int | None = None
    at_step: Mapping[str, Any] | None = None
    stalls: tuple[Mapping[str, Any], ...] = ()
    notes: tuple[str, ...] = ()
    curve: tuple[tuple[float, float, float], ...] = ()
    """(h, predicted acceptance, its bound over every L) up to the limit searched, if asked"""


@compared
@dataclass(frozen=True, eq=False)
class HmcReport:
    """Methods ranked by ``ranked_by`` at the largest step reaching ``target`` acceptance:
    gradient evaluations per accepted proposal at the L run when the trajectory is given,
    else per accepted unit of simulated time (:data:`stepsafe.core.hmc.RANKINGS`)."""

    rows: tuple[HmcRow, ...]
    target: float
    steps: int | None
    length: float | None
    jitter: float
    criterion: str
    modes: int
    beta_range: tuple[float, float]
    time_unit: str | None = None
    approximate: bool = False
    """True: some row's acceptance at h at target is approximate (its notes say why)"""
    allow_unstable_jitter: bool = False
    """False: the step at target keeps ``h (1 + jitter)`` within the criterion's limit"""
    target_for_every_length: bool = True
    """True: the step at target reaches the target for every trajectory length (the bound
    over L); False: for the L (or T) given"""
    ranked_by: str = "gradients_per_time"
    """the row key methods are ranked by (:data:`stepsafe.core.hmc.RANKINGS`)"""

    COST_UNIT: ClassVar[str] = "gradient evaluations"
    """what the gradient figures count"""
    ROUNDING_GAPS: ClassVar[str] = ROUNDING_GAP_RULE
    """how M = +-I points that float64 rounds into gaps of the stable steps are counted"""
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "target_accept": "target", "cost_unit": "COST_UNIT",
        "rounding_gaps": "ROUNDING_GAPS", "methods": "rows"})

    @property
    def beta_min(self) -> float:
        """The slowest mode's angular frequency 1/sigma, rad per time unit."""
        return self.beta_range[0]

    @property
    def beta_max(self) -> float:
        """The fastest mode's angular frequency 1/sigma, rad per time unit."""
        return self.beta_range[1]

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe hmc ... --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"target_accept": self.target, "steps": self.steps,
                          "length": self.length,
                          "target_for_every_length": self.target_for_every_length,
                          "jitter": self.jitter,
                          "allow_unstable_jitter": self.allow_unstable_jitter,
                          "criterion": self.criterion, "modes": self.modes,
                          "beta_min": self.beta_min, "beta_max": self.beta_max,
                          "time_unit": self.time_unit, "approximate": self.approximate,
                          "cost_unit": self.COST_UNIT, "ranked_by": self.ranked_by,
                          "rounding_gaps": self.ROUNDING_GAPS,
                          "methods": [copy.deepcopy(_row_dict(r)) for r in self.rows]})


def _row_dict(row: HmcRow) -> dict[str, Any]:
    out = {f.name: getattr(row, f.name) for f in fields(row)}
    at_step = None if row.at_step is None else dict(row.at_step)
    if at_step is not None and "largest_errors" in at_step:
        at_step["largest_errors"] = [dict(e) for e in at_step["largest_errors"]]
    out["at_step"] = None if at_step is None else json_ready(at_step)
    out["stalls"] = [dict(s) for s in row.stalls]
    out["resonance_h"] = list(row.resonance_h)
    out["notes"] = list(row.notes)
    out["curve"] = [list(point) for point in row.curve]
    return out


@compared
@dataclass(frozen=True, eq=False)
class DesignReport:
    """A 2- or 3-stage splitting designed for a Gaussian target at step ``step``, its method
    file (``method_file``, YAML that every command accepts) and the figures that justify it:
    for it and each of :data:`DESIGN_REFERENCES`, at the same gradient evaluations per unit
    of simulated time (each method at step ``step * evaluations / stages``), the error bound
    ``sum_k rho(beta_k h)`` over every trajectory length and the acceptance it guarantees,
    both averaged over the jitter interval (``error_bound`` None: a mode is unstable there),
    and ``resonance_h``, the steps up to the jitter interval's top where the fastest mode
    meets an M = +-I resonance, which does not end the stable steps
    (:data:`~stepsafe.core.regions.ROUNDING_GAP_RULE`, as ``hmc`` counts it)."""

    name: str
    stages: int
    params: Mapping[str, float]
    step: float
    method_file: str
    comparison: tuple[Mapping[str, Any], ...]
    modes: int
    binned: bool = False
    time_unit: str | None = None
    #: what the design minimises (:data:`stepsafe.core.design.OBJECTIVES`)
    objective: str = "error-bound"
    #: the trajectory of the comparison: L, or T with L = floor(T / h); neither: every L
    steps: int | None = None
    length: float | None = None
    jitter: float = 0.0
    #: the AIA-style minimax member's parameters (objective ``acceptance``; None: none is
    #: stable up to the top of the step distribution)
    aia_params: Mapping[str, float] | None = None

    ROUNDING_GAPS: ClassVar[str] = ROUNDING_GAP_RULE
    """how M = +-I points that float64 rounds into gaps of the stable steps are counted"""
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "rounding_gaps": "ROUNDING_GAPS"})

    @property
    def trajectory(self) -> str | None:
        """The comparison's trajectory as text: ``L = n``, ``T = t``, or None (every L)."""
        return (f"L = {self.steps}" if self.steps is not None else
                f"T = {self.length:g}" if self.length is not None else None)

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe design ... --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"name": self.name, "stages": self.stages, "params": dict(self.params),
                "step": self.step, "modes": self.modes, "binned": self.binned,
                "time_unit": self.time_unit, "objective": self.objective,
                "steps": self.steps, "length": self.length, "jitter": self.jitter,
                "trajectory": self.trajectory,
                "aia_params": None if self.aia_params is None else dict(self.aia_params),
                "method_file": self.method_file,
                "rounding_gaps": self.ROUNDING_GAPS,
                "comparison": [{**c, "resonance_h": list(c["resonance_h"])}
                               for c in self.comparison]})
