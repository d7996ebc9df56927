"""stepsafe's methods and advice in BlackJAX (optional: ``pip install 'stepsafe[blackjax]'``).

The only module that imports jax and blackjax, lazily, inside the functions that need them.

Integrators. BlackJAX's ``blackjax.mcmc.integrators.generate_euclidean_integrator(c)``
takes a palindromic list ``c`` of alternating momentum and position coefficients that
starts (and ends) with a momentum one: even indices are kicks ``p += c_i h grad log pi(q)``,
odd indices drifts ``q += c_i h M^-1 p``. stepsafe's splitting applies
``drift(a_1 h) kick(b_1 h) ...`` with ``kick(t): p -= t grad U``, ``U = -log pi``: the same
maps, so a method's merged drift/kick sequence (:attr:`Splitting.operations`; a
composition of a splitting multiplied out) is the list itself when it starts with a kick,
and gets a zero kick at each end when it starts with a drift (position Verlet, McLachlan's
position form). BlackJAX evaluates one gradient per drift; the zero kicks make such a method
cost one gradient more per step there than in stepsafe's count (first same as last), which
:class:`Export` states. Processed methods (their proposal is ``P^-1 K^L P``, not the L-th
power of one step), force-gradient splittings and Runge-Kutta methods have no such list and
are refused, as are non-symmetric splittings (HMC needs a reversible integrator).

Jittered steps. ``blackjax.hmc`` takes the step as a runtime argument of its kernel, so a
jittered sampler draws ``h (1 + J u)``, u uniform on (-1, 1), in each iteration and calls
the kernel with it (:func:`sample`); no recompilation.

Precision. The target's log-density is evaluated under ``jax.enable_x64(True)`` when
stepsafe analyses it (energy errors of 1e-3 on a log-density of 1e3 need float64); a
BlackJAX run in float32 has energy errors rounded at about ``1e-7 |log pi|``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from stepsafe.core.design import family_member
from stepsafe.core.hmc import Trajectory
from stepsafe.core.hmc_target.advice import TargetReport, hmc_on_target
from stepsafe.core.hmc_target.draws import SEED, given_draws
from stepsafe.core.hmc_target.potential import (
    CallablePotential,
    Guarded,
    Target,
    mass_matrix,
)
from stepsafe.core.hmc_target.trajectories import scheme
from stepsafe.exceptions import StepsafeError, finite_real
from stepsafe.methods.families import is_symmetric
from stepsafe.methods.library import resolve
from stepsafe.methods.tableaux import Composition, Method, Processed, Splitting

#: The optional extra that installs jax and blackjax.
EXTRA = "stepsafe[blackjax]"
#: Methods compared by :func:`blackjax_hmc` when none is named (those BlackJAX ships, in
#: stepsafe's names, and the BCSS ones).
DEFAULT_METHODS = ("verlet", "mclachlan2-min-velocity", "bcss2", "bcss3")


def _require() -> tuple[Any, Any]:
    """``(jax, blackjax)``, or a :class:`StepsafeError` naming the extra to install."""
    try:
        import blackjax
        import jax
    except ImportError as exc:
        raise StepsafeError(f"BlackJAX is not installed ({exc.name} is missing): "
                            f"pip install '{EXTRA}'") from None
    return jax, blackjax


def _tableau(method: Any) -> Method:
    """A method object from a name, an integrator (with ``tableau``), a tableau, or the
    report of ``stepsafe.design`` (its designed member, every digit)."""
    if hasattr(method, "method_file") and hasattr(method, "params"):  # a DesignReport
        return family_member(int(method.stages), tuple(float(v) for v in
                                                       method.params.values()), method.name)
    if isinstance(method, str):
        name, _, stages = method.strip().partition(":")
        return resolve(name, int(stages) if stages.isdigit() else None)[0]
    return getattr(method, "tableau", method)


@dataclass(frozen=True)
class Export:
    """A method as BlackJAX's coefficient list (module docstring): ``coefficients`` (kick
    first, alternating, palindromic), the gradient evaluations per step BlackJAX spends
    (one per drift) and stepsafe's own count."""

    name: str
    coefficients: tuple[float, ...]
    blackjax_gradients_per_step: int
    gradients_per_step: int


def coefficients(method: Any) -> Export:
    """The BlackJAX coefficient list of a symmetric splitting (module docstring).

    Parameters
    ----------
    method
        A method name (``"bcss2"``) or method file, a :class:`stepsafe.api.Integrator`, a
        splitting or composition of one (library or designed), or the report of
        :func:`stepsafe.design` (its designed member).

    Returns
    -------
    Export
    """
    m = _tableau(method)
    name = getattr(m, "name", "method")
    if isinstance(m, Processed):
        raise StepsafeError(f"{name} is a processed method: its proposal P^-1 K^L P is not L "
                            "steps of one integrator, so it has no BlackJAX coefficient list")
    if isinstance(m, Composition) and isinstance(m.flattened().base, Splitting):
        m = m.as_splitting()
    if not isinstance(m, Splitting):
        raise StepsafeError(f"{name} is not a splitting (drift/kick) method: BlackJAX's "
                            "integrators are drift/kick sequences")
    if m.force_gradient:
        raise StepsafeError(f"{name} has force-gradient kicks, which BlackJAX's euclidean "
                            "integrators do not have")
    if not is_symmetric(m):
        raise StepsafeError(f"{name} is not symmetric: HMC needs a reversible integrator "
                            "(BlackJAX's lists are palindromes)")
    ops = [(kind, float(c)) for kind, c in m.operations]
    own = scheme(m).gradients_per_step or 0
    if ops[0][0] == "drift":
        ops = [("kick", 0.0)] + ops
    if ops[-1][0] == "drift":
        ops = ops + [("kick", 0.0)]
    drifts = sum(1 for kind, _ in ops if kind == "drift")
    return Export(name, tuple(c for _, c in ops), drifts, own)


def integrator(method: Any) -> Callable:
    """BlackJAX's integrator factory for ``method``
    (``generate_euclidean_integrator(coefficients(method).coefficients)``), to pass as
    ``blackjax.hmc(..., integrator=...)``."""
    _, blackjax = _require()
    from blackjax.mcmc.integrators import generate_euclidean_integrator

    return generate_euclidean_integrator(list(coefficients(method).coefficients))


def jax_potential(logdensity: Callable, dimension: int) -> CallablePotential:
    """The potential ``U = -log pi`` of a JAX log-density of one position (shape (d,)),
    with its gradient (``jax.grad``), Hessian (``jax.hessian``) and Hessian-vector product
    (forward over reverse), each vmapped over a batch, jitted, evaluated in float64 and
    returned as numpy arrays batched over leading axes.

    Parameters
    ----------
    logdensity
        ``log pi(q)`` for q of shape (d,), written with ``jax.numpy``.
    dimension
        d.

    Returns
    -------
    CallablePotential
    """
    jax, _ = _require()
    import jax.numpy as jnp

    d = int(dimension)
    try:
        with jax.enable_x64(True):
            shape = jax.eval_shape(logdensity, jax.ShapeDtypeStruct((d,), jnp.float64)).shape
    except Exception as exc:  # the user's code: reported, not a crash
        raise StepsafeError(f"logdensity raised {type(exc).__name__} when traced by JAX at a "
                            f"position of shape ({d},): {str(exc).splitlines()[0][:120]}",
                            "logdensity") from None
    if tuple(shape) != ():
        raise StepsafeError(f"logdensity must return a scalar (log pi at one position of shape "
                            f"({d},)), it returned shape {tuple(shape)}", "logdensity")
    grad = jax.grad(logdensity)
    energy = jax.jit(jax.vmap(lambda q: -logdensity(q)))
    gradient = jax.jit(jax.vmap(lambda q: -grad(q)))
    hessian = jax.jit(jax.vmap(lambda q: -jax.hessian(logdensity)(q)))
    hvp = jax.jit(jax.vmap(lambda q, v: -jax.jvp(grad, (q,), (v,))[1]))

    def batched(fn: Callable, tail: tuple[int, ...]) -> Callable:
        # batches padded to a power of two: a jitted function compiles once per shape, and
        # the batches stepsafe passes (live trajectories, chains still moving) vary in size
        def call(*arrays: np.ndarray) -> np.ndarray:
            lead = np.shape(arrays[0])[:-1]
            flat = [np.asarray(a, dtype=np.float64).reshape(-1, d) for a in arrays]
            n = flat[0].shape[0]
            if n == 0:
                return np.zeros(lead + tail)
            size = max(8, 1 << (n - 1).bit_length())
            padded = [np.concatenate([a, np.repeat(a[:1], size - n, axis=0)]) for a in flat]
            with jax.enable_x64(True):
                out = np.asarray(fn(*[jnp.asarray(a) for a in padded]), dtype=float)
            return out[:n].reshape(lead + tail)
        return call

    return CallablePotential(batched(energy, ()), batched(gradient, (d,)), d,
                             hessian=batched(hessian, (d, d)), hvp=batched(hvp, (d,)))


@dataclass(frozen=True)
class Settings:
    """What stepsafe recommends for ``blackjax.hmc``: pass ``integrator``, ``step_size``,
    ``num_integration_steps`` and ``inverse_mass_matrix`` as they are; ``jitter`` is the
    relative jitter of the step the estimate assumed (0: none; :func:`sample` applies it);
    ``report`` holds every figure behind the choice (estimated acceptance with its
    standard error, divergences, Laplace figures, the other methods); ``verified`` is
    False when the draws it was estimated on fail the convergence diagnostics (the reason
    in ``report.unverified``): the step is then not a recommendation."""

    integrator: Callable
    step_size: float
    num_integration_steps: int
    inverse_mass_matrix: np.ndarray
    method: str
    coefficients: tuple[float, ...]
    jitter: float
    acceptance: float
    acceptance_se: float
    report: TargetReport

    @property
    def verified(self) -> bool:
        """Whether the draws behind the estimate pass R-hat and the effective sample size
        (:attr:`stepsafe.core.hmc_target.advice.TargetReport.verified`)."""
        return self.report.verified


def blackjax_hmc(logdensity: Callable, initial_position: Any, *,
                 method: Any | Sequence[Any] | None = None, target_accept: float = 0.8,
                 trajectory_steps: int = 10, jitter: float = 0.0,
                 inverse_mass_matrix: Any | None = None, draws: Any | None = None,
                 seed: int = SEED, require_converged: bool = False) -> Settings:
    """The integrator, step size and number of steps stepsafe recommends for BlackJAX's HMC
    on a JAX log-density: the step reaching ``target_accept`` at ``trajectory_steps`` steps
    per trajectory, estimated on the target itself (:mod:`stepsafe.core.hmc_target`), with
    ``h (1 + jitter)`` within the stability limit of the stiffest region the draws visit.

    Parameters
    ----------
    logdensity
        ``log pi(q)``, q of shape (d,), in ``jax.numpy``.
    initial_position
        A position of shape (d,) inside the target's support: the mode search starts there.
    method
        A method (name, integrator or splitting) or several (the best ranked is chosen:
        fewest gradient evaluations per accepted proposal at ``trajectory_steps``); default
        :data:`DEFAULT_METHODS`.
    target_accept
        The acceptance to reach.
    trajectory_steps
        L, the number of integration steps per trajectory (BlackJAX's
        ``num_integration_steps``).
    jitter
        Relative jitter J of the step (each iteration draws ``h (1 + J u)``).
    inverse_mass_matrix
        As BlackJAX takes it: a vector (diagonal) or a matrix; default ones.
    draws
        Draws from the target to estimate on, shape (n, d) or (chains, n, d) (default: a
        short adaptive run of stepsafe's own).
    seed
        Seed of stepsafe's draws and common random numbers.
    require_converged
        Refuse draws that fail R-hat or the effective sample size
        (:class:`~stepsafe.exceptions.NotConverged`, naming the diagnostic) before any
        estimate; without it such draws give settings with ``verified`` False.

    Returns
    -------
    Settings
    """
    _require()
    q0 = np.asarray(initial_position, dtype=float).ravel()
    d = q0.size
    if not 0.0 <= finite_real(jitter, "jitter") < 1.0:
        raise StepsafeError(f"jitter must be a number in [0, 1), got {jitter!r}", "jitter")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or \
            not 0 <= seed < 2**63:
        raise StepsafeError(f"seed must be an integer from 0 to 2^63 - 1, got {seed!r}",
                            "seed")
    if inverse_mass_matrix is None:
        inverse = np.ones(d)
    else:
        inverse = np.asarray(inverse_mass_matrix, dtype=float)
    inv_mass = mass_matrix(inverse, d, "inverse_mass_matrix")  # validates shape and SPD
    mass = 1.0 / inv_mass.matrix if inv_mass.diagonal else np.linalg.inv(inv_mass.matrix)
    target = Target(Guarded(jax_potential(logdensity, d), ("logdensity", "logdensity")),
                    mass_matrix(mass, d, "inverse_mass_matrix"))
    names = (DEFAULT_METHODS if method is None else
             [method] if isinstance(method, (str, Splitting, Composition)) or hasattr(
                 method, "tableau") else list(method))
    tableaux = [_tableau(m) for m in names]
    for m in tableaux:
        coefficients(m)  # refuse what BlackJAX cannot run before any work
    given = None if draws is None else given_draws(draws, d)
    steps = trajectory_steps
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or \
            not 1 <= steps <= 10**6:
        raise StepsafeError(f"trajectory_steps must be an integer from 1 to 1000000, got "
                            f"{steps!r}")
    report = hmc_on_target(target, tableaux, Trajectory(steps=int(steps), jitter=jitter),
                           target_accept=target_accept, draws=given, seed=seed, start=q0,
                           onset=False, require_converged=bool(require_converged))
    best = next((r for r in report.rows if r.rank == 1), None)
    if best is None or best.h_target is None or best.estimate is None:
        raise StepsafeError(f"no method reaches acceptance {target_accept:g} at {steps} "
                            "steps on this target within its stability limit")
    chosen = tableaux[[getattr(m, "name", "") for m in tableaux].index(best.method)]
    export = coefficients(chosen)
    return Settings(integrator(chosen), best.h_target, int(best.estimate.steps), inverse,
                    best.method, export.coefficients, float(jitter), best.estimate.acceptance,
                    best.estimate.acceptance_se, report)


@dataclass(frozen=True)
class Run:
    """A BlackJAX chain (or several): positions (chains, n, d) and each iteration's
    acceptance statistic ``min(1, e^-Delta)`` and divergence flag, as numpy arrays."""

    positions: np.ndarray
    acceptance: np.ndarray
    divergent: np.ndarray


def sample(settings: Settings, logdensity: Callable, initial_positions: Any,
           num_samples: int, seed: int = 0, x64: bool = True) -> Run:
    """Run ``blackjax.hmc``'s kernel with ``settings`` from each initial position (shape
    (chains, d)), drawing the step ``h (1 + J u)`` afresh in every iteration when the
    settings carry a jitter J (module docstring), chains vectorised by ``jax.vmap``.

    Parameters
    ----------
    settings
        From :func:`blackjax_hmc` (or built by hand).
    logdensity
        The JAX log-density.
    initial_positions
        Shape (chains, d).
    num_samples
        Iterations per chain.
    seed
        Seed of ``jax.random.key``.
    x64
        Run in float64 (``jax.enable_x64``).

    Returns
    -------
    Run
    """
    jax, blackjax = _require()
    import jax.numpy as jnp

    kernel = blackjax.hmc.build_kernel(integrator=settings.integrator)
    h, J, L = settings.step_size, settings.jitter, settings.num_integration_steps

    with jax.enable_x64(bool(x64)):
        inverse = jnp.asarray(settings.inverse_mass_matrix)
        start = jnp.asarray(np.asarray(initial_positions, dtype=float))

        def one_chain(position: Any, key: Any) -> tuple[Any, Any, Any]:
            state = blackjax.hmc.init(position, logdensity)

            def body(state: Any, key: Any) -> tuple[Any, tuple[Any, Any, Any]]:
                k_step, k_kernel = jax.random.split(key)
                eps = h * (1.0 + J * jax.random.uniform(k_step, minval=-1.0, maxval=1.0))
                state, info = kernel(k_kernel, state, logdensity, eps, inverse, L)
                return state, (state.position, info.acceptance_rate, info.is_divergent)

            _, out = jax.lax.scan(body, state, jax.random.split(key, num_samples))
            return out

        keys = jax.random.split(jax.random.key(seed), start.shape[0])
        positions, acc, div = jax.jit(jax.vmap(one_chain))(start, keys)
        return Run(np.asarray(positions), np.asarray(acc), np.asarray(div))
