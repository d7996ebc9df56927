"""The results of :func:`stepsafe.impulse` and :func:`stepsafe.impulse_advice` (impulse,
r-RESPA, methods): frozen objects whose ``to_dict()`` is the ``--json`` output of ``stepsafe
respa`` and of ``advise``/``check`` on an impulse method (see :mod:`stepsafe.api.reports`)."""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

from stepsafe.comparison import compared
from stepsafe.core.records import unversioned, versioned


@compared
@dataclass(frozen=True, eq=False)
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
    nonlinear: tuple[Mapping[str, Any], ...] = ()
    """n:m nonlinear resonances of the outer step (n theta = 2 pi m) below h_max, as
    ``{"resonance": "3:1", "h": ...}``: Ma, Izaguirre & Skeel's limit near a third of the
    fast period is the 3:1"""
    label: str | None = None
    """one mode of several (:class:`ImpulseModesReport`): its name in the scene (None:
    none; in the JSON of the modes only)"""
    ratio: float | None = None
    """``region METHOD --ratio R``: the frequency ratio omega/Omega (slow over fast) of a
    fast frequency 1, so that every step is Omega H (None: frequencies given)"""

    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "method": "name", "nonlinear_resonances": "nonlinear"})

    @property
    def units(self) -> str | None:
        """With a :attr:`ratio`: what the steps are, ``Omega H (fast frequency 1)``."""
        return None if self.ratio is None else "Omega H (fast frequency 1)"

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe respa ... --json`` prints (``region METHOD --ratio R --json``:
        with ``ratio`` and ``units``).

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        out = {"method": self.name, "substeps": self.substeps, "fast": self.fast,
               "slow": self.slow, "beta": self.beta, "criterion": self.criterion,
               "h_max": self.h_max, "safe_h": [list(iv) for iv in self.safe_h],
               "bands": [copy.deepcopy(dict(b)) for b in self.bands],
               "horizon": self.horizon, "step": self.step, "safe": self.safe,
               "reason": self.reason, "time_unit": self.time_unit,
               "nonlinear_resonances": [dict(r) for r in self.nonlinear]}
        if self.ratio is not None:
            out.update(ratio=self.ratio, units=self.units)
        return versioned(out)


@compared
@dataclass(frozen=True, eq=False)
class ImpulseModesReport:
    """Safe outer steps H of an impulse method for several modes, each with its own fast
    and slow frequency (``modes[i]`` is mode i's :class:`ImpulseReport`): ``safe_h`` is
    the intersection of their safe sets up to the nearest ``horizon``, ``h_max`` the end
    of its interval from 0 and ``limiting`` the mode that ends it; with a ``step``,
    ``safe`` and the ``failures`` (mode index, label, reason)."""

    name: str
    substeps: int
    criterion: str
    modes: tuple[ImpulseReport, ...]
    labels: tuple[str | None, ...]
    h_max: float | None
    safe_h: tuple[tuple[float, float | None], ...]
    horizon: float | None
    limiting: int | None
    step: float | None = None
    safe: bool | None = None
    failures: tuple[Mapping[str, Any], ...] = ()
    time_unit: str | None = None
    scene: str | None = None
    analysis: str = "decoupled: each mode's outer step on its own oscillator"
    """how the modes were analysed: each on its own, or (``coupled``) the 2n x 2n step of a
    split stiffness whose parts do not commute (then ``modes`` is empty)"""

    KIND: ClassVar[str] = "impulse"
    """the kind of method"""
    SHARED: ClassVar[tuple[str, ...]] = ("method", "substeps", "criterion", "time_unit",
                                         "step")
    """the keys of each mode's :class:`ImpulseReport` that its row in the JSON leaves out
    (they are the whole report's)"""
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "method": "name", "kind": "KIND", "limiting_mode": "limiting"})

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe advise`` / ``check`` print with ``--json`` for an impulse method.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        modes = []
        for mode in self.modes:
            row = unversioned(mode.to_dict())
            for key in self.SHARED:
                row.pop(key)
            modes.append({"label": mode.label, **row})
        return versioned({"method": self.name, "kind": self.KIND, "substeps": self.substeps,
                "criterion": self.criterion, "time_unit": self.time_unit,
                "scene": self.scene, "h_max": self.h_max,
                "safe_h": [list(iv) for iv in self.safe_h], "horizon": self.horizon,
                "limiting_mode": self.limiting, "step": self.step, "safe": self.safe,
                "failures": [dict(f) for f in self.failures], "analysis": self.analysis,
                "modes": modes})
