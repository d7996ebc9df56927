"""Structure-preservation regions as unions of z-intervals (docs/theory.md#regions).

For a symplectic method ``det M = 1`` and the type of ``M(z)`` follows from ``t = tr M``:
elliptic for ``|t| < 2``, hyperbolic with positive multipliers for ``t > 2``, a flip for
``t < -2``. Preserved means the flow's type **and** orientation:

* ``oscillator``: ``|t| < 2`` and the same sense of rotation, ``M[q, p] > 0`` (for an
  elliptic M the off-diagonal entries have opposite signs and cannot vanish);
* ``saddle``: ``t > 2`` and the q direction expands, ``M[q, q] > M[p, p]`` (M is diagonal);
  ``saddle-p`` alike with p expanding, ``M[p, p] > M[q, q]``;
* ``inverted``: ``t > 2`` and the expanding eigenvector ``v`` of M points outward,
  ``v_q v_p > 0``, tested as ``o = M_qp (mu - M_qq) + M_pq (mu - M_pp) > 0`` (both terms
  carry the sign of ``v_q v_p``; ``mu`` is the larger multiplier). This sign is
  independent of the scaling of p.

Algorithm. The positive poles (singular stage system) are exact eigenvalue data and split
``(0, zmax]`` into segments, all sampled in one vectorised pass on the grid of
:mod:`stepsafe.core.grid` (uniform near the features, geometric far out, cut short where a
polynomial trace can change no more); ``dev = tr M - 2`` (summed without cancellation, so
that it keeps its relative accuracy at z = 1e-8) and its slope are evaluated together,
and cells whose cubic Hermite interpolant hides a pair of extrema are subdivided. Cells
never span a pole. Extrema of ``tr M`` are located by Newton's method on ``dt/dz`` (the
jet carries ``d2t/dz2``), started where the Hermite interpolant is flat; between
consecutive extrema ``tr M`` is monotone, so every sign change of ``t -+ 2`` between
samples is exactly one boundary, refined by Newton from the Hermite interpolant's root
(all levels together) to the floating-point grid. An extremum whose value is within the
rounding bound ``tol`` of ``+-2`` is a tangency: an isolated *resonance* (e.g.
``M = -I``), reported with the half-width of z within which float64 cannot tell a touch
from a gap, never merged over. The rounding bound is ``tol = TOL_FACTOR * eps * scale``
with ``scale`` the first-order rounding sensitivity of ``tr M`` (see
:class:`stepsafe.core.engine.Jet`; it includes the conditioning of implicit stage solves),
computed only at the points where a tolerance is decided. Where ``M(z)`` overflows float64
the analysis stops below that z and the region says so (``zmax`` is lowered, with a note).

A method that is not symplectic on the model is never preserved (a centre becomes a
spiral for every h > 0); for the oscillator the classical interval ``rho(M) <= 1`` is
reported instead (for RK methods from the stability polynomials, :mod:`.rkstability`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from functools import partial
from typing import NamedTuple, cast

import numpy as np

from stepsafe.comparison import compared
from stepsafe.core.engine import TOL_FACTOR, Jet
from stepsafe.core.escalate import ESCALATE_REL, Escalation
from stepsafe.core.grid import (
    SAMPLE_WORK_BUDGET,
    Grid,
    default_resolution,
    far_bound,
)
from stepsafe.core.models import ELLIPTIC, check_model
from stepsafe.core.rkstability import imaginary_axis_crossings, stability_function
from stepsafe.core.roots import EPS, HermiteCubic, hermite_extremum, hermite_root, refine_brackets
from stepsafe.core.sets import contains, difference, distinct, union
from stepsafe.core.transfer import pole_locations, poles, transfer_jet
from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.methods.protocol import Shears
from stepsafe.methods.residuals import residuals
from stepsafe.methods.tableaux import Method, RungeKutta

DEFAULT_ZMAX = 10.0
#: Cells whose Hermite interpolant hides extrema are split this many times per level.
REFINE_SPLIT = 8
REFINE_LEVELS = 4
#: Past this magnitude of M - I (or its slope) the analysis stops: the rounding bounds,
#: products of such entries, would overflow float64.
OVERFLOW = 1e150
#: z is analysed up to here at most (unless nothing can change beyond a smaller z).
Z_CAP = 1e100


class Point(NamedTuple):
    """A distinguished z: a boundary, resonance or pole, with its float64 uncertainty."""

    z: float
    kind: str  # "root" (|tr M| = 2 crossing), "pole", "resonance", "orientation", "undecided"
    uncertainty: float = 0.0
    detail: str = ""


class Interval(NamedTuple):
    """An open interval ``(lo, hi)`` of z; ``hi`` is None when it reaches zmax.

    ``lo_point`` and ``hi_point`` are the points that end it (None: 0 and zmax). The
    interval stops short of each by that point's float64 uncertainty, ``lo = lo_point.z +
    lo_point.uncertainty`` and ``hi = hi_point.z - hi_point.uncertainty``: every z inside
    is decided, none lies in the band of a resonance, a root or a pole (nor in an
    undecided stretch, whose edges have no uncertainty). The points themselves (the first
    boundary ``z*`` among them) keep their own z."""

    lo: float
    hi: float | None
    lo_point: Point | None = None
    hi_point: Point | None = None

    def contains(self, z: float) -> bool:
        return self.lo < z and (self.hi is None or z < self.hi)


@compared
@dataclass(frozen=True, eq=False)
class Region:
    """Where a method preserves a model's structure, up to ``zmax``."""

    model: str
    zmax: float
    symplectic: bool
    intervals: tuple[Interval, ...]
    reversed: tuple[Interval, ...] = ()
    resonances: tuple[Point, ...] = ()
    poles: tuple[Point, ...] = ()
    resolution: float = 0.0
    classical: tuple[Interval, ...] | None = None
    notes: tuple[str, ...] = field(default=())
    #: oscillator only: end of the run of elliptic z (either orientation) from 0, i.e. the
    #: classical stability limit |tr M| <= 2; None when it reaches zmax
    stability_limit: float | None = None
    #: stretches where float64 cannot decide the type (|tr M| within rounding of 2 over a
    #: range of z, where features the grid resolves could be rounding noise): not preserved
    undecided: tuple[Interval, ...] = ()
    #: what ``intervals`` keep: ``structure`` (type and orientation) or ``stability`` (the
    #: type only), see :func:`under_criterion`
    criterion: str = "structure"

    @property
    def first_interval(self) -> Interval | None:
        """The interval that starts at 0, if the structure is preserved for small z."""
        if self.intervals and self.intervals[0].lo == 0.0:
            return self.intervals[0]
        return None

    @property
    def first_boundary(self) -> float | None:
        """``z*``: the point that ends the interval from 0 (the interval itself stops its
        uncertainty short of it); None if it reaches zmax, 0 if there is none."""
        first = self.first_interval
        if first is None:
            return 0.0
        return first.hi_point.z if first.hi_point is not None else first.hi

    @property
    def islands(self) -> tuple[tuple[Interval, bool], ...]:
        """Intervals of the flow's type other than the first, with ``True`` for the same
        orientation (preserved) and ``False`` for reversed, in increasing z."""
        first = self.first_interval
        both = [(iv, True) for iv in self.intervals if iv is not first]
        both += [(iv, False) for iv in self.reversed]
        return tuple(sorted(both, key=lambda pair: pair[0].lo))

    @property
    def first_boundary_point(self) -> Point | None:
        first = self.first_interval
        return None if first is None else first.hi_point


class _Evaluator:
    """Vectorised evaluation of the jet and the derived scalar functions for one model.

    The level ``tr M = +2`` is decided on ``dev = tr M - 2``, the level ``-2`` on
    ``dev_m = tr M + 2``: each is summed where it keeps its accuracy (see
    :class:`stepsafe.core.engine.Jet`)."""

    def __init__(self, method: Method, model: str) -> None:
        self.method = method
        self.model = model

    def jet(self, z, order: int = 1, scale: bool = False) -> Jet:
        return transfer_jet(self.method, np.asarray(z, dtype=float), self.model, scale, order)

    def matrix(self, z) -> np.ndarray:
        return self.jet(z, order=0).M

    def level(self, z, level: float) -> np.ndarray:
        return _at_level(self.jet(z, order=0), level)

    def level_slope(self, level: float):
        def slope(z) -> tuple[np.ndarray, np.ndarray]:
            jet = self.jet(z)
            return _at_level(jet, level), jet.dtrace
        return slope

    def dtrace(self, z) -> np.ndarray:
        return self.jet(z).dtrace

    def dtrace_slope(self, z) -> tuple[np.ndarray, np.ndarray]:
        jet = self.jet(z, order=2)
        return jet.dtrace, jet.d2trace

    def orientation(self, z) -> np.ndarray:
        return orientation(self.jet(z, order=0).D, self.model)


def _at_level(jet: Jet, level: float) -> np.ndarray:
    """``tr M - level`` from the jet, for ``level`` +2 or -2."""
    return jet.dev if level > 0 else jet.dev_m


def _tolerance(jet: Jet, level: float) -> np.ndarray:
    """The rounding bound of ``tr M - level`` (see :data:`~stepsafe.core.engine.TOL_FACTOR`)."""
    return TOL_FACTOR * EPS * (jet.scale if level > 0 else jet.scale_m)


def orientation(D: np.ndarray, model: str) -> np.ndarray:
    """Orientation indicator (> 0: same as the flow) from ``D = M - I``, shape (n, 2, 2).

    oscillator: ``M_qp``; saddle: ``M_qq - M_pp`` (``saddle-p``: the opposite); inverted:
    ``o = M_qp (mu - M_qq) + M_pq (mu - M_pp)`` with ``mu`` the larger multiplier. With
    ``u = (M_qq - M_pp)/2`` and ``r = sqrt(u^2 + M_qp M_pq)`` (the discriminant
    ``tr^2/4 - det``, free of cancellation), ``mu - M_qq = r - u`` and ``mu - M_pp = r + u``;
    whichever of those two cancels is taken as ``M_qp M_pq / (r -+ u)``. ``o`` is
    homogeneous in ``(u, M_qp, M_pq)``, which are first divided by their largest modulus,
    so neither t^2 far out on a barrier (|tr M| ~ 1e200) nor tiny entries over- or
    underflow."""
    a, b, c, d = D[:, 0, 0], D[:, 0, 1], D[:, 1, 0], D[:, 1, 1]
    if model == "oscillator":
        return b
    if model == "saddle":
        return a - d
    if model == "saddle-p":
        return d - a
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        u = 0.5 * (a - d)
        top = np.maximum.reduce([np.abs(u), np.abs(b), np.abs(c)])
        top = np.where(top > 0, top, 1.0)
        u, b, c = u / top, b / top, c / top
        bc = b * c
        r = np.sqrt(np.maximum(u * u + bc, 0.0))
        minus = np.where(u >= 0, bc / (r + u), r - u)  # r - u
        plus = np.where(u >= 0, r + u, bc / (r - u))  # r + u
        return b * minus + c * plus


def classify(jet: Jet, model: str) -> np.ndarray:
    """Per z of the jet: 1 preserved, -1 same type but reversed orientation, 0 otherwise."""
    if ELLIPTIC[model]:
        same_type = (jet.dev < 0.0) & (jet.dev_m > 0.0)
    else:
        same_type = jet.dev > 0.0
    sense = orientation(jet.D, model) > 0
    out = np.zeros(jet.dev.shape, dtype=int)
    out[same_type & sense] = 1
    out[same_type & ~sense] = -1
    return out


#: The smallest zmax analysed: below it, M(z) - I underflows float64 for every method.
MIN_ZMAX = 1e-250


def _validate_zmax(zmax: float) -> float:
    zmax = positive_finite(zmax, "zmax")
    if zmax < MIN_ZMAX:
        raise StepsafeError(f"zmax = {zmax:g} is below {MIN_ZMAX:g}: M(z) - I would underflow "
                            "float64 (give the frequencies and steps in other units)")
    return zmax


def _usable_extent(z: np.ndarray, *values: np.ndarray) -> int:
    """How many leading samples are finite and below :data:`OVERFLOW`."""
    bad = np.zeros(z.shape, dtype=bool)
    for v in values:
        with np.errstate(invalid="ignore"):
            bad |= ~(np.abs(v.reshape(z.size, -1)) < OVERFLOW).all(axis=1)
    return int(np.argmax(bad)) if bad.any() else z.size


def _hidden_extrema(z, t, dt, usable, levels: tuple[float, ...]) -> np.ndarray:
    """Cells where the cubic Hermite interpolant suggests extrema the samples miss, and
    that could matter: the interpolant's range over the cell, widened by the cell's own
    variation, reaches a level. (Far from every level a hidden wiggle cannot change the
    type; chasing it would only chase rounding noise where ``|tr M|`` is huge.)"""
    cubic = HermiteCubic.on_cells(z[:-1], z[1:], t[:-1], t[1:], dt[:-1], dt[1:])
    m0, m1, dtv = cubic.m0, cubic.m1, cubic.dv
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        same = np.sign(m0) * np.sign(m1) > 0
        contrary = same & (np.sign(dtv) * np.sign(m0) < 0)
        qa, qb = 3.0 * cubic.c3, 2.0 * cubic.c2  # p'(u) = m0 + qb u + qa u^2 on (0, 1)
        disc = qb * qb - 4.0 * qa * m0
        vertex = -qb / (2.0 * qa)
        # two roots of p' in (0, 1) although p'(0), p'(1) agree in sign
        dips = same & (disc > 0) & (vertex > 0) & (vertex < 1) & (qa * m0 > 0)
        flagged = np.flatnonzero((contrary | dips) & usable)
        cell = HermiteCubic(*(field[flagged] for field in cubic))
        lo, hi = np.minimum(cell.f0, cell.f0 + cell.dv), np.maximum(cell.f0, cell.f0 + cell.dv)
        root = np.sqrt(np.maximum(disc[flagged], 0.0))
        for sign in (1.0, -1.0):  # the interpolant at its critical points inside the cell
            u = np.clip((-qb[flagged] + sign * root) / (2.0 * qa[flagged]), 0.0, 1.0)
            p = cell.value(np.where(np.isfinite(u), u, 0.0))
            lo, hi = np.minimum(lo, p), np.maximum(hi, p)
        spread = np.maximum.reduce([np.abs(cell.dv), np.abs(cell.m0), np.abs(cell.m1)])
        near = np.zeros(flagged.size, dtype=bool)
        for L in levels:
            near |= (lo - spread <= L) & (L <= hi + spread)
    return flagged[near]


def _merge(z: np.ndarray, extra: np.ndarray, *pairs: tuple[np.ndarray, np.ndarray]):
    """Insert ``extra`` into sorted ``z``, and each ``(values, extra_values)`` alike."""
    order = np.argsort(np.concatenate([z, extra]), kind="stable")
    return (np.concatenate([z, extra])[order],
            *(np.concatenate([v, e])[order] for v, e in pairs))


def _with_samples(ev: _Evaluator, levels: tuple[float, ...], extra: np.ndarray, z, f, dt, D,
                  unc):
    """The samples ``(z, f, dt, D, unc)`` with ``extra`` points evaluated and merged in."""
    jet = ev.jet(extra)
    fe = _level_values(jet, levels)
    return _merge(z, extra, (f, fe), (dt, jet.dtrace), (D, jet.D),
                  (unc, _uncertain(ev, extra, fe, levels)))


class _Samples(NamedTuple):
    z: np.ndarray
    f: np.ndarray  # (n, levels): tr M - level, each level from its accurate form
    dt: np.ndarray
    D: np.ndarray
    uncertain: np.ndarray  # within the rounding bound of a level: the sign is not decided
    end: float  # the last z analysed (below the grid's end when M overflows beyond)


#: Samples this close to a level get their rounding bound computed.
NEAR_LEVEL = 1e-3


def _level_values(jet: Jet, levels: tuple[float, ...]) -> np.ndarray:
    return np.stack([_at_level(jet, L) for L in levels], axis=1)


def _uncertain(ev: _Evaluator, z: np.ndarray, f: np.ndarray,
               levels: tuple[float, ...]) -> np.ndarray:
    """Samples whose distance to some level is within the rounding bound (computed only
    for the few samples near a level)."""
    near = np.flatnonzero((np.abs(f) < NEAR_LEVEL).any(axis=1))
    out = np.zeros(z.size, dtype=bool)
    if near.size:
        jet = ev.jet(z[near], order=0, scale=True)
        tol = np.stack([_tolerance(jet, L) for L in levels], axis=1)
        out[near] = (np.abs(f[near]) <= tol).any(axis=1)
    return out


def _sample(ev: _Evaluator, grid: Grid, levels: tuple[float, ...]) -> _Samples:
    """Sample every segment, refining cells with hidden extrema (not where an end lies
    within rounding of a level: a wiggle there is not resolvable). Stops before the first
    sample where ``M - I`` or its slope leaves the float64 range (:data:`OVERFLOW`)."""
    z = grid.z
    with np.errstate(over="ignore", invalid="ignore"):  # beyond the range: cut just below
        jet = ev.jet(z)
        f, dt, D = _level_values(jet, levels), jet.dtrace, jet.D
        keep = _usable_extent(z, D, jet.dM)
    end = float(grid.edges[-1])
    if keep < z.size:
        if keep == 0:
            raise StepsafeError(f"M(z) overflows float64 already at z = {z[0]:.3g} for this "
                                "method: its coefficients are out of the range stepsafe "
                                "can analyse")
        z, f, dt, D = z[:keep], f[:keep], dt[:keep], D[:keep]
        end = float(z[-1])
    unc = _uncertain(ev, z, f, levels)
    for _ in range(REFINE_LEVELS):
        usable = grid.cells(z) & ~unc[:-1] & ~unc[1:]
        cells = distinct(np.concatenate([_hidden_extrema(z, f[:, i], dt, usable, (0.0,))
                                          for i in range(len(levels))]))
        if cells.size == 0:
            break
        frac = np.arange(1, REFINE_SPLIT) / REFINE_SPLIT
        extra = (z[cells, None] + np.diff(z)[cells, None] * frac[None, :]).ravel()
        z, f, dt, D, unc = _with_samples(ev, levels, extra, z, f, dt, D, unc)
    return _Samples(z, f, dt, D, unc, end)


def _brackets(z: np.ndarray, f: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Cells with a strict sign change of ``f`` (NaN never brackets)."""
    sign = np.sign(f)  # signs, not products: huge values must not overflow
    return np.flatnonzero((sign[:-1] * sign[1:] < 0) & usable)


def find_region(method: Method, model: str = "oscillator", zmax: float = DEFAULT_ZMAX,
                resolution: float | None = None) -> Region:
    """Every interval of ``(0, zmax]`` where ``method`` preserves ``model``'s structure.

    One vectorised pass over all pole-free segments: sample ``tr M`` and its slope, locate
    the extrema by Newton's method on ``d(tr M)/dz``, decide tangencies there, then refine
    every crossing of every level. Points float64 cannot place to the printed digits are
    re-decided at high precision (:mod:`stepsafe.core.escalate`).

    The map analysed is the method's :meth:`~stepsafe.methods.protocol.MethodKind.region_method`
    (a processed method's kernel). A method to which the structure criterion does not apply
    (a Langevin splitting, whose region method is the symplectic part that decides the
    stability of its mean map for every friction) gets that region under the stability
    criterion, marked not symplectic, with the method's ``analysis_note``.
    """
    check_model(model)
    zmax = _validate_zmax(zmax)
    analysed_on(method, model)
    shared = _SHARED.get()
    key = (id(method), model, zmax, resolution)
    if shared is not None and key in shared and shared[key][0] is method:
        return shared[key][1]
    region = _find_region(method.region_method(model), model, zmax, resolution)
    if "structure" not in method.criteria:
        region = replace(under_criterion(region, "stability"), symplectic=False,
                         notes=region.notes + ((method.analysis_note,)
                                               if method.analysis_note else ()))
    if shared is not None:
        shared[key] = (method, region)
    return region


#: The regions found inside a :func:`shared_regions` block, by ``(id(method), model, zmax,
#: resolution)``; each entry holds its method, so that the id stays that method's.
_SHARED: ContextVar[dict[tuple, tuple[Method, Region]] | None] = ContextVar(
    "stepsafe_shared_regions", default=None)


@contextmanager
def shared_regions() -> Iterator[None]:
    """Inside the block, :func:`find_region` analyses each method (the same object), model,
    zmax and resolution once and returns that region again to later calls: a region is
    immutable and its analysis depends on nothing else, so the answers are those of
    separate calls. A command that answers under both criteria (its other criterion's safe
    steps come from the same structure regions) analyses each model once. A block inside
    another shares the outer one's regions; nothing is kept after the outermost ends."""
    if _SHARED.get() is not None:
        yield
        return
    token = _SHARED.set({})
    try:
        yield
    finally:
        _SHARED.reset(token)


def analysed_on(method: Method, model: str) -> None:
    """A :class:`StepsafeError` unless ``method`` is analysed on ``model``."""
    if model not in method.models:
        raise StepsafeError(f"{method.name} (a {method.kind} method) is analysed on the "
                            f"{', '.join(method.models)} model only, not on {model}")


def _find_region(method: Method, model: str, zmax: float, resolution: float | None
                 ) -> Region:
    """The body of :func:`find_region` for the map it analyses."""
    dz = default_resolution(method) if resolution is None else float(resolution)
    ev = _Evaluator(method, model)
    symplectic = residuals(method).symplectic_for(model)
    pole_z, pole_u = pole_locations(method, model)
    # a pole whose uncertainty exceeds its distance from 0 (1/w for a weight w that is 0 up
    # to the rounding of the coefficients) may lie anywhere beyond z^2 / (z + u): nothing
    # there is decided, so the analysis stops below it (its band would reach down to 0)
    # (a splitting's saddle poles: 1/w, w a difference of the coefficients; the eigenvalue
    # bound of an implicit method's poles is a worst case over perturbations, and its
    # poles far beyond zmax are not this kind)
    vague = (pole_z > 0) & (pole_u >= pole_z) & _splitting_on_diagonal(method, model)
    # (z / (1 + u / z): z^2 overflows beyond 1e154, and a NaN would skip the stop)
    undecided_from = float(np.min(pole_z[vague] / (1.0 + pole_u[vague] / pole_z[vague]),
                                  initial=np.inf))
    vague_note: tuple[str, ...] = ()
    if undecided_from < zmax:
        zmax = undecided_from
        vague_note = (f"z above {zmax:.6g} is not analysed: there the float64 rounding of "
                      "the coefficients leaves a pole undecided (a weight that is 0 exactly "
                      "may be computed as 1e-17)",)
    keep = ~vague & (pole_z > 0) & (pole_z < zmax)
    inside = keep
    pole_z = pole_z[inside]
    pole_pts = tuple(Point(float(p), "pole", float(u), "stage system singular")
                     for p, u in zip(pole_z, pole_u[inside]))
    if not symplectic:
        classical = _classical(ev, zmax, dz) if ELLIPTIC[model] else None
        return Region(model, zmax, False, (), (), (), pole_pts, dz, classical,
                      ("not symplectic on this model: the structure is never preserved",))

    far = far_bound(method, model)
    z_end = min(zmax, far * 1.5 + 16 * dz)
    notes: tuple[str, ...] = vague_note
    if z_end > Z_CAP:
        z_end = zmax = Z_CAP
        notes = (f"z above {Z_CAP:g} is not analysed (the deviations of M from its limit "
                 "there fall below the float64 range)",)
        pole_z = pole_z[pole_z < zmax]
        pole_pts = tuple(p for p in pole_pts if p.z < zmax)
    grid = Grid.between_poles(pole_z, z_end, dz)
    grid.z = union(grid.z, _near_poles(pole_z, pole_u[inside][:pole_z.size], z_end))
    work = grid.z.size * method.sample_work
    if work > SAMPLE_WORK_BUDGET:
        raise StepsafeError(
            f"zmax = {zmax:g}: {grid.z.size} samples of M(z), each a stage solve of "
            f"{method.stages} stages, exceed the work budget ({work:.2g} > "
            f"{SAMPLE_WORK_BUDGET:.2g} units, a few seconds): give a smaller zmax")
    levels = (2.0, -2.0) if ELLIPTIC[model] else (2.0,)
    s = _sample(ev, grid, levels)
    z, f, dt, D, unc = s.z, s.f, s.dt, s.D, s.uncertain
    if s.end < z_end:
        zmax = s.end
        notes = (f"M(z) leaves the float64 range beyond z = {s.end:.6g}: not analysed "
                 "further",)
        pole_pts = tuple(p for p in pole_pts if p.z < zmax)
    usable = grid.cells(z)
    if model in DIAGONAL_MODELS:
        extra = _orientation_extrema(ev, z, usable)
        if extra.size:
            z, f, dt, D, unc = _with_samples(ev, levels, extra, z, f, dt, D, unc)
            usable = grid.cells(z)
    # extrema of tr M: roots of d(tr M)/dz, by Newton on its second derivative
    cells = _brackets(z, dt, usable)
    start = hermite_extremum(z[cells], z[cells + 1], f[cells, 0], f[cells + 1, 0], dt[cells],
                             dt[cells + 1])
    ext = refine_brackets(ev.dtrace, z[cells], z[cells + 1], dt[cells], dt[cells + 1],
                          slope=ev.dtrace_slope, start=start)
    ext = np.concatenate([ext, z[dt == 0.0]])
    resonances: list[_Candidate] = []
    if ext.size:
        ej = ev.jet(ext, order=2, scale=True)
        f_ext, curv = _level_values(ej, levels), ej.d2trace
        scales = np.stack([ej.scale if L > 0 else ej.scale_m for L in levels], axis=1)
        tol_ext = TOL_FACTOR * EPS * scales
        unc_ext = (np.abs(f_ext) <= tol_ext).any(axis=1)
        for i, L in enumerate(levels):
            for k in np.flatnonzero(touches(f_ext[:, i], 0.0, scales[:, i])):
                f_ext[k, i] = 0.0  # a tangency: never bracket a root across it
                if _touches_from_inside(model, L, curv[k]):
                    resonances.append(_Candidate(
                        _resonance(ext[k], ej.D[k], L, tol_ext[k, i], curv[k], dz), L,
                        float(tol_ext[k, i])))
        z, f, dt, D, unc = _merge(z, ext, (f, f_ext), (dt, ej.dtrace), (D, ej.D),
                                  (unc, unc_ext))
        usable = grid.cells(z)
    # crossings of every level
    roots_of: list[np.ndarray] = []
    levels_of: list[np.ndarray] = []
    for i, L in enumerate(levels):
        cells = _brackets(z, f[:, i], usable)
        f0, f1 = f[cells, i], f[cells + 1, i]
        start = hermite_root(z[cells], z[cells + 1], f0, f1, dt[cells], dt[cells + 1])
        found = refine_brackets(partial(ev.level, level=L), z[cells], z[cells + 1], f0, f1,
                                slope=ev.level_slope(L), start=start)
        found = np.concatenate([found, z[f[:, i] == 0.0]])
        roots_of.append(found)
        levels_of.append(np.full(found.size, L))
    roots, root_levels = np.concatenate(roots_of), np.concatenate(levels_of)
    keep = ~contains([r.point.z for r in resonances], roots)
    roots, root_levels = roots[keep], root_levels[keep]
    points = [_Candidate(p) for p in pole_pts]
    if roots.size:
        rj = ev.jet(roots, scale=True)
        tol = np.where(root_levels > 0, _tolerance(rj, 2.0), _tolerance(rj, -2.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            width = tol / np.abs(rj.dtrace)
        if not ELLIPTIC[model]:
            # the orientation is decided only where the type is: sample just beside each
            # root, where tr M - 2 clears its rounding bound, so that an axis crossing
            # between a root and the next sample is bracketed; the root's band covers the
            # stretch in between (2.5e-13 of it, below the escalation threshold)
            with np.errstate(over="ignore"):  # a flat root's width may be ~1e308
                delta = np.maximum(4.0 * np.nan_to_num(width, nan=0.0), 2.5e-13 * roots)
            width = np.maximum(width, delta)
            beside = np.concatenate([roots - delta, roots + delta])
            beside = beside[(beside > 0) & (beside < z[-1])]
            if beside.size:
                z, f, dt, D, unc = _with_samples(ev, levels, beside, z, f, dt, D, unc)
                usable = grid.cells(z)
        points += [_Candidate(Point(float(r), "root", float(u), f"tr M = {L:+g}"), L, float(t))
                   for r, u, L, t in zip(roots, width, root_levels, tol)]
    if not ELLIPTIC[model]:
        points += [_Candidate(p) for p in _orientation_switches(ev, z, f[:, 0], D, usable)]
    if model in DIAGONAL_MODELS and resonances:
        # M = +I on a saddle is where the multiplier R crosses 1: tr M - 2 = (R - 1)^2 / R
        # only touches 0, and its rounding bound vanishes there, but R - 1 is wrong by
        # eps sens: the touch is placed only to that over its slope (the orientation's)
        at = np.array([c.point.z for c in resonances])
        wide = _orientation_uncertainty(ev, at)
        resonances = [c._replace(point=c.point._replace(
            uncertainty=float(max(c.point.uncertainty, w)))) for c, w in zip(resonances, wide)]
    points += resonances
    spreads = _within_decided(points, z[~unc], zmax)
    spreads = _escalate(ev, spreads, Escalation(method, model), dz)
    return _assemble(ev, model, zmax, float(z[-1]) if z.size else zmax, spreads, dz, notes)


#: Relative distances from a pole at which the grid samples on both sides: tr M and the
#: orientation change fastest there, and a boundary (e.g. M = +I on the saddle, where the
#: multiplier crosses 1 on its way to 0 at the pole) can lie within 1e-6 of it, much closer
#: than the uniform spacing.
NEAR_POLE = 10.0 ** -np.arange(2, 14)


def _near_poles(pole_z: np.ndarray, pole_u: np.ndarray, z_end: float) -> np.ndarray:
    """Samples approaching each pole geometrically from both sides (outside its
    uncertainty), so that what happens between a pole and the uniform grid is seen."""
    if not pole_z.size:
        return np.empty(0)
    offsets = pole_z[:, None] * NEAR_POLE[None, :]
    keep = offsets > 2.0 * pole_u[:, None]
    z = np.concatenate([(pole_z[:, None] - offsets)[keep], (pole_z[:, None] + offsets)[keep]])
    return z[(z > 0) & (z < z_end) & ~contains(pole_z, z)]


def _splitting_on_diagonal(method: Method, model: str) -> bool:
    """A splitting method (or a composition of one) on the saddle models, whose poles are
    ``1/w`` for the weights ``w`` of its symplectic Euler factors."""
    return model in DIAGONAL_MODELS and all(isinstance(b, Shears)
                                            for b in method.decomposition(model))


#: Models on which M is diagonal for every method (q and p decouple).
DIAGONAL_MODELS = ("saddle", "saddle-p")


def _orientation_extrema(ev: _Evaluator, z: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Extrema of the orientation ``o = +-(M_qq - M_pp)`` inside cells, on the diagonal
    models, to be added as samples.

    There ``M = diag(R, 1/R)``, so ``tr M - 2 = (R - 1)^2 / R`` never changes sign: a dip of
    R below 1 inside one cell is three extrema of tr M (two touches of 2 around a
    maximum) that the cell's ends do not separate, while ``o = R - 1/R`` has one extremum
    there (``o' = R' (1 + 1/R^2)`` vanishes only with R'). A sample at that extremum
    splits the three, so each touch is found on its own. Cells where the cubic
    interpolant of o hides a pair of extrema are split into ``REFINE_SPLIT`` parts."""
    jet = ev.jet(z, order=2)
    sign = 1.0 if ev.model == "saddle" else -1.0
    o = sign * (jet.D[:, 0, 0] - jet.D[:, 1, 1])
    do = sign * (jet.dM[:, 0, 0] - jet.dM[:, 1, 1])
    with np.errstate(invalid="ignore", over="ignore"):
        cells = _brackets(z, do, usable)

        def slope(x):
            j = ev.jet(x, order=2)
            return (sign * (j.dM[:, 0, 0] - j.dM[:, 1, 1]),
                    sign * (j.d2M[:, 0, 0] - j.d2M[:, 1, 1]))

        start = hermite_extremum(z[cells], z[cells + 1], o[cells], o[cells + 1], do[cells],
                                 do[cells + 1])
        ext = refine_brackets(lambda x: slope(x)[0], z[cells], z[cells + 1], do[cells],
                              do[cells + 1], slope=slope, start=start)
        hidden = _hidden_extrema(z, o, do, usable & np.isfinite(o[:-1]) & np.isfinite(o[1:]),
                                 (0.0,))
    frac = np.arange(1, REFINE_SPLIT) / REFINE_SPLIT
    split = (z[hidden, None] + np.diff(z)[hidden, None] * frac[None, :]).ravel()
    extra = np.concatenate([ext[np.isfinite(ext)], split])
    return difference(extra, z)


def _orientation_switches(ev: _Evaluator, z, dev, D, usable) -> list[Point]:
    """Where the expanding direction crosses an axis inside a hyperbolic run: sign changes
    of the orientation between samples that are hyperbolic beyond the rounding bound."""
    o = np.where(dev > 0.0, orientation(D, ev.model), np.nan)
    cells = _brackets(z, o, usable)
    if cells.size:
        ends = np.concatenate([z[cells], z[cells + 1]])
        jet = ev.jet(ends, order=0, scale=True)
        hyper = (jet.dev > TOL_FACTOR * EPS * jet.scale).reshape(2, -1).all(axis=0)
        cells = cells[hyper]
    switches = refine_brackets(ev.orientation, z[cells], z[cells + 1], o[cells], o[cells + 1])
    width = _orientation_uncertainty(ev, switches)
    return [Point(float(r), "orientation", float(u), "expanding direction crosses an axis")
            for r, u in zip(switches, width)]


def _orientation_uncertainty(ev: _Evaluator, z: np.ndarray) -> np.ndarray:
    """The z half-width within which float64 cannot place a sign change of the orientation
    indicator: its rounding bound over its slope. The indicator is computed from the
    entries of ``D = M - I``, each wrong by up to ``eps * sens``, on the barrier after
    division by the largest of them (``top``; 1 on the diagonal models), so it is wrong by
    up to about ``4 eps max(sens) / top``
    (times the usual safety factor); its slope is a central difference."""
    if not z.size:
        return np.empty(0)
    jet = ev.jet(z, order=0, scale=True)
    D = jet.D
    a, b, c, d = D[:, 0, 0], D[:, 0, 1], D[:, 1, 0], D[:, 1, 1]
    top = (np.maximum.reduce([np.abs(0.5 * (a - d)), np.abs(b), np.abs(c)])
           if ev.model == "inverted" else 1.0)  # the diagonal models' o = +-(a - d)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        bound = TOL_FACTOR * EPS * 4.0 * jet.sens.reshape(z.size, -1).max(axis=1) / top
        step = np.maximum(np.abs(z) * 1e-7, 1e-300)
        slope = (ev.orientation(z + step) - ev.orientation(z - step)) / (2.0 * step)
        width = bound / np.abs(slope)
    return np.where(np.isfinite(width), width, np.abs(z))


def touches(t_ext: np.ndarray, level: float, scale: np.ndarray) -> np.ndarray:
    """Tolerance policy: an extremum of ``tr M`` (or of ``tr M -+ 2``, with ``level`` in the
    same terms) within the rounding bound of the level (``TOL_FACTOR * eps * scale``,
    ~1e-13 near ``tr M = -2`` for methods of moderate size) is a tangency and is
    reported as a resonance with the z half-width float64 cannot resolve; anything further
    from the level (e.g. a near-touch at 2 - 1e-9) is an ordinary extremum, and crossings
    around it are ordinary boundaries. Published coefficients are rounded, so an exact
    tangency of the ideal method may show up as a gap ~1e-13 wide or a near miss: both land
    inside this bound and are reported as the resonance they approximate."""
    return np.abs(np.asarray(t_ext) - level) <= TOL_FACTOR * EPS * np.asarray(scale)


def _touches_from_inside(model: str, level: float, curvature: float) -> bool:
    """Whether an extremum touching ``level`` (of ``tr M``) has the preserved type on both
    sides."""
    if ELLIPTIC[model]:
        return curvature < 0 if level > 0 else curvature > 0
    return curvature > 0


def _resonance(z: float, D: np.ndarray, level: float, tol: float, curvature: float,
               dz: float) -> Point:
    sign = 1.0 if level > 0 else -1.0
    M = D + np.eye(2)
    offdiag = max(abs(M[0, 1]), abs(M[1, 0]), abs(M[0, 0] - M[1, 1]))
    detail = ("M = +I" if sign > 0 else "M = -I") if offdiag <= 1e-6 * np.abs(M).max() \
        else f"tangency, tr M = {level:+g}"
    width = np.sqrt(2.0 * tol / abs(curvature)) if curvature != 0 else dz
    return Point(float(z), "resonance", float(width), detail)


class _Candidate(NamedTuple):
    """A point with the level it is a boundary of (None: a pole or an orientation switch)
    and the rounding bound of ``tr M - level`` there."""

    point: Point
    level: float | None = None
    band: float = 0.0


class _Spread(NamedTuple):
    """A candidate and the z-interval that surely holds it."""

    point: Point
    lo: float
    hi: float
    level: float | None = None
    band: float = 0.0


def _within_decided(points: list[_Candidate], decided: np.ndarray,
                    zmax: float) -> list[_Spread]:
    """Each point with the interval that holds it: its uncertainty interval, clipped to the
    nearest samples whose type float64 did decide. (The linearised bound ``tol / |slope|``,
    or ``sqrt(2 tol / |curvature|)``, explodes where ``tr M`` is flat, but the point surely
    lies between those samples.) The reported uncertainty shrinks to match."""
    out = []
    for p, level, band in points:
        u = p.uncertainty if np.isfinite(p.uncertainty) else np.inf
        lo, hi = p.z - u, p.z + u
        if p.kind in ("root", "resonance") and u > 0:
            i = int(np.searchsorted(decided, p.z))
            lo = max(lo, decided[i - 1] if i > 0 else 0.0)
            hi = min(hi, decided[i] if i < decided.size else zmax)
            p = p._replace(uncertainty=float(max(p.z - lo, hi - p.z)))
        out.append(_Spread(p, float(lo), float(hi), level, band))
    return out


def _escalate(ev: _Evaluator, spreads: list[_Spread], esc: Escalation,
              dz: float) -> list[_Spread]:
    """Re-decide at high precision the boundaries float64 places only to worse than
    :data:`~stepsafe.core.escalate.ESCALATE_REL` (see :mod:`stepsafe.core.escalate`)."""
    out: list[_Spread] = []
    # a resonance float64 found is already a touch within the policy (a deeper gap or a
    # wider miss would have shown in float64, whose error its band bounds): kept as it is
    touches = [(c.point.z, c.point.uncertainty) for c in spreads if c.point.kind == "resonance"]
    for c in spreads:
        p = c.point
        vague = p.uncertainty > ESCALATE_REL * p.z and c.lo < c.hi and p.kind != "resonance"
        if vague and p.kind == "pole":
            z = esc.pole(p.z, p.uncertainty)
            if z is not None:
                u = float(np.spacing(z))
                c = c._replace(point=p._replace(z=z, uncertainty=u), lo=z - u, hi=z + u)
            out.append(c)
            continue
        level = c.level
        decision = esc.decide(c.lo, c.hi, level, c.band) \
            if vague and level is not None else None
        if decision is None or level is None:
            out.append(c)
            continue
        if decision.touch is not None:
            if any(abs(decision.touch - t) <= max(u, 1e-9 * t) for t, u in touches):
                continue  # a resonance and rounding noise next to it were one touch
            touches.append((decision.touch, 0.0))
        widths = decision.widths or tuple(float(np.spacing(r)) for r in decision.roots)
        for r, u in zip(decision.roots, widths):
            out.append(_Spread(Point(r, "root", u, f"tr M = {level:+g}"), r - u, r + u,
                               level, c.band))
        if decision.touch is not None:
            jet = ev.jet([decision.touch], order=2)
            q = _resonance(decision.touch, jet.D[0], level, c.band, jet.d2trace[0], dz)
            out.append(_Spread(q, q.z - q.uncertainty, q.z + q.uncertainty, level, c.band))
    return out


def _bands(spreads: list[_Spread]) -> tuple[list[Point], list[tuple[float, float]]]:
    """Merge points whose intervals overlap: two or more boundaries that float64 cannot
    separate (rounding noise where ``|tr M|`` hugs 2 over a stretch of z) become one
    undecided band ``(lo, hi)``; the other points are returned as they are."""
    kept: list[Point] = []
    bands: list[tuple[float, float]] = []
    cluster: list[_Spread] = []

    def close() -> None:
        if len(cluster) == 1:
            kept.append(cluster[0].point)
        elif cluster:
            bands.append((min(c.lo for c in cluster), max(c.hi for c in cluster)))
        cluster.clear()

    reach = -np.inf
    for c in sorted(spreads, key=lambda c: c.point.z):
        if c.lo > reach:
            close()
        cluster.append(c)
        reach = max(reach, c.hi)
    close()
    return kept, bands


def _assemble(ev: _Evaluator, model: str, zmax: float, z_last: float,
              points: list[_Spread], dz: float,
              notes: tuple[str, ...]) -> Region:
    """Intervals between the points, each classified at one interior z (no further out
    than the last sample: beyond it nothing changes); undecided bands are never preserved."""
    unique = {c.point.z: c for c in points if 0.0 < c.point.z < zmax}
    pts, bands = _bands(list(unique.values()))
    undecided = []
    for lo, hi in bands:
        band_lo = Point(max(lo, 0.0), "undecided", 0.0,
                        "float64 cannot decide the type (|tr M| within rounding of 2)")
        if hi >= zmax:
            undecided.append(Interval(band_lo.z, None, band_lo, None))
            pts = [p for p in pts if p.z < band_lo.z] + ([band_lo] if band_lo.z > 0 else [])
            continue
        band_hi = band_lo._replace(z=hi)
        undecided.append(Interval(band_lo.z, hi, band_lo, band_hi))
        pts += [band_hi] + ([band_lo] if band_lo.z > 0 else [])
    pts.sort(key=lambda p: p.z)
    edges = [0.0] + [p.z for p in pts] + [zmax]
    mids = np.array([0.5 * (a + min(b, max(z_last, a))) if b > z_last else 0.5 * (a + b)
                     for a, b in zip(edges[:-1], edges[1:])])
    status = np.zeros(0, dtype=int)
    if mids.size:
        jet = ev.jet(mids, order=0, scale=True)
        status = classify(jet, model)
        # a stretch whose type float64 cannot decide at its midpoint is never preserved
        # (far past a pole |tr M - 2| ~ 1e16 can still be below a rounding bound ~ 1e31 eps)
        blind = np.abs(jet.dev) <= TOL_FACTOR * EPS * jet.scale
        if ELLIPTIC[model]:
            blind |= np.abs(jet.dev_m) <= TOL_FACTOR * EPS * jet.scale_m
        status[blind] = 0
    if undecided:  # a midpoint inside an undecided band (open): sorted starts, running ends
        starts = np.array([band.lo for band in undecided])
        ends = np.array([np.inf if band.hi is None else band.hi for band in undecided])
        order = np.argsort(starts, kind="stable")
        starts, reach = starts[order], np.maximum.accumulate(ends[order])
        k = np.searchsorted(starts, mids, side="left")
        status[(k > 0) & (reach[np.maximum(k - 1, 0)] > mids)] = 0
    intervals: list[Interval] = []
    reversed_: list[Interval] = []
    kept: list[Point] = []
    for i, st in enumerate(status):
        if st == 0:
            continue
        lo_pt = pts[i - 1] if i > 0 else None
        hi_pt = pts[i] if i < len(pts) else None
        lo = edges[i]
        end = None if hi_pt is None else edges[i + 1]
        target = intervals if st == 1 else reversed_
        # extend a run split by a point that is not a real boundary (same status both sides)
        if target and target[-1].hi == lo and lo_pt is not None and lo_pt.kind == "orientation":
            prev = target.pop()
            lo, lo_pt = prev.lo, prev.lo_point
        target.append(Interval(lo, end, lo_pt, hi_pt))
    # resonances: isolated parabolic points with the flow's type on both sides (the
    # orientation may differ across them, e.g. M = -I ends Gauss s=2's first interval)
    for i, p in enumerate(pts):
        if status[i] != 0 and status[i + 1] != 0 and p.kind in ("resonance", "root"):
            kept.append(p if p.kind == "resonance" else Point(p.z, "resonance", p.uncertainty,
                                                               p.detail))
    stability = None
    if ELLIPTIC[model]:
        run_end = next((i for i, st in enumerate(status) if st == 0), len(status))
        stability = (0.0 if run_end == 0 else
                     None if run_end == len(status) else pts[run_end - 1].z)
    pole_pts = tuple(sorted((c.point for c in points if c.point.kind == "pole"
                             and c.point.z <= zmax), key=lambda p: p.z))
    intervals, reversed_ = clear_of_bands(intervals), clear_of_bands(reversed_)
    return Region(model, zmax, True, tuple(intervals), tuple(reversed_), tuple(kept), pole_pts,
                  dz, stability_limit=stability, notes=notes, undecided=tuple(undecided))


def clear_of_bands(intervals: list[Interval]) -> list[Interval]:
    """Each interval shrunk by the uncertainty of the points that end it (see
    :class:`Interval`); one that nothing is left of is dropped (its end points' bands
    overlap: no z in it is decided)."""
    out = []
    for iv in intervals:
        lo = iv.lo + (iv.lo_point.uncertainty if iv.lo_point is not None else 0.0)
        hi = iv.hi
        if hi is not None and iv.hi_point is not None:
            hi = max(hi - iv.hi_point.uncertainty, 0.0)
        if hi is None or lo < hi:
            out.append(iv._replace(lo=lo, hi=hi))
    return out


#: ``structure``: the flow's type and orientation are kept (the default of every command
#: but ``hmc``); ``stability``: the type only, for the oscillator ``|tr M| <= 2`` (bounded
#: iterates: the stability interval quoted in the HMC and splitting literature).
CRITERIA = ("structure", "stability")


def validate_criterion(criterion: object, method: Method | None = None) -> str:
    """``criterion`` if it is one of :data:`CRITERIA` (and applies to ``method``, when
    given), else a :class:`StepsafeError` saying which apply. None is the method's own
    default: ``structure``, or the first that applies to it (``stability`` for a Langevin
    splitting); ``structure`` without a method."""
    if criterion is None:
        return "structure" if method is None else method.criteria[0]
    if not isinstance(criterion, str) or criterion not in CRITERIA:
        raise StepsafeError(f"criterion must be one of {', '.join(CRITERIA)}, got "
                            f"{str(criterion)[:30]!r}")
    if method is not None and criterion not in method.criteria:
        raise StepsafeError(f"the {criterion} criterion does not apply to {method.name}: "
                            f"{method.analysis_note or 'see its method kind'} (criterion "
                            f"{' or '.join(method.criteria)}: --criterion "
                            f"{method.criteria[0]})")
    return criterion


def under_criterion(region: Region, criterion: str) -> Region:
    """``region`` (computed for ``structure``) under ``criterion``.

    ``stability`` keeps every stretch of the flow's type whatever its orientation: the
    reversed islands join the preserved intervals, runs split only by an orientation switch
    merge. Resonances (``M = +-I`` within rounding) stay points of their float64
    uncertainty: a tangency of ``tr M`` to ``+-2`` cannot be told from a gap of width below
    that uncertainty (bcss3's ``M = -I`` point at 2.97632 is, at 60 digits, a gap of width
    1e-13), so it is never counted as stable. A method that is not symplectic keeps no type
    (a centre becomes a spiral) and is returned unchanged.
    """
    criterion = validate_criterion(criterion)
    if criterion == region.criterion or not region.symplectic:
        return region
    if criterion == "structure":
        raise StepsafeError("a region under the stability criterion cannot give the "
                            "structure region back: compute it with find_region")
    runs = sorted(region.intervals + region.reversed, key=lambda iv: iv.lo)
    merged: list[Interval] = []
    for iv in runs:
        last = merged[-1] if merged else None
        if (last is not None and last.hi_point is not None and iv.lo_point is not None
                and iv.lo_point.kind == "orientation" and last.hi_point.z == iv.lo_point.z):
            merged[-1] = Interval(last.lo, iv.hi, last.lo_point, iv.hi_point)
        else:
            merged.append(iv)
    return replace(region, intervals=tuple(merged), reversed=(), criterion=criterion)


#: The rule for rounding gaps that ``hmc`` and ``design`` share (:func:`stable_run`), as
#: their output states it.
ROUNDING_GAP_RULE = (
    "|tr M| past 2 by no more than the float64 rounding of the coefficients (a touch: "
    "M = +-I within rounding, as where the rounded coefficients of a method with an exact "
    "M = -I leave a gap of 1e-13) is a resonance: the steps within its uncertainty are "
    "excluded and listed, and the stable steps continue past it")


class StableRun(NamedTuple):
    """The stable steps from 0 of :func:`stable_run`: they end at ``end`` in z (None:
    stable up to the region's ``zmax``), known to float64's ``uncertainty``; the
    resonances below ``end`` are excluded points, not ends."""

    end: float | None
    uncertainty: float
    resonances: tuple[Point, ...]

    @property
    def first_unsafe(self) -> float | None:
        """``end`` less its uncertainty: every z below it is in the run (resonances
        excepted); None when the run reaches ``zmax``."""
        return None if self.end is None else max(self.end - self.uncertainty, 0.0)

    def reaches(self, z: float) -> bool:
        """Whether every step up to ``z`` is in the run (resonances excepted)."""
        first = self.first_unsafe
        return first is None or first > z


def stable_run(region: Region) -> StableRun:
    """The run of steps from 0 where ``|tr M| <= 2`` (the oscillator's stability
    criterion), under the one rule for rounding gaps that ``hmc`` and ``design`` use
    (:data:`ROUNDING_GAP_RULE`): an extremum of ``tr M`` within the rounding bound of
    ``+-2`` (:func:`touches`) is a resonance, whether float64 shows a touch, a near miss or
    a gap of width below its uncertainty, and it does not end the run. bcss3's published
    coefficients are rounded to 14 digits: at 50 digits their ``tr M`` dips 3.2e-27 below
    -2 over a width of 1e-13 at z = 2.97632, where the ideal method's ``M = -I``; under
    this rule its stable steps end at z = 4.66185 (the literature's interval), the
    resonance excluded. A gap wider than the uncertainty, or a stretch float64 cannot
    decide, ends the run (``Region.stability_limit``, assembled by :func:`find_region`).
    """
    if not region.symplectic or not ELLIPTIC.get(region.model, False):
        raise StepsafeError("a stable run is defined for a symplectic method on an "
                            "elliptic model")
    end = region.stability_limit
    runs = under_criterion(region, "stability")
    uncertainty = next((iv.hi_point.uncertainty for iv in runs.intervals
                        if end is not None and iv.hi_point is not None
                        and iv.hi_point.z == end), 0.0)
    resonances = tuple(r for r in runs.resonances if end is None or r.z < end)
    return StableRun(end, float(uncertainty), resonances)


def spectral_radius(M: np.ndarray) -> np.ndarray:
    """Largest eigenvalue modulus of each 2x2 matrix, in closed form."""
    t = M[:, 0, 0] + M[:, 1, 1]
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    disc = 0.25 * t * t - det
    with np.errstate(invalid="ignore"):
        real = 0.5 * np.abs(t) + np.sqrt(np.maximum(disc, 0.0))
        cplx = np.sqrt(np.maximum(det, 0.0))
    return np.where(disc >= 0, real, cplx)


def classical_interval(method: Method, model: str = "oscillator", zmax: float = DEFAULT_ZMAX,
                       resolution: float | None = None) -> tuple[Interval, ...]:
    """Intervals of z where the spectral radius of M(z) is at most 1 (up to rounding).

    For an RK method on the oscillator this is the imaginary-axis stability interval
    (``|R(iy)| <= 1``); unlike :func:`find_region` it ignores symplecticity and orientation.
    """
    check_model(model)
    zmax = _validate_zmax(zmax)
    analysed_on(method, model)
    method = method.region_method(model)
    return _classical(_Evaluator(method, model), zmax, resolution)


def _classical(ev: _Evaluator, zmax: float, dz: float | None) -> tuple[Interval, ...]:
    """Intervals where the spectral radius of M is at most 1 (+ rounding): classical stability.

    Candidate boundaries: for an RK method on the oscillator the positive roots of the
    stability polynomial ``|Q(iz)|^2 - |P(iz)|^2`` (:mod:`stepsafe.core.rkstability`), else the
    sign changes of the margin on the grid between poles. The status between candidates is
    decided from ``M`` at the midpoints; only candidates with different status on either
    side remain.
    """

    rk_axis = ev.method.single_tableau and ev.model == "oscillator"
    rk = cast(RungeKutta, ev.method)  # (read only when rk_axis)

    def margin(z):  # >= 0 where rho(M) <= 1 up to rounding
        if rk_axis:  # M acts as R(iz) on q + i p: entries Re R, +-Im R; rho = |R|
            R = stability_function(rk, 1j * np.asarray(z))
            return TOL_FACTOR * EPS * 2.0 * (np.abs(R.real) + np.abs(R.imag)) - (np.abs(R) - 1)
        M = ev.matrix(z)
        return TOL_FACTOR * EPS * np.abs(M).sum(axis=(1, 2)) - (spectral_radius(M) - 1.0)

    if rk_axis:
        roots = imaginary_axis_crossings(rk, zmax)
    else:
        dz = default_resolution(ev.method) if dz is None else float(dz)
        grid = Grid.between_poles(poles(ev.method, ev.model), zmax, dz)
        roots = _margin_crossings(ev, grid, margin)
    roots = roots[(roots > 0) & (roots < zmax)]
    cuts = np.concatenate([[0.0], roots, [zmax]])
    ok = margin(0.5 * (cuts[:-1] + cuts[1:])) >= 0
    out: list[Interval] = []
    start = None
    for i, good in enumerate(ok):
        if good and start is None:
            start = i
        if start is not None and (not good or i == ok.size - 1):
            end = i if not good else i + 1  # cuts[end] closes the run
            lo_pt = None if start == 0 else Point(float(cuts[start]), "root", 0.0, "|mu| = 1")
            hi_pt = (None if end == ok.size else
                     Point(float(cuts[end]), "root", 0.0, "|mu| = 1"))
            out.append(Interval(float(cuts[start]), None if hi_pt is None else hi_pt.z,
                                lo_pt, hi_pt))
            start = None
    return tuple(out)


def _margin_crossings(ev: _Evaluator, grid: Grid, margin) -> np.ndarray:
    """Sign changes of the margin on the grid, refined on ``rho(M) - 1`` without bias."""

    def excess(z):
        return spectral_radius(ev.matrix(z)) - 1.0

    z = grid.z
    m = margin(z)
    cells = _brackets(z, m, grid.cells(z))
    e_lo, e_hi = excess(z[cells]), excess(z[cells + 1])
    valid = e_lo * e_hi < 0
    roots = refine_brackets(excess, z[cells][valid], z[cells + 1][valid], e_lo[valid],
                            e_hi[valid])
    return np.sort(np.concatenate([roots, np.where(m[cells] > 0, z[cells],
                                                   z[cells + 1])[~valid]]))
