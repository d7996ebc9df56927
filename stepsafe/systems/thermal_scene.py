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
        x = np.asarray(item["x"], dtype=float) if many else \
            np.array([item["q"], item["p"]], dtype=float)
        if item.get("type") == "degenerate" and np.all(x[n:] == 0) and \
                _degenerate_minimum(system, x[:n]):
            label = ", ".join(f"{a} = {v:.6g}" for a, v in zip(names, x[:n]))
            raise StepsafeError(f"U has a degenerate minimum at {label} (a direction without "
                                "curvature along which U still rises): the analysis at "
                                "temperature samples about minima with curvature in every "
                                "direction and cannot judge that well, where the thermal "
                                "frequencies come from the amplitude alone; no step is "
                                "called safe at temperature for this system (a box that "
                                "leaves that minimum out analyses the others)", key)
        if item.get("type") != "elliptic":
            continue
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


#: Differing probes, nearest first, that must all fall below ``U(q0)`` for a side to fall
#: (:func:`_degenerate_minimum`): rounding noise in U, of either sign, leaves the point
#: a possible minimum (refused, the safe side).
FALLING = 8


def _degenerate_minimum(system: Any, q0: np.ndarray) -> bool:
    """Whether the degenerate equilibrium ``(q0, 0)`` may be a minimum of ``U = H(q, 0)``:
    no direction of negative curvature, and along each direction without curvature (the
    Hessian's eigenvalues within ``1e-8`` of its largest; each coordinate axis without a
    Hessian) U does not fall on either side. A side falls when U at ``q0 + s v`` is below
    ``U(q0)`` at each of the :data:`FALLING` smallest of the distances ``s = 2^k`` (every
    binary scale float64 has, so no unit is assumed) at which U differs from ``U(q0)``:
    the leading behaviour of U along v decides. A point where U falls along such a
    direction is a saddle or an inflection, not a well."""
    n = q0.size
    zero_p = np.zeros((1, n))
    with np.errstate(all="ignore"):
        u0 = float(system.energy(q0[None, :], zero_p)[0])
        directions = np.eye(n)
        if system.hessian is not None:
            K = np.asarray(system.hessian(q0[None, :], zero_p)[0], dtype=float).reshape(n, n)
            if np.all(np.isfinite(K)):
                lam, vecs = np.linalg.eigh(0.5 * (K + K.T))
                top = float(np.max(np.abs(lam))) if lam.size else 0.0
                if np.any(lam < -1e-8 * top):
                    return False
                directions = vecs[:, np.abs(lam) <= 1e-8 * top].T
        scales = np.exp2(np.arange(-1074, 1024, dtype=float))
        for v in directions:
            for side in (1.0, -1.0):
                points = q0[None, :] + (side * scales)[:, None] * v[None, :]
                d = np.asarray(system.energy(points, np.zeros_like(points)), dtype=float) - u0
                differing = d[np.isfinite(d) & (d != 0)][:FALLING]
                if differing.size and np.all(differing < 0):
                    return False
    return True
