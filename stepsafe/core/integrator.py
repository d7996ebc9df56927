"""Run a method on a Hamiltonian system: one engine driven by the method's data.

A :class:`System` gives the gradients of ``H(q, p)`` on arrays of shape ``(m, d)``: m
initial conditions of d degrees of freedom advance together. One step of size h:

* splitting methods (and compositions of them) on ``H = T(p) + V(q)``: ``drift(a h)``
  is ``q += a h dH/dp``, ``kick(b h)`` is ``p -= b h dH/dq``, in the file's order (on an H
  that mixes q and p they run as their PRK form of symplectic Euler factors, implicit, as
  the analysis treats them). A kick
  at a position the previous kick already saw reuses that force (first same as last), so
  the evaluations counted are those of the method as run in practice;
* Runge-Kutta and partitioned RK methods (and compositions of them) solve their stage
  equations ``Q_i = q + h sum_j A_q[i, j] dH/dp(Q_j, P_j)``,
  ``P_i = p - h sum_j A_p[i, j] dH/dq(Q_j, P_j)`` by fixed-point iteration from ``Q = q``,
  ``P = p`` in Gauss-Seidel order (the positions from the current momenta, the forces at
  the new positions, the momenta from those forces) until the largest change of a stage
  value is at most ``tol`` times the largest stage value (and 1), as
  :mod:`stepsafe.core.solver` models it; a stage whose ``A_q`` row is zero keeps
  ``Q_i = q`` and its force is evaluated once (none if the previous step's last stage
  ended there). Each iteration evaluates the forces of the stages that vary; the update
  uses the last iteration's (on an H that mixes q and p, it evaluates them once more at
  the converged stages). With ``solver="newton"`` each pass is a simplified Newton step
  ``X - J^-1 G(X)`` on the map of every stage from the previous pass instead, J the stage
  system's Jacobian from the Hessian at the step's start (one per step and implicit
  substep, counted in ``jacobians``), and the update evaluates the forces once more.

Force-gradient splittings (:class:`~stepsafe.methods.tableaux.Splitting` with ``gradient``)
need a separable H with ``T = p^T M^-1 p / 2``: a gradient term ``("gradient", c)`` is
``p += c h^3 grad |F|^2_{M^-1} = p - 2 c h^3 V''(q) M^-1 F`` with ``F = -dH/dq`` (one
Hessian evaluation, counted in ``gradient_evaluations``; ``M^-1 F = dH/dp(q, F)``); in the
displaced-force form a kick ``b`` with its gradient ``c`` is instead ``p += b h F(q')`` at
``q' = q + (2 c h^2 / b) M^-1 F(q)`` (two forces, no Hessian).

Force evaluations (``dH/dq``) and solver iterations are counted; a step whose iteration
does not converge in ``max_iterations`` marks the run as failed.

Processed methods ``P^-1 K P`` (:class:`~stepsafe.methods.tableaux.Processed`): the engine's
:meth:`Engine.step` is the kernel K; :meth:`Engine.start` applies the processor P once to
the initial state and :meth:`Engine.output` returns ``P^-1`` of the current state (on a
copy: the run continues from the kernel's variables). ``start`` counts its forces among
``force_evaluations``; ``output`` counts them in ``output_evaluations`` (the one-off cost
of each output), apart from the per-step work. For other methods both are the identity.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from stepsafe.exceptions import MethodError
from stepsafe.methods.protocol import Shears, Stages
from stepsafe.methods.tableaux import (
    Method,
    PartitionedRK,
    splitting_from_operations,
    step_end_stage,
)

Gradient = Callable[[np.ndarray, np.ndarray], np.ndarray]

#: One operation of a splitting as run: ``("drift" | "kick" | "gradient", c)``, or
#: ``("displaced", (b, c))`` for a kick with its gradient term in the displaced-force form.
Operation = tuple[str, Any]


class _Operations(NamedTuple):
    """A splitting's operations, run at ``weight`` times the step."""

    weight: float
    operations: tuple[Operation, ...]


class _Stages(NamedTuple):
    """A (partitioned) Runge-Kutta step, run at ``weight`` times the step."""

    weight: float
    prk: PartitionedRK


@dataclass(frozen=True)
class System:
    """``H(q, p)`` through its gradients, on arrays of shape ``(m, d)``; ``separable``
    when ``dH/dq`` depends on q only and ``dH/dp`` on p only."""

    dH_dq: Gradient
    dH_dp: Gradient
    energy: Callable[[np.ndarray, np.ndarray], np.ndarray]
    separable: bool
    dimension: int
    #: ``(dq/dt, dp/dt)`` in one evaluation, when cheaper than the two gradients
    vector_field: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    #: ``(H_qq, H_qp, H_pp)``, each of shape ``(m, d, d)`` (Newton's method needs it)
    hessian: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, ...]] | None = None

    def rates(self, q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(dH/dp, -dH/dq)``."""
        if self.vector_field is not None:
            return self.vector_field(q, p)
        return self.dH_dp(q, p), -self.dH_dq(q, p)


class SolverFailure(ArithmeticError):
    """The stage equations' fixed-point iteration did not converge."""


class Engine:
    """Steps of one method on one system, with the work counted."""

    def __init__(self, method: Method, system: System, tol: float = 1e-14,
                 max_iterations: int = 200, solver: str = "fixed-point") -> None:
        if solver not in ("fixed-point", "newton"):
            raise ValueError(f"solver must be fixed-point or newton, got {solver!r}")
        if solver == "newton" and system.hessian is None:
            raise ValueError("Newton's method needs the system's Hessian")
        self.system = system
        self.solver = solver
        self.tol, self.max_iterations = tol, max_iterations
        self.force_evaluations = 0
        self.iterations = 0
        self.solves = 0
        self.jacobians = 0
        self.output_evaluations = 0
        self.output_calls = 0
        self.gradient_evaluations = 0
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._processor: tuple[tuple, tuple] | None = None
        start, inverse = method.processor_operations, method.inverse_operations
        if start is not None and inverse is not None:
            if not system.separable:
                raise ValueError("a processed method's processor is a drift/kick sequence "
                                 "whose sums are not 1: it has no form for an H that mixes "
                                 "q and p")
            self._processor = (tuple(start), tuple(inverse))
        self.pieces = _pieces(method)
        operations = [op for piece in self.pieces if isinstance(piece, _Operations)
                      for op in piece.operations]
        gradient = any(op[0] in ("gradient", "displaced") for op in operations)
        if gradient and not system.separable:
            raise ValueError("a force-gradient method needs a separable H = p^T M^-1 p / 2 + "
                             "V(q); this H mixes q and p")
        if gradient and system.hessian is None and any(op[0] == "gradient" for op in operations):
            raise ValueError("a force-gradient method needs the system's Hessian")
        if not system.separable:  # a splitting on H(q, p) runs as its PRK form (implicit)
            try:
                self.pieces = [_Stages(piece.weight, _as_prk(piece.operations))
                               if isinstance(piece, _Operations) else piece
                               for piece in self.pieces]
            except MethodError:
                raise ValueError("this splitting method's drift and kick sums differ: it has "
                                 "no form for an H that mixes q and p") from None

    def _force(self, q: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``dH/dq`` at (q, p), reused when the same arrays were just evaluated."""
        c = self._cache
        if c is not None and c[0] is q and (self.system.separable or c[1] is p):
            return c[2]
        g = self.system.dH_dq(q, p)
        self.force_evaluations += 1
        self._cache = (q, p, g)
        return g

    def know_force(self, q: np.ndarray, p: np.ndarray, force: np.ndarray) -> None:
        """Take ``force`` as ``dH/dq`` at these very arrays (q, p), not counted: the next
        kick there reuses it."""
        self._cache = (q, p, force)

    def take(self, rows: np.ndarray, q: np.ndarray, p: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """The rows ``rows`` (a mask or indices) of the state (q, p), the force last taken
        at (q, p) going with them (so a run that drops trajectories reuses it)."""
        c = self._cache
        q1, p1 = q[rows], p[rows]
        if c is not None and c[0] is q and (self.system.separable or c[1] is p):
            self._cache = (q1, p1, c[2][rows])
        else:
            self._cache = None
        return q1, p1

    def start(self, q: np.ndarray, p: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """The processor P applied to the initial state (the identity for other methods);
        its forces count in ``force_evaluations``."""
        if self._processor is None:
            return q, p
        return self._ops(self._processor[0], q, p, h)

    def output(self, q: np.ndarray, p: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """``P^-1`` of the state (the identity for other methods), counted in
        ``output_evaluations``; the kernel's reused force is left as it was."""
        if self._processor is None:
            return q, p
        self.output_calls += 1
        for op, coef in self._processor[1]:
            if op == "drift":
                q = q + (coef * h) * self.system.dH_dp(q, p)
            else:
                p = p - (coef * h) * self.system.dH_dq(q, p)
                self.output_evaluations += 1
        return q, p

    def _ops(self, ops: tuple, q: np.ndarray, p: np.ndarray, h: float
             ) -> tuple[np.ndarray, np.ndarray]:
        for op, coef in ops:
            if op == "drift":
                q = q + (coef * h) * self.system.dH_dp(q, p)
            else:
                p = p - (coef * h) * self._force(q, p)
        return q, p

    def step(self, q: np.ndarray, p: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        for piece in self.pieces:
            weight = piece.weight
            if isinstance(piece, _Operations):
                for op, coef in piece.operations:
                    if op == "drift":
                        q = q + (coef * weight * h) * self.system.dH_dp(q, p)
                    elif op == "kick":
                        p = p - (coef * weight * h) * self._force(q, p)
                    elif op == "gradient":
                        p = p + (coef * (weight * h) ** 3) * self._force_gradient(q, p)
                    else:  # displaced: coef = (b, c)
                        b, c = coef
                        t = weight * h
                        F = -self._force(q, p)
                        shifted = q + (2.0 * c * t * t / b) * self.system.dH_dp(q, F)
                        self.force_evaluations += 1
                        p = p - (b * t) * self.system.dH_dq(shifted, p)
            else:
                q, p = self._prk_step(piece.prk, q, p, weight * h)
        return q, p

    def _force_gradient(self, q: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``grad |F|^2_{M^-1} = 2 V''(q) M^-1 V'(q)`` (rows: initial conditions)."""
        g = self._force(q, p)
        hessian = self.system.hessian
        assert hessian is not None  # (a force-gradient method's engine has one)
        H_qq = hessian(q, p)[0]
        self.gradient_evaluations += 1
        return 2.0 * np.einsum("mij,mj->mi", H_qq, self.system.dH_dp(q, g))

    def _prk_step(self, prk: PartitionedRK, q: np.ndarray, p: np.ndarray, h: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        A_q, A_p, b_q, b_p = prk.A_q, prk.A_p, prk.b_q, prk.b_p
        s = b_q.size
        # stages with Q_i = q for good: their force is that at q (and the step's p) only
        # when dH/dq does not depend on p
        fixed = np.asarray(~A_q.any(axis=1) & self.system.separable)
        Q = [q] * s
        P = [p] * s
        sys = self.system
        F: list[np.ndarray] = [np.zeros_like(q)] * s
        implicit = bool(np.triu(A_q).any() or np.triu(A_p).any())
        if not implicit:  # explicit: one sweep in stage order
            for i in range(s):
                Q[i] = q + h * sum(A_q[i, j] * sys.dH_dp(Q[j], P[j]) for j in range(i))
                P[i] = p - h * sum(A_p[i, j] * F[j] for j in range(i))
                F[i] = self._force(Q[i], P[i])
            V = [sys.dH_dp(Q[j], P[j]) for j in range(s)]
            return (q + h * sum(b_q[j] * V[j] for j in range(s)),
                    p - h * sum(b_p[j] * F[j] for j in range(s)))
        self.solves += 1
        if self.solver == "newton":
            Q, P, F = self._newton_solve(prk, q, p, h, fixed)
        else:
            Q, P, F = self._gauss_seidel_solve(prk, q, p, h, fixed)
        V = [sys.dH_dp(Q[j], P[j]) for j in range(s)]
        q1 = q + h * sum(b_q[j] * V[j] for j in range(s) if b_q[j])
        p1 = p - h * sum(b_p[j] * F[j] for j in range(s) if b_p[j])
        end = step_end_stage(prk)
        if end is not None and self.system.separable:
            self._cache = (q1, p1, F[end])  # that stage ended at q1 (Lobatto IIIA's last)
        return q1, p1

    def _converged(self, old: list, new: list) -> bool:
        """Whether the largest change of a stage value is at most ``tol`` times the largest
        stage value (and 1); a SolverFailure when it is not finite."""
        self.iterations += 1
        change = max(float(np.max(np.abs(a - b))) for a, b in zip(new, old))
        if not np.isfinite(change):
            raise SolverFailure("the stage iteration overflowed")
        size = max(1.0, max(float(np.max(np.abs(x))) for x in new))
        return change <= self.tol * size

    def _gauss_seidel_solve(self, prk: PartitionedRK, q: np.ndarray, p: np.ndarray,
                            h: float, fixed: np.ndarray) -> tuple[list, list, list]:
        """The stages by fixed-point iteration in Gauss-Seidel order: positions from the
        current momenta, the forces at the new positions, the momenta from those forces;
        returns ``(Q, P, F)`` with F the forces at the converged stages (the last sweep's
        when the force depends on q only, evaluated again otherwise)."""
        A_q, A_p = prk.A_q, prk.A_p
        s = A_q.shape[0]
        sys = self.system
        Q, P = [q] * s, [p] * s
        for _ in range(self.max_iterations):
            V = [sys.dH_dp(Q[j], P[j]) for j in range(s)]
            Qn = [q if fixed[i] else q + h * sum(A_q[i, j] * V[j] for j in range(s)
                                                 if A_q[i, j])
                  for i in range(s)]
            F = [self._force(q, p) if fixed[j] else self._stage_force(Qn[j], P[j])
                 for j in range(s)]
            Pn = [p - h * sum(A_p[i, j] * F[j] for j in range(s) if A_p[i, j])
                  for i in range(s)]
            done = self._converged(Q + P, Qn + Pn)
            Q, P = Qn, Pn
            if done:
                break
        else:
            raise SolverFailure(f"the stage iteration did not converge in "
                                f"{self.max_iterations} iterations")
        if not sys.separable:  # the forces moved with the momenta of the last sweep
            F = [self._stage_force(Q[j], P[j]) for j in range(s)]
        return Q, P, F

    def _newton_solve(self, prk: PartitionedRK, q: np.ndarray, p: np.ndarray, h: float,
                      fixed: np.ndarray) -> tuple[list, list, list]:
        """The stages by simplified Newton's method on ``G(X) = X - Phi(X)`` (``Phi`` the
        map of every stage from the previous iterate), the Jacobian at the step's start;
        returns ``(Q, P, F)`` with F the forces at the converged stages."""
        A_q, A_p = prk.A_q, prk.A_p
        s = A_q.shape[0]
        sys = self.system
        inverse = self._newton_matrix(prk, q, p, h)
        Q, P = [q] * s, [p] * s
        for _ in range(self.max_iterations):
            F = [self._force(q, p) if fixed[j] else self._stage_force(Q[j], P[j])
                 for j in range(s)]
            V = [sys.dH_dp(Q[j], P[j]) for j in range(s)]
            Qn = [q if fixed[i] else q + h * sum(A_q[i, j] * V[j] for j in range(s)
                                                 if A_q[i, j])
                  for i in range(s)]
            Pn = [p - h * sum(A_p[i, j] * F[j] for j in range(s) if A_p[i, j])
                  for i in range(s)]
            Qn, Pn = self._newton_update(inverse, Q, P, Qn, Pn)
            done = self._converged(Q + P, Qn + Pn)
            Q, P = Qn, Pn
            if done:
                break
        else:
            raise SolverFailure(f"the stage iteration did not converge in "
                                f"{self.max_iterations} iterations")
        F = [self._force(q, p) if fixed[j] else self._stage_force(Q[j], P[j])
             for j in range(s)]
        return Q, P, F

    def _newton_matrix(self, prk: PartitionedRK, q: np.ndarray, p: np.ndarray, h: float
                       ) -> np.ndarray:
        """``J^-1`` of the stage system at the step's start, one per initial condition:
        ``J = I - h [[A_q x H_pq, A_q x H_pp], [-A_p x H_qq, -A_p x H_qp]]`` on the
        unknowns ``(Q_1..Q_s, P_1..P_s)`` (simplified Newton: taken once per step)."""
        hessian = self.system.hessian
        assert hessian is not None  # (Newton's method's engine has one)
        H_qq, H_qp, H_pp = hessian(q, p)
        self.jacobians += 1
        H_pq = np.swapaxes(H_qp, 1, 2)
        A_q, A_p = prk.A_q, prk.A_p
        m, d = q.shape
        s = A_q.shape[0]
        kron = np.einsum  # (s, s) x (m, d, d) -> (m, s d, s d)

        def block(A: np.ndarray, B: np.ndarray) -> np.ndarray:
            return kron("ij,mab->miajb", A, B).reshape(m, s * d, s * d)

        top = np.concatenate([block(A_q, H_pq), block(A_q, H_pp)], axis=2)
        bottom = np.concatenate([-block(A_p, H_qq), -block(A_p, H_qp)], axis=2)
        J = np.eye(2 * s * d)[None] - h * np.concatenate([top, bottom], axis=1)
        try:
            return np.linalg.inv(J)
        except np.linalg.LinAlgError:
            raise SolverFailure("the stage system's Jacobian is singular") from None

    @staticmethod
    def _newton_update(inverse: np.ndarray, Q: list, P: list, Qf: list, Pf: list
                       ) -> tuple[list, list]:
        """One simplified Newton step from the fixed-point map's image ``(Qf, Pf)``:
        ``X - J^-1 (X - Phi(X))``."""
        s = len(Q)
        X = np.concatenate([np.stack(Q, 1), np.stack(P, 1)], axis=1)  # (m, 2s, d)
        G = X - np.concatenate([np.stack(Qf, 1), np.stack(Pf, 1)], axis=1)
        m, _, d = X.shape
        step = np.einsum("mij,mj->mi", inverse, G.reshape(m, -1)).reshape(m, 2 * s, d)
        Xn = X - step
        return [Xn[:, i] for i in range(s)], [Xn[:, s + i] for i in range(s)]

    def _stage_force(self, Q: np.ndarray, P: np.ndarray) -> np.ndarray:
        self.force_evaluations += 1
        return self.system.dH_dq(Q, P)


def _as_prk(operations: tuple) -> PartitionedRK:
    """The PRK form of a splitting given by its operations (symplectic Euler factors: on a
    non-separable H each drift and kick is an implicit half of a symplectic Euler step)."""
    return splitting_from_operations(list(operations)).as_prk()


def _pieces(method: Method) -> list[_Operations | _Stages]:
    """The step as run (:meth:`~stepsafe.methods.protocol.MethodKind.step_decomposition`)
    as weighted splitting operations and (partitioned) Runge-Kutta steps, in the order
    applied."""
    try:
        blocks = method.step_decomposition()
    except MethodError:
        blocks = ()
    pieces: list[_Operations | _Stages] = []
    for block in blocks:
        if isinstance(block, Shears):
            ops: list = list(block.splitting.operations)
            if block.splitting.displaced:  # each kick with its gradient: one displaced force
                merged: list[tuple[str, object]] = []
                for op, coef in ops:
                    if op == "gradient":
                        merged[-1] = ("displaced", (merged[-1][1], coef))
                    else:
                        merged.append((op, coef))
                ops = merged
            pieces.append(_Operations(block.weight, tuple(ops)))
        elif isinstance(block, Stages):
            prk = block.method.rk_form()
            assert prk is not None
            pieces.append(_Stages(block.weight, prk))
        else:
            raise ValueError(f"{method.name}: a Langevin friction step draws random numbers "
                             "at a temperature; this engine runs deterministic methods")
    if not pieces:
        raise ValueError(f"{getattr(method, 'name', method)!r} cannot be integrated here "
                         f"({getattr(method, 'kind', type(method).__name__)})")
    return pieces
