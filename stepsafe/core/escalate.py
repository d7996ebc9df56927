"""High precision for the few points float64 cannot decide.

A boundary or pole whose float64 uncertainty exceeds :data:`ESCALATE_REL` (relative; the
digits stepsafe prints) sits where ``tr M`` crosses ``+-2`` almost flat: next to a
tangency or a double root, or amid ill-conditioned stage solves or eigenvalues. There
float64 cannot tell a touch from a narrow gap or a near miss, nor give the point's digits.
Such points are re-decided with mpmath at :data:`DPS` digits, inside the interval the
float samples bracket them in (a resonance float64 finds is kept as it is: its band bounds
float64's error, so the truth is a touch, or a gap or miss too shallow for the tolerance
policy to tell apart):

* a sign change of ``tr M - L`` between the bracket's ends: one root, refined to full
  precision (uncertainty one ulp);
* no sign change: the extremum of ``tr M`` in the bracket (a root of its derivative),
  whose value decides: within the tolerance policy of ``L`` a resonance (a touch, reported
  as before), beyond it on the far side a gap (two roots, each refined), else a near miss
  (no boundary at all).

The high-precision transfer matrix is the method's own definition where it carries one
(``Method.exact``: decimal literals read exactly, family tableaux at high precision), else
its float coefficients converted exactly. At most :data:`MAX_EVALUATIONS` evaluations
are spent per region, fewer for large implicit methods (:data:`MP_WORK_BUDGET`); points
left over keep their float64 uncertainty, which is honest but wider. Imports mpmath only
when a point needs it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from stepsafe.lazy import lazy_module
from stepsafe.methods.protocol import HIGH_PRECISION_DIGITS
from stepsafe.methods.tableaux import Method

if TYPE_CHECKING:
    from stepsafe.core import mproots
    from stepsafe.methods import exact
else:  # the few points float64 cannot decide
    mproots = lazy_module("stepsafe.core.mproots")
    exact = lazy_module("stepsafe.methods.exact")

DPS = HIGH_PRECISION_DIGITS
ESCALATE_REL = 1e-12
MAX_EVALUATIONS = 300
#: High-precision work per region, in units of :func:`stepsafe.core.grid.sample_work`
#: (one 40-digit evaluation of an 80-unknown stage system, Gauss s = 40, is 512,000 units
#: and takes about 0.2 s here): a 40-stage method gets about 20 evaluations, not 300.
MP_WORK_BUDGET = 1e7

#: ``Mfun(z, model)``: the 2x2 transfer matrix at z (an mpf) as an mpmath matrix.
Reference = Callable[[Any, str], Any]


class Decision(NamedTuple):
    """What high precision found in a bracket: ``roots`` (floats) with their certified
    ``widths``, or a resonance at ``touch`` (its extremum), or neither (a near miss)."""

    roots: tuple[float, ...] = ()
    touch: float | None = None
    widths: tuple[float, ...] = ()


def reference_of(method: Method) -> Reference:
    """The high-precision transfer matrix of ``method``: its own ``exact`` definition when
    it has one, else built from its parts, float coefficients taken as exact
    (:func:`stepsafe.methods.exact.high_precision`)."""
    return exact.high_precision(method)


class _Undecided(Exception):
    """High precision cannot decide the bracket: the reference refused the method (e.g. a
    splitting whose drift and kick sums differ beyond the tolerance has no form on a
    non-separable model), or ``tr M - L`` at the bracket's ends is within the rounding
    noise even at three times the digits (far out, where ``M`` tends to a limit)."""


class Escalation:
    """Decides brackets at high precision for one method and model, within a budget."""

    def __init__(self, method: Method, model: str) -> None:
        self.method = method
        self.model = model
        self._reference: Reference | None = None
        self.evaluations = 0
        self.limit = int(min(MAX_EVALUATIONS, max(8, MP_WORK_BUDGET / method.sample_work)))

    @property
    def exhausted(self) -> bool:
        return self.evaluations >= self.limit

    def _trace(self, z):
        import mpmath as mp

        if self._reference is None:
            self._reference = reference_of(self.method)
        self.evaluations += 1
        try:
            M = self._reference(mp.mpf(z), self.model)
        except ValueError as exc:  # the reference has no form for the method on this model
            self.evaluations = self.limit  # nothing more to ask it
            raise _Undecided from exc
        return M[0, 0] + M[1, 1]

    def decide(self, lo: float, hi: float, level: float, band: float) -> Decision | None:
        """Roots of ``tr M = level`` in ``(lo, hi)``, or a touch within ``band`` of it
        (None when the budget ran out, the bracket holds a pole, or the high-precision
        reference cannot treat the method: then the point keeps its float64 uncertainty,
        which is conservative)."""
        try:
            return self._decide(lo, hi, level, band)
        except _Undecided:
            return None

    def _decide(self, lo: float, hi: float, level: float, band: float) -> Decision | None:
        import mpmath as mp

        if self.exhausted:
            return None
        with mp.workdps(DPS):
            def g(x):
                return self._trace(x) - level

            try:
                a, b = mp.mpf(lo), mp.mpf(hi)
                ga, gb = g(a), g(b)
                if min(abs(ga), abs(gb)) <= _noise(level, DPS):
                    # an end's sign is rounding noise here: ask three times the digits,
                    # and decide nothing more from DPS digits (conservative: None)
                    with mp.workdps(3 * DPS):
                        ga, gb = g(a), g(b)
                    if min(abs(ga), abs(gb)) <= _noise(level, 3 * DPS) \
                            or (ga > 0) == (gb > 0):
                        return None
                    root, width = self._certified_root(level, a, b, (3 * DPS,))
                    return Decision((root,), widths=(width,))
                if (ga > 0) != (gb > 0):
                    root, width = self._certified_root(level, a, b)
                    return Decision((root,), widths=(width,))
                step = mp.mpf(10) ** (-(DPS // 3)) * max(1, abs(b))

                def dg(x):
                    return (g(x + step) - g(x - step)) / (2 * step)

                da, db = dg(a + 2 * step), dg(b - 2 * step)
                if (da > 0) == (db > 0):
                    return Decision()  # monotone, no sign change: no boundary
                zm = mproots.refine_root(dg, a + 2 * step, b - 2 * step, tol=b * mp.mpf("1e-12"))
                gm = g(zm)
            except ZeroDivisionError:
                return None
            if abs(gm) <= band:
                return Decision(touch=float(zm))
            if (gm > 0) != (ga > 0):
                (r1, w1), (r2, w2) = (self._certified_root(level, a, zm),
                                      self._certified_root(level, zm, b))
                return Decision((r1, r2), widths=(w1, w2))
            return Decision()

    def _certified_root(self, level: float, a, b,
                        precisions: tuple[int, ...] = (DPS, 3 * DPS)) -> tuple[float, float]:
        """The root of ``tr M = level`` in ``(a, b)`` (a sign change) and a width the
        evaluation vouches for: the smallest ``u`` (from one ulp, growing 4x) at which
        ``tr M - level`` at ``r -+ u`` clears the working precision's noise with opposite
        signs. At a multiple root (``M = -I`` where ``tr M + 2`` has a triple root,
        Chin's 4A at 2 sqrt 3) the trace is flat to ``(z - r)^k``, so 40 digits place it
        only to about ``10^(-40 / k)``: the root is then redone at three times the digits.
        """
        import mpmath as mp

        def g(x):
            return self._trace(x) - level

        a0, b0 = a, b
        for digits in precisions:
            with mp.workdps(digits):
                if (a, b) != (a0, b0) and _same_sign(g(mp.mpf(a)), g(mp.mpf(b))):
                    # the narrowed bracket lost its sign change at more digits (the root
                    # at fewer digits was rounding noise): back to the whole bracket
                    a, b = a0, b0
                    if _same_sign(g(mp.mpf(a)), g(mp.mpf(b))):
                        raise _Undecided
                r = mproots.refine_root(g, mp.mpf(a), mp.mpf(b), tol=_digits(b))
                noise = _noise(level, digits)
                root = float(r)
                u = float(np.spacing(root))
                while u < ESCALATE_REL * root and not self.exhausted:
                    lo, hi = g(mp.mpf(root) - u), g(mp.mpf(root) + u)
                    if abs(lo) > noise and abs(hi) > noise and (lo > 0) != (hi > 0):
                        return root, u
                    u *= 4.0
            a, b = max(a, mp.mpf(root) - u), min(b, mp.mpf(root) + u)
        return root, u


    def pole(self, z0: float, width: float) -> float | None:
        """The pole float64 put at ``z0 +- width``: where ``1 / tr M`` changes sign
        (``tr M`` passes through infinity), the sign change nearest ``z0`` when the
        bracket is narrow, else the nearest found on a geometric scan of it (an
        ill-conditioned eigenvalue can be off by percent: Gauss s = 27, 37.2 for 36.45).
        None if no pole is found, the budget ran out or the reference cannot treat the
        method."""
        try:
            return self._pole(z0, width)
        except _Undecided:
            return None

    def _pole(self, z0: float, width: float) -> float | None:
        import mpmath as mp

        if self.exhausted:
            return None
        lo, hi = max(z0 - width, z0 / 8), min(z0 + width, 8 * z0)
        count = 2 if width <= 1e-3 * z0 else POLE_SCAN
        with mp.workdps(DPS):
            def g(x):
                try:
                    return 1 / self._trace(x)
                except ZeroDivisionError:  # exactly singular: the pole itself
                    return mp.mpf(0)

            xs = ([mp.mpf(lo), mp.mpf(hi)] if count == 2 else
                  [mp.mpf(lo) * (mp.mpf(hi) / lo) ** (mp.mpf(k) / (count - 1))
                   for k in range(count)])
            gs = [g(x) for x in xs]
            found = []
            for (a, ga), (b, gb) in zip(zip(xs, gs), zip(xs[1:], gs[1:])):
                if ga == 0:
                    found.append(a)
                elif gb != 0 and (ga > 0) != (gb > 0) and not self.exhausted:
                    found.append(mproots.refine_root(g, a, b, tol=_digits(b)))
            if not found and not self.exhausted:  # an even pole: |1/tr M| touches zero
                k = min(range(count), key=lambda i: abs(gs[i]))
                a, b = xs[max(k - 1, 0)], xs[min(k + 1, count - 1)]
                even = mproots.locate_pole(g, a, b, tol=_digits(b))
                found = [] if even is None else [even]
            if not found:
                return None
            return float(min(found, key=lambda x: abs(x - z0)))


#: Samples of a wide pole bracket scanned for sign changes of 1/tr M.
POLE_SCAN = 48


def _same_sign(ga, gb) -> bool:
    """True when ``ga`` and ``gb`` bracket no root (both nonzero, of one sign)."""
    return ga != 0 and gb != 0 and (ga > 0) == (gb > 0)


def _noise(level, digits: int):
    """Size below which ``tr M - level`` at ``digits`` digits is rounding noise."""
    import mpmath as mp

    return mp.mpf(10) ** (8 - digits) * max(1, abs(level))


def _digits(z):
    """Bracket width at which a root is known far beyond float64's digits."""
    import mpmath as mp

    return abs(z) * mp.mpf("1e-22")
