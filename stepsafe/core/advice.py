"""Safe step sizes for a set of frequencies: intersections of unions of intervals
(docs/theory.md#safe-steps-for-many-frequencies).

For modes ``(beta_k, model_k)`` the safe set is ``{h > 0 : beta_k h in R(model_k) for all
k}``, ``R`` the region of :func:`stepsafe.core.regions.find_region`. Its complement in
``(0, zmax]`` is a union of *gaps* ``(a, b)`` (the intervals where the structure is lost,
widened by their float64 uncertainty; resonances and poles are gaps of width twice their
uncertainty), so the unsafe steps are ``U_k U_gaps (a, b) / beta_k`` and the safe steps
their complement, computed by one sort and merge over all modes at once.

A margin ``0 < F <= 1`` means every frequency may be up to ``1/F`` times larger than
given: ``h`` is safe only if the whole z-range ``[beta h, beta h / F]`` lies in ``R``, which
turns each gap into ``(F a, b) / beta``. For the primary interval this is ``h_max = F z* /
beta``.

Only the largest beta of each model bounds ``h_max``; the islands beyond it need every mode,
but only modes whose first gap starts below the horizon ``zmax / beta_max`` can cut them.
``beta = 0`` (a free particle) constrains nothing. Steps beyond ``zmax / beta_max`` are not
analysed and never reported as safe.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from stepsafe.comparison import compared
from stepsafe.core.models import MODELS
from stepsafe.core.regions import (
    DEFAULT_ZMAX,
    Point,
    Region,
    find_region,
    under_criterion,
    validate_criterion,
)
from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.lazy import lazy_module
from stepsafe.methods.tableaux import Method

if TYPE_CHECKING:
    from stepsafe.core import resonances
else:  # with a resonance order only
    resonances = lazy_module("stepsafe.core.resonances")


@compared
@dataclass(frozen=True, eq=False)
class Modes:
    """Frequencies grouped by model: ``betas[model]`` is an array of beta >= 0, and
    ``errors[model]`` (same shape) the relative uncertainty of each: 0 for frequencies the
    user gives, the rounding bound for those computed from a system's matrices. Built by
    :meth:`from_arrays`, the arrays are read-only copies."""

    betas: Mapping[str, np.ndarray]
    errors: Mapping[str, np.ndarray] = field(default_factory=dict)

    def error(self, model: str) -> np.ndarray:
        return self.errors.get(model, np.zeros(self.betas[model].size))

    @classmethod
    def from_pairs(cls, pairs) -> Modes:
        grouped: dict[str, list[float]] = {}
        for beta, model in pairs:
            grouped.setdefault(model, []).append(beta)
        return cls.from_arrays({m: np.asarray(v, dtype=float) for m, v in grouped.items()})

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any],
                    errors: Mapping[str, Any] | None = None) -> Modes:
        out = {}
        errs = {}
        for model, betas in arrays.items():
            if model not in MODELS:
                raise StepsafeError(f"unknown model {model!r}; choose one of {', '.join(MODELS)}")
            betas = np.array(betas, dtype=float).ravel()  # a copy, made read-only
            bad = ~np.isfinite(betas) | (betas < 0)
            if bad.any():
                raise StepsafeError(f"beta must be a finite number >= 0, got {betas[bad][0]} "
                                    f"({model})")
            if betas.size:
                betas.setflags(write=False)
                out[model] = betas
                if errors and model in errors:
                    errs[model] = np.array(errors[model], dtype=float).ravel()
                    errs[model].setflags(write=False)
        if not out:
            raise StepsafeError("no frequencies given (use --beta, --saddle-beta, --inverted-beta "
                                "or --modes)")
        return cls(MappingProxyType(out), MappingProxyType(errs))

    @property
    def count(self) -> int:
        return sum(b.size for b in self.betas.values())


class ModelLimit(NamedTuple):
    model: str
    # (a NamedTuple field may shadow tuple.count; mypy flags every such field)
    count: int  # type: ignore[assignment]
    beta_max: float
    first_boundary: float | None  # z*, None when the first interval reaches zmax
    first_boundary_point: Point | None
    h_limit: float | None  # F (z* - its uncertainty) / beta_max (beta_max at its largest
    # within its stated error); None when unbounded (beta_max = 0 or no z*)


@compared
@dataclass(frozen=True, eq=False)
class Advice:
    """Safe steps for a method and a set of modes."""

    method: str
    margin: float
    h_max: float | None  # end of the safe interval from 0 (None: no limit found)
    safe_h: tuple[tuple[float, float | None], ...]
    limiting: ModelLimit | None
    models: tuple[ModelLimit, ...]
    horizon: float | None  # steps above this were not analysed
    regions: dict[str, Region] = field(default_factory=dict)
    criterion: str = "structure"

    @property
    def h_max_is_horizon(self) -> bool:
        """True when no boundary limits the step below the horizon: ``h_max`` is only how
        far the analysis looked (``zmax / beta_max``), not a safety limit."""
        return (self.h_max is not None and self.horizon is not None
                and self.h_max >= self.horizon * (1.0 - 1e-12))


def validate_margin(margin: float) -> float:
    if isinstance(margin, (bool, str)):
        got = "a bool" if isinstance(margin, bool) else f"the text {margin[:40]!r}"
        raise StepsafeError(f"margin must be a number in (0, 1], got {got}")
    try:
        margin = float(margin)
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError(f"margin must be a number in (0, 1], got {str(margin)[:40]}"
                            ) from None
    if not (0.0 < margin <= 1.0):
        raise StepsafeError(f"margin must be in (0, 1], got {margin}")
    return margin


class Gap(NamedTuple):
    """A closed z-interval ``[a, b]`` where the structure is not preserved, and why."""

    a: float
    b: float
    reason: str
    boundary: float | None = None  # the reported point that starts the gap
    uncertainty: float = 0.0  # its float64 uncertainty (the gap starts this much below it)


def labelled_gaps(region: Region) -> list[Gap]:
    """The complement in ``[0, inf)`` of the preserved intervals, which stop short of their
    end points by the points' float64 uncertainty (a resonance of uncertainty ``u`` is a gap
    of width ``2u``); everything from ``zmax`` on is a gap, since it was not analysed."""
    out: list[Gap] = []
    cursor, why = 0.0, ("not symplectic: never preserved" if not region.symplectic
                        else "not preserved for small z")
    point: tuple[float | None, float] = (None, 0.0)
    for k, iv in enumerate(region.intervals):
        if iv.lo > cursor:
            out.append(Gap(cursor, iv.lo, why, *point))
        if iv.hi is None:
            cursor, why = region.zmax, f"beyond the analysed range zmax = {region.zmax:.6g}"
            point = (None, 0.0)
            break
        p = iv.hi_point
        cursor = iv.hi
        why = _reason(p, first=k == 0 and iv.lo == 0.0)
        point = (iv.hi, 0.0) if p is None else (p.z, p.uncertainty)
    out.append(Gap(cursor, np.inf, why, *point))
    return out


def first_unsafe_z(region: Region) -> float:
    """Where the first gap of :func:`labelled_gaps` starts: the first boundary less its
    uncertainty (0 when that uncertainty covers the whole interval from 0)."""
    return min(g.a for g in labelled_gaps(region))


def _reason(p: Point | None, first: bool) -> str:
    where = "the first boundary z*" if first else "the island boundary"
    if p is None:
        return f"beyond {where}"
    if p.kind == "pole":
        return f"at or beyond {where} = {p.z:.13g}: a pole (the stage equations are singular)"
    if p.kind == "nonlinear":
        return (f"at or beyond the {p.detail} at z = {p.z:.13g} (the resonance order "
                "asked for)")
    if p.kind == "resonance":
        return (f"at or beyond {where} = {p.z:.13g}: a resonance ({p.detail}, "
                f"uncertainty {p.uncertainty:.1g})")
    return f"beyond {where} = {p.z:.13g} ({p.detail})"


def gaps(region: Region) -> np.ndarray:
    """:func:`labelled_gaps` as an array of rows ``[a, b]``."""
    return np.array([(g.a, g.b) for g in labelled_gaps(region)], dtype=float)


def _merge(intervals: np.ndarray) -> np.ndarray:
    """Union of closed intervals (rows ``[a, b]``), sorted and merged."""
    if intervals.size == 0:
        return intervals.reshape(0, 2)
    intervals = intervals[np.argsort(intervals[:, 0], kind="stable")]
    ends = np.maximum.accumulate(intervals[:, 1])
    starts_new = np.concatenate([[True], intervals[1:, 0] > ends[:-1]])
    group = np.cumsum(starts_new) - 1
    lo = intervals[starts_new, 0]
    hi = np.zeros(lo.size)
    np.maximum.at(hi, group, intervals[:, 1])
    return np.column_stack([lo, hi])


def advise(method: Method, modes: Modes, margin: float = 1.0, zmax: float = DEFAULT_ZMAX,
           name: str | None = None, regions: dict[str, Region] | None = None,
           resonance_order: int | None = None, criterion: str = "structure") -> Advice:
    """Safe steps for ``modes`` under ``method`` (see the module docstring), keeping what
    ``criterion`` asks (:data:`stepsafe.core.regions.CRITERIA`; ``regions`` given are
    structure regions). With ``resonance_order`` N, vibrations also keep below the first
    nonlinear resonance of order at most N (:mod:`stepsafe.core.resonances`)."""
    margin = validate_margin(margin)
    criterion = validate_criterion(criterion, method)
    regions = {model: under_criterion(region, criterion)
               for model, region in (regions or {}).items()}
    for model in modes.betas:
        if model not in regions:
            regions[model] = under_criterion(find_region(method, model, zmax), criterion)
    if resonance_order is not None and "oscillator" in modes.betas:
        regions["oscillator"] = resonances.capped_at_resonance(method, regions["oscillator"],
                                                    resonance_order)
    limits: list[ModelLimit] = []
    unsafe: list[np.ndarray] = [np.zeros((0, 2))]
    horizon = np.inf
    tops = {model: _largest(betas, modes.errors.get(model))
            for model, betas in modes.betas.items()}
    with np.errstate(over="ignore"):  # beta ~ 1e-310: the horizon is past every float
        for model in modes.betas:
            if tops[model] > 0:
                horizon = min(horizon, margin * regions[model].zmax / tops[model])
    if horizon == 0.0:
        raise StepsafeError("margin * zmax / beta underflows to 0: no step can be analysed "
                            "(give the frequencies in units nearer 1)")
    for model, betas in modes.betas.items():
        region = regions[model]
        beta_max = float(betas.max())
        z_star = region.first_boundary
        with np.errstate(over="ignore"):
            h_limit = (margin * first_unsafe_z(region) / tops[model]
                       if tops[model] > 0 and z_star is not None else None)
        if h_limit is not None and not np.isfinite(h_limit):
            h_limit = None  # beyond every float: no finite step reaches it
        limits.append(ModelLimit(model, int(betas.size), beta_max, z_star,
                                 region.first_boundary_point, h_limit))
        g = gaps(region)
        # a mode whose every gap starts above the horizon cannot cut the safe set below it:
        # drop those before any sort (beta (1 + r) < F a_min / horizon)
        floor = (margin * float(g[:, 0].min()) / horizon * (1.0 - 1e-12)
                 if np.isfinite(horizon) else 0.0)
        positive, err = _distinct(*_above(betas, modes.errors.get(model), floor))
        if positive.size:
            top = positive * (1.0 + err)
            # a beta known to a relative error r may be (1 -+ r) times itself: each gap
            # widens to (F a / (beta (1 + r)), b / (beta (1 - r)))
            low = np.maximum(positive * (1.0 - err), 0.0)
            with np.errstate(divide="ignore", over="ignore"):  # beta ~ 1e-320: gaps at inf
                # (the two roundings of F a / top, and beta h's in check, may each lift a
                # step by half an ulp: a step below the start taken SHRINK lower has its
                # product beta h below F a, in exact arithmetic and as check computes it)
                lo = (margin * g[:, 0])[None, :] / top[:, None] * SHRINK
                hi = g[:, 1][None, :] / low[:, None]
            # a mode cuts the safe set only below the horizon (and below every float): skip
            # gaps that start above it
            keep = (lo <= horizon) & np.isfinite(lo)
            unsafe.append(np.column_stack([lo[keep], hi[keep]]))
    safe = _complement(_merge(np.concatenate(unsafe)))
    limiting = min((lim for lim in limits if lim.h_limit is not None),
                   key=lambda lim: np.inf if lim.h_limit is None else lim.h_limit, default=None)
    h_max = (safe[0][1] if safe[0][0] == 0.0 else 0.0) if safe else 0.0
    return Advice(name or method.name, margin, h_max, tuple(safe), limiting, tuple(limits),
                  None if horizon == np.inf else float(horizon), regions, criterion)


def _largest(betas: np.ndarray, errors: np.ndarray | None) -> float:
    """The largest ``beta (1 + r)`` (0 if every beta is 0)."""
    if errors is None:
        return float(betas.max())
    return float((betas * (1.0 + errors)).max())


def _above(betas: np.ndarray, errors: np.ndarray | None, floor: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """The betas (with their errors) whose ``beta (1 + r)`` reaches ``floor``, positive."""
    top = betas if errors is None else betas * (1.0 + errors)
    keep = (top >= floor) & (betas > 0)
    return betas[keep], (np.zeros(int(keep.sum())) if errors is None else errors[keep])


def _distinct(betas: np.ndarray, errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct positive betas, each with the largest relative error given for it."""
    keep = betas > 0
    betas, errors = betas[keep], errors[keep]
    if not betas.size:
        return betas, errors
    unique, index = np.unique(betas, return_inverse=True)
    worst = np.zeros(unique.size)
    np.maximum.at(worst, index, errors)
    return unique, worst


def _complement(merged: np.ndarray) -> list[tuple[float, float | None]]:
    """The open intervals of (0, inf) not covered by ``merged``; ``None`` for unbounded."""
    out: list[tuple[float, float | None]] = []
    cursor = 0.0
    for a, b in merged:
        if a > cursor:
            out.append((float(cursor), float(a)))
        cursor = max(cursor, b)
        if cursor == np.inf:
            break
    if cursor < np.inf:
        out.append((float(cursor), None))
    return out


class Failure(NamedTuple):
    """A mode whose structure is lost at the checked step."""

    model: str
    beta: float
    z: float
    reason: str
    h_limit: float | None  # largest safe h for this mode in its primary interval
    # position of the mode among its model's frequencies (a NamedTuple field may shadow
    # tuple.index; mypy flags every such field)
    index: int = -1  # type: ignore[assignment]


@compared
@dataclass(frozen=True, eq=False)
class CheckResult:
    method: str
    h: float
    margin: float
    safe: bool
    in_primary: bool  # h below the end of the safe interval from 0
    n_modes: int
    n_failing: int
    failures: tuple[Failure, ...]  # the worst MAX_REPORTED failing modes (largest z first)
    advice: Advice


MAX_REPORTED = 50


#: A gap's start in h is taken this much lower (relative) than its float quotient, so that
#: every step below it is safe whatever the rounding of the quotient and of beta h.
SHRINK = 1.0 - 4 * float(np.finfo(float).eps)


def check_step(method: Method, modes: Modes, h: float, margin: float = 1.0,
               zmax: float = DEFAULT_ZMAX, name: str | None = None,
               resonance_order: int | None = None, criterion: str = "structure"
               ) -> CheckResult:
    """Is every mode's structure (under ``criterion``) preserved at step ``h`` (with the
    margin)? With ``resonance_order`` N, is every vibration also below its first nonlinear
    resonance of order at most N?"""
    margin = validate_margin(margin)
    criterion = validate_criterion(criterion, method)
    h = positive_finite(h, "h")
    beta_top = max(float(b.max()) for b in modes.betas.values())
    with np.errstate(over="ignore"):
        z_top = 1.05 * (beta_top * h / margin)  # (analysed 5% beyond z / margin)
    if not np.isfinite(z_top):
        if np.isfinite(beta_top * h):
            raise StepsafeError(f"z / margin = {beta_top:g} * {h:g} / {margin:g} is too near "
                                "float64's largest number to analyse beyond it: give the "
                                "frequencies and the step in units where z is nearer 1")
        raise StepsafeError(f"z = beta*h = {beta_top:g} * {h:g} overflows float64: give the "
                            "frequencies and the step in units where their product is finite")
    zmax = max(zmax, z_top)
    regions = {model: under_criterion(find_region(method, model, zmax), criterion)
               for model in modes.betas}
    if resonance_order is not None and "oscillator" in regions:
        regions["oscillator"] = resonances.capped_at_resonance(method, regions["oscillator"],
                                                    resonance_order)
    adv = advise(method, modes, margin, zmax, name, regions, criterion=criterion)
    failures: list[Failure] = []
    n_failing = 0
    for model, betas in modes.betas.items():
        region = regions[model]
        z = betas * h
        err = modes.error(model)
        z_lo, z_hi = z * np.maximum(1.0 - err, 0.0), z * (1.0 + err)
        failing = np.zeros(betas.size, dtype=bool)
        reason = np.full(betas.size, -1)
        gap_list = labelled_gaps(region)
        top = betas * (1.0 + err)
        for k, gap in enumerate(gap_list):
            # both tests, in z and in h (the gap's start as a step, computed as advise does):
            # rounding of beta*h may put h = h_max, the open end advise prints, just below
            # the gap's start in z
            with np.errstate(divide="ignore", over="ignore"):
                enters = (z_hi / margin >= gap.a) | (h >= (margin * gap.a) / top * SHRINK)
            hit = (z_lo <= gap.b) & enters & (betas > 0) & ~failing
            failing |= hit
            reason[hit] = k
        n_failing += int(failing.sum())
        idx = np.flatnonzero(failing)
        idx = idx[np.argsort(-z[idx], kind="stable")][:MAX_REPORTED]
        first_gap = min(g.a for g in gap_list)
        for i in idx:
            # the largest safe h in the interval from 0: the first gap's start (the boundary
            # less its uncertainty), for the largest beta this mode may have
            limit = (float(margin * first_gap / (betas[i] * (1.0 + err[i])) * SHRINK)
                     if region.first_boundary is not None else None)
            gap = gap_list[reason[i]]
            why = gap.reason
            if gap.boundary is not None and z_hi[i] / margin < gap.boundary:
                why = (f"within the float64 uncertainty (±{gap.uncertainty:.1g}) below a "
                       f"boundary, which cannot be certified: {gap.reason}")
            elif err[i] > 0 and z[i] / margin < gap.a:
                why = (f"with beta known to ±{err[i]:.2g} (relative: the rounding of the "
                       f"system's eigenvalues), z may be up to {z_hi[i]:.12g}: {gap.reason}")
            failures.append(Failure(model, float(betas[i]), float(z[i]), why, limit, int(i)))
    failures.sort(key=lambda f: -f.z)
    in_primary = adv.h_max is not None and (h < adv.h_max if adv.h_max else False)
    if adv.safe_h and adv.safe_h[0][0] == 0.0 and adv.safe_h[0][1] is None:
        in_primary = True
    return CheckResult(adv.method, h, margin, n_failing == 0, in_primary, modes.count,
                       n_failing, tuple(failures[:MAX_REPORTED]), adv)
