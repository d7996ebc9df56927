"""Structure-preservation regions as unions of z-intervals (DESIGN §2).

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
``(0, zmax]`` into segments, all sampled in one vectorised pass on a grid of spacing
``resolution`` (plus a geometric run towards 0); ``t`` and ``dt/dz`` are evaluated
together, and cells whose cubic Hermite interpolant hides a pair of extrema are
subdivided. Cells never span a pole. Extrema of ``t`` are located by Newton's method on
``dt/dz`` (the jet carries ``d2t/dz2``), started where the Hermite interpolant is flat;
between consecutive extrema ``t`` is monotone, so every sign change of ``t -+ 2`` between
samples is exactly one boundary, refined by Newton from the Hermite interpolant's root
(all levels together) to the floating-point grid. An extremum whose value is within the
rounding bound ``tol`` of ``+-2`` is a tangency: an isolated *resonance* (e.g.
``M = -I``), reported with the half-width of z within which float64 cannot tell a touch
from a gap, never merged over. The rounding bound is ``tol = TOL_FACTOR * eps * scale``
with ``scale`` the magnitude of the terms summed into ``tr M`` (see
:class:`stepsafe.transfer.Jet`), computed only at the points where a tolerance is decided.

A method that is not symplectic on the model is never preserved (a centre becomes a
spiral for every h > 0); for the oscillator the classical interval ``rho(M) <= 1`` is
reported instead (for RK methods from the stability polynomials, :mod:`.rkstability`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .checks import residuals
from .errors import StepsafeError, positive_finite
from .methods import Composition, Method, PartitionedRK, RungeKutta, Splitting
from .models import ELLIPTIC, check_model
from .rkstability import imaginary_axis_crossings, stability_function
from .roots import EPS, HermiteCubic, hermite_extremum, hermite_root, refine_brackets
from .transfer import Jet, poles, transfer_jet, transfer_matrix

DEFAULT_ZMAX = 10.0
#: Rounding bound factor: |computed tr M - tr M| <= TOL_FACTOR * eps * scale.
TOL_FACTOR = 256.0
#: Cells whose Hermite interpolant hides extrema are split this many times per level.
REFINE_SPLIT = 8
REFINE_LEVELS = 4
MAX_SAMPLES = 400_000


class Point(NamedTuple):
    """A distinguished z: a boundary, resonance or pole, with its float64 uncertainty."""

    z: float
    kind: str  # "root" (|tr M| = 2 crossing), "pole", "resonance", "orientation"
    uncertainty: float = 0.0
    detail: str = ""


class Interval(NamedTuple):
    """An open interval ``(lo, hi)`` of z; ``hi`` is None when it reaches zmax."""

    lo: float
    hi: float | None
    lo_point: Point | None = None
    hi_point: Point | None = None

    def contains(self, z: float) -> bool:
        return self.lo < z and (self.hi is None or z < self.hi)


@dataclass(frozen=True)
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

    @property
    def first_interval(self) -> Interval | None:
        """The interval that starts at 0, if the structure is preserved for small z."""
        if self.intervals and self.intervals[0].lo == 0.0:
            return self.intervals[0]
        return None

    @property
    def first_boundary(self) -> float | None:
        """``z*``: end of the interval from 0; None if it reaches zmax, 0 if there is none."""
        first = self.first_interval
        return 0.0 if first is None else first.hi

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


def default_resolution(method: Method, zmax: float) -> float:
    """Grid spacing: 1/200 in z, divided by how far the substeps reach (sum of |weights|)."""
    reach = _reach(method)
    return max(5e-3 / reach, zmax / MAX_SAMPLES)


def _reach(method: Method) -> float:
    if isinstance(method, Composition):
        flat = method.flattened()
        return float(np.abs(flat.weights).sum()) * _reach(flat.base)
    if isinstance(method, Splitting):
        return float(max(np.abs(method.drift).sum(), np.abs(method.kick).sum(), 1.0))
    if isinstance(method, (RungeKutta, PartitionedRK)):
        prk = method.as_prk()
        return float(max(1.0, np.abs(prk.A_q).sum(axis=1).max(), np.abs(prk.A_p).sum(axis=1).max()))
    return 1.0


class _Evaluator:
    """Vectorised evaluation of the jet and the derived scalar functions for one model."""

    def __init__(self, method: Method, model: str) -> None:
        self.method = method
        self.model = model

    def jet(self, z, order: int = 1, scale: bool = False) -> Jet:
        return transfer_jet(self.method, np.asarray(z, dtype=float), self.model, scale, order)

    def matrix(self, z) -> np.ndarray:
        return transfer_matrix(self.method, np.asarray(z, dtype=float), self.model)

    def trace(self, z) -> np.ndarray:
        M = self.matrix(z)
        return M[:, 0, 0] + M[:, 1, 1]

    def dtrace(self, z) -> np.ndarray:
        return self.jet(z).dtrace

    def trace_slope(self, z) -> tuple[np.ndarray, np.ndarray]:
        jet = self.jet(z)
        return jet.trace, jet.dtrace

    def dtrace_slope(self, z) -> tuple[np.ndarray, np.ndarray]:
        jet = self.jet(z, order=2)
        return jet.dtrace, jet.d2trace

    def orientation(self, z) -> np.ndarray:
        return orientation(self.matrix(z), self.model)


def orientation(M: np.ndarray, model: str) -> np.ndarray:
    """Orientation indicator (> 0: same as the flow) for matrices of shape (n, 2, 2).

    Each M is first divided by its largest entry (the sign is invariant under positive
    scaling), so huge M (|tr M| ~ 1e200 far out on a saddle) cannot overflow ``t^2``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        M = M / np.abs(M).max(axis=(1, 2))[:, None, None]
    a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
    if model == "oscillator":
        return b
    if model == "saddle":
        return a - d
    if model == "saddle-p":
        return d - a
    t = a + d
    mu = 0.5 * (t + np.sqrt(np.maximum(t * t - 4.0 * (a * d - b * c), 0.0)))
    return b * (mu - a) + c * (mu - d)


def classify(M: np.ndarray, model: str, tol: np.ndarray | float = 0.0) -> np.ndarray:
    """Per matrix: 1 preserved, -1 same type but reversed orientation, 0 otherwise.

    ``tol`` widens the parabolic set ``| |tr M| - 2 | <= tol`` counted as not preserved.
    """
    t = M[:, 0, 0] + M[:, 1, 1]
    if ELLIPTIC[model]:
        same_type = np.abs(t) < 2.0 - tol
    else:
        same_type = t > 2.0 + tol
    sense = orientation(M, model) > 0
    out = np.zeros(t.shape, dtype=int)
    out[same_type & sense] = 1
    out[same_type & ~sense] = -1
    return out


def _validate_zmax(zmax: float) -> float:
    return positive_finite(zmax, "zmax")


def _segment_grid(lo: float, hi: float, dz: float, closed_hi: bool) -> np.ndarray:
    n = max(16, int(np.ceil((hi - lo) / dz)))
    frac = np.arange(1, n + (1 if closed_hi else 0)) / n
    z = lo + (hi - lo) * frac
    if lo == 0.0:
        z = np.concatenate([np.geomspace(z[0] * 1e-3, z[0], 13)[:-1], z])
    return z


class _Grid:
    """Samples over all pole-free segments at once; a cell ``(z[i], z[i+1])`` is usable
    only when both ends lie in the same segment (no pole between them)."""

    def __init__(self, edges: list[float], dz: float, closed_hi: bool) -> None:
        self.edges = np.asarray(edges, dtype=float)
        last = len(edges) - 2
        parts = [_segment_grid(lo, hi, dz, closed_hi and i == last)
                 for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])) if hi > lo]
        self.z = np.concatenate(parts) if parts else np.empty(0)

    @classmethod
    def between_poles(cls, pole_z: np.ndarray, zmax: float, dz: float) -> _Grid:
        """The grid on ``(0, zmax]`` split at the poles in it (``zmax`` open if a pole)."""
        pole_z = pole_z[pole_z <= zmax]
        closed = not (pole_z.size and pole_z[-1] == zmax)
        return cls([0.0, *map(float, pole_z), zmax], dz, closed)

    def segment(self, z: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.edges, z, side="left") - 1

    def cells(self, z: np.ndarray) -> np.ndarray:
        """Mask of the usable cells between consecutive points of sorted ``z``."""
        seg = self.segment(z)
        return seg[:-1] == seg[1:]


def _overflow(z: np.ndarray, *values: np.ndarray) -> None:
    bad = np.zeros(z.shape, dtype=bool)
    for v in values:
        bad |= ~np.isfinite(v)
    if bad.any():
        z_bad = float(z[np.argmax(bad)])
        raise StepsafeError(f"M(z) overflows float64 at z = {z_bad:.3g} for this method; "
                            f"analyse a smaller range (--zmax below {z_bad:.3g}, or a smaller h)")


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


def _sample(ev: _Evaluator, grid: _Grid, levels: tuple[float, ...]):
    """Sample every segment, refining cells with hidden extrema; returns z, t, dt, M."""
    z = grid.z
    with np.errstate(over="ignore", invalid="ignore"):
        jet = ev.jet(z)
    t, dt, M = jet.trace, jet.dtrace, jet.M
    _overflow(z, t, dt)
    for _ in range(REFINE_LEVELS):
        cells = _hidden_extrema(z, t, dt, grid.cells(z), levels)
        if cells.size == 0:
            break
        frac = np.arange(1, REFINE_SPLIT) / REFINE_SPLIT
        extra = (z[cells, None] + np.diff(z)[cells, None] * frac[None, :]).ravel()
        ej = ev.jet(extra)
        z, t, dt, M = _merge(z, extra, (t, ej.trace), (dt, ej.dtrace), (M, ej.M))
    return z, t, dt, M


def _brackets(z: np.ndarray, f: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Cells with a strict sign change of ``f`` (NaN never brackets)."""
    sign = np.sign(f)  # signs, not products: huge values must not overflow
    return np.flatnonzero((sign[:-1] * sign[1:] < 0) & usable)


def find_region(method: Method, model: str = "oscillator", zmax: float = DEFAULT_ZMAX,
                resolution: float | None = None) -> Region:
    """Every interval of ``(0, zmax]`` where ``method`` preserves ``model``'s structure.

    One vectorised pass over all pole-free segments: sample ``tr M`` and its slope, locate
    the extrema by Newton's method on ``d(tr M)/dz``, decide tangencies there, then refine
    every crossing of every level together.
    """
    check_model(model)
    zmax = _validate_zmax(zmax)
    dz = default_resolution(method, zmax) if resolution is None else float(resolution)
    ev = _Evaluator(method, model)
    symplectic = residuals(method).symplectic_for(model)
    pole_z = poles(method, model)
    pole_z = pole_z[pole_z <= zmax]
    pole_pts = tuple(Point(float(p), "pole", 1e-14 * float(p), "stage system singular")
                     for p in pole_z)
    if not symplectic:
        classical = _classical(ev, zmax, dz) if ELLIPTIC[model] else None
        return Region(model, zmax, False, (), (), (), pole_pts, dz, classical,
                      ("not symplectic on this model: the structure is never preserved",))

    grid = _Grid.between_poles(pole_z, zmax, dz)
    levels = (2.0, -2.0) if ELLIPTIC[model] else (2.0,)
    z, t, dt, M = _sample(ev, grid, levels)
    # extrema of tr M: roots of d(tr M)/dz, by Newton on its second derivative
    usable = grid.cells(z)
    cells = _brackets(z, dt, usable)
    start = hermite_extremum(z[cells], z[cells + 1], t[cells], t[cells + 1], dt[cells],
                             dt[cells + 1])
    ext = refine_brackets(ev.dtrace, z[cells], z[cells + 1], dt[cells], dt[cells + 1],
                          slope=ev.dtrace_slope, start=start)
    ext = np.concatenate([ext, z[dt == 0.0]])
    resonances: list[Point] = []
    if ext.size:
        ej = ev.jet(ext, order=2, scale=True)
        t_ext, s_ext, curv = ej.trace.copy(), ej.scale, ej.d2trace
        _overflow(ext, s_ext)
        tol_ext = TOL_FACTOR * EPS * s_ext  # the bound used by touches()
        for L in levels:
            for k in np.flatnonzero(touches(t_ext, L, s_ext)):
                t_ext[k] = L  # a tangency: never bracket a root across it
                if _touches_from_inside(model, L, curv[k]):
                    resonances.append(_resonance(ext[k], ej.M[k], L, tol_ext[k], curv[k], dz))
        z, t, dt, M = _merge(z, ext, (t, t_ext), (dt, ej.dtrace), (M, ej.M))
        usable = grid.cells(z)
    # crossings of every level, refined together
    lo_idx, lv = [], []
    for L in levels:
        cells = _brackets(z, t - L, usable)
        lo_idx.append(cells)
        lv.append(np.full(cells.size, L))
    cells, lv = np.concatenate(lo_idx), np.concatenate(lv)
    f0, f1 = t[cells] - lv, t[cells + 1] - lv
    start = hermite_root(z[cells], z[cells + 1], f0, f1, dt[cells], dt[cells + 1])
    roots = refine_brackets(ev.trace, z[cells], z[cells + 1], f0, f1, slope=ev.trace_slope,
                            level=lv, start=start)
    exact = np.concatenate([np.flatnonzero(t == L) for L in levels])
    roots = np.concatenate([roots, z[exact]])
    lv = np.concatenate([lv, t[exact]])
    keep = ~np.isin(roots, [r.z for r in resonances])
    roots, lv = roots[keep], lv[keep]
    points: list[Point] = list(pole_pts)
    if roots.size:
        rj = ev.jet(roots, scale=True)
        _overflow(roots, rj.scale)
        with np.errstate(divide="ignore"):
            unc = TOL_FACTOR * EPS * rj.scale / np.abs(rj.dtrace)
        points += [Point(float(r), "root", float(u), f"tr M = {L:+g}")
                   for r, u, L in zip(roots, unc, lv)]
    if not ELLIPTIC[model]:
        points += _orientation_switches(ev, z, t, M, usable)
    points += resonances
    return _assemble(ev, model, zmax, points, resonances, pole_pts, dz)


def _orientation_switches(ev: _Evaluator, z, t, M, usable) -> list[Point]:
    """Where the expanding direction crosses an axis inside a hyperbolic run: sign changes
    of the orientation between samples that are hyperbolic beyond the rounding bound."""
    o = np.where(t > 2.0, orientation(M, ev.model), np.nan)
    cells = _brackets(z, o, usable)
    if cells.size:
        ends = np.concatenate([z[cells], z[cells + 1]])
        jet = ev.jet(ends, order=0, scale=True)
        hyper = (jet.trace > 2.0 + TOL_FACTOR * EPS * jet.scale).reshape(2, -1).all(axis=0)
        cells = cells[hyper]
    switches = refine_brackets(ev.orientation, z[cells], z[cells + 1], o[cells], o[cells + 1])
    return [Point(float(r), "orientation", 0.0, "expanding direction crosses an axis")
            for r in switches]


def touches(t_ext: np.ndarray, level: float, scale: np.ndarray) -> np.ndarray:
    """Tolerance policy: an extremum of tr M within the rounding bound of ``level``
    (``TOL_FACTOR * eps * scale``, ~1e-13 for methods of moderate size) is a tangency and is
    reported as a resonance with the z half-width float64 cannot resolve; anything further
    from ``level`` (e.g. a near-touch at 2 - 1e-9) is an ordinary extremum, and crossings
    around it are ordinary boundaries. Published coefficients are rounded, so an exact
    tangency of the ideal method may show up as a gap ~1e-13 wide or a near miss: both land
    inside this bound and are reported as the resonance they approximate."""
    return np.abs(np.asarray(t_ext) - level) <= TOL_FACTOR * EPS * np.asarray(scale)


def _touches_from_inside(model: str, level: float, curvature: float) -> bool:
    """Whether an extremum touching ``level`` has the preserved type on both sides."""
    if ELLIPTIC[model]:
        return curvature < 0 if level > 0 else curvature > 0
    return curvature > 0


def _resonance(z: float, M: np.ndarray, level: float, tol: float, curvature: float,
               dz: float) -> Point:
    sign = 1.0 if level > 0 else -1.0
    offdiag = max(abs(M[0, 1]), abs(M[1, 0]), abs(M[0, 0] - M[1, 1]))
    detail = ("M = +I" if sign > 0 else "M = -I") if offdiag <= 1e-6 * np.abs(M).max() \
        else f"tangency, tr M = {level:+g}"
    width = np.sqrt(2.0 * tol / abs(curvature)) if curvature != 0 else dz
    return Point(float(z), "resonance", float(width), detail)


def _assemble(ev: _Evaluator, model: str, zmax: float, points: list[Point],
              resonances: list[Point], pole_pts: tuple[Point, ...], dz: float) -> Region:
    pts = sorted({p.z: p for p in points if 0.0 < p.z < zmax}.values(), key=lambda p: p.z)
    edges = [0.0] + [p.z for p in pts] + [zmax]
    mids = np.array([0.5 * (a + b) for a, b in zip(edges[:-1], edges[1:])])
    status = classify(ev.matrix(mids), model) if mids.size else np.zeros(0, dtype=int)
    intervals: list[Interval] = []
    reversed_: list[Interval] = []
    kept: list[Point] = []
    for i, st in enumerate(status):
        if st == 0:
            continue
        lo_pt = pts[i - 1] if i > 0 else None
        hi_pt = pts[i] if i < len(pts) else None
        lo = edges[i]
        hi = None if hi_pt is None else edges[i + 1]
        target = intervals if st == 1 else reversed_
        # extend a run split by a point that is not a real boundary (same status both sides)
        if target and target[-1].hi == lo and lo_pt is not None and lo_pt.kind == "orientation":
            prev = target.pop()
            lo, lo_pt = prev.lo, prev.lo_point
        target.append(Interval(lo, hi, lo_pt, hi_pt))
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
    return Region(model, zmax, True, tuple(intervals), tuple(reversed_), tuple(kept), pole_pts,
                  dz, stability_limit=stability)


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
    return _classical(_Evaluator(method, model), zmax, resolution)


def _classical(ev: _Evaluator, zmax: float, dz: float | None) -> tuple[Interval, ...]:
    """Intervals where the spectral radius of M is at most 1 (+ rounding): classical stability.

    Candidate boundaries: for an RK method on the oscillator the positive roots of the
    stability polynomial ``|Q(iz)|^2 - |P(iz)|^2`` (:mod:`stepsafe.rkstability`), else the
    sign changes of the margin on the grid between poles. The status between candidates is
    decided from ``M`` at the midpoints; only candidates with different status on either
    side remain.
    """

    rk_axis = isinstance(ev.method, RungeKutta) and ev.model == "oscillator"

    def margin(z):  # >= 0 where rho(M) <= 1 up to rounding
        if rk_axis:  # M acts as R(iz) on q + i p: entries Re R, +-Im R; rho = |R|
            R = stability_function(ev.method, 1j * np.asarray(z))
            return TOL_FACTOR * EPS * 2.0 * (np.abs(R.real) + np.abs(R.imag)) - (np.abs(R) - 1)
        M = ev.matrix(z)
        return TOL_FACTOR * EPS * np.abs(M).sum(axis=(1, 2)) - (spectral_radius(M) - 1.0)

    if rk_axis:
        roots = imaginary_axis_crossings(ev.method, zmax)
    else:
        dz = default_resolution(ev.method, zmax) if dz is None else float(dz)
        grid = _Grid.between_poles(poles(ev.method, ev.model), zmax, dz)
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


def _margin_crossings(ev: _Evaluator, grid: _Grid, margin) -> np.ndarray:
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
