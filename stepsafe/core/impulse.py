"""Impulse / r-RESPA multiple time stepping on one coordinate with a fast and a slow force.

Model (Tuckerman, Berne & Martyna, J. Chem. Phys. 97 (1992) 1990; Garcia-Archilla,
Sanz-Serna & Skeel, SIAM J. Sci. Comput. 20 (1998) 930): ``q'' = -(Omega^2 + omega^2) q``.
One outer step H does the outer splitting with its kicks over the slow force ``-omega^2 q``
only, and each of its drifts ``a H`` by ``substeps`` steps of the inner splitting over the
fast force ``-Omega^2 q`` (step ``a H / substeps``). Outer Verlet with inner Verlet is
r-RESPA / Verlet-I: ``K_slow(H/2) [Phi_fast(H/k)]^k K_slow(H/2)``.

On the oscillator of the total frequency ``beta = sqrt(Omega^2 + omega^2)``, in ``(q, p/beta)``,
a kick of coefficient c by the fast force alone is a kick of coefficient ``c phi`` with
``phi = Omega^2 / beta^2``, one by the slow force a kick ``c (1 - phi)``; drifts are drifts.
So at a fixed frequency ratio one outer step *is* a splitting method (drift/kick sequence)
on that oscillator, ``z = beta H``, and every analysis of stepsafe applies to it unchanged:
regions with their float64 uncertainties, advice, checks and the mpmath ``--verify``. Its
unstable bands cluster near ``Omega H = j pi`` (the half-period resonances of the impulse
method). Only splitting methods (and compositions of them) can be outer or inner methods
(:class:`stepsafe.methods.tableaux.Impulse`).
"""

from __future__ import annotations

import math

import numpy as np

from stepsafe.exceptions import MethodError, StepsafeError
from stepsafe.methods.tableaux import Impulse, Splitting, splitting_from_operations

#: Drift/kick operations in one outer step (the region finder's cost grows with it).
MAX_OPERATIONS = 1000


def force_fractions(fast: float, slow: float) -> tuple[float, float]:
    """``(phi, 1 - phi)`` with ``phi = Omega^2 / (Omega^2 + omega^2)``, each computed on its
    own (``1 - phi = r^2 / (1 + r^2)``, r = omega / Omega, keeps its relative accuracy when
    the slow force is 1e-20 of the fast one). Either frequency may be 0, not both."""
    if not (fast >= 0 and math.isfinite(fast)) or not (slow >= 0 and math.isfinite(slow)) \
            or fast == slow == 0:
        raise StepsafeError(f"the fast and slow frequencies must be finite, >= 0 and not both "
                            f"0, got {fast:g} and {slow:g}")
    if slow <= fast:
        r2 = (slow / fast) * (slow / fast)
        return 1.0 / (1.0 + r2), r2 / (1.0 + r2)
    s2 = (fast / slow) * (fast / slow)  # the fast force is the smaller one
    return s2 / (1.0 + s2), 1.0 / (1.0 + s2)


def total_frequency(fast: float, slow: float) -> float:
    """``beta = sqrt(Omega^2 + omega^2)`` without overflow."""
    return math.hypot(fast, slow)


def impulse_method(outer, inner, substeps: int, name: str | None = None) -> Impulse:
    """The impulse method of two splittings (a :class:`StepsafeError` for anything else)."""
    try:
        return Impulse(outer, inner, substeps,
                       name=name or f"{outer.name}/{inner.name}x{substeps}")
    except MethodError as exc:
        raise StepsafeError(str(exc)) from None


def impulse_splitting(method: Impulse, fast: float, slow: float) -> Splitting:
    """One outer step of the impulse method as a splitting on the oscillator of frequency
    :func:`total_frequency` (see the module docstring)."""
    phi, slow_part = force_fractions(fast, slow)
    ops = method.operations
    if len(ops) > 4 * MAX_OPERATIONS:  # before merging: bounded work to build it at all
        raise StepsafeError(f"one outer step of {method.name} with {method.substeps} "
                            f"substeps has {len(ops)} drift/kick operations: fewer substeps "
                            "or a shorter inner method")
    scaled = [(kind, coef * (1.0 if kind == "drift" else phi if fast_force else slow_part))
              for kind, coef, fast_force in ops]
    title = (f"impulse {method.name}: {method.substeps} inner steps per outer drift (fast "
             f"fraction {phi:.6g})")
    split = splitting_from_operations(scaled, name=method.name, title=title)
    count = split.drift.size + split.kick.size  # adjacent kicks merged
    if count > MAX_OPERATIONS:
        raise StepsafeError(f"one outer step of {method.name} with {method.substeps} "
                            f"substeps has {count} drift/kick operations, more than the "
                            f"{MAX_OPERATIONS} analysed in bounded time: fewer substeps or a "
                            "shorter inner method")
    return split


def stability_chart(method: Impulse, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``|tr M| / 2`` of one outer step on the grid ``x = Omega H`` (columns) by ``y = omega H``
    (rows): below 1 the step is stable. In ``(q, H p)`` a kick of coefficient c by a force
    of frequency w is ``H p -= c (w H)^2 q`` and a drift ``q += a (H p)``, so M depends on
    ``x^2`` and ``y^2`` only (vectorised over the grid)."""
    fx, sy = np.meshgrid(np.asarray(x, float) ** 2, np.asarray(y, float) ** 2)
    m00, m01 = np.ones_like(fx), np.zeros_like(fx)
    m10, m11 = np.zeros_like(fx), np.ones_like(fx)
    with np.errstate(over="ignore", invalid="ignore"):
        for kind, coef, fast_force in method.operations:
            if kind == "drift":
                m00, m01 = m00 + coef * m10, m01 + coef * m11
            else:
                k = coef * (fx if fast_force else sy)
                m10, m11 = m10 - k * m00, m11 - k * m01
        return np.abs(0.5 * (m00 + m11))
