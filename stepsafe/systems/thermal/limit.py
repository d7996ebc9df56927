"""The step limit at temperature: what a hot, anharmonic system can run, not only its
linearisation at the minimum.

:func:`thermal_limit` combines

* the **0 K limit** ``h_zero = z* / omega_0``: ``z*`` the end of the method's preserved
  interval from 0 on the oscillator (:func:`stepsafe.core.regions.find_region`, under the
  chosen criterion), ``omega_0`` the largest frequency at the minimum;
* the **linear limit at temperature** ``h_linear = z* / omega_q``: ``omega_q`` the upper
  confidence bound of the largest instantaneous frequency a run of the stated length
  reaches (:mod:`.sampling`, :mod:`.inm`, :mod:`.extremes`). The run holds
  ``N = T omega_0 / pi`` independent frames for a simulated time T: one per half period of
  the fastest 0 K mode, the shortest time over which the configuration can change (so N
  is an upper bound, and the quantile a conservative one). ``h_linear`` never exceeds
  ``h_zero``;
* **resonance bands** measured on ``[LOW h_linear, TOP h_linear]`` (:mod:`.bands`; steps
  above are unsafe already, :func:`thermal_check` probes any step itself, and ``TOP`` is
  just below 1: at ``h_linear = h_zero`` the linear map itself is parabolic): the whole
  system when it has at most ``whole_up_to`` degrees of freedom; otherwise the whole system
  on a coarse uniform grid (``COARSE_POINTS`` steps, ``WHOLE_TRAJECTORIES`` trajectories)
  and 1-D profiles along the ``modes_profiled`` fastest normal modes at the minimum,
  tabulated (:func:`stepsafe.systems.thermal.potential.tabulate`, error stated). A profile
  along a mode of the minimum misses what localised thermal fluctuations do (an FPU chain
  of 100 masses fails 10% below the linear limit at temperature while the profiles of its
  fastest modes stay clear): the whole system decides;
* a **confirmation** on a fresh ensemble: ``trajectories_for(max_failure)`` thermal
  initial conditions of the whole system drawn with an independent seed
  (``seed + CONFIRM_SEED``), run at the resulting step (at ``TOP h_max`` when a linear
  limit, a supremum, sets it) with the energy tested at every step. The scan's edge is the
  largest step one sample happened to find clear, a selection that favours lucky samples;
  the fresh ensemble is not selected. When one of its trajectories fails, the step goes
  down to the next step the scan judged clear below it, by the factor ``STEP_DOWN`` at
  least, and is confirmed again, at most ``CONFIRM_TRIES`` times (``"resonance band ...
  (whole system)"``); the record states the confirming ensemble, its seed and failures.
  ``h_max`` is the step it confirmed: no step above one the fresh ensemble ran is given;
* the **drift** measured in that run (:mod:`.drift`); with a ``drift_tolerance`` the step
  is lowered, by bisection on drifts measured on the same fresh ensemble, until none of
  its trajectories fails and ``|drift| + 2 SE`` meets it (the rule :func:`thermal_check`'s
  caller applies to a step): the step given is one the fresh ensemble ran and passed.

``h_max`` is the smallest of these and ``limited_by`` says which: ``"linear at
temperature"``, ``"resonance band n:m"`` (the linear resonance point nearest to the band's
lower edge; ``"resonance band"`` when none is within 5%), ``"drift"``; at ``kT = 0`` the
answer is exactly the 0 K one (``"0 K"``) and nothing is sampled.

:func:`thermal_check` judges one step: UNSAFE above the linear limit at temperature, or
when an ensemble of ``trajectories_for(max_failure)`` trajectories (the whole system, and
for large systems the profiles too) at that very step has a failure or cannot show the
failure probability below ``max_failure`` (:func:`.bands.judge`). The whole system's
ensemble is drawn as :func:`thermal_limit`'s confirmation (seed ``seed + CONFIRM_SEED``):
at the step ``advise`` gives, the check runs the trajectories that confirmed it.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from stepsafe.core.accuracy import errors
from stepsafe.core.regions import find_region, under_criterion, validate_criterion
from stepsafe.core.resonances import DEFAULT_ORDERS, nonlinear_resonances, validate_orders
from stepsafe.exceptions import StepsafeError, finite_real, positive_finite
from stepsafe.methods.tableaux import Method
from stepsafe.systems.thermal import bands as bands_
from stepsafe.systems.thermal.drift import Drift, from_outcome
from stepsafe.systems.thermal.extremes import RunExtreme, run_extreme
from stepsafe.systems.thermal.inm import Frequencies, frequencies, modes
from stepsafe.systems.thermal.potential import (
    Potential,
    Tabulated,
    mode_direction,
    profile,
    tabulate,
)
from stepsafe.systems.thermal.sampling import (
    Ensemble,
    draw,
    exits,
    minimum_modes,
    one_dimensional,
)
from stepsafe.systems.thermal.trajectories import (
    DISTANCE,
    GROWTH,
    Start,
    run,
    thermal_start,
)

#: The band scan starts at this fraction of the linear limit at temperature.
LOW = 0.35
#: ... and ends at this fraction of it.
TOP = 0.999
#: Steps per trajectory at most in band scans and drift measurements: a run of up to this
#: many steps is followed for its whole length (memory does not grow with the steps: the
#: trajectories are streamed, see :mod:`stepsafe.core.ensemble`); a longer one is followed
#: this far, and the analysis says so.
BAND_STEPS = 10_000
FRAMES = 1000
TRAJECTORIES = 500
#: Systems with at most this many degrees of freedom are integrated whole.
WHOLE_UP_TO = 16
#: Larger systems: profiles along this many of the fastest modes, and the whole system on
#: a coarse uniform grid of this many steps with this many trajectories (a profile along a
#: mode at the minimum misses what localised thermal fluctuations do).
MODES = 3
COARSE_POINTS = 12
WHOLE_TRAJECTORIES = 300
#: Resonance orders whose points refine the band grid (orders 3 and 4: Verlet's 3:1 and
#: 4:1 at z = sqrt 3 and sqrt 2 are the ones a thermal run meets).
ORDERS = (3, 4)
#: Drift tolerance is met when ``|drift| + SIGMAS * SE`` is within it.
SIGMAS = 2.0
#: The confirming ensemble's seed is the analysis's seed plus this.
CONFIRM_SEED = 1000
#: Confirmations tried at most, stepping down after each that sees a failure ...
CONFIRM_TRIES = 24
#: ... to the next step the scan judged clear below, but by this factor at least.
STEP_DOWN = 0.97


@dataclass(frozen=True)
class ZeroKelvin:
    """The 0 K answer: ``h_zero = z_star / omega_zero``."""

    z_star: float
    omega_zero: float
    h_zero: float
    criterion: str
    resonances: tuple[tuple[float, str], ...]
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class AtTemperature:
    """The linear limit at temperature and what it rests on."""

    h_linear: float
    omega: RunExtreme
    frequencies: Frequencies
    ensemble: Ensemble
    run_frames: float


@dataclass(frozen=True)
class Confirmation:
    """The fresh ensemble at the advised step.

    Attributes
    ----------
    h : float
        The step confirmed (0 when none was).
    max_failure, confidence : float
        The failure probability it must show to be exceeded with at most ``1 - confidence``
        probability.
    trajectories, steps, seed : int
        The ensemble: its size, steps per trajectory and seed (independent of the scan's).
    failures : int
        At h.
    upper : float
        The one-sided upper bound on the failure probability at h.
    rejected : tuple of (float, int, int)
        The steps above h tried first: each with the failures seen when its run stopped
        (at its first failure) and the step by which it was seen.
    """

    h: float
    max_failure: float
    confidence: float
    trajectories: int
    steps: int
    seed: int
    failures: int
    upper: float
    rejected: tuple[tuple[float, int, int], ...] = ()


@dataclass(frozen=True)
class ThermalLimit:
    """The step limit at temperature (module docstring).

    Attributes
    ----------
    kT : float
    h_max : float
        The limit.
    limited_by : str
        ``"0 K"``, ``"linear at temperature"``, ``"resonance band ..."`` or ``"drift"``.
    zero : ZeroKelvin
        The 0 K answer.
    h_range : tuple of float
        ``(h_max, h_high)``: where the limit itself lies at the stated confidence. For the
        linear limit ``h_high = z* / omega`` at the quantile's point estimate; for a band,
        the nearest step judged in the band; for the drift, the smallest step found to
        exceed the tolerance; inf where no such step was measured; ``h_max`` at 0 K.
    h_linear : float or None
        The linear limit at temperature.
    h_band : float or None
        The clear side of the lowest band's lower edge (None: no band below ``h_linear``).
    h_drift : float or None
        The step the drift tolerance allows, when it was given.
    linear : AtTemperature or None
    scans : tuple of BandScan
    tables : tuple of Tabulated
        The tabulated profiles behind profile scans.
    drift : Drift or None
        Of the whole system at ``h_max`` (the step confirmed).
    run_steps, run_length : float or None
        The run as stated.
    seed : int
    notes : tuple of str
    confirmation : Confirmation or None
        The fresh ensemble that confirmed ``h_max`` (None at 0 K).
    """

    kT: float
    h_max: float
    limited_by: str
    zero: ZeroKelvin
    h_range: tuple[float, float]
    h_linear: float | None = None
    h_band: float | None = None
    h_drift: float | None = None
    linear: AtTemperature | None = None
    scans: tuple[bands_.BandScan, ...] = ()
    tables: tuple[Tabulated, ...] = ()
    drift: Drift | None = None
    run_steps: float | None = None
    run_length: float | None = None
    seed: int = 0
    notes: tuple[str, ...] = ()
    confirmation: Confirmation | None = None


@dataclass(frozen=True)
class ThermalCheck:
    """The verdict at one step: ``safe`` False above ``h_linear`` or where a probe at h is
    not clear; ``reasons`` says which."""

    h: float
    safe: bool
    reasons: tuple[str, ...]
    kT: float
    zero: ZeroKelvin
    linear: AtTemperature | None
    probes: tuple[tuple[str, bands_.Probe], ...]
    drift: Drift | None
    seed: int


def zero_kelvin(method: Method, pot: Potential, criterion: str = "structure",
                orders: tuple[int, ...] = DEFAULT_ORDERS) -> ZeroKelvin:
    """``z*``, ``omega_0`` and ``h_zero = z* / omega_0`` for the method on the potential's
    minimum, with the method's linear resonance points (as z) of the given orders and of
    the default ones (those name bands; the given ones refine band grids)."""
    criterion = validate_criterion(criterion)
    region = under_criterion(find_region(method, "oscillator"), criterion)
    notes = []
    z_star = region.first_boundary
    if z_star is None:
        z_star = region.zmax
        notes.append(f"the method is stable up to z = {z_star:g} (the analysed range); "
                     f"that z is taken as its limit")
    found = minimum_modes(pot)
    # a difference Hessian's eigenvalue may lie anywhere within its error: the upper end
    top = float(found.eigenvalues[-1]) + (0.0 if pot.has_hessian else found.error)
    omega = math.sqrt(top)
    every = tuple(sorted(set(orders) | set(DEFAULT_ORDERS)))
    res = tuple((r.z, r.name) for r in nonlinear_resonances(method, region, every)) \
        if z_star > 0 else ()
    return ZeroKelvin(float(z_star), omega, float(z_star) / omega, criterion, res,
                      tuple(notes))


def rho_function(method: Method, omega_ref: float, h_top: float) -> Callable[[np.ndarray],
                                                                            np.ndarray]:
    """``h -> max_{z <= h omega_ref} (1 + e_energy(z))``: the largest energy ratio of the
    method's invariant ellipse over the frequencies up to ``omega_ref`` (inf beyond the
    elliptic interval), on a grid of 1024 z up to ``h_top omega_ref``."""
    z_top = h_top * omega_ref
    z = np.linspace(0.0, z_top, 1025)[1:]
    with np.errstate(all="ignore"):
        r = 1.0 + errors(method, z).energy
    r = np.where(np.isfinite(r), r, np.inf)
    r = np.maximum.accumulate(r)

    def rho(h: np.ndarray) -> np.ndarray:
        zz = np.asarray(h, dtype=float) * omega_ref
        i = np.clip(np.searchsorted(z, zz, side="left"), 0, z.size - 1)
        return np.where(zz <= z_top, r[i], np.inf)

    return rho


def _run_time(h: float, length: float | None, steps: float | None) -> float:
    """The run's simulated time: ``length``, else ``steps h``."""
    if length is not None:
        return float(length)
    if steps is None:
        raise StepsafeError("give the run's length (simulated time) or its number of steps")
    return float(steps) * h


def run_steps(h: float, length: float | None, steps: float | None) -> int:
    """The run's number of steps at step ``h``: ``steps`` rounded up, else ``length / h``
    rounded up (a quotient within a few rounding errors of an integer counts as it)."""
    if steps is not None:
        return math.ceil(float(steps))
    ratio = _run_time(h, length, steps) / h
    return math.ceil(ratio * (1.0 - 4.0 * sys.float_info.epsilon))


def _validate_run(length, steps) -> tuple[float | None, float | None]:
    if (length is None) == (steps is None):
        raise StepsafeError("give the run's length (simulated time) or its number of steps, "
                            "one of them")
    if length is not None:
        return positive_finite(length, "length"), None
    return None, positive_finite(steps, "steps")


def at_temperature(pot: Potential, kT: float, zero: ZeroKelvin, length: float | None,
                   steps: float | None, frames: int = FRAMES, seed: int = 0,
                   confidence: float = 0.95) -> AtTemperature:
    """The linear limit at temperature ``z* / omega_q`` (module docstring), never above
    ``h_zero``."""
    ensemble = draw(pot, kT, frames, seed)
    freq = frequencies(pot, ensemble.q)
    run_frames = max(1.0, _run_time(zero.h_zero, length, steps) * zero.omega_zero / math.pi)
    omega = run_extreme(freq.omega_max_upper, run_frames, ensemble.chain,
                        confidence=confidence, seed=seed)
    h_linear = min(zero.h_zero, zero.z_star / omega.upper) if omega.upper > 0 else 0.0
    return AtTemperature(h_linear, omega, freq, ensemble, run_frames)


@dataclass(frozen=True)
class _Target:
    """One thing to integrate: the whole system or a profile, with its start, the 0 K
    frequencies whose resonance points name its bands (and refine its grid unless it is
    coarse) and the largest of them."""

    name: str
    potential: Potential
    start: Start
    omega: float
    modes: tuple[float, ...]
    grid_points: int
    refine: bool = True
    table: Tabulated | None = None
    notes: tuple[str, ...] = ()


def _targets(pot: Potential, kT: float, ensemble: Ensemble, trajectories: int, seed: int,
             whole_up_to: int, count_modes: int, grid_points: int,
             whole_trajectories: int = WHOLE_TRAJECTORIES,
             whole: Start | None = None) -> list[_Target]:
    """The whole system when small; else the whole system on a coarse grid (with
    ``whole_trajectories``) and 1-D profiles along the fastest modes, tabulated. The whole
    system starts from ``whole`` when given (else from the ensemble's configurations)."""
    found = minimum_modes(pot)
    omegas = tuple(float(w) for w in found.omegas)
    if pot.dimension <= whole_up_to:
        start = whole if whole is not None else _start_from(pot, kT, ensemble, trajectories,
                                                            seed)
        return [_Target("whole system", pot, start, omegas[-1], omegas, grid_points)]
    fastest = modes(pot, pot.minimum, count=count_modes)
    start = whole if whole is not None else _start_from(pot, kT, ensemble, whole_trajectories,
                                                        seed)
    out = [_Target("whole system (coarse grid)", pot, start, omegas[-1],
                   tuple(float(w) for w in fastest.omegas), COARSE_POINTS, refine=False)]
    for j in range(fastest.eigenvalues.size - 1, -1, -1):
        omega = math.sqrt(max(float(fastest.eigenvalues[j]), 0.0))
        if omega <= 0:
            continue
        d = mode_direction(pot, fastest.vectors[:, j])
        name = f"profile along the mode of omega = {omega:.6g}"
        prof = profile(pot, pot.minimum, d, name)
        s_seed = seed + 1 + len(out)
        s, notes = one_dimensional(prof, kT, trajectories, np.random.default_rng(s_seed))
        half = 1.05 * DISTANCE * float(np.max(np.abs(s)))
        table = tabulate(prof, -half, half)
        if not math.isfinite(table.error):
            raise StepsafeError(f"the {name} is not finite within {half:.6g} of the minimum")
        start = thermal_start(table.potential, kT, trajectories, s_seed, s,
                              "exact 1-D (inverse distribution function)", exits(prof, kT))
        notes += (f"{name}: tabulated on [{-half:.6g}, {half:.6g}], force within "
                  f"{table.relative_error:.2g} of its largest value",)
        out.append(_Target(name, table.potential, start, omega, (omega,), grid_points,
                           table=table, notes=notes))
    return out


def _start_from(pot: Potential, kT: float, ensemble: Ensemble, count: int, seed: int) -> Start:
    """``count`` initial conditions from the ensemble's configurations (evenly spread over
    it; drawn afresh when it has fewer)."""
    if ensemble.size >= count:
        pick = np.linspace(0, ensemble.size - 1, count).round().astype(int)
        return thermal_start(pot, kT, count, seed, ensemble.q[pick], ensemble.how)
    return thermal_start(pot, kT, count, seed + 1)


def thermal_limit(method: Method, pot: Potential, kT: float, *, length: float | None = None,
                  steps: float | None = None, criterion: str = "structure",
                  orders: tuple[int, ...] = ORDERS, frames: int = FRAMES,
                  trajectories: int = TRAJECTORIES, band_steps: int = BAND_STEPS,
                  threshold: float = bands_.THRESHOLD, confidence: float = bands_.CONFIDENCE,
                  grid_points: int = bands_.GRID_POINTS, bisections: int = bands_.BISECTIONS,
                  drift_tolerance: float | None = None, whole_up_to: int = WHOLE_UP_TO,
                  modes_profiled: int = MODES, seed: int = 0,
                  max_failure: float = bands_.MAX_FAILURE,
                  progress: Callable[[str, float], None] | None = None) -> ThermalLimit:
    """The largest step at temperature (module docstring).

    Parameters
    ----------
    method : Method
    pot : Potential
        With its minimum.
    kT : float
        Thermal energy in the potential's unit (0: the 0 K answer).
    length, steps : float
        The user's run: simulated time, or number of steps (at ``h_zero``: more frames
        than at any smaller step). One of them (not needed at kT = 0).
    criterion : str
        ``structure`` or ``stability`` (for ``z*``).
    orders : tuple of int
        Resonance orders whose points refine the band grid.
    frames : int
        Thermal configurations for the frequency distribution.
    trajectories : int
        Per step h in band scans.
    band_steps : int
        Steps per trajectory at most (fewer when the run is shorter).
    threshold, confidence : float
        The scans screen for steps whose failure probability is not shown below
        ``threshold`` (one-sided bounds at ``confidence``); also the confidence of the
        frequency bound.
    grid_points, bisections : int
        The uniform grid's size and the halvings of each band edge.
    drift_tolerance : float, optional
        Largest acceptable ``|drift|`` (energy per unit time, whole system).
    whole_up_to : int
        Integrate the whole system up to this many degrees of freedom.
    modes_profiled : int
        Profiles along this many fastest modes beyond that.
    seed : int
        Seed of every draw (stated in the record); the confirmation's is
        ``seed + CONFIRM_SEED``.
    max_failure : float
        The largest acceptable failure probability of a run: the confirmation runs
        ``trajectories_for(max_failure)`` trajectories and needs every one to survive.
    progress : callable, optional
        ``progress(stage, fraction)``.

    Returns
    -------
    ThermalLimit
    """
    m_confirm = bands_.trajectories_for(max_failure, confidence)
    kT = finite_real(kT, "kT")
    if kT < 0:
        raise StepsafeError(f"kT must not be negative, got {kT}")
    orders = validate_orders(orders)
    zero = zero_kelvin(method, pot, criterion, orders)
    if kT == 0 or zero.h_zero == 0:
        return ThermalLimit(kT, zero.h_zero, "0 K", zero, (zero.h_zero, zero.h_zero), seed=seed,
                            notes=("the method preserves no oscillator",) if
                            zero.h_zero == 0 else ())
    length, steps = _validate_run(length, steps)
    report = (lambda stage: (lambda f: progress(stage, f))) if progress else (
        lambda stage: None)
    linear = at_temperature(pot, kT, zero, length, steps, max(frames, 1), seed, confidence)
    notes: list[str] = list(zero.notes) + list(linear.ensemble.notes)
    h_lo = LOW * linear.h_linear
    h_hi = TOP * linear.h_linear
    n_steps = int(min(band_steps, run_steps(h_lo, length, steps)))
    n_steps = max(n_steps, 2)
    targets = _targets(pot, kT, linear.ensemble, trajectories, seed, whole_up_to,
                       modes_profiled, grid_points)
    for t in targets:
        notes += t.notes
    scans = []
    ratio = max(1.0, linear.omega.upper / zero.omega_zero)
    for t in targets:
        points = [(z / w, f"{name}" + (f" of the mode of omega = {w:.6g}"
                                       if len(t.modes) > 1 else ""))
                  for z, name in zero.resonances for w in t.modes]
        points = [(h, name) for h, name in points if h_lo / 1.05 <= h <= 1.05 * h_hi]
        refine = [h for h, name in points if t.refine and int(name.split(":")[0]) in orders]
        hs = bands_.grid(h_lo, h_hi, t.grid_points, refine)
        rho = rho_function(method, t.omega * ratio, h_hi)
        scans.append(bands_.scan(method, t.potential, t.start, hs, n_steps, rho, threshold,
                                 confidence, bisections, points, t.name,
                                 progress=report(f"bands ({t.name})")))
    h_band = None
    band_name = ""
    band_top = math.inf
    for sc in scans:
        if not sc.bands:
            continue
        edge = sc.clear_up_to
        first = sc.bands[0].lower
        if edge is None:
            edge = 0.0
            notes.append(f"{sc.target}: unsafe from the scan's first step "
                         f"{sc.h_range[0]:.6g} on; smaller steps were not scanned")
        if h_band is None or edge < h_band:
            h_band, band_name = edge, sc.bands[0].name
            band_top = first.band if first is not None and first.band is not None \
                else math.inf
    omega_point = linear.omega.estimate
    h_high = min(zero.h_zero, zero.z_star / omega_point) if omega_point > 0 else math.inf
    h_max, limited_by = linear.h_linear, "linear at temperature"
    if h_band is not None and h_band < h_max:
        h_max, h_high = h_band, band_top
        limited_by = "resonance band" + (f" {band_name}" if band_name != "unnamed" else "")
    # the whole system at h_max on a fresh ensemble, every step's energy: a confirmation
    # that it is clear of failures (else the next clear step below), and its drift
    fresh = thermal_start(pot, kT, m_confirm, seed + CONFIRM_SEED)
    rho_whole = rho_function(method, zero.omega_zero * ratio, h_hi)
    drift, h_drift, confirmation = None, None, None
    if h_max > 0:
        # a linear limit is a supremum: the run goes at the scan's last step below it
        at = h_max if limited_by.startswith("resonance") else TOP * h_max
        at, drift, confirmation = _confirm(method, pot, fresh, at, scans, n_steps,
                                           rho_whole, max_failure, confidence,
                                           report("confirmation"))
        lowered = bool(confirmation.rejected)
        h_max = at  # the answer is a step the fresh ensemble ran (TOP below a linear limit)
        if lowered:
            h_high = math.inf
            near = bands_.names_near(
                [(z / w, f"{name}" + (f" of the mode of omega = {w:.6g}"
                                       if len(targets[0].modes) > 1 else ""))
                 for z, name in zero.resonances for w in targets[0].modes], h_max, h_max)
            limited_by = "resonance band" + (f" {near[0]}" if near else "") + \
                " (whole system)"
            where = (f"above h = {h_max:.6g}" if h_max > 0 else
                     f"at every step tried ({len(confirmation.rejected)} steps)")
            notes.append(f"the whole system fails {where}: a fresh ensemble "
                         f"(seed {fresh.seed}) saw failures at "
                         + ", ".join(f"h = {x:.6g} ({k} of {m_confirm} by step {n})"
                                     for x, k, n in confirmation.rejected))
        if drift_tolerance is not None and h_max > 0:
            tol = positive_finite(drift_tolerance, "drift_tolerance")
            if drift is None or not drift.bound(SIGMAS) <= tol:
                # bisected on the fresh ensemble itself: the step given has its m
                # trajectories clear of failures and its drift bound within tol, the rule
                # a check of that step applies
                h_drift, h_high, drift = _drift_limit(method, pot, fresh, h_lo * 0.25, h_max,
                                                      n_steps, rho_whole, tol, bisections)
                h_max, limited_by = h_drift, "drift"
                confirmation = dataclasses.replace(
                    confirmation, h=h_drift, trajectories=drift.trajectories,
                    steps=drift.steps, failures=drift.failed,
                    upper=bands_.clopper_pearson(drift.failed, drift.trajectories,
                                                 confidence)[1])
    return ThermalLimit(kT, h_max, limited_by, zero, (h_max, max(h_max, h_high)),
                        linear.h_linear, h_band, h_drift, linear, tuple(scans),
                        tuple(t.table for t in targets if t.table is not None), drift, steps,
                        length, seed, tuple(notes), confirmation)


def _confirm(method: Method, pot: Potential, start: Start, h: float,
             scans: list[bands_.BandScan], steps: int, rho, max_failure: float,
             confidence: float, progress: Callable[[float], None] | None = None
             ) -> tuple[float, Drift | None, Confirmation]:
    """The fresh ensemble ``start`` at h with the energy tested at every step, stopped
    at its first failure; while one of its trajectories fails (or its bound is not below
    ``max_failure``), the next step
    below that the scan judged clear, ``STEP_DOWN`` times the step at least, at most
    ``CONFIRM_TRIES`` steps: ``(h, drift, confirmation)``, h = 0 and no drift when none
    was clear. Each try runs first the trajectories that failed in the tries before it,
    then the others from the most energy to the least: the order changes what a
    rejection costs, not which steps are rejected."""
    clear = sorted({p.h for p in scans[0].probes if p.clear}, reverse=True)
    rejected: list[tuple[float, int, int]] = []
    x = h
    suspects: list[int] = []  # the trajectories that failed at the steps above, latest first
    # then the hottest starts: escapes and resonant growth come first to the trajectories
    # with the most energy (the rows that failed the 100-dof chain's rejected steps ranked
    # 9th to 384th of 2995 by energy)
    with np.errstate(all="ignore"):
        heat = pot.energy(start.q) + 0.5 * np.sum(start.p ** 2 / pot.masses[None, :], axis=1)
    hottest = [int(i) for i in np.argsort(-np.nan_to_num(heat, nan=np.inf), kind="stable")]
    for _ in range(CONFIRM_TRIES):
        # one failure settles a step (it is not clear): the run stops there; the
        # trajectories that failed above run first (at a step just below they often fail
        # again, and the rejection then costs a block, not a run)
        out = run(method, pot, start, [x], steps, rho(np.array([x])), GROWTH, DISTANCE,
                  stop_failures=1, first=suspects + [i for i in hottest if i not in
                                                     set(suspects)],
                  progress=progress)[0]
        suspects = list(out.failed) + [i for i in suspects if i not in out.failed]
        pr = bands_.judge(out, max_failure, confidence)
        if pr.clear:
            return x, from_outcome(out, start.kT, pot.dimension, start.seed), Confirmation(
                x, max_failure, confidence, pr.trajectories, pr.steps, start.seed,
                pr.failures, pr.upper, tuple(rejected))
        rejected.append((x, pr.failures, pr.steps))
        below = [c for c in clear if c < x]
        x = max(below[0], STEP_DOWN * x) if below else STEP_DOWN * x
    return 0.0, None, Confirmation(0.0, max_failure, confidence, start.size, steps,
                                   start.seed, 0, 1.0, tuple(rejected))


def _drift(method: Method, pot: Potential, start: Start, h: float, steps: int, rho) -> Drift:
    out = run(method, pot, start, [h], steps, rho(np.array([h])), GROWTH, DISTANCE)[0]
    return from_outcome(out, start.kT, pot.dimension, start.seed)


def _drift_limit(method: Method, pot: Potential, start: Start, lo: float, hi: float,
                 steps: int, rho, tol: float, rounds: int) -> tuple[float, float, Drift]:
    """The largest h in ``[lo, hi]`` found by bisection whose drift bound meets ``tol`` (none
    of the start's trajectories failing: :meth:`Drift.bound`), the smallest found not to,
    and the drift at the first."""
    low = _drift(method, pot, start, lo, steps, rho)
    if not low.bound(SIGMAS) <= tol:
        raise StepsafeError(f"the drift at h = {lo:.6g} already exceeds the tolerance "
                            f"{tol:.6g} ({low.rate:.3g} +- {low.error:.2g})")
    best = low
    for _ in range(rounds):
        mid = 0.5 * (lo + hi)
        d = _drift(method, pot, start, mid, steps, rho)
        if d.bound(SIGMAS) <= tol:
            lo, best = mid, d
        else:
            hi = mid
    return lo, hi, best


def _stage(progress: Callable[[str, float], None] | None, stage: str
           ) -> Callable[[float], None] | None:
    """``fraction -> progress(stage, fraction)`` (None without a progress)."""
    if progress is None:
        return None

    def report(fraction: float) -> None:
        progress(stage, fraction)
    return report


def thermal_check(method: Method, pot: Potential, kT: float, h: float, *,
                  length: float | None = None, steps: float | None = None,
                  criterion: str = "structure", frames: int = FRAMES,
                  trajectories: int | None = None, band_steps: int = BAND_STEPS,
                  max_failure: float = bands_.MAX_FAILURE,
                  confidence: float = bands_.CONFIDENCE,
                  whole_up_to: int = WHOLE_UP_TO, modes_profiled: int = MODES,
                  seed: int = 0,
                  progress: Callable[[str, float], None] | None = None) -> ThermalCheck:
    """Whether the step h is safe at temperature: not above the linear limit at
    temperature and clear of failures at h itself: every target probed at h (with the
    same conventions as :func:`thermal_limit`) loses none of its trajectories and so shows
    the failure probability below ``max_failure`` at ``confidence``. At ``kT = 0``:
    ``h < h_zero``.

    Parameters
    ----------
    method, pot, kT, length, steps, criterion, frames, band_steps, confidence,
    whole_up_to, modes_profiled, seed
        As for :func:`thermal_limit` (``steps`` here at the step h).
    h : float
        The step.
    trajectories : int, optional
        Per target (default ``trajectories_for(max_failure)``, the fewest that can show
        the failure probability below it).
    max_failure : float
        The largest acceptable failure probability.
    progress : callable, optional
        ``progress(stage, fraction)``, one stage per target probed.

    Returns
    -------
    ThermalCheck
    """
    h = positive_finite(h, "h")
    count = bands_.trajectories_for(max_failure, confidence) if trajectories is None \
        else int(trajectories)
    kT = finite_real(kT, "kT")
    if kT < 0:
        raise StepsafeError(f"kT must not be negative, got {kT}")
    zero = zero_kelvin(method, pot, criterion, ORDERS)
    if kT == 0:
        safe = h < zero.h_zero
        return ThermalCheck(h, safe, () if safe else ("above the 0 K limit",), kT, zero, None,
                            (), None, seed)
    length, steps = _validate_run(length, steps)
    run_length = _run_time(h, length, steps)
    linear = at_temperature(pot, kT, zero, run_length, None, frames, seed, confidence)
    reasons = []
    if h >= linear.h_linear:
        reasons.append("above the linear limit at temperature")
    n_steps = max(2, int(min(band_steps, run_steps(h, length, steps))))
    # the whole system from the very initial conditions advise confirms its answer on: at
    # the step advise gives, check runs the trajectories that confirmed it
    targets = _targets(pot, kT, linear.ensemble, count, seed, whole_up_to,
                       modes_profiled, bands_.GRID_POINTS, count,
                       thermal_start(pot, kT, count, seed + CONFIRM_SEED))
    ratio = max(1.0, linear.omega.upper / zero.omega_zero)
    probes = []
    for t in targets:
        rho = float(rho_function(method, t.omega * ratio, h)(np.array([h]))[0])
        if not math.isfinite(rho):
            # above the linear limit at temperature (unsafe already) the bound of the
            # largest thermal frequency is infinite and nothing but overflow would count
            # as a failure: the probe uses the minimum's frequency, to say what runs do
            rho = float(rho_function(method, t.omega, h)(np.array([h]))[0])
        pr = bands_.probe(method, t.potential, t.start, h, n_steps, rho, max_failure,
                          confidence, progress=_stage(progress, f"probe ({t.name})"))
        probes.append((t.name, pr))
        if not pr.clear:
            what = {"band": "in a resonance band", "failures observed": "failures observed",
                    }.get(pr.verdict, "failures not excluded")
            reasons.append(f"{what} ({t.name}: {pr.failures} of {pr.trajectories} "
                           f"trajectories failed in {pr.steps} steps; failure probability "
                           f"up to {pr.upper:.2g} at {confidence:.0%} confidence, "
                           f"max_failure {max_failure:g})")
    _, pr = probes[0]  # the whole system's
    drift = Drift(h, pr.drift, pr.drift_error, pr.fluctuation, kT, pot.dimension,
                  pr.trajectories, pr.failures, pr.steps, targets[0].start.seed)
    return ThermalCheck(h, not reasons, tuple(reasons), kT, zero, linear, tuple(probes), drift,
                        seed)
