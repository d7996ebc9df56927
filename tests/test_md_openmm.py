"""The MD-engine core on OpenMM: finite-difference Hessians against analytic second
derivatives, the constraint projection against reduced coordinates, hydrogen mass
repartitioning and the constraint rules against OpenMM's own createSystem, and the
flexible-water O-H stretch. (The verdicts against OpenMM's own integrators:
test_md_validation.py and test_md_scene.py.)"""

from __future__ import annotations

import math
import os
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from md_support import (
    TIP3P,
    angle_hessian,
    bond_hessian,
    reduced_coordinate_frequencies,
    single_water_hessian,
    triatomic,
)

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.md import constraints as cs
from stepsafe.systems.md import hessian as hs
from stepsafe.systems.md import hmr
from stepsafe.systems.md import openmm_engine as oe

openmm = pytest.importorskip("openmm")
app = pytest.importorskip("openmm.app")
unit = pytest.importorskip("openmm.unit")

pytestmark = pytest.mark.openmm


@pytest.fixture(scope="session")
def built(tmp_path_factory):
    """Example systems written once per test session (per xdist worker)."""
    root = tmp_path_factory.mktemp("md-systems")

    @cache
    def make(kind, **kw):
        return oe.write_example_system(kind, root, **kw)

    return make


def masses_of(system):
    return np.array([system.getParticleMass(i).value_in_unit(unit.dalton)
                     for i in range(system.getNumParticles())])


# --- finite differences against analytic second derivatives --------------------------------

def test_fd_hessian_of_bonds_and_angles_matches_the_analytic_hessian():
    k_b, r_b = [3e5, 2.5e5, 4e5], [0.15, 0.14, 0.10]
    k_a, t_a = [500.0, 650.0], [1.9, 2.0]
    system = openmm.System()
    masses = [12.0, 14.0, 12.0, 1.0]
    for m in masses:
        system.addParticle(m)
    bonds = openmm.HarmonicBondForce()
    for (i, j), k, r0 in zip([(0, 1), (1, 2), (2, 3)], k_b, r_b):
        bonds.addBond(i, j, r0, k)
    angles = openmm.HarmonicAngleForce()
    for (i, j, k_), k, t0 in zip([(0, 1, 2), (1, 2, 3)], k_a, t_a):
        angles.addAngle(i, j, k_, t0, k)
    system.addForce(bonds)
    system.addForce(angles)
    x = np.array([[0.0, 0.0, 0.0], [0.16, 0.01, 0.0], [0.20, 0.145, 0.02], [0.31, 0.16, -0.03]])
    engine = oe.OpenMMEngine(system, x)
    h = hs.hessian(engine)
    exact = np.zeros((12, 12))
    for (i, j), k, r0 in zip([(0, 1), (1, 2), (2, 3)], k_b, r_b):
        idx = np.r_[3 * i:3 * i + 3, 3 * j:3 * j + 3]
        exact[np.ix_(idx, idx)] += bond_hessian(x[i], x[j], k, r0)
    for (i, j, k_), k, t0 in zip([(0, 1, 2), (1, 2, 3)], k_a, t_a):
        idx = np.r_[3 * i:3 * i + 3, 3 * j:3 * j + 3, 3 * k_:3 * k_ + 3]
        exact[np.ix_(idx, idx)] += angle_hessian(x[i], x[j], x[k_], k, t0)
    assert np.abs(h.matrix - exact).max() <= 1e-6 * np.abs(exact).max()
    sp = hs.spectrum(h)
    s = 1 / np.repeat(np.sqrt(masses), 3)
    want = np.linalg.eigvalsh(s[:, None] * exact * s[None, :])[::-1]
    assert np.all(np.abs(sp.eigenvalues - want) <= sp.bound)
    # OpenMM's Reference platform is double precision: the step control reaches 1e-7
    assert h.step.relative_error < 1e-6


def test_virtual_site_forces_reach_their_parents():
    """Two flexible TIP4P-Ew waters (a massless M site each): the Hessian from forces equals
    second differences of the energy over the 6 real atoms; the M sites are no coordinates."""
    ff = app.ForceField("tip4pew.xml")
    top = app.Topology()
    chain = top.addChain()
    pos = []
    for shift in (0.0, 0.29):
        res = top.addResidue("HOH", chain)
        o = top.addAtom("O", app.element.oxygen, res)
        h1 = top.addAtom("H1", app.element.hydrogen, res)
        h2 = top.addAtom("H2", app.element.hydrogen, res)
        top.addAtom("M", None, res)
        top.addBond(o, h1)
        top.addBond(o, h2)
        pos += [[shift, 0, 0], [shift + 0.0957, 0, 0], [shift - 0.024, 0.0927, 0],
                [shift, 0, 0]]
    system = ff.createSystem(top, nonbondedMethod=app.NoCutoff, rigidWater=False)
    engine = oe.OpenMMEngine(system, np.array(pos, dtype=float) + [0, 0, 0.01])
    assert engine.virtual_sites.tolist() == [False, False, False, True] * 2
    assert engine.masses[3] == 0 and engine.masses[7] == 0
    h = hs.hessian(engine)
    assert h.particles.tolist() == [0, 1, 2, 4, 5, 6]
    x0 = engine.positions.copy()
    step = 1e-4
    ref = np.zeros((18, 18))
    coords = [(p, a) for p in h.particles for a in range(3)]
    for i, (pi, ai) in enumerate(coords):
        for j, (pj, aj) in enumerate(coords):
            if j < i:
                continue
            total = 0.0
            for si, sj, sign in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
                x = x0.copy()
                x[pi, ai] += si * step
                x[pj, aj] += sj * step
                total += sign * engine.energy(x)
            ref[i, j] = ref[j, i] = total / (4 * step * step)
    # energy second differences carry ~1e-9 kJ/mol rounding / 4e-8 nm^2 plus O(step^2)
    assert np.abs(h.matrix - ref).max() <= 1e-4 * np.abs(ref).max()


# --- constraints ---------------------------------------------------------------------------

def test_constraint_projection_equals_reduced_coordinates_for_an_openmm_triatomic():
    net, p = triatomic()
    system = openmm.System()
    for m in p["masses"]:
        system.addParticle(m)
    bonds = openmm.HarmonicBondForce()
    for (i, j), k, r0 in zip([(0, 1), (1, 2), (0, 2)], [p["k_ab"], p["k_bc"], p["k_ac"]],
                             [p["r0_ab"], p["r_bc"], p["r_ac"]]):
        bonds.addBond(i, j, r0, k)
    system.addForce(bonds)
    system.addConstraint(0, 1, p["d"])
    engine = oe.OpenMMEngine(system, net.positions)
    assert len(engine.constraints) == 1
    sp = cs.constrained_spectrum(hs.hessian(engine), engine.constraints)
    want = reduced_coordinate_frequencies(p)
    assert np.all(np.abs(sp.eigenvalues - want) <= sp.bound + 1e-9 * max(want))
    assert np.allclose(sp.eigenvalues, want, rtol=0, atol=1e-7 * max(want))


def reference_terms(top_system):
    lengths, angles = {}, {}
    for f in top_system.getForces():
        if isinstance(f, openmm.HarmonicBondForce):
            for n in range(f.getNumBonds()):
                i, j, r0, _ = f.getBondParameters(n)
                lengths[(min(i, j), max(i, j))] = r0.value_in_unit(unit.nanometer)
        if isinstance(f, openmm.HarmonicAngleForce):
            for n in range(f.getNumAngles()):
                i, j, k, t0, _ = f.getAngleParameters(n)
                angles[(min(i, k), j, max(i, k))] = t0.value_in_unit(unit.radian)
    return lengths, angles


@pytest.fixture(scope="module")
def villin_with_water(tmp_path_factory):
    pdb = app.PDBFile(os.path.join(os.path.dirname(app.__file__), "data", "test.pdb"))
    model = app.Modeller(pdb.topology, pdb.positions)
    waters = [r for r in model.topology.residues() if r.name == "HOH"]
    model.delete(waters[20:] + [r for r in model.topology.residues()
                                if r.name in ("NA", "CL", "Na", "Cl")])
    path = tmp_path_factory.mktemp("villin") / "villin-water.pdb"
    with open(path, "w") as fh:
        app.PDBFile.writeFile(model.topology, model.positions, fh)
    ff = app.ForceField("amber14-all.xml", "amber14/tip3p.xml")
    return model, ff, oe.read_structure(path)


@pytest.mark.parametrize("kind", cs.KINDS)
def test_constraint_rules_match_openmm_create_system(villin_with_water, kind):
    model, ff, structure = villin_with_water
    flexible = ff.createSystem(model.topology, nonbondedMethod=app.NoCutoff, constraints=None,
                               rigidWater=False)
    lengths, angle_values = reference_terms(flexible)
    top = structure.topology
    bond_lengths = [lengths[(min(i, j), max(i, j))] for i, j in top.bonds.tolist()]
    angles = cs.angles_of(top)
    values = [angle_values[(i, j, k)] for i, j, k in angles.tolist()]
    ours = cs.constraints_for(kind, top, bond_lengths, angles, values, rigid_water=True)
    option = {"none": None, "h-bonds": app.HBonds, "all-bonds": app.AllBonds,
              "h-angles": app.HAngles}[kind]
    system = ff.createSystem(model.topology, nonbondedMethod=app.NoCutoff, constraints=option)
    theirs = {}
    for n in range(system.getNumConstraints()):
        i, j, d = system.getConstraintParameters(n)
        theirs[(min(i, j), max(i, j))] = d.value_in_unit(unit.nanometer)
    mine = {(min(i, j), max(i, j)): d for (i, j), d in zip(ours.pairs.tolist(), ours.distances)}
    assert mine.keys() == theirs.keys()
    assert all(mine[key] == pytest.approx(theirs[key], rel=1e-12) for key in mine)


# --- hydrogen mass repartitioning ----------------------------------------------------------

@pytest.mark.parametrize("rigid", [None, False])
@pytest.mark.parametrize("constraints", [None, "HBonds"])
def test_hmr_matches_openmm_hydrogen_mass(villin_with_water, rigid, constraints):
    model, ff, structure = villin_with_water
    option = getattr(app, constraints) if constraints else None
    kw = dict(nonbondedMethod=app.NoCutoff, constraints=option, rigidWater=rigid)
    plain = ff.createSystem(model.topology, **kw)
    heavy = ff.createSystem(model.topology, hydrogenMass=3 * unit.amu, **kw)
    engine = oe.OpenMMEngine(plain, structure.positions, topology=structure.topology)
    keep = hmr.rigid_waters(structure.topology, engine.constraints)
    assert len(keep) == (20 if rigid is None else 0)
    ours = hmr.repartition(engine.masses, structure.topology, 3.0, keep_residues=keep)
    np.testing.assert_allclose(ours.masses, masses_of(heavy), rtol=1e-14, atol=0)
    moved = engine.with_masses(ours.masses)
    np.testing.assert_array_equal(moved.masses, ours.masses)
    np.testing.assert_array_equal(moved.forces(moved.positions), engine.forces(moved.positions))


# --- flexible water ------------------------------------------------------------------------

def isolated_tip3p_stretch():
    """omega^2 (rad^2/ps^2) of the antisymmetric O-H stretch of one TIP3P molecule at its
    minimum: the largest eigenvalue of the analytic mass-weighted Hessian."""
    p = TIP3P
    t = p["theta0"]
    x = np.array([[0, 0, 0], [p["r0"], 0, 0], [p["r0"] * math.cos(t), p["r0"] * math.sin(t), 0]])
    s = 1 / np.repeat(np.sqrt([p["mO"], p["mH"], p["mH"]]), 3)
    return np.linalg.eigvalsh(s[:, None] * single_water_hessian(x) * s[None, :])[-1]


def test_one_flexible_water_in_openmm_has_the_analytic_spectrum():
    ff = app.ForceField("amber14/tip3p.xml")
    top = app.Topology()
    res = top.addResidue("HOH", top.addChain())
    o = top.addAtom("O", app.element.oxygen, res)
    h1 = top.addAtom("H1", app.element.hydrogen, res)
    h2 = top.addAtom("H2", app.element.hydrogen, res)
    top.addBond(o, h1)
    top.addBond(o, h2)
    system = ff.createSystem(top, nonbondedMethod=app.NoCutoff, rigidWater=False)
    x = np.array([[0.01, 0.0, 0.0], [0.105, 0.003, 0.0], [-0.015, 0.09, 0.002]])   # off minimum
    engine = oe.OpenMMEngine(system, x)
    sp = hs.spectrum(hs.hessian(engine))
    s = 1 / np.repeat(np.sqrt(engine.masses), 3)
    want = np.linalg.eigvalsh(s[:, None] * single_water_hessian(x) * s[None, :])[::-1]
    assert np.all(np.abs(sp.eigenvalues - want) <= sp.bound)


@pytest.fixture(scope="module")
def water_minimum(built):
    """The water box minimised on the CPU platform, then evaluated on Reference."""
    cpu = oe.load(*built("water"), platform="CPU", threads=1)
    cpu.minimize(1.0)
    return cpu.at(cpu.positions, platform="Reference")


@pytest.mark.slow
def test_largest_frequency_of_the_water_box_is_the_tip3p_stretch(water_minimum):
    """129 flexible TIP3P waters with PME at their minimum: the fastest mode is an O-H stretch
    within 1% of the isolated molecule's antisymmetric stretch (hydrogen bonds shift it by a
    fraction of a percent), its kinetic energy carried by hydrogens (an isolated O-H stretch
    puts m_O / (m_O + m_H) = 94% on H)."""
    engine = water_minimum
    assert engine.n_particles == 387
    sp = hs.largest_modes(engine, k=2, tol=1e-6)
    lam_free = isolated_tip3p_stretch()
    assert abs(sp.eigenvalues[0] / lam_free - 1) < 0.01
    assert sp.errors[0] < 1e-6 * sp.eigenvalues[0]
    hydrogen = np.array([engine.topology.elements[i] == "H" for i in sp.particles])
    assert sp.participation(0)[hydrogen].sum() > 0.9
    (mode,) = hs.describe(sp, engine.labels, modes=1, share=0.9)
    assert mode.atoms[0][1].endswith((":H1", ":H2"))
    assert mode.wavenumber == pytest.approx(sp.wavenumbers[0])


# --- files and errors ----------------------------------------------------------------------

def test_engine_reads_a_state_xml_and_refuses_bad_files(built, tmp_path):
    xml, pdb = built("water")
    engine = oe.load(xml, pdb)
    state = tmp_path / "state.xml"
    state.write_text(engine.state_xml())
    again = oe.load(xml, state)
    np.testing.assert_array_equal(again.positions, engine.positions)
    np.testing.assert_array_equal(again.forces(again.positions), engine.forces(engine.positions))
    with pytest.raises(StepsafeError, match="not found") as err:
        oe.load(tmp_path / "missing.xml", pdb)
    assert err.value.where == str(tmp_path / "missing.xml")
    junk = tmp_path / "junk.xml"
    junk.write_text("<System")
    with pytest.raises(StepsafeError, match="not an OpenMM XML"):
        oe.load(junk, pdb)
    with pytest.raises(StepsafeError, match="not a System"):
        oe.load(state, pdb)
    villin_xml, villin_pdb = built("villin")
    with pytest.raises(StepsafeError, match="holds 582 particles, the system 387"):
        oe.load(xml, villin_pdb)
    with pytest.raises(StepsafeError, match="positions must be"):
        oe.load(xml, Path(str(pdb).replace(".pdb", ".gro")))
    with pytest.raises(StepsafeError, match="unknown platform"):
        oe.load(xml, pdb, platform="GPU")


@pytest.mark.slow
def test_constrained_villin_keeps_the_heavy_atom_modes(built):
    """Villin (the PDB structure, put on the constraints, not minimised) with h-bond
    constraints: every X-H stretch is gone from the fastest modes, which now move heavy atoms,
    and the limit rises well above the unconstrained one."""
    free = hs.largest_modes(oe.load(*built("villin")), k=1, tol=1e-4)
    xml, pdb = built("villin", constraints="h-bonds")
    engine = oe.load(xml, pdb)
    assert len(engine.constraints) == sum(1 for i, j in engine.topology.bonds.tolist()
                                          if "H" in (engine.topology.elements[i],
                                                     engine.topology.elements[j]))
    sp = cs.constrained_modes(hs.HessianVectorProduct(engine), engine.constraints, k=3,
                              tol=1e-4)
    assert sp.removed == len(engine.constraints)
    assert sp.verlet_limit() > 1.5 * free.verlet_limit()
    for mode in hs.describe(sp, engine.labels, modes=3, share=0.5):
        heaviest = mode.atoms[0][0]
        assert engine.topology.elements[heaviest] != "H"
