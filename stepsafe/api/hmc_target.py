"""HMC on a target that is not Gaussian: what :func:`stepsafe.api.hmc.hmc` does when the
target is a log-density (``logdensity=`` in Python) or a potential (a scene's
``system: {potential:}``, :mod:`stepsafe.systems.potential`).

Such a target is never analysed as a Gaussian: the acceptance, its Monte Carlo standard
error, the divergence rate and the mean energy error are estimated on draws from the target
with each method's own trajectories (:mod:`stepsafe.core.hmc_target`), and the Gaussian
figures at the mode (Laplace) are stated beside them as ``laplace_*``. Draws come from a
short adaptive warm-up run of stepsafe's own (seeded, the seed stated) or from the user
(``draws=``, ``--draws FILE``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.api.inputs import Integrator
from stepsafe.core.hmc import Trajectory
from stepsafe.core.hmc_target.advice import TargetReport, hmc_on_target
from stepsafe.core.hmc_target.draws import SEED, Draws, given_draws
from stepsafe.core.hmc_target.potential import CallablePotential, Guarded, Target, mass_matrix
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.blackjax_bridge import jax_potential
from stepsafe.systems.potential import PotentialTarget, is_potential, potential_target, read_draws
from stepsafe.systems.scene import Scene, load_scene


def callable_target(logdensity: Callable[[np.ndarray], Any],
                    gradient: Callable[[np.ndarray], Any] | None, start: Any,
                    mass: Any = None) -> PotentialTarget:
    """The target of a Python log-density.

    Parameters
    ----------
    logdensity
        ``log pi(q)`` (up to a constant): with ``gradient``, a numpy function batched over
        leading axes (``(..., d) -> (...)``); without, a JAX function of one position
        (``(d,) -> ()``), differentiated by JAX (needs ``stepsafe[blackjax]`` or jax).
    gradient
        ``grad log pi(q)``, ``(..., d) -> (..., d)``, or None (JAX).
    start
        A position of shape (d,) inside the target's support: sets d, and the mode search
        starts there.
    mass
        The mass matrix M of the kinetic energy ``p^T M^-1 p / 2``: None (unit), a number,
        d masses or a d x d SPD matrix.

    Returns
    -------
    PotentialTarget
    """
    if not callable(logdensity):
        raise StepsafeError(f"logdensity must be a function of the position, got "
                            f"{type(logdensity).__name__}", "logdensity")
    if gradient is not None and not callable(gradient):
        raise StepsafeError(f"gradient must be a function of the position, got "
                            f"{type(gradient).__name__}", "gradient")
    if start is None:
        raise StepsafeError("a log-density needs start=, a position of shape (d,) inside its "
                            "support (it sets d; the mode search starts there)", "start")
    try:
        q0 = np.array(start, dtype=float)
    except (TypeError, ValueError):
        raise StepsafeError("start must be a vector of numbers", "start") from None
    if q0.ndim != 1 or not 1 <= q0.size <= 10**6 or not np.isfinite(q0).all():
        raise StepsafeError(f"start must be a finite vector of shape (d,), got shape "
                            f"{q0.shape}", "start")
    d = int(q0.size)
    if gradient is None:
        try:
            import jax  # noqa: F401
        except ImportError:
            raise StepsafeError("give gradient= (grad log pi, a numpy function batched over "
                                "leading axes), or install jax to differentiate a JAX "
                                "log-density: pip install 'stepsafe[blackjax]'",
                                "gradient") from None
        inner = jax_potential(logdensity, d)
        names = ("logdensity", "logdensity")
    else:
        inner = CallablePotential(lambda q: -np.asarray(logdensity(q), dtype=float),
                                  lambda q: -np.asarray(gradient(q), dtype=float), d)
        names = ("logdensity", "gradient")
    potential = Guarded(inner, names)
    with np.errstate(all="ignore"):
        u0 = potential.energy(q0[None, :])
        g0 = potential.gradient(q0[None, :])
    if not (np.isfinite(u0).all() and np.isfinite(g0).all()):
        raise StepsafeError("the log-density or its gradient is not finite at start: start "
                            "inside the target's support", "start")
    return PotentialTarget(Target(potential, mass_matrix(mass, d, "mass")), q0,
                           tuple(f"q{i}" for i in range(d)), "")


def target_of(logdensity: Any, gradient: Any, start: Any, mass: Any, scene: Any,
              system: Any) -> PotentialTarget | None:
    """The non-Gaussian target given to ``hmc``, or None when the target is Gaussian (given
    by frequencies, a covariance, a precision, or a scene with such a ``system:``)."""
    if logdensity is not None:
        if scene is not None or system is not None:
            raise StepsafeError("give the target once: logdensity= or a scene/system, not "
                                "both", "logdensity")
        return callable_target(logdensity, gradient, start, mass)
    for key, value in (("gradient", gradient), ("start", start), ("mass", mass)):
        if value is not None and not is_potential(system) and not _scene_has_potential(scene):
            raise StepsafeError(f"{key}= goes with logdensity= (a Gaussian target takes its "
                                "mass in system=)", key)
    if is_potential(system):
        if scene is not None:
            raise StepsafeError("give the target once: system= or a scene, not both",
                                "system")
        tree = dict(system)
        for key, value in (("start", start), ("mass", mass)):
            if value is not None:
                if key in tree:
                    raise StepsafeError(f"{key} is given twice (in system= and as {key}=)",
                                        key)
                tree[key] = value
        return potential_target(tree)
    if scene is None:
        return None
    loaded = _scene(scene)
    if loaded is None or not is_potential(loaded.system):
        return None
    found = potential_target(loaded.system, loaded.where)
    if start is not None or mass is not None:
        raise StepsafeError("the scene gives the target: write start: and mass: in its "
                            "system:", "start" if start is not None else "mass")
    return found


def _scene(scene: Any) -> Any:
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, (str, Path)):
        return load_scene(scene)
    return None


def _scene_has_potential(scene: Any) -> bool:
    loaded = _scene(scene) if scene is not None else None
    return loaded is not None and is_potential(loaded.system)


def draws_of(draws: Any, found: PotentialTarget) -> Draws | None:
    """Draws given as an array ((n, d) or (chains, n, d)) or a file
    (:func:`stepsafe.systems.potential.read_draws`); None: stepsafe's own."""
    if draws is None:
        return None
    if isinstance(draws, (str, Path)):
        return read_draws(draws, found.names)
    return given_draws(draws, found.target.dimension, "draws")


def on_target(found: PotentialTarget, integrators: Sequence[Integrator], *,
              steps: int | None, length: float | None, jitter: float, target_accept: float,
              step: float | None, draws: Any, seed: Any, allow_unstable_jitter: bool,
              zmax: float | None, require_converged: bool = False) -> TargetReport:
    """HMC with each method on the target (module docstring; the arguments as
    :func:`stepsafe.api.hmc.hmc` takes them, already checked).

    Returns
    -------
    TargetReport
        ``to_dict()`` is ``stepsafe hmc --json`` for such a target.
    """
    if steps is None and length is None:
        raise StepsafeError("HMC on a non-Gaussian target needs the number of steps per "
                            "trajectory or the trajectory length (trajectory_steps= or "
                            "length=; --steps L or --length T on the command line): its "
                            "acceptance is estimated for that trajectory", "trajectory_steps")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or \
            not 0 <= seed < 2**63:
        raise StepsafeError(f"seed must be an integer from 0 to 2^63 - 1, got {seed!r}",
                            "seed")
    given = draws_of(draws, found)
    methods = []
    for integrator in integrators:
        with integrator.naming_its_file():
            methods.append(integrator.tableau)
    return hmc_on_target(found.target, methods, Trajectory(steps, length, jitter),
                         target_accept=target_accept, step=step, draws=given,
                         seed=int(seed), start=found.start,
                         allow_unstable_jitter=allow_unstable_jitter,
                         zmax=10.0 if zmax is None else float(zmax),
                         where=found.where or None, require_converged=require_converged,
                         check_gradient=_given_gradient(found.target))


def _given_gradient(target: Target) -> str | None:
    """The keyword of a numpy gradient the user gave beside the log-density (checked
    against it), or None (a scene's exact gradient, JAX's)."""
    pot = target.potential
    if isinstance(pot, Guarded) and pot.names == ("logdensity", "gradient"):
        return "gradient"
    return None


__all__ = ["SEED", "TargetReport", "callable_target", "on_target", "target_of"]
