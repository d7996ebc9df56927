"""The MD-engine core without an engine: finite-difference Hessians, Lanczos, the constraint
projection, the constraint rules, hydrogen mass repartitioning and the trial-run bookkeeping,
checked on a hand-written harmonic force engine against exact or 50-digit values."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from md_support import HarmonicNetwork, reduced_coordinate_frequencies, triatomic

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.md import constraints as cs
from stepsafe.systems.md import enginerun as er
from stepsafe.systems.md import hessian as hs
from stepsafe.systems.md import hmr
from stepsafe.systems.md.engine import (
    DistanceConstraints,
    ForceEngine,
    Topology,
    as_positions,
    engine_missing,
    mobile_particles,
)

SLOW = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def networks(draw, max_atoms=6, constrained=False):
    """A random connected harmonic network at a random length, stiffness and mass scale."""
    n = draw(st.integers(2, max_atoms))
    seed = draw(st.integers(0, 2**32 - 1))
    scale = 10.0 ** draw(st.floats(-3, 3))
    stiff = 10.0 ** draw(st.floats(-2, 6))
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 3)) * scale
    m = 10.0 ** rng.uniform(-1, 3, n)
    bonds = [(i, int(rng.integers(0, i))) for i in range(1, n)]
    r = np.array([np.linalg.norm(x[i] - x[j]) for i, j in bonds])
    k = stiff * 10.0 ** rng.uniform(-1, 1, len(bonds))
    r0 = r * rng.uniform(0.5, 1.5, len(bonds))
    return HarmonicNetwork(x, m, bonds, k, r0)


def mass_weighted(h, masses):
    s = 1.0 / np.repeat(np.sqrt(masses), 3)
    return s[:, None] * h * s[None, :]


def test_the_hand_written_engine_is_a_force_engine():
    net = HarmonicNetwork([[0, 0, 0], [0.1, 0, 0]], [1.0, 2.0], [(0, 1)], 100.0, 0.12)
    assert isinstance(net, ForceEngine)


@SLOW
@given(networks())
def test_fd_hessian_eigenvalues_within_the_stated_bound(net):
    h = hs.hessian(net)
    sp = hs.spectrum(h)
    exact = np.linalg.eigvalsh(mass_weighted(net.exact_hessian(), net.masses))[::-1]
    assert np.all(np.abs(sp.eigenvalues - exact) <= sp.bound)
    # and the bound is a small fraction of the spectrum: the step control found a good step
    assert sp.bound <= 1e-5 * np.abs(exact).max()


@SLOW
@given(networks())
def test_fd_hessian_matches_exact_entries_to_its_relative_error(net):
    h = hs.hessian(net)
    exact = net.exact_hessian()
    assert np.abs(h.matrix - exact).max() <= 1e-6 * np.abs(exact).max()


@SLOW
@given(networks(max_atoms=12))
def test_lanczos_largest_modes_agree_with_the_exact_spectrum(net):
    exact = np.linalg.eigvalsh(mass_weighted(net.exact_hessian(), net.masses))[::-1]
    k = min(3, len(exact) - 1)
    sp = hs.largest_modes(net, k=k, tol=1e-10)
    top = exact[:k]
    # a Ritz value never exceeds the operator's largest eigenvalue (here up to FD error)
    assert sp.eigenvalues[0] <= top[0] + 1e-6 * abs(top[0])
    assert np.all(np.abs(sp.eigenvalues - top) <= sp.errors + 1e-7 * abs(top[0]))
    assert sp.products > 0


@settings(max_examples=40, deadline=None)
@given(st.integers(5, 60), st.integers(0, 2**32 - 1), st.floats(-200, 200))
def test_lanczos_on_a_matrix_with_known_spectrum(n, seed, log_scale):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    lam = np.sort(rng.uniform(-1, 1, n))[::-1] * 10.0 ** (log_scale / 10)
    a = (q * lam) @ q.T
    for which, want in (("largest", lam[:2]), ("smallest", lam[::-1][:2])):
        sp = hs.extreme_eigenvalues(lambda v: a @ v, n, k=2, which=which, tol=1e-12)
        gap = np.abs(lam).max()
        assert np.allclose(sp.eigenvalues, want, rtol=0, atol=1e-9 * gap)
        assert np.all(np.abs(sp.eigenvalues - want) <= sp.errors + 1e-12 * gap)


def test_lanczos_start_vector_is_fixed():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((40, 40))
    a = a + a.T
    one = hs.extreme_eigenvalues(lambda v: a @ v, 40, k=3)
    two = hs.extreme_eigenvalues(lambda v: a @ v, 40, k=3)
    assert np.array_equal(one.eigenvalues, two.eigenvalues)
    assert one.products == two.products


def test_lanczos_refuses_impossible_requests():
    with pytest.raises(StepsafeError, match="k must be"):
        hs.extreme_eigenvalues(lambda v: v, 3, k=3)
    with pytest.raises(StepsafeError, match="which"):
        hs.extreme_eigenvalues(lambda v: v, 9, k=1, which="middle")


def test_a_force_jump_inside_the_stencil_is_stepped_around():
    """A force with a jump at a plain cutoff: the product is formed again with a smaller step
    and comes out as the smooth part's."""

    class Cutoff(HarmonicNetwork):
        def forces(self, x):
            f = super().forces(x)
            if x[1, 0] - x[0, 0] > self.cut:        # a 5 kJ/mol/nm jump beyond the cutoff
                f[1, 0] += 5.0
                f[0, 0] -= 5.0
            return f

    net = Cutoff([[0, 0, 0], [0.1, 0, 0]], [16.0, 1.0], [(0, 1)], 4e5, 0.1)
    net.cut = np.inf
    fd = hs.ForceDifferences(net, step=1e-6)
    assert fd.choice.step == 1e-6
    net.cut = 0.1 + 0.4e-6       # inside (x - eps, x + eps) along +x of atom 1
    u = np.zeros(6)
    u[3] = 1.0
    hu, err = fd.product(u)
    exact = net.exact_hessian()[:, 3]
    assert fd.retries >= 1
    assert np.abs(hu - exact).max() <= 1e-6 * 4e5
    assert np.all(np.abs(hu - exact) <= err + 1e-9 * 4e5)


def test_step_control_refuses_noisy_forces():
    class Noisy(HarmonicNetwork):
        def forces(self, x):
            return super().forces(x) + np.random.default_rng().standard_normal(x.shape) * 1e3

    net = Noisy([[0, 0, 0], [0.1, 0, 0]], [16.0, 1.0], [(0, 1)], 4e5, 0.1)
    with pytest.raises(StepsafeError, match="not smooth or precise enough"):
        hs.choose_step(hs.ForceDifferences(net, step=1e-3))


def test_particles_of_mass_zero_are_not_degrees_of_freedom():
    net = HarmonicNetwork([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0]], [16.0, 1.0, 0.0],
                          [(0, 1), (1, 2)], 4e5, [0.1, 0.09])
    h = hs.hessian(net)
    assert list(h.particles) == [0, 1]
    assert h.matrix.shape == (6, 6)
    assert np.allclose(h.matrix, net.exact_hessian()[:6, :6], rtol=0, atol=1e-6 * 4e5)


def test_spectrum_units_and_verlet_limit():
    """One O-H-like bond: omega^2 = k/mu, limit 2/omega, wavenumber omega/(2 pi c)."""
    k, m1, m2 = 462750.4, 15.99943, 1.007947
    net = HarmonicNetwork([[0, 0, 0], [0.09572, 0, 0]], [m1, m2], [(0, 1)], k, 0.09572)
    sp = hs.spectrum(hs.hessian(net), k=1)
    mu = m1 * m2 / (m1 + m2)
    omega = math.sqrt(k / mu)
    assert sp.omega[0] == pytest.approx(omega, rel=1e-8)
    assert sp.verlet_limit() == pytest.approx(2 / omega, rel=1e-8)
    assert sp.wavenumbers[0] == pytest.approx(omega / (2 * math.pi * 0.0299792458), rel=1e-8)
    share = sp.participation(0)
    assert share.sum() == pytest.approx(1.0)
    assert share[1] == pytest.approx(m1 / (m1 + m2), rel=1e-8)    # the light atom moves
    (report,) = hs.describe(sp, net.labels, modes=1, share=0.9)
    assert report.atoms[0][:2] == (1, "A1")


# --- constraints --------------------------------------------------------------------------

def test_constrained_spectrum_equals_reduced_coordinates_at_a_stressed_equilibrium():
    net, p = triatomic()
    sp = cs.constrained_spectrum(hs.hessian(net), net.constraints)
    want = reduced_coordinate_frequencies(p)
    assert sp.removed == 1 and len(sp.eigenvalues) == 8
    scale = max(want)
    assert np.allclose(sp.eigenvalues, want, rtol=0, atol=1e-7 * scale)
    assert np.all(np.abs(sp.eigenvalues - want) <= sp.bound + 1e-9 * scale)
    # the curvature term matters: without it the rotations and the bend are wrong
    space = cs.ConstrainedSpace(net.constraints, net.positions, net.masses,
                                net.forces(net.positions).reshape(-1))
    assert abs(space.multipliers[0]) == pytest.approx(p["k_ab"] * (p["r0_ab"] - p["d"]),
                                                      rel=1e-12)
    h = hs.hessian(net)
    w, _ = h.mass_weighted()
    q = space.basis()
    plain = np.sort(np.linalg.eigvalsh(q.T @ w @ q))[::-1]
    assert np.abs(plain - want).max() > 1e-3 * scale


@SLOW
@given(st.integers(3, 7), st.integers(0, 2**32 - 1), st.floats(0.5, 1.5))
def test_a_term_along_a_constrained_bond_changes_nothing(n, seed, stretch):
    """At any configuration on the constraints, a harmonic term on a constrained bond
    (stretched or not) leaves the constrained spectrum unchanged: the projection removes its
    longitudinal part, the multiplier's curvature cancels its transverse part."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 3)) * 0.15
    m = 10.0 ** rng.uniform(0, 1.5, n)
    bonds = [(i, int(rng.integers(0, i))) for i in range(1, n)]
    r = np.array([np.linalg.norm(x[i] - x[j]) for i, j in bonds])
    k = 10.0 ** rng.uniform(4, 5.5, len(bonds))
    r0 = r * rng.uniform(0.8, 1.2, len(bonds))
    c = DistanceConstraints([bonds[0]], [r[0]])
    with_term = HarmonicNetwork(x, m, bonds, k, np.r_[r[0] * stretch, r0[1:]], constraints=c)
    without = HarmonicNetwork(x, m, bonds[1:], k[1:], r0[1:], constraints=c)
    a = cs.constrained_spectrum(hs.hessian(with_term), c)
    b = cs.constrained_spectrum(hs.hessian(without), c)
    scale = np.abs(b.eigenvalues).max()
    assert np.allclose(a.eigenvalues, b.eigenvalues, rtol=0, atol=1e-6 * scale)


@SLOW
@given(st.integers(4, 10), st.integers(0, 2**32 - 1))
def test_constrained_lanczos_agrees_with_the_dense_tangent_space(n, seed):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, 3)) * 0.15
    m = 10.0 ** rng.uniform(0, 1.5, n)
    bonds = [(i, int(rng.integers(0, i))) for i in range(1, n)]
    r = np.array([np.linalg.norm(x[i] - x[j]) for i, j in bonds])
    chosen = rng.choice(len(bonds), size=max(1, len(bonds) // 2), replace=False)
    c = DistanceConstraints([bonds[i] for i in chosen], r[chosen])
    net = HarmonicNetwork(x, m, bonds, 10.0 ** rng.uniform(4, 5.5, len(bonds)),
                          r * rng.uniform(0.8, 1.2, len(bonds)), constraints=c)
    dense = cs.constrained_spectrum(hs.hessian(net), c)
    lanczos = cs.constrained_modes(hs.HessianVectorProduct(net), c, k=2, tol=1e-12)
    scale = abs(dense.eigenvalues[0])
    assert np.allclose(lanczos.eigenvalues, dense.eigenvalues[:2], rtol=0, atol=1e-6 * scale)
    assert lanczos.removed == len(c)
    # eigenvectors lie in the tangent space: J v = 0
    space = cs.ConstrainedSpace(c, net.positions, net.masses, net.forces(net.positions).ravel())
    assert np.abs(space.J @ lanczos.vectors).max() <= 1e-8


def test_positions_off_the_constraints_are_refused():
    net, _ = triatomic()
    c = DistanceConstraints([[0, 1]], [0.2])
    with pytest.raises(StepsafeError, match="violate the constraint"):
        cs.constrained_spectrum(hs.hessian(net), c)


def test_a_constraint_to_a_fixed_particle_acts_as_a_wall():
    """A pendulum: particle 1 (mass m) on a rod of length L from a fixed particle 0, pulled
    outward by a spring to a far anchor (force f along the rod): omega^2 = f / (m L) for the
    two swinging directions, and the rod removes the radial one."""
    L, m, kk, far = 0.2, 3.0, 1000.0, 0.5
    x = np.array([[0, 0, 0], [L, 0, 0], [L + far, 0, 0]])
    c = DistanceConstraints([[0, 1]], [L])
    # spring 1-2 with rest length far - 0.1: tension f = kk * 0.1 pulls 1 away from 0
    net = HarmonicNetwork(x, [0.0, m, 0.0], [(1, 2)], kk, far - 0.1, constraints=c)
    sp = cs.constrained_spectrum(hs.hessian(net), c)
    f = kk * 0.1
    # the swing frequency f/(m L) and the spring's transverse stiffness f/(m far)
    assert sp.removed == 1 and len(sp.eigenvalues) == 2
    assert np.allclose(sp.eigenvalues, [f / m * (1 / L + 1 / far)] * 2, rtol=1e-7)


# --- the constraint rules ------------------------------------------------------------------

def methanol():
    """C0 O1 H2 (on O) H3 H4 H5 (on C), bonds with lengths, and all angles."""
    el = ("C", "O", "H", "H", "H", "H")
    bonds = [(0, 1), (1, 2), (0, 3), (0, 4), (0, 5)]
    top = Topology(el, bonds, ("MOH",) * 6, [0] * 6)
    lengths = [0.143, 0.096, 0.109, 0.1091, 0.1092]
    return top, lengths


def test_constraint_rules_pick_openmm_bonds_and_angles():
    top, lengths = methanol()
    angles = cs.angles_of(top)
    assert angles.tolist() == [[0, 1, 2], [1, 0, 3], [1, 0, 4], [1, 0, 5], [3, 0, 4], [3, 0, 5],
                               [4, 0, 5]]
    theta = np.full(len(angles), 1.9)
    assert len(cs.constraints_for("none", top, lengths, angles, theta)) == 0
    hb = cs.constraints_for("h-bonds", top, lengths, angles, theta)
    assert hb.pairs.tolist() == [[1, 2], [0, 3], [0, 4], [0, 5]]
    assert hb.distances.tolist() == lengths[1:]
    assert cs.constraints_for("all-bonds", top, lengths, angles, theta).pairs.tolist() == \
        [list(b) for b in top.bonds.tolist()]
    ha = cs.constraints_for("h-angles", top, lengths, angles, theta)
    # all bonds; H-O-C has an oxygen centre and one H end: constrained (C...H2); H-C-O has a
    # carbon centre and one H end: not; the three H-C-H angles: constrained
    extra = ha.pairs.tolist()[5:]
    assert extra == [[0, 2], [3, 4], [3, 5], [4, 5]]
    l1, l2 = 0.143, 0.096
    assert ha.distances[5] == pytest.approx(math.sqrt(l1**2 + l2**2 - 2 * l1 * l2 * math.cos(1.9)),
                                            rel=1e-15)


def test_constraint_rules_make_water_rigid_on_request():
    top = Topology(("O", "H", "H"), [(0, 1), (0, 2)], ("HOH",) * 3, [0, 0, 0])
    angles = cs.angles_of(top)
    c = cs.constraints_for("none", top, [0.09572, 0.09572], angles, [1.82421813418],
                           rigid_water=True)
    assert c.pairs.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert c.distances[2] == pytest.approx(2 * 0.09572 * math.sin(1.82421813418 / 2), rel=1e-14)


def test_constraint_rules_refuse_bad_input():
    top, lengths = methanol()
    with pytest.raises(StepsafeError, match="unknown constraints"):
        cs.constraints_for("hbonds", top, lengths)
    with pytest.raises(StepsafeError, match="bond lengths"):
        cs.constraints_for("h-bonds", top, lengths[:2])


# --- hydrogen mass repartitioning ----------------------------------------------------------

def test_hmr_takes_the_mass_from_the_bonded_heavy_atom():
    top, _ = methanol()
    m = np.array([12.01, 16.00, 1.008, 1.008, 1.008, 1.008])
    r = hmr.repartition(m, top, 3.0)
    assert r.masses.tolist() == pytest.approx([12.01 - 3 * (3 - 1.008), 16.0 - (3 - 1.008),
                                               3, 3, 3, 3], rel=1e-15)
    assert r.masses.sum() == pytest.approx(m.sum(), rel=1e-15)
    assert r.hydrogens.tolist() == [2, 3, 4, 5] and r.donors.tolist() == [0, 1]


def test_hmr_leaves_rigid_water_alone_and_repartitions_flexible_water():
    top = Topology(("O", "H", "H", "O", "H", "H"), [(0, 1), (0, 2), (3, 4), (3, 5)],
                   ("HOH",) * 6, [0, 0, 0, 1, 1, 1])
    rigid = DistanceConstraints([[0, 1], [0, 2], [1, 2]], [0.1, 0.1, 0.15])
    keep = hmr.rigid_waters(top, rigid)
    assert keep == {0}
    m = np.array([15.99943, 1.007947, 1.007947] * 2)
    r = hmr.repartition(m, top, 3.0, keep_residues=keep)
    assert r.masses[:3].tolist() == m[:3].tolist()
    assert r.masses[3:].tolist() == pytest.approx([15.99943 - 2 * (3 - 1.007947), 3, 3])


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 12), st.integers(0, 2**32 - 1), st.floats(0.5, 4.0))
def test_hmr_conserves_mass_and_sets_every_bonded_hydrogen(n, seed, target):
    rng = np.random.default_rng(seed)
    el = tuple(rng.choice(["H", "C", "N", "O"], n, p=[0.5, 0.2, 0.15, 0.15]).tolist())
    bonds = [(i, int(rng.integers(0, i))) for i in range(1, n)]
    mass_of = {"H": 1.008, "C": 12.011, "N": 14.007, "O": 15.999}
    m = np.array([mass_of[e] for e in el])
    top = Topology(el, bonds, ("RES",) * n, [0] * n)
    try:
        r = hmr.repartition(m, top, target)
    except StepsafeError as exc:
        assert "leaves atom" in str(exc)
        return
    assert r.masses.sum() == pytest.approx(m.sum(), rel=1e-12)
    for a, b in bonds:
        for h_, x_ in ((a, b), (b, a)):
            if el[h_] == "H" and el[x_] != "H":
                assert r.masses[h_] == target
    assert np.all(r.masses > 0)


def test_hmr_refuses_a_mass_that_empties_the_heavy_atom():
    top, _ = methanol()
    m = np.array([12.01, 16.00, 1.008, 1.008, 1.008, 1.008])
    with pytest.raises(StepsafeError, match="leaves atom 0"):
        hmr.repartition(m, top, 6.0)        # 12.01 - 3 (6 - 1.008) < 0
    for bad in (0, -1, float("nan"), "x"):
        with pytest.raises(StepsafeError, match="hydrogen mass"):
            hmr.repartition(m, top, bad)


# --- the engine interface ------------------------------------------------------------------

def test_engine_data_validation():
    with pytest.raises(StepsafeError, match="to itself"):
        DistanceConstraints([[1, 1]], [0.1])
    with pytest.raises(StepsafeError, match="positive and finite"):
        DistanceConstraints([[0, 1]], [0.0])
    with pytest.raises(StepsafeError, match="distances"):
        DistanceConstraints([[0, 1]], [0.1, 0.2])
    with pytest.raises(StepsafeError, match="twice"):
        DistanceConstraints([[0, 1], [1, 0]], [0.1, 0.1]).check_indices(2)
    with pytest.raises(StepsafeError, match="names particle 5"):
        DistanceConstraints([[0, 5]], [0.1]).check_indices(3)
    with pytest.raises(StepsafeError, match="outside"):
        Topology(("C", "H"), [(0, 2)], ("A", "A"), [0, 0])
    with pytest.raises(StepsafeError, match="shape"):
        as_positions(np.zeros((2, 2)), 2)
    with pytest.raises(StepsafeError, match="finite"):
        as_positions([[0, 0, float("nan")]], 1)
    with pytest.raises(StepsafeError, match="not negative"):
        mobile_particles([1.0, -1.0])
    assert mobile_particles([0.0, 2.0, 0.0, 1.0]).tolist() == [1, 3]


def test_missing_openmm_names_the_extra(monkeypatch, tmp_path):
    from stepsafe.systems.md import openmm_engine

    for name in ("openmm", "openmm.app", "openmm.unit"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(StepsafeError, match=r"pip install 'stepsafe\[openmm\]'"):
        openmm_engine.load(tmp_path / "system.xml", tmp_path / "x.pdb")
    assert "stepsafe[openmm]" in str(engine_missing("openmm"))


def test_md_modules_do_not_import_openmm():
    code = ("import sys\n"
            "import stepsafe.systems.md.engine, stepsafe.systems.md.hessian, "
            "stepsafe.systems.md.constraints, stepsafe.systems.md.hmr, "
            "stepsafe.systems.md.enginerun, stepsafe.systems.md.openmm_engine, "
            "stepsafe.systems.md.system\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('openmm', 'scipy')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert json.loads(out.replace("'", '"')) == []


# --- trial-run bookkeeping -----------------------------------------------------------------

def test_energy_fit_recovers_an_exact_line():
    t = list(np.linspace(0, 2, 50))
    slope, err, rms = er._fit(t, [3.0 - 0.25 * v for v in t])
    assert slope == pytest.approx(-0.25, rel=1e-12) and err < 1e-12 and rms < 1e-12


def test_trial_spec_validation():
    with pytest.raises(StepsafeError, match="unknown integrator"):
        er.TrialSpec("leapfrog", 0.001, 1.0)
    with pytest.raises(StepsafeError, match="step"):
        er.TrialSpec("verlet", -0.001, 1.0)
    with pytest.raises(StepsafeError, match="seeds"):
        er.TrialSpec("verlet", 0.001, 1.0, seeds=(1, 1))
    assert er.TrialSpec("verlet", 0.001, 1.0, sample_every=7).steps % 7 == 0


SYSTEM_XML = """<?xml version="1.0" ?>
<System openmmVersion="8.6.1" type="System" version="1">
  <Particles><Particle mass="16"/><Particle mass="1.008"/><Particle mass="1.008"/>
  <Particle mass="0"/></Particles>
  <Constraints><Constraint d=".1" p1="0" p2="1"/></Constraints>
  <Forces><Force type="CMMotionRemover" frequency="1"/></Forces>
</System>"""


def test_degrees_of_freedom_from_the_system_xml():
    assert er.degrees_of_freedom(SYSTEM_XML) == 3 * 3 - 1 - 3
    with pytest.raises(StepsafeError, match="does not parse"):
        er.degrees_of_freedom("<System")


def worker(script):
    """An engine process running the Python ``script`` in place of OpenMM's worker."""
    return er.TrialWorker(command=[sys.executable, "-c", script])


def test_a_crashed_engine_process_counts_as_a_blow_up_and_is_started_again(tmp_path):
    """The process kills itself with SIGSEGV on its first job (a marker file says so) and
    answers the next: the first seed is a blow-up naming the signal, the second is run."""
    marker = tmp_path / "crashed"
    script = (f"import json, os, signal, sys\nmarker = {str(marker)!r}\n"
              "for line in sys.stdin:\n"
              "    if not os.path.exists(marker):\n"
              "        open(marker, 'w').close(); os.kill(os.getpid(), signal.SIGSEGV)\n"
              "    job = json.loads(line)\n"
              "    print(json.dumps({'seed': job['seed'], 'n_dof': 5, 'blew_up': False, "
              "'blowup_step': None, 'reason': '', 'equilibrated': True, 'steps_done': 100, "
              "'times': [0.0, 0.1, 0.2], 'potential': [1.0, 1.0, 1.0], "
              "'kinetic': [2.0, 2.0, 2.0]}), flush=True)\n")
    with worker(script) as w:
        rec = er.run_trials(SYSTEM_XML, "<State/>",
                            er.TrialSpec("verlet", 0.001, 0.1, seeds=(4, 5)), worker=w)
    assert rec.blew_up and rec.verdict() == "blew up"
    assert "signal 11" in rec.runs[0].reason and rec.n_dof == 5
    assert not rec.runs[1].blew_up and rec.runs[1].seed == 5


def test_a_run_past_its_timeout_is_stopped_and_named():
    spec = er.TrialSpec("verlet", 0.001, 0.1, seeds=(4,))
    with er.TrialWorker(timeout=0.5, command=[sys.executable, "-c",
                                             "import time; time.sleep(60)"]) as w:
        with pytest.raises(StepsafeError, match="seed 4 took longer than 0.5 s"):
            er.run_trials(SYSTEM_XML, "<State/>", spec, worker=w)


def test_engine_errors_and_bugs_are_told_apart():
    spec = er.TrialSpec("verlet", 0.001, 0.1, seeds=(4,))
    with worker("import sys\nfor line in sys.stdin: print('{\"error\": \"file::x: bad\"}', "
                "flush=True)") as w:
        with pytest.raises(StepsafeError, match="bad"):
            er.run_trials(SYSTEM_XML, "<State/>", spec, worker=w)
    with worker("raise SystemExit('Traceback')") as w:
        with pytest.raises(RuntimeError, match="trial run failed"):
            er.run_trials(SYSTEM_XML, "<State/>", spec, worker=w)


def test_drift_is_averaged_over_seeds_in_kT_per_ps_per_dof():
    results = iter([
        {"seed": s, "n_dof": 5, "blew_up": False, "blowup_step": None, "reason": "",
         "equilibrated": True, "steps_done": 100, "times": [0.0, 0.1, 0.2, 0.3],
         "potential": [10 + slope * t for t in (0.0, 0.1, 0.2, 0.3)], "kinetic": [2.0] * 4}
        for s, slope in ((1, 0.5), (2, 1.5))])
    class Replies:
        def run(self, job):
            return next(results)

    spec = er.TrialSpec("verlet", 0.001, 0.3, seeds=(1, 2), temperature=300.0)
    rec = er.run_trials(SYSTEM_XML, "<State/>", spec, worker=Replies())
    kT = er.MOLAR_GAS_CONSTANT * 300.0
    mean, se = rec.drift()
    assert mean == pytest.approx(1.0 / (5 * kT), rel=1e-12)
    assert se == pytest.approx(0.5 / (5 * kT), rel=1e-12)          # std(ddof=1)/sqrt(2)
    assert rec.runs[0].kinetic_temperature == pytest.approx(2 * 2.0 / (5 * er.MOLAR_GAS_CONSTANT))
    assert rec.verdict(tolerance=mean * 0.99) == "drifts"
    assert rec.verdict(tolerance=mean * 1.01) == "stable"


# --- rigid-body motions ---------------------------------------------------------------------

@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(networks(max_atoms=5))
def test_leaving_out_rigid_motions_moves_no_eigenvalue_beyond_the_coupling(net):
    """A network off equilibrium (r0 drawn away from r): its exact W has rigid-body
    directions coupled to the rest through the forces. The spectrum without them is a
    compression of W (Cauchy: its largest is at most W's), and with the coupling added to
    its bound it and the rigid block together hold W's largest (Weyl); the 6 (or 5) rigid
    directions are orthonormal and keep every bond length to first order."""
    exact = mass_weighted(net.exact_hessian(), net.masses)
    particles = np.arange(len(net.masses))
    rigid = cs.rigid_body_basis(net.positions, net.masses, particles)
    assert rigid.shape[1] == (5 if len(net.masses) == 2 else 6)
    assert np.allclose(rigid.T @ rigid, np.eye(rigid.shape[1]), atol=1e-12)
    dx = (rigid / np.repeat(np.sqrt(net.masses), 3)[:, None]).T.reshape(rigid.shape[1], -1, 3)
    for i, j in net.bonds:
        e = net.positions[i] - net.positions[j]
        assert np.allclose((dx[:, i] - dx[:, j]) @ e, 0, atol=1e-9 * np.abs(dx).max()
                           * np.linalg.norm(e))
    h = hs.hessian(net)
    sp = cs.constrained_spectrum(h, DistanceConstraints(), exclude=rigid)
    assert len(sp.eigenvalues) == 3 * len(net.masses) - rigid.shape[1]
    top = np.linalg.eigvalsh(exact)[-1]
    assert sp.eigenvalues[0] <= top + sp.bound
    rigid_top = np.linalg.eigvalsh(rigid.T @ exact @ rigid)[-1]
    assert top <= max(sp.eigenvalues[0], rigid_top) + sp.bound + 1e-12 * abs(top)
