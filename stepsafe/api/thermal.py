"""Safe at temperature: what :func:`stepsafe.advise` and :func:`stepsafe.check` add when
given a temperature (``temperature=`` in kelvin, or ``kT=`` in the system's energy unit)
and the length of the run (``length=`` simulated time, or ``steps=``).

The analysis (:mod:`stepsafe.systems.thermal`) draws configurations of the system's own
potential at that temperature around each of its minima, measures the largest
instantaneous frequency a run of that length meets (the linear limit at temperature),
iterates the method's own map from thermal initial conditions to find the resonance bands
at amplitude, and measures the energy drift. Its answer ``h_max`` at temperature is the
smallest of the 0 K one (every equilibrium, as without a temperature), the linear limit at
temperature, the lower edge of the first band (and, with ``max_drift``, the largest step
whose measured drift meets it), times the margin; ``limited_by`` names the
criterion: ``"0 K"`` (the answer without a temperature), ``"linear at temperature"``,
``"resonance band n:m"`` or ``"drift"``. A linear system (frequencies, stiffness, Hessian,
Gaussian) is harmonic: its answer at any temperature is the 0 K one, and it says so.
An MD engine's system (OpenMM) is answered by the engine itself
(:mod:`stepsafe.systems.md.thermal`: its thermal snapshots, the largest instantaneous
frequency at each, and runs of the method in the engine in place of bands; ``limited_by``
``"OpenMM runs"``), in the engine's energy unit, kJ/mol.
At ``T = 0`` (or without a temperature) nothing changes.

A step is safe at temperature only when none of the thermal trajectories run at it fails:
``max_failure=`` (default :data:`stepsafe.api.temperature.MAX_FAILURE`) sets how many, the
fewest (``ln(20) / max_failure``) whose zero failures show the failure probability below it at
95% confidence; ``check`` runs them at the step, ``advise`` confirms its answer on them,
drawn with a seed of their own (the record's ``confirmation``). On an OpenMM system the
failures counted are runs of the system in OpenMM, ``max_failure`` (default
:data:`stepsafe.systems.md.thermal.MAX_FAILURE`, 0.05) is per run, and ``check`` needs none of
``confirmations(max_failure)`` fresh runs at the step to fail (59 for 0.05); the record's
``engine_runs`` states the seeds, counts, run length and bounds.

Every draw is seeded (``seed``, stated in the record): the same inputs give the same
answer on one machine.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

from stepsafe.api.temperature import MAX_FOLLOW_STEPS, Request, where_in_scene
from stepsafe.core.regions import find_region, under_criterion
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.md import thermal as md_thermal
from stepsafe.systems.md.engine import MOLAR_GAS_CONSTANT
from stepsafe.systems.md.system import ENGINE_INTEGRATORS
from stepsafe.systems.md.thermal import THERMALISATION
from stepsafe.systems.scene import load_scene
from stepsafe.systems.thermal import thermal_check, thermal_limit
from stepsafe.systems.thermal.bands import CONFIDENCE, trajectories_for
from stepsafe.systems.thermal.limit import run_steps
from stepsafe.systems.thermal_scene import Minimum, is_harmonic, minima
from stepsafe.units import TIME_UNITS

#: The seed of every draw of the analysis at temperature.
SEED = 0


def followed(req: Request, h: float) -> None:
    """Refuse a run at step h longer than the thermal trajectories follow
    (``req.follow``): its later steps are not followed, so nothing would show them safe (a
    :class:`StepsafeError` naming the run's key, with what to give instead)."""
    n = run_steps(h, req.length, req.steps)
    if n <= req.follow:
        return
    option = "--steps" if req.steps is not None else "--length"
    remedy = (f"give --follow-steps {n} (follow_steps:) to follow it all (the cost grows in "
              f"proportion to the steps), or a shorter run ({option})"
              if n <= MAX_FOLLOW_STEPS else
              f"that is more than the {MAX_FOLLOW_STEPS:.0e} steps they can follow: give a "
              f"shorter run ({option})")
    steps = f"{n}" if n <= MAX_FOLLOW_STEPS else f"{n:.3g}"
    message = (f"the run's {steps} steps at h = {h:.6g} are more than the thermal trajectories "
               f"follow ({req.follow}): failures that develop after step {req.follow} would "
               f"not be seen, so no step is called safe for this run; {remedy}")
    if req.run_key.startswith("--"):
        raise StepsafeError(f"{req.run_key}: {message}")
    raise StepsafeError(message, req.run_key)


def followed_from(req: Request) -> float | None:
    """The smallest step whose run the thermal trajectories follow whole: ``length /
    follow`` for a run given by its length (a smaller step makes more than ``follow``
    steps, refused by :func:`followed`); None for a run given by its steps (every step's
    run has that many)."""
    if req.length is None:
        return None
    # the smallest float whose run_steps is within follow (run_steps counts a quotient
    # within 4 rounding errors of an integer as it): up from just below length / follow
    h = req.length / req.follow * (1.0 - 8.0 * sys.float_info.epsilon)
    for _ in range(64):
        if run_steps(h, req.length, None) <= req.follow:
            return h
        h = math.nextafter(h, math.inf)
    return req.length / req.follow * (1.0 + 16.0 * sys.float_info.epsilon)


def _minima(p: Any, req: Request) -> list[Minimum] | None:
    """The minima of the problem's potential (None: harmonic, the 0 K answer holds)."""
    if p.integrator.kind == "langevin":
        raise StepsafeError(f"temperature: the analysis at temperature iterates a "
                            f"Hamiltonian map; {p.integrator.name} is a Langevin splitting, "
                            "not analysed at temperature yet")
    system = p.system
    if system is None or is_harmonic(system.tree):
        return None
    if not (isinstance(system.tree, Mapping) and "hamiltonian" in system.tree):
        raise StepsafeError("temperature: only a scene's hamiltonian: is analysed at "
                            "temperature (it samples that potential); an MD engine's system "
                            "is not yet, and its verdicts are the 0 K ones: give no "
                            "temperature, or check the step by the engine's own runs (runs: "
                            "in the scene's system)")
    where = (p.scene or "system") if system.tree is not None else "system"
    return minima(system.tree, system.items, where)


def _progress(progress: Callable[[float], None] | None, count: int
              ) -> Callable[[int], Callable[[str, float], None] | None]:
    """Per minimum i of ``count``, a ``(stage, fraction)`` callback reporting the whole,
    never backwards: the k-th stage of a minimum (their number is not known beforehand)
    fills the next half of what is left of its share, ``1 - 2^-(k-1) (1 - f / 2)``."""
    if progress is None:
        return lambda i: None

    def of(i: int) -> Callable[[str, float], None]:
        state: dict[str, Any] = {"stage": None, "k": 0}

        def report(stage: str, fraction: float) -> None:
            if stage != state["stage"]:
                state["stage"], state["k"] = stage, state["k"] + 1
            f = min(max(fraction, 0.0), 1.0)
            local = 1.0 - 0.5 ** (state["k"] - 1) * (1.0 - 0.5 * f)
            progress((i + local) / count)
        return report
    return of


def _harmonic_record(req: Request, h_zero: float | None, criterion: str) -> dict[str, Any]:
    return {**_request_record(req, criterion, ensemble=False), "h_max": h_zero,
            "h_max_0K": h_zero, "limited_by": "0 K", "harmonic": True, "minima": [],
            "notes": ["the system is linear (harmonic): its frequencies do not depend on "
                      "amplitude and its map has no resonance bands below the linear limit, "
                      "so the answer at temperature is the 0 K one"]}


def _request_record(req: Request, criterion: str, ensemble: bool = True) -> dict[str, Any]:
    """The request, with the criterion (``structure`` or ``stability``) of the method's
    interval z* that the 0 K limit and the linear limit at temperature rest on; with
    ``ensemble`` (a ``hamiltonian:`` analysed by thermal ensembles) the failure threshold,
    the trajectories that can show it and the confidence."""
    out = {"kT": req.kT, "criterion": criterion, "temperature": req.temperature,
           "energy_unit": req.energy_unit, "run": req.run(), "max_drift": req.max_drift,
           "seed": SEED}
    if ensemble:
        out.update(max_failure=req.failure, follow_steps=req.follow,
                   trajectories=trajectories_for(req.failure, CONFIDENCE),
                   confidence=CONFIDENCE)
    return out


def _no_follow_steps(req: Request) -> None:
    """An engine's runs last what the engine's analysis states (the run's length, at most
    :data:`stepsafe.systems.md.thermal.MAX_DURATION`), not ``follow_steps``."""
    if req.follow_steps is not None:
        raise StepsafeError("follow_steps: applies to a hamiltonian: system's thermal "
                            "trajectories; an MD engine's runs last what its analysis "
                            "states (give no follow_steps)")


@contextmanager
def _naming_the_scene(p: Any, req: Request) -> Iterator[None]:
    """An error of the analysis (a potential not finite or not confining at that kT) names
    the scene's Hamiltonian and where the temperature came from."""
    try:
        yield
    except StepsafeError as exc:
        if exc.where:
            raise
        where = f"{p.scene}::$.system.hamiltonian" if p.scene else None
        raise StepsafeError(f"at kT = {req.kT:.6g} ({req.key}): {exc.message}",
                            where) from None


def advise_at_temperature(p: Any, req: Request, h_zero: float | None, criterion: str,
                          orders: tuple[int, ...],
                          progress: Callable[[float], None] | None = None) -> dict[str, Any]:
    """The record of the answer at temperature for :func:`stepsafe.advise`.

    Parameters
    ----------
    p : Problem
        The analysed problem (its method, system, margin).
    req : Request
        The temperature and the run.
    h_zero : float or None
        The 0 K answer (every equilibrium), in the time unit.
    criterion : str
        ``structure`` or ``stability``, for the method's interval z*.
    orders : tuple of int
        Resonance orders whose points refine the band grid.
    progress : callable, optional
        Called with the fraction done.

    Returns
    -------
    dict
        ``h_max`` (the smallest of ``h_zero`` and each minimum's limit at temperature
        times the margin), ``h_min`` (:func:`followed_from`: the safe steps are
        ``h_min <= h < h_max``; None: from 0), ``limited_by`` (``"0 K"`` when ``h_zero``
        is the smaller),
        ``criterion`` (the one given: the limits rest on the method's z* under it),
        ``h_max_0K``, ``h_range`` (where the limit lies at the stated confidence), and
        each minimum's analysis (:func:`limit_record`).
    """
    if _engine_analysis(p) is not None:
        return _engine_advice(p, req, h_zero, criterion, progress)
    found = _minima(p, req)
    if found is None:
        return _harmonic_record(req, h_zero, criterion)
    if h_zero is not None and h_zero > 0:
        followed(req, h_zero / p.margin)  # (every step at temperature is smaller)
    each = []
    report = _progress(progress, len(found))
    for i, m in enumerate(found):
        with p.integrator.naming_its_file(), _naming_the_scene(p, req):
            r = thermal_limit(p.integrator.tableau, m.potential, req.kT, length=req.length,
                              steps=None if req.steps is None else req.steps,
                              criterion=criterion, orders=orders, seed=SEED,
                              drift_tolerance=req.max_drift, max_failure=req.failure,
                              band_steps=req.follow, progress=report(i))
        each.append((m, r))
    best_m, best = min(each, key=lambda e: e[1].h_max)
    if best.h_max > 0:
        followed(req, best.h_max)  # the confirmation followed this many steps at most
    h_t = p.margin * best.h_max
    out = {**_request_record(req, criterion), "h_max_0K": h_zero}
    if h_zero is not None and h_zero <= h_t:
        out.update(h_max=h_zero, limited_by="0 K")
    else:
        out.update(h_max=h_t, limited_by=best.limited_by, at=best_m.label)
    out["h_range"] = [p.margin * best.h_range[0], p.margin * best.h_range[1]]
    out["h_min"] = followed_from(req)
    out["margin"] = p.margin
    out["minima"] = [limit_record(m, r, p.margin) for m, r in each]
    out["harmonic"] = False
    out["notes"] = []
    return out


def no_margin(p: Any, margin_key: str | None) -> None:
    """Refuse a margin below 1 at temperature in a check (a :class:`StepsafeError` naming
    where it came from).

    A margin F promises every frequency up to ``1 / F`` times larger, so a verdict with it
    is about every step from h to ``h / F``. At 0 K failure grows with the step and ``h / F``
    is the worst of them; at temperature a resonance band is an island in h (a step can fail
    while a larger one is clear), so an ensemble at ``h / F`` says nothing of h, and
    ensembles on a grid between would not show that no band lies between their points.
    ``advise`` carries the margin soundly (its steps below the first band it scanned stay
    below it when divided by F)."""
    if p.margin >= 1.0:
        return
    message = (f"a margin {p.margin:g} stands for every step from h to h/{p.margin:g}, and at "
               f"temperature a resonance band can lie between them (bands are islands in "
               f"h), so no ensemble shows them all safe: check h with no margin, or ask "
               f"advise (its range carries the margin)")
    if margin_key is None or margin_key.startswith("--"):
        raise StepsafeError(f"{margin_key or '--margin, margin='}: {message}")
    raise StepsafeError(message, margin_key)


def check_at_temperature(p: Any, req: Request, h: float, criterion: str,
                         progress: Callable[[float], None] | None = None,
                         margin_key: str | None = None) -> dict[str, Any]:
    """The record of the check of step h at temperature for :func:`stepsafe.check`.

    Parameters
    ----------
    p : Problem
        The analysed problem.
    req : Request
        The temperature, the run and ``max_drift``.
    h : float
        The step, in the time unit.
    criterion : str
        ``structure`` or ``stability``.
    progress : callable, optional
        Called with the fraction done.
    margin_key : str, optional
        Where a margin below 1 came from (the option, or the scene's key), which is
        refused at temperature (:func:`no_margin`) unless the system is harmonic.

    Returns
    -------
    dict
        ``safe``: h lies below every minimum's linear limit at
        temperature (z* under ``criterion``, stated), an ensemble at h itself is clear
        of failures
        (:func:`stepsafe.systems.thermal.thermal_check`) and its drift meets
        ``max_drift``; ``reasons`` says what fails, ``minima`` each check
        (:func:`check_record`).
    """
    if _engine_analysis(p) is not None:
        no_margin(p, margin_key)
        return _engine_check(p, req, h, criterion, progress)
    found = _minima(p, req)
    if found is None:
        return {**_request_record(req, criterion, ensemble=False), "safe": True,
                "harmonic": True, "reasons": [], "minima": [],
                "notes": _harmonic_record(req, None, criterion)["notes"]}
    no_margin(p, margin_key)
    step = h
    followed(req, step)
    each, reasons, notes = [], [], []
    report = _progress(progress, len(found))
    for i, m in enumerate(found):
        with p.integrator.naming_its_file(), _naming_the_scene(p, req):
            c = thermal_check(p.integrator.tableau, m.potential, req.kT, step,
                              length=req.length, steps=req.steps, criterion=criterion,
                              max_failure=req.failure, band_steps=req.follow, seed=SEED,
                              progress=report(i))
        if progress is not None:
            progress((i + 1) / len(found))
        each.append(check_record(m, c, p.margin))
        reasons += [f"{r} (minimum at {m.label})" for r in c.reasons]
        if c.linear is not None:  # (how the draws were made: a note on their mixing)
            notes += [n if len(found) == 1 else f"minimum at {m.label}: {n}"
                      for n in c.linear.ensemble.notes]
        d = c.drift
        if req.max_drift is not None and d is not None and d.failed:
            reasons.append(f"{d.failed} of {d.trajectories} trajectories failed: the "
                           f"ensemble's energy is not bounded, so no drift meets max_drift "
                           f"{req.max_drift:g} (minimum at {m.label})")
        elif req.max_drift is not None and d is not None and \
                not d.bound(2.0) <= req.max_drift:
            reasons.append(f"the energy drift {d.rate:.3g} +- {d.error:.2g} per time unit "
                           f"(2 standard errors) exceeds max_drift {req.max_drift:g} "
                           f"(minimum at {m.label})")
    return {**_request_record(req, criterion), "safe": not reasons, "reasons": reasons,
            "harmonic": False, "margin": p.margin, "minima": each, "notes": notes}


def _edge(e: Any) -> dict[str, Any] | None:
    if e is None:
        return None
    return {"clear": e.clear, "unsafe": e.unsafe, "band": e.band,
            "uncertainty": None if math.isinf(e.uncertainty) else e.uncertainty}


def _scan_record(sc: Any, margin: float) -> dict[str, Any]:
    def scaled(e):
        d = _edge(e)
        if d is None:
            return None
        return {k: (None if v is None else margin * v) for k, v in d.items()}

    return {"target": sc.target, "h_range": [margin * sc.h_range[0], margin * sc.h_range[1]],
            "spacing": margin * sc.spacing, "trajectories": sc.trajectories,
            "steps": sc.steps, "threshold": sc.threshold, "confidence": sc.confidence,
            "seed": sc.seed, "start": sc.start_how, "failure": sc.criterion,
            "bands": [{"name": b.name, "resonances": list(b.resonances),
                       "lower": scaled(b.lower), "upper": scaled(b.upper), "peak": b.peak}
                      for b in sc.bands]}


def _drift_record(d: Any, margin: float) -> dict[str, Any] | None:
    if d is None:
        return None
    return {"h": margin * d.h, "rate": d.rate, "error": d.error,
            "fluctuation": d.fluctuation, "per_dof": d.per_dof, "dof": d.dimension,
            "trajectories": d.trajectories, "failed": d.failed, "steps": d.steps,
            "seed": d.seed}


def _frequency_record(linear: Any) -> dict[str, Any] | None:
    if linear is None:
        return None
    w, e = linear.omega, linear.ensemble
    return {"median": w.median, "maximum": w.maximum, "frames": w.frames,
            "effective_frames": w.effective, "run_frames": w.run_frames, "level": w.level,
            "run_quantile": w.estimate, "upper": w.upper, "confidence": w.confidence,
            "extrapolation": w.method, "tail_shape": w.shape,
            "tail_shape_fitted": w.shape_fitted, "threshold": w.threshold,
            "exceedances": w.exceedances, "bootstrap": w.bootstrap, "seed": w.seed,
            "eigenvalues": linear.frequencies.how,
            "sampling": {"how": e.how, "seed": e.seed, "chains": e.chains, "h": e.h,
                         "friction": e.friction, "burn_in": e.burn_in, "thin": e.thin,
                         "tau": e.tau}}


def limit_record(m: Minimum, r: Any, margin: float = 1.0) -> dict[str, Any]:
    """One minimum's :class:`~stepsafe.systems.thermal.ThermalLimit`, JSON-ready (steps
    times the margin)."""
    def scaled(x):
        return None if x is None else margin * x

    return {"at": m.label, "h_max": scaled(r.h_max), "limited_by": r.limited_by,
            "h_range": [scaled(r.h_range[0]), scaled(r.h_range[1])],
            "h_zero": scaled(r.zero.h_zero), "omega_zero": r.zero.omega_zero,
            "z_star": r.zero.z_star, "h_linear": scaled(r.h_linear),
            "h_band": scaled(r.h_band), "h_drift": scaled(r.h_drift),
            "frequencies": _frequency_record(r.linear),
            "scans": [_scan_record(sc, margin) for sc in r.scans],
            "drift": _drift_record(r.drift, margin),
            "confirmation": _confirmation_record(r.confirmation, margin), "seed": r.seed,
            "notes": list(r.notes)}


def _confirmation_record(c: Any, margin: float) -> dict[str, Any] | None:
    if c is None:
        return None
    return {"h": margin * c.h, "max_failure": c.max_failure, "confidence": c.confidence,
            "trajectories": c.trajectories, "steps": c.steps, "seed": c.seed,
            "failures": c.failures, "upper": c.upper,
            "rejected": [{"h": margin * h, "failures": k, "steps": n}
                         for h, k, n in c.rejected]}


def check_record(m: Minimum, c: Any, margin: float = 1.0) -> dict[str, Any]:
    """One minimum's :class:`~stepsafe.systems.thermal.ThermalCheck`, JSON-ready (each
    probe's ``h`` the step its ensemble ran; the limits times the margin)."""
    probes = [{"target": name, "h": pr.h, "verdict": pr.verdict,
               "trajectories": pr.trajectories, "failures": pr.failures, "steps": pr.steps,
               "probability": pr.probability, "lower": pr.lower, "upper": pr.upper,
               "max_failure": pr.threshold}
              for name, pr in c.probes]
    h_linear = None if c.linear is None else margin * c.linear.h_linear
    return {"at": m.label, "safe": c.safe, "reasons": list(c.reasons),
            "h_zero": margin * c.zero.h_zero, "h_linear": h_linear,
            "frequencies": _frequency_record(c.linear), "probes": probes,
            "drift": _drift_record(c.drift, margin), "seed": c.seed}


# --- an MD engine's system (stepsafe.systems.md.thermal) ----------------------------------

#: How the records name the configuration an engine's system is analysed at.
ENGINE_AT = "the OpenMM system at temperature"


def _engine_analysis(p: Any) -> Any:
    """The MD analysis of an engine's system (None for other problems)."""
    return getattr(p.system, "md", None) if p.system is not None else None


def _scale(p: Any) -> float:
    """Picoseconds per time unit of the problem (an engine works in ps)."""
    return float(TIME_UNITS[p.time_unit or "ps"] / TIME_UNITS["ps"])


def _z_star(p: Any, criterion: str) -> float:
    """The end of the method's interval from 0 on the oscillator (its analysed range when
    it has none)."""
    with p.integrator.naming_its_file():
        region = under_criterion(find_region(p.integrator.tableau, "oscillator"), criterion)
    return float(region.first_boundary if region.first_boundary is not None else region.zmax)


def _engine_runs(p: Any, req: Request, run_length: float) -> Any:
    """The runs of the user's integrator in the engine: the method as OpenMM's integrator,
    at the request's temperature, with the seeds, duration and friction of the scene's
    ``runs:`` when it has one (its temperature must be the request's)."""
    name = p.integrator.name
    integrator = ENGINE_INTEGRATORS.get(name)
    if integrator is None:
        raise StepsafeError(f"temperature: on an OpenMM system the step at temperature is "
                            f"measured by runs of the method in OpenMM, which runs "
                            f"{', '.join(ENGINE_INTEGRATORS)} only, not {name}")
    T = req.temperature if req.temperature is not None else req.kT / MOLAR_GAS_CONSTANT
    analysis = _engine_analysis(p)
    tolerance = md_thermal.DRIFT_TOLERANCE
    if req.max_drift is not None:  # energy per time unit, the whole system
        n_dof = analysis.engine.degrees_of_freedom()
        tolerance = req.max_drift / _scale(p) / (max(n_dof, 1) * MOLAR_GAS_CONSTANT * T)
    chosen = analysis.settings.runs
    failure = md_thermal.MAX_FAILURE if req.max_failure is None else req.max_failure
    if chosen is None:
        return md_thermal.Runs(integrator, T, duration=min(md_thermal.MAX_DURATION, run_length),
                               tolerance=tolerance, max_failure=failure)
    if abs(chosen.temperature - T) > 1e-9 * T:
        raise StepsafeError(f"the runs' temperature {chosen.temperature:g} K is not the "
                            f"temperature asked for, {T:g} K",
                            where_in_scene(_scene_of(p), "system.runs.temperature"))
    return md_thermal.Runs(integrator, T, chosen.seeds, chosen.duration, chosen.friction,
                           tolerance, failure)


def _scene_of(p: Any) -> Any:
    return load_scene(p.scene, p.time_unit) if p.scene else None


def _engine_progress(progress: Callable[[float], None] | None
                     ) -> Callable[[str, float], None] | None:
    """Sampling and frequencies fill the first 40%, the runs the rest (a check's runs at
    its step, then the scan of the limit)."""
    if progress is None:
        return None
    share = {"sampling": (0.0, 0.1), "frequencies": (0.1, 0.3), "runs": (0.4, 0.6),
             "step": (0.4, 0.2), "limit": (0.6, 0.4)}

    def report(stage: str, fraction: float) -> None:
        start, width = share.get(stage, (0.0, 1.0))
        progress(start + width * min(max(fraction, 0.0), 1.0))
    return report


def _engine_advice(p: Any, req: Request, h_zero: float | None, criterion: str,
                   progress: Callable[[float], None] | None) -> dict[str, Any]:
    """The record of the answer at temperature on an engine's system
    (:func:`stepsafe.systems.md.thermal.thermal_limit`), in the problem's time unit."""
    scale = _scale(p)
    z_star = _z_star(p, criterion)
    analysis = _engine_analysis(p)
    if req.length is not None:
        run_length = req.length * scale
    else:
        omega = float(analysis.spectrum.eigenvalues[0])
        run_length = float(req.steps or 1) * z_star / math.sqrt(omega) if omega > 0 else 1.0
    _no_follow_steps(req)
    runs = _engine_runs(p, req, run_length)
    r = md_thermal.thermal_limit(analysis, runs, z_star, run_length, _engine_progress(progress),
                                 engine_name="OpenMM")
    h_t = p.margin * r.h_max / scale
    out = {**_request_record(req, criterion, ensemble=False), "h_max_0K": h_zero}
    if h_zero is not None and h_zero <= h_t:
        out.update(h_max=h_zero, limited_by="0 K")
    else:
        out.update(h_max=h_t, limited_by=r.limited_by, at=ENGINE_AT)
    out["h_range"] = [p.margin * r.h_range[0] / scale, p.margin * r.h_range[1] / scale]
    out["margin"] = p.margin
    out["harmonic"] = False
    out["minima"] = [engine_limit_record(r, p.margin, scale)]
    out["notes"] = []
    return out


def _engine_check(p: Any, req: Request, h: float, criterion: str,
                  progress: Callable[[float], None] | None) -> dict[str, Any]:
    """The record of the check at temperature on an engine's system
    (:func:`stepsafe.systems.md.thermal.thermal_check`)."""
    scale = _scale(p)
    step = h / p.margin * scale
    run_length = req.length * scale if req.length is not None else float(req.steps or 1) * step
    _no_follow_steps(req)
    runs = _engine_runs(p, req, run_length)
    c = md_thermal.thermal_check(_engine_analysis(p), runs, _z_star(p, criterion), step, run_length,
                                 _engine_progress(progress))
    linear = c.linear
    entry = {"at": ENGINE_AT, "safe": c.safe, "reasons": list(c.reasons),
             "h_zero": p.margin * c.h_zero / scale,
             "h_linear": p.margin * linear.h_linear / scale,
             "frequencies": _engine_frequencies(linear, scale), "probes": [], "drift": None,
             "seed": int(runs.seeds[0]),
             "engine_runs": _runs_record(runs, ([] if c.trial is None else [c.trial])
                                         + ([] if c.limit is None else list(c.limit.trials)),
                                         p.margin, scale, run_length)}
    if c.limit is not None:
        entry["engine_runs"].update(_scan_limits(c.limit, p.margin, scale))
        entry["h_max"] = p.margin * c.h_max / scale
    return {**_request_record(req, criterion, ensemble=False), "safe": c.safe,
            "reasons": list(c.reasons), "harmonic": False, "margin": p.margin,
            "minima": [entry], "notes": list(c.notes)}



def _engine_frequencies(linear: Any, scale: float) -> dict[str, Any]:
    """:func:`_frequency_record` of the snapshots' frequencies, rad per time unit."""
    w, e = linear.omega, linear.ensemble

    def per_unit(x: float | None) -> float | None:
        return None if x is None else x * scale

    return {"median": per_unit(w.median), "maximum": per_unit(w.maximum), "frames": w.frames,
            "effective_frames": w.effective, "run_frames": w.run_frames, "level": w.level,
            "run_quantile": per_unit(w.estimate), "upper": per_unit(w.upper),
            "confidence": w.confidence, "extrapolation": w.method, "tail_shape": w.shape,
            "tail_shape_fitted": w.shape_fitted, "threshold": per_unit(w.threshold),
            "exceedances": w.exceedances, "bootstrap": w.bootstrap, "seed": w.seed,
            "eigenvalues": linear.frequencies.how,
            "sampling": {"how": e.how, "seed": e.seed, "chains": e.chains, "h": e.h / scale,
                         "friction": e.friction * scale, "burn_in": e.burn_in,
                         "thin": e.thin, "tau": e.tau}}


def _runs_record(runs: Any, trials: list[Any], margin: float, scale: float,
                 run_length: float) -> dict[str, Any]:
    """The runs in the engine, JSON-ready (steps in the time unit times the margin; drifts
    in kT per ps per degree of freedom; ``duration``, ``max_duration`` and the user's
    ``run_length`` in ps; ``max_failure`` the failure probability of one run that the
    confirmations bound at ``confidence``, with the runs each needs)."""
    def trial(t: Any) -> dict[str, Any]:
        drift, error = t.record.drift()
        return {"h": margin * t.h / scale, "stage": t.stage, "verdict": t.verdict,
                "seeds": [r.seed for r in t.record.runs],
                "planned_seeds": len(t.planned), "failures": t.failures,
                "confidence": t.confidence, "upper": t.upper,
                "drift": drift if math.isfinite(drift) else None,
                "drift_error": error if math.isfinite(error) else None,
                "runs": [{"seed": r.seed, "blew_up": r.blew_up, "step": r.blowup_step,
                          "reason": r.reason} for r in t.record.runs]}

    return {"engine": "OpenMM", "integrator": runs.integrator,
            "temperature": runs.temperature, "seeds": list(runs.seeds),
            "max_failure": runs.max_failure, "failure_per": "run",
            "confidence": runs.confidence,
            "check_runs": md_thermal.confirmations(runs.max_failure, runs.confidence),
            "confirmation_runs": [md_thermal.confirmations(runs.max_failure, runs.confidence, k)
                                  for k in range(md_thermal.LOWERINGS)],
            "duration": runs.duration, "max_duration": md_thermal.MAX_DURATION,
            "run_length": run_length, "followed": md_thermal.followed(runs, run_length),
            "thermalisation": THERMALISATION, "friction": runs.friction,
            "drift_tolerance": runs.tolerance, "energy_bound": 0.5,
            "trials": [trial(t) for t in trials]}


def engine_limit_record(r: Any, margin: float, scale: float) -> dict[str, Any]:
    """An :class:`~stepsafe.systems.md.thermal.EngineThermalLimit`, JSON-ready in the time
    unit (steps times the margin), with the keys of :func:`limit_record`."""
    def step(x: float | None) -> float | None:
        return None if x is None else margin * x / scale

    found = r.scan
    runs = _runs_record(found.runs, list(found.trials), margin, scale, r.run_length)
    runs.update(_scan_limits(found, margin, scale))
    return {"at": ENGINE_AT, "h_max": step(r.h_max), "limited_by": r.limited_by,
            "h_range": [step(r.h_range[0]), step(r.h_range[1])], "h_zero": step(r.h_zero),
            "omega_zero": r.omega_zero * scale, "z_star": r.z_star,
            "h_linear": step(r.linear.h_linear), "h_band": None, "h_drift": None,
            "frequencies": _engine_frequencies(r.linear, scale), "scans": [], "drift": None,
            "seed": int(found.runs.seeds[0]), "notes": list(r.notes), "engine_runs": runs}


def _scan_limits(found: Any, margin: float, scale: float) -> dict[str, Any]:
    """What a :class:`~stepsafe.systems.md.thermal.Scan` found: the largest step that
    passed in every seed and the smallest that failed (time unit, times the margin), the
    drift at the first (kT/ps per degree of freedom) and the seeds run there."""
    drift = error = None
    if found.confirmed is not None:
        d, e = found.confirmed.drift()
        drift = d if math.isfinite(d) else None
        error = e if math.isfinite(e) else None
    return {"h_clear": margin * found.h_clear / scale,
            "h_fail": None if found.h_fail is None else margin * found.h_fail / scale,
            "drift": drift, "drift_error": error,
            "confirmed_seeds": [] if found.confirmed is None
            else [x.seed for x in found.confirmed.runs]}
