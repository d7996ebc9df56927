"""Resonance bands at amplitude: the steps h where a thermal ensemble fails.

A linear resonance point ``n theta(z) = 2 pi m`` becomes, at finite amplitude, a band of h
whose width and place depend on the temperature and on the potential's anharmonicity;
nothing closed-form is reliable. So the method's own map is iterated on the potential from
thermal initial conditions (:mod:`stepsafe.systems.thermal.trajectories`: the whole
system, or a 1-D profile along a mode) at each h of a grid, and a step is judged from the
number k of the m trajectories that fail within the steps run:

* one-sided Clopper-Pearson bounds at level ``confidence`` on the failure probability P,
  ``lower = Beta^-1(1 - confidence; k, m - k + 1)`` and
  ``upper = Beta^-1(confidence; k + 1, m - k)``;
* ``clear`` when no trajectory failed (``k = 0``) and ``upper < threshold``; ``band`` when
  ``lower > threshold``; ``failures observed`` for any other ``k > 0`` and ``undecided``
  for ``k = 0`` with ``upper >= threshold`` (both unsafe: a step is never clear while a
  trajectory of its sample failed, nor while the sample cannot bound the probability
  below the threshold). With ``k = 0`` the upper bound is ``1 - (1 - confidence)^(1/m)``:
  :func:`trajectories_for` gives the smallest m that can show ``P < threshold``.

The grid is uniform in h plus points at relative offsets ``+-OFFSETS`` around each linear
resonance point of each mode (``h = z_r / omega_k``, ``z_r`` from
:func:`stepsafe.core.resonances.nonlinear_resonances`). Every edge between a clear and an
unsafe grid point is bisected ``bisections`` times with the same initial conditions (common
random numbers; a bisection point stops once its failures make it a band, the verdict
a full run would give: its ``failures`` are then that count and its ``steps`` where the
last of them was seen); the edge is reported as the bracket ``(clear, unsafe)``, its
statistical uncertainty half the bracket's width (the h on its clear side was judged
clear, the one on the other side not, at the stated confidence). Bands narrower than the
grid's spacing can be missed between grid points: :attr:`BandScan.spacing` says how fine
it was. A scan tests escapes at every step and the energy every ``ENERGY_EVERY`` steps
(the energy costs as much as a force); it measures no drift (:mod:`.drift` does, at
chosen steps, over every step).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method
from stepsafe.systems.thermal.potential import Potential
from stepsafe.systems.thermal.trajectories import DISTANCE, GROWTH, Outcome, Start, run

#: The failure probability a band scan screens for (500 trajectories per step can show
#: it with none failed).
THRESHOLD = 0.01
CONFIDENCE = 0.95
#: The default largest acceptable failure probability of a run at temperature: the
#: confirmation of an advised step and the check of a step use
#: ``trajectories_for(MAX_FAILURE)`` trajectories and need every one to survive.
MAX_FAILURE = 1e-3
BISECTIONS = 6
GRID_POINTS = 48
#: A scan tests the energy every this many steps (escapes at every step).
ENERGY_EVERY = 8
#: Relative offsets around each resonance point added to the grid (both sides).
OFFSETS = (0.0025, 0.005, 0.01, 0.02, 0.04)


def clopper_pearson(k: int, m: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """One-sided ``confidence`` lower and upper bounds on a binomial probability from k
    successes in m trials (exact, Clopper-Pearson): quantiles of Beta distributions, the
    inverse of the regularised incomplete beta function."""
    from scipy.special import betaincinv

    lower = 0.0 if k == 0 else float(betaincinv(k, m - k + 1, 1.0 - confidence))
    upper = 1.0 if k == m else float(betaincinv(k + 1, m - k, confidence))
    return lower, upper


def band_failures(m: int, threshold: float = THRESHOLD,
                  confidence: float = CONFIDENCE) -> int | None:
    """The fewest failures k of m trajectories whose lower bound exceeds ``threshold``
    (``lower(k, m) > threshold``: the verdict is ``band`` whatever the others do; the
    lower bound grows with k), None when even ``k = m`` does not.

    Parameters
    ----------
    m : int
        Trajectories.
    threshold, confidence : float
        As for :func:`judge`.

    Returns
    -------
    int or None
    """
    if not clopper_pearson(m, m, confidence)[0] > threshold:
        return None
    lo, hi = 0, m  # lower(lo) <= threshold < lower(hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if clopper_pearson(mid, m, confidence)[0] > threshold:
            hi = mid
        else:
            lo = mid
    return hi


def trajectories_for(threshold: float, confidence: float = CONFIDENCE) -> int:
    """The smallest m whose zero failures show ``P < threshold`` at ``confidence``:
    ``1 - (1 - confidence)^(1/m) < threshold``, i.e. ``m > ln(1 - confidence) /
    ln(1 - threshold)`` (about ``ln 20 / threshold`` at 95%).

    Parameters
    ----------
    threshold : float
        In (0, 1).
    confidence : float
        In (0, 1).

    Returns
    -------
    int
    """
    if not (0 < threshold < 1 and 0 < confidence < 1):
        raise StepsafeError(f"the failure threshold must lie in (0, 1), got {threshold}")
    return int(math.floor(math.log1p(-confidence) / math.log1p(-threshold))) + 1


@dataclass(frozen=True)
class Probe:
    """The ensemble at one h: failures, their bounds, the verdict, and the energy drift.

    Attributes
    ----------
    h : float
    trajectories, failures, steps : int
    probability, lower, upper : float
        ``failures / trajectories`` and its one-sided bounds.
    verdict : str
        ``"clear"``, ``"band"``, ``"failures observed"`` or ``"undecided"``.
    threshold : float
        The failure probability the verdict was judged against.
    drift, drift_error, fluctuation : float
        See :class:`stepsafe.systems.thermal.trajectories.Outcome` (NaN in a scan).
    """

    h: float
    trajectories: int
    failures: int
    steps: int
    probability: float
    lower: float
    upper: float
    verdict: str
    drift: float
    drift_error: float
    fluctuation: float
    threshold: float = THRESHOLD

    @property
    def clear(self) -> bool:
        return self.verdict == "clear"


def judge(outcome: Outcome, threshold: float = THRESHOLD,
          confidence: float = CONFIDENCE) -> Probe:
    """The :class:`Probe` of an outcome: ``clear`` only with no failure and the upper
    bound below ``threshold`` (module docstring)."""
    k, m = outcome.failures, outcome.trajectories
    lower, upper = clopper_pearson(k, m, confidence)
    if k == 0:
        verdict = "clear" if upper < threshold else "undecided"
    else:
        verdict = "band" if lower > threshold else "failures observed"
    return Probe(outcome.h, m, k, outcome.steps, k / m, lower, upper, verdict, outcome.drift,
                 outcome.drift_error, outcome.fluctuation, threshold)


@dataclass(frozen=True)
class Edge:
    """A band edge: ``clear`` (an h judged clear), ``unsafe`` (the nearest h judged not
    clear, band or undecided) and ``band`` (the nearest h on that side judged in the band,
    None if none was). Where the failure probability is monotone across the edge, its
    crossing of the threshold lies between ``clear`` and ``band`` at the stated confidence:
    :attr:`uncertainty` is that distance (inf without a ``band`` point); ``unsafe`` only
    says how finely the conservative edge was bisected."""

    clear: float
    unsafe: float
    band: float | None = None

    @property
    def h(self) -> float:
        return 0.5 * (self.clear + self.unsafe)

    @property
    def uncertainty(self) -> float:
        return math.inf if self.band is None else abs(self.band - self.clear)


@dataclass(frozen=True)
class Band:
    """A run of unsafe h. ``lower`` is None when it starts at the scan's first point,
    ``upper`` when it reaches the last; ``resonances`` names the linear resonance points
    inside it or within 5% of its ends, the one nearest to its lower end first (an
    anharmonic potential moves a band away from its linear point)."""

    lower: Edge | None
    upper: Edge | None
    peak: float
    resonances: tuple[str, ...]

    @property
    def name(self) -> str:
        return self.resonances[0] if self.resonances else "unnamed"


@dataclass(frozen=True)
class BandScan:
    """Every probe of a scan, the bands found, and how they were measured.

    Attributes
    ----------
    probes : tuple of Probe
        Sorted by h (grid and bisection points).
    bands : tuple of Band
        In increasing h.
    h_range : tuple of float
        The first and last grid point.
    spacing : float
        The uniform grid's spacing.
    threshold, confidence : float
    trajectories, steps, seed : int
    target : str
        What was integrated (the whole system, or a profile along a mode).
    start_how : str
        How the initial configurations were drawn.
    criterion : str
        When a trajectory counts as failed.
    """

    probes: tuple[Probe, ...]
    bands: tuple[Band, ...]
    h_range: tuple[float, float]
    spacing: float
    threshold: float
    confidence: float
    trajectories: int
    steps: int
    seed: int
    target: str
    start_how: str
    criterion: str

    @property
    def clear_up_to(self) -> float | None:
        """The largest h with every grid and bisection point from the scan's start up to
        it clear: the clear side of the first band's lower edge, the scan's end without a
        band, None when the first grid point is not clear."""
        if not self.bands:
            return self.h_range[1]
        first = self.bands[0]
        return None if first.lower is None else first.lower.clear

    def probe_at(self, h: float) -> Probe | None:
        for p in self.probes:
            if p.h == h:
                return p
        return None


def grid(h_lo: float, h_hi: float, points: int = GRID_POINTS,
         around: Sequence[float] = (), offsets: Sequence[float] = OFFSETS) -> np.ndarray:
    """``points`` uniform steps on ``[h_lo, h_hi]`` plus each of ``around`` and its relative
    offsets ``h (1 +- offset)`` that fall inside, sorted and unique."""
    if not (0 < h_lo < h_hi and math.isfinite(h_hi)):
        raise StepsafeError(f"the scan needs 0 < h_lo < h_hi, got {h_lo}, {h_hi}")
    extra = [h * (1 + s * o) for h in around for o in (0.0, *offsets) for s in (-1, 1)]
    h = np.concatenate([np.linspace(h_lo, h_hi, max(2, int(points))), np.asarray(extra)])
    return np.unique(h[(h >= h_lo) & (h <= h_hi)])


def criterion_text(growth: float = GROWTH, distance: float = DISTANCE,
                   start: Start | None = None) -> str:
    """The failure criterion in words (with the start's well exits, when it has some)."""
    out = (f"a trajectory fails when its state is not finite, a coordinate leaves "
           f"{distance:g} sqrt(rho) times the initial ensemble's extent around the minimum, "
           f"or its energy above the minimum exceeds {growth:g} rho^2 times its initial one "
           f"(rho: the largest energy ratio of the linear map's invariant ellipse at that "
           f"step)")
    if start is None:
        return out
    for e in start.exits:
        if e.valley is not None:
            along = " along the floor of a valley (its relaxed profile)"
            where, what = "e . sqrt(M)", "valley"
        elif e.split:
            n = start.q.shape[1]
            along = (f" where q_1..q_{e.split} part from q_{e.split + 1}..q_{n} (centre of "
                     f"mass fixed)")
            where, what = "e . sqrt(M)", "direction"
        elif e.direction is not None:
            along = f" along the normal mode of omega = {e.omega:.6g}"
            where, what = "e . sqrt(M)", "direction"
        else:
            along = f" along q_{e.axis + 1}" if start.q.shape[1] > 1 else ""
            where, what = "sqrt(m)", "coordinate"
        out += (f"; or it leaves the well{along}: its {where} (q - q0) passes {e.at:.6g}, "
                f"where the profile levels off or tops a barrier "
                f"{e.energy / start.kT:.3g} kT above the minimum, or lies beyond "
                f"{e.edge:.6g} with more energy than that in that {what}")
    return out


def scan(method: Method, pot: Potential, start: Start, h_values, steps: int,
         rho_of: Callable[[np.ndarray], np.ndarray], threshold: float = THRESHOLD,
         confidence: float = CONFIDENCE, bisections: int = BISECTIONS,
         resonances: Sequence[tuple[float, str]] = (), target: str = "whole system",
         growth: float = GROWTH, distance: float = DISTANCE,
         energy_every: int = ENERGY_EVERY,
         progress: Callable[[float], None] | None = None) -> BandScan:
    """Probe every h of ``h_values`` (see :func:`grid`), bisect every edge, collect bands.

    Parameters
    ----------
    method : Method
    pot : Potential
        What is integrated (the whole system or a 1-D profile).
    start : Start
        Thermal initial conditions of ``pot``.
    h_values : array_like
        The grid, increasing.
    steps : int
        Steps per trajectory.
    rho_of : callable
        The linear map's energy-ratio bound at an array of h.
    threshold, confidence : float
        Failure probability that makes a band, and the bounds' level.
    bisections : int
        Halvings of each edge's bracket.
    resonances : sequence of (h, name)
        Linear resonance points, to name the bands.
    target : str
        For the report.
    growth, distance : float
        The failure thresholds (:mod:`stepsafe.systems.thermal.trajectories`).
    energy_every : int
        The energy test every this many steps (the drift is not measured in a scan).
    progress : callable, optional
        Called with a fraction done.

    Returns
    -------
    BandScan
    """
    if not 0 < threshold < 1:
        raise StepsafeError(f"the threshold must lie in (0, 1), got {threshold}")
    h_values = np.unique(np.asarray(h_values, dtype=float))
    total = 1 + bisections

    def measure(hs: np.ndarray, part: int) -> list[Probe]:
        report = None if progress is None else (
            lambda f: progress((part + f) / total))
        outs = run(method, pot, start, hs, steps, rho_of(hs), growth, distance, energy_every,
                   progress=report)
        return [judge(o, threshold, confidence) for o in outs]

    stop = band_failures(start.size, threshold, confidence)

    def bisect(hs: np.ndarray, part: int) -> list[Probe]:
        # each point alone, stopped once its failures make it a band
        found = []
        for j, h in enumerate(hs):
            report = None if progress is None else (
                lambda f, j=j: progress((part + (j + f) / hs.size) / total))
            one = np.array([h])
            out, = run(method, pot, start, one, steps, rho_of(one), growth, distance,
                       energy_every, stop_failures=stop, progress=report)
            found.append(judge(out, threshold, confidence))
        return found

    probes = measure(h_values, 0)
    clear = np.array([p.clear for p in probes])
    brackets = []  # (clear h, unsafe h, is_lower_edge)
    for i in range(len(probes) - 1):
        if clear[i] != clear[i + 1]:
            a, b = probes[i].h, probes[i + 1].h
            brackets.append([a, b] if clear[i] else [b, a])
    extra: list[Probe] = []
    for r in range(bisections):
        if not brackets:
            break
        mids = np.array([0.5 * (c + u) for c, u in brackets])
        found = bisect(mids, 1 + r)
        extra += found
        for br, pr in zip(brackets, found):
            br[0 if pr.clear else 1] = pr.h
    if progress is not None:  # (done, though bisections may have ended early)
        progress(1.0)
    every = sorted(probes + extra, key=lambda p: p.h)
    inside = [p.h for p in every if p.verdict == "band"]

    def nearest_band(c: float, u: float) -> float | None:
        side = [h for h in inside if (h - c) * (u - c) > 0]
        return min(side, key=lambda h: abs(h - c)) if side else None

    edges = {(min(c, u), max(c, u)): Edge(c, u, nearest_band(c, u)) for c, u in brackets}
    # bands: runs of unsafe grid points; their edges are the bisected brackets
    bands = []
    i = 0
    n = len(probes)
    edge_list = list(edges.values())
    while i < n:
        if clear[i]:
            i += 1
            continue
        j = i
        while j + 1 < n and not clear[j + 1]:
            j += 1
        lo_edge = _edge_between(edge_list, probes[i - 1].h, probes[i].h) if i > 0 else None
        hi_edge = _edge_between(edge_list, probes[j].h, probes[j + 1].h) if j + 1 < n else None
        peak = max(p.probability for p in probes[i:j + 1])
        a = lo_edge.clear if lo_edge else probes[i].h
        b = hi_edge.clear if hi_edge else probes[j].h
        bands.append(Band(lo_edge, hi_edge, peak, names_near(resonances, a, b)))
        i = j + 1
    all_probes = tuple(every)
    spacing = float(np.max(np.diff(h_values))) if h_values.size > 1 else 0.0
    return BandScan(all_probes, tuple(bands), (float(h_values[0]), float(h_values[-1])),
                    spacing, threshold, confidence, start.size, int(steps), start.seed,
                    target, start.how, criterion_text(growth, distance, start))


def _edge_between(edges: list[Edge], a: float, b: float) -> Edge:
    lo, hi = min(a, b), max(a, b)
    for e in edges:
        if lo <= e.clear <= hi and lo <= e.unsafe <= hi:
            return e
    return Edge(a, b)  # (not reached: every clear/unsafe neighbour pair was bisected)


def names_near(resonances: Sequence[tuple[float, str]], a: float, b: float) -> tuple[str, ...]:
    """The resonance points in ``[a / 1.05, 1.05 b]``, nearest to the lower end a first."""
    near = sorted((abs(h - a), name) for h, name in resonances if a / 1.05 <= h <= 1.05 * b)
    return tuple(name for _, name in near)


def probe(method: Method, pot: Potential, start: Start, h: float, steps: int, rho: float,
          threshold: float = THRESHOLD, confidence: float = CONFIDENCE,
          growth: float = GROWTH, distance: float = DISTANCE,
          progress: Callable[[float], None] | None = None) -> Probe:
    """The ensemble's verdict at one step h (see :func:`judge`), over every step: its
    failure fraction is the run's (an unsafe step's too)."""
    out = run(method, pot, start, [h], steps, [rho], growth, distance, progress=progress)[0]
    return judge(out, threshold, confidence)
