"""Ensembles of trajectories of a method's own map on a potential, many steps at once.

One run advances ``m`` thermal initial conditions at each of ``k`` steps h together, as
``k m`` rows, through :func:`stepsafe.core.ensemble.integrate` (the method's nonlinear map;
h is a column, one value per row), in blocks of rows (:data:`BLOCK_VALUES`) that each run
all their steps in turn: a row's trajectory does not depend on the block it runs in (for
an implicit method, up to its stage iteration's tolerance). At every step it

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
  A row also fails when it **leaves the well**, whatever its start's energy. Along a
  direction through the minimum, a mass-weighted unit vector e, the profile
  ``u(s) = U(q0 + s M^-1/2 e)`` may end, on a side, at a plateau or a barrier's top ``E``
  above the minimum (at least 12 kT; :func:`stepsafe.systems.thermal.sampling.exits`; a
  one-coordinate well's own sides). The directions walked
  (:func:`stepsafe.systems.thermal.sampling.well_exits`) are each coordinate, each normal
  mode of the mass-weighted Hessian at the minimum (a bond written ``q2 - q1`` or
  ``q1 + q2`` dissociates along its mode and along no coordinate), and each split of the
  coordinates into those before k and those from k on, moved apart at a fixed centre of
  mass (a chain of bonds ``q[i+1] - q[i]`` dissociates at one bond, along no normal mode:
  each mode stretches some bonds and compresses others); a direction that coincides with
  one already walked is walked once. A row fails when its ``s = e . M^1/2 (q - q0)``
  passes that point, or lies beyond the side's edge (where u is within kT of ``E``) with
  the energy of that direction, ``(e . M^-1/2 p)^2 / 2 + U(q) - U(q - s M^-1/2 e)``,
  above ``E`` (unbound: the well no longer turns it back; for one coordinate it is
  ``H - U_ref``, for a U separable along e that direction's own energy). Along each of
  those directions the *relaxed* profile is walked too
  (:func:`stepsafe.systems.thermal.sampling.relaxed_exits`): ``u(s)`` the least U on the
  hyperplane ``e . M^1/2 (q - q0) = s``, which every trajectory that reaches s crosses,
  found by following the floor ``v(s)`` (the displacement ``q - q0`` where that least U
  lies) out from the minimum; it levels off where a valley bends away from every straight
  line (a bond coupled to a coordinate that its stretch shifts). Its exit is kept where it
  is lower, by more than kT, than the straight profile's along the same direction and
  side, and does not run straight out along a walked exit. A row fails at a relaxed exit
  when s passes its point, or lies beyond its edge with the energy along the valley,
  ``(t . M^-1/2 p)^2 / 2 + U(q) - U(q - v(s))`` (t the floor's unit tangent in
  mass-weighted coordinates), above ``E``: the straight test with the floor in place of
  the line, the same for a U separable along it. A row whose start's energy along the
  valley (the same expression at its start) is within ``VALLEY_EXCHANGE`` kT of a
  relaxed exit's ``E`` or above is not failed by that exit: the exact flow may take it
  out too, with energy drawn from the other coordinates, and such starts would
  otherwise fail runs at any step (the start's whole energy would exempt nearly every
  row of a system of many coordinates, whose energy is some kT in each). Both are tested
  where the energy is measured. The ceilings above scale with the start's energy, which
  may exceed ``E`` by itself, and a row that has just left moves slowly, short of
  ``distance`` times the extent in a short run. A bond that parts along none of those
  directions, straight or relaxed (atoms in two or three dimensions whose coordinates'
  order does not split its fragments; beyond ``EXACT_UP_TO`` coordinates, a mode other
  than the fastest ``MODE_EXITS_LARGE``; within modes of one repeated frequency, walked in
  one basis of their space, a combination other than its vectors; beyond
  ``RELAXED_UP_TO`` coordinates, a bent valley; a valley whose floor the relaxed walk
  loses to another branch of the hyperplane's minima) is seen by the ceilings alone.
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from stepsafe.core.ensemble import integrate
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method
from stepsafe.systems.thermal.potential import Potential, system_of
from stepsafe.systems.thermal.sampling import Exit, draw, momenta, split_shifts
from stepsafe.systems.thermal.sampling import well_exits as well_exits_of

#: Energy beyond ``GROWTH rho^2`` times the initial energy (above U_ref) is a failure.
GROWTH = 4.0
#: A coordinate beyond ``DISTANCE`` times the initial ensemble's extent is a failure.
DISTANCE = 10.0
#: A row that starts with at least its valley exit's energy less this many kT along the
#: valley is not failed by that exit (:func:`leaving`).
VALLEY_EXCHANGE = 3.0
#: A run integrates its rows in blocks of at most this many state values (rows times
#: degrees of freedom), one block after the other over all its steps: every array of a
#: step is then 512 KiB. A step of 3000 rows of 100 dof made temporaries of 2.4 MB, which
#: glibc's default thresholds map afresh and page-fault at each allocation (twice the CPU
#: time of the blocks); blocks of 64 KiB cost more Python operations per trajectory: the
#: 100-dof chain's ``advise`` took 69 s with them, 58 s with these, with the default
#: allocator and with the command line's (55 s), which keeps freed memory
#: (``benchmarks/thermal.py``).
BLOCK_VALUES = 1 << 16


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
        ``U_ref``: the lowest U of the region drawn, ``U(q_ref)`` for one well (with several
        basins drawn, the lowest U over the starts and, for one coordinate, over a fine grid
        of their range).
    extent : ndarray
        The largest ``|q - q_ref|`` of each coordinate over the start ``(n,)``.
    seed : int
    how : str
        How the configurations were drawn.
    exits : tuple of Exit
        Where the well can be left along a coordinate (empty: confined).
    """

    q: np.ndarray
    p: np.ndarray
    kT: float
    reference: np.ndarray
    energy_reference: float
    extent: np.ndarray
    seed: int
    how: str
    exits: tuple[Exit, ...] = ()

    @property
    def size(self) -> int:
        return int(self.q.shape[0])


def thermal_start(pot: Potential, kT: float, count: int, seed: int = 0,
                  configurations: np.ndarray | None = None, how: str = "",
                  well_exits: tuple[Exit, ...] | None = None) -> Start:
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
    well_exits : tuple of Exit, optional
        Where the well can be left (default: ``well_exits(pot, kT)``, along the
        coordinates and the normal modes; none for a quadratic potential).

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
    # the growth test's U_ref: the lowest U of the region drawn (a draw over several basins
    # holds starts below the analysed minimum's U): over the starts and, for one
    # coordinate, a fine grid over their range
    with np.errstate(all="ignore"):
        low = [U0, float(np.nanmin(pot.energy(q)))] if q.shape[0] else [U0]
        if pot.dimension == 1 and q.shape[0]:
            grid = np.linspace(float(q.min()), float(q.max()), 20001)[:, None]
            low.append(float(np.nanmin(pot.energy(grid))))
    U0 = min(x for x in low if math.isfinite(x)) if any(map(math.isfinite, low)) else U0
    if well_exits is None:
        well_exits = () if pot.quadratic else well_exits_of(pot, kT)
    return Start(q, p, float(kT), q0, U0, extent, seed, how, tuple(well_exits))


class WellTest(NamedTuple):
    """Whether rows leave the start's well (module docstring).

    Attributes
    ----------
    leaves : callable
        ``leaves(q, p, start_energies=None)``: True for the rows of the output states
        ``q``, ``p`` (r, n) that have left; ``start_energies`` (r, k), when given, are the
        rows' initial energies along each valley exit (:attr:`along_valleys` of their
        starts): a row that started above a valley exit's energy may leave along it by
        the exact flow, and that exit does not fail it.
    along_valleys : callable
        ``along_valleys(q, p)``: the energies (r, k) of states along each valley exit.
    """

    leaves: Callable[..., np.ndarray]
    along_valleys: Callable[[np.ndarray, np.ndarray], np.ndarray]


def leaving(pot: Potential, start: Start) -> WellTest | None:
    """The test of rows that leave the start's well (module docstring); None when it has
    no exit."""
    if not start.exits:
        return None
    n = pot.dimension
    root = np.sqrt(pot.masses)
    q0 = start.reference
    along = [e for e in start.exits if e.direction is None]
    modal = [e for e in start.exits
             if e.direction is not None and not e.split and e.valley is None]
    splits = [e for e in start.exits if e.split and e.valley is None]
    valleys = [e for e in start.exits if e.valley is not None]
    # a coordinate's s = sqrt(m_i) (q_i - q0_i), its velocity p_i / sqrt(m_i); the point of
    # the profile behind q is q with q_i = q0_i
    axes = np.array([e.axis for e in along], dtype=np.intp)
    # a normal mode's s = (q - q0) . (e sqrt(m)), its velocity p . (e / sqrt(m)), one column
    # each; the point behind q is q - s e / sqrt(m)
    unit = np.array([e.direction for e in modal], dtype=float).T.reshape(n, -1)
    weigh, behind = unit * root[:, None], unit / root[:, None]
    # a split's s from running sums of m (q - q0) over each group (its velocity from those
    # of p): O(n) a row for all of them, where a dense direction costs O(n) each
    cuts = np.array([e.split for e in splits], dtype=np.intp)
    shifts = np.array([split_shifts(pot.masses, int(k)) for k in cuts]).reshape(-1, n)

    first, second = shifts[:, 0], shifts[:, -1]
    # (the splits' columns of the running sum: a slice when they are consecutive, as they
    # are for a chain)
    heads: slice | np.ndarray = cuts - 1
    if cuts.size and np.array_equal(cuts, np.arange(cuts[0], cuts[0] + cuts.size)):
        heads = slice(int(cuts[0]) - 1, int(cuts[0]) - 1 + cuts.size)

    def split_coordinate(v: np.ndarray) -> np.ndarray:
        """``sum_j shift_j v_j`` of every split ``(r, k)`` (v = m (q - q0), or p)."""
        running = np.cumsum(v, axis=1)
        head = running[:, heads]
        return first * head + second * (running[:, -1:] - head)

    # a relaxed profile's s as a mode's; the point behind q is q less the valley floor's
    # displacement at s, and the speed along the valley is that along the floor's tangent
    floor = np.array([e.direction for e in valleys], dtype=float).T.reshape(n, -1) * root[:, None]
    straight = len(along) + len(modal) + len(splits)
    exits = along + modal + splits + valleys
    side = np.array([e.side for e in exits])
    at = side * np.array([e.at for e in exits])
    edge = side * np.array([e.edge for e in exits])
    energy = np.array([e.energy for e in exits])
    # the displacement along each exit's direction (n,) that takes s to 0
    back = np.zeros((straight, n))
    back[np.arange(axes.size), axes] = 1.0 / root[axes]
    back[axes.size:axes.size + len(modal)] = behind.T
    back[axes.size + len(modal):] = shifts

    def positions(q: np.ndarray) -> np.ndarray:
        x = q - q0[None, :]
        return np.concatenate([root[axes] * x[:, axes], x @ weigh,
                               split_coordinate(pot.masses[None, :] * x), x @ floor], axis=1)

    def speeds(p: np.ndarray) -> np.ndarray:
        return np.concatenate([p[:, axes] / root[axes], p @ behind, split_coordinate(p)],
                              axis=1)

    # a row that starts within VALLEY_EXCHANGE kT of a valley exit's energy along it may
    # gain the rest from the other coordinates by the exact flow
    exempt = energy[straight:] - VALLEY_EXCHANGE * start.kT

    def leaves(q: np.ndarray, p: np.ndarray,
               start_energies: np.ndarray | None = None) -> np.ndarray:
        with np.errstate(all="ignore"):
            s = positions(q)
            past = side * s > at
            if valleys and start_energies is not None:  # (a row that starts above a
                # relaxed exit's energy along it may leave by the exact flow: not the
                # step's failure)
                past[:, straight:] &= ~(start_energies > exempt[None, :])
            out = np.any(past, axis=1)
            rows, which = np.nonzero((side * s > edge) & ~out[:, None])
            rows_v, beyond = rows[which >= straight], which[which >= straight]
            if start_energies is not None:
                bound = ~(start_energies[rows_v, beyond - straight]
                          > exempt[beyond - straight])
                rows_v, beyond = rows_v[bound], beyond[bound]
            lined = which < straight
            rows, which = rows[lined], which[lined]
            if rows.size:  # (rare: within kT of an exit's energy)
                x = q[rows]
                speed = speeds(p[rows])[np.arange(rows.size), which]
                own = 0.5 * speed ** 2 + (pot.energy(x) - pot.energy(
                    x - s[rows, which][:, None] * back[which]))
                out[rows[~(own <= energy[which])]] = True
            for j in np.unique(beyond):
                mine = rows_v[beyond == j]
                out[mine[valley_leaves(valleys[j - straight], q[mine], p[mine],
                                       side[j] * s[mine, j])]] = True
        return out

    def valley_leaves(exit: Exit, q: np.ndarray, p: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Rows beyond a relaxed exit's edge (at ``s``, measured out from the minimum) whose
        energy along its valley (:func:`valley_energy`) exceeds the exit's."""
        return ~(valley_energy(exit, q, p, s) <= exit.energy)

    def along_valleys(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            s = positions(q)[:, straight:] * side[None, straight:]
            return np.stack([valley_energy(e, q, p, s[:, j]) for j, e in enumerate(valleys)],
                            axis=1) if valleys else np.zeros((q.shape[0], 0))

    def valley_energy(exit: Exit, q: np.ndarray, p: np.ndarray, s: np.ndarray) -> np.ndarray:
        """The energy of rows along a relaxed exit's valley at ``s`` (measured out from the
        minimum), ``(t . M^-1/2 p)^2 / 2 + U(q) - U(q - v(s))`` with ``v`` the floor's
        displacement and t its unit tangent (mass-weighted), both interpolated linearly."""
        table = exit.valley
        assert table is not None
        at = s / exit.spacing
        j = np.clip(np.floor(at).astype(np.intp), 0, table.shape[0] - 2)
        part = (at - j)[:, None]
        shift = (1.0 - part) * table[j] + part * table[j + 1]
        tangent = (table[j + 1] - table[j]) * root[None, :]
        tangent /= np.linalg.norm(tangent, axis=1)[:, None]
        speed = np.sum(tangent * p / root[None, :], axis=1)
        return 0.5 * speed ** 2 + (pot.energy(q) - pot.energy(q - shift))
    return WellTest(leaves, along_valleys)


@dataclass(frozen=True)
class Outcome:
    """What the ensemble did at one step h.

    Attributes
    ----------
    h : float
    trajectories, failures : int
    steps : int
        Steps every surviving trajectory ran; when the run stopped at ``stop_failures``
        failures, the step at which the last of them failed.
    drift, drift_error : float
        Mean energy drift per unit time over the survivors and its standard error (NaN
        with fewer than 2 survivors, and when the run stopped at its failures).
    fluctuation : float
        Root mean square over survivors of the standard deviation of ``H_n - H_0``.
    failed : tuple of int
        The rows of the start whose trajectories failed, in increasing order.
    """

    h: float
    trajectories: int
    failures: int
    steps: int
    drift: float
    drift_error: float
    fluctuation: float
    failed: tuple[int, ...] = ()


def run(method: Method, pot: Potential, start: Start, h_values, steps: int,
        rho, growth: float = GROWTH, distance: float = DISTANCE, energy_every: int = 1,
        stop_failures: int | None = None, first: Sequence[int] = (),
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
    stop_failures : int, optional
        With one h: stop once this many trajectories have failed (their verdict is then
        settled): the block where the last of them failed stops after that step and the
        blocks after it do not run. Every trajectory is the one the full run would
        follow, so each failure seen is one of the full run's, and ``steps`` says at which
        step the last was seen.
    first : sequence of int
        Rows of the start to run first, in this order (the others follow in theirs): a
        run stopped at its failures stops sooner when the rows likeliest to fail come
        first. Every value of a full run is the same in any order.
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
    if stop_failures is not None and k != 1:
        raise StepsafeError("a run stopped at its failures takes one step h")
    system = system_of(pot)
    rows = k * m
    rho_rows = np.repeat(rho, m)
    h_rows = np.repeat(h_values, m)
    with np.errstate(over="ignore", invalid="ignore"):
        reach = distance * np.sqrt(rho_rows)[:, None] * start.extent[None, :]
    reach = np.where(np.isfinite(reach), reach, np.finfo(float).max)  # (inf q still fails)
    growth_rows = growth * rho_rows ** 2
    order = _order(m, first)
    # row r of the run is row perm[r] of the k starts one after the other (the same h:
    # h, rho, the reach and the growth bound are per start)
    perm = (np.arange(k)[:, None] * m + order[None, :]).ravel()
    q0, p0 = np.tile(start.q[order], (k, 1)), np.tile(start.p[order], (k, 1))
    block = block_rows(pot.dimension)
    escaped = np.zeros(rows, dtype=bool)
    slope = np.full(rows, np.nan)
    variance = np.full(rows, np.nan)
    ran_steps, done, seen = steps, rows, 0
    # one step per row: the engine's updates are elementwise in h, so a column runs each
    # row at its own step (bit for bit as a run of that step alone); a block of rows runs
    # all its steps before the next block starts
    test = leaving(pot, start)
    for b in _blocks(rows, block, stop_failures is not None):
        a, size = b.start, b.stop - b.start
        report = None if progress is None else (
            lambda f, a=a, size=size: progress((a + f * size) / rows))
        ran = integrate(method, system, q0[b], p0[b], h_rows[b], steps, energy_every=every,
                        reference_energy=start.energy_reference, growth=growth_rows[b],
                        centre=start.reference, reach=reach[b], fit=every == 1,
                        unit=start.kT, leaves=None if test is None else test.leaves,
                        leave_data=None if test is None else test.along_valleys(q0[b], p0[b]),
                        stop_escapes=None if stop_failures is None else stop_failures - seen,
                        progress=report)
        escaped[perm[b]] = ran.escaped
        seen += int(ran.escaped.sum())
        if every == 1:
            slope[perm[b]] = ran.slopes() / h_rows[b]
            variance[perm[b]] = ran.variances()
        if stop_failures is not None and seen >= stop_failures:
            ran_steps, done = ran.steps, b.stop
            break
    if progress is not None:
        progress(1.0)
    stopped = done < rows or ran_steps < steps
    which = np.repeat(np.arange(k), m)
    failures = np.bincount(which[escaped], minlength=k)
    unit = start.kT
    out = []
    for j in range(k):
        mine = (which == j) & ~escaped
        count = int(mine.sum())
        drift = error = fluct = math.nan
        if every == 1 and count and not stopped:
            b_i = slope[mine]
            drift = float(b_i.mean()) * unit
            error = float(b_i.std(ddof=1) / math.sqrt(count)) * unit if count > 1 else math.nan
            fluct = float(math.sqrt(variance[mine].mean())) * unit
        failed = tuple(int(i) for i in np.flatnonzero(escaped[j * m:(j + 1) * m]))
        out.append(Outcome(float(h_values[j]), m, int(failures[j]), ran_steps, drift, error,
                           fluct, failed))
    return out


def _blocks(rows: int, block: int, stopping: bool) -> list[slice]:
    """The blocks of a run, of ``block`` rows; a run that stops at its failures starts
    with a quarter block and doubles up to ``block`` (its first rows are the likeliest to
    fail: a failure there costs a quarter of a block's run, for a few percent more per row
    in the small blocks when none fails)."""
    out, a, size = [], 0, max(1, block // 4) if stopping else block
    while a < rows:
        out.append(slice(a, min(rows, a + size)))
        a, size = a + size, min(block, 2 * size)
    return out


def _order(m: int, first: Sequence[int]) -> np.ndarray:
    """The rows 0..m-1 with ``first`` (distinct, in range) ahead of the others."""
    lead = np.array([int(i) for i in first], dtype=np.intp)
    if lead.size and (lead.min() < 0 or lead.max() >= m or np.unique(lead).size != lead.size):
        raise StepsafeError(f"the rows run first must be distinct rows of the {m} starts")
    rest = np.ones(m, dtype=bool)
    rest[lead] = False
    return np.concatenate([lead, np.flatnonzero(rest)])


def block_rows(dimension: int) -> int:
    """The rows of one block of a run: :data:`BLOCK_VALUES` values of its state at most
    (one row at least)."""
    return max(1, BLOCK_VALUES // max(1, int(dimension)))
