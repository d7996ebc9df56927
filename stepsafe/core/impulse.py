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
method). Only splitting methods (and compositions of them) can be outer or inner methods.
"""

from __future__ import annotations

import math

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Composition, Method, Splitting, splitting_from_operations

#: Substep counts accepted (each costs one inner step per outer drift) ...
MAX_SUBSTEPS = 1000
#: ... and drift/kick operations in one outer step (the region finder's cost grows with it).
MAX_OPERATIONS = 1000


def _operations(method: Method, role: str) -> list[tuple[str, float]]:
    if isinstance(method, Composition) and isinstance(method.flattened().base, Splitting):
        method = method.as_splitting()
    if not isinstance(method, Splitting):
        raise StepsafeError(f"the {role} method of an impulse (r-RESPA) integrator must be a "
                            f"splitting (drift/kick) method; {method.name} is a "
                            f"{method.kind} method")
    return method.operations


def force_fractions(fast: float, slow: float) -> tuple[float, float]:
    """``(phi, 1 - phi)`` with ``phi = Omega^2 / (Omega^2 + omega^2)``, each computed on its
    own (``1 - phi = r^2 / (1 + r^2)``, r = omega / Omega, keeps its relative accuracy when
    the slow force is 1e-20 of the fast one)."""
    if not (fast > 0 and math.isfinite(fast)) or not (slow >= 0 and math.isfinite(slow)):
        raise StepsafeError(f"the fast frequency must be > 0 and the slow one >= 0 (finite), "
                            f"got {fast:g} and {slow:g}")
    if slow <= fast:
        r2 = (slow / fast) * (slow / fast)
        return 1.0 / (1.0 + r2), r2 / (1.0 + r2)
    s2 = (fast / slow) * (fast / slow)  # the fast force is the smaller one
    return s2 / (1.0 + s2), 1.0 / (1.0 + s2)


def total_frequency(fast: float, slow: float) -> float:
    """``beta = sqrt(Omega^2 + omega^2)`` without overflow."""
    return math.hypot(fast, slow)


def impulse_splitting(outer: Method, inner: Method, substeps: int, fast: float,
                      slow: float, name: str | None = None) -> Splitting:
    """One outer step of the impulse method as a splitting on the oscillator of frequency
    :func:`total_frequency` (see the module docstring)."""
    if isinstance(substeps, bool) or not isinstance(substeps, int) or not (
            1 <= substeps <= MAX_SUBSTEPS):
        raise StepsafeError(f"substeps must be an integer from 1 to {MAX_SUBSTEPS}, got "
                            f"{substeps!r}")
    phi, slow_part = force_fractions(fast, slow)
    inner_ops = _operations(inner, "inner")
    ops: list[tuple[str, float]] = []
    for kind, coef in _operations(outer, "outer"):
        if kind == "kick":
            ops.append(("kick", coef * slow_part))
            continue
        for _ in range(substeps):
            ops += [(k, c * coef / substeps * (phi if k == "kick" else 1.0))
                    for k, c in inner_ops]
    count = sum(1 for _ in ops)
    if count > MAX_OPERATIONS:
        raise StepsafeError(f"one outer step of {outer.name}/{inner.name} with {substeps} "
                            f"substeps has {count} drift/kick operations, more than the "
                            f"{MAX_OPERATIONS} analysed in bounded time: fewer substeps or a "
                            "shorter inner method")
    label = name or f"{outer.name}/{inner.name}x{substeps}"
    return splitting_from_operations(ops, name=label, title=(
        f"impulse: outer {outer.name} over the slow force, {substeps} {inner.name} substeps "
        f"over the fast force (fast fraction {phi:.6g})"))


def stability_chart(outer: Method, inner: Method, substeps: int, x: np.ndarray,
                    y: np.ndarray) -> np.ndarray:
    """``|tr M| / 2`` of one outer step on the grid ``x = Omega H`` (columns) by ``y = omega H``
    (rows): below 1 the step is stable. In ``(q, H p)`` a kick of coefficient c by a force
    of frequency w is ``H p -= c (w H)^2 q`` and a drift ``q += a (H p)``, so M depends on
    ``x^2`` and ``y^2`` only (vectorised over the grid)."""
    fx, sy = np.meshgrid(np.asarray(x, float) ** 2, np.asarray(y, float) ** 2)
    ops: list[tuple[str, float, bool]] = []  # (kind, coefficient, fast force?)
    inner_ops = _operations(inner, "inner")
    for kind, coef in _operations(outer, "outer"):
        if kind == "kick":
            ops.append(("kick", coef, False))
            continue
        for _ in range(substeps):
            ops += [(k, c * coef / substeps, True) for k, c in inner_ops]
    m00, m01 = np.ones_like(fx), np.zeros_like(fx)
    m10, m11 = np.zeros_like(fx), np.ones_like(fx)
    with np.errstate(over="ignore", invalid="ignore"):
        for kind, coef, fast_force in ops:
            if kind == "drift":
                m00, m01 = m00 + coef * m10, m01 + coef * m11
            else:
                k = coef * (fx if fast_force else sy)
                m10, m11 = m10 - k * m00, m11 - k * m01
        return np.abs(0.5 * (m00 + m11))
