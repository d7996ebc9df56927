"""Safe at temperature for an MD engine's system: the largest step of the user's integrator at
temperature T, from the engine's own thermal states and runs.

With harmonic bonds the potential of a molecule is anharmonic only through its couplings
(bond lengths against angles, neighbours against each other), and the instability a hot system
meets below the linear limit comes from those couplings: a 1-D profile along a mode of the
minimum misses it. So here everything at temperature comes from the engine (units: nm, amu, ps,
kJ/mol, K; :class:`~stepsafe.systems.md.engine.DynamicsEngine`):

1. **Thermal snapshots** (:class:`~stepsafe.systems.md.enginerun.SamplingSpec`): per seed of
   :data:`SAMPLING_SEEDS`, the engine's LangevinMiddle at the conservative step
   ``Z_SAMPLE / omega_0`` (``omega_0`` the largest frequency at the configuration analysed,
   upper end of its error), friction :data:`FRICTION`, :data:`THERMALISATION` ps of
   thermalisation, then :data:`FRAMES` frames :data:`SPACING` ps apart.
2. **Instantaneous frequencies**: at each snapshot (put on the constraints) the largest
   eigenvalue ``lambda`` of the mass-weighted Hessian on the constraints' tangent space, by
   Lanczos on finite-difference Hessian-vector products
   (:mod:`~stepsafe.systems.md.hessian`, :mod:`~stepsafe.systems.md.constraints`; the step of
   the differences chosen at the first snapshot), and ``omega = sqrt(lambda + error)``. The
   value a run of length L reaches: the ``1 - 1/N`` quantile of their distribution,
   ``N = L omega_0 / pi`` frames (one per half period of the fastest mode), with its upper
   confidence bound (:func:`~stepsafe.systems.thermal.extremes.run_extreme`, chains = seeds).
   The **linear limit at temperature** is ``z* / omega_q`` (``z*`` the end of the method's
   interval from 0 on the oscillator), never above the 0 K limit ``z* / omega_0``.
3. **Runs of the user's integrator in the engine** (:mod:`~stepsafe.systems.md.enginerun`:
   per seed, 1 ps of thermalisation, then the user's run, at most :data:`MAX_DURATION` ps
   unless the scene's ``runs: duration:`` sets the length): a run *fails* when it blows up (a
   non-finite energy, the engine stopping, or the total energy moving by more than half of
   n_dof kT; with a thermostat, the kinetic energy exceeding its mean by that much); for
   Verlet a step also fails when the mean energy drift over its runs exceeds
   :data:`~stepsafe.systems.md.enginerun.DRIFT_TOLERANCE` kT per ps per degree of freedom.
   Runs at a step stop at their first blow-up.

   *Bisection* (cheap, seeds :data:`SEEDS`): first at ``TOP h_linear``; if a seed fails,
   from ``LOW h_linear`` (halved until it passes) by bisection to a relative width
   :data:`RESOLUTION`. *Confirmation* (the statistical rule): with p the probability that
   one run of the system fails at a step, the step given must show ``p < max_failure``
   (:data:`MAX_FAILURE` unless the user gives one) at :data:`CONFIDENCE`. The step lies
   :data:`BACKOFF` below the bisection's largest passing step and is run in m fresh seeds
   (:func:`confirm_seeds`), m the fewest whose zero failures put the one-sided
   Clopper-Pearson bound ``1 - a^(1/m)`` below ``max_failure``; a confirmation with a failure
   lowers the step (by ``2^(k+1) BACKOFF`` after confirmation k: 6%, 12%, 24%) and confirms
   again on fresh seeds, :data:`LOWERINGS` confirmations at most. Confirmation k (from 0)
   uses ``a = (1 - CONFIDENCE) / 2^(k+1)`` (:func:`confirmations`: 72, 86, 99, 113 runs for
   ``max_failure = 0.05``), so the chance that any of them passes a step whose p exceeds
   ``max_failure`` stays below ``1 - CONFIDENCE``.

``h_max`` is the confirmed step, with the drift measured there; ``limited_by`` is ``"linear
at temperature"`` when it is the first step tried, ``TOP h_linear``, and ``"<engine> runs"``
when runs failed above it.
A check at h fails at or above the linear limit at temperature; when any of
``confirmations(max_failure)`` runs at h itself in fresh seeds (59 for 0.05 at 95%) fails;
when they pass, at or above that ``h_max`` (the same scan), so that check and advise agree on
both sides of it; and when the user's run is longer than the runs (a failure that takes longer
to develop is not excluded). The verdicts bound the failure probability of one run of the
stated length, not of a longer one; the record states the runs, their seeds and the bound.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.systems.md.constraints import constrained_modes
from stepsafe.systems.md.engine import MOLAR_GAS_CONSTANT, DynamicsEngine
from stepsafe.systems.md.enginerun import (
    DRIFT_TOLERANCE,
    SamplingSpec,
    TrialRecord,
    TrialSpec,
)
from stepsafe.systems.md.hessian import HessianVectorProduct, extreme_eigenvalues
from stepsafe.systems.md.system import eigenvalue_errors
from stepsafe.systems.thermal.bands import CONFIDENCE as CONFIDENCE_
from stepsafe.systems.thermal.bands import clopper_pearson, trajectories_for
from stepsafe.systems.thermal.extremes import RunExtreme, run_extreme
from stepsafe.systems.thermal.inm import Frequencies
from stepsafe.systems.thermal.limit import AtTemperature
from stepsafe.systems.thermal.sampling import Ensemble

#: The sampling step in units of the fastest 0 K period: ``h = Z_SAMPLE / omega_0`` (0.5 fs for
#: an O-H stretch).
Z_SAMPLE = 0.35
#: Friction of the sampling Langevin dynamics, 1/ps.
FRICTION = 10.0
#: Thermalisation before the first frame, ps.
THERMALISATION = 1.0
#: Time between frames, ps.
SPACING = 0.025
#: Frames per seed, and the seeds of the sampling chains.
FRAMES = 30
SAMPLING_SEEDS = (1, 2, 3, 4)
#: Seeds of the bisection's runs of the user's integrator.
SEEDS = (1, 2, 3)
#: The runs follow the user's run up to this length (ps); a longer run is not followed to its
#: end (the check says so and is not SAFE; ``runs: duration:`` in the scene sets another).
MAX_DURATION = 10.0
#: The default largest acceptable failure probability of one run of the system (a blow-up in
#: one seed's run of the run's length), and the confidence of its bound.
MAX_FAILURE = 0.05
CONFIDENCE = CONFIDENCE_
#: Friction of the user's LangevinMiddle in the runs, 1/ps (when the method is one).
RUN_FRICTION = 1.0
#: The runs start at this fraction of the linear limit at temperature ...
TOP = 0.999
#: ... and, when that fails, the bisection starts from this fraction.
LOW = 0.7
#: The bisection stops when its bracket is this narrow (relative).
RESOLUTION = 0.02
#: The step given lies this fraction below the largest step the bisection found to pass
#: (and is run there in every seed): near the step where runs first fail, a run passes or
#: fails by chance (the water cluster at 300 K passed at 2.507 fs and drifted at 2.505 fs in
#: the same seeds).
BACKOFF = 0.03
#: Confirmations of the step (each after a failed one lowers it), and halvings of LOW, at
#: most.
LOWERINGS = 4
#: Lanczos's relative tolerance at the snapshots (its residual is added to the error).
LANCZOS_TOL = 1e-6

Progress = Callable[[str, float], None]


def confirmations(max_failure: float, confidence: float = CONFIDENCE,
                  attempt: int | None = None) -> int:
    """How many runs a confirmation needs, none failing, to show the failure probability of
    one run below ``max_failure``: the fewest m whose zero failures put the one-sided
    Clopper-Pearson bound ``1 - alpha^(1/m)`` below it, ``alpha = 1 - confidence`` for a
    single confirmation (``attempt`` None: a check's runs at its step) and ``alpha / 2^(k+1)``
    for the scan's confirmation number ``attempt = k`` (0, 1, ...), so that the scan's
    confirmations together give a step whose failure probability exceeds ``max_failure``
    with probability at most ``alpha`` (``sum_k alpha / 2^(k+1) < alpha``).

    Parameters
    ----------
    max_failure : float
        In (0, 1).
    confidence : float
        In (0, 1).
    attempt : int, optional

    Returns
    -------
    int
        59 for ``max_failure = 0.05`` at 95%; 72, 86, 99, ... for the scan's.
    """
    level = confidence if attempt is None else 1.0 - (1.0 - confidence) / 2 ** (attempt + 1)
    return trajectories_for(max_failure, level)


def confirm_seeds(seeds: tuple[int, ...], count: int, offset: int = 0) -> tuple[int, ...]:
    """``count`` seeds none of ``seeds``, after the first ``offset`` such ones:
    ``max + 1 + offset, ..., max + offset + count``.

    Parameters
    ----------
    seeds : tuple of int
        The bisection's.
    count, offset : int

    Returns
    -------
    tuple of int
    """
    top = max(seeds)
    return tuple(top + 1 + offset + k for k in range(count))


@dataclass(frozen=True)
class Runs:
    """What the runs of the user's integrator are (units: ps, K, 1/ps).

    Attributes
    ----------
    integrator : str
        The engine's integrator (``verlet`` or ``langevin-middle``).
    temperature : float
    seeds : tuple of int
        Of the bisection; the confirmations run :func:`confirm_seeds` (fresh ones each).
    duration : float
        Each run's production length (the user's run, at most :data:`MAX_DURATION`).
    friction : float
        Of the user's LangevinMiddle.
    tolerance : float
        Verlet's drift tolerance, kT per ps per degree of freedom.
    max_failure : float
        The largest acceptable failure probability of one run (a seed's run of ``duration``).
    confidence : float
        Of the Clopper-Pearson bound that shows it (:func:`confirmations`).
    """

    integrator: str
    temperature: float
    seeds: tuple[int, ...] = SEEDS
    duration: float = MAX_DURATION
    friction: float = RUN_FRICTION
    tolerance: float = DRIFT_TOLERANCE
    max_failure: float = MAX_FAILURE
    confidence: float = CONFIDENCE

    def spec(self, h: float, seeds: tuple[int, ...], equilibration_step: float,
             stop_at_blowup: bool = True) -> TrialSpec:
        return TrialSpec(self.integrator, h, self.duration, temperature=self.temperature,
                         friction=self.friction, seeds=seeds, equilibration=THERMALISATION,
                         equilibration_step=equilibration_step,
                         stop_at_blowup=stop_at_blowup)


@dataclass(frozen=True)
class Trial:
    """The runs at one step (ps): ``passed`` when every seed of ``planned`` ran without a
    blow-up and (Verlet) the mean drift is within ``tolerance`` kT per ps per degree of
    freedom (the runs stop at the first blow-up: ``record`` holds the seeds run); ``stage``
    says why the step was run; ``confidence`` (None: a bisection's step) that of the bound
    on the failure probability the passing seeds show."""

    h: float
    record: TrialRecord
    passed: bool
    stage: str
    tolerance: float = DRIFT_TOLERANCE
    planned: tuple[int, ...] = ()
    confidence: float | None = None

    @property
    def verdict(self) -> str:
        """``"stable"``, ``"drifts"`` or ``"blew up"``."""
        return self.record.verdict(self.tolerance)

    @property
    def failures(self) -> int:
        """Seeds that blew up."""
        return sum(1 for r in self.record.runs if r.blew_up)

    @property
    def upper(self) -> float | None:
        """The one-sided Clopper-Pearson upper bound on the failure probability of one run
        at ``confidence`` when every planned seed ran without failing (None otherwise: a run
        stopped at its first failure bounds nothing)."""
        if self.confidence is None or self.failures or len(self.record.runs) < len(
                self.planned):
            return None
        return clopper_pearson(0, len(self.record.runs), self.confidence)[1]


@dataclass(frozen=True)
class Scan:
    """The runs that placed the step limit, in the order made.

    Attributes
    ----------
    runs : Runs
    trials : tuple of Trial
    h_clear : float
        The largest step that passed, confirmed (0: none).
    h_fail : float or None
        The smallest step that failed (None: none failed).
    confirmed : TrialRecord or None
        The confirmation's runs at ``h_clear`` (fresh seeds, none failed).
    """

    runs: Runs
    trials: tuple[Trial, ...]
    h_clear: float
    h_fail: float | None
    confirmed: TrialRecord | None


@dataclass(frozen=True)
class EngineThermalLimit:
    """The step limit at temperature of an engine's system (module docstring; ps).

    Attributes
    ----------
    temperature, kT : float
        K and kJ/mol.
    z_star, omega_zero, h_zero : float
        The method's interval, the largest frequency at the configuration (rad/ps), and the
        0 K limit ``z* / omega_zero``.
    linear : AtTemperature
        The frequencies at the snapshots and the linear limit at temperature.
    h_max : float
    limited_by : str
    h_range : tuple of float
        ``(h_max, h_high)``: where the limit lies (the smallest failing step, or the linear
        limit at the quantile's point estimate).
    scan : Scan or None
        The runs (None when the method preserves no oscillator).
    run_length : float
        The user's run, ps.
    notes : tuple of str
    """

    temperature: float
    kT: float
    z_star: float
    omega_zero: float
    h_zero: float
    linear: AtTemperature
    h_max: float
    limited_by: str
    h_range: tuple[float, float]
    scan: Scan | None
    run_length: float
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class EngineThermalCheck:
    """The verdict on one step at temperature (ps): ``safe`` False at or above the linear
    limit at temperature, when a run at h fails, or at or above the limit ``h_max`` the
    scan of the runs gives (``limit``, as :func:`thermal_limit` finds it); ``reasons`` says
    which."""

    h: float
    safe: bool
    reasons: tuple[str, ...]
    temperature: float
    kT: float
    z_star: float
    omega_zero: float
    h_zero: float
    linear: AtTemperature
    trial: Trial | None
    runs: Runs
    run_length: float
    notes: tuple[str, ...] = ()
    limit: Scan | None = None
    h_max: float | None = None


def _stage(progress: Progress | None, stage: str) -> Callable[[float], None]:
    if progress is None:
        return lambda f: None
    return lambda f: progress(stage, f)


def sampling_spec(temperature: float, omega_zero: float) -> SamplingSpec:
    """The sampling of step 1 (module docstring) for a system whose fastest 0 K frequency is
    ``omega_zero``: step ``Z_SAMPLE / omega_zero``, the times in whole steps.

    Parameters
    ----------
    temperature : float
        K.
    omega_zero : float
        rad/ps.

    Returns
    -------
    SamplingSpec
    """
    step = Z_SAMPLE / omega_zero
    return SamplingSpec(temperature, step, FRICTION, max(1, round(THERMALISATION / step)),
                        max(1, round(SPACING / step)), FRAMES, SAMPLING_SEEDS)


def snapshot_frequencies(engine: DynamicsEngine, spec: SamplingSpec,
                         progress: Progress | None = None) -> tuple[Frequencies, Ensemble]:
    """The largest eigenvalue of the constrained mass-weighted Hessian at each snapshot of
    the engine's Langevin dynamics, with its error (Lanczos residual plus the
    finite-difference estimate), rad^2/ps^2; and the snapshots.

    Parameters
    ----------
    engine : DynamicsEngine
    spec : SamplingSpec
    progress : callable, optional
        ``progress(stage, fraction)``.

    Returns
    -------
    (Frequencies, Ensemble)
        ``lambda_max`` and ``error`` per snapshot (``lambda_min`` is not computed: nan);
        the snapshots as rows of flattened positions (nm), their chains the seeds.
    """
    frames = engine.thermal_frames(spec)
    _stage(progress, "sampling")(1.0)
    seeds, count = frames.shape[:2]
    cons = engine.constraints
    lam = np.empty(seeds * count)
    err = np.empty(seeds * count)
    step = None
    report = _stage(progress, "frequencies")
    for k, x in enumerate(frames.reshape(seeds * count, *frames.shape[2:])):
        hvp = HessianVectorProduct(engine, engine.on_constraints(x), step=step)
        if step is None:
            step = hvp.fd.step
        if len(cons):
            sp = constrained_modes(hvp, cons, k=1, tol=LANCZOS_TOL, which="largest")
        else:
            sp = extreme_eigenvalues(hvp, hvp.dim, k=1, which="largest", tol=LANCZOS_TOL,
                                     with_error=hvp.with_error, particles=hvp.particles)
        lam[k], err[k] = float(sp.eigenvalues[0]), float(sp.errors[0])
        report((k + 1) / lam.size)
    if not (np.all(np.isfinite(lam)) and np.all(np.isfinite(err))):
        raise StepsafeError("the Hessian is not finite at a thermal snapshot")
    how = ("Lanczos on finite-difference Hessian-vector products" +
           (" on the constraints' tangent space" if len(cons) else "") +
           f" (step {step:.2g} nm, chosen at the first snapshot)")
    frequencies = Frequencies(lam, np.full(lam.size, np.nan), err, how, None)
    chain = np.repeat(np.arange(seeds), count)
    kT = MOLAR_GAS_CONSTANT * spec.temperature
    sampled = (f"the engine's LangevinMiddle, seeds {', '.join(map(str, spec.seeds))}: step "
               f"{spec.step * 1000:.3g} fs, friction {spec.friction:g}/ps, "
               f"{spec.thermalisation * spec.step:.3g} ps of thermalisation, then a frame "
               f"every {spec.spacing * spec.step * 1000:.3g} fs")
    ensemble = Ensemble(frames.reshape(seeds * count, -1), chain, kT, sampled,
                        int(spec.seeds[0]), spec.step, spec.friction, spec.thermalisation,
                        spec.spacing, None, seeds)
    return frequencies, ensemble


def linear_at_temperature(engine: DynamicsEngine, temperature: float, z_star: float,
                          omega_zero: float, run_length: float,
                          progress: Progress | None = None,
                          confidence: float = 0.95) -> AtTemperature:
    """Steps 1 and 2 of the module docstring: the linear limit at temperature.

    Parameters
    ----------
    engine : DynamicsEngine
    temperature : float
        K.
    z_star : float
        The end of the method's interval from 0 on the oscillator.
    omega_zero : float
        The largest frequency at the configuration analysed, rad/ps.
    run_length : float
        The user's run, ps: ``N = run_length omega_zero / pi`` frames.
    progress : callable, optional
        ``progress(stage, fraction)``.
    confidence : float
        Of the frequency's upper bound.

    Returns
    -------
    AtTemperature
        ``h_linear = min(z* / omega_zero, z* / omega_q)`` in ps, ``omega_q`` the upper bound
        of the value a run of N frames reaches.
    """
    spec = sampling_spec(temperature, omega_zero)
    frequencies, ensemble = snapshot_frequencies(engine, spec, progress)
    run_frames = max(1.0, run_length * omega_zero / math.pi)
    omega: RunExtreme = run_extreme(frequencies.omega_max_upper, run_frames, ensemble.chain,
                                    confidence=confidence, seed=0)
    h_zero = z_star / omega_zero
    h_linear = min(h_zero, z_star / omega.upper) if omega.upper > 0 else h_zero
    return AtTemperature(h_linear, omega, frequencies, ensemble, run_frames)


def _trial(engine: DynamicsEngine, runs: Runs, h: float, seeds: tuple[int, ...], eq_step: float,
           stage: str, worker: Any = None, seeds_done: Any = None,
           confidence: float | None = None) -> Trial:
    record = engine.trials(runs.spec(h, seeds, eq_step), progress=seeds_done, worker=worker)
    passed = record.verdict(runs.tolerance) == "stable" and len(record.runs) == len(seeds)
    return Trial(h, record, passed, stage, runs.tolerance, seeds, confidence)


def scan(engine: DynamicsEngine, runs: Runs, h_linear: float, eq_step: float,
         progress: Progress | None = None, stage: str = "runs") -> Scan:
    """Step 3 of the module docstring: the largest step below ``TOP h_linear`` whose runs
    pass, confirmed in every seed (every run in one engine process).

    Parameters
    ----------
    engine : DynamicsEngine
    runs : Runs
    h_linear : float
        The linear limit at temperature, ps.
    eq_step : float
        The thermalisation's step, ps.
    progress : callable, optional
        ``progress(stage, fraction)``.
    stage : str
        The stage named to ``progress``.

    Returns
    -------
    Scan
    """
    with engine.trial_worker() as worker:
        return _scan(engine, runs, h_linear, eq_step, _stage(progress, stage), worker)


def _scan(engine: DynamicsEngine, runs: Runs, h_linear: float, eq_step: float,
          report: Callable[[float], None], worker: Any) -> Scan:
    trials: list[Trial] = []

    def attempt_at(h: float, seeds: tuple[int, ...], stage: str,
                   confidence: float | None = None) -> Trial:
        t = _trial(engine, runs, h, seeds, eq_step, stage, worker, confidence=confidence)
        trials.append(t)
        report(1.0 - 0.5 ** len(trials))
        return t

    def attempt(h: float, seeds: tuple[int, ...], stage: str) -> Trial:
        return attempt_at(h, seeds, stage)

    top = TOP * h_linear
    h_fail: float | None = None
    first = attempt(top, runs.seeds, "at the linear limit at temperature")
    clear: Trial | None = first if first.passed else None
    if clear is None:
        h_fail = top
        lo = LOW * h_linear
        for _ in range(LOWERINGS):
            t = attempt(lo, runs.seeds, "start of the bisection")
            if t.passed:
                clear = t
                break
            h_fail, lo = lo, 0.5 * lo
        if clear is None:
            return Scan(runs, tuple(trials), 0.0, h_fail, None)
        while h_fail / clear.h - 1.0 > RESOLUTION:
            t = attempt(0.5 * (clear.h + h_fail), runs.seeds, "bisection")
            if t.passed:
                clear = t
            else:
                h_fail = t.h
    # near the step where the seeds first fail a run passes or fails by chance (not at
    # one sharp step): the step given lies BACKOFF below the bisection's and is confirmed on
    # fresh seeds, enough that none failing bounds the failure probability of a run below
    # max_failure; a confirmation stops at its first failure and the step is lowered
    h = clear.h if h_fail is None else clear.h * (1.0 - BACKOFF)
    offset = 0
    for k in range(LOWERINGS):
        count = confirmations(runs.max_failure, runs.confidence, k)
        level = 1.0 - (1.0 - runs.confidence) / 2 ** (k + 1)
        seeds = confirm_seeds(runs.seeds, count, offset)
        offset += count
        c = attempt_at(h, seeds, f"confirmation {k + 1}", level)
        if c.passed:
            report(1.0)
            return Scan(runs, tuple(trials), h, h_fail, c.record)
        h_fail, h = h, h * (1.0 - BACKOFF * 2 ** (k + 1))
    return Scan(runs, tuple(trials), 0.0, h_fail, None)


def _zero(analysis, z_star: float) -> tuple[float, float]:
    """``omega_0`` (the upper end of the largest eigenvalue's error, rad/ps) and
    ``h_zero = z* / omega_0``."""
    lam = float(analysis.spectrum.eigenvalues[0]) + float(eigenvalue_errors(analysis)[0])
    if not lam > 0:
        raise StepsafeError("the configuration has no vibration (omega^2 <= 0): no analysis "
                            "at temperature")
    omega = math.sqrt(lam)
    return omega, z_star / omega


def followed(runs: Runs, run_length: float) -> bool:
    """Whether each run in the engine lasts the user's whole run (ps).

    Parameters
    ----------
    runs : Runs
    run_length : float

    Returns
    -------
    bool
    """
    return run_length <= runs.duration * (1 + 1e-12)


def _runs_note(runs: Runs, run_length: float) -> tuple[str, ...]:
    if followed(runs, run_length):
        return ()
    return (f"the runs in the engine last {runs.duration:g} ps of the run's "
            f"{run_length:.3g} ps: failures that take longer to develop are not excluded",)


def _at_temperature(analysis, runs: Runs, z_star: float, run_length: float,
                    progress: Progress | None):
    """What :func:`thermal_limit` and :func:`thermal_check` both start from: the engine, the
    0 K frequency and limit, kT (kJ/mol) and the linear limit over OpenMM's snapshots."""
    z_star = positive_finite(z_star, "z_star")
    run_length = positive_finite(run_length, "length")
    omega_zero, h_zero = _zero(analysis, z_star)
    engine = analysis.engine
    kT = MOLAR_GAS_CONSTANT * runs.temperature
    linear = linear_at_temperature(engine, runs.temperature, z_star, omega_zero, run_length,
                                   progress)
    return engine, omega_zero, h_zero, kT, linear


def thermal_limit(analysis, runs: Runs, z_star: float, run_length: float,
                  progress: Progress | None = None, engine_name: str = "engine"
                  ) -> EngineThermalLimit:
    """The largest step at temperature (module docstring).

    Parameters
    ----------
    analysis : MDAnalysis
        The 0 K analysis (:func:`stepsafe.systems.md.system.analyse`): its engine (a
        :class:`~stepsafe.systems.md.engine.DynamicsEngine`) and its largest frequency.
    runs : Runs
        The user's integrator, the temperature, seeds and durations.
    z_star : float
        The end of the method's interval from 0 on the oscillator (> 0).
    run_length : float
        The user's run, ps (how far into the frequencies' tail it reaches).
    progress : callable, optional
        ``progress(stage, fraction)``.
    engine_name : str
        For ``limited_by`` (``"OpenMM runs"``).

    Returns
    -------
    EngineThermalLimit
    """
    engine, omega_zero, h_zero, kT, linear = _at_temperature(analysis, runs, z_star,
                                                             run_length, progress)
    found = scan(engine, runs, linear.h_linear, min(0.5 * h_zero, linear.ensemble.h or h_zero),
                 progress)
    omega_point = linear.omega.estimate
    h_high = min(h_zero, z_star / omega_point) if omega_point > 0 else h_zero
    notes = list(_runs_note(runs, run_length))
    h_max = found.h_clear
    if found.h_clear >= TOP * linear.h_linear:
        limited_by = "linear at temperature"
    else:
        limited_by = f"{engine_name} runs"
        h_high = found.h_fail if found.h_fail is not None else h_high
        if found.h_clear == 0:
            notes.append(f"every run failed down to {found.trials[-1].h:.4g} ps")
    return EngineThermalLimit(runs.temperature, kT, z_star, omega_zero, h_zero, linear, h_max,
                              limited_by, (h_max, max(h_max, h_high)), found, run_length,
                              tuple(notes))


def thermal_check(analysis, runs: Runs, z_star: float, h: float, run_length: float,
                  progress: Progress | None = None) -> EngineThermalCheck:
    """Whether the step h (ps) is safe at temperature: below the linear limit at
    temperature, every run at h (the seeds and the confirmation's) passes, and h lies below
    the limit :func:`thermal_limit` gives (the scan of the runs, made only when the runs at
    h pass), so that ``check`` fails every step ``advise`` puts above its limit.

    Parameters
    ----------
    analysis, runs, z_star, run_length, progress
        As for :func:`thermal_limit` (``run_length`` at the step h).
    h : float
        The step, ps.

    Returns
    -------
    EngineThermalCheck
    """
    h = positive_finite(h, "h")
    engine, omega_zero, h_zero, kT, linear = _at_temperature(analysis, runs, z_star,
                                                             run_length, progress)
    reasons: list[str] = []
    trial = None
    if h >= linear.h_linear:
        reasons.append("above the linear limit at temperature")
    else:
        seeds = confirm_seeds(runs.seeds, confirmations(runs.max_failure, runs.confidence))
        report = _stage(progress, "step")
        trial = _trial(engine, runs, h, seeds,
                       min(0.5 * h_zero, linear.ensemble.h or h_zero), "at the step",
                       seeds_done=lambda stage, done, total: report(done / (total or 1)),
                       confidence=runs.confidence)
        found = h_max = None
        if not trial.passed:
            reasons.append(f"the runs in the engine at h: {trial_summary(trial, runs)}")
        else:
            found = scan(engine, runs, linear.h_linear,
                         min(0.5 * h_zero, linear.ensemble.h or h_zero), progress, "limit")
            h_max = found.h_clear
            if h >= h_max:
                reasons.append("at or above the largest step the runs in the engine pass "
                               "(the limit at temperature advise gives)")
        if not reasons and not followed(runs, run_length):
            reasons.append(f"the run's {run_length:.4g} ps are longer than the runs in the "
                           f"engine ({runs.duration:g} ps; at most {MAX_DURATION:g} unless "
                           "the scene's runs: duration: says): failures that take longer to "
                           "develop are not excluded")
        return EngineThermalCheck(h, not reasons, tuple(reasons), runs.temperature, kT,
                                  z_star, omega_zero, h_zero, linear, trial, runs, run_length,
                                  _runs_note(runs, run_length), found, h_max)
    return EngineThermalCheck(h, not reasons, tuple(reasons), runs.temperature, kT, z_star,
                              omega_zero, h_zero, linear, trial, runs, run_length,
                              _runs_note(runs, run_length))


def trial_summary(trial: Trial, runs: Runs) -> str:
    """One line: the verdict, which seeds failed and how, or the drift.

    Parameters
    ----------
    trial : Trial
    runs : Runs

    Returns
    -------
    str
    """
    record = trial.record
    ran = len(record.runs)
    of = f"{ran} of {len(trial.planned)} seeds" if ran < len(trial.planned) else \
        f"{ran} seeds"
    head = f"{runs.integrator}, {of} of {runs.duration:g} ps: {trial.verdict}"
    blown = [r for r in record.runs if r.blew_up]
    if blown:
        return head + " (" + "; ".join(
            f"seed {r.seed} by step {r.blowup_step}" if r.blowup_step is not None
            else f"seed {r.seed}: {r.reason}" for r in blown) + ")"
    drift, error = record.drift()
    if math.isfinite(drift):
        e = f" +- {error:.1g}" if math.isfinite(error) else ""
        return head + (f" (drift {drift:.2g}{e} kT/ps per degree of freedom, tolerance "
                       f"{runs.tolerance:g})")
    return head
