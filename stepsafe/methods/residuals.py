"""Symplecticity and consistency residuals of a method's coefficients.

* RK ``(A, b)``: symplectic iff ``B A + A^T B - b b^T = 0`` with ``B = diag(b)``.
* PRK: ``B_q A_p + A_q^T B_p - b_q b_p^T = 0`` makes the method symplectic for separable
  Hamiltonians ``T(p) + V(q)`` (the ``oscillator`` and ``inverted`` models); a general H
  (the ``saddle`` model) also needs ``b_q = b_p`` (Hairer–Lubich–Wanner, Thm VI.4.6).
* Splitting methods are symplectic by construction; compositions inherit from the base,
  impulse methods from their outer and inner splittings.
* Consistency (order >= 1): ``sum(b) = 1`` (RK, PRK), ``sum(drift) = sum(kick) = 1``
  (splitting), ``sum(weights) = 1`` (composition; the base consistent too).

The symplecticity residuals are relative, entry by entry: each entry of the condition over
the sum of the absolute values of the products it is made of (``|b_q,i| |a_p,ij| + |a_q,ji|
|b_p,j| + |b_q,i| |b_p,j|``; for ``b_q = b_p``, over ``max(|b_q,i|, |b_p,i|)``), the
largest of them, so that a huge coefficient elsewhere hides nothing and scaling every
coefficient (the same method at another step) changes nothing: RK4 with its coefficients
times 1e-7 is as far from symplectic as RK4. The consistency residual is absolute (the sums
are compared with 1). A residual below :data:`~stepsafe.methods.tableaux.RESIDUAL_TOL`
(consistency: times ``max(1, size of the coefficients)``) counts as zero: coefficients
given to about 12 digits or more pass, which is what a method file's decimals of a
symplectic method can promise.
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

    symplectic_separable: float  # B_q A_p + A_q^T B_p - b_q b_p^T, relative
    weights_equal: float  # |b_q - b_p| over max |b|, needed for non-separable H
    consistency: float  # distance of the weight sums from 1
    row_sums: float | None  # |A 1 - c| for RK methods with given nodes
    magnitude: float  # size of the coefficients, for the consistency test

    @property
    def symplectic_for_separable(self) -> bool:
        return bool(self.symplectic_separable <= RESIDUAL_TOL)  # (NaN: not symplectic)

    @property
    def symplectic(self) -> bool:
        """Symplectic for every Hamiltonian."""
        return self.symplectic_for_separable and bool(self.weights_equal <= RESIDUAL_TOL)

    @property
    def consistent(self) -> bool:
        return bool(self.consistency <= RESIDUAL_TOL * max(1.0, self.magnitude))

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
    coefficients = (prk.A_q, prk.A_p, prk.b_q, prk.b_p)
    mag = float(max(np.abs(c).max() for c in coefficients))
    cons = max(abs(float(prk.b_q.sum()) - 1.0), abs(float(prk.b_p.sum()) - 1.0))
    if not np.isfinite(mag):
        return Residuals(np.nan, np.nan, cons, row_sums, mag)
    # divided by the power of two of the largest coefficient (exact), so that neither the
    # products nor their sizes over- or underflow
    exponent = int(np.frexp(mag)[1])
    A_q, A_p, b_q, b_p = (np.ldexp(c, -exponent) for c in coefficients)
    sym = b_q[:, None] * A_p + A_q.T * b_p[None, :] - np.outer(b_q, b_p)
    size = (np.abs(b_q)[:, None] * np.abs(A_p) + np.abs(A_q.T) * np.abs(b_p)[None, :]
            + np.outer(np.abs(b_q), np.abs(b_p)))
    # entry by entry: a huge coefficient elsewhere does not hide a defect in one entry
    return Residuals(_relative(sym, size),
                     _relative(b_q - b_p, np.maximum(np.abs(b_q), np.abs(b_p))),
                     cons, row_sums, mag)


def _relative(residual: np.ndarray, size: np.ndarray) -> float:
    """The largest ``|residual| / size`` entry by entry (an exact zero counts 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(residual == 0, 0.0, np.abs(residual) / size)
    return float(np.max(ratio, initial=0.0))


def is_partitioned(method: Method) -> bool:
    """True when the method treats q and p differently (PRK, splitting, or built on one)."""
    from stepsafe.methods.tableaux import Processed

    if isinstance(method, Processed):
        return True
    if isinstance(method, Composition):
        return is_partitioned(method.base)
    return isinstance(method, (PartitionedRK, Splitting))
