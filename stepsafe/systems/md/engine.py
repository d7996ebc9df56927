"""The interface to an MD engine: what the analysis needs from it, and nothing else.

An engine (OpenMM today; ASE or LAMMPS's Python module could implement the same) exposes a
system of N particles through :class:`ForceEngine`:

* ``masses`` (N,) in amu; a particle of mass 0 never moves (a virtual site, whose position the
  engine computes from its parents, or a particle the engine holds fixed). The degrees of
  freedom are the 3 Cartesian coordinates of every particle of positive mass
  (:func:`mobile_particles`).
* ``positions`` (N, 3) in nm: the configuration to analyse.
* ``constraints``: holonomic distance constraints ``|x_i - x_j| = d``
  (:class:`DistanceConstraints`). An angle constraint i-j-k is a distance constraint between
  i and k (as OpenMM builds it, with d from the law of cosines on the two bond lengths and the
  angle), so distances are all there is.
* ``virtual_sites`` (N,) bool: particles whose position is a function of others (mass 0).
* ``forces(x)`` (N, 3) in kJ/mol/nm and ``energy(x)`` in kJ/mol at positions ``x`` (N, 3) nm.
  The engine places the virtual sites from their parents first; the force on a parent already
  contains its share of the force on its virtual sites (the chain rule), and the entries of
  the virtual sites themselves are ignored.

Units (:data:`UNITS`) are OpenMM's: nm, amu, ps, kJ/mol, K. They are consistent,
1 kJ/mol = 1 amu nm^2 / ps^2 (up to the 3.5e-10 relative difference between the molar mass
constant and 1 g/mol, which OpenMM, like every MD engine, ignores), so a force over a mass is
an acceleration in nm/ps^2 with no conversion factor.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from stepsafe.exceptions import StepsafeError

#: The units of every quantity an engine exchanges (OpenMM's internal units).
UNITS = {"length": "nm", "mass": "amu", "time": "ps", "energy": "kJ/mol",
         "force": "kJ/mol/nm", "temperature": "K"}

#: Boltzmann's constant times Avogadro's number in kJ/mol/K (exact in the SI since 2019:
#: k_B = 1.380649e-23 J/K, N_A = 6.02214076e23 /mol).
MOLAR_GAS_CONSTANT = 1.380649e-23 * 6.02214076e23 / 1000.0

#: What to install for each engine (the package extra).
EXTRAS = {"openmm": "pip install 'stepsafe[openmm]'"}


def engine_missing(engine: str, where: str | None = None) -> StepsafeError:
    """The error raised when an engine's Python package is not installed: it names the extra
    that installs it.

    Parameters
    ----------
    engine : str
        The engine's name, a key of :data:`EXTRAS` (``"openmm"``).
    where : str, optional
        The file and key the user named the engine in.

    Returns
    -------
    StepsafeError
        To be raised by the caller (exit code 2 through the CLI).
    """
    return StepsafeError(f"{engine} is not installed; install it with {EXTRAS[engine]}", where)


@dataclass(frozen=True)
class DistanceConstraints:
    """Holonomic constraints ``g_k(x) = |x_i - x_j| - d_k = 0``, one per row.

    Attributes
    ----------
    pairs : ndarray of int, shape (K, 2)
        Particle indices ``(i, j)``, ``i != j``.
    distances : ndarray of float, shape (K,)
        The constrained distances ``d_k`` in nm.
    """

    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    distances: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        pairs = np.asarray(self.pairs, dtype=np.int64).reshape(-1, 2)
        distances = np.asarray(self.distances, dtype=float).reshape(-1)
        if len(pairs) != len(distances):
            raise StepsafeError(f"{len(pairs)} constrained pairs but {len(distances)} distances")
        if len(pairs) and (np.any(pairs < 0) or np.any(pairs[:, 0] == pairs[:, 1])):
            raise StepsafeError("a constraint joins a particle to itself or names a negative index")
        if len(distances) and not np.all(np.isfinite(distances) & (distances > 0)):
            raise StepsafeError("constrained distances must be positive and finite")
        pairs.setflags(write=False)
        distances.setflags(write=False)
        object.__setattr__(self, "pairs", pairs)
        object.__setattr__(self, "distances", distances)

    def __len__(self) -> int:
        return len(self.distances)

    def check_indices(self, n_particles: int) -> None:
        """A :class:`StepsafeError` if a pair names a particle beyond ``n_particles``, or the
        same pair appears twice."""
        if len(self) and int(self.pairs.max()) >= n_particles:
            raise StepsafeError(f"a constraint names particle {int(self.pairs.max())} of a "
                                f"system of {n_particles}")
        keys = np.sort(self.pairs, axis=1)
        if len(np.unique(keys, axis=0)) != len(keys):
            raise StepsafeError("the same pair of particles is constrained twice")

    def residuals(self, positions: np.ndarray) -> np.ndarray:
        """``|x_i - x_j| - d_k`` in nm at ``positions`` (N, 3), one per constraint."""
        r = positions[self.pairs[:, 0]] - positions[self.pairs[:, 1]]
        return np.linalg.norm(r, axis=1) - self.distances


@dataclass(frozen=True)
class Topology:
    """Chemistry the engine's system does not carry but its structure file does: what hydrogen
    mass repartitioning and the ``constraints:`` rules need.

    Attributes
    ----------
    elements : tuple of (str or None)
        Element symbol per particle (``"H"``, ``"C"``, ...); None for a virtual site or an
        unknown element.
    bonds : ndarray of int, shape (B, 2)
        Chemical bonds (pairs of particle indices).
    residues : tuple of str
        Residue name per particle (``"HOH"`` is water, as in OpenMM).
    residue_ids : ndarray of int, shape (N,)
        Which residue each particle belongs to (particles of one residue share the number).
    """

    elements: tuple[str | None, ...]
    bonds: np.ndarray
    residues: tuple[str, ...]
    residue_ids: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.elements)
        bonds = np.asarray(self.bonds, dtype=np.int64).reshape(-1, 2)
        ids = np.asarray(self.residue_ids, dtype=np.int64).reshape(-1)
        if len(self.residues) != n or len(ids) != n:
            raise StepsafeError(f"a topology of {n} particles needs {n} residue names and ids")
        if len(bonds) and (bonds.min() < 0 or bonds.max() >= n
                           or np.any(bonds[:, 0] == bonds[:, 1])):
            raise StepsafeError("a bond names a particle outside the topology or itself")
        bonds.setflags(write=False)
        ids.setflags(write=False)
        object.__setattr__(self, "bonds", bonds)
        object.__setattr__(self, "residue_ids", ids)
        object.__setattr__(self, "elements", tuple(self.elements))
        object.__setattr__(self, "residues", tuple(self.residues))

    def __len__(self) -> int:
        return len(self.elements)


@runtime_checkable
class ForceEngine(Protocol):
    """A system of particles an MD engine evaluates (units: :data:`UNITS`)."""

    @property
    def n_particles(self) -> int:
        """N, the number of particles (virtual sites included)."""
        ...

    @property
    def masses(self) -> np.ndarray:
        """(N,) masses in amu; 0 for virtual sites and for particles held fixed."""
        ...

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) positions in nm: the configuration to analyse."""
        ...

    @property
    def constraints(self) -> DistanceConstraints:
        """The system's distance constraints (angle constraints included as distances)."""
        ...

    @property
    def virtual_sites(self) -> np.ndarray:
        """(N,) bool: True where the particle is a virtual site."""
        ...

    @property
    def labels(self) -> tuple[str, ...]:
        """N names for reports (``"ALA2:CB"``; empty strings when the engine has none)."""
        ...

    def forces(self, positions: np.ndarray) -> np.ndarray:
        """(N, 3) forces ``-dU/dx`` in kJ/mol/nm at ``positions`` (N, 3) nm."""
        ...

    def energy(self, positions: np.ndarray) -> float:
        """The potential energy U in kJ/mol at ``positions`` (N, 3) nm."""
        ...


@runtime_checkable
class DynamicsEngine(ForceEngine, Protocol):
    """A :class:`ForceEngine` that also runs its own integrators: what the analysis at
    temperature needs (:mod:`~stepsafe.systems.md.thermal`). Specifications and records are
    those of :mod:`~stepsafe.systems.md.enginerun`."""

    def degrees_of_freedom(self) -> int:
        """n_dof: 3 per particle of positive mass, less one per constraint and those a
        centre-of-mass motion remover takes (what the equipartition of the runs counts)."""
        ...

    def on_constraints(self, positions: np.ndarray) -> np.ndarray:
        """(N, 3) positions put on the constraints to the engine's tightest tolerance (and
        virtual sites placed): where a Hessian can be taken."""
        ...

    def thermal_frames(self, spec: Any) -> np.ndarray:
        """Configurations ``(seeds, frames, N, 3)`` nm of the engine's own Langevin dynamics
        at temperature (a ``SamplingSpec``), from :attr:`positions`."""
        ...

    def trials(self, spec: Any, progress: Any = None, worker: Any = None) -> Any:
        """Runs of the engine's integrator from thermal states (a ``TrialSpec``; returns a
        ``TrialRecord``), in ``worker`` (from :meth:`trial_worker`) when given."""
        ...

    def trial_worker(self) -> Any:
        """A context manager holding what many :meth:`trials` share (an engine process)."""
        ...


def mobile_particles(masses: np.ndarray) -> np.ndarray:
    """Indices of the particles that move: positive mass (virtual sites and particles held
    fixed have mass 0).

    Parameters
    ----------
    masses : ndarray, shape (N,)
        Masses in amu.

    Returns
    -------
    ndarray of int
        Sorted indices; the degrees of freedom are their 3 coordinates each, in the order
        ``(x_0, y_0, z_0, x_1, ...)``.
    """
    masses = np.asarray(masses, dtype=float)
    if not np.all(np.isfinite(masses)) or np.any(masses < 0):
        raise StepsafeError("particle masses must be finite and not negative")
    return np.flatnonzero(masses > 0)


def as_positions(positions: object, n_particles: int, name: str = "positions") -> np.ndarray:
    """``positions`` as a finite float array of shape (N, 3), else a :class:`StepsafeError`."""
    try:
        x = np.array(positions, dtype=float)
    except (TypeError, ValueError):
        raise StepsafeError(f"{name} must be an array of numbers") from None
    if x.shape != (n_particles, 3):
        raise StepsafeError(f"{name} must have shape ({n_particles}, 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise StepsafeError(f"{name} must be finite")
    return x
