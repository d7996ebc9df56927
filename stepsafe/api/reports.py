"""The results of the public API: frozen objects whose ``to_dict()`` is exactly the
``--json`` output of the matching command (the command line prints ``to_dict()``).

This module holds those of the linear analysis (``region``, ``advise``, ``check``,
``error``, ``compare``) and the helpers every report uses; the other user groups' reports
are in :mod:`.hmc_reports`, :mod:`.md_reports` and :mod:`.measure_reports`, so that a
command loads only its own."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from stepsafe.api.inputs import REGION_MODELS, Integrator
from stepsafe.comparison import compared
from stepsafe.core.records import (
    json_ready,
    method_data,
    nonlinear_data,
    region_data,
    unversioned,
    versioned,
)

# --------------------------------------------------------------------------- region


@compared
@dataclass(frozen=True, eq=False)
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
        """z*, the end of the preserved interval from 0 (None: none below zmax).

        Parameters
        ----------
        model : str
            ``"oscillator"`` or another model of the report's ``regions``.

        Returns
        -------
        float or None
            z* of ``model``.
        """
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
        """What ``stepsafe region METHOD --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
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


@compared
@dataclass(frozen=True, eq=False)
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
        """What ``stepsafe advise ... --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        out = _record_of(self)
        if self.verification is not None:
            out["verify"] = _plain(self.verification)
        return versioned(out)


# --------------------------------------------------------------------------- check


@compared
@dataclass(frozen=True, eq=False)
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
        """This check's entry of ``checks`` in ``stepsafe check ... --json``.

        Returns
        -------
        dict
            The entry (no ``schema_version``: the enclosing record has it).
        """
        out = _record_of(self)
        if self.verification is not None:
            out["verify"] = _plain(self.verification)
        return out

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe check ... --json`` prints for this input:
        ``{"safe": safe, "checks": [entry]}``.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"safe": self.safe, "checks": [self.entry()]})


@compared
@dataclass(frozen=True, eq=False)
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
        """Its entry of ``checks`` in ``stepsafe check ... --json``: ``safe`` is null.

        Returns
        -------
        dict
            The entry: ``where``, ``error`` and ``safe`` (null).
        """
        return {"scene": self.scene, "safe": self.safe, "error": self.message,
                "where": self.where}


@compared
@dataclass(frozen=True, eq=False)
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
        ``{"safe": safe, "checks": [one entry per file]}``.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"safe": self.safe,
                "checks": [unversioned(c.to_dict()) if not isinstance(c, (CheckReport, CheckError))
                           else c.entry() for c in self.checks]})


# --------------------------------------------------------------------------- errors


@compared
@dataclass(frozen=True, eq=False)
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
        """What ``stepsafe error METHOD --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({"method": self.method, "model": self.model,
                          "phase_error": self.phase_definition,
                          "rows": [row.to_dict() for row in self.rows]})


@compared
@dataclass(frozen=True, eq=False)
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


@compared
@dataclass(frozen=True, eq=False)
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


@compared
@dataclass(frozen=True, eq=False)
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
        """What ``stepsafe compare ... --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
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
