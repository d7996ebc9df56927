"""Multiple time stepping (impulse / r-RESPA): the public :func:`impulse` behind
``stepsafe respa``.

A fast and a slow force on one coordinate (frequencies ``fast`` Omega and ``slow`` omega);
the outer step H of the impulse method built from an outer and an inner splitting with
``substeps`` inner steps per outer drift (:mod:`stepsafe.core.impulse`). The answer: the safe
outer steps, the unstable bands of H between them (with ``Omega H / pi``: the half-period
resonances cluster near whole numbers), and the verdict for a step.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from stepsafe.api.inputs import Integrator, named_method
from stepsafe.api.md_reports import ImpulseModesReport, ImpulseReport
from stepsafe.arguments import public
from stepsafe.core.advice import Modes, advise, check_step
from stepsafe.core.impulse import impulse_method as build
from stepsafe.core.impulse import impulse_splitting, total_frequency
from stepsafe.core.regions import find_region, validate_criterion
from stepsafe.core.resonances import DEFAULT_ORDERS, nonlinear_resonances, validate_orders
from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.methods.tableaux import MAX_SUBSTEPS, Impulse
from stepsafe.systems.multiple import coupled_impulse, coupled_impulse_preserved, read_split
from stepsafe.systems.scene import Scene, load_scene, time_unit_in_force
from stepsafe.units import duration, implied_time_unit
from stepsafe.units import time_unit as known_time_unit

#: The default search in beta H stops here at most (a slow force 1e6 times the fast one).
ZMAX_CAP = 1e6
EPS = 2.0**-52


@public()
def impulse(outer: Integrator | str = "verlet", inner: Integrator | str | None = None, *,
            substeps: int | None = None, fast_beta: float, slow_beta: float,
            step: float | str | None = None, criterion: str = "stability",
            zmax: float | None = None, time_unit: str | None = None,
            resonance_order: int | None = None) -> ImpulseReport:
    """The safe outer steps of the impulse method ``outer``/``inner`` with ``substeps``
    inner steps per outer drift, for the fast and slow forces' angular frequencies
    ``fast_beta`` and ``slow_beta`` (rad per ``time_unit``); with ``step`` (in the time
    unit, or a text with a time unit such as ``"2 fs"``), whether it is safe. ``outer``
    may also be an impulse method (a method file of kind ``impulse``, e.g.
    ``"respa-verlet"``): then it brings its inner method and substep count
    (``substeps`` overrides the count); otherwise ``inner``
    defaults to ``"verlet"`` and ``substeps`` to 4. ``criterion``: ``stability`` (the
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

    Parameters
    ----------
    outer : Integrator or str
        The outer method, or an impulse method (see above).
    inner : Integrator or str, optional
        The inner method (default ``verlet``).
    substeps : int, optional
        Inner steps per outer drift (default: the impulse method's, else 4).
    fast_beta, slow_beta : float
        Angular frequencies of the fast and the slow force, rad per time unit.
    step : float or str, optional
        An outer step H to judge, in the time unit or as a text with a time unit.
    criterion : str
        ``stability`` or ``structure`` (see above).
    zmax : float, optional
        How far in beta H (dimensionless) to search (see above).
    time_unit : str, optional
        The unit of every step in and out (default: the time unit of 1/beta).
    resonance_order : int, optional
        N: keep H below the first nonlinear resonance of order at most N.

    Returns
    -------
    ImpulseReport
        ``h_max``, ``safe_h`` and the bands in the time unit (and the verdict on
        ``step``); ``to_dict()`` is ``stepsafe respa --json``.

    Examples
    --------
    >>> report = impulse("verlet", "verlet", substeps=4, fast_beta=10.0, slow_beta=1.0)
    >>> round(10.0 * report.h_max / 3.141592653589793, 4)   # just below Omega H = pi
    0.9649
    >>> impulse("respa-verlet", fast_beta=10.0, slow_beta=1.0).h_max == report.h_max
    True
    """
    method = impulse_method(outer, inner, substeps)
    return _impulse(method, fast_beta, slow_beta, step, criterion, zmax,
                    known_time_unit(time_unit) or implied_time_unit(step), resonance_order)


def impulse_method(outer: Integrator | str = "verlet", inner: Integrator | str | None = None,
                   substeps: int | None = None) -> Any:
    """The :class:`stepsafe.methods.tableaux.Impulse` of an impulse method (name, path or
    :class:`Integrator` of kind ``impulse``) or of an outer and an inner splitting."""
    if isinstance(outer, Impulse) and inner is None:
        return _substeps_of(outer, substeps)
    outer_i = outer if isinstance(outer, Integrator) else named_method(_name(outer, "outer"))
    if outer_i.kind == "impulse":
        if inner is not None:
            raise StepsafeError(f"{outer_i.name} is an impulse method with its own inner "
                                "method: give no inner method")
        return _substeps_of(outer_i.tableau, substeps)
    inner_i = inner if isinstance(inner, Integrator) else named_method(
        _name("verlet" if inner is None else inner, "inner"))
    if inner_i.kind == "impulse":
        raise StepsafeError(f"the inner method {inner_i.name} is itself an impulse method")
    return build(outer_i.tableau, inner_i.tableau, _substeps(4 if substeps is None
                                                             else substeps))


def _substeps_of(method: Any, substeps: int | None) -> Any:
    return method.with_substeps(None if substeps is None else _substeps(substeps))


def _substeps(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_SUBSTEPS:
        raise StepsafeError(f"substeps must be an integer from 1 to {MAX_SUBSTEPS}, got "
                            f"{value!r}")
    return value


def _name(value: Any, role: str) -> str:
    if not isinstance(value, str):
        raise StepsafeError(f"the {role} method must be a name, a path or a "
                            f"stepsafe.Integrator, got {type(value).__name__}")
    return value


def _impulse(method: Any, fast: Any, slow: Any, step: float | str | None, criterion: str,
             zmax: float | None, time_unit: str | None, resonance_order: int | None
             ) -> ImpulseReport:
    criterion = validate_criterion(criterion)
    time_unit = known_time_unit(time_unit)
    fast, slow = _frequency(fast, "fast"), _frequency(slow, "slow")
    if fast == slow == 0:
        raise StepsafeError("the fast and slow frequencies are both 0: nothing to analyse")
    split = impulse_splitting(method, fast, slow)
    beta = total_frequency(fast, slow)
    if not math.isfinite(beta) or beta < 1e-300:
        raise StepsafeError(f"the frequencies {fast:g} and {slow:g} leave float64 together "
                            "(their steps would overflow): give them in units nearer 1")
    if zmax is None:  # up to just past the inner method's own limit, Omega H = K z*_inner
        if fast > 0:
            z_in = find_region(method.inner, "oscillator", 40.0).first_boundary or 40.0
            zmax = 1.05 * method.substeps * z_in * beta / fast
        else:  # the outer method alone, on the slow force
            zmax = 1.05 * (find_region(method.outer, "oscillator", 40.0).first_boundary
                           or 40.0)
        zmax = min(max(4.0, zmax), ZMAX_CAP)
    else:
        zmax = positive_finite(zmax, "zmax")
    order = None if resonance_order is None else validate_orders((resonance_order,))[0]
    modes = Modes.from_arrays({"oscillator": [beta]})
    verdict, reason = None, None
    if step is not None:
        step = _outer_step(step, time_unit)
        result = check_step(split, modes, step, zmax=zmax, name=split.name,
                            criterion=criterion, resonance_order=order)
        adv, verdict = result.advice, result.safe
        reason = None if verdict else (
            f"{result.failures[0].reason}; z = beta H, beta = sqrt(fast^2 + slow^2) = "
            f"{beta:.12g} rad per {time_unit or 'time unit'}")
    else:
        adv = advise(split, modes, zmax=zmax, name=split.name, criterion=criterion,
                     resonance_order=order)
    horizon = adv.horizon
    resonances = [(r.z / beta, r.uncertainty / beta)
                  for r in adv.regions["oscillator"].resonances]
    gaps: list[tuple[float, float | None]] = []
    for (_, hi), (lo, _) in zip(adv.safe_h[:-1], adv.safe_h[1:]):
        assert hi is not None  # only the last safe interval is open
        gaps.append((hi, lo))
    if adv.safe_h and adv.safe_h[-1][1] is not None and (
            horizon is None or adv.safe_h[-1][1] < horizon * (1 - 1e-12)):
        gaps.append((adv.safe_h[-1][1], horizon))
    first = adv.regions["oscillator"].first_boundary_point
    capped = first is not None and first.kind == "nonlinear"

    def kind(lo: float, hi: float | None) -> str:
        if capped and lo == adv.h_max:
            return "nonlinear"  # beyond the resonance order asked for
        # a gap no wider than a resonance's own uncertainty window around it (and the few
        # ulps by which advise takes a gap's start lower: SHRINK)
        if hi is not None and any(lo <= r <= hi and
                                  hi - lo <= 2.0 * u * (1.0 + 1e-9) + 16 * EPS * hi
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
    return ImpulseReport(split.name, method.substeps, fast, slow, beta, criterion, adv.h_max, safe,
                         tuple(bands), horizon, step, verdict, reason, time_unit, split,
                         nonlinear)


def _frequency(value: Any, name: str) -> float:
    if isinstance(value, (bool, str)):
        raise StepsafeError(f"the {name} frequency must be a number (rad per time unit), "
                            f"got {'a bool' if isinstance(value, bool) else 'a text'}")
    try:
        value = float(value)
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError(f"the {name} frequency must be a number, got "
                            f"{str(value)[:40]!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise StepsafeError(f"the {name} frequency must be a finite number >= 0, got {value}")
    return value


def _outer_step(step: Any, time_unit: str | None) -> float:
    """An outer step H: a number in the time unit, or a text with a time unit."""
    return positive_finite(duration(step, "step", time_unit), "step")


@public()
def impulse_advice(method: Integrator | str | None = None, pairs: Any = None, *,
                   labels: Any = None, scene: str | None = None,
                   substeps: int | None = None, step: float | None = None,
                   time_unit: str | None = None, criterion: str = "stability",
                   resonance_order: int | None = None,
                   use_scene_step: bool = False) -> ImpulseModesReport:
    """The safe outer steps of an impulse method for every mode of a system: ``pairs`` is
    a list of ``(fast, slow)`` angular frequencies (rad per ``time_unit``; ``step`` in it,
    or a text with a time unit), or a ``scene``
    file gives them (its ``modes:`` with ``fast:`` and ``slow:``, or ``system:`` with
    ``stiffness_fast``, ``stiffness_slow`` and ``mass``), with the method, ``substeps``,
    the time unit and, when ``use_scene_step``, the step ``h`` to check. Arguments given
    here win over the scene's. Each mode is its own oscillator of frequency
    ``sqrt(fast^2 + slow^2)`` (:func:`impulse`); H is safe when it is safe for every mode.

    Parameters
    ----------
    method : Integrator or str, optional
        The impulse method (default: the scene's).
    pairs : list of (float, float), optional
        ``(fast, slow)`` angular frequencies of each mode, rad per time unit.
    labels : list of str, optional
        The modes' names, in the order of ``pairs``.
    scene : str, optional
        A scene file giving the modes, the method and the step.
    substeps : int, optional
        Inner steps per outer drift (default: the method's).
    step : float or str, optional
        An outer step H to judge, in the time unit or as a text with a time unit.
    time_unit : str, optional
        The unit of every step in and out (default: the scene's, else the time unit of
        1/beta).
    criterion : str
        ``stability`` or ``structure`` (as for :func:`impulse`).
    resonance_order : int, optional
        N: keep H below each mode's first nonlinear resonance of order at most N.
    use_scene_step : bool
        Judge the scene's ``h:`` when ``step`` is not given.

    Returns
    -------
    ImpulseModesReport
        The safe steps for all modes, the limiting mode and each mode's report;
        ``to_dict()`` is ``stepsafe advise SCENE --json`` for an impulse method.

    Examples
    --------
    >>> report = impulse_advice("respa-verlet", [(10.0, 1.0), (4.0, 2.0)])
    >>> report.limiting, round(report.h_max, 6)   # the fastest mode's band near Omega H = pi
    (0, 0.303118)
    """
    import numpy as np

    if not isinstance(use_scene_step, (bool, np.bool_)):
        raise StepsafeError(f"use_scene_step must be True or False, got "
                            f"{type(use_scene_step).__name__}")
    time_unit = time_unit_in_force(known_time_unit(time_unit), scene, step)
    loaded = load_scene(scene, time_unit) if scene is not None else Scene(time_unit=time_unit)
    if method is None:
        if loaded.method is None:
            raise StepsafeError("no method: give an impulse method (or a scene with method:)")
        method = loaded.method.name
    chosen = impulse_method(method, None, substeps if substeps is not None
                            else loaded.substeps)
    errors = None
    if pairs is None:
        if loaded.pairs is not None:
            pairs, labels = loaded.pairs, (labels or loaded.pair_labels)
        elif loaded.system is not None:
            split = read_split(loaded.system, loaded.where, loaded.folder)
            if split.pairs is None:
                if step is None and use_scene_step:
                    step = loaded.h
                return _coupled_advice(chosen, split, step, criterion, resonance_order,
                                       loaded)
            pairs, errors = split.pairs, split.errors
        else:
            raise StepsafeError("no modes: an impulse method needs a fast and a slow "
                                "frequency per mode (modes: [{fast:, slow:}] or system: "
                                "{stiffness_fast:, stiffness_slow:} in a scene file)",
                                loaded.where or None)
    try:
        if np.asarray(pairs).dtype.kind not in "iuf":  # complex, texts, ragged lists
            raise TypeError
        table = np.array(pairs, dtype=float).reshape(-1, 2)
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError("pairs must be a list of (fast, slow) frequencies") from None
    if table.shape[0] == 0:
        raise StepsafeError("pairs is empty: give at least one (fast, slow) pair")
    if labels is not None and (isinstance(labels, str) or not isinstance(labels, (list, tuple))
                               or not all(n is None or isinstance(n, str) for n in labels)):
        raise StepsafeError("labels must be a list of texts (or None), one per mode")
    labels = tuple(labels) if labels is not None else (None,) * table.shape[0]
    if len(labels) != table.shape[0]:
        raise StepsafeError(f"{len(labels)} labels for {table.shape[0]} modes")
    if step is None and use_scene_step:
        step = loaded.h
    if step is not None:
        step = _outer_step(step, loaded.time_unit)
    from_scene = pairs is loaded.pairs and loaded.pairs is not None
    reports_list = []
    for i, (fast, slow) in enumerate(table):
        try:
            reports_list.append(_impulse(chosen, fast, slow, step, criterion, None,
                                         loaded.time_unit, resonance_order))
        except StepsafeError as exc:
            if exc.where or not from_scene:
                raise
            raise StepsafeError(exc.message, f"{loaded.where}::$.modes[{i}]") from None
    reports = tuple(reports_list)
    if errors is not None:  # frequencies known to a relative error: shrink the safe sets
        reports = tuple(_uncertain(r, float(e)) for r, e in zip(reports, errors))
    horizon = min((r.horizon for r in reports if r.horizon is not None), default=None)
    safe_h = _intersection([r.safe_h for r in reports], [r.horizon for r in reports],
                           horizon)
    first = safe_h[0] if safe_h and safe_h[0][0] == 0.0 else None
    h_max = None if first is None else horizon if first[1] is None else first[1]
    limiting = None if not reports else int(np.argmin(
        [np.inf if r.h_max is None else r.h_max for r in reports]))
    failures = tuple(MappingProxyType({"mode": i, "label": labels[i], "reason": r.reason})
                     for i, r in enumerate(reports) if r.safe is False)
    verdict = None if step is None else not failures
    labelled = tuple(dataclasses.replace(r, label=label) for r, label in zip(reports, labels))
    return ImpulseModesReport(chosen.name, chosen.substeps, reports[0].criterion, labelled,
                              labels, h_max, safe_h, horizon, limiting, step, verdict,
                              failures, loaded.time_unit, loaded.where or None)


def _coupled_advice(method: Any, split: Any, step: float | None, criterion: str,
                    resonance_order: int | None, scene: Any) -> ImpulseModesReport:
    """advise/check on a split stiffness whose parts do not commute: the coupled analysis
    of the 2n x 2n outer step (its safe interval from 0; islands are not analysed)."""
    where = f"{split.where}::$.system"
    if validate_criterion(criterion) != "structure":
        raise StepsafeError("the fast and slow parts do not commute, so the modes couple: the "
                            "coupled analysis decides the structure criterion only (give "
                            "--criterion structure)", where)
    if resonance_order is not None:
        raise StepsafeError("the fast and slow parts do not commute: the modes couple and "
                            "have no rotation angle each, so --resonance-order does not "
                            "apply", where)
    result = coupled_impulse(method, split)
    # the matrices analysed carry the whitening's rounding: the boundary is known to a
    # relative EDGE_FACTOR * coupled_error, so h_max is taken that much lower
    h_max = result.h_max * (1 - EDGE_FACTOR * split.coupled_error) \
        if result.h_max < result.horizon else result.h_max
    safe_h = ((0.0, None if result.h_max >= result.horizon else h_max),)
    verdict: bool | None = None
    failures: tuple[Mapping[str, Any], ...] = ()
    if step is not None:
        step = _outer_step(step, scene.time_unit)
        reason = None
        if step >= h_max and result.h_max < result.horizon:
            reason = (f"H = {step:.12g} is at or beyond the end {h_max:.12g} of the safe "
                      "interval from 0 (less the frequencies' float64 uncertainty)")
        elif step > result.h_max:
            reason = (f"H = {step:.12g} is beyond the end {result.h_max:.12g} of the safe "
                      "interval from 0" if result.h_max < result.horizon else
                      f"H = {step:.12g} is beyond the horizon {result.horizon:.12g} analysed")
        elif not coupled_impulse_preserved(method, split, step):
            reason = f"the outer step H = {step:.12g} does not keep the structure"
        verdict = reason is None
        if reason:
            failures = (MappingProxyType({"mode": None, "label": None, "reason": reason}),)
    return ImpulseModesReport(method.name, method.substeps, "structure", (), (),
                              h_max, safe_h, result.horizon, None, step, verdict,
                              failures, scene.time_unit, scene.where or None,
                              result.analysis.replace(
                                  "(the modes do not decouple for this method)",
                                  "(the fast and slow parts do not commute)"))


#: Band edges move by at most this many times the frequencies' relative error (both
#: frequencies and their ratio change).
EDGE_FACTOR = 4.0


def _uncertain(report: ImpulseReport, error: float) -> ImpulseReport:
    """``report`` for frequencies known to a relative ``error``: every safe interval shrunk
    by ``EDGE_FACTOR * error`` at both ends, and the step's verdict with it."""
    import dataclasses

    if error <= 0:
        return report
    d = EDGE_FACTOR * error
    safe = tuple((lo * (1 + d), None if hi is None else hi * (1 - d))
                 for lo, hi in report.safe_h if hi is None or hi * (1 - d) > lo * (1 + d))
    h_max = safe[0][1] if safe and safe[0][0] == 0.0 else None
    verdict, reason = report.safe, report.reason
    if report.step is not None and verdict:
        # (no horizon: nothing above the safe intervals was left unanalysed)
        end = math.inf if report.horizon is None else report.horizon
        inside = any(lo < report.step < (end if hi is None else hi) for lo, hi in safe)
        if not inside:
            verdict = False
            reason = (f"within the frequencies' relative uncertainty {error:.2g} of a band "
                      "edge (from the mass matrix's conditioning)")
    return dataclasses.replace(report, safe_h=safe, h_max=h_max, safe=verdict, reason=reason)


def _intersection(sets: list, horizons: list, horizon: float | None
                  ) -> tuple[tuple[float, float | None], ...]:
    """The common part of interval lists (``hi`` None: up to that list's horizon), as
    intervals up to ``horizon`` (the last ``hi`` None when it reaches it)."""
    top = math.inf if horizon is None else horizon
    current = [(0.0, top)]
    for intervals, own in zip(sets, horizons):
        ends = [(lo, (own if own is not None else math.inf) if hi is None else hi)
                for lo, hi in intervals]
        current = [(max(a, c), min(b, d)) for a, b in current for c, d in ends
                   if max(a, c) < min(b, d)]
    return tuple((lo, None if hi >= top else hi) for lo, hi in sorted(current))
