"""``--verify``: recompute every reported point with mpmath from the method's coefficients.

The method is rebuilt at high precision from its definition, independently of the float64
path (:func:`stepsafe.methods.exact.mp_method`): method files are re-read with the mpmath
backend of the expression evaluator (decimal literals exactly), family tableaux computed
with nodes and weights at raised precision, recipes from their formulas; M(z) is then
computed in mpmath alone (:func:`stepsafe.methods.exact.mp_transfer`, stage equations
solved with mpmath). Each
reported point is re-derived in a bracket around it:

* a boundary (``root``): a sign change of ``tr M -+ 2``, refined at the working precision;
* an ``orientation`` switch: a sign change of the orientation indicator;
* a ``pole``: ``|1/tr M|`` vanishes at it (simple or multiple: palindromic compositions
  repeat a substep's pole);
* a ``resonance``: an extremum of ``tr M`` (root of a central difference) at ``|tr M| = 2``
  within 1e-8; its float64 ``uncertainty`` is part of the allowed discrepancy;
* between the points, the claimed status (preserved, reversed, not preserved) at one
  interior z: a region that says 'never preserved' where the method does preserve, or
  the reverse, fails even when it reports no point at all. Undecided bands claim nothing.

The discrepancy of a point is ``|z_float - z_mp| / z_mp``, less its stated uncertainty.
Imports mpmath, so only the commands run with ``--verify`` (and the tests) load it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from stepsafe.core.regions import Point, Region
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.exact import MPMethod, mp_method, mp_transfer
from stepsafe.reference import highprec as reference

DPS = 40
TOLERANCE = 1e-10


class Check(NamedTuple):
    model: str
    point: Point
    reference: float | None  # the mpmath location (None when no sign change was found)
    discrepancy: float  # |z_float - z_mp| / z_mp; inf when not confirmed
    allowed: float  # TOLERANCE plus the point's stated uncertainty, relative
    #: a status the float answer got wrong on the safe side where it says float64 cannot
    #: decide (see :func:`check_status`): counted, not a failure
    conservative: bool = False

    @property
    def ok(self) -> bool:
        return self.discrepancy <= self.allowed


def _tr(M):
    return M[0, 0] + M[1, 1]


def check_point(Mfun: Callable, model: str, p: Point, dps: int = DPS) -> Check:
    """Re-derive one reported point at ``dps`` digits (see the module docstring)."""
    import mpmath as mp

    allowed = TOLERANCE + p.uncertainty / abs(p.z)
    with mp.workdps(dps):
        z = p.z
        width = max(1e-9 * z, 4 * p.uncertainty)
        lo, hi = mp.mpf(z - width), mp.mpf(z + width)  # (a point at zmax: look past it)
        if p.kind == "pole":
            def signed(x):
                try:
                    return 1 / _tr(Mfun(x, model))
                except ZeroDivisionError:
                    return mp.mpf(0)

            # the pole (odd: a sign change of 1/tr M; even: a zero of |1/tr M|) within
            # twice the stated uncertainty; first the float z itself, where the stage
            # system may be singular exactly (a weight 2^53: a pole at 2^-53 whose residue
            # is so small that 1/tr M is ~ 1/2 all around it but at the point)
            band = max(2 * p.uncertainty, 1e-13 * z)
            found = mp.mpf(z) if signed(mp.mpf(z)) == 0 else reference.locate_pole(
                signed, mp.mpf(z) - band, mp.mpf(z) + band)
            if found is None:
                return Check(model, p, None, float("inf"), allowed)
            return Check(model, p, float(found), float(abs(found - z) / abs(found)), allowed)
        if p.kind in ("root", "nonlinear"):
            level = (2 if "+2" in p.detail else -2) if p.kind == "root" else _level(p.detail)

            def f(x):
                return _tr(Mfun(x, model)) - level
        elif p.kind == "orientation":
            def f(x):
                M = Mfun(x, model)
                if model == "saddle":
                    return M[0, 0] - M[1, 1]
                if model == "saddle-p":
                    return M[1, 1] - M[0, 0]
                t = _tr(M)
                mu = t / 2 + mp.sqrt(max(t * t / 4 - 1, 0))
                return M[0, 1] * (mu - M[0, 0]) + M[1, 0] * (mu - M[1, 1])
        else:
            step = mp.mpf(10) ** (-dps // 3)

            def f(x):
                return (_tr(Mfun(x + step, model)) - _tr(Mfun(x - step, model))) / (2 * step)
        f_lo, f_hi = f(lo), f(hi)
        if f_lo * f_hi > 0:
            return Check(model, p, None, float("inf"), allowed)
        root = reference.refine_root(f, lo, hi) if f_lo * f_hi < 0 else (
            lo if f_lo == 0 else hi)
        if p.kind == "resonance" and abs(abs(_tr(Mfun(root, model))) - 2) > mp.mpf(10) ** -8:
            return Check(model, p, float(root), float("inf"), allowed)
        return Check(model, p, float(root), float(abs(root - z) / abs(root)), allowed)


def _level(detail: str):
    """``2 cos(2 pi m / n)`` at the working precision for a point whose detail starts with
    its resonance ``n:m``."""
    import mpmath as mp

    n, m = (int(k) for k in detail.split()[0].split(":"))
    return 2 * mp.cos(2 * mp.pi * m / n)


def points(region: Region) -> list[Point]:
    """Every distinct point a region reports (interval ends, resonances, poles)."""
    found: dict[tuple, Point] = {}
    for iv in region.intervals + region.reversed:
        for p in (iv.lo_point, iv.hi_point):
            if p is not None and p.kind != "undecided":  # a band's edge claims nothing
                found[(p.z, p.kind)] = p
    for p in region.resonances + region.poles:
        found[(p.z, p.kind)] = p
    return sorted(found.values(), key=lambda p: p.z)


def stretches(region: Region) -> list[tuple[float, float, int | None]]:
    """The region cut at its points and at the edges of their uncertainty bands into
    ``(lo, hi, status)``: 1 preserved, -1 the flow's type with reversed orientation, 0 not
    preserved, None not claimed (an undecided stretch, or within a point's band)."""
    found = points(region)
    bands = [(p.z - p.uncertainty, p.z + p.uncertainty) for p in found if p.uncertainty > 0]
    edges = {p.z for p in found} | {x for band in bands for x in band}
    cuts = sorted({0.0, region.zmax} | {x for x in edges if 0 < x < region.zmax}
                  | {iv.lo for iv in region.undecided}
                  | {iv.hi for iv in region.undecided if iv.hi is not None})
    inf = float("inf")
    covers = [(_covering([(iv.lo, inf if iv.hi is None else iv.hi) for iv in ivs]), value)
              for ivs, value in ((region.intervals, 1), (region.reversed, -1),
                                 (region.undecided, None))]
    in_band = _covering(bands, closed=False)
    out = []
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        mid = 0.5 * (lo + hi)
        status: int | None = 0
        for covered, value in covers:
            if covered(mid):
                status = value
        if in_band(mid):
            status = None
        out.append((lo, hi, status))
    return out


def _covering(spans: list[tuple[float, float]], closed: bool = True) -> Callable:
    """``x -> whether some (a, b) of spans holds x`` (``[a, b]``, or ``(a, b)`` when not
    ``closed``), in O(log n) a query: the spans sorted by start, with the running largest
    end (a linear scan per stretch is quadratic: 28,000 undecided bands on one barrier)."""
    from bisect import bisect_left, bisect_right
    from itertools import accumulate

    spans = sorted(spans)
    starts = [a for a, _ in spans]
    reach = list(accumulate((b for _, b in spans), max))

    def covered(x: float) -> bool:
        k = bisect_right(starts, x) if closed else bisect_left(starts, x)
        return k > 0 and (reach[k - 1] >= x if closed else reach[k - 1] > x)

    return covered


def status_samples(lo: float, hi: float) -> list[float]:
    """Where a stretch's status is re-derived: its middle (geometric on wide stretches)
    and, on the stretch from 0, also 1e-3, 1e-6 and 1e-9 of its end (near 0 every
    consistent method keeps the structure, whatever the grid did)."""
    mid = (lo * hi) ** 0.5 if lo > 0 and hi > 4 * lo else 0.5 * (lo + hi)
    return [mid] + ([hi * 1e-3, hi * 1e-6, hi * 1e-9] if lo == 0 else [])


#: Most digits a status sample is recomputed at (see :func:`check_status`).
STATUS_DIGITS = 1280


def check_status(Mfun: Callable, model: str, z: float, claimed: int,
                 dps: int = DPS, beside_undecided: bool = False) -> Check:
    """Re-derive the status a region claims at z: a 'never preserved' region, a stretch
    claimed preserved that is not, or the reverse, fails here. One exception: a stretch
    claimed 'not preserved' that borders a band float64 says it cannot decide
    (``beside_undecided``), where the reference finds the structure preserved, is a
    ``conservative`` check that passes: float64 cannot resolve the method there (its
    coefficients cancel to far below their size, e.g. drift 2^53 and -2^53 + 1.4), and
    the claim errs on the safe side."""
    import mpmath as mp

    point = Point(z, "status", 0.0, {1: "preserved", -1: "reversed", 0: "not preserved"}[
        claimed])
    # the quantities that decide (tr M -+ 2, M's entries, ...) can be far below 1 (2 - tr M
    # = z^2 for verlet: 1e-42 at z = 1e-21): the precision is raised until each is
    # resolved, up to STATUS_DIGITS
    digits = dps
    while True:
        with mp.workdps(digits):
            try:
                M = Mfun(mp.mpf(z), model)
            except ZeroDivisionError:
                return Check(model, point, z, 0.0 if claimed == 0 else float("inf"),
                             TOLERANCE)
            tr = M[0, 0] + M[1, 1]
            if model == "saddle-p":  # p expands
                deciding = [M[1, 1] - 1, 1 - M[0, 0], M[0, 0]]
            else:  # type and orientation (det M = 1 is the method's, checked elsewhere)
                deciding = reference.constraints(M, model)
            deciding += [2 - abs(tr)] if model == "oscillator" else [tr - 2]
            size = 1 + max(abs(M[i, j]) for i in range(2) for j in range(2))
            resolved = all(abs(g) > mp.mpf(10) ** (8 - digits) * size for g in deciding)
            if resolved or digits >= STATUS_DIGITS:
                same_type = (abs(tr) < 2) if model == "oscillator" else (tr > 2)
                preserved = all(g > 0 for g in deciding[:-1])
                break
        digits *= 2
    actual = 1 if preserved else (-1 if same_type else 0)
    ok = actual == claimed or (claimed == 0 and actual == -1)
    if not ok and claimed == 0 and beside_undecided:
        return Check(model, point, z, 0.0, TOLERANCE, conservative=True)
    return Check(model, point, z if ok else None, 0.0 if ok else float("inf"), TOLERANCE)


def verify_regions(name: str, stages: int | None, base: str | None,
                   regions: dict[str, Region], dps: int = DPS,
                   up_to: float | None = None) -> list[Check]:
    """Check every point of every region and the status claimed between them; with
    ``up_to``, only the first boundary and what lies at z <= up_to (what a check at that z
    depends on)."""
    try:
        return _verify_regions(name, stages, base, regions, dps, up_to)
    except ValueError as exc:  # the reference has no form for the method (on a model)
        raise StepsafeError(f"{name}: --verify cannot recompute this method with mpmath: "
                            f"{exc}") from exc


def _verify_regions(name: str, stages: int | None, base: str | None,
                    regions: dict[str, Region], dps: int, up_to: float | None) -> list[Check]:
    m = mp_method(name, stages, base, dps)
    Mfun = mp_transfer(m)
    if m.kind == "langevin":  # its region is that of its drifts and kicks from the O step
        drift, kick = reference.langevin_hamiltonian_part(m.data["letters"])
        Mfun = mp_transfer(MPMethod("splitting", None, {"drift": drift, "kick": kick}))
    out = []
    for model, region in regions.items():
        first = region.first_boundary_point
        for p in points(region):
            if up_to is None or p.z <= up_to or p == first:
                out.append(check_point(Mfun, model, p, dps))
        if not region.symplectic:
            continue
        # a region capped at a nonlinear resonance claims nothing beyond it (the linear map
        # may well be stable there): only the interval below it is checked
        cap = region.zmax if first is None or first.kind != "nonlinear" else first.z
        undecided_ends = {iv.lo for iv in region.undecided} | {
            iv.hi for iv in region.undecided if iv.hi is not None}
        for lo, hi, claimed in stretches(region):
            if lo >= cap:
                continue
            if claimed is not None and (up_to is None or lo <= up_to) and hi - lo > 1e-9 * hi:
                beside = lo in undecided_ends or hi in undecided_ends
                out += [check_status(Mfun, model, z, claimed, dps, beside)
                        for z in status_samples(lo, hi)]
    return out
