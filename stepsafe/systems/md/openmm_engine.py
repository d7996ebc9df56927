"""OpenMM behind :class:`~stepsafe.systems.md.engine.ForceEngine`: the only module that imports
OpenMM, and only inside its functions (``pip install 'stepsafe[openmm]'``).

Input is what OpenMM users keep: a ``System`` serialized with ``XmlSerializer`` (forces,
masses, constraints, virtual sites, default periodic box) and its coordinates, a PDB or
PDBx/mmCIF file (which also gives atom names, elements and bonds:
:class:`~stepsafe.systems.md.engine.Topology`) or a serialized ``State`` with positions (and
its periodic box, which then replaces the System's default box). With a PDB file the
System's default box is used, as ``openmm.app.Simulation`` does.

Platforms: forces for Hessians come from the ``Reference`` platform (double precision); the
``CPU`` platform computes forces in single precision (relative errors 1e-5 to 1e-2 measured
against Reference), too coarse for finite differences of forces, but fine for MD runs.
Positions that violate the constraints are projected onto them (``Context.applyConstraints``,
relative tolerance :data:`CONSTRAINT_TOLERANCE`) when the engine is built; minimisation
(:meth:`OpenMMEngine.minimize`, OpenMM's ``LocalEnergyMinimizer``) happens only when asked for.

:func:`write_example_system` builds the systems the tests and the documentation use from
files shipped inside the OpenMM wheel; :func:`trial_run` runs OpenMM's integrators for
:mod:`~stepsafe.systems.md.enginerun`, in a subprocess started by that module.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.md.constraints import ConstrainedSpace
from stepsafe.systems.md.engine import (
    MOLAR_GAS_CONSTANT,
    DistanceConstraints,
    Topology,
    as_positions,
    engine_missing,
    mobile_particles,
)
from stepsafe.systems.md.enginerun import (
    SamplingSpec,
    TrialRecord,
    TrialSpec,
    TrialWorker,
    degrees_of_freedom,
    run_trials,
)

#: Relative tolerance (a fraction of each constrained distance) to which positions are put on
#: the constraints when an engine is built.
CONSTRAINT_TOLERANCE = 1e-10
#: Platforms an engine may run on (Reference: double precision, for Hessians; CPU: MD runs).
PLATFORMS = ("Reference", "CPU")


def _openmm() -> Any:
    """The ``openmm`` module (with ``openmm.app`` and ``openmm.unit`` loaded), or the error
    that names the extra."""
    try:
        import openmm  # type: ignore[import-untyped,import-not-found,unused-ignore]
        import openmm.app  # type: ignore[import-untyped,import-not-found,unused-ignore] # noqa: F401
        import openmm.unit  # type: ignore[import-untyped,import-not-found,unused-ignore] # noqa: F401
    except ImportError:
        raise engine_missing("openmm") from None
    return openmm


def _platform(name: str, threads: int | None) -> tuple[Any, dict[str, str]]:
    mm = _openmm()
    if name not in PLATFORMS:
        raise StepsafeError(f"unknown platform {str(name)[:20]!r}; choose one of "
                            f"{', '.join(PLATFORMS)}")
    try:
        platform = mm.Platform.getPlatformByName(name)
    except Exception:
        raise StepsafeError(f"OpenMM has no {name} platform here") from None
    properties = {"Threads": str(int(threads))} if name == "CPU" and threads else {}
    return platform, properties


@dataclass(frozen=True)
class Minimization:
    """What :meth:`OpenMMEngine.minimize` did (energies in kJ/mol, forces in kJ/mol/nm).

    Attributes
    ----------
    energy_before, energy_after : float
        Potential energy before and after.
    rms_force : float
        Root mean square of the force components on the moving particles afterwards, with
        the constraint forces taken off (OpenMM stops when its RMS force falls below
        ``tolerance``).
    max_force : float
        Largest such force component afterwards.
    tolerance : float
        The requested RMS force.
    max_iterations : int
        The iteration cap (0: none).
    """

    energy_before: float
    energy_after: float
    rms_force: float
    max_force: float
    tolerance: float
    max_iterations: int


class OpenMMEngine:
    """An OpenMM ``System`` at a configuration, evaluated on one platform.

    Parameters
    ----------
    system : openmm.System
        The system (it is copied: later changes to it do not reach the engine).
    positions : array_like, shape (N, 3)
        Positions in nm.
    platform : {"Reference", "CPU"}
        ``Reference`` (double precision) for Hessians.
    threads : int, optional
        CPU threads (CPU platform only).
    box : array_like, shape (3, 3), optional
        Periodic box vectors in nm (rows); the System's default box when omitted.
    topology : Topology, optional
        Elements, bonds and residues from the structure file.
    labels : sequence of str, optional
        Particle names for reports.
    """

    def __init__(self, system: Any, positions: Any, *, platform: str = "Reference",
                 threads: int | None = None, box: Any = None, topology: Topology | None = None,
                 labels: Any = None) -> None:
        mm = _openmm()
        self.system = mm.XmlSerializer.clone(system)
        n = self.system.getNumParticles()
        x = as_positions(positions, n)
        self.platform_name = platform
        self.threads = threads
        self.topology = topology
        self._labels = tuple(labels) if labels is not None else ("",) * n
        if len(self._labels) != n:
            raise StepsafeError(f"{len(self._labels)} labels for {n} particles")
        dalton = mm.unit.dalton
        self._masses = np.array([self.system.getParticleMass(i).value_in_unit(dalton)
                                 for i in range(n)])
        self._masses.setflags(write=False)
        self._virtual = np.array([self.system.isVirtualSite(i) for i in range(n)], dtype=bool)
        self._virtual.setflags(write=False)
        pairs, distances = [], []
        for k in range(self.system.getNumConstraints()):
            i, j, d = self.system.getConstraintParameters(k)
            pairs.append((i, j))
            distances.append(d.value_in_unit(mm.unit.nanometer))
        self._constraints = DistanceConstraints(np.array(pairs, dtype=np.int64).reshape(-1, 2),
                                                np.array(distances, dtype=float))
        self._constraints.check_indices(n)
        mobile_particles(self._masses)
        integrator = mm.VerletIntegrator(0.001)
        integrator.setConstraintTolerance(CONSTRAINT_TOLERANCE)
        plat, properties = _platform(platform, threads)
        self._context = mm.Context(self.system, integrator, plat, properties)
        if box is not None:
            b = np.asarray(box, dtype=float).reshape(3, 3)
            self._context.setPeriodicBoxVectors(*(mm.Vec3(*row) for row in b))
        self._box = box
        self._context.setPositions(x)
        if len(self._constraints):
            self._context.applyConstraints(CONSTRAINT_TOLERANCE)
        self._context.computeVirtualSites()
        state = self._context.getState(getPositions=True)
        self._positions = np.array(state.getPositions(asNumpy=True).value_in_unit(
            mm.unit.nanometer), dtype=float)
        self._positions.setflags(write=False)
        #: Force or energy evaluations so far.
        self.calls = 0

    # --- the ForceEngine interface -------------------------------------------------------

    @property
    def n_particles(self) -> int:
        return len(self._masses)

    @property
    def masses(self) -> np.ndarray:
        return self._masses

    @property
    def positions(self) -> np.ndarray:
        return self._positions

    @property
    def constraints(self) -> DistanceConstraints:
        return self._constraints

    @property
    def virtual_sites(self) -> np.ndarray:
        return self._virtual

    @property
    def labels(self) -> tuple[str, ...]:
        return self._labels

    @property
    def periodic(self) -> bool:
        """Whether the System uses periodic boundaries (then only translations leave the
        energy unchanged, not rotations)."""
        return bool(self.system.usesPeriodicBoundaryConditions())

    def _state(self, positions: np.ndarray, **what: bool) -> Any:
        self.calls += 1
        self._context.setPositions(np.asarray(positions, dtype=float))
        if self._virtual.any():
            self._context.computeVirtualSites()
        return self._context.getState(**what)

    def forces(self, positions: np.ndarray) -> np.ndarray:
        state = self._state(positions, getForces=True)
        return np.asarray(state.getForces(asNumpy=True)._value, dtype=float)

    def energy(self, positions: np.ndarray) -> float:
        state = self._state(positions, getEnergy=True)
        return float(state.getPotentialEnergy()._value)

    # --- beyond the interface ------------------------------------------------------------

    def minimize(self, tolerance: float = 10.0, max_iterations: int = 0,
                 progress: Callable[[str, int, int | None], None] | None = None
                 ) -> Minimization:
        """Move :attr:`positions` to a local minimum of the energy (OpenMM's
        ``LocalEnergyMinimizer``, L-BFGS; constraints held by a penalty to the integrator's
        tolerance, then applied exactly).

        Parameters
        ----------
        tolerance : float
            Stop when the RMS force component falls below this, kJ/mol/nm.
        max_iterations : int
            Iteration cap; 0 runs to convergence.
        progress : callable, optional
            ``progress("minimize", iterations, None)`` after each L-BFGS iteration (counted
            over OpenMM's restarts with stronger constraint restraints).

        Returns
        -------
        Minimization
            Energies and the remaining forces.
        """
        mm = _openmm()
        before = self.energy(self._positions)
        self._context.setPositions(self._positions)
        reporter = None
        if progress is not None:
            count, tell = [0], progress

            class Reporter(mm.MinimizationReporter):  # type: ignore[misc,name-defined]
                def report(self, iteration: int, x: Any, grad: Any, args: Any) -> bool:
                    count[0] += 1
                    tell("minimize", count[0], None)
                    return False

            reporter = Reporter()
        mm.LocalEnergyMinimizer.minimize(self._context, float(tolerance), int(max_iterations),
                                         reporter)
        if len(self._constraints):
            self._context.applyConstraints(CONSTRAINT_TOLERANCE)
        self._context.computeVirtualSites()
        x = np.array(self._context.getState(getPositions=True).getPositions(
            asNumpy=True)._value, dtype=float)
        x.setflags(write=False)
        self._positions = x
        f = self.forces(x)[mobile_particles(self._masses)].reshape(-1)
        if len(self._constraints):
            f = ConstrainedSpace(self._constraints, x, self._masses, f).tangent_forces(f)
        return Minimization(before, self.energy(x), float(np.sqrt(np.mean(f ** 2))),
                            float(np.abs(f).max()), float(tolerance), int(max_iterations))

    def at(self, positions: Any, *, platform: str | None = None,
           threads: int | None = None) -> OpenMMEngine:
        """The same system (topology, labels, box) at other positions (nm), optionally on
        another platform (e.g. minimised on CPU, then differentiated on Reference)."""
        return OpenMMEngine(self.system, positions,
                            platform=self.platform_name if platform is None else platform,
                            threads=self.threads if threads is None else threads,
                            box=self._box, topology=self.topology, labels=self._labels)

    def with_masses(self, masses: Any) -> OpenMMEngine:
        """The same system and configuration with other particle masses (amu), e.g. after
        hydrogen mass repartitioning; virtual sites keep mass 0."""
        m = np.asarray(masses, dtype=float)
        if m.shape != self._masses.shape or not np.all(np.isfinite(m)) or np.any(m < 0):
            raise StepsafeError(f"masses must be {self.n_particles} finite numbers >= 0")
        if np.any((m > 0) & self._virtual):
            raise StepsafeError("a virtual site cannot carry mass")
        mm = _openmm()
        system = mm.XmlSerializer.clone(self.system)
        for i, mi in enumerate(m):
            system.setParticleMass(i, float(mi))
        return OpenMMEngine(system, self._positions, platform=self.platform_name,
                            threads=self.threads, box=self._box, topology=self.topology,
                            labels=self._labels)

    def with_constraints(self, constraints: DistanceConstraints) -> OpenMMEngine:
        """The same system with ``constraints`` added to its own (a pair it already
        constrains must keep its distance); positions are put on them.

        Parameters
        ----------
        constraints : DistanceConstraints
            Pairs and distances (nm) to add.

        Returns
        -------
        OpenMMEngine
        """
        own = {(min(i, j), max(i, j)): d for (i, j), d in
               zip(self._constraints.pairs.tolist(), self._constraints.distances.tolist())}
        mm = _openmm()
        system = mm.XmlSerializer.clone(self.system)
        for (i, j), d in zip(constraints.pairs.tolist(), constraints.distances.tolist()):
            key = (min(i, j), max(i, j))
            if key in own:
                if abs(own[key] - d) > 1e-9 * d:
                    raise StepsafeError(f"particles {i} and {j} are already constrained to "
                                        f"{own[key]:.6g} nm, not {d:.6g} nm")
                continue
            if self._virtual[i] or self._virtual[j]:
                raise StepsafeError(f"a constraint cannot join virtual site {i}-{j}")
            system.addConstraint(int(i), int(j), float(d))
            own[key] = d
        return OpenMMEngine(system, self._positions, platform=self.platform_name,
                            threads=self.threads, box=self._box, topology=self.topology,
                            labels=self._labels)

    def bonded_terms(self) -> tuple[dict[tuple[int, int], float], np.ndarray, np.ndarray]:
        """The equilibrium lengths of the System's harmonic bonds (``{(i, j): r0}`` in nm,
        ``i < j``; constrained pairs without a bond term give their constrained distance)
        and its harmonic angles ``(A, 3)`` with their equilibrium values in radians: what
        the ``constraints:`` rules need (OpenMM's ``createSystem`` takes them from the force
        field the same way)."""
        mm = _openmm()
        unit = mm.unit
        lengths = {(min(i, j), max(i, j)): d for (i, j), d in
                   zip(self._constraints.pairs.tolist(), self._constraints.distances.tolist())}
        angles, values = [], []
        for force in self.system.getForces():
            if isinstance(force, mm.HarmonicBondForce):
                for b in range(force.getNumBonds()):
                    i, j, r0, _ = force.getBondParameters(b)
                    lengths[(min(i, j), max(i, j))] = r0.value_in_unit(unit.nanometer)
            elif isinstance(force, mm.HarmonicAngleForce):
                for a in range(force.getNumAngles()):
                    i, j, k, theta, _ = force.getAngleParameters(a)
                    angles.append((i, j, k))
                    values.append(theta.value_in_unit(unit.radian))
        return (lengths, np.array(angles, dtype=np.int64).reshape(-1, 3),
                np.array(values, dtype=float))

    def degrees_of_freedom(self) -> int:
        """3 per particle of positive mass, less one per constraint and 3 with a
        ``CMMotionRemover`` (:func:`~stepsafe.systems.md.enginerun.degrees_of_freedom`)."""
        return degrees_of_freedom(self.system_xml())

    def on_constraints(self, positions: Any) -> np.ndarray:
        """``positions`` (N, 3) nm put on the constraints (``Context.applyConstraints`` to
        :data:`CONSTRAINT_TOLERANCE`) with the virtual sites placed: a configuration of
        another platform's run (single precision) made one the Hessian can be taken at."""
        x = as_positions(positions, self.n_particles)
        self._context.setPositions(x)
        if len(self._constraints):
            self._context.applyConstraints(CONSTRAINT_TOLERANCE)
        self._context.computeVirtualSites()
        return np.array(self._context.getState(getPositions=True).getPositions(
            asNumpy=True)._value, dtype=float)

    def thermal_frames(self, spec: SamplingSpec) -> np.ndarray:
        """Configurations at temperature from OpenMM's own ``LangevinMiddleIntegrator``
        (:class:`~stepsafe.systems.md.enginerun.SamplingSpec`: per seed, velocities drawn at
        T, ``thermalisation`` steps, then a frame every ``spacing`` steps), on the CPU
        platform with one thread where there is one (else this engine's platform), started
        from :attr:`positions`.

        Parameters
        ----------
        spec : SamplingSpec

        Returns
        -------
        ndarray, shape (seeds, frames, N, 3)
            Positions in nm.
        """
        mm = _openmm()
        try:
            platform, properties = _platform("CPU", 1)
        except StepsafeError:
            platform, properties = _platform(self.platform_name, self.threads)
        out = np.empty((len(spec.seeds), spec.frames, self.n_particles, 3))
        for s, seed in enumerate(spec.seeds):
            integrator = mm.LangevinMiddleIntegrator(float(spec.temperature),
                                                     float(spec.friction), float(spec.step))
            integrator.setRandomNumberSeed(int(seed))
            context = mm.Context(self.system, integrator, platform, properties)
            if self._box is not None:
                b = np.asarray(self._box, dtype=float).reshape(3, 3)
                context.setPeriodicBoxVectors(*(mm.Vec3(*row) for row in b))
            context.setPositions(self._positions)
            if len(self._constraints):
                context.applyConstraints(1e-8)
            context.setVelocitiesToTemperature(float(spec.temperature), int(seed))
            try:
                integrator.step(int(spec.thermalisation))
                for k in range(spec.frames):
                    integrator.step(int(spec.spacing))
                    state = context.getState(getPositions=True, getEnergy=True)
                    if not math.isfinite(state.getPotentialEnergy()._value):
                        raise ArithmeticError("non-finite energy")
                    out[s, k] = state.getPositions(asNumpy=True)._value
            except Exception as exc:
                raise StepsafeError(
                    f"the thermal sampling (LangevinMiddle at {spec.step:g} ps, seed {seed}) "
                    f"failed: {str(exc).splitlines()[0][:60]}") from None
            del context, integrator
        return out

    def trials(self, spec: TrialSpec, progress: Any = None,
               worker: TrialWorker | None = None) -> TrialRecord:
        """Runs of OpenMM's own integrator from thermal states of this configuration
        (:func:`~stepsafe.systems.md.enginerun.run_trials`, in an engine process).

        Parameters
        ----------
        spec : TrialSpec
        progress : callable, optional
            ``progress("trials", seeds_done, seeds)``.
        worker : TrialWorker, optional
            The engine process (from :meth:`trial_worker`) to run in; one for this call
            when omitted.

        Returns
        -------
        TrialRecord
        """
        return run_trials(self.system_xml(), self.state_xml(), spec, progress=progress,
                          worker=worker)

    def trial_worker(self) -> TrialWorker:
        """An engine process for many :meth:`trials` (a context manager)."""
        return TrialWorker()

    def system_xml(self) -> str:
        """The System, serialized (``XmlSerializer``)."""
        return _openmm().XmlSerializer.serialize(self.system)

    def state_xml(self) -> str:
        """A serialized State holding :attr:`positions` and the periodic box."""
        mm = _openmm()
        self._context.setPositions(self._positions)
        return mm.XmlSerializer.serialize(self._context.getState(getPositions=True))


# --- reading files ----------------------------------------------------------------------

def _read_text(path: Path, what: str) -> str:
    if not path.is_file():
        raise StepsafeError(f"{what} file not found", str(path))
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise StepsafeError(f"cannot read {what}: {exc}", str(path)) from None


def read_system(path: str | os.PathLike[str]) -> Any:
    """An ``openmm.System`` from a file written by ``XmlSerializer.serialize``.

    Parameters
    ----------
    path : path-like
        The XML file.

    Returns
    -------
    openmm.System
    """
    mm = _openmm()
    p = Path(path)
    text = _read_text(p, "OpenMM system")
    try:
        obj = mm.XmlSerializer.deserialize(text)
    except Exception as exc:
        raise StepsafeError(f"not an OpenMM XML file ({str(exc).splitlines()[0][:80]})",
                            str(p)) from None
    if not isinstance(obj, mm.System):
        raise StepsafeError(f"holds an OpenMM {type(obj).__name__}, not a System", str(p))
    return obj


@dataclass(frozen=True)
class Structure:
    """Coordinates read from a structure file.

    Attributes
    ----------
    positions : ndarray, shape (N, 3)
        In nm.
    box : ndarray, shape (3, 3) or None
        Periodic box vectors in nm when the file sets them for the run (a State does; a PDB's
        box is left to the System's default).
    topology : Topology or None
        From a PDB or PDBx/mmCIF file.
    labels : tuple of str
        ``"RES<id>:<atom>"`` per particle, or empty strings.
    """

    positions: np.ndarray
    box: np.ndarray | None
    topology: Topology | None
    labels: tuple[str, ...]


def read_structure(path: str | os.PathLike[str]) -> Structure:
    """Positions (and, from PDB/PDBx, the topology) from ``.pdb``, ``.cif``/``.pdbx`` or a
    serialized State ``.xml``.

    Parameters
    ----------
    path : path-like
        The file; its suffix picks the reader.

    Returns
    -------
    Structure
    """
    mm = _openmm()
    app, unit = mm.app, mm.unit
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".pdb", ".ent", ".cif", ".pdbx", ".mmcif", ".xml"):
        raise StepsafeError("positions must be a .pdb, .cif/.pdbx or serialized State .xml file",
                            str(p))
    if suffix == ".xml":
        text = _read_text(p, "positions")
        try:
            state = mm.XmlSerializer.deserialize(text)
        except Exception as exc:
            raise StepsafeError(f"not an OpenMM XML file ({str(exc).splitlines()[0][:80]})",
                                str(p)) from None
        if not isinstance(state, mm.State):
            raise StepsafeError(f"holds an OpenMM {type(state).__name__}, not a State", str(p))
        try:
            x = state.getPositions(asNumpy=True).value_in_unit(unit.nanometer)
        except Exception:
            raise StepsafeError("the State holds no positions", str(p)) from None
        box = np.array([v.value_in_unit(unit.nanometer) for v in state.getPeriodicBoxVectors()])
        return Structure(np.array(x, dtype=float), box, None, ("",) * len(x))
    _read_text(p, "positions")
    try:
        reader = app.PDBFile(str(p)) if suffix in (".pdb", ".ent") else app.PDBxFile(str(p))
    except Exception as exc:
        raise StepsafeError(f"cannot read the structure ({str(exc).splitlines()[0][:80]})",
                            str(p)) from None
    x = np.array(reader.getPositions(asNumpy=True).value_in_unit(unit.nanometer), dtype=float)
    top = reader.topology
    atoms = list(top.atoms())
    index = {a: k for k, a in enumerate(atoms)}
    residues = list(top.residues())
    rid = {r: k for k, r in enumerate(residues)}
    topology = Topology(
        elements=tuple(a.element.symbol if a.element is not None else None for a in atoms),
        bonds=np.array([(index[a], index[b]) for a, b in top.bonds()], dtype=np.int64),
        residues=tuple(a.residue.name for a in atoms),
        residue_ids=np.array([rid[a.residue] for a in atoms], dtype=np.int64))
    labels = tuple(f"{a.residue.name}{a.residue.id}:{a.name}" for a in atoms)
    return Structure(x, None, topology, labels)


def load(system: str | os.PathLike[str], positions: str | os.PathLike[str], *,
         platform: str = "Reference", threads: int | None = None) -> OpenMMEngine:
    """An engine from a System XML file and a structure file.

    Parameters
    ----------
    system : path-like
        ``XmlSerializer`` output holding a System.
    positions : path-like
        ``.pdb``, ``.cif``/``.pdbx`` or a serialized State ``.xml`` with positions.
    platform : {"Reference", "CPU"}
        ``Reference`` for Hessians.
    threads : int, optional
        CPU threads.

    Returns
    -------
    OpenMMEngine
    """
    sys_ = read_system(system)
    structure = read_structure(positions)
    n = sys_.getNumParticles()
    if len(structure.positions) != n:
        raise StepsafeError(f"holds {len(structure.positions)} particles, the system {n}",
                            str(positions))
    if not np.all(np.isfinite(structure.positions)):
        raise StepsafeError("positions must be finite", str(positions))
    return OpenMMEngine(sys_, structure.positions, platform=platform, threads=threads,
                        box=structure.box, topology=structure.topology,
                        labels=structure.labels)


# --- example systems from files shipped in the OpenMM wheel -----------------------------

#: ``constraints:`` names and OpenMM's createSystem values.
CONSTRAINT_KINDS = ("none", "h-bonds", "all-bonds", "h-angles")


def write_example_system(kind: str, directory: str | os.PathLike[str], *,
                         constraints: str = "none", hydrogen_mass: float | None = None,
                         box_edge: float = 1.6, cutoff: float = 0.7,
                         rigid_water: bool = False) -> tuple[Path, Path]:
    """Build a test system from the force fields and structures inside the OpenMM wheel and
    write ``<name>.xml`` (the System) and ``<name>.pdb`` (positions, topology) into
    ``directory``.

    * ``"water"``: a cubic box of TIP3P water (``amber14/tip3p.xml``) of edge
      ``box_edge`` nm filled by ``Modeller.addSolvent`` (1.6 nm: 129 molecules, 387 atoms),
      PME with a ``cutoff`` nm direct-space cutoff, flexible (``rigidWater=False``: harmonic
      O-H bonds and H-O-H angle) unless ``rigid_water``.
    * ``"villin"``: the villin headpiece of OpenMM's ``test.pdb`` with its water and ions
      removed (582 atoms), Amber14 (``amber14-all.xml``), vacuum, no cutoff.

    Both without a centre-of-mass motion remover (it would change velocities in NVE runs).

    Parameters
    ----------
    kind : {"water", "villin"}
    directory : path-like
        Where to write; created if missing.
    constraints : {"none", "h-bonds", "all-bonds", "h-angles"}
        OpenMM's ``constraints=None, HBonds, AllBonds, HAngles``.
    hydrogen_mass : float, optional
        OpenMM's ``hydrogenMass`` in amu.
    box_edge, cutoff : float
        Water box edge and PME cutoff in nm (cutoff at most half the edge).
    rigid_water : bool
        Rigid water (three distance constraints per molecule).

    Returns
    -------
    (Path, Path)
        The System XML and the PDB file.
    """
    mm = _openmm()
    app, unit = mm.app, mm.unit
    if constraints not in CONSTRAINT_KINDS:
        raise StepsafeError(f"unknown constraints {constraints!r}; choose one of "
                            f"{', '.join(CONSTRAINT_KINDS)}")
    cons = {"none": None, "h-bonds": app.HBonds, "all-bonds": app.AllBonds,
            "h-angles": app.HAngles}[constraints]
    extra: dict[str, Any] = {}
    if hydrogen_mass is not None:
        extra["hydrogenMass"] = float(hydrogen_mass) * unit.amu
    if kind == "water":
        ff = app.ForceField("amber14/tip3p.xml")
        model = app.Modeller(app.Topology(), [])
        edge = float(box_edge)
        model.addSolvent(ff, model="tip3p", boxSize=mm.Vec3(edge, edge, edge) * unit.nanometer)
        system = ff.createSystem(model.topology, nonbondedMethod=app.PME,
                                 nonbondedCutoff=float(cutoff) * unit.nanometer,
                                 constraints=cons, rigidWater=bool(rigid_water),
                                 removeCMMotion=False, **extra)
        name = f"water{model.topology.getNumResidues()}"
    elif kind == "villin":
        pdb = app.PDBFile(os.path.join(os.path.dirname(app.__file__), "data", "test.pdb"))
        model = app.Modeller(pdb.topology, pdb.positions)
        model.deleteWater()
        model.delete([r for r in model.topology.residues() if r.name in ("NA", "CL", "Na", "Cl")])
        ff = app.ForceField("amber14-all.xml")
        system = ff.createSystem(model.topology, nonbondedMethod=app.NoCutoff,
                                 constraints=cons, removeCMMotion=False, **extra)
        name = "villin"
    else:
        raise StepsafeError(f"unknown example system {kind!r}; choose water or villin")
    tag = f"{name}-{constraints}" + (f"-hmr{hydrogen_mass:g}" if hydrogen_mass else "") + \
        ("-rigid" if kind == "water" and rigid_water else "")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    xml, pdbfile = out / f"{tag}.xml", out / f"{tag}.pdb"
    xml.write_text(mm.XmlSerializer.serialize(system))
    with open(pdbfile, "w") as fh:
        app.PDBFile.writeFile(model.topology, model.positions, fh, keepIds=True)
    return xml, pdbfile


# --- trial runs of OpenMM's integrators (run in a subprocess by enginerun) ---------------

def trial_run(spec: dict[str, Any]) -> dict[str, Any]:
    """One seed of a trial run: thermalise with ``LangevinMiddleIntegrator``, then run the
    integrator under test, sampling the energies every ``sample_every`` steps and stopping at
    the first sign of a blow-up. Called in a subprocess by
    :func:`stepsafe.systems.md.enginerun.run_trials`, which documents the keys of ``spec`` and
    of the result (plain JSON types).

    Parameters
    ----------
    spec : dict

    Returns
    -------
    dict
    """
    mm = _openmm()
    unit = mm.unit
    system = read_system(spec["system"])
    structure = read_structure(spec["positions"])
    n = system.getNumParticles()
    masses = np.array([system.getParticleMass(i).value_in_unit(unit.dalton) for i in range(n)])
    has_cm_remover = any(isinstance(f, mm.CMMotionRemover) for f in system.getForces())
    n_dof = 3 * int(np.count_nonzero(masses > 0)) - system.getNumConstraints() \
        - (3 if has_cm_remover else 0)
    seed = int(spec["seed"])
    temperature = float(spec["temperature"])
    friction = float(spec["friction"])
    kT = MOLAR_GAS_CONSTANT * temperature
    platform, properties = _platform(spec["platform"], spec.get("threads"))

    def context(integrator: Any) -> Any:
        if spec.get("constraint_tolerance") is not None:
            integrator.setConstraintTolerance(float(spec["constraint_tolerance"]))
        ctx = mm.Context(system, integrator, platform, properties)
        if structure.box is not None:
            ctx.setPeriodicBoxVectors(*(mm.Vec3(*row) for row in structure.box))
        return ctx

    result: dict[str, Any] = {"seed": seed, "n_dof": n_dof, "cm_motion_remover": has_cm_remover,
                              "blew_up": False, "blowup_step": None, "reason": "",
                              "equilibrated": False, "times": [], "potential": [],
                              "kinetic": []}
    eq = mm.LangevinMiddleIntegrator(temperature, float(spec["equilibration_friction"]),
                                     float(spec["equilibration_step"]))
    eq.setRandomNumberSeed(seed)
    ctx = context(eq)
    ctx.setPositions(structure.positions)
    if system.getNumConstraints():
        ctx.applyConstraints(1e-8)
    ctx.setVelocitiesToTemperature(temperature, seed)
    try:
        eq.step(int(spec["equilibration_steps"]))
        state = ctx.getState(getPositions=True, getVelocities=True, getEnergy=True)
        ok = math.isfinite(state.getPotentialEnergy()._value)
    except Exception:
        ok = False
    if not ok:
        result["reason"] = "thermalisation failed (non-finite energy)"
        return result
    result["equilibrated"] = True
    h = float(spec["step"])
    if spec["integrator"] == "verlet":
        integrator = mm.VerletIntegrator(h)
    else:
        integrator = mm.LangevinMiddleIntegrator(temperature, friction, h)
        integrator.setRandomNumberSeed(seed + 1)
    del ctx
    ctx = context(integrator)
    ctx.setState(state)
    every = int(spec["sample_every"])
    bound = float(spec["energy_bound"]) * n_dof * kT
    e0 = None
    done = 0
    for _ in range(int(spec["steps"]) // every):
        try:
            integrator.step(every)
            st = ctx.getState(getEnergy=True)
            done += every
            pe, ke = st.getPotentialEnergy()._value, st.getKineticEnergy()._value
        except Exception as exc:      # within the last `every` steps
            result.update(blew_up=True, blowup_step=done + every,
                          reason=f"OpenMM: {str(exc).splitlines()[0][:60]}")
            break
        if not (math.isfinite(pe) and math.isfinite(ke)):
            result.update(blew_up=True, blowup_step=done, reason="non-finite energy")
            break
        e0 = pe + ke if e0 is None else e0
        result["times"].append(done * h)
        result["potential"].append(pe)
        result["kinetic"].append(ke)
        if spec["integrator"] == "verlet" and abs(pe + ke - e0) > bound:
            result.update(blew_up=True, blowup_step=done,
                          reason=f"energy changed by more than {spec['energy_bound']:g} n_dof kT")
            break
        # with a thermostat the total energy wanders with the heat exchanged (and U with
        # the structure); an instability heats: the kinetic energy beyond its mean
        if spec["integrator"] != "verlet" and ke - 0.5 * n_dof * kT > bound:
            result.update(blew_up=True, blowup_step=done,
                          reason=f"kinetic energy above its mean by more than "
                                 f"{spec['energy_bound']:g} n_dof kT")
            break
    result["steps_done"] = done
    return result


def _worker() -> int:
    """Subprocess entry: a JSON spec on stdin, the JSON result on stdout (exit 2 with
    ``{"error": ...}`` for bad input); with ``--serve``, one spec per line and one result
    per line until stdin closes (bad input answered by an ``{"error": ...}`` line)."""
    if "--serve" in sys.argv[1:]:
        for line in sys.stdin:
            if not line.strip():
                continue
            try:
                out = trial_run(json.loads(line))
            except StepsafeError as exc:
                out = {"error": str(exc)}
            sys.stdout.write(json.dumps(out) + "\n")
            sys.stdout.flush()
        return 0
    spec = json.loads(sys.stdin.read())
    try:
        out = trial_run(spec)
    except StepsafeError as exc:
        sys.stdout.write(json.dumps({"error": str(exc)}))
        return 2
    sys.stdout.write(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(_worker())
