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
|b_p,j| + |b_q,i| |b_p,j|``; for ``b_q = b_p``, over ``max(|b_q,i|, |b_p,i|)``), so that a
huge coefficient elsewhere hides nothing and scaling every coefficient (the same method at
another step) changes nothing: RK4 with its coefficients times 1e-7 is as far from
symplectic as RK4. The consistency residual is absolute (the sums are compared with 1).

When a residual counts as zero:

* float coefficients as given (families, tableaux built in code): each entry's relative
  residual at most :data:`~stepsafe.methods.tableaux.RESIDUAL_TOL` (consistency: times
  ``max(1, size of the coefficients)``);
* an RK or PRK method file, which says how precisely each coefficient is meant: the
  condition is evaluated on the exact values of the texts (decimal literals read exactly,
  50 digits) and each entry must lie within what the rounding of the written digits can
  explain, at most twice the first-order bound ``|b_q,i| d(a_p,ij) + d(b_q,i) |a_p,ij| +
  ...`` (plus the second-order terms) from the allowances ``d`` of the coefficients, and
  never beyond ``RESIDUAL_TOL`` either. A literal of fewer than 10 significant digits
  (``1/2``, ``0.25``, ``1e-12``) and ``sqrt``, ``cbrt``, ``pi`` are exact, so their
  allowance is 0; a longer literal is the rounding of the value meant to its last digit,
  or to 4 ulps of float64, whichever is coarser
  (:func:`~stepsafe.files.expressions.written_rounding`), and expressions carry their
  literals' allowances through to first order. So the midpoint rule written ``1/2 +
  1e-12`` is not symplectic (``det M - 1 = -2e-12 z^2 / (1 + ...)``: a slow sink, not a
  centre), nor is Gauss s = 2 with ``1e-13`` added to a coefficient, while a tableau
  printed to 17 digits of float64 from the exact one passes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from stepsafe.methods.protocol import MethodKind
    from stepsafe.methods.tableaux import PartitionedRK

#: Rounding-level threshold for the symplecticity and consistency residuals.
RESIDUAL_TOL = 1e-12


class Residuals(NamedTuple):
    """Residuals of the coefficient conditions (0.0 where exact by construction) with what
    each may be and still count as zero. A symplecticity residual is that of the entry
    that decides (the largest over its tolerance; for float coefficients as given, the
    largest: their tolerance is the same everywhere)."""

    symplectic_separable: float  # B_q A_p + A_q^T B_p - b_q b_p^T, relative
    weights_equal: float  # |b_q - b_p| over max |b|, needed for non-separable H
    consistency: float  # distance of the weight sums from 1
    row_sums: float | None  # |A 1 - c| for RK methods with given nodes
    magnitude: float  # size of the coefficients, for the consistency test
    #: what ``symplectic_separable`` and ``weights_equal`` may be (relative, at their entry)
    symplectic_tolerance: float = RESIDUAL_TOL
    weights_tolerance: float = RESIDUAL_TOL

    @property
    def symplectic_for_separable(self) -> bool:
        # (NaN: not symplectic)
        return bool(self.symplectic_separable <= self.symplectic_tolerance)

    @property
    def symplectic(self) -> bool:
        """Symplectic for every Hamiltonian."""
        return self.symplectic_for_separable and bool(
            self.weights_equal <= self.weights_tolerance)

    @property
    def consistent(self) -> bool:
        return bool(self.consistency <= RESIDUAL_TOL * max(1.0, self.magnitude))

    def symplectic_for(self, model: str) -> bool:
        """Symplectic on the given test model (``saddle`` is not of the form T + V)."""
        return self.symplectic if model == "saddle" else self.symplectic_for_separable


def residuals(method: MethodKind) -> Residuals:
    """The :class:`Residuals` of ``method`` from its coefficients (each kind computes its
    own: :meth:`~stepsafe.methods.protocol.MethodKind.residuals`)."""
    return method.residuals()


def prk_residuals(prk: PartitionedRK, row_sums: float | None = None,
                  written: Any = None) -> Residuals:
    """The :class:`Residuals` of the tableaux of ``prk`` (``row_sums``: ``|A 1 - c|`` of an RK
    method with given nodes; ``written``: the residuals of a method file's coefficients as
    written, :func:`written_residuals`, which then decide)."""
    coefficients = (prk.A_q, prk.A_p, prk.b_q, prk.b_p)
    mag = float(max(np.abs(c).max() for c in coefficients))
    cons = max(abs(float(prk.b_q.sum()) - 1.0), abs(float(prk.b_p.sum()) - 1.0))
    if not np.isfinite(mag):
        return Residuals(np.nan, np.nan, cons, row_sums, mag)
    if written is not None:  # a method file: decided on the coefficients as written
        return Residuals(written.symplectic_separable, written.weights_equal, cons, row_sums,
                         mag, written.symplectic_tolerance, written.weights_tolerance)
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


class Written(NamedTuple):
    """Symplecticity residuals of a tableau as written (see the module docstring), each at
    the entry that decides, with the tolerance there."""

    symplectic_separable: float
    symplectic_tolerance: float
    weights_equal: float
    weights_tolerance: float
    #: the last stage whose ``A_q`` row equals ``b_q`` as written (their exact values
    #: within the allowances of their digits), None if none
    step_end_stage: int | None = None


#: Residuals below this (relative) are the 50-digit evaluation's own rounding.
WRITTEN_NOISE = 1e-40


def written_residuals(A_q: list, b_q: list, A_p: list, b_p: list) -> Written:
    """:class:`Written` from a PRK's coefficients as written: each a ``(value,
    allowance)`` pair, ``value`` the exact value of the text (an mpmath number at 50
    digits or more), ``allowance`` how far it may lie from the value meant."""
    import mpmath as mp

    def split(pairs: list) -> tuple[list, list]:
        return [v for v, _ in pairs], [float(d) for _, d in pairs]

    (bq, dbq), (bp, dbp) = split(b_q), split(b_p)
    (aq, daq), (ap, dap) = zip(*(split(row) for row in A_q)), zip(*(split(row) for row in A_p))
    s = len(bq)
    entries = []  # (residual, size, allowance), entry by entry
    with mp.workdps(60):
        for i in range(s):
            for j in range(s):
                terms = ((bq[i], dbq[i], ap[i][j], dap[i][j]),
                         (aq[j][i], daq[j][i], bp[j], dbp[j]),
                         (bq[i], dbq[i], bp[j], dbp[j]))
                residual = bq[i] * ap[i][j] + aq[j][i] * bp[j] - bq[i] * bp[j]
                size = mp.fsum(abs(x * y) for x, _, y, _ in terms)
                allow = mp.fsum(abs(x) * dy + dx * abs(y) + dx * dy for x, dx, y, dy in terms)
                entries.append((abs(residual), size, allow))
        sym, sym_tol = _deciding(entries)
        weights = [(abs(bq[i] - bp[i]), max(abs(bq[i]), abs(bp[i])), mp.mpf(dbq[i] + dbp[i]))
                   for i in range(s)]
        weq, weq_tol = _deciding(weights)
        ends = [i for i in range(s)
                if all(abs(aq[i][j] - bq[j]) <= daq[i][j] + dbq[j] for j in range(s))]
    return Written(sym, sym_tol, weq, weq_tol, ends[-1] if ends else None)


def _deciding(entries: list) -> tuple[float, float]:
    """``(relative residual, relative tolerance)`` of the entry whose residual is the
    largest multiple of its tolerance: twice its allowance, at most ``RESIDUAL_TOL``, at
    least :data:`WRITTEN_NOISE` (an exact zero counts 0)."""
    worst = (0.0, RESIDUAL_TOL, 0.0)  # (residual, tolerance, their ratio)
    for residual, size, allow in entries:
        if residual == 0:
            continue
        rel = float(residual / size)
        tol = min(RESIDUAL_TOL, max(float(2 * allow / size), WRITTEN_NOISE))
        if rel / tol > worst[2]:
            worst = (rel, tol, rel / tol)
    return worst[0], worst[1]


def _relative(residual: np.ndarray, size: np.ndarray) -> float:
    """The largest ``|residual| / size`` entry by entry (an exact zero counts 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(residual == 0, 0.0, np.abs(residual) / size)
    return float(np.max(ratio, initial=0.0))
