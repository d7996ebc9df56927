"""The results of the public API: frozen objects whose ``to_dict()`` is exactly the
``--json`` output of the matching command (the command line prints ``to_dict()``)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from stepsafe.api.inputs import REGION_MODELS, Integrator
from stepsafe.core.records import (
    json_ready,
    method_data,
    nonlinear_data,
    region_data,
    unversioned,
    versioned,
)
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
    nonlinear: tuple[Any, ...] = ()
    """oscillator: the nonlinear resonances n theta = 2 pi m in the interval from 0"""
    criterion: str = "structure"
    """``structure`` or ``stability`` (see :func:`region`)"""
    structure_boundaries: Mapping[str, float | None] = field(default_factory=dict)
    """under ``stability``: each model's first boundary under ``structure``"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"verify": "verification"})

    def first_boundary(self, model: str = "oscillator") -> float | None:
        """z*, the end of the preserved interval from 0 (None: none below zmax)."""
        return self.regions[model].first_boundary

    @property
    def method(self) -> str:
        """The method's name."""
        return str(self._head["method"])

    @property
    def title(self) -> str:
        """The method's title (with its reference)."""
        return str(self._head["title"])

    @property
    def kind(self) -> str:
        """The method's kind (``rk``, ``prk``, ``splitting``, ``composition``, ...)."""
        return str(self._head["kind"])

    @property
    def stages(self) -> int | None:
        """The method's stages (None: not a fixed number)."""
        return self._head["stages"]

    @property
    def order(self) -> int | None:
        """The method's order of accuracy (None: not known)."""
        return self._head["order"]

    @property
    def symplectic(self) -> bool:
        """Whether the method is symplectic."""
        return bool(self._head["symplectic"])

    @property
    def _head(self) -> dict[str, Any]:

        return method_data(self.integrator.tableau, self.integrator.entry)

    @property
    def models(self) -> dict[str, dict[str, Any]]:
        """Per model, its region as JSON (:func:`stepsafe.core.records.region_data`:
        intervals, islands, resonances, poles of z = beta h, zmax), with its
        ``structure_first_boundary`` under ``stability`` and the oscillator's
        ``nonlinear_resonances``; a model without a form for this method:
        ``{"not_analysed": why}``."""

        models: dict[str, dict[str, Any]] = {
            m: region_data(self.regions[m]) if m in self.regions
            else {"not_analysed": self.not_analysed[m]}
            for m in (*self.regions, *self.not_analysed)}
        out = {m: models[m] for m in _ordered(models)}
        for m, z_star in self.structure_boundaries.items():
            out[m]["structure_first_boundary"] = z_star
        if "oscillator" in self.regions and self.regions["oscillator"].symplectic:
            out["oscillator"]["nonlinear_resonances"] = nonlinear_data(self.nonlinear)
        return out

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe region METHOD --json`` prints."""
        head = self._head
        out = {key: head[key] for key in ("method", "title", "kind", "stages", "order",
                                          "symplectic")}
        out["models"] = self.models
        out["criterion"] = self.criterion
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return versioned(out)


def _ordered(models: Mapping[str, Any]) -> list[str]:
    rank = {m: i for i, m in enumerate(REGION_MODELS)}
    return sorted(models, key=lambda m: rank.get(m, len(rank)))


# --------------------------------------------------------------------------- advise


def _frozen(value: Any) -> Any:
    """A JSON value made immutable: objects as read-only mappings, arrays as tuples."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: _frozen(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(v) for v in value)
    return value


def _plain(value: Any) -> Any:
    """A field's value as JSON: mappings as dicts, tuples as lists, a nested report as its
    record (without ``schema_version``)."""
    if hasattr(value, "to_dict"):
        return unversioned(value.to_dict())
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def json_attribute(report_type: type, key: str) -> str:
    """The attribute of ``report_type`` that holds its JSON record's ``key`` (the key
    itself unless the type's ``JSON_NAMES`` renames it)."""
    return getattr(report_type, "JSON_NAMES", {}).get(key, key)


def record_fields(report_type: type, data: Mapping[str, Any], **objects: Any) -> dict[str, Any]:
    """The constructor keywords of a report whose JSON record is ``data``: each key's value
    (frozen) under its field, ``keys`` the keys in their order, and ``objects`` (results
    that are not in the JSON). A key without a field is an error of the code."""
    known = {f.name for f in fields(report_type)}
    values = {}
    for key, value in json_ready(dict(data)).items():
        name = json_attribute(report_type, key)
        if name not in known or name in objects or name == "keys":
            raise TypeError(f"{report_type.__name__} has no field for the JSON key {key!r}")
        values[name] = _frozen(value)
    return {**values, **objects, "keys": tuple(data)}


def _record_of(report: Any) -> dict[str, Any]:
    """The JSON record of a keyed report: each of its ``keys`` from its field."""
    return {key: _plain(getattr(report, json_attribute(type(report), key)))
            for key in report.keys}


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
    unsafe).

    Each key of ``stepsafe advise --json`` is a field (``verify`` is
    :attr:`verification`); ``keys`` lists those this report carries, in their order
    (the optional ones appear only where they apply). Steps are in :attr:`time_unit`.
    """

    method: str
    """the method's name"""
    h_max: float | None
    """the end of the safe interval of h from 0 (None: no end below the horizon)"""
    h_max_limited_by: str
    """what ends it: ``boundary``, ``resonance n:m``, ``horizon``, ``none`` (with a
    temperature, the ``limited_by`` of :attr:`thermal`)"""
    safe_h: tuple[tuple[float, float | None], ...]
    """every safe open interval of h, ``(lo, hi)``; hi None: no end below the horizon"""
    horizon: float | None
    """how far in h the analysis looked (None: no limit)"""
    advice: Any = field(repr=False, default=None)
    """the core result with the regions used (decoupled modes; not in the JSON)"""
    verification: Mapping[str, Any] | None = None
    """the ``--verify`` verdict (JSON ``verify``): mpmath's recomputation of the points"""
    undecided_h: tuple[tuple[float, float], ...] = ()
    """intervals of h float64 could not decide in a coupled analysis (systems)"""
    margin: float = 1.0
    """F in (0, 1]: every frequency taken up to 1/F times larger"""
    criterion: str = "structure"
    """``structure`` (type and orientation kept) or ``stability`` (type only)"""
    limiting: Mapping[str, Any] | None = field(repr=False, default=None)
    """the mode that ends h_max: its model, beta (rad per time unit), h_limit, the
    boundary's z and kind (and ``label``); None unless a boundary ends it"""
    models: Mapping[str, Mapping[str, Any]] = field(repr=False, default_factory=dict)
    """per model (``oscillator``, ``saddle``, ``inverted``, ...): its fastest beta, how many
    modes, its first boundary z and the h it allows"""
    time_unit: str | None = None
    """the unit of every step (None: the time unit of 1/beta)"""
    nonlinear_resonances: tuple[Mapping[str, Any], ...] = field(repr=False, default=())
    """the fastest vibration's nonlinear resonances n theta = 2 pi m (orders 3 to 6 and up
    to ``resonance_order``): resonance ``n:m``, z and h"""
    fixed_point_limit: float | None = None
    """implicit methods: the h where fixed-point iteration of the stages stops converging
    (in the time unit; None: explicit, or no limit)"""
    other_criterion: Mapping[str, Any] | None = field(repr=False, default=None)
    """the safe steps under the criterion not asked for, where its h_max differs"""
    stochastic: Mapping[str, Any] | None = field(repr=False, default=None)
    """a Langevin splitting: its letters, friction, kT, what its stability means and (at
    a step) how it samples the fastest vibration"""
    system: Mapping[str, Any] | None = field(repr=False, default=None)
    """a system: its analysis, its modes or equilibria (``items``: type, beta, h_limit),
    notes and the equilibrium search"""
    thermal: Mapping[str, Any] | None = field(repr=False, default=None)
    """at temperature: the request (kT, run) and each minimum's measured frequencies,
    resonance-band scans and drift (:mod:`stepsafe.api.thermal`)"""
    zero_kelvin: Mapping[str, Any] | None = field(repr=False, default=None)
    """at temperature: the 0 K answer (``h_max``, ``h_max_limited_by``, ``safe_h``)"""
    accuracy: tuple[Mapping[str, Any], ...] = field(repr=False, default=())
    """with tolerances: per mode, the tolerance bound's z and h (time unit) and what
    limits it"""
    h: float | None = None
    """with tolerances: the step to use, in the time unit (None: none)"""
    bound_by: str | None = None
    """with tolerances: which limit sets ``h`` (``safety``, ``phase``, ``energy``,
    ``solver``)"""
    evaluations: float | None = None
    """with tolerances: force evaluations per step (a force gradient counted at its cost)"""
    solver_iterations: int | None = None
    """with tolerances: fixed-point iterations of the stages per step (implicit methods)"""
    cost_per_unit_time: float | None = None
    """with tolerances: force evaluations per unit of simulated time at ``h``"""
    processor_evaluations: Mapping[str, int] | None = None
    """with tolerances, a processed method: forces of its processor, at the start and at
    each output (``{"start": n, "per_output": n}``)"""
    keys: tuple[str, ...] = field(repr=False, default=())
    """the JSON keys this report carries, in their order (``verify`` aside)"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"verify": "verification"})

    @property
    def record(self) -> Mapping[str, Any]:
        """The JSON record without ``schema_version`` and ``verify`` (read-only)."""
        return MappingProxyType(_record_of(self))

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe advise ... --json`` prints."""
        out = _record_of(self)
        if self.verification is not None:
            out["verify"] = _plain(self.verification)
        return versioned(out)


# --------------------------------------------------------------------------- check


@dataclass(frozen=True)
class CheckReport:
    """Whether step ``h`` keeps every mode's structure (``safe``), the failing modes with
    their reasons, and the safe steps for all modes (``h_max``, ``safe_h``).

    Each key of this check's entry in ``stepsafe check --json`` is a field (``verify`` is
    :attr:`verification`); ``keys`` lists those it carries, in their order. Steps are in
    :attr:`time_unit`.
    """

    method: str
    """the method's name"""
    h: float
    """the step checked, in the time unit"""
    safe: bool
    """every mode keeps its structure at h (and every further condition asked for holds)"""
    h_max: float | None
    """the end of the safe interval of h from 0 (None: no end below the horizon)"""
    failures: tuple[Mapping[str, Any], ...]
    """the failing modes: model, beta (rad per time unit), z = beta h / margin, reason,
    ``largest_safe_h`` (and ``label``)"""
    scene: str | None
    """the scene file (None: the command line)"""
    result: Any = field(repr=False, default=None)
    """the core result (decoupled modes; not in the JSON)"""
    verification: Mapping[str, Any] | None = None
    """the ``--verify`` verdict (JSON ``verify``)"""
    margin: float = 1.0
    """F in (0, 1]: every frequency taken up to 1/F times larger"""
    in_primary_interval: bool = False
    """h lies in the safe interval from 0 (not in an island beyond it)"""
    modes: int = 0
    """how many modes (or degrees of freedom of a coupled system) were checked"""
    failing: int = 0
    """how many of them fail"""
    h_max_limited_by: str | None = None
    """what ends h_max (see :attr:`AdviceReport.h_max_limited_by`)"""
    safe_h: tuple[tuple[float, float | None], ...] = ()
    """every safe open interval of h, ``(lo, hi)``; hi None: no end below the horizon"""
    criterion: str = "structure"
    """``structure`` or ``stability``"""
    other_criterion: Mapping[str, Any] | None = field(repr=False, default=None)
    """the verdict under the criterion not asked for, where its h_max differs"""
    stochastic: Mapping[str, Any] | None = field(repr=False, default=None)
    """a Langevin splitting: what its verdict means and how it samples at h"""
    solver_failure: str | None = None
    """why fixed-point iteration of the stages fails at h (implicit methods)"""
    time_unit: str | None = None
    """the unit of every step (None: the time unit of 1/beta)"""
    system: Mapping[str, Any] | None = field(repr=False, default=None)
    """a system: its analysis, modes or equilibria and the equilibrium search"""
    engine_runs: Mapping[str, Any] | None = field(repr=False, default=None)
    """an MD engine's system checked with runs: the runs and their verdict"""
    engine_failure: str | None = None
    """why those runs fail the step"""
    search_failure: str | None = None
    """why the equilibrium search cannot vouch for completeness (when required)"""
    thermal: Mapping[str, Any] | None = field(repr=False, default=None)
    """at temperature: the request and each minimum's probes, reasons and verdict"""
    thermal_failure: str | None = None
    """why the step fails at temperature"""
    keys: tuple[str, ...] = field(repr=False, default=())
    """the JSON keys this check's entry carries, in their order (``verify`` aside)"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"verify": "verification"})

    @property
    def record(self) -> Mapping[str, Any]:
        """This check's entry without ``verify`` (read-only)."""
        return MappingProxyType(_record_of(self))

    def entry(self) -> dict[str, Any]:
        """This check's entry of ``checks`` in ``stepsafe check ... --json``."""
        out = _record_of(self)
        if self.verification is not None:
            out["verify"] = _plain(self.verification)
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

    safe: ClassVar[None] = None
    """no verdict: the file could not be checked"""
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"error": "message"})

    def entry(self) -> dict[str, Any]:
        """Its entry of ``checks`` in ``stepsafe check ... --json``: ``safe`` is null."""
        return {"scene": self.scene, "safe": self.safe, "error": self.message,
                "where": self.where}


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

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "phase_error": "phase_definition"})

    @property
    def phase_definition(self) -> str:
        """What ``phase_error`` measures: ``theta/z - 1`` on the oscillator, ``log(mu)/z -
        1`` on a saddle or barrier."""
        return "theta/z - 1" if self.model == "oscillator" else "log(mu)/z - 1"

    @property
    def rows(self) -> tuple[ErrorRow, ...]:
        """One row per z, in order (see :class:`ErrorRow`)."""
        oscillator = self.model == "oscillator"
        kernel = self.kernel_energy is not None and oscillator
        kernel_energy = self.energy if self.kernel_energy is None or not kernel \
            else self.kernel_energy
        return tuple(
            ErrorRow(float(zz), None if over else _finite(p),
                     _finite(en) if oscillator and not over else None, bool(over),
                     None if over or not kernel else _finite(ken), kernel)
            for zz, p, en, over, ken in zip(self.z, self.phase, self.energy, self.overflow,
                                            kernel_energy))

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe error METHOD --json`` prints."""
        return versioned({"method": self.method, "model": self.model,
                          "phase_error": self.phase_definition,
                          "rows": [row.to_dict() for row in self.rows]})


@dataclass(frozen=True)
class ErrorRow:
    """The accuracy of one step at one z = beta h (dimensionless); None where the structure
    is lost or M(z) leaves float64."""

    z: float
    """z = beta h"""
    phase_error: float | None
    """theta/z - 1 (vibration) or log(mu)/z - 1 (saddle, barrier)"""
    energy_error: float | None
    """the relative energy error bound (vibrations only)"""
    overflow: bool
    """M(z) left float64 at this z"""
    kernel_energy_error: float | None = None
    """a processed method: the energy error bound of its kernel run alone"""
    processed: bool = field(repr=False, default=False)
    """whether the row carries ``kernel_energy_error`` (a processed method, oscillator)"""

    def to_dict(self) -> dict[str, Any]:
        """This row of ``stepsafe error --json``."""
        out: dict[str, Any] = {"z": self.z, "phase_error": self.phase_error,
                               "energy_error": self.energy_error, "overflow": self.overflow}
        if self.processed:
            out["kernel_energy_error"] = self.kernel_energy_error
        return out


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
    solver: str | None = None
    """implicit methods: the stage solver counted (``fixed-point`` or ``newton``; with
    ``solver="best"`` the cheaper at its step) and Newton's Jacobians per step (each
    costing :attr:`CompareReport.jacobian_cost` force evaluations in ``cost``)"""
    jacobians: int | None = None

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "processor_evaluations": "processor_cost"})

    @property
    def processor_cost(self) -> Mapping[str, int] | None:
        """``processor_evaluations`` as the JSON gives it: ``{"start": n, "per_output":
        n}`` (None: not a processed method)."""
        n = self.processor_evaluations
        return None if n is None else {"start": n, "per_output": n}


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
    measured: Mapping[str, Any] | None = field(repr=False, default=None)
    """``compare --measure SCENE``: each method's measured cost on the scene's system at
    the trajectory error the phase tolerance allows over the run (``scene``, ``time``,
    ``tolerance``), beside the predicted cost, both as ratios to the first method's
    (None: not measured)"""

    COST_UNIT: ClassVar[str] = "force evaluations per unit of simulated time"
    """what ``cost`` counts"""
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "methods": "rows", "cost_unit": "COST_UNIT"})

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe compare ... --json`` prints."""
        out = {"modes": dict(self.modes), "tolerances": dict(self.tolerances),
               "margin": self.margin, "time_unit": self.time_unit, "solver": self.solver,
               "jacobian_cost": self.jacobian_cost, "criterion": self.criterion,
               "cost_unit": self.COST_UNIT,
               "methods": [_compare_row_dict(r) for r in self.rows]}
        if self.measured is not None:
            out["measured"] = _plain(self.measured)
        return versioned(out)


def _compare_row_dict(row: CompareRow) -> dict[str, Any]:
    from dataclasses import asdict

    out = asdict(row)
    out["tolerance_status"] = list(row.tolerance_status)
    if row.processor_evaluations is None:
        del out["processor_evaluations"]  # only processed methods have one
    else:
        out["processor_evaluations"] = row.processor_cost
    return out


@dataclass(frozen=True)
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
        """What ``stepsafe hmc ... --json`` prints."""
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
        """What ``stepsafe design ... --json`` prints."""
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
    nonlinear: tuple[Mapping[str, Any], ...] = ()
    """n:m nonlinear resonances of the outer step (n theta = 2 pi m) below h_max, as
    ``{"resonance": "3:1", "h": ...}``: Ma, Izaguirre & Skeel's limit near a third of the
    fast period is the 3:1"""
    label: str | None = None
    """one mode of several (:class:`ImpulseModesReport`): its name in the scene (None:
    none; in the JSON of the modes only)"""
    ratio: float | None = None
    """``region METHOD --ratio R``: the frequency ratio omega/Omega (slow over fast) of a
    fast frequency 1, so that every step is Omega H (None: frequencies given)"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "method": "name", "nonlinear_resonances": "nonlinear"})

    @property
    def units(self) -> str | None:
        """With a :attr:`ratio`: what the steps are, ``Omega H (fast frequency 1)``."""
        return None if self.ratio is None else "Omega H (fast frequency 1)"

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe respa ... --json`` prints (``region METHOD --ratio R --json``:
        with ``ratio`` and ``units``)."""
        out = {"method": self.name, "substeps": self.substeps, "fast": self.fast,
               "slow": self.slow, "beta": self.beta, "criterion": self.criterion,
               "h_max": self.h_max, "safe_h": [list(iv) for iv in self.safe_h],
               "bands": [copy.deepcopy(dict(b)) for b in self.bands],
               "horizon": self.horizon, "step": self.step, "safe": self.safe,
               "reason": self.reason, "time_unit": self.time_unit,
               "nonlinear_resonances": [dict(r) for r in self.nonlinear]}
        if self.ratio is not None:
            out.update(ratio=self.ratio, units=self.units)
        return versioned(out)


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
    analysis: str = "decoupled: each mode's outer step on its own oscillator"
    """how the modes were analysed: each on its own, or (``coupled``) the 2n x 2n step of a
    split stiffness whose parts do not commute (then ``modes`` is empty)"""

    KIND: ClassVar[str] = "impulse"
    """the kind of method"""
    SHARED: ClassVar[tuple[str, ...]] = ("method", "substeps", "criterion", "time_unit",
                                         "step")
    """the keys of each mode's :class:`ImpulseReport` that its row in the JSON leaves out
    (they are the whole report's)"""
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "method": "name", "kind": "KIND", "limiting_mode": "limiting"})

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe advise`` / ``check`` print with ``--json`` for an impulse method."""
        modes = []
        for mode in self.modes:
            row = unversioned(mode.to_dict())
            for key in self.SHARED:
                row.pop(key)
            modes.append({"label": mode.label, **row})
        return versioned({"method": self.name, "kind": self.KIND, "substeps": self.substeps,
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

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"ensemble": "count"})

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
    below_reference: bool = False
    """the trajectory error at ``h`` is below the reference's own error: ``error`` is that
    floor, an upper bound"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({"predicted_h": "predicted"})

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe measure --tol-energy T --json`` (or ``--tol-trajectory``)
        prints."""
        return versioned({"quantity": self.quantity, "tol": self.tol, "h": self.h,
                          "error": self.error, "below_reference": self.below_reference,
                          "predicted_h": self.predicted, "h_safe": self.h_safe,
                          "limited_by": self.limited_by,
                          "runs": unversioned(self.runs.to_dict())})
