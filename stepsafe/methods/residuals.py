"""Symplecticity and consistency residuals of a method's coefficients.

* RK ``(A, b)``: symplectic iff ``B A + A^T B - b b^T = 0`` with ``B = diag(b)``.
* PRK: ``B_q A_p + A_q^T B_p - b_q b_p^T = 0`` makes the method symplectic for separable
  Hamiltonians ``T(p) + V(q)`` (the ``oscillator`` and ``inverted`` models); a general H
  (the ``saddle`` model) also needs ``b_q = b_p`` (Hairer–Lubich–Wanner, Thm VI.4.6).
* Splitting methods are symplectic by construction; compositions inherit from the base,
  impulse methods from their outer and inner splittings.
* Consistency (order >= 1): ``sum(b) = 1`` (RK, PRK), ``sum(drift) = sum(kick) = 1``
  (splitting), ``sum(weights) = 1`` (composition; the base consistent too).

Residuals are max-norms; a residual below :data:`~stepsafe.methods.tableaux.RESIDUAL_TOL` times the
size of the coefficients counts as zero.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from stepsafe.methods.tableaux import (
    RESIDUAL_TOL,
    Composition,
    Impulse,
    Method,
    PartitionedRK,
    RungeKutta,
    Splitting,
)


class Residuals(NamedTuple):
    """Max-norm residuals of the coefficient conditions (0.0 where exact by construction)."""

    symplectic_separable: float  # B_q A_p + A_q^T B_p - b_q b_p^T
    weights_equal: float  # |b_q - b_p|, needed for non-separable H
    consistency: float  # distance of the weight sums from 1
    row_sums: float | None  # |A 1 - c| for RK methods with given nodes
    magnitude: float  # size of the coefficients, for the relative test

    def _zero(self, value: float) -> bool:
        return value <= RESIDUAL_TOL * max(1.0, self.magnitude)

    @property
    def symplectic_for_separable(self) -> bool:
        return self._zero(self.symplectic_separable)

    @property
    def symplectic(self) -> bool:
        """Symplectic for every Hamiltonian."""
        return self.symplectic_for_separable and self._zero(self.weights_equal)

    @property
    def consistent(self) -> bool:
        return self._zero(self.consistency)

    def symplectic_for(self, model: str) -> bool:
        """Symplectic on the given test model (``saddle`` is not of the form T + V)."""
        return self.symplectic if model == "saddle" else self.symplectic_for_separable


def residuals(method: Method | Impulse) -> Residuals:
    """Compute the :class:`Residuals` of ``method`` from its coefficients."""
    from stepsafe.methods.tableaux import Processed

    if isinstance(method, Processed):  # P^-1 K P: the kernel's sums, symplectic as it is
        return residuals(method.per_step())
    if isinstance(method, Composition):
        base = residuals(method.base)
        cons = max(base.consistency, abs(float(method.weights.sum()) - 1.0))
        mag = max(base.magnitude, float(np.abs(method.weights).max()))
        return Residuals(base.symplectic_separable, base.weights_equal, cons, None, mag)
    if isinstance(method, Impulse):  # every force's kicks and the drifts sum to 1 iff both do
        outer, inner = residuals(method.outer), residuals(method.inner)
        return Residuals(0.0, 0.0, max(outer.consistency, inner.consistency), None,
                         max(outer.magnitude, inner.magnitude))
    if isinstance(method, Splitting):
        cons = max(abs(float(method.drift.sum()) - 1.0), abs(float(method.kick.sum()) - 1.0))
        mag = float(max(np.abs(method.drift).max(), np.abs(method.kick).max()))
        return Residuals(0.0, 0.0, cons, None, mag)
    row_sums = None
    if isinstance(method, RungeKutta):
        row_sums = float(np.abs(method.A.sum(axis=1) - method.c).max())
    prk = method.as_prk()
    sym = (np.diag(prk.b_q) @ prk.A_p + prk.A_q.T @ np.diag(prk.b_p)
           - np.outer(prk.b_q, prk.b_p))
    cons = max(abs(float(prk.b_q.sum()) - 1.0), abs(float(prk.b_p.sum()) - 1.0))
    mag = float(max(np.abs(prk.A_q).max(), np.abs(prk.A_p).max(), np.abs(prk.b_q).max()))
    return Residuals(float(np.abs(sym).max()), float(np.abs(prk.b_q - prk.b_p).max()), cons,
                     row_sums, mag)


def is_partitioned(method: Method) -> bool:
    """True when the method treats q and p differently (PRK, splitting, or built on one)."""
    from stepsafe.methods.tableaux import Processed

    if isinstance(method, Processed):
        return True
    if isinstance(method, Composition):
        return is_partitioned(method.base)
    return isinstance(method, (PartitionedRK, Splitting))
