"""The potentials a scene's system gives the analysis at temperature: one per minimum
(:mod:`stepsafe.systems.thermal` itself reads no scene).

A ``system:`` Hamiltonian ``H = p^T M^-1 p / 2 + U(q)`` (1 dof, or named or indexed
coordinates) has been searched for its equilibria (:mod:`stepsafe.systems.loader`); each
elliptic one at ``p = 0`` is a minimum of U, and the thermal ensemble of U is drawn around
it (:func:`stepsafe.systems.thermal.potential.of_system` reads the masses and checks that
the kinetic energy has that form). A linear system (stiffness and mass, precision,
covariance, Hessian) is harmonic: its frequencies do not depend on amplitude, and the
answer at any temperature is the 0 K one (:func:`is_harmonic`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.dynamics import hamiltonian_system
from stepsafe.systems.loader import read_many
from stepsafe.systems.manydof import system_of
from stepsafe.systems.nonlinear import parse_hamiltonian
from stepsafe.systems.thermal.potential import Potential, of_system

#: Minima analysed at most (each is sampled and scanned on its own).
MAX_MINIMA = 8


class Minimum(NamedTuple):
    """A minimum of the scene's potential: where it is (``q``, named), and U about it."""

    q: tuple[float, ...]
    names: tuple[str, ...]
    potential: Potential

    @property
    def label(self) -> str:
        return ", ".join(f"{n} = {v:.6g}" for n, v in zip(self.names, self.q))


def is_harmonic(tree: Any) -> bool:
    """Whether a ``system:`` is linear (a stiffness, precision, covariance or Hessian
    matrix): frequencies that do not depend on amplitude. Anything else (a Hamiltonian, an
    MD engine's force field, a Python function) is not known to be linear."""
    return isinstance(tree, Mapping) and any(
        key in tree for key in ("stiffness", "precision", "covariance", "hessian"))


def minima(tree: Mapping[str, Any], items: list[dict[str, Any]], where: str) -> list[Minimum]:
    """Every minimum of a Hamiltonian ``system:`` among the equilibria ``items`` its
    analysis found (elliptic, at p = 0), as a :class:`Minimum`; a system the analysis at
    temperature cannot use is refused naming ``$.system.hamiltonian``."""
    key = f"{where}::$.system.hamiltonian"
    many = "q" in tree or "p" in tree
    if many:
        H, _, _ = read_many(tree, where)
        system, names = system_of(H), tuple(H.q)
    else:
        params = {k: float(v) for k, v in (tree.get("parameters") or {}).items()}
        H1 = parse_hamiltonian(tree["hamiltonian"], params)
        system, names = hamiltonian_system(H1), ("q",)
    n = len(names)
    found = []
    for item in items:
        if item.get("type") != "elliptic":
            continue
        x = np.asarray(item["x"], dtype=float) if many else \
            np.array([item["q"], item["p"]], dtype=float)
        if np.any(x[n:] != 0):
            raise StepsafeError(f"the elliptic equilibrium at {x.tolist()} has p != 0: the "
                                "analysis at temperature needs H = p^T M^-1 p / 2 + U(q)",
                                key)
        found.append(x[:n])
    if not found:
        raise StepsafeError("no minimum of U in the box (no elliptic equilibrium): nothing "
                            "to sample at temperature", key)
    if len(found) > MAX_MINIMA:
        raise StepsafeError(f"{len(found)} minima in the box; the analysis at temperature "
                            f"samples each and takes at most {MAX_MINIMA} (a smaller box)",
                            key)
    out = []
    for q0 in found:
        try:
            pot = of_system(system, q0, f"minimum at {q0.tolist()}")
        except StepsafeError as exc:
            raise StepsafeError(exc.message, key) from None
        out.append(Minimum(tuple(float(v) for v in q0), names, pot))
    return out
