"""Ensembles of trajectories of a method's own map on a potential, many steps at once.

One run advances ``m`` thermal initial conditions at each of ``k`` steps h together, as
``k m`` rows of one array, through :class:`stepsafe.core.integrator.Engine` (the method's
nonlinear map; h is a column, one value per row). At every step it

* measures the exact energy ``H = U(q) + p^T M^-1 p / 2`` of every row (on the processor's
  output for a processed method) and accumulates, per row, ``sum dH``, ``sum n dH`` and
  ``sum dH^2`` with ``dH = H_n - H_0`` (every step, never a stride: a stride can alias with
  the rotation of the map);
* marks a row **failed** (and drops it) when its state is not finite, when a coordinate
  leaves ``q_ref +- distance * sqrt(rho) * extent`` (``extent`` the largest ``|q - q_ref|``
  of each coordinate over the initial conditions), or when ``H_n - U_ref`` exceeds
  ``growth * rho^2 * (H_0 - U_ref)``. ``rho`` is the largest ratio of the energy along the
  invariant ellipse of the method's linear map (``1 + e_energy``, see
  :mod:`stepsafe.core.accuracy`) over the frequencies the ensemble meets at that h: a
  linear map never exceeds ``rho`` per mode and ``rho^2`` when modes share energy, and its
  ellipse reaches ``sqrt(rho)`` times further in q than the exact orbit of the same energy
  (Verlet near its limit: ``rho = 1 / (1 - z^2/4)``); beyond ``growth`` (``distance``)
  times that the energy (coordinate) is not the bounded oscillation of a stable map.
  An implicit method whose stage iteration fails on some rows fails those rows (found by
  halving the batch).

The energy error of surviving row i is fitted by a line in the step number n (least
squares over n = 1..N, from the three sums): its slope per unit time is ``b_i / h``; the
drift at h is the mean over rows and its standard error ``std(b_i / h) / sqrt(rows)`` (the
rows are independent); the fluctuation is the root mean square over rows of each row's
standard deviation of ``dH`` over time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from stepsafe.core.integrator import Engine, SolverFailure
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method, Processed
from stepsafe.systems.thermal.potential import Potential, system_of
from stepsafe.systems.thermal.sampling import draw, momenta

#: Energy beyond ``GROWTH rho^2`` times the initial energy (above U_ref) is a failure.
GROWTH = 4.0
#: A coordinate beyond ``DISTANCE`` times the initial ensemble's extent is a failure.
DISTANCE = 10.0


@dataclass(frozen=True)
class Start:
    """Thermal initial conditions: configurations from the Boltzmann distribution, momenta
    ``N(0, kT M)`` (every energy and phase).

    Attributes
    ----------
    q, p : ndarray
        ``(m, n)``.
    kT : float
    reference : ndarray
        ``q_ref`` (n,), the minimum.
    energy_reference : float
        ``U_ref = U(q_ref)``.
    extent : ndarray
        The largest ``|q - q_ref|`` of each coordinate over the start ``(n,)``.
    seed : int
    how : str
        How the configurations were drawn.
    """

    q: np.ndarray
    p: np.ndarray
    kT: float
    reference: np.ndarray
    energy_reference: float
    extent: np.ndarray
    seed: int
    how: str

    @property
    def size(self) -> int:
        return int(self.q.shape[0])


def thermal_start(pot: Potential, kT: float, count: int, seed: int = 0,
                  configurations: np.ndarray | None = None, how: str = "") -> Start:
    """``count`` thermal initial conditions: configurations drawn by
    :func:`stepsafe.systems.thermal.sampling.draw` with ``seed`` (or the given ones),
    momenta from ``default_rng((seed, 1))``.

    Parameters
    ----------
    pot : Potential
        With its minimum.
    kT : float
    count : int
    seed : int
    configurations : ndarray, optional
        ``(count, n)`` configurations already drawn.
    how : str
        How those were drawn.

    Returns
    -------
    Start
    """
    if pot.minimum is None:
        raise StepsafeError("the thermal analysis needs the potential's minimum")
    if configurations is None:
        ensemble = draw(pot, kT, count, seed)
        q, how = ensemble.q[:count], ensemble.how
    else:
        q = np.asarray(configurations, dtype=float)
    p = momenta(pot, kT, q.shape[0], np.random.default_rng((seed, 1)))
    q0 = pot.minimum
    extent = np.max(np.abs(q - q0[None, :]), axis=0)
    extent = np.where(extent > 0, extent, np.sqrt(kT / pot.masses))
    U0 = float(pot.energy(q0[None, :])[0])
    return Start(q, p, float(kT), q0, U0, extent, seed, how)


@dataclass(frozen=True)
class Outcome:
    """What the ensemble did at one step h.

    Attributes
    ----------
    h : float
    trajectories, failures : int
    steps : int
        Steps every surviving trajectory ran.
    drift, drift_error : float
        Mean energy drift per unit time over the survivors and its standard error (NaN
        with fewer than 2 survivors).
    fluctuation : float
        Root mean square over survivors of the standard deviation of ``H_n - H_0``.
    """

    h: float
    trajectories: int
    failures: int
    steps: int
    drift: float
    drift_error: float
    fluctuation: float


def run(method: Method, pot: Potential, start: Start, h_values, steps: int,
        rho, growth: float = GROWTH, distance: float = DISTANCE, energy_every: int = 1,
        progress: Callable[[float], None] | None = None) -> list[Outcome]:
    """Run the start at every h for ``steps`` steps (module docstring).

    Parameters
    ----------
    method : Method
    pot : Potential
    start : Start
    h_values : array_like
        The steps (k,).
    steps : int
    rho : array_like
        The energy-ratio bound at each h (k,) (see the module docstring).
    growth, distance : float
        The failure thresholds.
    energy_every : int
        Measure the energy every this many steps (and at the last). Above 1 the energy
        test runs only there and no drift is measured (``drift`` NaN): for band scans,
        where the energy costs as much as the force.
    progress : callable, optional
        Called with the fraction of steps done.

    Returns
    -------
    list of Outcome
        One per h, in the order given.
    """
    h_values = np.atleast_1d(np.asarray(h_values, dtype=float))
    rho = np.broadcast_to(np.asarray(rho, dtype=float), h_values.shape)
    steps = int(steps)
    if steps < 2:
        raise StepsafeError(f"at least 2 steps are needed, got {steps}")
    every = max(1, int(energy_every))
    k, m = h_values.size, start.size
    system = system_of(pot)
    engine = Engine(method, system)
    processed = isinstance(method, Processed)
    U_ref = start.energy_reference
    H0 = np.tile(system.energy(start.q, start.p), k)
    q = np.tile(start.q, (k, 1))
    p = np.tile(start.p, (k, 1))
    which = np.repeat(np.arange(k), m)
    with np.errstate(invalid="ignore"):  # (inf rho times a zero energy: no limit)
        limit = growth * np.repeat(rho, m) ** 2 * np.maximum(H0 - U_ref, 0.0)
    limit = np.where(np.isnan(limit), np.inf, limit)
    ref = start.reference[None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        reach = distance * np.sqrt(np.repeat(rho, m))[:, None] * start.extent[None, :]
    reach = np.where(np.isfinite(reach), reach, np.finfo(float).max)  # (inf q still fails)
    sums = np.zeros((3, k * m))  # sum dH, sum n dH, sum dH^2, dH in units of kT
    unit = start.kT
    failures = np.zeros(k, dtype=int)
    # one step per row: the engine's updates are elementwise in h, so an (rows, 1) column
    # runs each row at its own step (bit for bit as a run of that step alone)
    hcol = np.repeat(h_values, m)[:, None]
    with np.errstate(all="ignore"):
        if processed:
            q, p = engine.start(q, p, cast(float, hcol))
        for n in range(1, steps + 1):
            q, p, bad = _step(engine, q, p, hcol)
            qo, po = engine.output(q, p, cast(float, hcol)) if processed else (q, p)
            # (a NaN or infinite coordinate fails the comparison; a momentum, the energy
            # test or the next step's coordinate)
            bad |= ~np.all(np.abs(qo - ref) <= reach, axis=1)
            measured = every == 1 or n % every == 0 or n == steps
            if measured:
                dH = system.energy(qo, po) - H0
                bad |= ~(dH + (H0 - U_ref) <= limit)
            if bad.any():
                failures += np.bincount(which[bad], minlength=k)
                keep = ~bad
                q, p, hcol, which, H0, limit, reach = (
                    q[keep], p[keep], hcol[keep], which[keep], H0[keep], limit[keep],
                    reach[keep])
                sums = sums[:, keep]
                if measured:
                    dH = dH[keep]
                if not which.size:
                    break
            if every == 1:  # (in units of kT: squares of energies of 1e200 overflow)
                x = dH / unit
                sums[0] += x
                sums[1] += n * x
                sums[2] += x * x
            if progress is not None and n % 256 == 0:
                progress(n / steps)
    out = []
    if every == 1:
        N = float(steps)
        sum_n = N * (N + 1) / 2
        sum_nn = N * (N + 1) * (2 * N + 1) / 6
        slope = (N * sums[1] - sum_n * sums[0]) / (N * sum_nn - sum_n ** 2) / hcol[:, 0]
        variance = np.maximum(sums[2] / N - (sums[0] / N) ** 2, 0.0)
    for j in range(k):
        mine = which == j
        count = int(mine.sum())
        drift = error = fluct = math.nan
        if every == 1 and count:
            b = slope[mine]
            drift = float(b.mean()) * unit
            error = float(b.std(ddof=1) / math.sqrt(count)) * unit if count > 1 else math.nan
            fluct = float(math.sqrt(variance[mine].mean())) * unit
        out.append(Outcome(float(h_values[j]), m, int(failures[j]), steps, drift, error, fluct))
    if progress is not None:
        progress(1.0)
    return out


def _step(engine: Engine, q: np.ndarray, p: np.ndarray, h: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of every row; rows whose implicit stage iteration fails are returned
    unchanged and marked (the batch is halved until the failing rows are alone)."""
    try:
        q1, p1 = engine.step(q, p, cast(float, h))
        return q1, p1, np.zeros(q.shape[0], dtype=bool)
    except SolverFailure:
        if q.shape[0] == 1:
            return q, p, np.ones(1, dtype=bool)
    half = q.shape[0] // 2
    qa, pa, fa = _step(engine, q[:half], p[:half], h[:half])
    qb, pb, fb = _step(engine, q[half:], p[half:], h[half:])
    return np.concatenate([qa, qb]), np.concatenate([pa, pb]), np.concatenate([fa, fb])
