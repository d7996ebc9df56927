"""An MD engine's system as the ``system:`` of a scene (or ``openmm_system=`` in Python): read
it, apply the scene's constraint rule and hydrogen mass repartitioning, minimise if asked, and
compute the instantaneous normal modes of the configuration the analysis uses.

::

    time_unit: fs
    system:
      openmm: system.xml          # an OpenMM System serialized with XmlSerializer
      positions: structure.pdb    # or .cif/.pdbx, or a serialized State (.xml) with positions
      constraints: h-bonds        # optional: none | h-bonds | all-bonds | h-angles
      hydrogen_mass: 3            # optional, amu: OpenMM's hydrogenMass rule
      minimize: true              # optional (default false): OpenMM's LocalEnergyMinimizer

Paths are read next to the scene file. The System brings its own constraints (rigid water,
``HBonds``, ...); ``constraints:`` adds those of the rule (as ``ForceField.createSystem``
would have, from the structure's bonds and the System's harmonic bond and angle terms, which
is why the rule needs a PDB or PDBx file, not a State), ``none`` adds nothing.

The modes: the Hessian of the potential at the configuration (the structure's positions, put
on the constraints, or the minimum reached from them) by central differences of OpenMM's
forces on its Reference platform (:mod:`~stepsafe.systems.md.hessian`), on the constraints'
tangent space in the mass metric (:mod:`~stepsafe.systems.md.constraints`). Up to
:data:`DENSE_ATOMS` moving particles the Hessian is dense and every mode is found; above, the
:data:`FASTEST` modes of largest ``|omega^2|`` come from Lanczos on Hessian-vector products
(memory linear in the atoms: a Lanczos basis of at most 20 vectors of 3N numbers, no
3N x 3N matrix), and every other eigenvalue lies within plus or minus the smallest of them in
modulus. Above :data:`ONE_MODE_ATOMS` moving particles Lanczos looks for the fastest mode
alone, to the relative tolerance :data:`LARGE_TOL`: in a large system the next modes are
copies of the same bond stretch a fraction of a percent below it, which Lanczos separates
only after several times as many products, and the verdict needs the largest modulus only
(the residual of the pair found is part of its error). The squared angular frequencies are in
rad^2/ps^2 (OpenMM's units) and are converted to rad per the scene's time unit.

What a verdict on these modes means: the linear stability of the integrator at this
configuration (0 K when it is a minimum). Thermal motion moves the frequencies and couples
the modes; measured runs of OpenMM's integrators at 300 K fail from about 0.8-0.95 of the 0 K
limit (README, engine validation), which the analysis at this configuration does not cover:
the analysis at temperature (:mod:`~stepsafe.systems.md.thermal`) measures it with the
engine's own snapshots and runs.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError, unknown_key
from stepsafe.systems.md import openmm_engine as oe
from stepsafe.systems.md.constraints import (
    KINDS,
    ConstrainedSpace,
    constrained_modes,
    constrained_spectrum,
    constraints_for,
    rigid_body_basis,
)
from stepsafe.systems.md.engine import Topology, mobile_particles
from stepsafe.systems.md.enginerun import DRIFT_TOLERANCE, TrialSpec, run_trials
from stepsafe.systems.md.hessian import (
    LANCZOS_TOL,
    HessianVectorProduct,
    ModeReport,
    Spectrum,
    describe,
    extreme_eigenvalues,
    hessian,
)
from stepsafe.systems.md.hmr import Repartition, repartition, rigid_waters
from stepsafe.systems.scene import parse_real

#: The keys of ``system:`` for an OpenMM system.
KEYS = ("openmm", "positions", "constraints", "hydrogen_mass", "minimize", "runs")
#: The keys of ``runs:`` and their defaults (K, ps, 1/ps).
RUN_KEYS = {"temperature": None, "seeds": (1, 2, 3), "duration": 2.0, "friction": 1.0}
#: The methods whose runs OpenMM can make: the method's name, OpenMM's integrator.
ENGINE_INTEGRATORS = {"verlet": "verlet", "langevin-middle": "langevin-middle"}
#: Up to this many moving particles the Hessian is dense (6 N force evaluations); above, the
#: fastest modes come from Lanczos.
DENSE_ATOMS = 200
#: Modes reported with the atoms that move in them (and computed by Lanczos above
#: :data:`DENSE_ATOMS`).
FASTEST = 5
#: Above this many moving particles the Lanczos path computes the fastest mode only, to the
#: relative tolerance :data:`LARGE_TOL` (measured on 9786 atoms of water: 112 products,
#: against about 200 at 1e-6 and several times that for 5 modes).
ONE_MODE_ATOMS = 2000
LARGE_TOL = 1e-4
#: The minimiser tolerance, RMS force in kJ/mol/nm (OpenMM's default is 10; at 1 the rotations of
#: a molecule in vacuum keep omega^2 within the finite-difference error of 0).
MINIMIZE_TOLERANCE = 1.0


@dataclass(frozen=True)
class Settings:
    """What the scene asks of the system besides its files.

    Attributes
    ----------
    constraints : str or None
        A rule of :data:`~stepsafe.systems.md.constraints.KINDS`; None: the System's own only.
    hydrogen_mass : float or None
        amu; None: the System's masses.
    minimize : bool
        Minimise the energy before the analysis.
    runs : Runs or None
        Runs of the method in OpenMM that a checked step must also pass.
    """

    constraints: str | None = None
    hydrogen_mass: float | None = None
    minimize: bool = False
    runs: Runs | None = None


@dataclass(frozen=True)
class Runs:
    """``runs:``: short runs of the checked method in OpenMM from thermal states.

    Attributes
    ----------
    temperature : float
        K.
    seeds : tuple of int
        One run per seed (thermalisation and Langevin noise).
    duration : float
        ps per run after 1 ps of thermalisation.
    friction : float
        1/ps, for ``langevin-middle``.
    """

    temperature: float
    seeds: tuple[int, ...] = (1, 2, 3)
    duration: float = 2.0
    friction: float = 1.0


@dataclass(frozen=True)
class MDAnalysis:
    """The modes of an engine's system at a configuration.

    Attributes
    ----------
    spectrum : Spectrum
        omega^2 in rad^2/ps^2 (all of them, or the :data:`FASTEST` of largest modulus).
    complete : bool
        Whether every mode was computed (dense Hessian).
    fastest : tuple of ModeReport
        The fastest modes with the atoms that carry them.
    n_particles, n_moving, n_constraints : int
        Particles, particles of positive mass, distance constraints.
    settings : Settings
    repartition : Repartition or None
        The hydrogen mass repartitioning applied.
    minimization : Any
        :class:`~stepsafe.systems.md.openmm_engine.Minimization`, or None.
    rms_force : float
        RMS force on the moving particles at the configuration (kJ/mol/nm, constraint forces
        removed).
    step : float
        The finite-difference step, nm.
    relative_error : float
        The step control's relative error estimate of a Hessian-vector product.
    force_calls : int
        Force evaluations for the Hessian.
    engine : Any
        The engine at the configuration analysed (with the constraints and masses used).
    rigid : int
        Rigid-body motions left out of a dense spectrum (translations, and rotations
        without periodic boundaries; 0 on the Lanczos path, where they sit near 0 below
        the modes found).
    """

    spectrum: Spectrum
    complete: bool
    fastest: tuple[ModeReport, ...]
    n_particles: int
    n_moving: int
    n_constraints: int
    settings: Settings
    repartition: Repartition | None
    minimization: Any
    rms_force: float
    step: float
    relative_error: float
    force_calls: int
    engine: Any
    rigid: int = 0


def settings(tree: dict[str, Any], fail: Callable[[str, str], StepsafeError]) -> Settings:
    """The :class:`Settings` of a ``system:`` mapping; ``fail(key, message)`` makes the
    error that names the key."""
    unknown = set(tree) - set(KEYS)
    if unknown:
        key = sorted(unknown)[0]
        raise fail(key, unknown_key(key, KEYS))
    rule = tree.get("constraints")
    if rule is not None and rule not in KINDS:
        raise fail("constraints", f"must be one of {', '.join(KINDS)}, got {str(rule)[:30]!r}")
    mass = tree.get("hydrogen_mass")
    if mass is not None:
        mass = _amu(mass)
        if mass is None:
            raise fail("hydrogen_mass", f"must be a mass in amu (3, or 3 amu), got "
                                        f"{str(tree['hydrogen_mass'])[:30]!r}")
        if not 0 < mass <= 100:  # (nan too)
            raise fail("hydrogen_mass", f"must be a mass in amu between 0 and 100, got {mass:g}")
    flag = tree.get("minimize", False)
    if str(flag).lower() not in ("true", "false"):
        raise fail("minimize", f"must be true or false, got {str(flag)[:30]!r}")
    runs = _runs(tree["runs"], fail) if tree.get("runs") is not None else None
    return Settings(rule, mass, str(flag).lower() == "true", runs)


def _runs(value: Any, fail: Callable[[str, str], StepsafeError]) -> Runs:
    """``runs: {temperature: 300 K, seeds: [1, 2, 3], duration: 2 ps, friction: 1}``."""
    if not isinstance(value, dict):
        raise fail("runs", "must be a mapping {temperature:, seeds:, duration:, friction:}")
    unknown = set(value) - set(RUN_KEYS)
    if unknown:
        key = sorted(unknown)[0]
        raise fail(f"runs.{key}", unknown_key(key, tuple(RUN_KEYS)))
    if "temperature" not in value:
        raise fail("runs.temperature", "missing: the temperature of the runs, in K")

    def amount(key: str, units: tuple[str, ...], low: float, high: float) -> float:
        given = value.get(key, RUN_KEYS[key])
        text = str(given).strip()
        for suffix in units:
            if text.endswith(suffix):
                text = text[:-len(suffix)]
                break
        x = None if isinstance(given, bool) else parse_real(text)
        if x is None or not low < x <= high:
            raise fail(f"runs.{key}", f"must be a number in ({low:g}, {high:g}] "
                                      f"{units[0]}, got {str(given)[:30]!r}")
        return x

    given = value.get("seeds", RUN_KEYS["seeds"])
    if not isinstance(given, (list, tuple)):
        given = []  # refused below
    texts = [str(k).strip() for k in given if not isinstance(k, bool)]
    seeds = [int(t) for t in texts if t.isascii() and t.isdigit() and len(t) < 10]
    if not seeds or len(seeds) > 20 or len(seeds) != len(given) or \
            len(set(seeds)) != len(seeds):
        raise fail("runs.seeds", "must be a list of 1 to 20 distinct whole numbers below "
                                 f"10^9, got {str(given)[:40]!r}")
    return Runs(amount("temperature", ("K",), 0.0, 1e4), tuple(seeds),
                amount("duration", ("ps",), 0.0, 1e3), amount("friction", ("/ps", "ps-1"),
                                                                 0.0, 1e4))


def _amu(value: Any) -> float | None:
    """A mass in amu: a number, or a text ``"3"``, ``"3 amu"`` (also ``Da``, ``u``,
    ``g/mol``); None if it is neither."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if not isinstance(value, str):
        return None
    text = value.strip()
    for suffix in ("amu", "Da", "g/mol", "u"):
        if text.endswith(suffix):
            text = text[:-len(suffix)]
            break
    return parse_real(text)


def load_engine(system: Any, positions: Any, folder: Path,
                fail: Callable[[str, str], StepsafeError]) -> Any:
    """An :class:`~stepsafe.systems.md.openmm_engine.OpenMMEngine` on the Reference platform
    from file names (read next to the scene, ``folder``) or, from Python, an
    ``openmm.System`` and positions (an (N, 3) array in nm or an OpenMM ``Quantity``)."""
    if positions is None:
        raise fail("positions", "missing: the coordinates (a .pdb, .cif/.pdbx or serialized "
                                "State .xml file; in Python an (N, 3) array in nm)")
    if isinstance(system, (str, os.PathLike)):
        path = folder / Path(system)
        sys_ = _named(lambda: oe.read_system(path), fail, "openmm")
    else:
        mm = oe._openmm()
        if not isinstance(system, mm.System):
            raise fail("openmm", f"must be a file name or an openmm.System, got "
                                 f"{type(system).__name__}")
        sys_ = system
    n = sys_.getNumParticles()
    if isinstance(positions, (str, os.PathLike)):
        path = folder / Path(positions)
        structure = _named(lambda: oe.read_structure(path), fail, "positions")
        if len(structure.positions) != n:
            raise fail("positions", f"{path} holds {len(structure.positions)} particles, the "
                                    f"system {n}")
        return _named(lambda: oe.OpenMMEngine(sys_, structure.positions, box=structure.box,
                                              topology=structure.topology,
                                              labels=structure.labels), fail, "positions")
    if hasattr(positions, "value_in_unit"):
        positions = positions.value_in_unit(oe._openmm().unit.nanometer)
    return _named(lambda: oe.OpenMMEngine(sys_, positions), fail, "positions")


def _named(make: Callable[[], Any], fail: Callable[[str, str], StepsafeError], key: str) -> Any:
    """``make()``, its StepsafeError named after ``key`` (with the file it names)."""
    try:
        return make()
    except StepsafeError as exc:
        if exc.where and "::" in exc.where:
            raise
        raise fail(key, f"{exc.where}: {exc.message}" if exc.where else exc.message) from None


def prepare(engine: Any, chosen: Settings, fail: Callable[[str, str], StepsafeError], *,
            progress: Callable[[str, int, int | None], None] | None = None
            ) -> tuple[Any, Repartition | None, Any]:
    """The engine with the hydrogen masses repartitioned, the rule's constraints added
    and (if asked) minimised (OpenMM's ``LocalEnergyMinimizer`` on the CPU platform, one
    thread, where there is one; the Hessian is then taken on Reference):
    ``(engine, repartition, minimization)``. As in OpenMM's
    ``createSystem``, the masses are set before the positions are put on the new
    constraints (a mass-weighted projection), and the waters the System itself holds rigid
    keep their masses (``createSystem`` skips the waters its ``rigidWater`` makes rigid, not
    those its ``HAngles`` rule does). ``progress("minimize", iterations, None)`` follows the
    minimiser."""
    topology: Topology | None = engine.topology
    rule = None
    if chosen.constraints not in (None, "none"):
        if topology is None:
            raise fail("constraints", "a constraint rule needs the bonds and elements of a "
                                      "PDB or PDBx structure file (a State has none)")
        lengths, angles, values = engine.bonded_terms()
        missing = [(i, j) for i, j in topology.bonds.tolist()
                   if (min(i, j), max(i, j)) not in lengths]
        if missing:
            i, j = missing[0]
            raise fail("constraints", f"the structure's bond {engine.labels[i] or i}-"
                                      f"{engine.labels[j] or j} has no harmonic bond term or "
                                      "constraint in the System: its length is unknown")
        rule = constraints_for(chosen.constraints, topology,
                               [lengths[(min(i, j), max(i, j))]
                                for i, j in topology.bonds.tolist()], angles, values)
    done = None
    mass = chosen.hydrogen_mass
    if mass is not None:
        if topology is None:
            raise fail("hydrogen_mass", "hydrogen mass repartitioning needs the bonds and "
                                        "elements of a PDB or PDBx structure file")
        done = _named(lambda: repartition(engine.masses, topology, mass,
                                          keep_residues=rigid_waters(topology,
                                                                     engine.constraints)),
                      fail, "hydrogen_mass")
        engine = engine.with_masses(done.masses)
    if rule is not None:
        engine = _named(lambda: engine.with_constraints(rule), fail, "constraints")
    minimization = None
    if chosen.minimize:  # on the CPU platform (fast), then back on Reference for the Hessian
        try:
            fast = engine.at(engine.positions, platform="CPU", threads=1)
        except StepsafeError:  # no CPU platform here
            fast = engine
        minimization = fast.minimize(MINIMIZE_TOLERANCE, progress=progress)
        engine = engine.at(fast.positions)
    return engine, done, minimization


def analyse(engine: Any, chosen: Settings, repartitioned: Repartition | None = None,
            minimization: Any = None, *, dense_atoms: int | None = None,
            progress: Callable[[str, int, int | None], None] | None = None) -> MDAnalysis:
    """The modes of ``engine`` at its positions (see the module docstring).

    Parameters
    ----------
    engine : ForceEngine
        With ``topology`` and ``labels`` (an OpenMMEngine).
    chosen : Settings
    repartitioned, minimization :
        What :func:`prepare` did, for the record.
    dense_atoms : int, optional
        The dense Hessian up to this many moving particles (default :data:`DENSE_ATOMS`).
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    MDAnalysis
    """
    moving = mobile_particles(engine.masses)
    cons = engine.constraints
    rigid = 0
    if len(moving) <= (DENSE_ATOMS if dense_atoms is None else dense_atoms):
        h = hessian(engine, progress=progress)
        exclude = None
        # the whole system's rigid-body motions (every particle moves with it: no particle
        # held fixed); rotations only without periodic boundaries
        if not np.any((np.asarray(engine.masses) == 0) & ~np.asarray(engine.virtual_sites)):
            exclude = rigid_body_basis(h.positions, engine.masses, h.particles,
                                       rotations=not getattr(engine, "periodic", True))
            rigid = exclude.shape[1]
        sp = constrained_spectrum(h, cons, exclude=exclude)
        complete, step, rel, calls = True, h.step.step, h.step.relative_error, h.calls
        forces = h.forces
    else:
        hvp = HessianVectorProduct(engine, progress=progress)
        large = len(moving) > ONE_MODE_ATOMS
        k = 1 if large else min(FASTEST, hvp.dim - 1)
        tol = LARGE_TOL if large else LANCZOS_TOL
        sp = (constrained_modes(hvp, cons, k=k, tol=tol, which="magnitude") if len(cons)
              else extreme_eigenvalues(hvp, hvp.dim, k=k, tol=tol, which="magnitude",
                                       with_error=hvp.with_error, particles=hvp.particles))
        complete, step = False, hvp.fd.step
        rel, calls = hvp.fd.choice.relative_error, hvp.fd.calls
        forces = hvp.fd.f0
    f = np.asarray(forces, dtype=float).reshape(-1)
    if len(cons):
        f = ConstrainedSpace(cons, engine.positions, engine.masses, f).tangent_forces(f)
    rms = float(np.sqrt(np.mean(f ** 2))) if f.size else 0.0
    order = np.argsort(sp.eigenvalues)[::-1]
    fastest_first = Spectrum(sp.eigenvalues[order], sp.vectors[:, order], sp.errors[order],
                             sp.particles, sp.bound, sp.products, sp.removed)
    return MDAnalysis(fastest_first, complete,
                      describe(fastest_first, engine.labels, modes=FASTEST), engine.n_particles,
                      len(moving), len(cons), chosen, repartitioned, minimization, rms, step,
                      rel, calls, engine, rigid)


def eigenvalue_errors(analysis: MDAnalysis) -> np.ndarray:
    """The absolute error allowed each eigenvalue (rad^2/ps^2): Weyl's bound for a dense
    Hessian (no eigenvalue moves by more), else each Lanczos pair's residual and
    finite-difference estimate."""
    sp = analysis.spectrum
    if analysis.complete and np.isfinite(sp.bound):
        return np.maximum(np.full(len(sp.eigenvalues), sp.bound), sp.errors)
    return np.asarray(sp.errors, dtype=float)


def engine_check(analysis: MDAnalysis, method: str, step_ps: float) -> dict[str, Any]:
    """Short runs of ``method`` in OpenMM at ``step_ps`` from the configuration analysed,
    thermalised at ``runs.temperature`` (:mod:`~stepsafe.systems.md.enginerun`: 1 ps of
    LangevinMiddle with friction 10/ps at a step of at most half the 0 K limit, then the
    method for ``runs.duration`` ps per seed, CPU platform, one thread). The record says
    ``"stable"``, ``"drifts"`` (Verlet: mean energy drift beyond 0.01 kT/ps per degree of
    freedom) or ``"blew up"`` (a non-finite energy, OpenMM stopping, or the total energy
    moving by more than n_dof kT / 2), with each seed's outcome.

    Parameters
    ----------
    analysis : MDAnalysis
        With ``settings.runs``.
    method : str
        ``verlet`` or ``langevin-middle`` (:data:`ENGINE_INTEGRATORS`).
    step_ps : float
        The step, ps.

    Returns
    -------
    dict
        JSON-ready.
    """
    runs = analysis.settings.runs
    if runs is None:
        raise StepsafeError("no runs: were asked for")
    integrator = ENGINE_INTEGRATORS.get(method)
    if integrator is None:
        raise StepsafeError(f"runs: OpenMM runs {', '.join(ENGINE_INTEGRATORS)} only, not "
                            f"{method}")
    equilibration = min(0.001, 0.5 * analysis.spectrum.verlet_limit())
    spec = TrialSpec(integrator, step_ps, runs.duration, temperature=runs.temperature,
                     friction=runs.friction, seeds=runs.seeds, equilibration=1.0,
                     equilibration_step=equilibration)
    record = run_trials(analysis.engine.system_xml(), analysis.engine.state_xml(), spec)
    drift, error = record.drift()
    return {"integrator": integrator, "temperature": runs.temperature,
            "duration": runs.duration, "friction": runs.friction, "step_ps": step_ps,
            "seeds": list(runs.seeds), "verdict": record.verdict(),
            "drift": None if drift != drift else drift,
            "drift_error": None if error != error else error,
            "drift_tolerance": DRIFT_TOLERANCE,
            "runs": [{"seed": r.seed, "blew_up": r.blew_up, "step": r.blowup_step,
                      "reason": r.reason} for r in record.runs]}
