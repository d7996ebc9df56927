"""Regions, safe steps and accuracy of linear models: :func:`region`, :func:`advise`,
:func:`check`, :func:`check_scenes`, :func:`errors`, :func:`transfer_matrices` and
:func:`compare`, behind the commands of the same names.

>>> import stepsafe
>>> verlet = stepsafe.method("verlet")
>>> verlet.order, verlet.kind, verlet.evaluations
(2, 'splitting', 1)
>>> advice = stepsafe.advise(verlet, beta=[1.0, 4.0])
>>> round(advice.h_max, 12)   # Verlet keeps a centre a centre for beta*h < 2
0.5
>>> stepsafe.check(verlet, 0.6, beta=[4.0]).safe
False
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from stepsafe.api.inputs import (
    REGION_MODELS,
    ArrayLike,
    Integrator,
    Problem,
    UnitValues,
    as_flag,
    as_integrator,
    as_text,
    betas_by_model,
    compared_methods,
    converted_betas,
    frozen_record,
    method,
    problem_of,
    step_cost,
    step_in_unit,
    valid_order,
    valid_solver,
    valid_stage_solver,
    valid_tolerance,
    z_values,
)
from stepsafe.api.keywords import shared_keywords
from stepsafe.api.reports import (
    AdviceReport,
    CheckError,
    CheckReport,
    CompareReport,
    CompareRow,
    ErrorTable,
    RegionReport,
    SceneChecks,
    record_fields,
)
from stepsafe.api.temperature import request, where_in_scene
from stepsafe.arguments import public
from stepsafe.core.advice import Modes, check_step, validate_margin
from stepsafe.core.advice import advise as core_advise
from stepsafe.core.models import MAIN_MODELS
from stepsafe.core.records import (
    advice_data,
    check_data,
    compare_row,
    label_limits,
    nonlinear_data,
    tradeoff_data,
)
from stepsafe.core.regions import (
    CRITERIA,
    find_region,
    shared_regions,
    under_criterion,
    validate_criterion,
)
from stepsafe.core.transfer import has_form, transfer_matrix
from stepsafe.exceptions import StepsafeError, finite_real, positive_finite
from stepsafe.lazy import lazy_module
from stepsafe.systems.scene import Scene, load_scene
from stepsafe.units import implied_time_unit
from stepsafe.units import time_unit as known_time_unit

if TYPE_CHECKING:
    from stepsafe.api import md, thermal
    from stepsafe.core import accuracy as core_accuracy
    from stepsafe.core import langevin
    from stepsafe.core import resonances as core_resonances
    from stepsafe.core import solver as core_solver
    from stepsafe.core import tradeoff as core_tradeoff
    from stepsafe.reference import verify
    from stepsafe.systems import advice as systems_advice
else:  # what only some inputs reach: an impulse method, a temperature, --verify, a system:
    md = lazy_module("stepsafe.api.md")
    langevin = lazy_module("stepsafe.core.langevin")  # Langevin splittings only
    thermal = lazy_module("stepsafe.api.thermal")
    verify = lazy_module("stepsafe.reference.verify")
    systems_advice = lazy_module("stepsafe.systems.advice")
    # nonlinear resonances (advise, a resonance order), stage solvers (advise, implicit
    # methods), tolerances and errors
    core_resonances = lazy_module("stepsafe.core.resonances")
    core_solver = lazy_module("stepsafe.core.solver")
    core_tradeoff = lazy_module("stepsafe.core.tradeoff")
    core_accuracy = lazy_module("stepsafe.core.accuracy")


def _verification(integrator: Integrator, regions: Mapping[str, Any],
                  up_to: float | None = None) -> dict[str, Any]:
    """Recompute the regions' points with mpmath; a JSON-ready verdict."""
    name, stages, base = integrator.reference
    checks = verify.verify_regions(name, stages, base, dict(regions), up_to=up_to)
    worst = max((c.discrepancy for c in checks), default=0.0)
    failed = [{"model": c.model, "z": c.point.z, "kind": c.point.kind,
               "reference": c.reference,
               "discrepancy": None if c.discrepancy == float("inf") else c.discrepancy}
              for c in checks if not c.ok]
    return {"digits": verify.DPS, "points": len(checks),
            "largest_discrepancy": None if worst == float("inf") else worst,
            "tolerance": verify.TOLERANCE, "ok": not failed, "failed": failed,
            "conservative": sum(c.conservative for c in checks)}


@public()
def region(method: Integrator | str, model: str = "all", *, zmax: float = 10.0,
           verify: bool = False, resonance_orders: Sequence[int] = (3, 4, 5, 6),
           criterion: str | None = None) -> RegionReport:
    """The regions of ``method`` for ``model`` (``"all"``: oscillator, saddle and inverted;
    a model the method has no form for is then listed in ``not_analysed``). On the
    oscillator, also the nonlinear resonances ``n theta = 2 pi m`` of the orders n in
    ``resonance_orders`` below the first boundary. ``criterion``: ``structure`` keeps the
    flow's type and orientation, ``stability`` the type only (for the oscillator
    ``|tr M| <= 2``, the stability interval of the HMC literature; islands of reversed
    orientation join the intervals). None: the method's own (``structure``; ``stability``
    for a Langevin splitting, the only one that applies to it).

    Parameters
    ----------
    method : Integrator or str
        The method (name, ``family:N``, path or Integrator).
    model : str
        ``oscillator``, ``saddle``, ``inverted`` (a barrier top), another model of
        :data:`~stepsafe.api.inputs.REGION_MODELS`, or ``all``.
    zmax : float
        How far in z = beta*h (dimensionless) to analyse.
    verify : bool
        Recompute the regions' points with mpmath (50 digits): ``verification``.
    resonance_orders : sequence of int
        The orders n (3 or more) of the oscillator's nonlinear resonances listed.
    criterion : str, optional
        ``structure`` or ``stability`` (see above).

    Returns
    -------
    RegionReport
        The regions per model; ``to_dict()`` is ``stepsafe region METHOD --json``.

    Examples
    --------
    >>> round(region("verlet", "oscillator").first_boundary(), 12)
    2.0
    """
    integrator = as_integrator(method)
    criterion = validate_criterion(criterion, integrator.tableau)
    model, verify = as_text(model, "model"), as_flag(verify, "verify")
    if model != "all" and model not in REGION_MODELS:
        raise StepsafeError(f"unknown model {model!r}; choose one of "
                            f"{', '.join(REGION_MODELS)} or all")
    zmax = positive_finite(zmax, "zmax")
    models = MAIN_MODELS if model == "all" else (model,)
    regions, skipped, first_error = {}, {}, None
    with integrator.naming_its_file():
        for name in models:
            try:
                regions[name] = find_region(integrator.tableau, name, zmax)
            except StepsafeError as exc:
                skipped[name], first_error = exc.message, first_error or exc
        if first_error and (model != "all" or not regions):  # nothing the user asked for
            raise first_error
    nonlinear: tuple[Any, ...] = ()
    if "oscillator" in regions and regions["oscillator"].symplectic:
        orders = core_resonances.validate_orders(resonance_orders)
        nonlinear = core_resonances.nonlinear_resonances(integrator.tableau,
                                                         regions["oscillator"], orders)
    verdict = _verification(integrator, regions) if verify else None
    structure = {}
    if criterion != "structure":
        structure = {m: r.first_boundary for m, r in regions.items() if r.symplectic}
        regions = {m: under_criterion(r, criterion) for m, r in regions.items()}
    return RegionReport(integrator, MappingProxyType(regions), MappingProxyType(skipped),
                        None if verdict is None else frozen_record(verdict), nonlinear, criterion,
                        MappingProxyType(structure))


@public()
@shared_keywords
def advise(method: Integrator | str | None = None, beta: ArrayLike | None = None, *,
           saddle_beta: ArrayLike | None = None, inverted_beta: ArrayLike | None = None,
           modes: Mapping[str, ArrayLike] | None = None,
           ordinary_frequency: UnitValues | None = None, wavenumber: UnitValues | None = None,
           period: UnitValues | None = None, sigma: ArrayLike | None = None,
           time_unit: str | None = None,
           labels: Mapping[str, Sequence[str | None]] | None = None,
           system: Mapping[str, Any] | None = None,
           scene: str | Path | Scene | None = None, stages: int | None = None,
           base: str | None = None, margin: float | None = None,
           zmax: float | None = None, budget: float | None = None,
           progress: Callable[[float], None] | None = None, problem: Problem | None = None,
           openmm_system: Any = None, positions: Any = None, constraints: str | None = None,
           hydrogen_mass: float | str | None = None, minimize: bool | None = None,
           tol_phase: float | None = None, tol_energy: float | None = None,
           resonance_order: int | None = None, solver: str = "fixed-point",
           criterion: str | None = None, verify: bool = False, gradient_cost: float = 1.0,
           temperature: float | str | None = None, kT: float | None = None,
           length: float | str | None = None, steps: int | None = None,
           max_drift: float | None = None, max_failure: float | None = None,
           follow_steps: int | None = None) -> AdviceReport:
    """Safe step sizes for a method and angular frequencies ``beta`` (or a scene, or a
    system), with the inputs of :func:`problem`.

    Parameters
    ----------
    method : Integrator or str, optional
        The method (name, family with ``stages``, or path); default: the scene's.
    <keywords: frequencies>
    <keywords: analysis>
    <keywords: openmm>
    <keywords: scene>
    tol_phase, tol_energy : float, optional
        Also bound the phase (growth-rate) error theta/z - 1 and the relative energy
        error (dimensionless), and add the usable step and its cost (implicit methods:
        the force evaluations of fixed-point iteration).
    resonance_order : int, optional
        N: also keep every vibration below its first nonlinear resonance
        n theta = 2 pi m with n <= N; the resonances of orders 3 to 6 (and up to N) of
        the fastest vibration are listed in ``nonlinear_resonances`` either way.
    solver : str
        How implicit stages are costed: ``fixed-point`` iteration, or ``nominal`` (one
        evaluation per stage).
    criterion : str, optional
        ``structure`` (type and orientation) or ``stability`` (type only: ``|tr M| <= 2``
        for vibrations); where the other criterion gives another ``h_max``,
        ``other_criterion`` holds it. Default: the method's own (``structure``;
        ``stability`` for a Langevin splitting, whose ``stochastic`` says what
        its verdict means).
    verify : bool
        Recompute the regions' points with mpmath (50 digits): ``verification``.
    gradient_cost : float
        Force evaluations one force-gradient term costs (force-gradient methods; see
        :data:`stepsafe.methods.tableaux.GRADIENT_COST`).
    temperature : float or str, optional
        Analyse at this temperature, in kelvin (``300`` or ``"300 K"``; the scene's
        ``energy_unit:`` names the system's energy unit): ``h_max`` is then the smallest
        of the 0 K one, the linear limit at temperature and the first resonance band
        measured below it (``thermal["limited_by"]`` says which;
        ``zero_kelvin`` holds the 0 K answer), and ``resonance_order`` excludes
        the measured bands as well as the points (the 0 K answer keeps below them:
        a temperature never passes a step the 0 K answer refuses;
        :mod:`stepsafe.api.thermal`). An OpenMM
        system is sampled by OpenMM and its limit measured by runs of the method in OpenMM
        (:mod:`stepsafe.systems.md.thermal`; ``limited_by`` ``"OpenMM runs"``). At T = 0
        (or without a temperature) nothing changes.
    kT : float, optional
        Or the thermal energy, in the system's energy unit.
    length : float or str, optional
        With a temperature: the run's simulated time, in the time unit or as a text with
        a time unit (``"10 ps"``).
    steps : int, optional
        Or the run's number of steps.
    max_drift : float, optional
        With a temperature: the largest acceptable energy drift (energy per time unit);
        the step is lowered until the measured drift meets it (``limited_by`` ``drift``).
    max_failure : float, optional
        With a temperature: the largest acceptable probability that a trajectory of the
        run fails (default 0.001, in [1e-5, 0.1]): the answer is confirmed on a fresh
        ensemble of ``ln(20) / max_failure`` thermal trajectories, none of which may fail.
        On an OpenMM system: the probability that one run of the system in OpenMM fails
        (default 0.05): the answer is confirmed on 72 or more fresh runs
        (:func:`stepsafe.systems.md.thermal.confirmations`), none of which may fail.
    follow_steps : int, optional
        With a temperature: the most steps the thermal trajectories follow (default
        10000). A run of more steps at the answer is refused (a ``StepsafeError``), not
        judged by its first steps.

    Returns
    -------
    AdviceReport
        ``h_max`` and ``safe_h`` in the time unit; ``to_dict()`` is ``stepsafe advise
        --json``.

    >>> report = advise("yoshida4", [3.2], inverted_beta=[1.1])
    >>> report.h_max_limited_by, f"{report.h_max:.6f}"
    ('boundary', '0.491688')
    """
    criterion = None if criterion is None else validate_criterion(criterion)
    order = valid_order(resonance_order)  # (checked before anything is analysed)
    inputs = {"saddle_beta": saddle_beta, "inverted_beta": inverted_beta, "modes": modes,
              "ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
              "period": period, "sigma": sigma, "time_unit": time_unit, "labels": labels,
              "system": system, "scene": scene, "stages": stages, "base": base, "margin": margin,
              "zmax": zmax, "budget": budget,
              "progress": None if problem is not None else progress, "problem": problem,
              "openmm_system": openmm_system, "positions": positions,
              "constraints": constraints, "hydrogen_mass": hydrogen_mass,
              "minimize": minimize}  # (beside problem=, progress reports on the thermal work)
    p = problem_of(method, beta, inputs, run=length)
    warm = _thermal_request(p, temperature, kT, length, steps, max_drift, max_failure,
                            follow_steps)
    if warm is not None and (tol_phase is not None or tol_energy is not None):
        raise StepsafeError("temperature: the answer at temperature does not bound the phase "
                            "or energy error yet; give tol_phase/tol_energy without it")
    # (at temperature the points stay excluded: the 0 K answer caps the one measured)
    integrator, result = p.integrator, None
    criterion = validate_criterion(criterion, integrator.tableau)
    with integrator.naming_its_file(), shared_regions():
        if p.system is not None:
            if tol_phase is not None or tol_energy is not None:
                raise StepsafeError("--tol-phase/--tol-energy apply to frequencies, not yet "
                                    "to system: scenes")
            data = systems_advice.system_advice(integrator.tableau, p.system, p.margin, p.zmax,
                                 integrator.name, criterion, valid_order(resonance_order))
            data["fixed_point_limit"] = _system_solver_limit(integrator, p)
        elif tol_phase is None and tol_energy is None:
            result = core_advise(integrator.tableau, p.modes, p.margin, p.zmax, integrator.name,
                                 resonance_order=valid_order(resonance_order), criterion=criterion)
            data = advice_data(result)
        else:
            tols = tuple(core_tradeoff.Tolerance(k, valid_tolerance(k, v)) for k, v in
                         (("phase", tol_phase), ("energy", tol_energy)) if v is not None)
            res = core_tradeoff.tradeoff(integrator.tableau, p.modes, tols, p.margin,
                                         integrator.name, step_cost(integrator, gradient_cost),
                                         p.zmax, valid_order(resonance_order),
                                         valid_solver(solver), criterion)
            result = res.advice
            data = tradeoff_data(res)
        if result is not None:
            other = _other_criterion(integrator, p, result, resonance_order)
            if other is not None:
                data["other_criterion"] = other
            data["nonlinear_resonances"] = _fastest_resonances(
                integrator, result, p, resonance_order) \
                if integrator.tableau.hamiltonian else []
            if not integrator.tableau.hamiltonian:
                data["stochastic"] = _stochastic_record(integrator, p, None)
            data["fixed_point_limit"] = core_solver.step_limit(integrator.tableau, p.modes.betas)
    if result is not None and p.labels:
        label_limits(data, p.modes.betas, p.labels)
    data["time_unit"] = p.time_unit
    if warm is not None:
        _advise_at_temperature(p, warm, data, criterion, order, progress)
    verdict = (_verification(integrator, result.regions)
               if as_flag(verify, "verify") and result else None)
    return AdviceReport(**record_fields(AdviceReport, data, advice=result,
                                        verification=None if verdict is None
                                        else frozen_record(verdict)))


def _stochastic_record(integrator: Integrator, p: Problem, h: float | None
                       ) -> dict[str, Any]:
    """What the verdict on a method that is not Hamiltonian (a Langevin splitting) means:
    its stability is that of the map of the mean, which for the library's splittings holds
    for every friction gamma > 0; at a step ``h``, how it samples the fastest vibration
    (stationary configurational and kinetic temperature over the true ones, 1 exact; see
    :func:`stepsafe.core.langevin.sampling`)."""
    m = integrator.tableau
    coefficients = m.coefficients()
    record: dict[str, Any] = {
        "letters": coefficients.get("letters"), "friction": coefficients.get("friction"),
        "kT": coefficients.get("kT"),
        "stability": "of the mean map, for every friction gamma > 0", "sampling": None}
    betas = p.modes.betas.get("oscillator")
    if h is not None and betas is not None and betas.size:
        mode = langevin.sampling(m, [float(betas.max())], h).modes[0]
        record["sampling"] = mode.to_dict()
    return record


def _thermal_request(p: Problem, temperature: Any, kT: Any, length: Any, steps: Any,
                     max_drift: Any, max_failure: Any = None, follow_steps: Any = None
                     ) -> Any:
    """The request at temperature of the keywords and the problem's scene (None: none,
    or T = 0)."""
    scene = load_scene(p.scene, p.time_unit) if p.scene else None
    tree = p.system.tree if p.system is not None else None
    return request(temperature=temperature, kT=kT, length=length, steps=steps,
                   max_drift=max_drift, max_failure=max_failure, follow_steps=follow_steps,
                   scene=scene, system=tree,
                   time_unit=p.time_unit)


def _advise_at_temperature(p: Problem, warm: Any, data: dict[str, Any], criterion: str,
                           order: int | None, progress: Any) -> None:
    """The answer at temperature into ``data``: ``h_max``, ``h_max_limited_by`` and
    ``safe_h`` become it; the 0 K answer moves to ``zero_kelvin``. A harmonic system's
    answer is the 0 K one, islands included."""
    orders = tuple(range(3, order + 1)) if order is not None else core_resonances.DEFAULT_ORDERS[:2]
    found = thermal.advise_at_temperature(p, warm, data["h_max"], criterion, orders, progress)
    data["zero_kelvin"] = {key: data[key] for key in ("h_max", "h_max_limited_by", "safe_h")}
    # no step at all is confirmed safe at temperature (h_max 0): said, not hidden in a 0
    found["confirmed"] = found["h_max"] is None or found["h_max"] > 0
    data["thermal"] = found
    if found["limited_by"] != "0 K":
        data["h_max"] = found["h_max"]
        data["h_max_limited_by"] = found["limited_by"]
    if data["h_max"] is not None and not found["harmonic"]:
        # (below h_min a run of the stated length has more steps than were followed)
        low = found.get("h_min") or 0.0
        data["safe_h"] = [[low, data["h_max"]]] if data["h_max"] > low else []


def _other_criterion(integrator: Integrator, p: Problem, result: Any,
                     resonance_order: int | None, h: float | None = None
                     ) -> dict[str, Any] | None:
    """The safe steps under the criterion not asked for, when they differ (with ``h``:
    whether that step is safe under it)."""
    other = next((c for c in CRITERIA if c != result.criterion
                  and c in integrator.tableau.criteria), None)
    if other is None:
        return None
    zmax = max(r.zmax for r in result.regions.values())
    alt = advice_data(core_advise(integrator.tableau, p.modes, p.margin, zmax,
                                  integrator.name, resonance_order=valid_order(resonance_order),
                                  criterion=other))
    if alt["safe_h"] == [[float(lo), hi] for lo, hi in result.safe_h]:
        return None
    out = {key: alt[key] for key in ("criterion", "h_max", "h_max_limited_by", "limiting",
                                     "safe_h")}
    if h is not None:
        out["safe"] = any(lo < h and (hi is None or h < hi) for lo, hi in alt["safe_h"])
    return out


def _fastest_resonances(integrator: Integrator, result: Any, p: Problem,
                        order: int | None) -> list[dict[str, Any]]:
    """The nonlinear resonances of the fastest vibration below its first boundary (or
    below the resonance that caps it), with their steps h."""
    region = result.regions.get("oscillator")
    betas = p.modes.betas.get("oscillator")
    if region is None or betas is None or not region.symplectic or not betas.max() > 0:
        return []
    orders = tuple(range(3, max(order or 0, max(core_resonances.DEFAULT_ORDERS)) + 1))
    found = core_resonances.nonlinear_resonances(integrator.tableau, region, orders)
    return nonlinear_data(found, float(betas.max()), p.margin)


def _system_solver_limit(integrator: Integrator, p: Problem) -> float | None:
    """The step beyond which fixed-point iteration of an implicit method's stages diverges
    for the problem's frequencies or system (None: explicit, or no limit)."""
    if integrator.explicit:
        return None
    if p.system is None:
        return core_solver.system_step_limit(integrator.tableau, p.modes.betas, [])
    betas = p.system.modes.betas if p.system.modes is not None else None
    return core_solver.system_step_limit(integrator.tableau, betas,
                                         [S for _, S in p.system.coupled])


@public()
@shared_keywords
def check(method: Integrator | str | None = None, h: float | str | None = None,
          beta: ArrayLike | None = None, *,
          saddle_beta: ArrayLike | None = None, inverted_beta: ArrayLike | None = None,
          modes: Mapping[str, ArrayLike] | None = None,
          ordinary_frequency: UnitValues | None = None, wavenumber: UnitValues | None = None,
          period: UnitValues | None = None, sigma: ArrayLike | None = None,
          time_unit: str | None = None,
          labels: Mapping[str, Sequence[str | None]] | None = None,
          system: Mapping[str, Any] | None = None,
          scene: str | Path | Scene | None = None, stages: int | None = None,
          base: str | None = None, margin: float | None = None,
          zmax: float | None = None, budget: float | None = None,
          progress: Callable[[float], None] | None = None, problem: Problem | None = None,
          openmm_system: Any = None, positions: Any = None, constraints: str | None = None,
          hydrogen_mass: float | str | None = None, minimize: bool | None = None,
          resonance_order: int | None = None, criterion: str | None = None,
          verify: bool = False, solver: str = "fixed-point",
          require_complete_search: bool = False, temperature: float | str | None = None,
          kT: float | None = None, length: float | str | None = None,
          steps: int | None = None, max_drift: float | None = None,
          max_failure: float | None = None, follow_steps: int | None = None) -> CheckReport:
    """Is step ``h`` safe for every frequency? A scene may give the step (``h:``). A step
    exactly on a resonance or a pole is unsafe.

    Parameters
    ----------
    method : Integrator or str, optional
        The method (name, family with ``stages``, or path); default: the scene's.
    h : float or str, optional
        The step: a number in the time unit, or a text with a time unit (``"0.5 fs"``,
        converted); default: the scene's ``h:``.
    <keywords: frequencies>
    <keywords: analysis>
    <keywords: openmm>
    <keywords: scene>
    resonance_order : int, optional
        N: a vibration at or beyond its first nonlinear resonance of order at most N is
        unsafe too.
    criterion : str, optional
        As for :func:`advise` (``other_criterion`` says whether ``h`` is safe
        under the other one, when its ``h_max`` differs).
    verify : bool
        Recompute the regions' points up to the step with mpmath: ``verification``.
    solver : str
        ``fixed-point`` (the default): an implicit method's step must also lie below the
        convergence limit of fixed-point iteration of its stages for every vibration and
        barrier (``solver_failure`` says why not); ``newton`` has no such limit.
    require_complete_search : bool
        A system given by a Hamiltonian fails when its equilibrium search cannot vouch
        that it found every equilibrium (``system["search"]`` says what was
        searched, ``search_failure`` why it falls short; see
        :mod:`stepsafe.systems.walks`); other inputs are unaffected.
    temperature, kT, length, steps, max_drift, max_failure, follow_steps : optional
        As for :func:`advise` (a run of more steps at h than ``follow_steps`` is refused
        before anything is run): the step is unsafe too when it lies above the linear
        limit
        at temperature, a trajectory of an ensemble of ``ln(20) / max_failure`` thermal
        trajectories at that step fails, or its measured drift exceeds ``max_drift``
        (a failed trajectory fails it too; ``thermal``;
        ``resonance_order`` keeps excluding the points, as at 0 K); on an OpenMM
        system, when any of ``ln(20) / max_failure`` fresh runs of the method in OpenMM at
        that step fails (59 for the default 0.05 per run), or the run is longer than the
        runs in OpenMM.

    Returns
    -------
    CheckReport
        ``safe``, the failing modes and the safe steps; ``to_dict()`` is ``stepsafe check
        --json``.

    >>> check("verlet", 0.49, [4.0]).safe
    True
    """
    criterion = None if criterion is None else validate_criterion(criterion)
    resonance_order = valid_order(resonance_order)  # (checked before anything is analysed)
    require_complete_search = as_flag(require_complete_search, "require_complete_search")
    inputs = {"saddle_beta": saddle_beta, "inverted_beta": inverted_beta, "modes": modes,
              "ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
              "period": period, "sigma": sigma, "time_unit": time_unit, "labels": labels,
              "system": system, "scene": scene, "stages": stages, "base": base, "margin": margin,
              "zmax": zmax, "budget": budget,
              "progress": None if problem is not None else progress, "problem": problem,
              "openmm_system": openmm_system, "positions": positions,
              "constraints": constraints, "hydrogen_mass": hydrogen_mass,
              "minimize": minimize}  # (beside problem=, progress reports on the thermal work)
    if problem is None:
        p = problem_of(method, beta, {**inputs, "h": h}, run=length)
        step = p.h
    else:
        p = problem_of(method, beta, inputs)
        step = p.h if h is None else step_in_unit(h, p.time_unit)
    if step is None:
        raise StepsafeError(f"{p.scene or 'check'}: no step: give --step H or h: in the "
                            "scene file (h= in Python)")
    warm = _thermal_request(p, temperature, kT, length, steps, max_drift, max_failure,
                            follow_steps)
    integrator, result = p.integrator, None
    criterion = validate_criterion(criterion, integrator.tableau)
    with integrator.naming_its_file(), shared_regions():
        if p.system is not None:
            # (at temperature the engine's runs are those of the analysis at temperature)
            analysed = p.system if warm is None else p.system._replace(engine_check=None)
            data = systems_advice.system_check(integrator.tableau, analysed, step, p.margin, p.zmax,
                                integrator.name, criterion, valid_order(resonance_order),
                                require_complete_search)
        else:
            result = check_step(integrator.tableau, p.modes, step, p.margin, p.zmax,
                                integrator.name, valid_order(resonance_order), criterion)
            data = check_data(result, p.labels)
            other = _other_criterion(integrator, p, result.advice, resonance_order,
                                     float(step))
            if other is not None:
                data["other_criterion"] = other
            if not integrator.tableau.hamiltonian:
                data["stochastic"] = _stochastic_record(integrator, p, float(step))
        if valid_stage_solver(solver) == "fixed-point":
            limit = _system_solver_limit(integrator, p)
            if limit is not None and float(step) >= p.margin * limit:
                data["safe"] = False
                data["solver_failure"] = (
                    f"fixed-point iteration of the stages diverges at this step (it "
                    f"converges for h < {p.margin * limit:.12g}); solve them by Newton's "
                    "method (--solver newton) or take a smaller step")
    data["scene"] = p.scene
    data["time_unit"] = p.time_unit
    if warm is not None:
        # (the scene's margin: when no keyword gave one, and the problem's is the scene's)
        scene = load_scene(p.scene, p.time_unit) if p.scene else None
        margin_key = where_in_scene(scene, "margin") if margin is None and \
            scene is not None and scene.margin == p.margin else "--margin, margin="
        found = thermal.check_at_temperature(p, warm, float(step), criterion, progress,
                                             margin_key)
        data["thermal"] = found
        if not found["safe"]:
            data["safe"] = False
            data["thermal_failure"] = "at temperature " + "; ".join(found["reasons"])
    verdict = None
    if as_flag(verify, "verify") and result is not None:
        top = max(float(b.max()) for b in p.modes.betas.values()) * float(step) / p.margin
        verdict = _verification(integrator, result.advice.regions, up_to=1.05 * top)
    return CheckReport(**record_fields(CheckReport, data, result=result,
                                       verification=None if verdict is None
                                       else frozen_record(verdict)))


#: The inputs that describe a method's single-force frequencies: an impulse method's modes
#: come from its scene's fast: and slow: frequencies instead.
_SINGLE_FORCE = ("beta", "saddle_beta", "inverted_beta", "modes", "ordinary_frequency",
                 "wavenumber", "period", "sigma", "labels", "system", "margin", "zmax",
                 "budget", "stages", "base")


@public()
@shared_keywords
def check_scenes(scenes: Sequence[str | Path], *, method: Integrator | str | None = None,
                 h: float | str | None = None, beta: ArrayLike | None = None,
                 saddle_beta: ArrayLike | None = None, inverted_beta: ArrayLike | None = None,
                 modes: Mapping[str, ArrayLike] | None = None,
                 ordinary_frequency: UnitValues | None = None,
                 wavenumber: UnitValues | None = None,
                 period: UnitValues | None = None, sigma: ArrayLike | None = None,
                 time_unit: str | None = None,
                 labels: Mapping[str, Sequence[str | None]] | None = None,
                 system: Mapping[str, Any] | None = None,
                 stages: int | None = None,
                 base: str | None = None, margin: float | None = None,
                 zmax: float | None = None, budget: float | None = None,
                 progress: Callable[[float], None] | None = None,
                 resonance_order: int | None = None, criterion: str | None = None,
                 verify: bool = False, solver: str = "fixed-point",
                 require_complete_search: bool = False, substeps: int | None = None
                 ) -> SceneChecks:
    """:func:`check` of each scene file in ``scenes``, the other inputs the same for all
    (as ``stepsafe check A.yaml B.yaml`` with options): a file that cannot be checked
    (bad input) becomes a :class:`CheckError` in its place and the others are checked
    still. A scene whose method is an impulse method is checked by
    :func:`stepsafe.impulse_advice` (``substeps`` overrides its count).

    Parameters
    ----------
    scenes : list of str or Path
        The scene files, checked in this order.
    method : Integrator or str, optional
        The method for every scene; default: each scene's.
    h : float or str, optional
        The step for every scene, in its time unit or as a text with a time unit
        (``"0.5 fs"``); default: each scene's ``h:``.
    <keywords: frequencies>
    <keywords: analysis>
    progress : callable, optional
        Called with the fraction done.
    resonance_order, criterion, verify, solver, require_complete_search
        As for :func:`check`.
    substeps : int, optional
        Inner steps per outer drift of an impulse method's scenes.

    Returns
    -------
    SceneChecks
        ``checks`` in the order of ``scenes``; ``safe``, ``exit_code`` and ``to_dict()``
        (what ``stepsafe check A.yaml B.yaml ... --json`` prints).

    >>> checks = check_scenes(["examples/scene.yaml", "examples/paper-section3.yaml"])
    >>> checks.safe, checks.exit_code
    (False, 1)
    """
    if isinstance(scenes, (str, Path)) or not isinstance(scenes, Sequence) or not scenes:
        raise StepsafeError("scenes must be a non-empty list of scene files")
    inputs: dict[str, Any] = {"method": method, "beta": beta, "saddle_beta": saddle_beta,
              "inverted_beta": inverted_beta, "modes": modes,
              "ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
              "period": period, "sigma": sigma, "time_unit": time_unit, "labels": labels,
              "system": system, "stages": stages, "base": base, "margin": margin, "zmax": zmax,
              "budget": budget, "progress": progress}
    known_time_unit(time_unit)  # (before any scene is read with it)
    out: list[Any] = []
    for scene in scenes:
        try:
            impulse = _impulse_of(scene, inputs)
            if impulse is None:
                if substeps is not None:
                    raise StepsafeError("substeps applies to impulse (multiple time stepping) "
                                        "methods only")
                out.append(check(h=h, scene=scene, resonance_order=resonance_order,
                                 criterion=criterion, verify=verify, solver=solver,
                                 require_complete_search=require_complete_search, **inputs))
                continue
            out.append(_impulse_check(impulse, scene, h, substeps, criterion,
                                      resonance_order, verify, inputs))
        except StepsafeError as exc:
            out.append(CheckError(as_text(scene, "scene") if isinstance(scene, (str, Path))
                                  else None, exc.message, exc.where))
    return SceneChecks(tuple(out))


def _impulse_of(scene: Any, inputs: Mapping[str, Any]) -> Integrator | None:
    """The impulse method a scene is checked with (``method`` given, else the scene's), or
    None for any other method."""
    name = inputs.get("method")
    if isinstance(name, Integrator):
        return name if name.kind == "impulse" else None
    if inputs.get("stages") is not None or inputs.get("base") is not None:
        return None
    if name is None:
        ref = load_scene(as_text(scene, "scene"), inputs.get("time_unit")).method
        name = None if ref is None or ref.stages or ref.base else ref.name
    if not isinstance(name, str):
        return None
    try:
        integrator = method(name)
    except StepsafeError:
        return None  # the check of any other method reports it in context
    return integrator if integrator.kind == "impulse" else None


def _impulse_check(integrator: Integrator, scene: Any, h: Any, substeps: int | None,
                   criterion: str | None, resonance_order: int | None, verify: bool,
                   inputs: Mapping[str, Any]) -> Any:

    given = [key for key in _SINGLE_FORCE if inputs.get(key) is not None]
    if given or as_flag(verify, "verify"):
        raise StepsafeError(f"{(given or ['verify'])[0]} does not apply to the impulse method "
                            f"{integrator.name}: its modes come as fast: and slow: frequencies "
                            "in a scene file (or use stepsafe.impulse for one pair)")
    report = md.impulse_advice(integrator, scene=as_text(scene, "scene"), substeps=substeps, step=h,
                            time_unit=inputs.get("time_unit"),
                            criterion="structure" if criterion is None else criterion,
                            resonance_order=resonance_order, use_scene_step=h is None)
    if report.step is None:
        raise StepsafeError("no step to check: give --step H or h: in the scene", str(scene))
    return report


#: |M| beyond this: products of its entries leave float64, the errors cannot be evaluated.
OVERFLOW = 1e150


@public()
def errors(method: Integrator | str, z: ArrayLike, model: str = "oscillator") -> ErrorTable:
    """Phase and energy errors of one step at each z = beta*h > 0.

    Parameters
    ----------
    method : Integrator or str
        The method (name, ``family:N``, path or Integrator).
    z : array_like
        The points z = beta*h (dimensionless, positive).
    model : str
        ``oscillator`` (phase error theta/z - 1 and the relative energy error bound),
        ``saddle`` or ``inverted`` (growth-rate error log(mu)/z - 1).

    Returns
    -------
    ErrorTable
        The errors at each z, NaN where the structure is lost; ``to_dict()`` is
        ``stepsafe error METHOD --json``.

    Examples
    --------
    >>> table = errors("verlet", [0.1])
    >>> f"{table.phase[0]:.3e}"
    '4.171e-04'
    """
    integrator = as_integrator(method)
    model = as_text(model, "model")
    if model not in REGION_MODELS:
        raise StepsafeError(f"unknown model {model!r}; choose one of {', '.join(REGION_MODELS)}")
    zs = z_values(z)
    if not zs.size or not np.all(np.isfinite(zs) & (zs > 0)):
        raise StepsafeError("z must be positive finite numbers")
    with np.errstate(all="ignore"):  # far out, M(z) overflows: those rows say so
        e = core_accuracy.errors(integrator.tableau, zs, model)
        M = np.asarray(transfer_matrix(integrator.tableau, zs, model))
        size = np.abs(M).max(axis=(1, 2))
        kernel = core_accuracy.kernel_errors(integrator.tableau, zs, model)
    overflow = ~(np.isfinite(M).all(axis=(1, 2)) & (size <= OVERFLOW))
    phase = np.where(overflow, np.nan, np.asarray(e.phase, dtype=float))
    energy = np.where(overflow, np.nan, np.asarray(e.energy, dtype=float))
    kernel_energy = None if kernel is None else \
        np.where(overflow, np.nan, np.asarray(kernel.energy, dtype=float))
    for arr in (zs, phase, energy, overflow) + (() if kernel_energy is None
                                                 else (kernel_energy,)):
        arr.flags.writeable = False
    return ErrorTable(integrator.name, model, zs, phase, energy, overflow, kernel_energy)


@public()
def transfer_matrices(method: Integrator | str, z: ArrayLike,
                      model: str = "oscillator") -> np.ndarray:
    """The one-step matrices M(z) of ``method`` on ``model`` at each z = beta*h, shape
    (len(z), 2, 2), read-only: (q, p) after one step = M (q, p) before, in units where
    beta = 1 (p scaled by beta). The structure is kept where |tr M| < 2 (oscillator) or
    tr M > 2 (saddle, barrier). NaN where the implicit stage equations are singular (a pole);
    entries may overflow to inf far out; no warning is raised.

    Parameters
    ----------
    method : Integrator or str
        The method (name, ``family:N``, path or Integrator).
    z : array_like
        The points z = beta*h (dimensionless).
    model : str
        ``oscillator`` (q'' = -beta^2 q), ``saddle`` (H = beta p q) or ``inverted``
        (q'' = +beta^2 q).

    Returns
    -------
    numpy.ndarray
        M(z), shape (len(z), 2, 2), read-only.

    Examples
    --------
    >>> M = transfer_matrices("verlet", [1.0])[0]
    >>> float(M[0, 0] + M[1, 1])   # 2 - z^2
    1.0
    """
    integrator = as_integrator(method)
    model = as_text(model, "model")
    if model not in REGION_MODELS:
        raise StepsafeError(f"unknown model {model!r}; choose one of {', '.join(REGION_MODELS)}")
    zs = z_values(z)
    if not np.all(np.isfinite(zs) & (zs >= 0)):
        raise StepsafeError("z must be finite numbers >= 0")
    with np.errstate(all="ignore"), integrator.naming_its_file():
        M = np.array(transfer_matrix(integrator.tableau, zs, model), dtype=float)
    M.flags.writeable = False
    return M


@public()
@shared_keywords
def compare(methods: Sequence[Integrator | str] | str | None = None,
            beta: ArrayLike | None = None, *, saddle_beta: ArrayLike | None = None,
            inverted_beta: ArrayLike | None = None,
            modes: Mapping[str, ArrayLike] | None = None,
            tol_phase: float | None = None, tol_energy: float | None = None,
            margin: float = 1.0, zmax: float | None = None,
            ordinary_frequency: UnitValues | None = None, wavenumber: UnitValues | None = None,
            period: UnitValues | None = None, sigma: ArrayLike | None = None,
            time_unit: str | None = None, solver: str = "best",
            criterion: str = "structure", gradient_cost: float = 1.0,
            jacobian_cost: float = 1.0) -> CompareReport:
    """Rank ``methods`` (names, ``"family:N"`` such as ``"gauss:2"``, Integrators; ``"all"``:
    every built-in method with the families at s = 2 and 3; None: :data:`COMPARE_DEFAULT`)
    by the cost of the usable step h = min(safe, accurate) for the same frequencies
    (``beta`` in rad per time unit, the others with their units as for :func:`problem`;
    h in ``time_unit``; ``"all"`` leaves out the methods
    with no form for a given model: force-gradient methods on saddles). Implicit methods
    cost, by default (``solver="best"``), the cheaper per unit time of two stage solvers
    at the step each allows (the row's ``solver`` says which): fixed-point iteration in
    Gauss-Seidel order, its force evaluations at h with h below 0.9 of its convergence
    limit, or simplified Newton's method, its force evaluations plus ``jacobian_cost``
    force evaluations per Jacobian evaluated and factorised (``"fixed-point"`` or
    ``"newton"``: that solver only; ``"nominal"``: one evaluation per stage). The safe
    step follows ``criterion`` (see :func:`advise`). A force-gradient method costs its
    forces plus ``gradient_cost`` forces per force-gradient term.

    Parameters
    ----------
    methods : list of Integrator or str, or "all", optional
        The methods (see above).
    <keywords: frequencies>
    tol_phase, tol_energy : float, optional
        Bounds on the phase (growth-rate) error theta/z - 1 and on the relative energy
        error (dimensionless); the accurate step meets both.
    margin : float
        F in (0, 1]: every frequency may be up to 1/F times larger.
    zmax : float, optional
        How far in z = beta*h (dimensionless) each method's region is analysed (default
        10).
    solver : str
        ``best``, ``fixed-point``, ``newton`` or ``nominal`` (see above).
    criterion : str
        ``structure`` or ``stability``.
    gradient_cost : float
        Force evaluations one force-gradient term costs.
    jacobian_cost : float
        Force evaluations one Jacobian evaluated and factorised costs (Newton).

    Returns
    -------
    CompareReport
        The rows, cheapest first; ``to_dict()`` is ``stepsafe compare --json``.

    Examples
    --------
    >>> best = compare(["verlet", "pefrl"], [1.0], tol_phase=1e-6).rows[0]
    >>> best.method, best.bound_by
    ('pefrl', 'accuracy')
    """
    criterion = validate_criterion(criterion)
    time_unit = known_time_unit(time_unit) or implied_time_unit(period)
    converted = converted_betas({"ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
                            "period": period, "sigma": sigma}, time_unit)
    grid = Modes.from_arrays(betas_by_model(beta, saddle_beta, inverted_beta, modes, converted))
    tolerances = tuple(core_tradeoff.Tolerance(k, valid_tolerance(k, v)) for k, v in
                       (("phase", tol_phase), ("energy", tol_energy)) if v is not None)
    margin = validate_margin(margin)
    if zmax is not None:
        zmax = positive_finite(zmax, "zmax")
    jacobian_cost = finite_real(jacobian_cost, "jacobian_cost")
    if jacobian_cost < 0:
        raise StepsafeError(f"jacobian_cost must be >= 0 force evaluations, got "
                            f"{jacobian_cost:g}")
    rows = []
    compared = compared_methods(methods)
    if isinstance(methods, str) and methods == "all":  # every method that applies to the modes
        compared = [i for i in compared if all(has_form(i.tableau, model)
                                               for model in grid.betas)]
    for integrator in compared:
        with integrator.naming_its_file():
            res = core_tradeoff.tradeoff(integrator.tableau, grid, tolerances, margin,
                                         integrator.name, step_cost(integrator, gradient_cost),
                                         zmax, solver=valid_solver(solver),
                                         criterion=criterion, jacobian_cost=jacobian_cost)
        rows.append(compare_row(res, integrator.explicit))
    rows.sort(key=lambda r: (r["cost"] is None, r["cost"] or 0.0))
    ranked = []
    for i, r in enumerate(rows, 1):
        r["rank"] = i if r["cost"] is not None else None
        if "processor_evaluations" in r:
            r["processor_evaluations"] = r["processor_evaluations"]["start"]
        ranked.append(CompareRow(**{**r, "tolerance_status": tuple(r["tolerance_status"])}))
    return CompareReport(tuple(ranked),
                         MappingProxyType({k: int(v.size) for k, v in grid.betas.items()}),
                         MappingProxyType({t.kind: t.value for t in tolerances}), margin,
                         time_unit, solver, criterion, jacobian_cost)
