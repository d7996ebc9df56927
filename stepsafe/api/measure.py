"""Measure the trade on the user's own system: :func:`measure` and :func:`refine`, behind
``stepsafe measure``; what is measured and how is :mod:`stepsafe.systems.measurement`."""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, overload

import numpy as np

from stepsafe.api.inputs import Integrator, as_integrator
from stepsafe.api.keywords import shared_keywords
from stepsafe.api.measure_reports import (
    NEGLIGIBLE,
    EnsembleReport,
    EnsembleRow,
    InvariantRow,
    MeasureReport,
    MeasureRow,
    Refinement,
)
from stepsafe.arguments import public
from stepsafe.core.accuracy import errors, z_for_tolerance
from stepsafe.core.ensemble import engine_for, integrate
from stepsafe.core.integrator import Engine
from stepsafe.core.regions import find_region
from stepsafe.exceptions import StepsafeError, finite_real, positive_finite
from stepsafe.systems.integrate import shell_states, thermal_states
from stepsafe.systems.measurement import (
    UNSTABLE,
    MeasuredSystem,
    Run,
    measured_system,
    reference_floor,
    run_steps,
)
from stepsafe.systems.scene import time_unit_in_force
from stepsafe.units import duration
from stepsafe.units import time_unit as known_time_unit

#: Steps of one run at most by default (each costs the method's evaluations in Python)...
MAX_STEPS = 2_000_000
#: ... and at most when asked (``max_steps``).
MAX_STEPS_CAP = 100_000_000
#: Steps h measured in one call at most.
MAX_STEP_SIZES = 200
#: Default length of a run, in periods of the vibration the start orbits.
DEFAULT_PERIODS = 100
#: Trajectories of one ensemble at most, and trajectory steps (trajectories times steps,
#: summed over the step sizes) of one call at most.
MAX_ENSEMBLE = 1_000_000
MAX_ENSEMBLE_STEPS = 1_000_000_000
#: State values of one ensemble at most (trajectories times 2n: 80 MB of float64).
MAX_ENSEMBLE_VALUES = 10_000_000
#: The seed of an ensemble's draw unless given (printed with the results).
DEFAULT_SEED = 0


@overload
def measure(method: Integrator | str, h: Sequence[float | str] | float | str, *,
            scene: str | Path | None = ..., system: Mapping[str, Any] | None = ...,
            time: float | str | None = ..., initial: Sequence[float] | None = ...,
            energy: float | None = ..., time_unit: str | None = ..., solver: str = ...,
            max_steps: int = ..., budget: float | None = ...,
            progress: Callable[[float], None] | None = ..., ensemble: None = ...,
            kT: None = ..., seed: int = ...) -> MeasureReport: ...


@overload
def measure(method: Integrator | str, h: Sequence[float | str] | float | str, *,
            scene: str | Path | None = ..., system: Mapping[str, Any] | None = ...,
            time: float | str | None = ..., initial: Sequence[float] | None = ...,
            energy: float | None = ..., time_unit: str | None = ..., solver: str = ...,
            max_steps: int = ..., budget: float | None = ...,
            progress: Callable[[float], None] | None = ..., ensemble: int,
            kT: float | None = ..., seed: int = ...) -> EnsembleReport: ...


@public()
@shared_keywords
def measure(method: Integrator | str, h: Sequence[float | str] | float | str, *,
            scene: str | Path | None = None,
            system: Mapping[str, Any] | None = None, time: float | str | None = None,
            initial: Sequence[float] | None = None, energy: float | None = None,
            time_unit: str | None = None, solver: str = "fixed-point",
            max_steps: int = MAX_STEPS, budget: float | None = None,
            progress: Callable[[float], None] | None = None, ensemble: int | None = None,
            kT: float | None = None, seed: int = DEFAULT_SEED
            ) -> MeasureReport | EnsembleReport:
    """Integrate the system of ``scene`` (or ``system``: the mapping a scene's ``system:``
    holds) with ``method`` at each step size of ``h`` for a time ``time`` (default: 100
    periods of the vibration the start orbits), from ``initial`` (q then p) or, for a
    1-dof Hamiltonian, from the elliptic equilibrium with momentum raised to the
    ``energy`` given (default start: q displaced from that equilibrium by a tenth of the
    box). Implicit methods solve their stages by ``solver``: ``fixed-point`` iteration or
    simplified ``newton`` (the Jacobian from the Hessian at each step's start). A run of
    more than ``max_steps`` steps is refused; after ``budget`` seconds the run under way
    stops (status ``budget``) and the rest are not run (``not run``). Steps and the time
    are numbers in ``time_unit`` (else the scene's, else the unit their texts name), or
    texts with a time unit (``"0.5 fs"``). See the module docstring for what is measured.

    With ``ensemble`` (a number N of trajectories) the method runs N initial conditions
    at once instead (:func:`stepsafe.core.ensemble.integrate`), drawn with ``seed``
    around the elliptic equilibrium the default start orbits (its Hessian ``S`` positive
    definite): on the energy shell ``energy`` (H there is
    ``H_e + (x - x_e)^T S (x - x_e) / 2``: every phase and every split of the energy among
    the modes) or, with ``kT`` instead, from the Boltzmann distribution
    ``N(x_e, kT S^-1)`` of the quadratic model; the result is an :class:`EnsembleReport`
    of the distribution of each trajectory's largest energy error over every step,
    relative to its energy above the equilibrium's.

    Parameters
    ----------
    method : Integrator or str
        The method (name, ``family:N``, path or Integrator).
    h : float, str or list of them
        The step sizes, in the time unit or as texts with a time unit.
    <keywords: run>
    max_steps : int
        The most steps one run may take.
    budget : float, optional
        Seconds after which the run under way stops.
    progress : callable, optional
        Called with the fraction done.
    ensemble : int, optional
        N: run N trajectories at once (see above).
    kT : float, optional
        With ``ensemble``: draw from the Boltzmann distribution at this thermal energy, in
        the system's energy unit.
    seed : int
        The seed of the ensemble's draws.

    Returns
    -------
    MeasureReport or EnsembleReport
        A row per step size; ``to_dict()`` is ``stepsafe measure --json``.

    Examples
    --------
    >>> report = measure("verlet", [0.1], system={"hamiltonian": "p**2/2 + q**2/2",
    ...                  "box": {"q": [-1, 1], "p": [-1, 1]}}, initial=[0.0, 1.0])
    >>> row = report.rows[0]
    >>> round(row.energy_ratio, 3), row.status   # the linear bound kappa - 1 is reached
    (1.0, 'ok')
    """
    integrator = as_integrator(method)
    if ensemble is not None or kT is not None:
        if initial is not None or budget is not None or solver != "fixed-point":
            raise StepsafeError("ensemble: give no initial, budget or solver (the ensemble "
                                "draws its own starts and runs splitting methods)")
        return _ensemble(integrator, h, scene, system, time, energy, kT, ensemble, seed,
                         time_unit, max_steps, progress)
    time_unit = known_time_unit(time_unit)
    steps = [h] if isinstance(h, (int, float, str)) else h
    time_unit = time_unit_in_force(time_unit, scene,
                                   list(steps) if isinstance(steps, (list, tuple)) else None,
                                   time)
    hs = _steps(steps, time_unit)
    problem = measured_system(integrator.tableau, scene, system, initial, energy, time_unit)
    if time is None:
        if problem.beta is None:
            raise StepsafeError("give the time to integrate (--time T): the start orbits no "
                                "vibration whose period would set it")
        time = DEFAULT_PERIODS * 2 * math.pi / problem.beta
    time = positive_finite(duration(time, "time", time_unit), "time")
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or \
            not 1 <= max_steps <= MAX_STEPS_CAP:
        raise StepsafeError(f"max_steps must be an integer from 1 to {MAX_STEPS_CAP}")
    deadline = None if budget is None else _time.monotonic() + positive_finite(budget,
                                                                                 "budget")
    longest = max(hs)
    if longest > time:
        raise StepsafeError(f"the step h = {longest:.6g} is longer than the run time "
                            f"{time:.6g}: give a longer --time or a smaller step")
    ratios = [time / h * (1 - 1e-12) for h in hs]  # (inf where T / h overflows)
    if not max(ratios) <= max_steps:
        raise StepsafeError(f"T / h = {max(ratios):.3g} steps exceeds the {max_steps} allowed "
                            "in one run: a shorter --time, larger steps or --max-steps")
    counts = [max(1, math.ceil(r)) for r in ratios]
    if not isinstance(solver, str) or solver not in ("fixed-point", "newton"):
        raise StepsafeError(f"solver must be fixed-point or newton, got {str(solver)[:20]!r}")
    try:
        Engine(integrator.tableau, problem.system, solver=solver)
    except ValueError as exc:
        raise StepsafeError(f"{integrator.name}: {exc}") from None
    total, done = float(sum(counts)), 0
    exact = problem.reference([n * step for step, n in zip(hs, counts)], deadline)
    check = getattr(exact, "check", None)
    floors = [None] * len(hs) if check is None else \
        [reference_floor(x, c, problem) for x, c in zip(exact, check)]
    rows = []
    for step, n, state, floor in zip(hs, counts, exact, floors):
        def tick(k: int, done=done) -> None:
            if progress:
                progress((done + k) / total)

        if deadline is not None and _time.monotonic() > deadline:
            rows.append(MeasureRow(step, n, n * step, "not run", *(None,) * 7))
            continue
        rows.append(_row(integrator, problem, step, n,
                         run_steps(integrator.tableau, problem, step, n, state, tick,
                                   solver, deadline), floor))
        done += n
    state = np.concatenate([problem.q0[0], problem.p0[0]])
    return MeasureReport(integrator.name, problem.description, tuple(map(float, state)),
                         float(problem.system.energy(problem.q0, problem.p0)[0]),
                         problem.beta, problem.reference_text, tuple(rows), time_unit)


def _ensemble(integrator: Integrator, h: Any, scene: Any, system: Any, time: Any,
              energy: float | None, kT: float | None, count: Any, seed: Any,
              time_unit: str | None, max_steps: int,
              progress: Callable[[float], None] | None) -> EnsembleReport:
    """:func:`measure` on an ensemble (see there)."""
    if count is None:
        raise StepsafeError("--kT needs --ensemble N (the number of trajectories)")
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or \
            not 1 <= count <= MAX_ENSEMBLE:
        raise StepsafeError(f"--ensemble must be an integer from 1 to {MAX_ENSEMBLE}, "
                            f"got {str(count)[:20]}")
    count = int(count)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or \
            not 0 <= seed < 2 ** 63:
        raise StepsafeError(f"--seed must be an integer from 0 to 2**63 - 1, got "
                            f"{str(seed)[:20]}")
    if (energy is None) == (kT is None):
        raise StepsafeError("--ensemble: give the energy shell (--energy E) or the "
                            "temperature (--kT E), one of them")
    tableau = integrator.tableau
    time_unit = known_time_unit(time_unit)
    steps = [h] if isinstance(h, (int, float, str)) else h
    time_unit = time_unit_in_force(time_unit, scene,
                                   list(steps) if isinstance(steps, (list, tuple)) else None,
                                   time)
    hs = _steps(steps, time_unit)
    problem = measured_system(tableau, scene, system, None, None, time_unit)
    if problem.metric is None or problem.centre is None or \
            problem.equilibrium_energy is None:
        raise StepsafeError("--ensemble: no elliptic equilibrium (positive definite "
                            "Hessian) in the box to draw the trajectories around")
    try:
        engine_for(tableau, problem.system)  # what the method cannot run on this H
    except StepsafeError as exc:
        raise StepsafeError(f"--ensemble: {exc}") from None
    if time is None:
        if problem.beta is None:
            raise StepsafeError("give the time to integrate (--time T)")
        time = DEFAULT_PERIODS * 2 * math.pi / problem.beta
    time = positive_finite(duration(time, "time", time_unit), "time")
    if max(hs) > time:
        raise StepsafeError(f"the step h = {max(hs):.6g} is longer than the run time "
                            f"{time:.6g}: give a longer --time or a smaller step")
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or \
            not 1 <= max_steps <= MAX_STEPS_CAP:
        raise StepsafeError(f"max_steps must be an integer from 1 to {MAX_STEPS_CAP}")
    ratios = [time / step * (1 - 1e-12) for step in hs]
    if not max(ratios) <= max_steps:
        raise StepsafeError(f"T / h = {max(ratios):.3g} steps exceeds the {max_steps} allowed "
                            "in one run: a shorter --time, larger steps or --max-steps")
    counts = [max(1, math.ceil(r)) for r in ratios]
    if sum(counts) * count > MAX_ENSEMBLE_STEPS:
        raise StepsafeError(f"--ensemble {count} times {sum(counts)} steps exceeds the "
                            f"{MAX_ENSEMBLE_STEPS:.0e} trajectory steps of one call")
    centre, S, H_e = problem.centre, problem.metric, float(problem.equilibrium_energy)
    if count * centre.size > MAX_ENSEMBLE_VALUES:
        raise StepsafeError(f"--ensemble {count} trajectories of {centre.size} state values "
                            f"each exceed the {MAX_ENSEMBLE_VALUES:.0e} values of one call")
    rng = np.random.default_rng(int(seed))
    if energy is not None:
        energy = finite_real(energy, "--energy")
        if not energy > H_e:
            raise StepsafeError(f"--energy {energy:g} is not above the minimum {H_e:g} of "
                                "the equilibrium the ensemble is drawn around")
        X0 = shell_states(centre, S, energy - H_e, count, rng)
    else:
        kT = positive_finite(kT, "--kT")
        X0 = thermal_states(centre, S, kT, count, rng)
    n = X0.shape[1] // 2
    q0, p0 = X0[:, :n], X0[:, n:]
    rows = []
    for k, (step, steps_n) in enumerate(zip(hs, counts)):
        ran = integrate(tableau, problem.system, q0, p0, step, steps_n)
        assert ran.worst is not None and ran.energy0 is not None
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.abs(ran.energy0 - H_e)
            errors = ran.worst / np.where(scale > 0, scale, 1.0)
        unstable = int(np.sum(~(errors <= UNSTABLE)))
        with np.errstate(invalid="ignore"):
            q = np.quantile(errors, [0.5, 0.9, 0.99])

        def value(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        rows.append(EnsembleRow(step, steps_n, steps_n * step, value(q[0]), value(q[1]),
                                value(q[2]), value(float(np.max(errors))), unstable,
                                tuple(map(float, errors))))
        if progress:
            progress((k + 1) / len(hs))
    return EnsembleReport(integrator.name, problem.description, count, int(seed),
                          "shell" if energy is not None else "thermal", energy,
                          None if kT is None else float(kT), tuple(map(float, centre)), H_e,
                          tuple(rows), time_unit, tuple(tuple(map(float, x)) for x in X0))


def _steps(steps: Sequence[float | str], time_unit: str | None) -> list[float]:
    """The step sizes h in ``time_unit`` (numbers, or texts with a time unit)."""
    try:
        items = list(steps)
    except TypeError:
        raise StepsafeError("h must be a step size or a list of step sizes") from None
    if not items:
        raise StepsafeError("no step sizes: give --h H (repeatable) or --h-range LO,HI,N")
    if len(items) > MAX_STEP_SIZES:
        raise StepsafeError(f"{len(items)} step sizes; at most {MAX_STEP_SIZES} per run")
    return [positive_finite(duration(h, "h", time_unit), "h") for h in items]


def _row(integrator: Integrator, problem: MeasuredSystem, h: float, n: int, run: Run,
         floor: float | None = None) -> MeasureRow:
    """The row of one run beside the linear prediction (status ``beyond z*`` for a run that
    stayed finite past the method's first boundary, where the model predicts nothing); a
    trajectory error below the reference's ``floor`` is not reported as a number."""
    T = n * h
    prediction = _prediction(integrator, problem.beta, h, T)
    status = run.status
    if status == "ok" and problem.beta is not None and prediction[0] is None:
        status = "beyond z*"  # ran, but past the linear model's first boundary
    trajectory, below = run.trajectory_error, False
    if trajectory is not None and floor is not None and not trajectory > floor:
        trajectory, below = None, True
    fit = run.energy_fit
    invariants = tuple(InvariantRow(name, f.spread, f.slope, f.r2, f.behaviour)
                       for name, f in run.invariants)
    return MeasureRow(h, n, T, status, run.energy_error, run.energy_drift,
                      trajectory, run.evaluations_per_time, run.iterations_per_step,
                      *prediction, run.jacobians_per_time, run.gradients_per_time,
                      floor, below, None if fit is None else fit.r2,
                      None if fit is None else fit.behaviour, invariants,
                      run.seconds_per_time)


def _prediction(integrator: Integrator, beta: float | None, h: float, T: float
                ) -> tuple[float | None, float | None]:
    """The linear model's energy error bound and phase drift over T (None beyond the
    method's first boundary or without a vibration)."""
    if beta is None:
        return None, None
    z = beta * h
    boundary = find_region(integrator.tableau, "oscillator", max(10.0, 1.1 * z)).first_boundary
    if boundary is not None and z >= boundary:
        return None, None
    e = errors(integrator.tableau, np.array([z]), "oscillator")
    energy, phase = float(np.asarray(e.energy)[0]), float(np.asarray(e.phase)[0])
    if not (math.isfinite(energy) and math.isfinite(phase)):
        return None, None
    drift = abs(phase) * beta * T  # the phase the run falls behind (or ahead) by
    energy = abs(energy) if abs(energy) > NEGLIGIBLE else 0.0
    return energy, 2.0 * abs(math.sin(min(drift, math.pi) / 2))


# ---------------------------------------------------------------- refinement by measurement

#: Measurement runs of one refinement at most, and the relative bracket it stops at.
MAX_REFINE_RUNS = 24
REFINE_REL = 1e-3
#: With no vibration to predict from, the refinement starts at h = T / this.
NO_VIBRATION_START = 1000


@public()
@shared_keywords
def refine(method: Integrator | str, quantity: str, tol: float, *,
           scene: str | Path | None = None, system: Mapping[str, Any] | None = None,
           time: float | str | None = None, initial: Sequence[float] | None = None,
           energy: float | None = None, time_unit: str | None = None,
           solver: str = "fixed-point",
           progress: Callable[[float], None] | None = None) -> Refinement:
    """The largest h whose measured error meets ``tol`` on the scene's own system, by
    bisection on measurements started from the linear prediction (what
    ``advise --tol-*`` predicts, checked and corrected by running the method), or from
    ``T / 1000`` when the start orbits no vibration (an orbit of Kepler's problem; then
    ``time`` is required and h stays below it).
    ``quantity``: ``energy`` or ``trajectory`` (see :class:`MeasureRow`).

    Parameters
    ----------
    method : Integrator or str
        The method (name, ``family:N``, path or Integrator).
    quantity : str
        ``energy`` or ``trajectory``.
    tol : float
        The largest error allowed (relative, dimensionless).
    <keywords: run>
    progress : callable, optional
        Called with the fraction done.

    Returns
    -------
    Refinement
        The step found, its error, the prediction and every run; ``to_dict()`` is
        ``stepsafe measure --tol-energy T --json`` (or ``--tol-trajectory``).

    Examples
    --------
    >>> r = refine("verlet", "energy", 1e-3, system={"hamiltonian": "p**2/2 - cos(q)",
    ...            "box": {"q": [-4, 4], "p": [-1, 1]}}, initial=[0.0, 0.5], time=20.0)
    >>> r.limited_by, round(r.h / r.predicted, 2)   # the pendulum allows a little more
    ('tolerance', 1.01)
    """
    if not isinstance(quantity, str) or quantity not in ("energy", "trajectory"):
        raise StepsafeError(f"quantity must be energy or trajectory, got {quantity!r}")
    tol = positive_finite(tol, f"the {quantity} tolerance")
    integrator = as_integrator(method)
    time_unit = time_unit_in_force(known_time_unit(time_unit), scene, time)
    problem = measured_system(integrator.tableau, scene, system, initial, energy, time_unit)
    beta = problem.beta
    if time is None:
        if beta is None:
            raise StepsafeError("give the time to integrate (--time T): the start orbits no "
                                "vibration whose period would set it")
        time = DEFAULT_PERIODS * 2 * math.pi / beta
    time = positive_finite(duration(time, "time", time_unit), "time")
    predicted: float | None
    h_safe: float | None
    if beta is None:  # no linear model to start from: T / 1000, and the run time at most
        predicted, h_safe, top = None, None, time
    else:
        z_star = find_region(integrator.tableau, "oscillator").first_boundary or 10.0
        h_safe = z_star / beta
        if quantity == "energy":
            step = z_for_tolerance(integrator.tableau, tol, z_star, kind="energy")
        else:  # the phase error whose drift over T gives that trajectory error
            phase_tol = 2 * math.asin(min(tol, 2.0) / 2) / (beta * time)
            step = z_for_tolerance(integrator.tableau, phase_tol, z_star, kind="phase")
        predicted = None if step.z is None else step.z / beta
        top = h_safe * (1 - 1e-9)
    key = "energy_error" if quantity == "energy" else "trajectory_error"
    rows: list[MeasureRow] = []

    def error_at(h: float) -> float:
        if len(rows) >= MAX_REFINE_RUNS:
            raise _Exhausted
        try:
            report = measure(integrator, [h], scene=scene, system=system, time=time,
                             initial=initial, energy=energy, time_unit=time_unit,
                             solver=solver)
        except StepsafeError:
            raise _Exhausted from None  # a run too long for the step budget: stop here
        row = report.rows[0]
        rows.append(row)
        if progress:
            progress(len(rows) / MAX_REFINE_RUNS)
        value = getattr(row, key)
        if key == "trajectory_error" and row.below_reference:
            value = row.reference_error  # (less than it: what can be said)
            if value is not None and value > tol:
                raise _BelowReference
        return math.inf if row.status != "ok" or value is None else value

    lo = hi = None
    limited = "tolerance"
    if beta is None:
        h = time / NO_VIBRATION_START
    elif predicted is None:  # the linear model meets the tolerance at no step: say so
        return Refinement(quantity, tol, None, None, None, h_safe, "unreachable",
                          MeasureReport(integrator.name, problem.description, (), float("nan"),
                                        beta, problem.reference_text, (), time_unit))
    else:
        h = min(predicted, top)
    try:
        if error_at(h) <= tol:
            lo = h
            while hi is None:
                if lo >= top:
                    limited = "safety" if beta is not None else "time"
                    break
                h = min(2 * lo, top)
                if error_at(h) <= tol:
                    lo = h
                else:
                    hi = h
        else:
            hi = h
            while lo is None:
                h = hi / 4
                if error_at(h) <= tol:
                    lo = h
                else:
                    hi = h
        while hi is not None and hi / lo > 1 + REFINE_REL:
            mid = math.sqrt(lo * hi)
            if error_at(mid) <= tol:
                lo = mid
            else:
                hi = mid
    except _Exhausted:
        if lo is None:
            limited = "unreachable"
    except _BelowReference:
        if lo is None:
            limited = "reference"
    chosen = None if lo is None else next(r for r in rows if r.h == lo)
    below = chosen is not None and key == "trajectory_error" and chosen.below_reference
    best = None if chosen is None else (chosen.reference_error if below
                                        else getattr(chosen, key))
    runs = MeasureReport(integrator.name, problem.description,
                         tuple(map(float, np.concatenate([problem.q0[0], problem.p0[0]]))),
                         float(problem.system.energy(problem.q0, problem.p0)[0]), beta,
                         problem.reference_text, tuple(rows), time_unit)
    return Refinement(quantity, tol, lo, best, predicted, h_safe, limited, runs, below)


class _Exhausted(Exception):
    """The refinement used all its runs."""


class _BelowReference(Exception):
    """A run's error is below the reference's floor, which is above the tolerance."""


# ---------------------------------------------------------------- work-precision

#: Runs of one method in a work-precision diagram at most (each doubles the steps).
WORK_PRECISION_RUNS = 12
#: With no vibration to start from, the first run takes this many steps over T.
WORK_PRECISION_START = 100
#: A method's runs stop once its error is within this factor of the reference's floor.
FLOOR_MARGIN = 10.0


@public()
def work_precision(methods: Sequence[Integrator | str], *, scene: str | Path | None = None,
                   system: Mapping[str, Any] | None = None, time: float | str | None = None,
                   initial: Sequence[float] | None = None, energy: float | None = None,
                   time_unit: str | None = None, solver: str = "fixed-point",
                   budget: float = 60.0, error: str = "trajectory",
                   max_steps: int = MAX_STEPS,
                   progress: Callable[[float], None] | None = None
                   ) -> tuple[MeasureReport, ...]:
    """Error against cost for each of ``methods`` on the scene's system, with step ranges
    chosen per method: every run ends exactly at ``time`` (h = T / n, so one reference
    serves all), the first with n = ``T beta / (0.9 z*)`` steps (just inside the method's
    first boundary for the vibration the start orbits) or 100 with no vibration, and each
    next run with twice the steps, until the ``error`` (``trajectory`` or ``energy``) is
    within 10 times the reference's floor (trajectory) or below 1e-15 (energy), the method
    has used :data:`WORK_PRECISION_RUNS` runs or ``max_steps`` steps, or its share of the
    ``budget`` (seconds for the whole call, the set-up and reference included, shared
    evenly by the methods still to run) is spent. Runs that do not finish (``budget``) are
    left out; unstable runs are kept (they have no error). One :class:`MeasureReport` per
    method, in the order given."""
    began = _time.monotonic()
    if isinstance(methods, (str, Integrator)):
        methods = [methods]
    integrators = [as_integrator(m) for m in methods]
    if not integrators:
        raise StepsafeError("no methods to compare")
    if not isinstance(error, str) or error not in ("trajectory", "energy"):
        raise StepsafeError(f"error must be trajectory or energy, got {str(error)[:20]!r}")
    deadline = began + positive_finite(budget, "budget")
    time_unit = time_unit_in_force(known_time_unit(time_unit), scene, time)
    problem = measured_system(integrators[0].tableau, scene, system, initial, energy,
                              time_unit)
    if time is None:
        if problem.beta is None:
            raise StepsafeError("give the time to integrate (--time T): the start orbits no "
                                "vibration whose period would set it")
        time = DEFAULT_PERIODS * 2 * math.pi / problem.beta
    T = positive_finite(duration(time, "time", time_unit), "time")
    exact = problem.reference([T], deadline)
    check = getattr(exact, "check", None)
    floor = None if check is None else reference_floor(exact[0], check[0], problem)
    key = "trajectory_error" if error == "trajectory" else "energy_error"
    start = np.concatenate([problem.q0[0], problem.p0[0]])
    energy0 = float(problem.system.energy(problem.q0, problem.p0)[0])
    reports = []
    for k, integrator in enumerate(integrators):
        share = began + (deadline - began) if k == len(integrators) - 1 else \
            _time.monotonic() + (deadline - _time.monotonic()) / (len(integrators) - k)
        n = WORK_PRECISION_START
        if problem.beta is not None:
            z_star = find_region(integrator.tableau, "oscillator").first_boundary
            if z_star is not None:
                n = max(1, math.ceil(T * problem.beta / (0.9 * z_star)))
        rows: list[MeasureRow] = []
        while len(rows) < WORK_PRECISION_RUNS and n <= max_steps and \
                _time.monotonic() < share:
            h = T / n
            run = run_steps(integrator.tableau, problem, h, n, exact[0], lambda _: None,
                            solver, share)
            if run.status == "budget":
                break
            row = _row(integrator, problem, h, n, run, floor)
            rows.append(row)
            if progress:
                progress((k + len(rows) / WORK_PRECISION_RUNS) / len(integrators))
            value = getattr(row, key)
            if row.below_reference or (value is not None and (
                    value <= FLOOR_MARGIN * (floor or 0.0) if key == "trajectory_error"
                    else value <= 1e-15)):
                break
            n *= 2
        reports.append(MeasureReport(integrator.name, problem.description,
                                     tuple(map(float, start)), energy0, problem.beta,
                                     problem.reference_text, tuple(rows), time_unit))
    return tuple(reports)


def cost_at(report: MeasureReport, tol: float, error: str = "trajectory") -> float | None:
    """Force evaluations per unit time at which the method's measured ``error`` reaches
    ``tol``: interpolated linearly in (log cost, log error) between the two runs of
    ``report`` (a :func:`work_precision` curve) that bracket it; the cheaper run's cost if
    its error already meets ``tol``; None when no run reaches it (or a run below the
    reference's floor is all that does: its error is not known)."""
    key = "trajectory_error" if error == "trajectory" else "energy_error"
    points = sorted((r.evaluations_per_time, getattr(r, key)) for r in report.rows
                    if r.status == "ok" and r.evaluations_per_time
                    and getattr(r, key) is not None)
    for k, (cost, value) in enumerate(points):
        if value <= tol:
            if k == 0:
                return cost
            cost_a, value_a = points[k - 1]
            if not value_a > 0 or not value > 0:
                return cost
            share = math.log(value_a / tol) / math.log(value_a / value)
            return math.exp(math.log(cost_a) + share * math.log(cost / cost_a))
    return None
