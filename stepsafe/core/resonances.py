"""Nonlinear resonances: steps where the rotation per step is a rational part of a turn.

On the oscillator the step map is a rotation by theta(z) in its invariant ellipse, with
``tr M(z) = 2 cos theta`` and theta in (0, pi) on the preserved interval from 0. A
nonlinear (anharmonic) force couples the mode to itself and to others through the
harmonics of theta: where ``n theta = 2 pi m`` the low-order terms of the perturbation
are resonant and the discrete dynamics can be unstable although the linear map is stable
(Mandziuk & Schlick 1995 for the implicit midpoint rule; Schlick, Mandziuk, Skeel &
Srinivas 1998, J. Comput. Phys. 140, "Nonlinear resonance artifacts in molecular dynamics
simulations", for Verlet: the 3:1 resonance at ``z = sqrt 3`` and the 4:1 at
``z = sqrt 2``, well below its linear limit ``z = 2``). The resonance of order n with
``0 < m < n/2`` (coprime) is where ``tr M = 2 cos(2 pi m / n)``: its roots are located
on the region finder's grid and refined, with the float64 uncertainty
``16 eps scale / |d tr M / dz|`` of the region finder's own rounding bound. Order 2
(``theta = pi``, ``M = -I``) is the linear limit itself, and order 1 (``theta = 0``) is
``z = 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from stepsafe.comparison import compared
from stepsafe.core.accuracy import hamiltonian_only
from stepsafe.core.engine import TOL_FACTOR
from stepsafe.core.grid import Grid, default_resolution
from stepsafe.core.regions import Interval, Point, Region, clear_of_bands
from stepsafe.core.roots import EPS, refine_brackets
from stepsafe.core.transfer import transfer_jet
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method

#: The orders shown by ``region`` and ``advise``: n = 3, 4, 5, 6.
DEFAULT_ORDERS = (3, 4, 5, 6)
#: Orders above this are refused: the resonances of order n are n/2 apart in theta / (2 pi)
#: fractions, and dense beyond use.
MAX_ORDER = 50


@compared
@dataclass(frozen=True, eq=False)
class NonlinearResonance:
    """``n theta(z) = 2 pi m`` at ``z`` (within ``uncertainty``): the n:m resonance."""

    n: int
    m: int
    z: float
    uncertainty: float

    @property
    def name(self) -> str:
        return f"{self.n}:{self.m}"

    @property
    def level(self) -> float:
        """The value of ``tr M`` there: ``2 cos(2 pi m / n)``."""
        return 2.0 * math.cos(2.0 * math.pi * self.m / self.n)


def fractions(orders: tuple[int, ...]) -> list[tuple[int, int]]:
    """Every ``(n, m)`` with n in ``orders``, ``0 < m < n/2`` and gcd(n, m) = 1."""
    return [(n, m) for n in sorted(set(orders)) for m in range(1, (n + 1) // 2)
            if math.gcd(n, m) == 1 and 2 * m < n]


def validate_orders(orders) -> tuple[int, ...]:
    """``orders`` as a tuple of whole numbers from 3 to :data:`MAX_ORDER` (not texts, not
    bools, not fractions), else a StepsafeError."""
    from numbers import Integral

    items = None if isinstance(orders, (str, bytes)) else \
        list(orders) if isinstance(orders, (list, tuple, range)) else None
    if not items or any(isinstance(n, bool) or not isinstance(n, Integral)
                        or not 3 <= int(n) <= MAX_ORDER for n in items):
        raise StepsafeError(f"resonance orders must be integers from 3 to {MAX_ORDER} (2 is the "
                            f"linear limit M = -I), got {str(orders)[:40]}")
    return tuple(int(n) for n in items)


def nonlinear_resonances(method: Method, region: Region,
                         orders: tuple[int, ...] = DEFAULT_ORDERS
                         ) -> tuple[NonlinearResonance, ...]:
    """Every n:m resonance of the given orders in the preserved interval from 0 of the
    oscillator ``region`` (up to its ``zmax`` when it has no end), sorted by z."""
    return rotations(method, region, fractions(orders))


def rotations(method: Method, region: Region, pairs: list[tuple[int, int]]
              ) -> tuple[NonlinearResonance, ...]:
    """Every z in the preserved interval from 0 of the oscillator ``region`` where
    ``n theta(z) = 2 pi m`` for the given ``(n, m)`` (``0 < 2 m < n``), sorted by z."""
    first = region.first_interval
    if region.model != "oscillator" or first is None:
        return ()
    hamiltonian_only(method)  # a rotation angle theta is a symplectic map's
    z_end = region.zmax if first.hi is None else first.hi
    dz = default_resolution(method)
    z = Grid.between_poles(np.empty(0), z_end, dz).z
    z = z[z < z_end]
    if z.size < 2:
        return ()
    with np.errstate(all="ignore"):
        jet = transfer_jet(method, z, "oscillator", scale=False, order=1)
    t, dt = jet.trace, jet.dtrace
    usable = np.isfinite(t) & np.isfinite(dt)
    # the extrema of tr M inside cells join the samples, so that every level crossed
    # twice within one cell is seen as two sign changes
    cells = np.flatnonzero((np.sign(dt[:-1]) * np.sign(dt[1:]) < 0) & usable[:-1] & usable[1:])
    if cells.size:
        def slope(x):
            return transfer_jet(method, x, "oscillator", order=1).dtrace

        ext = refine_brackets(slope, z[cells], z[cells + 1], dt[cells], dt[cells + 1])
        ej = transfer_jet(method, ext, "oscillator", order=1)
        order = np.argsort(np.concatenate([z, ext]), kind="stable")
        z = np.concatenate([z, ext])[order]
        t = np.concatenate([t, ej.trace])[order]
        usable = np.concatenate([usable, np.isfinite(ej.trace)])[order]
    found: list[NonlinearResonance] = []
    for n, m in pairs:
        level = 2.0 * math.cos(2.0 * math.pi * m / n)
        f = t - level
        cells = np.flatnonzero((f[:-1] * f[1:] < 0) & usable[:-1] & usable[1:])
        roots = np.concatenate([
            refine_brackets(lambda x: transfer_jet(method, x, "oscillator", order=0).trace,
                            z[cells], z[cells + 1], f[cells], f[cells + 1], level=level),
            z[(f == 0) & usable]])
        if not roots.size:
            continue
        rj = transfer_jet(method, roots, "oscillator", scale=True, order=1)
        bound = TOL_FACTOR * EPS * (np.maximum(rj.scale, rj.scale_m) + abs(level))
        with np.errstate(divide="ignore"):
            width = bound / np.abs(rj.dtrace)
        found += [NonlinearResonance(n, m, float(r), float(u)) for r, u in zip(roots, width)]
    return tuple(sorted(found, key=lambda r: r.z))


def first_resonance(method: Method, region: Region, order: int
                    ) -> NonlinearResonance | None:
    """The resonance of order at most ``order`` with the smallest z (None: none)."""
    orders = tuple(range(3, validate_orders((order,))[0] + 1))
    found = nonlinear_resonances(method, region, orders)
    return found[0] if found else None


def capped_at_resonance(method: Method, region: Region, order: int) -> Region:
    """``region`` with its preserved interval from 0 ending at the first resonance of order
    at most ``order`` (and nothing beyond it: islands are past the resonance), so that
    advice and checks keep every step below it."""
    res = first_resonance(method, region, order)
    if res is None:
        return region
    point = Point(res.z, "nonlinear", res.uncertainty,
                  f"{res.name} nonlinear resonance, {res.n} theta = 2 pi"
                  + (f" {res.m}" if res.m > 1 else ""))
    first = region.first_interval
    assert first is not None  # a resonance lies inside it
    capped = clear_of_bands([Interval(0.0, res.z, first.lo_point, point)])
    return replace(region, intervals=tuple(capped),
                   reversed=(), resonances=tuple(p for p in region.resonances if p.z < res.z))
