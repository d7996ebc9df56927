"""HMC proposals on a target, many at once: the method's own trajectories and their energy
errors.

A proposal from ``(q, p)`` runs L steps of the method at step h and returns
``Delta = H(q_L, p_L) - H(q, p)``, ``H = U(q) + p^T M^-1 p / 2``. A jittered sampler
draws one step per trajectory, ``h (1 + J u)`` with u uniform on (-1, 1) and L kept (as
Stan's ``stepsize_jitter`` and :class:`stepsafe.core.hmc.Trajectory`).

Every method runs through the shared engine over trajectories,
:func:`stepsafe.core.ensemble.integrate`: splittings and compositions of them as their
drifts ``q += c h M^-1 p`` and kicks ``p -= c h grad U(q)``, the gradient reused where q
has not moved since it was taken (first same as last); processed methods ``P^-1 K^L P``
with P and P^-1 run once per trajectory; Runge–Kutta and partitioned RK methods, and
force-gradient splittings with the Hessian (the target's, or central differences).

A trajectory whose state stops being finite (or whose implicit stage iteration fails) is
frozen there (its gradient no longer asked for) and its ``Delta`` is +inf: a divergent
transition. Gradient evaluations are counted per trajectory; the gradient at the starting
point is not (a sampler has it from the previous iteration).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stepsafe.core.ensemble import integrate
from stepsafe.core.hmc_target.potential import Target, hessian_matrix
from stepsafe.core.integrator import System
from stepsafe.methods.families import is_symmetric
from stepsafe.methods.tableaux import Composition, Method, Processed, Splitting


@dataclass(frozen=True)
class Scheme:
    """A method as HMC runs it on a target, with its cost.

    ``operations`` is one step (a processed method's kernel) as ``("drift"|"kick", c)``
    pairs, None for a method that is not one drift/kick sequence; ``gradients_per_step``
    counts the kicks of a step as run with first-same-as-last (None where the run counts
    them); ``gradients_per_trajectory_extra`` is the processor's one-off cost (P and
    P^-1)."""

    name: str
    method: Method
    operations: tuple[tuple[str, float], ...] | None
    gradients_per_step: int | None = None
    gradients_per_trajectory_extra: int = 0
    symmetric: bool = True


def _kicks_per_step(ops: list[tuple[str, float]]) -> int:
    """Gradient evaluations per step of a drift/kick sequence run repeatedly: one per kick
    that follows a drift (the step's first kick reuses the previous step's last gradient
    when no drift separates them, as in kick-drift-kick Verlet)."""
    kicks = sum(1 for kind, _ in ops if kind == "kick")
    if kicks > 1 and ops and ops[0][0] == "kick" and ops[-1][0] == "kick":
        kicks -= 1
    return max(kicks, 0)


def scheme(method: Method) -> Scheme:
    """The :class:`Scheme` of a method (see the module docstring).

    Parameters
    ----------
    method
        Any method of :mod:`stepsafe.methods.tableaux`.

    Returns
    -------
    Scheme
    """
    name = getattr(method, "name", "method")
    symmetric = is_symmetric(method)
    split = None
    if isinstance(method, Splitting) and not method.force_gradient:
        split = method
    elif isinstance(method, Composition) and isinstance(method.flattened().base, Splitting):
        candidate = method.as_splitting()
        split = None if candidate.force_gradient else candidate
    if split is not None:
        ops = [(k, float(c)) for k, c in split.operations]
        return Scheme(name, method, tuple(ops), gradients_per_step=_kicks_per_step(ops),
                      symmetric=symmetric)
    if isinstance(method, Processed):
        kernel = method.kernel_splitting
        if not kernel.force_gradient:
            ops = [(k, float(c)) for k, c in kernel.operations]
            return Scheme(name, method, tuple(ops), _kicks_per_step(ops),
                          2 * method.processor_evaluations, symmetric)
    return Scheme(name, method, None, symmetric=symmetric)


@dataclass(frozen=True)
class Proposals:
    """Energy errors of a batch of proposals: ``delta`` (+inf where the trajectory stopped
    being finite) and the gradient evaluations each trajectory took."""

    delta: np.ndarray
    gradients: float


def energy_errors(target: Target, run: Scheme, q0: np.ndarray, p0: np.ndarray,
                  h: float | np.ndarray, steps: int, energy0: np.ndarray | None = None,
                  gradient0: np.ndarray | None = None,
                  scale: float | np.ndarray = 1.0) -> Proposals:
    """Run the proposals from ``(q0, p0)`` (shape (n, d)) at step ``h`` (a number, or one
    per trajectory of shape (n,)) for ``steps`` steps.

    Parameters
    ----------
    target
        The potential and mass.
    run
        The method (:func:`scheme`).
    q0, p0
        Starting positions and momenta, shape (n, d).
    h
        The step, or one step per trajectory.
    steps
        L >= 1.
    energy0, gradient0
        ``U(q0)`` and ``grad U(q0)`` if already known.
    scale
        The length scale of central differences where a Hessian is needed
        (force-gradient methods without a Hessian).

    Returns
    -------
    Proposals
    """
    q0 = np.asarray(q0, dtype=float)
    p0 = np.asarray(p0, dtype=float)
    pot = target.potential
    with np.errstate(all="ignore"):
        u0 = pot.energy(q0) if energy0 is None else energy0
        g0 = pot.gradient(q0) if gradient0 is None else gradient0
        ran = integrate(run.method, _system(target, scale), q0, p0, h, steps, energy_every=0,
                        force0=g0)
        finite = ~ran.escaped
        delta = np.full(q0.shape[0], np.inf)
        if finite.any():
            qf, pf = ran.q[finite], ran.p[finite]
            u1 = pot.energy(qf)
            delta[finite] = (u1 - u0[finite]) + (target.mass.kinetic(pf)
                                                 - target.mass.kinetic(p0[finite]))
        delta = np.where(np.isnan(delta), np.inf, delta)
    return Proposals(delta, ran.forces / max(q0.shape[0], 1))


def _system(target: Target, scale: float | np.ndarray) -> System:
    """The target's equations of motion for the engine, with the Hessian a force-gradient
    method asks for (the target's, or central differences over ``scale``)."""
    pot, mass = target.potential, target.mass

    def hessian(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        H = hessian_matrix(pot, q, scale)
        d = q.shape[1]
        zero = np.zeros_like(H)
        M_inv = (np.diag(1.0 / mass.matrix) if mass.diagonal else np.linalg.inv(mass.matrix))
        return H, zero, np.broadcast_to(M_inv, (q.shape[0], d, d))

    return System(lambda q, p: pot.gradient(q), lambda q, p: mass.velocity(p),
                  lambda q, p: target.hamiltonian(q, p), True, target.dimension,
                  hessian=hessian)
