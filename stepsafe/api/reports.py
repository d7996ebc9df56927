"""The results of the public API: frozen objects whose ``to_dict()`` is exactly the
``--json`` output of the matching command (the command line prints ``to_dict()``)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from stepsafe.api.inputs import REGION_MODELS, Integrator
from stepsafe.core.records import unversioned, versioned
from stepsafe.core.regions import ROUNDING_GAP_RULE

# --------------------------------------------------------------------------- region


@dataclass(frozen=True)
class RegionReport:
    """Every interval of z = beta*h where the method keeps each model's structure.

    ``regions[model]`` is a :class:`stepsafe.core.regions.Region` (intervals, islands,
    resonances, poles); ``not_analysed[model]`` says why a model has no form for this
    method. ``verification`` is the ``--verify`` verdict when asked for.
    """

    integrator: Integrator
    regions: Mapping[str, Any]
    not_analysed: Mapping[str, str] = field(default_factory=dict)
    verification: Mapping[str, Any] | None = None
    #: oscillator: the nonlinear resonances n theta = 2 pi m in the interval from 0
    nonlinear: tuple[Any, ...] = ()
    #: ``structure`` or ``stability`` (see :func:`region`)
    criterion: str = "structure"
    #: under ``stability``: each model's first boundary under ``structure``
    structure_boundaries: Mapping[str, float | None] = field(default_factory=dict)

    def first_boundary(self, model: str = "oscillator") -> float | None:
        """z*, the end of the preserved interval from 0 (None: none below zmax)."""
        return self.regions[model].first_boundary

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe region METHOD --json`` prints."""
        from stepsafe.core.records import method_data, region_data

        head = method_data(self.integrator.tableau, self.integrator.entry)
        models = {m: region_data(self.regions[m]) if m in self.regions
                  else {"not_analysed": self.not_analysed[m]}
                  for m in (*self.regions, *self.not_analysed)}
        out = {key: head[key] for key in ("method", "title", "kind", "stages", "order",
                                          "symplectic")}
        out["models"] = {m: models[m] for m in _ordered(models)}
        out["criterion"] = self.criterion
        for m, z_star in self.structure_boundaries.items():
            out["models"][m]["structure_first_boundary"] = z_star
        if "oscillator" in self.regions and self.regions["oscillator"].symplectic:
            from stepsafe.core.records import nonlinear_data

            out["models"]["oscillator"]["nonlinear_resonances"] = nonlinear_data(self.nonlinear)
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return versioned(out)


def _ordered(models: Mapping[str, Any]) -> list[str]:
    rank = {m: i for i, m in enumerate(REGION_MODELS)}
    return sorted(models, key=lambda m: rank.get(m, len(rank)))


# --------------------------------------------------------------------------- advise


@dataclass(frozen=True)
class AdviceReport:
    """Safe steps: ``h_max`` ends the safe interval from 0 (``h_max_limited_by``:
    ``boundary``, ``resonance n:m`` when the nonlinear resonance n theta = 2 pi m of the
    ``resonance_order`` asked for ends it, ``horizon`` when no boundary was found below
    how far the analysis looked, ``none`` when no step is safe); ``safe_h`` lists every
    safe interval of h (islands included, ``None`` for no upper end). ``advice`` is the
    core result (with the regions used) for decoupled modes. ``undecided_h``: intervals of
    h that float64 could not decide in the coupled analysis of a nearly semidefinite
    system too large for the high-precision criterion (neither certified nor certainly
    unsafe)."""

    method: str
    h_max: float | None
    h_max_limited_by: str
    safe_h: tuple[tuple[float, float | None], ...]
    horizon: float | None
    record: Mapping[str, Any] = field(repr=False)
    advice: Any = field(repr=False, default=None)
    verification: Mapping[str, Any] | None = None
    undecided_h: tuple[tuple[float, float], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe advise ... --json`` prints."""
        out = copy.deepcopy(dict(self.record))
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return versioned(out)


# --------------------------------------------------------------------------- check


@dataclass(frozen=True)
class CheckReport:
    """Whether step ``h`` keeps every mode's structure (``safe``), the failing modes with
    their reasons, and the safe steps for all modes (``h_max``, ``safe_h``)."""

    method: str
    h: float
    safe: bool
    h_max: float | None
    failures: tuple[Mapping[str, Any], ...]
    scene: str | None
    record: Mapping[str, Any] = field(repr=False)
    result: Any = field(repr=False, default=None)
    verification: Mapping[str, Any] | None = None

    def entry(self) -> dict[str, Any]:
        """This check's entry of ``checks`` in ``stepsafe check ... --json``."""
        out = copy.deepcopy(dict(self.record))
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return out

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe check ... --json`` prints for this input:
        ``{"safe": safe, "checks": [entry]}``."""
        return versioned({"safe": self.safe, "checks": [self.entry()]})


@dataclass(frozen=True)
class CheckError:
    """A scene file that could not be checked (bad input: exit code 2): its file, the
    message and where (the file and key) the error lies."""

    scene: str | None
    message: str
    where: str | None = None

    def entry(self) -> dict[str, Any]:
        """Its entry of ``checks`` in ``stepsafe check ... --json``: ``safe`` is null."""
        return {"scene": self.scene, "safe": None, "error": self.message, "where": self.where}


@dataclass(frozen=True)
class SceneChecks:
    """The checks of several scene files, in their order: each a :class:`CheckReport`, an
    impulse method's :class:`~stepsafe.respa_advice.ImpulseModesReport`, or a
    :class:`CheckError` for a file that could not be checked."""

    checks: tuple[Any, ...]

    @property
    def safe(self) -> bool:
        """Every step checked is safe (a file that could not be checked is not)."""
        return all(not isinstance(c, CheckError) and bool(c.safe) for c in self.checks)

    @property
    def exit_code(self) -> int:
        """The command's exit code (the worst of the files'): 2 when a file could not be
        checked, else 1 when a step is unsafe, else 0 (a failed ``verify`` is 3, decided
        by the command)."""
        if any(isinstance(c, CheckError) for c in self.checks):
            return 2
        return 0 if self.safe else 1

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe check A.yaml B.yaml ... --json`` prints:
        ``{"safe": safe, "checks": [one entry per file]}``."""
        return versioned({"safe": self.safe,
                "checks": [unversioned(c.to_dict()) if not isinstance(c, (CheckReport, CheckError))
                           else c.entry() for c in self.checks]})


# --------------------------------------------------------------------------- errors


@dataclass(frozen=True)
class ErrorTable:
    """Accuracy of one step at each z: ``phase`` (theta/z - 1 for a vibration, log(mu)/z - 1
    for a saddle or barrier) and ``energy`` (relative energy error bound, vibrations), NaN
    where the structure is lost; ``overflow`` where M(z) leaves float64. A processed method
    ``P^-1 K P`` also has ``kernel_energy``, the energy error bound of its kernel run alone
    (its phase error is the kernel's: the processor changes the invariant ellipse, not the
    rotation); None for other methods."""

    method: str
    model: str
    z: np.ndarray = field(repr=False)
    phase: np.ndarray = field(repr=False)
    energy: np.ndarray = field(repr=False)
    overflow: np.ndarray = field(repr=False)
    kernel_energy: np.ndarray | None = field(repr=False, default=None)

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe error METHOD --json`` prints."""
        oscillator = self.model == "oscillator"
        rows = [{"z": float(zz), "phase_error": None if over else _finite(p),
                 "energy_error": _finite(en) if oscillator and not over
                 else None, "overflow": bool(over)}
                for zz, p, en, over in zip(self.z, self.phase, self.energy, self.overflow)]
        if self.kernel_energy is not None and oscillator:
            for row, en, over in zip(rows, self.kernel_energy, self.overflow):
                row["kernel_energy_error"] = None if over else _finite(en)
        return versioned({"method": self.method, "model": self.model,
                "phase_error": "theta/z - 1" if self.model == "oscillator"
                else "log(mu)/z - 1", "rows": rows})


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


@dataclass(frozen=True)
class CompareRow:
    """One method in a :class:`CompareReport`: ``first_boundary`` z* on the oscillator,
    ``h_max`` the safe limit, ``h_tol`` the largest step meeting the tolerances (0: none
    does), ``h`` the step to use (``bound_by`` says which limit), ``cost`` force
    evaluations per unit of simulated time at ``h``, ``rank`` (cheapest first; None when
    there is no cost). A processed method also has ``processor_evaluations``, the forces
    of its processor P, spent once before the first step, and as many for P^-1 at each
    output (not in ``cost``; JSON: ``{"start": n, "per_output": n}``)."""

    method: str
    implicit: bool
    first_boundary: float | None
    h_max: float | None
    h_tol: float | None
    tolerance_status: tuple[str, ...]
    h: float | None
    bound_by: str
    evaluations: int | None
    solver_iterations: int | None
    cost: float | None
    rank: int | None
    processor_evaluations: int | None = None
    #: implicit methods: the stage solver counted (``fixed-point`` or ``newton``; with
    #: ``solver="best"`` the cheaper at its step) and Newton's Jacobians per step (each
    #: costing :attr:`CompareReport.jacobian_cost` force evaluations in ``cost``)
    solver: str | None = None
    jacobians: int | None = None


@dataclass(frozen=True)
class CompareReport:
    """Methods ranked by cost per unit of simulated time for the same frequencies."""

    rows: tuple[CompareRow, ...]
    modes: Mapping[str, int]
    tolerances: Mapping[str, float]
    margin: float
    time_unit: str | None = None
    solver: str = "best"
    criterion: str = "structure"
    jacobian_cost: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe compare ... --json`` prints."""
        from dataclasses import asdict

        return versioned({"modes": dict(self.modes), "tolerances": dict(self.tolerances),
                "margin": self.margin, "time_unit": self.time_unit, "solver": self.solver,
                "jacobian_cost": self.jacobian_cost, "criterion": self.criterion,
                "cost_unit": "force evaluations per unit of simulated time",
                "methods": [_compare_row_dict(asdict(r)) for r in self.rows]})


def _compare_row_dict(row: dict[str, Any]) -> dict[str, Any]:
    row["tolerance_status"] = list(row["tolerance_status"])
    if row["processor_evaluations"] is None:
        del row["processor_evaluations"]  # only processed methods have one
    else:
        n = row["processor_evaluations"]
        row["processor_evaluations"] = {"start": n, "per_output": n}
    return row


@dataclass(frozen=True)
class HmcRow:
    """One method's HMC figures (steps in the time unit of 1/beta; None where a figure
    does not exist, e.g. no step reaches the target)."""

    method: str
    #: gradient evaluations per step (first same as last merged; a force gradient counted
    #: at ``gradient_cost``; None for an implicit method, whose count depends on h)
    evaluations: float | None
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
    #: (h, predicted acceptance, its bound over every L) up to the limit searched, if asked
    curve: tuple[tuple[float, float, float], ...] = ()


@dataclass(frozen=True)
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
    #: False: the step at target keeps ``h (1 + jitter)`` within the criterion's limit
    allow_unstable_jitter: bool = False
    #: True: the step at target reaches the target for every trajectory length (the bound
    #: over L); False: for the L (or T) given
    target_for_every_length: bool = True
    #: the row key methods are ranked by (:data:`stepsafe.core.hmc.RANKINGS`)
    ranked_by: str = "gradients_per_time"

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe hmc ... --json`` prints."""
        return versioned({"target_accept": self.target, "steps": self.steps,
                          "length": self.length,
                          "target_for_every_length": self.target_for_every_length,
                          "jitter": self.jitter,
                          "allow_unstable_jitter": self.allow_unstable_jitter,
                          "criterion": self.criterion, "modes": self.modes,
                          "beta_min": self.beta_range[0], "beta_max": self.beta_range[1],
                          "time_unit": self.time_unit, "approximate": self.approximate,
                          "cost_unit": "gradient evaluations",
                          "ranked_by": self.ranked_by,
                          "rounding_gaps": ROUNDING_GAP_RULE,
                          "methods": [copy.deepcopy(_row_dict(r)) for r in self.rows]})


def _row_dict(row: HmcRow) -> dict[str, Any]:
    from stepsafe.core.records import json_ready

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


@dataclass(frozen=True)
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

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe design ... --json`` prints."""
        return versioned({"name": self.name, "stages": self.stages, "params": dict(self.params),
                "step": self.step, "modes": self.modes, "binned": self.binned,
                "time_unit": self.time_unit, "objective": self.objective,
                "steps": self.steps, "length": self.length, "jitter": self.jitter,
                "trajectory": (f"L = {self.steps}" if self.steps is not None else
                               f"T = {self.length:g}" if self.length is not None else None),
                "aia_params": None if self.aia_params is None else dict(self.aia_params),
                "method_file": self.method_file,
                "rounding_gaps": ROUNDING_GAP_RULE,
                "comparison": [{**c, "resonance_h": list(c["resonance_h"])}
                               for c in self.comparison]})


@dataclass(frozen=True)
class ImpulseReport:
    """Safe outer steps H of an impulse (r-RESPA) integrator for one fast and one slow
    frequency: ``h_max`` ends the safe interval from 0, ``safe_h`` lists every safe interval
    up to the horizon, ``bands`` the unstable intervals of H between them; with a ``step``,
    ``safe`` is its verdict. ``method`` is the equivalent splitting (a
    :class:`stepsafe.methods.tableaux.Splitting` on the oscillator of frequency ``beta``)."""

    name: str
    substeps: int
    fast: float
    slow: float
    beta: float
    criterion: str
    h_max: float | None
    safe_h: tuple[tuple[float, float | None], ...]
    bands: tuple[Mapping[str, Any], ...]
    horizon: float | None
    step: float | None = None
    safe: bool | None = None
    reason: str | None = None
    time_unit: str | None = None
    method: Any = None
    #: n:m nonlinear resonances of the outer step (n theta = 2 pi m) below h_max, as
    #: ``{"resonance": "3:1", "h": ...}``: Ma, Izaguirre & Skeel's limit near a third of the
    #: fast period is the 3:1
    nonlinear: tuple[Mapping[str, Any], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe respa ... --json`` prints."""
        return versioned({"method": self.name, "substeps": self.substeps, "fast": self.fast,
                "slow": self.slow, "beta": self.beta, "criterion": self.criterion,
                "h_max": self.h_max, "safe_h": [list(iv) for iv in self.safe_h],
                "bands": [copy.deepcopy(dict(b)) for b in self.bands],
                "horizon": self.horizon, "step": self.step, "safe": self.safe,
                "reason": self.reason, "time_unit": self.time_unit,
                "nonlinear_resonances": [dict(r) for r in self.nonlinear]})


@dataclass(frozen=True)
class ImpulseModesReport:
    """Safe outer steps H of an impulse method for several modes, each with its own fast
    and slow frequency (``modes[i]`` is mode i's :class:`ImpulseReport`): ``safe_h`` is
    the intersection of their safe sets up to the nearest ``horizon``, ``h_max`` the end
    of its interval from 0 and ``limiting`` the mode that ends it; with a ``step``,
    ``safe`` and the ``failures`` (mode index, label, reason)."""

    name: str
    substeps: int
    criterion: str
    modes: tuple[ImpulseReport, ...]
    labels: tuple[str | None, ...]
    h_max: float | None
    safe_h: tuple[tuple[float, float | None], ...]
    horizon: float | None
    limiting: int | None
    step: float | None = None
    safe: bool | None = None
    failures: tuple[Mapping[str, Any], ...] = ()
    time_unit: str | None = None
    scene: str | None = None
    #: how the modes were analysed: each on its own, or (``coupled``) the 2n x 2n step of a
    #: split stiffness whose parts do not commute (then ``modes`` is empty)
    analysis: str = "decoupled: each mode's outer step on its own oscillator"

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe advise`` / ``check`` print with ``--json`` for an impulse method."""
        modes = []
        for label, mode in zip(self.labels, self.modes):
            row = unversioned(mode.to_dict())
            for key in ("method", "substeps", "criterion", "time_unit", "step"):
                row.pop(key)
            modes.append({"label": label, **row})
        return versioned({"method": self.name, "kind": "impulse", "substeps": self.substeps,
                "criterion": self.criterion, "time_unit": self.time_unit,
                "scene": self.scene, "h_max": self.h_max,
                "safe_h": [list(iv) for iv in self.safe_h], "horizon": self.horizon,
                "limiting_mode": self.limiting, "step": self.step, "safe": self.safe,
                "failures": [dict(f) for f in self.failures], "analysis": self.analysis,
                "modes": modes})


@dataclass(frozen=True)
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


@dataclass(frozen=True)
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
    #: Hessian evaluations (and stage-matrix factorisations) per unit time: simplified
    #: Newton's method takes one per implicit step, on top of the force evaluations
    jacobians_per_time: float | None = None
    #: force-gradient terms (Hessian-vector products) per unit time, on top of the forces
    gradients_per_time: float | None = None
    #: the reference's own error at ``time``, relative as ``trajectory_error`` (None: the
    #: exact flow); a trajectory error below it is not a number: ``trajectory_error`` is
    #: then None and ``below_reference`` True (the error is less than this floor)
    reference_error: float | None = None
    below_reference: bool = False
    #: the energy error against time: the share of its variance the least-squares line
    #: through every step explains, and ``drift`` (at least one half) or ``bounded``
    energy_r2: float | None = None
    energy_behaviour: str | None = None
    #: the scene's declared invariants, measured like the energy
    invariants: tuple[InvariantRow, ...] = ()
    #: wall-clock seconds per unit of simulated time of the run (monitoring included)
    seconds_per_time: float | None = None

    @property
    def energy_ratio(self) -> float | None:
        return _ratio(self.energy_error, self.predicted_energy_error)

    @property
    def trajectory_ratio(self) -> float | None:
        """None once the predicted phase drift reaches half a turn (the prediction is then
        the largest error, 2, not the error)."""
        if self.predicted_trajectory_error is not None and \
                self.predicted_trajectory_error >= 2.0:
            return None
        return _ratio(self.trajectory_error, self.predicted_trajectory_error)

    def to_dict(self) -> dict[str, Any]:
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


@dataclass(frozen=True)
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
        """What ``stepsafe measure --json`` prints."""
        return versioned(copy.deepcopy({"method": self.method, "system": self.system,
                              "initial": list(self.initial), "energy": self.energy,
                              "beta": self.beta, "reference": self.reference,
                              "time_unit": self.time_unit,
                              "rows": [r.to_dict() for r in self.rows]}))


@dataclass(frozen=True)
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
        return {"h": self.h, "steps": self.steps, "time": self.time, "median": self.median,
                "q90": self.q90, "q99": self.q99, "max": self.max, "unstable": self.unstable}


@dataclass(frozen=True)
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

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe measure --ensemble N --json`` prints."""
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


@dataclass(frozen=True)
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
    #: the trajectory error at ``h`` is below the reference's own error: ``error`` is that
    #: floor, an upper bound
    below_reference: bool = False

    def to_dict(self) -> dict[str, Any]:
        return versioned({"quantity": self.quantity, "tol": self.tol, "h": self.h,
                          "error": self.error, "below_reference": self.below_reference,
                          "predicted_h": self.predicted, "h_safe": self.h_safe,
                          "limited_by": self.limited_by,
                          "runs": unversioned(self.runs.to_dict())})
