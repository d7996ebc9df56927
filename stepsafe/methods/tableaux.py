"""One-step methods as data: Runge–Kutta, partitioned RK, splitting, composition and
impulse (multiple time stepping).

Conventions. Phase space is ``x = (q, p)``; a partitioned method integrates
``q' = f(q, p)`` with the tableau ``(A_q, b_q)`` and ``p' = g(q, p)`` with ``(A_p, b_p)``::

    Q_i = q0 + h sum_j A_q[i, j] f(Q_j, P_j)      q1 = q0 + h sum_j b_q[j] f(Q_j, P_j)
    P_i = p0 + h sum_j A_p[i, j] g(Q_j, P_j)      p1 = p0 + h sum_j b_p[j] g(Q_j, P_j)

A splitting method for ``H = T(p) + V(q)`` applies ``drift(a_1 h), kick(b_1 h),
drift(a_2 h), ...`` in that order (``drift(t): q += t T'(p)``, ``kick(t): p -= t V'(q)``).
A composition ``Phi_{g_k h} o ... o Phi_{g_1 h}`` applies the base with ``g_1 h`` first.

Each class implements :class:`~stepsafe.methods.protocol.MethodKind` (its stages, symmetry,
residuals, decomposition into blocks, ...), which is all the analyses ask of it.

The classes are frozen and their coefficient arrays are read-only copies (an analysis
made later sees the coefficients the method was built with); they validate shapes and
finiteness when built and raise :class:`~stepsafe.exceptions.MethodError`. Nothing here
knows of files or terminals.

``exact`` (optional, never compared) names the method's exact definition
(:class:`~stepsafe.methods.protocol.Exact`: a family member, or a method file read with its
decimal literals exact), from which :mod:`stepsafe.methods.exact` builds its transfer matrix
at high precision rather than from the rounded floats; the region finder asks for it where
float64 cannot decide (:mod:`stepsafe.core.escalate`). Without it the float coefficients are
taken as exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from stepsafe.exceptions import MethodError
from stepsafe.methods.protocol import (
    DIAGONAL_MODELS,
    Block,
    Exact,
    MethodKind,
    Shears,
    Stages,
)
from stepsafe.methods.residuals import RESIDUAL_TOL, Residuals, prk_residuals

#: Most base steps a composition may take once nested compositions are multiplied out
#: (checked when it is built, before :meth:`Composition.flattened` allocates anything):
#: three nested files of 100 weights would be 10^6 steps and gigabytes.
MAX_BASE_STEPS = 1000
#: Most drifts and kicks a composition over a splitting may apply a step, once multiplied
#: out (the library's largest: 105, sofroniou-spaletta10); the work of every analysis is in
#: proportion (399 steps of a 400-operation base take more than 15 minutes).
MAX_COMPOSED_OPERATIONS = 4000
#: A composition of an RK/PRK base solves one stage system per base step and per sample of
#: M(z), and needs samples in proportion to how far its substeps reach: at most this much
#: work, counted as base steps x stages^3 x sum |weights| (yoshida4 over Gauss s = 40:
#: 8.4e5, about 10 s; 200 steps of Gauss s = 10 of total weight 1: 2e5).
MAX_IMPLICIT_WORK = 1_000_000


def _vector(values, name: str) -> np.ndarray:
    """``values`` as a read-only 1-d float copy (a method's coefficients never change)."""
    arr = np.array(values, dtype=float)
    if arr.ndim != 1 or arr.size == 0:
        raise MethodError(f"{name} must be a non-empty list of numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MethodError(f"{name} has a non-finite entry")
    arr.setflags(write=False)
    return arr


def mirrored(x, y, tol: float) -> bool:
    """Each of ``x`` equal to its mirror in ``y`` to ``tol`` relative to the pair (a large
    coefficient elsewhere does not hide a mismatch between two small ones)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    return bool(np.all(np.abs(x - y) <= tol * np.maximum(np.abs(x), np.abs(y))))


def _rk_symmetric(prk: PartitionedRK, tol: float) -> bool:
    """``a_ij + a_{s+1-i, s+1-j} = b_j`` and ``b`` palindromic for both tableaux (after the
    standard stage reversal), each to ``tol`` relative."""
    ok = True
    for A, b in ((prk.A_q, prk.b_q), (prk.A_p, prk.b_p)):
        size = np.abs(A) + np.abs(A[::-1, ::-1]) + np.abs(b)[None, :]
        ok &= bool(np.all(np.abs(A + A[::-1, ::-1] - b[None, :]) <= tol * size))
        ok &= mirrored(b, b[::-1], tol)
    return ok


def _prk_reach(prk: PartitionedRK) -> float:
    return float(max(1.0, np.abs(prk.A_q).sum(axis=1).max(), np.abs(prk.A_p).sum(axis=1).max()))


def _square(values, name: str, size: int) -> np.ndarray:
    """``values`` as a read-only (size, size) float copy."""
    arr = np.array(values, dtype=float)
    if arr.shape != (size, size):
        raise MethodError(f"{name} must be {size}x{size} to match its weights, "
                          f"got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MethodError(f"{name} has a non-finite entry")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class PartitionedRK(MethodKind):
    """Partitioned Runge–Kutta method: ``(A_q, b_q)`` for q, ``(A_p, b_p)`` for p."""

    A_q: np.ndarray
    b_q: np.ndarray
    A_p: np.ndarray
    b_p: np.ndarray
    name: str = "prk"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    exact: Exact | None = field(default=None, compare=False, repr=False)
    #: the symplecticity residuals of the coefficients as a method file writes them
    #: (:func:`stepsafe.methods.residuals.written_residuals`); None: the floats as given
    written: Any = field(default=None, compare=False, repr=False)

    kind = "prk"

    def __post_init__(self) -> None:
        b_q = _vector(self.b_q, "b_q")
        b_p = _vector(self.b_p, "b_p")
        if b_q.size != b_p.size:
            raise MethodError(f"b_q has {b_q.size} entries but b_p has {b_p.size}")
        object.__setattr__(self, "b_q", b_q)
        object.__setattr__(self, "b_p", b_p)
        object.__setattr__(self, "A_q", _square(self.A_q, "A_q", b_q.size))
        object.__setattr__(self, "A_p", _square(self.A_p, "A_p", b_p.size))

    @property
    def stages(self) -> int:
        return int(self.b_q.size)

    @property
    def explicit(self) -> bool:
        """True when both tableaux are strictly lower triangular (no stage solve needed)."""
        return bool(not np.triu(self.A_q).any() and not np.triu(self.A_p).any())

    def as_prk(self) -> PartitionedRK:
        return self

    def rk_form(self) -> PartitionedRK:
        return self

    def symmetric(self, tol: float = 1e-12) -> bool:
        return _rk_symmetric(self, tol)

    def residuals(self) -> Residuals:
        return prk_residuals(self, None, self.written)

    def coefficients(self) -> dict[str, Any]:
        return {k: getattr(self, k).tolist() for k in ("A_q", "b_q", "A_p", "b_p")}

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        return (Stages(self),)

    @property
    def reach(self) -> float:
        return _prk_reach(self)

    @property
    def sample_work(self) -> float:
        """``(2s)^3`` for an implicit method (a stage solve), ``s^2`` for an explicit one."""
        s = self.stages
        return float((2 * s) ** 3 if not self.explicit else s * s)

@dataclass(frozen=True, eq=False)
class RungeKutta(MethodKind):
    """Runge–Kutta method ``(A, b, c)``; the PRK with both tableaux equal."""

    A: np.ndarray
    b: np.ndarray
    c: np.ndarray | None = None
    name: str = "rk"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    exact: Exact | None = field(default=None, compare=False, repr=False)
    #: as :attr:`PartitionedRK.written`
    written: Any = field(default=None, compare=False, repr=False)

    kind = "rk"

    def __post_init__(self) -> None:
        b = _vector(self.b, "b")
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "A", _square(self.A, "A", b.size))
        c = _vector(self.A.sum(axis=1) if self.c is None else self.c, "c")
        if c.size != b.size:
            raise MethodError(f"c has {c.size} entries but b has {b.size}")
        object.__setattr__(self, "c", c)

    @property
    def stages(self) -> int:
        return int(self.b.size)

    @cached_property
    def explicit(self) -> bool:
        return bool(not np.triu(self.A).any())

    def as_prk(self) -> PartitionedRK:
        return PartitionedRK(self.A, self.b, self.A, self.b, name=self.name, order=self.order,
                             exact=self.exact, written=self.written)

    def rk_form(self) -> PartitionedRK:
        return self.as_prk()

    @property
    def single_tableau(self) -> bool:
        return True

    @property
    def partitioned(self) -> bool:
        return False

    def symmetric(self, tol: float = 1e-12) -> bool:
        return _rk_symmetric(self.as_prk(), tol)

    def residuals(self) -> Residuals:
        row_sums = float(np.abs(self.A.sum(axis=1) - self.c).max())
        return prk_residuals(self.as_prk(), row_sums, self.written)

    def coefficients(self) -> dict[str, Any]:
        c = self.A.sum(axis=1) if self.c is None else self.c  # (c is set when built)
        return {"A": self.A.tolist(), "b": self.b.tolist(), "c": c.tolist()}

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        return (Stages(self),)

    @property
    def reach(self) -> float:
        return _prk_reach(self.as_prk())

    @property
    def sample_work(self) -> float:
        """``(2s)^3`` for an implicit method (a stage solve), ``s^2`` for an explicit one."""
        s = self.stages
        return float((2 * s) ** 3 if not self.explicit else s * s)

@dataclass(frozen=True, eq=False)
class Splitting(MethodKind):
    """Splitting method ``drift(a_1 h) kick(b_1 h) drift(a_2 h) ...`` for ``H = T(p) + V(q)``.

    ``drift`` has as many entries as ``kick`` or one more; zero coefficients are allowed
    (a method that starts with a kick has ``a_1 = 0``).

    Force-gradient methods carry ``gradient`` (one coefficient ``c_i`` per kick, zeros
    allowed): with ``F = -V'(q)`` and ``T = p^T M^-1 p / 2`` kick i is then
    ``p += b_i h F + c_i h^3 grad(|F|^2_{M^-1})``, the kick by the potential
    ``b_i V - c_i h^2 |grad V|^2_{M^-1}``; ``grad |F|^2_{M^-1} = 2 V''(q) M^-1 V'(q)``.
    This is Chin's ``exp(b_i h V~)``, ``V~ = V + (c_i / b_i) h^2 [V, [T, V]]``, with the
    double commutator of the classical Lie operators (``T = p M^-1 d/dq``,
    ``V = F d/dp``): ``[V, [T, V]] = grad(|F|^2_{M^-1}) d/dp``, the kick of the potential
    ``-sum_j (d_j V)^2 / m_j`` (the quantum ``[V, [T, V]] = sum_j (d_j V)^2 / m_j`` of
    ``T = -nabla^2 / 2m`` enters ``exp(-h H)`` with the opposite sign: the published
    positive coefficients, e.g. Chin's 4A ``c = (2/3)(1/48) = 1/72``, keep their sign
    here). Such a method has
    no PRK form (:meth:`euler_factors` refuses it): it needs a separable H with a quadratic
    kinetic energy. ``displaced`` marks the Hessian-free evaluation of the same kick (a force
    at a displaced position, see :mod:`stepsafe.core.integrator`), identical on quadratic V.
    """

    drift: np.ndarray
    kick: np.ndarray
    name: str = "splitting"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    exact: Exact | None = field(default=None, compare=False, repr=False)
    gradient: np.ndarray | None = None
    displaced: bool = False

    kind = "splitting"

    def __post_init__(self) -> None:
        a = _vector(self.drift, "drift")
        b = _vector(self.kick, "kick")
        if a.size not in (b.size, b.size + 1):
            raise MethodError(
                f"drift must have as many entries as kick or one more, got {a.size} and {b.size}"
            )
        object.__setattr__(self, "drift", a)
        object.__setattr__(self, "kick", b)
        if self.gradient is not None:
            c = _vector(self.gradient, "gradient")
            if c.size != b.size:
                raise MethodError(f"gradient must have one entry per kick, got {c.size} "
                                  f"for {b.size} kicks")
            object.__setattr__(self, "gradient", c if c.any() else None)
        if self.displaced and self.gradient is not None:
            bad = [i for i in range(b.size) if self.gradient[i] != 0 and b[i] == 0]
            if bad:
                raise MethodError(f"kick {bad[0]}: a displaced-force (Hessian-free) kick "
                                  "needs a nonzero kick coefficient where its gradient "
                                  "coefficient is nonzero")

    @property
    def force_gradient(self) -> bool:
        """True when some kick carries a force-gradient term."""
        return self.gradient is not None

    @property
    def operations(self) -> list[tuple[str, float]]:
        """The step as a list of ``("drift"|"kick"|"gradient", coefficient)``, zeros dropped,
        merged. ``("gradient", c)`` is ``p += c h^3 grad |grad V|^2_{M^-1}``; it commutes
        with the kick at the same q, so the kicks and gradients between two drifts are
        merged into one ``kick`` followed by one ``gradient``. Without a gradient the list
        alternates drift and kick."""
        ops: list[tuple[str, float]] = []
        grad = self.gradient
        for i, a in enumerate(self.drift):
            seq = [("drift", a)]
            if i < self.kick.size:
                seq.append(("kick", self.kick[i]))
                if grad is not None:
                    seq.append(("gradient", grad[i]))
            for kind, coef in seq:
                if coef == 0.0:
                    continue
                ops.append((kind, float(coef)))
        return merge_operations(ops)

    @property
    def gradient_evaluations(self) -> int:
        """Force-gradient terms per step as run (Hessian-vector products): one per kick
        group with a gradient, the step's last and the next step's first merged when no
        drift separates them; 0 without a gradient, and for the displaced-force form,
        whose extra forces the file counts as forces."""
        if self.displaced or self.gradient is None:
            return 0
        ops = self.operations
        count = sum(1 for kind, _ in ops if kind == "gradient")
        head = [kind for kind, _ in ops[:2]]
        tail = [kind for kind, _ in ops[-2:]]
        if count > 1 and ops[0][0] != "drift" and ops[-1][0] != "drift" \
                and "gradient" in head and "gradient" in tail:
            count -= 1  # the closing gradient is the next step's opening one
        return count

    @property
    def forces_per_step(self) -> int | None:
        """Force evaluations per step as run: the kicks, the step's closing kick and the
        next step's opening one merged when no drift separates them (both at the same q);
        None for the displaced-force form, whose extra forces depend on how the file
        counts them."""
        if self.displaced:
            return None
        ops = self.operations
        kicks = sum(1 for kind, _ in ops if kind == "kick")
        if kicks > 1 and ops[0][0] != "drift" and ops[-1][0] != "drift":
            kicks -= 1
        return kicks

    @property
    def stages(self) -> int:
        """Number of kicks (force evaluations before first-same-as-last merging)."""
        return sum(1 for kind, _ in self.operations if kind == "kick")

    @property
    def explicit(self) -> bool:
        return True

    def euler_factors(self) -> list[tuple[str, float]]:
        """The step as a composition of symplectic Euler steps and their adjoints.

        ``DK(c)`` is drift(c h) then kick(c h); ``KD(d)`` is kick(d h) then drift(d h).
        ``DK(c_1) KD(d_1) ... DK(c_m) KD(d_m)`` merges to drift(c_1) kick(c_1 + d_1)
        drift(d_1 + c_2) ... kick(c_m + d_m) drift(d_m), so ``c_1 = a_1``,
        ``d_k = b_k - c_k``, ``c_{k+1} = a_{k+1} - d_k`` and the last drift must equal
        ``d_m``, which holds exactly when ``sum(a) = sum(b)``. Each factor is a 1-stage PRK
        with ``b_q = b_p``, so the product is a PRK that is symplectic for every H:
        kick-drift-kick Verlet becomes ``KD(1/2) DK(1/2)``, the 2-stage
        Lobatto IIIA–IIIB pair. Zero-weight factors are dropped.
        """
        if self.force_gradient:
            raise MethodError(
                f"{self.name} is a force-gradient method: its kicks use grad |grad V|^2 of a "
                "separable H = p^T M^-1 p / 2 + V(q), so it has no PRK form and no form for "
                "an H that mixes q and p (such as the saddle model)")
        m = self.kick.size
        a = np.zeros(m + 1)
        a[: self.drift.size] = self.drift
        mismatch = abs(a.sum() - self.kick.sum())
        if not mismatch <= RESIDUAL_TOL * max(np.abs(a).sum(), np.abs(self.kick).sum()):
            raise MethodError(
                f"sum(drift) - sum(kick) = {a.sum() - self.kick.sum():.3g}: a splitting method "
                "with unequal drift and kick sums has no PRK form for non-separable models"
            )
        factors: list[tuple[str, float]] = []
        c = a[0]
        for k in range(m):
            d = self.kick[k] - c
            factors += [("DK", float(c)), ("KD", float(d))]
            c = a[k + 1] - d
        return [(kind, w) for kind, w in factors if w != 0.0]

    def as_prk(self) -> PartitionedRK:
        """PRK tableaux with ``b_q = b_p`` built from :meth:`euler_factors`.

        Stage i is factor i: ``A_q[i, j] = A_p[i, j] = w_j`` for ``j < i``; the diagonal is
        ``w_i`` in ``A_q`` for a DK factor and in ``A_p`` for a KD factor.
        """
        factors = self.euler_factors()
        w = np.array([wk for _, wk in factors])
        A_q = np.tril(np.tile(w, (w.size, 1)), k=-1)
        A_p = A_q.copy()
        for i, (kind, wi) in enumerate(factors):
            (A_q if kind == "DK" else A_p)[i, i] = wi
        return PartitionedRK(A_q, w, A_p, w.copy(), name=self.name, order=self.order,
                             exact=self.exact)

    def splitting(self) -> Splitting:
        return self

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        return (Shears(self),)

    def symmetric(self, tol: float = 1e-12) -> bool:
        """The merged drift/kick sequence is a palindrome (each kick group, a kick and its
        gradient term at one q, one symbol)."""
        ops: list[tuple[str, float, float]] = []
        for kind, c in self.operations:
            if kind == "gradient" and ops and ops[-1][0] == "kick":
                ops[-1] = ("kick", ops[-1][1], c)
            else:
                ops.append((kind, c, 0.0) if kind != "gradient" else ("kick", 0.0, c))
        return all(k1 == k2 and mirrored(b1, b2, tol) and mirrored(c1, c2, tol)
                   for (k1, b1, c1), (k2, b2, c2) in zip(ops, ops[::-1]))

    def residuals(self) -> Residuals:
        """Symplectic by construction; consistent when the drifts and the kicks sum to 1."""
        cons = max(abs(float(self.drift.sum()) - 1.0), abs(float(self.kick.sum()) - 1.0))
        mag = float(max(np.abs(self.drift).max(), np.abs(self.kick).max()))
        return Residuals(0.0, 0.0, cons, None, mag)

    def coefficients(self) -> dict[str, Any]:
        out = {"drift": self.drift.tolist(), "kick": self.kick.tolist()}
        if self.gradient is not None:
            out["gradient"] = self.gradient.tolist()
        return out

    @property
    def reach(self) -> float:
        """The larger of the drift and the kick sums of absolute values (at least 1); with
        force gradients, where a kick's coefficient ``b - 2 c z^2`` turns and how far the
        ``2 c z^3`` terms reach."""
        kicks = float(np.abs(self.kick).sum())
        if self.gradient is not None:
            # a kick's coefficient b - 2 c z^2 turns at z = sqrt(|b| / 2|c|); with no kick the
            # term 2 c z^3 = (cbrt(2 c) z)^3 (cube roots taken apart: c may be ~1e308)
            c = np.abs(self.gradient)
            b = np.abs(self.kick[: c.size])
            with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
                turn = np.where(b > 0, np.sqrt(2.0) * np.sqrt(c) / np.sqrt(b), 0.0)
            kicks += float(np.cbrt(2.0) * np.cbrt(c).sum()) + float(turn.max(initial=0.0))
        return float(max(np.abs(self.drift).sum(), kicks, 1.0))

    @property
    def sample_work(self) -> float:
        """The number of factors."""
        extra = 0 if self.gradient is None else int(np.count_nonzero(self.gradient))
        return float(max(1, self.drift.size + self.kick.size + extra))

#: Any method kind (the protocol every kind implements).
Method = MethodKind


@dataclass(frozen=True, eq=False)
class Composition(MethodKind):
    """Composition ``Phi_{g_k h} o ... o Phi_{g_1 h}`` of a base method (weights may be < 0)."""

    base: MethodKind
    weights: np.ndarray
    name: str = "composition"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    base_order: int | None = field(default=None)
    exact: Exact | None = field(default=None, compare=False, repr=False)

    kind = "composition"

    def __post_init__(self) -> None:
        object.__setattr__(self, "weights", _vector(self.weights, "weights"))
        if getattr(self.base, "kind", "") == "impulse":
            raise MethodError(f"{self.name}: the base of a composition must be a one-force "
                              f"method; {self.base.name} is an impulse (multiple time "
                              "stepping) method")
        if getattr(self.base, "kind", "") == "langevin":
            raise MethodError(f"{self.name}: the base of a composition must be a Hamiltonian "
                              f"method; {self.base.name} is a Langevin splitting (its "
                              "friction step has no substeps of negative length)")
        if self.base_steps > MAX_BASE_STEPS:
            raise MethodError(
                f"{self.name}: {self.base_steps} steps of the base method once the nested "
                f"compositions are multiplied out, more than the {MAX_BASE_STEPS} allowed")
        inner = self.base
        while isinstance(inner, Composition):
            inner = inner.base
        if isinstance(inner, Splitting) and \
                self.base_steps * len(inner.operations) > MAX_COMPOSED_OPERATIONS:
            raise MethodError(
                f"{self.name}: {self.base_steps} steps of a base of {len(inner.operations)} "
                f"drifts and kicks: {self.base_steps * len(inner.operations)} operations a "
                f"step, more than the {MAX_COMPOSED_OPERATIONS} analysed in bounded time")
        if isinstance(inner, (RungeKutta, PartitionedRK)) and not inner.explicit:
            work = self.base_steps * inner.stages ** 3 * max(1.0, self.weight_sum)
            if work > MAX_IMPLICIT_WORK:
                raise MethodError(
                    f"{self.name}: {self.base_steps} steps of a {inner.stages}-stage implicit "
                    f"base: stage-solve work {work:.3g} (steps x stages^3 x sum |weights|) "
                    f"exceeds the {MAX_IMPLICIT_WORK:.3g} allowed")

    @property
    def weight_sum(self) -> float:
        """Sum of |weights| once nested compositions are multiplied out (how far the
        substeps reach, in steps of the base), counted without multiplying out."""
        inner = self.base.weight_sum if isinstance(self.base, Composition) else 1.0
        return float(np.abs(self.weights).sum()) * inner

    @property
    def base_steps(self) -> int:
        """Steps of the innermost base per step, counted without multiplying out."""
        inner = self.base.base_steps if isinstance(self.base, Composition) else 1
        return int(self.weights.size) * inner

    @property
    def stages(self) -> int:
        """Total stages: base stages times the number of substeps."""
        return self.base.stages * int(self.weights.size)

    @property
    def explicit(self) -> bool:
        return self.base.explicit

    def as_splitting(self) -> Splitting:
        """A composition of a splitting method is a splitting method: its operations with
        every coefficient scaled by the substep's weight, adjacent drifts/kicks merged."""
        flat = self.flattened()
        if not isinstance(flat.base, Splitting):
            raise MethodError(f"{self.name}: the base is not a splitting method")
        ops = [(kind, (g ** 3 if kind == "gradient" else g) * coef) for g in flat.weights
               for kind, coef in flat.base.operations]  # a gradient term scales as h^3
        return splitting_from_operations(ops, name=self.name, order=self.order,
                                         evaluations=self.evaluations, title=self.title,
                                         exact=self.exact, displaced=flat.base.displaced)

    def flattened(self) -> Composition:
        """The same map with a non-composition base (nested weights multiplied out)."""
        if not isinstance(self.base, Composition):
            return self
        inner = self.base.flattened()
        weights = np.concatenate([g * inner.weights for g in self.weights])
        return Composition(inner.base, weights, name=self.name, order=self.order,
                           evaluations=self.evaluations, title=self.title, exact=self.exact)

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        """The base's blocks once per weight (nested compositions multiplied out), each
        block's weight times the substep's."""
        flat = self.flattened()
        blocks = flat.base.decomposition(model)
        return tuple(replace(b, weight=float(g) * b.weight) for g in flat.weights
                     for b in blocks)

    def splitting(self) -> Splitting | None:
        return self.as_splitting() if isinstance(self.flattened().base, Splitting) else None

    @property
    def force_gradient(self) -> bool:
        return self.flattened().base.force_gradient

    @property
    def forces_per_step(self) -> int | None:
        step = self.splitting()
        return None if step is None else step.forces_per_step

    @property
    def gradient_evaluations(self) -> int:
        step = self.splitting()
        return 0 if step is None else step.gradient_evaluations

    @property
    def partitioned(self) -> bool:
        return self.base.partitioned

    def symmetric(self, tol: float = 1e-12) -> bool:
        """Palindromic weights over a symmetric base."""
        w = self.weights
        return mirrored(w, w[::-1], tol) and self.base.symmetric(tol)

    def residuals(self) -> Residuals:
        """The base's, consistent when the weights also sum to 1."""
        base = self.base.residuals()
        cons = max(base.consistency, abs(float(self.weights.sum()) - 1.0))
        mag = max(base.magnitude, float(np.abs(self.weights).max()))
        return base._replace(consistency=cons, row_sums=None, magnitude=mag)

    def coefficients(self) -> dict[str, Any]:
        return {"base": self.base.name, "weights": self.weights.tolist()}

    @property
    def reach(self) -> float:
        flat = self.flattened()
        return float(np.abs(flat.weights).sum()) * flat.base.reach

    @property
    def sample_work(self) -> float:
        """The base's, once per substep."""
        flat = self.flattened()
        return float(flat.weights.size) * flat.base.sample_work

def step_end_stage(prk: PartitionedRK) -> int | None:
    """The stage whose position ends at the step's ``q_{n+1}`` (its ``A_q`` row is ``b_q``,
    as Lobatto IIIA's last), else None: a force there is the next step's first force when
    that stage is fixed at ``q`` (first same as last). Decided on the coefficients as
    written where a method file gives them (their exact values equal within what their
    digits allow: :attr:`PartitionedRK.written`), else on the floats exactly (the
    families build Lobatto IIIA's last row as ``b`` itself)."""
    decided = getattr(getattr(prk, "written", None), "step_end_stage", False)
    if decided is not False:
        return decided
    rows = [i for i in range(prk.stages) if np.array_equal(prk.A_q[i], prk.b_q)]
    return rows[-1] if rows else None


def merge_operations(ops: list[tuple[str, float]]) -> list[tuple[str, float]]:
    """``ops`` with adjacent drifts added and each run of kicks and gradients between two
    drifts (all functions of the same q, so they commute) merged into one ``kick`` then one
    ``gradient``; zero coefficients dropped before merging."""
    out: list[tuple[str, float]] = []
    group: dict[str, float] = {}

    def close() -> None:
        for kind in ("kick", "gradient"):
            if kind in group:
                out.append((kind, group[kind]))
        group.clear()

    for kind, coef in ops:
        if kind == "drift":
            close()
            if out and out[-1][0] == "drift":
                out[-1] = ("drift", out[-1][1] + coef)
            elif coef != 0.0:
                out.append(("drift", coef))
        elif coef != 0.0:
            group[kind] = group.get(kind, 0.0) + coef
    close()
    return out


def splitting_from_operations(ops: list[tuple[str, float]], **fields: Any) -> Splitting:
    """The splitting ``drift a_1, kick b_1, drift a_2, ...`` doing the ``("drift"|"kick"|
    "gradient", coefficient)`` operations in order, adjacent operations merged as in
    :func:`merge_operations` (``fields``: name, order, ... of :class:`Splitting`)."""
    drift: list[float] = []
    kick: list[float] = []
    gradient: list[float] = []
    previous = "drift"
    for kind, coef in merge_operations(ops):
        if kind == "drift":
            drift.append(coef)
        elif kind == "gradient" and previous == "kick":  # the group the kick opened
            gradient[-1] = coef
        else:
            if len(drift) == len(kick):  # no drift before this group: a zero drift
                drift.append(0.0)
            kick.append(coef if kind == "kick" else 0.0)
            gradient.append(coef if kind == "gradient" else 0.0)
        previous = kind
    if any(gradient):
        fields["gradient"] = gradient
    else:
        fields.pop("displaced", None)
    return Splitting(np.array(drift or [0.0], dtype=float), np.array(kick or [0.0], dtype=float),
                     **fields)


def linear_blocks(method: MethodKind, model: str | None = None) -> tuple[Block, ...]:
    """The one description the linear step maps are built from: the blocks of
    ``method.decomposition(model)``, a step made of splittings only as one merged splitting
    (the operations of each scaled by its weight, ``w^3`` for a force-gradient term,
    adjacent ones merged: :meth:`~stepsafe.methods.tableaux.Composition.as_splitting`), any
    other step as it is."""
    blocks = method.decomposition(model)
    if len(blocks) == 1 and blocks[0].weight == 1.0 or \
            not all(isinstance(b, Shears) for b in blocks):
        return blocks
    shears = [b for b in blocks if isinstance(b, Shears)]
    ops = [(kind, (b.weight ** 3 if kind == "gradient" else b.weight) * coef)
           for b in shears for kind, coef in b.splitting.operations]
    return (Shears(splitting_from_operations(
        ops, name=method.name, order=method.order, evaluations=method.evaluations,
        title=method.title, exact=method.exact, displaced=shears[0].splitting.displaced)),)


#: Default cost of one force-gradient term (a Hessian-vector product ``V''(q) v``) in force
#: evaluations. Reverse-mode automatic differentiation gives ``V''(q) v`` as the gradient
#: of ``V'(q) . v`` at a small constant multiple of the cost of ``V'`` (Griewank &
#: Walther, Evaluating Derivatives, 2nd ed., Sec. 5.4), and lattice-QCD force-gradient
#: codes form it from one extra force at a displaced position (the displaced-force form,
#: whose cost is exactly one force and is counted among the forces); so 1 by default,
#: changeable where costs are compared (``--gradient-cost``).
GRADIENT_COST = 1.0


def validate_gradient_cost(value: float) -> float:
    """``value`` if it is a finite number >= 0 (not a text), else a :class:`MethodError`."""
    if isinstance(value, str):
        raise MethodError(f"the gradient cost must be a number, got the text {value[:40]!r}")
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise MethodError(f"the gradient cost must be a number, got {str(value)[:40]}") from None
    if isinstance(value, bool) or not np.isfinite(number) or number < 0:
        raise MethodError(f"the gradient cost must be a finite number >= 0, got {value!r}")
    return number


#: Inner steps per outer drift an impulse method may take.
MAX_SUBSTEPS = 1000


def splitting_operations(method: Any, role: str) -> list[tuple[str, float]]:
    """The drift/kick operations of a splitting method or of a composition of one;
    a :class:`~stepsafe.exceptions.MethodError` naming ``role`` for any other method."""
    step = method.splitting() if isinstance(method, MethodKind) and \
        method.processor_operations is None else None
    if step is None:
        kind = getattr(method, "kind", type(method).__name__)
        raise MethodError(f"the {role} method of an impulse (r-RESPA) integrator must be a "
                          f"splitting (drift/kick) method; {getattr(method, 'name', '?')} is "
                          f"a {kind} method")
    if step.force_gradient:
        raise MethodError(f"the {role} method of an impulse (r-RESPA) integrator must be a "
                          f"drift/kick splitting; {step.name} is a force-gradient method")
    return step.operations


@dataclass(frozen=True, eq=False)
class Impulse(MethodKind):
    """Impulse / r-RESPA multiple time stepping for ``H = T(p) + V_fast(q) + V_slow(q)``.

    One outer step H applies the ``outer`` splitting with its kicks by the slow force only;
    each of its drifts ``drift(a H)`` becomes ``substeps`` steps of the ``inner`` splitting
    of size ``a H / substeps`` over ``T + V_fast`` (Tuckerman, Berne & Martyna, J. Chem.
    Phys. 97 (1992) 1990). Outer and inner Verlet make r-RESPA / Verlet-I:
    ``K_slow(H/2) [K_fast(h/2) D(h) K_fast(h/2)]^k K_slow(H/2)``, ``h = H/k``.
    """

    outer: Any
    inner: Any
    substeps: int
    name: str = "impulse"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    exact: Exact | None = field(default=None, compare=False, repr=False)

    kind = "impulse"

    def __post_init__(self) -> None:
        splitting_operations(self.outer, "outer")
        splitting_operations(self.inner, "inner")
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, (int, np.integer)) \
                or not 1 <= self.substeps <= MAX_SUBSTEPS:
            raise MethodError(f"substeps must be an integer from 1 to {MAX_SUBSTEPS}, got "
                              f"{self.substeps!r}")
        object.__setattr__(self, "substeps", int(self.substeps))

    def with_substeps(self, substeps: int | None) -> Impulse:
        """The same method with another substep count (None: unchanged)."""
        if substeps is None or substeps == self.substeps:
            return self
        return Impulse(self.outer, self.inner, substeps, name=self.name, order=self.order,
                       title=self.title)

    @property
    def operations(self) -> list[tuple[str, float, bool]]:
        """One outer step (H = 1) as ``(kind, coefficient, fast)``: ``fast`` tells a kick by
        the fast force from one by the slow force (drifts have ``fast`` True)."""
        inner_ops = splitting_operations(self.inner, "inner")
        ops: list[tuple[str, float, bool]] = []
        for kind, coef in splitting_operations(self.outer, "outer"):
            if kind == "kick":
                ops.append(("kick", coef, False))
                continue
            for _ in range(self.substeps):
                ops += [(k, c * coef / self.substeps, True) for k, c in inner_ops]
        return ops

    @property
    def stages(self) -> int:
        """Kicks in one outer step, fast and slow (before first-same-as-last merging)."""
        return sum(1 for kind, _, _ in self.operations if kind == "kick")

    @property
    def force_evaluations(self) -> tuple[int, int]:
        """``(fast, slow)`` force evaluations per outer step as run: a kick that follows
        another kick of the same force with no drift between (the end of one step and the
        start of the next included) reuses its force."""
        ops = self.operations
        counts = {True: 0, False: 0}
        for i, (kind, _, fast) in enumerate(ops):
            if kind != "kick":
                continue
            j = i - 1
            while ops[j % len(ops)][0] == "kick" and (j % len(ops)) != i:
                if ops[j % len(ops)][2] == fast:
                    break
                j -= 1
            else:
                counts[fast] += 1
        return counts[True], counts[False]

    @property
    def explicit(self) -> bool:
        return True

    def symmetric(self, tol: float = 1e-12) -> bool:
        """Symmetric outer and inner splittings (each outer drift is then K steps of a
        symmetric map)."""
        return self.outer.symmetric(tol) and self.inner.symmetric(tol)

    def residuals(self) -> Residuals:
        """Every force's kicks and the drifts sum to 1 iff both splittings' do."""
        outer, inner = self.outer.residuals(), self.inner.residuals()
        return Residuals(0.0, 0.0, max(outer.consistency, inner.consistency), None,
                         max(outer.magnitude, inner.magnitude))

    @property
    def partitioned(self) -> bool:
        return False

    def coefficients(self) -> dict[str, Any]:
        fast, slow = self.force_evaluations
        return {"outer": self.outer.name, "inner": self.inner.name,
                "substeps": self.substeps,
                "force_evaluations_per_outer_step": {"fast": fast, "slow": slow}}

    def _two_forces(self) -> MethodError:
        return MethodError(f"{self.name} is an impulse (multiple time stepping) method: its "
                           "step needs a fast and a slow force (stepsafe.core.impulse turns it "
                           "into a splitting at a frequency ratio)")

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        raise self._two_forces()

@dataclass(frozen=True, eq=False)
class Processed(MethodKind):
    """Processed method ``psi_h = P_h^-1 o K_h o P_h``: a kernel K and a processor P.

    The kernel is a splitting method (or a composition of one) and the processor a
    drift/kick sequence ``drift(c_1 h), kick(d_1 h), ...`` whose sums need not be 1 (it
    is a near-identity change of variables, not a step). Over n steps
    ``psi^n = P^-1 K^n P``: P runs once at the start, K every step, and P^-1 only when an
    output is wanted (on a copy, the run continues from ``K^n P x``). The processor's cost
    is therefore one-off: :attr:`processor_evaluations` forces for P and as many for
    P^-1, apart from the kernel's ``evaluations`` per step.

    Linear analysis (why the kernel alone decides the region). On a test model every map
    is a 2x2 matrix and ``M_psi(z) = P(z)^-1 M_K(z) P(z)`` with ``det P = 1`` (drifts
    and kicks are shears), so ``M_psi`` is similar to ``M_K``: same trace, same
    eigenvalues, and ``M_psi^n = P^-1 M_K^n P`` is bounded exactly when ``M_K^n`` is.
    The structure boundaries (``tr M = +-2``), poles and resonances are functions of the
    trace, and the orientation of an elliptic matrix (the sense of rotation, the sign of
    ``M_qp``'s side of the invariant ellipse) is unchanged by conjugation with a matrix
    of determinant +1. Hence :meth:`region_method` hands the region finder the kernel.
    What the processor changes are the invariant ellipse (``M_psi``'s energy error, and
    the HMC energy error ``E_1``) and, on nonlinear problems, the error constants:
    a kernel of *effective* order r with a suitable P gives a method of order r.
    """

    kernel: MethodKind
    processor: Splitting
    name: str = "processed"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    exact: Exact | None = field(default=None, compare=False, repr=False)

    kind = "processed"

    def __post_init__(self) -> None:
        kernel = self.kernel.splitting() if isinstance(self.kernel, MethodKind) and \
            self.kernel.processor_operations is None else None
        if kernel is None:
            kind = getattr(self.kernel, "kind", type(self.kernel).__name__)
            raise MethodError(f"{self.name}: the kernel of a processed method must be a "
                              f"splitting (drift/kick) method or a composition of one; "
                              f"{getattr(self.kernel, 'name', '?')} is a {kind} method")
        if not isinstance(self.processor, Splitting):
            raise MethodError(f"{self.name}: the processor must be a drift/kick sequence")
        if self.processor.force_gradient:
            raise MethodError(f"{self.name}: the processor must be a plain drift/kick "
                              f"sequence; {self.processor.name} has force-gradient terms")
        if not self.processor.operations:
            raise MethodError(f"{self.name}: the processor has no nonzero coefficient (it "
                              "would be the identity: give the kernel alone)")

    @property
    def kernel_splitting(self) -> Splitting:
        """The kernel as one splitting (a composition multiplied out)."""
        step = self.kernel.splitting()
        assert step is not None  # (checked when built)
        return step

    @property
    def processor_operations(self) -> list[tuple[str, float]]:
        """P as ``("drift"|"kick", coefficient)`` in the order applied."""
        return self.processor.operations

    @property
    def inverse_operations(self) -> list[tuple[str, float]]:
        """P^-1: P's operations in reverse order with negated coefficients (a drift or
        kick of ``-c h`` undoes one of ``c h`` exactly)."""
        return [(kind, -coef) for kind, coef in reversed(self.processor.operations)]

    @property
    def processor_evaluations(self) -> int:
        """Force evaluations of P (P^-1 costs as many): its kicks."""
        return sum(1 for kind, _ in self.processor.operations if kind == "kick")

    def per_step(self) -> Splitting:
        """The full one-step map ``P^-1 K P`` as one splitting (P's operations, the
        kernel's, then P^-1's, adjacent ones merged). Its drift and kick sums are the
        kernel's (P and P^-1 cancel), so it has a PRK form whenever the kernel has."""
        ops = (self.processor_operations + self.kernel_splitting.operations
               + self.inverse_operations)
        return splitting_from_operations(ops, name=self.name, order=self.order,
                                         title=self.title)

    @property
    def stages(self) -> int:
        """The kernel's stages (the processor is not part of a step)."""
        return self.kernel_splitting.stages

    @property
    def explicit(self) -> bool:
        return True

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        """The full one-step map ``P^-1 K P`` as one splitting; on the diagonal (saddle)
        models, where every factor is diagonal and P commutes with K, the kernel's."""
        if model in DIAGONAL_MODELS:
            return (Shears(self.kernel_splitting),)
        return (Shears(self.per_step()),)

    def step_decomposition(self) -> tuple[Block, ...]:
        """The kernel's blocks (P runs once at the start, ``P^-1`` at each output)."""
        return self.kernel.step_decomposition()

    def splitting(self) -> Splitting:
        """The kernel, run every step."""
        return self.kernel_splitting

    @property
    def force_gradient(self) -> bool:
        return self.kernel.force_gradient

    @property
    def forces_per_step(self) -> int | None:
        return self.kernel.forces_per_step

    @property
    def gradient_evaluations(self) -> int:
        return self.kernel.gradient_evaluations

    def one_step(self) -> Splitting:
        return self.per_step()

    def symmetric(self, tol: float = 1e-12) -> bool:
        """Its one-step map ``P^-1 K P``, operation by operation."""
        return self.per_step().symmetric(tol)

    def residuals(self) -> Residuals:
        """``P^-1 K P``: the kernel's sums, symplectic as it is."""
        return self.per_step().residuals()

    def coefficients(self) -> dict[str, Any]:
        kernel = self.kernel_splitting
        return {"kernel": {"drift": kernel.drift.tolist(), "kick": kernel.kick.tolist()},
                "processor": {"drift": self.processor.drift.tolist(),
                              "kick": self.processor.kick.tolist()}}

    def region_method(self, model: str = "oscillator") -> Splitting:
        """The kernel, except on the ``inverted`` model. On the oscillator the kernel's
        region is the processed method's (same trace, same sense of rotation, see the class
        docstring); on the diagonal models (``saddle``, ``saddle-p``) every drift and kick
        is a diagonal matrix (a symplectic Euler factor), so P commutes with K and
        ``P^-1 K P = K`` exactly. On the ``inverted`` model the orientation indicator
        compares M's eigenvectors with the flow's and conjugation by P moves them, so the
        full one-step map ``P^-1 K P`` is analysed (the trace, and with it every boundary of
        the type, is still the kernel's). The substitute carries the processed method's
        high-precision ``exact`` (the full map, of the same trace) when it has none of its
        own."""
        target = self.per_step() if model == "inverted" else self.kernel_splitting
        if target.exact is None and self.exact is not None:
            target = replace(target, exact=self.exact)
        return target

