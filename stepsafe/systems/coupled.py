"""The coupled analysis of ``x' = J S x`` when the modes do not decouple
(docs/theory.md#systems-beyond-the-test-models).

``x = (q, p)``, ``J = [[0, I], [-I, 0]]``, ``S`` symmetric 2n x 2n. One step of size h is a
2n x 2n matrix ``M(h)``; it keeps the structure of the flow when its eigenvalues have the
types of those of ``J S`` (elliptic pairs with their Krein signatures, hyperbolic pairs with
positive multipliers, loxodromic quadruplets) and none is negative real (a flip).

Two criteria, both exact, chosen by S:

* **S definite** (one Cholesky of ``S`` or ``-S`` tells): every mode is elliptic with the
  Krein signature of ``sign(S)``, and the structure is kept iff
  ``Q(h) = sign(S) (M^T J - J M)`` is positive definite. For ``M v = e^{i theta} v``,
  ``v^H Q v = 2 sin(theta) Im(v^H J v)`` (times the sign), so ``Q > 0`` says every
  multiplier is on the unit circle, off the real axis, with the flow's sense of rotation;
  ``Q`` is singular exactly where M has a multiplier +-1. The margin
  ``phi(h) = lambda_min(L^-1 Q L^-T) / (2h)`` with ``L L^T = sign(S) S`` is 1 at h -> 0
  and changes sign at the boundary, which a bracketing root finder locates.
* **S indefinite**: the multipliers' types from the eigenvalues of M alone, and the
  difference of the Krein counts from the inertia of Q: ``n+ - n- = 2 (e+ - e-)``
  (elliptic pairs contribute +-2, hyperbolic and loxodromic blocks 0).

``M - I`` is accumulated without forming ``I + (small)`` and subtracting: each symplectic
Euler factor of a splitting adds its increment ``c (...)`` (one n x n solve and one matrix
product, the products ``S_qq q`` and ``S_pp p`` reused between factors), so ``Q = D^T J -
J D`` with ``D = M - I`` has no cancellation at small h. A decision within the rounding
bound of Q is not a pass: such an h counts as not preserved. Where that bound reaches the
margin before the structure is lost (a nearly semidefinite S), the first failure is not a
certain loss: a small splitting system is then decided at high precision
(:mod:`stepsafe.systems.coupled_exact`), a larger one reports the band float64 leaves open
(:attr:`CoupledResult.undecided_to`).

The scan runs only until the first failure (the safe interval from 0 is what limits h;
islands beyond it are not analysed), in steps of ``SCAN_DZ`` in z = h |mu|_max, and looks
between samples for a dip of ``phi`` that the samples straddle.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Literal, NamedTuple, Protocol, cast

import numpy as np

from stepsafe.core.engine import (
    Jet,
    Rounding,
    StageOperator,
    stage_jet,
    stage_operator,
    step_jet,
)
from stepsafe.core.engine import jet as make_jet
from stepsafe.core.threads import blas_threads_for
from stepsafe.core.transfer import blocks_of
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.protocol import Friction, MethodKind, Shears, Stages
from stepsafe.methods.tableaux import Method, PartitionedRK, RungeKutta, Splitting
from stepsafe.systems import coupled_exact
from stepsafe.systems.frame import (
    DiagonalFrame,
    Solver,
    balanced_blocks,
    diagonal_frame,
    equilibrated,
    euler_deviation,
    norm_2,
)
from stepsafe.systems.linear import ZERO_TOL, hamiltonian_matrix
from stepsafe.systems.smallest import extreme_eigenvalue, smallest

EPS = float(np.finfo(float).eps)
#: |nu| within this of 1 is on the unit circle (indefinite S only)
CIRCLE_TOL = 1e-8
#: scan step in z = h |mu|_max
SCAN_DZ = 0.2
#: bracket width at which the boundary is accepted, relative
REL_TOL = 1e-12
#: safety factor on the rounding estimate of Q (first-order terms plus the measured
#: symplecticity defect)
ROUNDING_FACTOR = 8.0

@dataclass(frozen=True)
class Signature:
    """Counts of multiplier types: elliptic pairs by Krein sign, hyperbolic pairs, flips
    (negative real multipliers), loxodromic quadruplets, parabolic (multiplier 1) pairs."""

    elliptic_plus: int
    elliptic_minus: int
    hyperbolic: int
    flips: int
    loxodromic: int
    parabolic: int


@dataclass(frozen=True)
class CoupledResult:
    """The safe interval from 0 found by the coupled analysis."""

    h_max: float  #: end of the preserved interval from 0 (the horizon if none was found)
    horizon: float  #: zmax / |mu|_max: steps beyond it were not analysed
    evaluations: int  #: one-step matrices built
    analysis: str
    #: where float64 could not decide: steps in (h_max, undecided_to) are neither certified
    #: nor certainly lost (the rounding bound of Q reaches its margin; a system too large
    #: for the high-precision criterion); None when the boundary was decided
    undecided_to: float | None = None

    @property
    def safe_h(self) -> tuple[tuple[float, float | None], ...]:
        return ((0.0, self.h_max),) if self.h_max > 0 else ()


def _krein_counts(eigvecs: np.ndarray, elliptic: np.ndarray) -> tuple[int, int]:
    """Krein signs ``sign Im(v^H J v)`` of the elliptic eigenvectors (columns)."""
    V = eigvecs[:, elliptic]
    n = V.shape[0] // 2
    # v^H J v = conj(v_q) . v_p - conj(v_p) . v_q
    form = (np.conj(V[:n]) * V[n:]).sum(axis=0) - (np.conj(V[n:]) * V[:n]).sum(axis=0)
    return int((form.imag > 0).sum()), int((form.imag < 0).sum())


def continuous_signature(S: np.ndarray) -> Signature:
    """The types of the eigenvalues of ``J S`` (once per system)."""
    mu, V = np.linalg.eig(hamiltonian_matrix(S))
    top = max(float(np.abs(mu).max()), 1e-300)
    zero = np.abs(mu) <= ZERO_TOL * top
    ell = ~zero & (np.abs(mu.real) <= 1e-9 * np.abs(mu)) & (mu.imag > 0)
    hyp = ~zero & (np.abs(mu.imag) <= 1e-9 * np.abs(mu)) & (mu.real > 0)
    lox = ~zero & ~ell & ~hyp & (mu.real > 0) & (mu.imag > 0)
    plus, minus = _krein_counts(V, ell)
    return Signature(plus, minus, int(hyp.sum()), 0, int(lox.sum()), int(zero.sum()) // 2)


def _multiplier_types(nu: np.ndarray) -> tuple[int, int, int, int, int]:
    """(elliptic, hyperbolic, flips, loxodromic, parabolic) from the multipliers alone."""
    mod = np.abs(nu)
    one = np.abs(nu - 1) <= CIRCLE_TOL
    circle = (np.abs(mod - 1) <= CIRCLE_TOL) & ~one
    ell = circle & (nu.imag > CIRCLE_TOL)
    minus_one = circle & (np.abs(nu.imag) <= CIRCLE_TOL)
    real = (np.abs(nu.imag) <= CIRCLE_TOL * mod) & ~circle & ~one
    hyp = real & (nu.real > 1)
    flips = real & (nu.real < -1)
    lox = ~circle & ~real & ~one & (mod > 1) & (nu.imag > 0)
    return (int(ell.sum()), int(hyp.sum()), int(flips.sum() + minus_one.sum()),
            int(lox.sum()), int(one.sum()) // 2)


def discrete_signature(M: np.ndarray) -> Signature | None:
    """The types of the multipliers of a one-step matrix (eigenvectors for the Krein signs;
    the reference implementation the fast criteria are tested against)."""
    if not np.all(np.isfinite(M)):
        return None
    nu, V = np.linalg.eig(M)
    ell_count, hyp, flips, lox, par = _multiplier_types(nu)
    mod = np.abs(nu)
    ell = (np.abs(mod - 1) <= CIRCLE_TOL) & (np.abs(nu - 1) > CIRCLE_TOL) & (nu.imag > CIRCLE_TOL)
    plus, minus = _krein_counts(V, ell)
    return Signature(plus, minus, hyp, flips, lox, par)


# ---------------------------------------------------------------- one-step matrix


class Factors(NamedTuple):
    """A run of symplectic Euler factors (``kind`` "euler", each ``("DK" | "KD", c)``) or
    of a force-gradient splitting's operations (``kind`` "ops", each ``(label, c)``), in the
    order applied."""

    kind: Literal["euler", "ops"]
    factors: list[tuple[str, float]]


class Weighted(NamedTuple):
    """The step ``M(g h)`` of a PRK method, ``g`` its weight in a composition."""

    weight: float
    prk: PartitionedRK


#: One piece of a step: :class:`Factors` or :class:`Weighted`.
Piece = Factors | Weighted


class StepMatrices(Protocol):
    """What :class:`CoupledSystem` asks of the one-step matrices it analyses: ``D = M(h) -
    I`` with a bound on its rounding error (Frobenius), and the pieces of the step (for
    the poles; none for an explicit step)."""

    @property
    def pieces(self) -> Sequence[Piece]: ...

    def deviation(self, h: float) -> tuple[np.ndarray, float]: ...


class _Steps:
    """Builds ``D(h) = M(h) - I`` for one method on one S (see module docstring): the step
    engine (:func:`stepsafe.core.engine.step_jet`) on this system, whose blocks are a
    splitting's symplectic Euler factors by n x n solves (in a :class:`DiagonalFrame` by
    :func:`euler_deviation`; a force-gradient splitting by its operations) and a Runge–Kutta
    step by the engine's stage system on ``L = J S``. Rounding: the engine's normwise
    bound."""

    def __init__(self, method: Method, S: np.ndarray, frame: DiagonalFrame | None = None
                 ) -> None:
        n = S.shape[0] // 2
        self.n = n
        self.S = S
        self.S_qq, self.S_qp = S[:n, :n], S[:n, n:]
        self.S_pq, self.S_pp = S[n:, :n], S[n:, n:]
        self.norm_S = float(np.linalg.norm(S))
        self.pieces = _pieces(method)
        self.blocks = blocks_of(method, None)
        self.frame = frame
        self._stage_systems: dict[int, tuple[object, StageOperator]] = {}
        if any(isinstance(piece, Factors) and piece.kind == "ops" for piece in self.pieces) \
                and (self.S_qp.any() or self.S_pq.any()):
            raise StepsafeError("a force-gradient method needs a separable H = p^T M^-1 p / 2 "
                                "+ V(q); this system couples q and p")

    @cached_property
    def S_pq_norm(self) -> float:
        """A bound on ``||S_pq||_2`` (for the stage matrices' condition)."""
        return norm_2(self.S_pq)

    @cached_property
    def S_qp_norm(self) -> float:
        return norm_2(self.S_qp)

    def deviation(self, h: float) -> tuple[np.ndarray, float]:
        """``(D, err)``: ``D = M(h) - I`` and a first-order bound on its rounding error
        (Frobenius); D is NaN where the step is not unique (a singular stage system)."""
        out = step_jet(self.blocks, self, np.array([float(h)]), order=0, rounding="norm")
        D = out.D[0]
        assert out.err is not None
        if not np.all(np.isfinite(D)):
            return np.full_like(D, np.nan), np.inf
        return D, float(out.err[0])

    def shears(self, splitting: Splitting, z: np.ndarray, order: int,
               rounding: Rounding) -> Jet:
        """The splitting at each h in ``z`` (values only: the coupled criteria take no
        derivatives), with its normwise rounding bound."""
        Ds, errs = zip(*(self._shears(splitting, float(h)) for h in z))
        nan = np.full((z.size, 2 * self.n, 2 * self.n), np.nan)
        return make_jet(np.array(Ds), nan, nan, err=np.array(errs))

    def _shears(self, splitting: Splitting, h: float) -> tuple[np.ndarray, float]:
        if self.frame is not None and not splitting.force_gradient:
            return euler_deviation(self.frame, splitting.euler_factors(), h, self.norm_S)
        D = np.zeros((2 * self.n, 2 * self.n))
        if splitting.force_gradient:
            err = sum(self._operation(D, label, c, h) for label, c in splitting.operations)
        else:
            err = sum(self._euler(D, label, c * h) for label, c in splitting.euler_factors())
        return D, err

    def stages(self, method: RungeKutta | PartitionedRK, z: np.ndarray, order: int,
               rounding: Rounding) -> Jet:
        """The stage system of ``method`` on ``L = J S`` (built once per method; without
        the far form, which serves the accuracy of ``tr M -+ 2`` on the 2x2 models)."""
        hit = self._stage_systems.get(id(method))
        if hit is None or hit[0] is not method:
            hit = self._stage_systems[id(method)] = (
                method, stage_operator(method, hamiltonian_matrix(self.S)))
        out = stage_jet(hit[1], None, z, order, rounding, norm_L=self.norm_S)
        if out.err is not None:  # the products with the stage sums: 1 + ||D||
            out = out._replace(err=out.err * (1.0 + np.linalg.norm(out.D, axis=(1, 2))))
        return out

    def friction(self, block: Friction, z: np.ndarray, order: int,
                 rounding: Rounding) -> Jet:
        raise StepsafeError("a Langevin splitting is analysed on the modes of a system (its "
                            "oscillator models), not on a coupled 2n x 2n system")

    def _operation(self, D: np.ndarray, label: str, c: float, h: float) -> float:
        """Apply one operation of a force-gradient splitting to ``X = I + D`` in place
        (separable S: ``K = S_qq``, ``M^-1 = S_pp``): a drift ``q += c h M^-1 p``, a kick
        ``p -= c h K q``, a gradient term ``p += c h^3 grad |K q|^2_{M^-1} = p + 2 c h^3
        K M^-1 K q``; returns the rounding bound of the increment."""
        n = self.n
        X = D.copy()
        X[np.arange(2 * n), np.arange(2 * n)] += 1.0
        q, p = X[:n], X[n:]
        if label == "drift":
            D[:n] += (c * h) * (self.S_pp @ p)
            scale = abs(c * h) * float(np.linalg.norm(self.S_pp))
        elif label == "kick":
            D[n:] -= (c * h) * (self.S_qq @ q)
            scale = abs(c * h) * float(np.linalg.norm(self.S_qq))
        else:
            D[n:] += (2.0 * c * h ** 3) * (self.S_qq @ (self.S_pp @ (self.S_qq @ q)))
            scale = 2.0 * abs(c * h ** 3) * float(np.linalg.norm(self.S_qq)) ** 2 * \
                float(np.linalg.norm(self.S_pp))
        return 3 * n * EPS * scale * float(np.linalg.norm(X))

    def _euler(self, D: np.ndarray, label: str, c: float) -> float:
        """Apply one symplectic Euler factor to ``X = I + D`` in place (on D); returns the
        rounding bound of the increment."""
        n = self.n
        X = D.copy()
        X[np.arange(2 * n), np.arange(2 * n)] += 1.0
        q, p = X[:n], X[n:]
        eye = np.eye(n)
        A = eye - c * self.S_pq if label == "DK" else eye + c * self.S_qp
        solver = Solver.of(A, abs(c) * (self.S_pq_norm if label == "DK" else self.S_qp_norm))
        if solver is None:
            D[:] = np.nan
            return np.inf
        if label == "DK":  # q1 = q0 + c f(q1, p0), p1 = p0 + c g(q1, p0)
            dq = np.empty((n, 2 * n))
            solver.solve(c * (self.S_pq @ q + self.S_pp @ p), 0.0, dq)
            q1 = q + dq
            dp = -c * (self.S_qq @ q1 + self.S_qp @ p)
        else:  # p1 = p0 + c g(q0, p1), q1 = q0 + c f(q0, p1)
            dp = np.empty((n, 2 * n))
            solver.solve(-c * (self.S_qq @ q + self.S_qp @ p), 0.0, dp)
            p1 = p + dp
            dq = c * (self.S_pq @ q + self.S_pp @ p1)
        D[:n] += dq
        D[n:] += dp
        # (the stage solve amplifies rounding near a pole, where A turns singular)
        return 2 * n * EPS * abs(c) * self.norm_S * float(np.linalg.norm(X)) \
            * solver.amplification


def _pieces(method: Method) -> list[Piece]:
    """The step as Euler factors (splittings, compositions of them) or weighted PRK
    steps, in the order they are applied: the blocks of the step
    (:func:`stepsafe.core.transfer.blocks_of`, the description the 2x2 transfer matrix is
    built from too). A splitting (a processed method ``P^-1 K P`` as its full one-step
    map, a composition of splittings merged) runs as its PRK form of symplectic Euler
    factors, as on every H that mixes q and p; a force-gradient one as its operations."""
    pieces: list[Piece] = []
    for block in blocks_of(method, None):
        if isinstance(block, Shears):
            step = block.splitting
            pieces.append(Factors("ops", step.operations) if step.force_gradient
                          else Factors("euler", step.euler_factors()))
        elif isinstance(block, Stages):
            prk = block.method.rk_form()
            assert prk is not None
            pieces.append(Weighted(block.weight, prk))
        else:
            raise StepsafeError(f"{method.name}: a Langevin splitting is analysed on the "
                                "modes of a system (its oscillator models), not on a coupled "
                                "2n x 2n system")
    return pieces


def one_step_matrix(method: Method, S: np.ndarray, h: float) -> np.ndarray:
    """The 2n x 2n matrix of one step of size h on ``x' = J S x`` (NaN if no unique step)."""
    D, _ = _Steps(method, S).deviation(h)
    return D + np.eye(D.shape[0])


# ---------------------------------------------------------------- criteria


def criterion_matrix(D: np.ndarray, err: float) -> tuple[np.ndarray, float]:
    """``(Q, bound)``: ``Q = D^T J - J D = M^T J - J M`` for ``D = M - I``, and a bound on
    its error (Frobenius) from the bound ``err`` on D's rounding and the symplecticity
    defect ``M^T J M - J = D^T J + J D + D^T J D`` (0 in exact arithmetic), which measures
    what the stage solves' conditioning did to M."""
    n = D.shape[0] // 2
    JD = np.vstack([D[n:], -D[:n]])  # J D
    Q = np.add(JD, JD.T)
    Q *= -1.0
    # D^T J D = G - G^T with G = D_q^T D_p (half the work of the full product), so the
    # defect is X - X^T with X = J D + G
    G = D[:n].T @ D[n:]
    JD += G
    np.subtract(JD, JD.T, out=G)
    return Q, ROUNDING_FACTOR * (2 * err + float(np.linalg.norm(G)))


class CoupledSystem:
    """One method on one S, with what every h shares computed once. ``steps`` (optional)
    builds the one-step matrices instead of ``method``: called with the scale ``unit`` by
    which S is divided, it returns an object with ``deviation(h)`` (``M(h / unit) - I``
    and its rounding bound, as :class:`_Steps`) and ``pieces`` (for the poles): a
    :class:`StepMatrices`."""

    def __init__(self, method: Method | None, S: np.ndarray,
                 steps: Callable[[float], StepMatrices] | None = None) -> None:
        self.method, self.given = method, S
        if steps is None and S.size:
            # q and p in units where the two diagonal blocks are of one size: an exact
            # power-of-two point transformation (the criteria are invariant), so that
            # rounding bounds made of |S| do not swamp a block given in small units (S_pp
            # times 2^40 left an indefinite system "never safe")
            S = balanced_blocks(S)
        # work on S / |S|_max and h |S|_max (the same one-step matrices), so neither S nor
        # its norms over- or underflow whatever its units
        largest = float(np.abs(S).max()) if S.size else 0.0
        self.unit = largest if largest > 0 and np.isfinite(largest) else 1.0
        S = S / self.unit
        self.n = S.shape[0] // 2
        self.sign = 0
        self.chol: np.ndarray | None = None  # the Cholesky factor of sign S (definite S)
        for sign in (1, -1):
            try:
                self.chol = np.linalg.cholesky(sign * S)
                self.sign = sign
                break
            except np.linalg.LinAlgError:
                continue
        frame = None
        self.weight = None
        if self.sign and steps is None and method is not None:
            S, self.chol, frame = _definite_coordinates(S, self.sign, method)
            if frame is not None:
                self.weight = self.sign * np.concatenate([frame.a, frame.b])
        self.S = S
        if steps is None and method is None:
            raise ValueError("a coupled analysis needs a method or its one-step matrices")
        self.steps = steps(self.unit) if steps is not None else \
            _Steps(cast(MethodKind, method), S, frame)
        self.top = self.unit * _largest_frequency(S, self.chol if self.sign else None)
        self.evaluations = 0
        self._cache: dict[float, float] = {}
        self._slack: dict[float, float] = {}  # the rounding bound in the units of the margin
        self._certified: dict[float, bool] = {}  # lambda_min(W) above it proved (definite S)
        self._built: dict[float, tuple | None] = {}

    @property
    def definite(self) -> bool:
        return self.sign != 0

    @cached_property
    def reference(self) -> Signature:
        """The types of the eigenvalues of ``J S`` (computed only when a criterion needs
        them: the definite one does not)."""
        return continuous_signature(self.S)

    @property
    def tracks_types(self) -> bool:
        """Whether :meth:`margin` follows every type change (not with zero modes or
        loxodromic quadruplets, whose traces sit at 2 or off the real axis)."""
        return self.definite or (self.reference.parabolic == 0
                                 and self.reference.loxodromic == 0)

    def _evaluate(self, h: float) -> tuple[np.ndarray, np.ndarray, float] | None:
        """``(D, Q, err)`` at h, err bounding the rounding of Q; None if no unique step."""
        if h not in self._built:
            if len(self._built) > 8:
                self._built.clear()
            self._built[h] = self._build(h)
        return self._built[h]

    def _build(self, h: float) -> tuple[np.ndarray, np.ndarray, float] | None:
        self.evaluations += 1
        D, err = self.steps.deviation(h * self.unit)
        if not np.all(np.isfinite(D)):
            return None
        return (D, *criterion_matrix(D, err))

    def margin(self, h: float) -> float:
        """A continuous function of h that is > 0 where the structure is kept and must
        reach 0 wherever it is lost (cached per h). Definite S: ``phi(h)`` less its rounding
        bound. Indefinite S: from the pair traces ``t_k = nu + 1/nu`` (eigenvalues of
        ``D - J D^T J`` are ``t_k - 2``, each twice), sorted: the smallest ``2e`` (e elliptic
        pairs) must lie in (-2, 2) and the rest above 2, so the distance to those limits
        reaches 0 whenever a pair changes type, even when two pairs swap types between
        samples; the smallest gap between distinct elliptic traces is included, so a dip
        towards a Krein collision is followed too."""
        if h not in self._cache:
            self._cache[h] = self._margin(h) if self.definite else self._trace_margin(h)
        return self._cache[h]

    def _trace_margin(self, h: float) -> float:
        out = self._evaluate(h)
        if out is None:
            return -np.inf
        D = out[0]
        n = self.n
        JDt = np.vstack([D.T[n:], -D.T[:n]])  # J D^T
        JDtJ = np.hstack([-JDt[:, n:], JDt[:, :n]])  # (J D^T) J
        u = np.sort(np.linalg.eigvals(D - JDtJ).real)
        ref = self.reference
        e = 2 * (ref.elliptic_plus + ref.elliptic_minus)
        limits = [np.inf]
        if e:
            limits += [u[0] + 4, -u[e - 1]]
            singles = u[0:e:2]
            if singles.size > 1:
                limits.append(float(np.diff(singles).min()))
        if e < u.size:
            limits.append(u[e])
        return float(min(limits))

    def _margin(self, h: float) -> float:
        import scipy.linalg as sla

        out = self._evaluate(h)
        if out is None:
            return -np.inf
        _, Q, err = out
        if self.weight is not None:
            scale = 1.0 / np.sqrt(self.weight)
            W = (self.sign * scale[:, None]) * Q * scale[None, :]
            inverse_norm2 = float(scale.max()) ** 2
        else:
            L = self.chol
            assert L is not None  # (the margin of a definite S)
            W = sla.solve_triangular(L, self.sign * Q, lower=True)
            W = sla.solve_triangular(L, W.T, lower=True)
            inverse_norm2 = self.inv_chol_norm2
        # |delta lambda| <= ||L^-1||_2^2 ||delta Q||_2 (L = diag(weight)^1/2 in the frame);
        # lambda_min(W) above that is proved by a Cholesky factorisation
        found = smallest(W, err * inverse_norm2)
        self._certified[h] = found.certified
        self._slack[h] = found.shift / (2 * h * self.unit)
        value = found.value if found.certified else min(found.value, 0.0)
        return value / (2 * h * self.unit)

    def certainly_lost(self, h: float) -> bool:
        """Definite S: whether the structure is lost at h beyond rounding (``Q`` has an
        eigenvalue below minus its rounding bound), at a pole, or the step is not unique."""
        poles = self.poles
        if poles.size and float(np.min(np.abs(poles - h))) <= POLE_BAND * h:
            return True
        value = self.margin(h)
        return value == -np.inf or value + 2 * self._slack.get(h, 0.0) < 0

    def certified(self, h: float) -> bool:
        """:meth:`preserved`, and where float64 cannot decide a small definite system,
        the criterion at high precision (:mod:`stepsafe.systems.coupled_exact`)."""
        if self.preserved(h):
            return True
        if not self.exact_sign or (self.definite and self.exact_sign != self.sign):
            return False
        if self.definite and self.certainly_lost(h):
            return False
        # (also where float64's Cholesky could not tell S definite and its floats are)
        factors = coupled_exact.euler_factors(self.method)
        assert factors is not None  # (exact_sign: a splitting)
        return coupled_exact.kept_exactly(factors, self.given, self.exact_sign, h)

    @cached_property
    def exact_sign(self) -> int:
        """The sign of the exact floats of S if they are definite and the criterion can be
        decided at high precision (a splitting, at most ``EXACT_SIZE`` rows); else 0."""
        if not coupled_exact.exact_capable(self.method, self.given):
            return 0
        return coupled_exact.definite_sign(self.given)

    @cached_property
    def inv_chol_norm2(self) -> float:
        """An upper bound on ``||L^-1||_2^2 = 1 / lambda_min(sign S)``: the computed smallest
        eigenvalue less its rounding bound (``4 (2n) eps |S|_F``), or, if that leaves
        nothing, ``||L^-1||_F^2``."""
        import scipy.linalg as sla

        low = extreme_eigenvalue(self.sign * self.S)
        low -= 8 * self.n * EPS * float(np.linalg.norm(self.S))
        if low > 0:
            return 1.0 / low
        assert self.chol is not None  # (asked of a definite S only)
        Linv = sla.solve_triangular(self.chol, np.eye(2 * self.n), lower=True)
        return float(np.linalg.norm(Linv)) ** 2

    def preserved(self, h: float) -> bool:
        """Whether one step of size h keeps the structure (decided beyond rounding). At a
        pole (within :data:`POLE_BAND` of it) the step is not unique: not kept."""
        if h <= 0:
            return True
        poles = self.poles
        if poles.size and float(np.min(np.abs(poles - h))) <= POLE_BAND * h:
            return False
        if self.definite:
            return self.margin(h) > 0 and self._certified.get(h, False)
        out = self._evaluate(h)
        if out is None:
            return False
        D, Q, err = out
        nu = np.linalg.eigvals(D + np.eye(D.shape[0]))
        ell, hyp, flips, lox, par = _multiplier_types(nu)
        lam = np.linalg.eigvalsh(Q)
        if np.any(np.abs(lam) <= err):
            return False  # Q singular within rounding: a multiplier at +-1, undecided
        krein = (int((lam > 0).sum()) - int((lam < 0).sum())) // 2
        ref = self.reference
        if ref.elliptic_plus and ref.elliptic_minus and _near_collision(nu):
            return False  # elliptic pairs of both Krein signs about to meet: undecided
        types = (flips == 0 and ell == ref.elliptic_plus + ref.elliptic_minus
                 and krein == ref.elliptic_plus - ref.elliptic_minus
                 and hyp == ref.hyperbolic and lox == ref.loxodromic
                 and par == ref.parabolic)
        return types and (ref.hyperbolic == 0 or self.oriented(D))

    @property
    def mixed_krein(self) -> bool:
        """Whether the flow has elliptic pairs of both Krein signs (indefinite S): such
        pairs become loxodromic where their multipliers meet (a Krein collision)."""
        return not self.definite and self.reference.elliptic_plus > 0 \
            and self.reference.elliptic_minus > 0

    def krein_order(self, h: float) -> tuple[int, ...] | None:
        """The Krein signs of the elliptic multipliers ordered by their angle in (0, pi):
        it changes between two steps exactly when pairs of opposite sign have crossed,
        i.e. met (None where the step is not unique)."""
        out = self._evaluate(h)
        if out is None:
            return None
        D = out[0]
        nu, V = np.linalg.eig(D + np.eye(D.shape[0]))
        upper = (np.abs(np.abs(nu) - 1) <= COLLISION_TOL) & (nu.imag > CIRCLE_TOL)
        plus, _ = _krein_counts(V, upper)
        n = self.n
        Vu = V[:, upper]
        form = ((np.conj(Vu[:n]) * Vu[n:]).sum(axis=0)
                - (np.conj(Vu[n:]) * Vu[:n]).sum(axis=0)).imag
        order = np.argsort(np.angle(nu[upper]))
        return tuple(int(np.sign(form[k])) for k in order)

    @cached_property
    def poles(self) -> np.ndarray:
        """The positive h where a step has no unique solution (sorted): ``1 / (c lambda)``
        for each Euler factor of weight c (``lambda`` a real eigenvalue of ``S_pq``, or of
        ``-S_qp`` for a KD factor), ``1 / (g lambda)`` for each PRK piece of weight g
        (``lambda`` a real eigenvalue of its stage operator; only up to
        :data:`MAX_POLE_SIZE` unknowns). Near a pole the structure can change within 1e-6
        of it, far closer than the scan's spacing, so the scan samples around each."""
        found: list[float] = []
        S = self.S
        n = self.n
        S_pq = S[n:, :n]
        eig_pq = None  # -S_qp = -S_pq^T has the eigenvalues of -S_pq
        for piece in self.steps.pieces:
            if isinstance(piece, Factors) and piece.kind == "ops":
                continue  # explicit: no stage equations, no poles
            if isinstance(piece, Factors):
                for label, c in piece.factors:
                    eig_pq = np.linalg.eigvals(S_pq) if eig_pq is None else eig_pq
                    lam = eig_pq if label == "DK" else -eig_pq
                    found += _reciprocals(c * lam)
            else:
                g, prk = piece
                if 2 * prk.stages * n > MAX_POLE_SIZE:
                    continue
                K = stage_operator(prk, hamiltonian_matrix(S)).K
                found += _reciprocals(g * np.linalg.eigvals(K))
        h = np.array(sorted(found)) / self.unit
        return h[np.isfinite(h) & (h > 0)]

    @cached_property
    def _flow_hyperbolic(self) -> tuple[np.ndarray, list[tuple[int, int]]]:
        """The inverse of the eigenvector matrix of ``J S`` (columns of unit length) and,
        per hyperbolic pair of the flow, the indices of its unstable and stable vectors."""
        mu, V = np.linalg.eig(hamiltonian_matrix(self.S))
        V = V / np.linalg.norm(V, axis=0)
        top = max(float(np.abs(mu).max()), 1e-300)
        real = (np.abs(mu.imag) <= 1e-9 * np.abs(mu)) & (np.abs(mu) > ZERO_TOL * top)
        pairs = [(int(i), int(np.argmin(np.abs(mu + mu[i])))) for i in np.flatnonzero(
            real & (mu.real > 0))]
        return np.linalg.inv(V), pairs

    def oriented(self, D: np.ndarray) -> bool:
        """Whether every expanding real multiplier's eigenvector lies with the flow's
        unstable direction: written in the flow's eigenvectors (unit length), its
        component on the unstable vector of the pair it is mostly made of exceeds the one
        on that pair's stable vector. For one degree of freedom this is the saddle's
        'q expands' and the barrier's 'v_q v_p > 0' (the flow's u and s of equal length
        are symmetric about the axes). Within 1e-8 of a tie it is undecided: not kept."""
        inverse, pairs = self._flow_hyperbolic
        if not pairs:
            return True
        nu, X = np.linalg.eig(D + np.eye(D.shape[0]))
        expanding = (np.abs(nu.imag) <= CIRCLE_TOL * np.abs(nu)) & (nu.real > 1 + CIRCLE_TOL)
        for x in X[:, expanding].T:
            c = np.abs(inverse @ x)
            u, s = max(((c[i], c[j]) for i, j in pairs), key=lambda pair: pair[0] + pair[1])
            if not u - s > 1e-8 * (u + s):
                return False
        return True


def _definite_coordinates(S: np.ndarray, sign: int, method: Method
                          ) -> tuple[np.ndarray, np.ndarray, DiagonalFrame | None]:
    """``(S', chol, frame)``: the coordinates a definite S is analysed in. Masses brought
    to O(1) by an exact power-of-two scaling, then the diagonal frame where its error
    leaves the margin room (:func:`_frame_pays`); the criterion and the types are invariant
    under both, and the margin is then weighted by ``diag(sign S~)``. Otherwise the
    original S or its q/p-balanced scaling, whichever has the larger
    ``lambda_min(sign S) / max |S|`` (the original coordinates' margin is weighted by the
    Cholesky factor of ``sign S``, and its rounding bound by ``1 / lambda_min``); ``chol``
    is the Cholesky factor of ``sign S'`` (also for the largest frequency)."""
    scaled = equilibrated(S)
    frame = diagonal_frame(scaled)
    if frame is not None and _frame_pays(frame, method, sign):
        return frame.S, np.linalg.cholesky(sign * scaled), frame
    best, best_ratio = S, -np.inf
    for candidate in (S, equilibrated(S, balance=True)):
        low = extreme_eigenvalue(sign * candidate)
        ratio = low / float(np.abs(candidate).max())
        if ratio > best_ratio:
            best, best_ratio = candidate, ratio
    return best, np.linalg.cholesky(sign * best), None


#: The frame's error may take at most this fraction of the margin at h -> 0.
FRAME_SHARE = 1e-3


def _frame_pays(frame: DiagonalFrame, method: Method, sign: int) -> bool:
    """Whether the frame's error leaves the margin room: at h -> 0 the weighted margin is
    ``lambda_min(W^-1/2 sign S~ W^-1/2)`` (``W = sign diag S~``) and the frame's error
    takes about ``ROUNDING_FACTOR 2 error sqrt(2n) sum |c| / min W`` of it (each Euler
    factor of weight c adds ``|c| h error |I + D|_F`` to the bound on Q). On a nearly
    semidefinite S (condition 1e9 and beyond) that can be all of it, and the analysis in
    the original coordinates, whose bound has no frame term, is kept instead."""
    weight = sign * np.concatenate([frame.a, frame.b])
    if not np.all(weight > 0):
        return False
    scale = 1.0 / np.sqrt(weight)
    low = extreme_eigenvalue((sign * scale[:, None]) * frame.S * scale[None, :])
    pieces = _pieces(method)
    euler = [piece for piece in pieces if isinstance(piece, Factors) and piece.kind == "euler"]
    reach = sum(abs(c) for piece in euler for _, c in piece.factors) \
        if len(euler) == len(pieces) else 0.0
    if reach == 0.0:
        return False  # only splittings run in the frame
    n = frame.a.size
    cost = ROUNDING_FACTOR * 2 * frame.error * np.sqrt(2 * n) * reach / float(weight.min())
    return bool(low > 0 and cost <= FRAME_SHARE * low)


def _largest_frequency(S: np.ndarray, chol: np.ndarray | None) -> float:
    """``max |mu|`` over the eigenvalues of ``J S``. For definite S (``sign S = L L^T``)
    ``J S`` is similar to the antisymmetric ``K = L^T J L``, whose eigenvalues ``+-i w`` have
    ``w^2`` the eigenvalues of ``K^T K``: one symmetric eigenvalue instead of a
    nonsymmetric eigenproblem."""
    if chol is None:
        return float(np.abs(np.linalg.eigvals(hamiltonian_matrix(S))).max())
    n = S.shape[0] // 2
    JL = np.vstack([chol[n:], -chol[:n]])
    K = chol.T @ JL
    top = extreme_eigenvalue(K.T @ K, highest=True)
    return float(np.sqrt(max(top, 0.0)))


def _reciprocals(lam: np.ndarray) -> list[float]:
    """``1 / lambda`` of the (numerically) real, nonzero entries of ``lam``."""
    lam = np.asarray(lam)
    top = float(np.abs(lam).max()) if lam.size else 0.0
    real = (np.abs(lam.imag) <= 1e-7 * np.abs(lam)) & (np.abs(lam) > 1e-14 * top)
    with np.errstate(divide="ignore", over="ignore"):
        return list(1.0 / lam.real[real])


#: Stage systems of more unknowns than this are not searched for poles (an eigenvalue
#: problem of that size per PRK piece).
MAX_POLE_SIZE = 400
#: Elliptic multipliers of an indefinite S closer than this to each other (and to the unit
#: circle) are about to collide: a weak coupling turns them loxodromic within a band of its
#: size, below what float64 eigenvalues show, so such a step is not certified.
COLLISION_TOL = 1e-6


def _near_collision(nu: np.ndarray) -> bool:
    upper = nu[(np.abs(np.abs(nu) - 1) <= COLLISION_TOL) & (nu.imag > CIRCLE_TOL)]
    if upper.size < 2:
        return False
    gaps = np.abs(upper[:, None] - upper[None, :]) + np.eye(upper.size)
    return bool(gaps.min() <= COLLISION_TOL)


#: A step within this (relative) of a pole is treated as the pole (its float64 location).
POLE_BAND = 1e-10
#: Relative distances from a pole at which the scan samples on both sides.
NEAR_POLE = 10.0 ** -np.arange(2, 14)

# ---------------------------------------------------------------- the safe interval


def coupled_safe_steps(method: Method | None, S: np.ndarray, zmax: float = 10.0,
                       progress: Callable[[float], None] | None = None,
                       deadline: float | None = None,
                       steps: Callable[[float], StepMatrices] | None = None) -> CoupledResult:
    """The safe interval from 0 of ``method`` on ``x' = J S x``, up to the horizon
    ``zmax / |mu|_max``.

    The scan steps by ``SCAN_DZ`` in z = h |mu|_max until the first h that is not
    preserved; for definite S it also follows ``phi`` into any dip between samples (a
    local minimum among three samples is refined by golden section) and brackets the
    boundary on ``phi`` (Brent), for indefinite S by bisection; both to ``REL_TOL``
    relative, ending on an h that is preserved.

    ``progress(fraction)`` is called after each scan sample (the fraction of the horizon
    scanned). At ``deadline`` (a ``time.monotonic()`` value) the scan stops: the horizon
    becomes the last h scanned, every h below it having been found preserved. ``steps``:
    see :class:`CoupledSystem`.
    """
    with blas_threads_for(S.shape[0]):
        return _safe_steps(method, S, zmax, progress, deadline, steps)


def _safe_steps(method: Method | None, S: np.ndarray, zmax: float,
                progress: Callable[[float], None] | None, deadline: float | None,
                steps: Callable[[float], StepMatrices] | None = None) -> CoupledResult:
    system = CoupledSystem(method, S, steps)
    if system.top == 0:
        return CoupledResult(np.inf, np.inf, 0, "coupled: S = 0, no limit")
    horizon = zmax / system.top
    count = max(2, int(np.ceil(zmax / SCAN_DZ)))
    hs = horizon * np.arange(1, count + 1) / count
    if not system.definite and system.exact_sign:
        # float64's Cholesky could not tell S definite, its exact floats are: every step
        # is decided at high precision
        factors = coupled_exact.euler_factors(method)
        assert factors is not None  # (exact_sign: a splitting)
        h_max = coupled_exact.exact_boundary(factors, S, system.exact_sign, 0.0, horizon,
                                             REL_TOL, hs, progress)
        if progress:
            progress(1.0)
        return CoupledResult(h_max, horizon, system.evaluations,
                             "coupled: full 2n x 2n one-step matrix; S definite at "
                             f"{coupled_exact.PRECISION} digits (float64 could not tell), "
                             "Q(h) = M^T J - J M positive definite decided at that precision")
    poles = system.poles[system.poles < horizon]
    if poles.size:
        near = (poles[:, None] * (1.0 + np.concatenate([-NEAR_POLE, NEAR_POLE])[None, :]))
        near = near[(near > 0) & (near < horizon)].ravel()
        hs = np.union1d(hs, near[~np.isin(near, poles)])
        count = hs.size
    analysis = ("coupled: full 2n x 2n one-step matrix; "
                + ("S definite, Q(h) = M^T J - J M positive definite"
                   if system.definite else
                   "S indefinite, multiplier types and the inertia of M^T J - J M")
                + " against J S (the modes do not decouple for this method)")
    lo = 0.0
    order = None
    if system.mixed_krein:
        # finer steps: an opposite-Krein crossing is seen as a change of the ordering
        # between two samples, and the loxodromic band it opens can be narrow
        hs = np.union1d(hs, horizon * np.arange(1, 10 * count + 1) / (10 * count))
        count = hs.size
        order = system.krein_order(hs[0] * 1e-3)
    for k, h in enumerate(hs):
        if deadline is not None and time.monotonic() > deadline and lo > 0:
            return CoupledResult(lo, lo, system.evaluations, analysis + "; stopped by the "
                                 f"time budget at z = {lo * system.top:.3g} of {zmax:g}")
        bad = _first_failure(system, lo, h, hs[k - 2] if k >= 2 else None)
        if bad is None and poles.size and lo < poles[0] <= h:
            bad = (lo, float(poles[0]))  # the first pole ends the interval from 0
        if bad is None and order is not None and system.krein_order(h) != order:
            bad = (lo, h)  # pairs of opposite Krein sign met in between
        if bad is not None:
            good, lost = bad
            h_max = _boundary(system, good, lost, order)
            undecided = _undecided(system, h_max, hs, horizon)
            if undecided is not None and system.exact_sign == system.sign:
                factors = coupled_exact.euler_factors(method)
                assert factors is not None  # (exact_sign: a splitting)
                h_max = max(h_max, coupled_exact.exact_boundary(
                    factors, S, system.sign, h_max, undecided, REL_TOL, hs,
                    _rescaled(progress, undecided / horizon)))
                analysis += (f"; the boundary decided at {coupled_exact.PRECISION} digits "
                             "(float64's rounding bound reached the margin)")
                undecided = None
            if progress:
                progress(1.0)
            return CoupledResult(h_max, horizon, system.evaluations, analysis, undecided)
        lo = h
        if progress:
            progress((k + 1) / count)
    return CoupledResult(horizon, horizon, system.evaluations, analysis)


def _first_failure(system: CoupledSystem, lo: float, h: float, before: float | None
                   ) -> tuple[float, float] | None:
    """``(good, bad)`` bracketing a first failure in (lo, h], or None if none is seen."""
    if not system.preserved(h):
        return lo, h
    if before is None or not system.tracks_types:
        return None
    # a dip of phi between samples: lo is a local minimum among (before, lo, h)
    a, m, b = before, lo, h
    fa, fm, fb = system.margin(a), system.margin(m), system.margin(b)
    if not (fm < fa and fm < fb):
        return None
    golden = 0.5 * (3 - 5 ** 0.5)
    for _ in range(40):
        if b - a <= REL_TOL * b:
            break
        x = m + golden * (b - m) if b - m > m - a else m - golden * (m - a)
        fx = system.margin(x)
        # hyperbolic pairs can reverse where their trace only touches 2 (M = +I on a
        # saddle): there the margin need not go below 0, so each point is decided
        if (fx <= 0 or system.reference.hyperbolic) and not system.preserved(x):
            return (a, x) if x < m else (m, x)  # preserved at a / m, not at x
        if fx < fm:
            a, b = (m, b) if x > m else (a, m)
            m, fm = x, fx
        else:
            a, b = (a, x) if x > m else (x, b)
    return None


#: A boundary is taken as decided by float64 when the criterion is certainly lost within
#: this (relative) of the first step found not preserved. Every boundary has such a band,
#: of the size of the rounding bound: about 1e-11 on a well-conditioned S of a few rows,
#: 1e-6 at 200 dof (the accuracy the analysis states for h_max); a wider one means the
#: bound reaches the margin before the structure is lost.
BAND_MIN = 1e-4


def _undecided(system: CoupledSystem, h_max: float, hs: np.ndarray, horizon: float
               ) -> float | None:
    """Definite S: None if the boundary after ``h_max`` is decided, i.e. the criterion is
    certainly lost within :data:`BAND_MIN` of the first step found not preserved (among
    the steps evaluated, by the margin's slope there, or at that distance: one more
    one-step matrix); else the first step found certainly lost beyond it (the horizon if
    none is): float64 decides nothing between."""
    if not system.definite:
        return None
    after = sorted(h for h in system._cache if h > h_max)
    first = next((h for h in after if not system.preserved(h)), None)
    if first is None:
        return None
    near = first * (1.0 + BAND_MIN)
    if any(h <= near and system.certainly_lost(h) for h in after):
        return None
    # where the margin, falling at the slope between the two nearest steps whose margins
    # are decided far beyond their rounding bounds (its slope, not its noise), is certainly
    # lost: within half of BAND_MIN is taken as decided without another one-step matrix
    clear = sorted((abs(h - first), h) for h in system._cache
                   if np.isfinite(system.margin(h))
                   and abs(system.margin(h)) > 100 * system._slack.get(h, np.inf))
    estimate = None
    if len(clear) >= 2 and np.isfinite(system.margin(first)):
        (_, a), (_, b) = clear[:2]
        slope = (system.margin(b) - system.margin(a)) / (b - a)
        if slope < 0:
            estimate = first + (system.margin(first) + 2 * system._slack.get(first, 0.0)
                                ) / -slope
            if estimate <= first * (1.0 + 0.5 * BAND_MIN):
                return None
    if system.certainly_lost(near):
        return None
    lost = next((h for h in sorted(set(after) | {float(x) for x in hs if x > first})
                 if h > first and system.certainly_lost(h)), horizon)
    if estimate is not None and near < 2 * estimate - first < lost and \
            system.certainly_lost(2 * estimate - first):
        lost = 2 * estimate - first  # a tighter end, found at twice the estimated distance
    return lost


def _rescaled(progress: Callable[[float], None] | None, scale: float
              ) -> Callable[[float], None] | None:
    """``progress`` called with its fraction times ``scale``."""
    return None if progress is None else (lambda fraction: progress(fraction * scale))


def _tightest(system: CoupledSystem, good: float, bad: float) -> tuple[float, float]:
    """The narrowest ``(good, bad)`` among the steps already evaluated: the last preserved
    one inside and the first not preserved after it (no new one-step matrix)."""
    inside = sorted(h for h in system._cache if good < h < bad)
    for h in inside:
        if system.margin(h) > 0 and system.preserved(h):
            good = h
    for h in inside:
        if h > good and not system.preserved(h):
            return good, h
    return good, bad


def _boundary(system: CoupledSystem, good: float, bad: float,
              order: tuple[int, ...] | None = None) -> float:
    """The last preserved h of ``(good, bad)``, to ``REL_TOL``: Brent on phi (definite S),
    bisection otherwise; the result is always an h that was found preserved (0 if none
    down to ``bad`` 1e-30 is)."""
    if good == 0.0:
        for _ in range(30):
            trial = bad / 10
            if trial == 0.0:  # (below the subnormals: no step is known to be kept)
                return 0.0
            if system.preserved(trial):
                good = trial
                break
            bad = trial
        else:
            return 0.0
    if system.definite and np.isfinite(system.margin(bad)) and good > 0:
        from scipy.optimize import brentq

        try:
            root = brentq(system.margin, good, bad, xtol=REL_TOL * bad * 0.25, rtol=4 * EPS,
                          maxiter=60)
            # Brent's own last samples usually bracket the root to REL_TOL already (the
            # margin changes sign once between good and bad, as Brent assumes)
            good, bad = _tightest(system, good, bad)
            # otherwise: the root is within xtol = REL_TOL bad / 4 of brentq's, and a
            # bracket of root -+ REL_TOL root / 2 is accepted as it stands
            step = 0.5 * REL_TOL * root
            if bad - good > REL_TOL * bad:
                for candidate in (root - step, root - 4 * step, root - 16 * step):
                    if good < candidate and system.preserved(candidate):
                        good = candidate
                        break
            if bad - good > REL_TOL * bad and system.preserved(min(bad, root + step)) is False:
                bad = min(bad, root + step)
        except (ValueError, RuntimeError):
            pass  # no sign change seen, or no convergence: bisection below decides
    while bad - good > REL_TOL * bad:
        mid = 0.5 * (good + bad)
        if not good < mid < bad:
            break  # adjacent floats (subnormal h: REL_TOL * bad underflows to 0)
        if system.preserved(mid) and (order is None or system.krein_order(mid) == order):
            good = mid
        else:
            bad = mid
    return good
