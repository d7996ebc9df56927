"""Multiple time stepping (impulse / r-RESPA): the public :func:`impulse` behind
``stepsafe respa``.

A fast and a slow force on one coordinate (frequencies ``fast`` Omega and ``slow`` omega);
the outer step H of the impulse method built from an outer and an inner splitting with
``substeps`` inner steps per outer drift (:mod:`stepsafe.core.impulse`). The answer: the safe
outer steps, the unstable bands of H between them (with ``Omega H / pi``: the half-period
resonances cluster near whole numbers), and the verdict for a step.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from stepsafe.api import Integrator, _compared
from stepsafe.exceptions import StepsafeError, positive_finite

#: The default search in beta H stops here at most (a slow force 1e6 times the fast one).
ZMAX_CAP = 1e6


@dataclass(frozen=True)
class ImpulseReport:
    """Safe outer steps H of an impulse (r-RESPA) integrator for one fast and one slow
    frequency: ``h_max`` ends the safe interval from 0, ``safe_h`` lists every safe interval
    up to the horizon, ``bands`` the unstable intervals of H between them; with a ``step``,
    ``safe`` is its verdict. ``method`` is the equivalent splitting (a
    :class:`stepsafe.methods.tableaux.Splitting` on the oscillator of frequency ``beta``)."""

    name: str
    substeps: int
    fast: float
    slow: float
    beta: float
    criterion: str
    h_max: float | None
    safe_h: tuple[tuple[float, float | None], ...]
    bands: tuple[Mapping[str, Any], ...]
    horizon: float | None
    step: float | None = None
    safe: bool | None = None
    reason: str | None = None
    time_unit: str | None = None
    method: Any = None
    #: n:m nonlinear resonances of the outer step (n theta = 2 pi m) below h_max, as
    #: ``{"resonance": "3:1", "h": ...}``: Ma, Izaguirre & Skeel's limit near a third of the
    #: fast period is the 3:1
    nonlinear: tuple[Mapping[str, Any], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe respa ... --json`` prints."""
        return {"method": self.name, "substeps": self.substeps, "fast": self.fast,
                "slow": self.slow, "beta": self.beta, "criterion": self.criterion,
                "h_max": self.h_max, "safe_h": [list(iv) for iv in self.safe_h],
                "bands": [copy.deepcopy(dict(b)) for b in self.bands],
                "horizon": self.horizon, "step": self.step, "safe": self.safe,
                "reason": self.reason, "time_unit": self.time_unit,
                "nonlinear_resonances": [dict(r) for r in self.nonlinear]}


def impulse(outer: Integrator | str = "verlet", inner: Integrator | str = "verlet",
            substeps: int = 4, *, fast: float, slow: float, step: float | None = None,
            criterion: str = "stability", zmax: float | None = None,
            time_unit: str | None = None, resonance_order: int | None = None
            ) -> ImpulseReport:
    """The safe outer steps of the impulse method ``outer``/``inner`` with ``substeps``
    inner steps per outer drift, for the fast and slow angular frequencies (rad per
    ``time_unit``); with ``step``, whether it is safe. ``criterion``: ``stability`` (the
    default: |tr M| <= 2, the unstable bands of the impulse literature) or ``structure``
    (also the sense of rotation, reversed by the outer step between Omega H = pi and 2 pi).
    ``zmax`` bounds ``beta H`` searched (default: 1.05 times the inner method's own limit,
    ``Omega H = substeps z*_inner``). A band of
    ``kind`` ``nonlinear`` lies beyond the resonance order asked for, one of ``kind``
    ``resonance`` is where M = +-I within rounding: float64 cannot tell a touch of
    |tr M| = 2 from a narrow gap there (with no slow force, M = -I is an exact touch).
    The outer step rotates by theta(beta H); its nonlinear resonances n theta = 2 pi m
    (orders 3 to 6) are listed, and ``resonance_order`` N keeps H below the first of
    order at most N (the 3:1 is the limit near a third of the fast period that Ma,
    Izaguirre & Skeel, SIAM J. Sci. Comput. 24 (2003) 1951, found for impulse methods).

    >>> report = impulse("verlet", "verlet", 4, fast=10.0, slow=1.0)
    >>> round(10.0 * report.h_max / 3.141592653589793, 4)   # just below Omega H = pi
    0.9649
    """
    from stepsafe.core.advice import Modes, advise, check_step
    from stepsafe.core.impulse import impulse_splitting, total_frequency
    from stepsafe.core.regions import find_region, validate_criterion
    from stepsafe.core.resonances import DEFAULT_ORDERS, nonlinear_resonances, validate_orders
    from stepsafe.units import time_unit as known_time_unit

    criterion = validate_criterion(criterion)
    time_unit = known_time_unit(time_unit)
    fast, slow = _frequency(fast, "fast"), _frequency(slow, "slow")
    if not fast > 0:
        raise StepsafeError("the fast frequency must be > 0")
    outer_i, inner_i = _compared([outer])[0], _compared([inner])[0]
    split = impulse_splitting(outer_i.tableau, inner_i.tableau, substeps, fast, slow)
    beta = total_frequency(fast, slow)
    if not math.isfinite(beta) or beta < 1e-300:
        raise StepsafeError(f"the frequencies {fast:g} and {slow:g} leave float64 together "
                            "(their steps would overflow): give them in units nearer 1")
    if zmax is None:  # up to just past the inner method's own limit, Omega H = K z*_inner
        z_inner = find_region(inner_i.tableau, "oscillator", 40.0).first_boundary or 40.0
        zmax = min(max(4.0, 1.05 * substeps * z_inner * beta / fast), ZMAX_CAP)
    else:
        zmax = positive_finite(zmax, "zmax")
    order = None if resonance_order is None else validate_orders((resonance_order,))[0]
    modes = Modes.from_arrays({"oscillator": [beta]})
    verdict, reason = None, None
    if step is not None:
        step = positive_finite(step, "step")
        result = check_step(split, modes, step, zmax=zmax, name=split.name,
                            criterion=criterion, resonance_order=order)
        adv, verdict = result.advice, result.safe
        reason = None if verdict else result.failures[0].reason
    else:
        adv = advise(split, modes, zmax=zmax, name=split.name, criterion=criterion,
                     resonance_order=order)
    horizon = adv.horizon
    resonances = [(r.z / beta, r.uncertainty / beta)
                  for r in adv.regions["oscillator"].resonances]
    gaps = list(zip([hi for _, hi in adv.safe_h[:-1]], [lo for lo, _ in adv.safe_h[1:]]))
    if adv.safe_h and adv.safe_h[-1][1] is not None and (
            horizon is None or adv.safe_h[-1][1] < horizon * (1 - 1e-12)):
        gaps.append((adv.safe_h[-1][1], horizon))
    first = adv.regions["oscillator"].first_boundary_point
    capped = first is not None and first.kind == "nonlinear"

    def kind(lo: float, hi: float | None) -> str:
        if capped and lo == adv.h_max:
            return "nonlinear"  # beyond the resonance order asked for
        # a gap no wider than a resonance's own uncertainty window around it
        if hi is not None and any(lo <= r <= hi and hi - lo <= 2.0 * u * (1.0 + 1e-9)
                                  for r, u in resonances):
            return "resonance"
        return "unstable"

    bands = [MappingProxyType({
        "lo": lo, "hi": hi, "kind": kind(lo, hi),
        "fast_phase_lo": fast * lo / math.pi,
        "fast_phase_hi": None if hi is None else fast * hi / math.pi}) for lo, hi in gaps]
    safe = tuple((float(lo), None if hi is None else float(hi)) for lo, hi in adv.safe_h)
    orders = tuple(range(3, max(order or 0, max(DEFAULT_ORDERS)) + 1))
    found = nonlinear_resonances(split, find_region(split, "oscillator", zmax), orders)
    nonlinear = tuple(MappingProxyType({"resonance": r.name, "h": r.z / beta,
                                        "uncertainty": r.uncertainty / beta})
                      for r in found)
    return ImpulseReport(split.name, substeps, fast, slow, beta, criterion, adv.h_max, safe,
                         tuple(bands), horizon, step, verdict, reason, time_unit, split,
                         nonlinear)


def _frequency(value: Any, name: str) -> float:
    if isinstance(value, bool):
        raise StepsafeError(f"the {name} frequency must be a number, got a bool")
    try:
        value = float(value)
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError(f"the {name} frequency must be a number, got "
                            f"{str(value)[:40]!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise StepsafeError(f"the {name} frequency must be a finite number >= 0, got {value}")
    return value


__all__ = ["ImpulseReport", "impulse"]
