"""A force engine written out by hand for the MD tests: harmonic bonds with exact forces and an
exact Hessian, so finite differences, Lanczos and the constraint projection are checked
against numbers that share no code with stepsafe."""

from __future__ import annotations

import math

import mpmath
import numpy as np

from stepsafe.systems.md.engine import DistanceConstraints


class HarmonicNetwork:
    """``U = sum over bonds of k/2 (|x_i - x_j| - r0)^2`` (nm, kJ/mol, amu), implementing
    :class:`stepsafe.systems.md.engine.ForceEngine`."""

    def __init__(self, positions, masses, bonds, k, r0, constraints=None, labels=None):
        self._x = np.array(positions, dtype=float)
        self._m = np.array(masses, dtype=float)
        self.bonds = np.array(bonds, dtype=int).reshape(-1, 2)
        self.k = np.broadcast_to(np.asarray(k, dtype=float), (len(self.bonds),)).copy()
        self.r0 = np.broadcast_to(np.asarray(r0, dtype=float), (len(self.bonds),)).copy()
        self._c = constraints if constraints is not None else DistanceConstraints()
        n = len(self._m)
        self._labels = tuple(labels) if labels is not None else tuple(f"A{i}" for i in range(n))
        self.calls = 0

    n_particles = property(lambda self: len(self._m))
    masses = property(lambda self: self._m)
    positions = property(lambda self: self._x)
    constraints = property(lambda self: self._c)
    virtual_sites = property(lambda self: np.zeros(len(self._m), dtype=bool))
    labels = property(lambda self: self._labels)

    def energy(self, x):
        x = np.asarray(x, dtype=float)
        r = np.linalg.norm(x[self.bonds[:, 0]] - x[self.bonds[:, 1]], axis=1)
        return float(0.5 * np.sum(self.k * (r - self.r0) ** 2))

    def forces(self, x):
        self.calls += 1
        x = np.asarray(x, dtype=float)
        f = np.zeros_like(x)
        for (i, j), k, r0 in zip(self.bonds, self.k, self.r0):
            d = x[i] - x[j]
            r = np.linalg.norm(d)
            g = k * (r - r0) * d / r          # dU/dx_i
            f[i] -= g
            f[j] += g
        return f

    def exact_hessian(self, x=None):
        """d^2U over all 3N coordinates: per bond ``k [e e^T + (r - r0)/r (I - e e^T)]`` on
        (i, i) and (j, j), its negative on (i, j) and (j, i)."""
        x = self._x if x is None else np.asarray(x, dtype=float)
        n = len(self._m)
        h = np.zeros((3 * n, 3 * n))
        for (i, j), k, r0 in zip(self.bonds, self.k, self.r0):
            d = x[i] - x[j]
            r = np.linalg.norm(d)
            e = d / r
            block = k * (np.outer(e, e) + (r - r0) / r * (np.eye(3) - np.outer(e, e)))
            for a, b, s in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
                h[3 * a:3 * a + 3, 3 * b:3 * b + 3] += s * block
        return h


def bond_hessian(xi, xj, k, r0):
    """The 6x6 Hessian of k/2 (|xi - xj| - r0)^2 over (xi, xj):
    ``k [e e^T + (r - r0)/r (I - e e^T)]`` and its negative off the diagonal."""
    d = np.asarray(xi, float) - np.asarray(xj, float)
    r = np.linalg.norm(d)
    e = d / r
    b = k * (np.outer(e, e) + (r - r0) / r * (np.eye(3) - np.outer(e, e)))
    return np.block([[b, -b], [-b, b]])


def angle_hessian(x1, x2, x3, k, theta0):
    """The 9x9 Hessian of k/2 (theta - theta0)^2 over (x1, x2, x3), theta the angle at x2.

    With a = x1 - x2, b = x3 - x2, c = cos theta = a.b/(|a||b|):
    dc/da = g_a = (b^ - c a^)/|a|, dc/db = g_b = (a^ - c b^)/|b|,
    d2c/da2 = -(g_a a^T + a^ g_a^T)/|a| - c (I - a^ a^T)/|a|^2 (and likewise for b),
    d2c/da db = (I - a^ a^T - b^ b^T + c a^ b^T)/(|a||b|);
    theta = arccos c: theta' = -1/s, theta'' = -c/s^3 (s = sin theta);
    d2U = k (grad theta grad theta^T + (theta - theta0) d2 theta), and x1 -> a, x3 -> b,
    x2 -> -(a + b)."""
    a = np.asarray(x1, float) - np.asarray(x2, float)
    b = np.asarray(x3, float) - np.asarray(x2, float)
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    ah, bh = a / la, b / lb
    c = float(ah @ bh)
    ga, gb = (bh - c * ah) / la, (ah - c * bh) / lb
    eye = np.eye(3)
    haa = -(np.outer(ga, ah) + np.outer(ah, ga)) / la - c * (eye - np.outer(ah, ah)) / la**2
    hbb = -(np.outer(gb, bh) + np.outer(bh, gb)) / lb - c * (eye - np.outer(bh, bh)) / lb**2
    hab = (eye - np.outer(ah, ah) - np.outer(bh, bh) + c * np.outer(ah, bh)) / (la * lb)
    grad_c = np.concatenate([ga, gb])
    hess_c = np.block([[haa, hab], [hab.T, hbb]])
    s = math.sqrt(1.0 - c * c)
    theta = math.acos(c)
    grad_t = -grad_c / s
    hess_t = -c / s**3 * np.outer(grad_c, grad_c) - hess_c / s
    h_ab = k * (np.outer(grad_t, grad_t) + (theta - theta0) * hess_t)
    chain = np.zeros((6, 9))          # (a, b) = chain @ (x1, x2, x3)
    chain[0:3, 0:3] = eye
    chain[0:3, 3:6] = -eye
    chain[3:6, 6:9] = eye
    chain[3:6, 3:6] = -eye
    return chain.T @ h_ab @ chain


def triatomic(d=0.1, r0_ab=0.11, theta=1.9, r_bc=0.1, k_ab=3e5, k_bc=2e5, k_ac=5e4,
              masses=(12.0, 14.0, 1.0)):
    """A-B-C with A-B constrained at d and also carrying a harmonic term stretched to
    r0_ab != d; B-C and the 1-3 term A-C at rest: an equilibrium of the constrained system
    whose multiplier is not zero."""
    xb = np.zeros(3)
    xa = np.array([d, 0.0, 0.0])
    xc = r_bc * np.array([math.cos(theta), math.sin(theta), 0.0])
    x = np.array([xa, xb, xc])
    r_ac = float(np.linalg.norm(xa - xc))
    c = DistanceConstraints([[0, 1]], [d])
    net = HarmonicNetwork(x, masses, [(0, 1), (1, 2), (0, 2)], [k_ab, k_bc, k_ac],
                          [r0_ab, r_bc, r_ac], constraints=c)
    return net, dict(d=d, r0_ab=r0_ab, theta=theta, r_bc=r_bc, r_ac=r_ac, k_ab=k_ab, k_bc=k_bc,
                     k_ac=k_ac, masses=masses)


def reduced_coordinate_frequencies(p):
    """omega^2 of the triatomic in reduced coordinates q = (x_B, phi, psi, x_C) with
    x_A = x_B + d (sin psi cos phi, sin psi sin phi, cos psi): the generalized eigenvalues of
    (d^2 U(x(q))/dq^2, J^T M J), J = dx/dq, at 50 digits (mpmath)."""
    mpmath.mp.dps = 50
    mp = mpmath.mp
    d, mA, mB, mC = mp.mpf(p["d"]), *map(mp.mpf, p["masses"])

    def x_of(q):
        xb, phi, psi, xc = q[0:3], q[3], q[4], q[5:8]
        xa = [xb[0] + d * mp.sin(psi) * mp.cos(phi), xb[1] + d * mp.sin(psi) * mp.sin(phi),
              xb[2] + d * mp.cos(psi)]
        return xa, list(xb), list(xc)

    def dist(a, b):
        return mp.sqrt(sum((a[i] - b[i]) ** 2 for i in range(3)))

    def U(*q):
        xa, xb, xc = x_of(q)
        return (mp.mpf(p["k_ab"]) / 2 * (dist(xa, xb) - mp.mpf(p["r0_ab"])) ** 2
                + mp.mpf(p["k_bc"]) / 2 * (dist(xb, xc) - mp.mpf(p["r_bc"])) ** 2
                + mp.mpf(p["k_ac"]) / 2 * (dist(xa, xc) - mp.mpf(p["r_ac"])) ** 2)

    th = mp.mpf(p["theta"])
    q0 = [0, 0, 0, 0, mp.pi / 2, p["r_bc"] * mp.cos(th), p["r_bc"] * mp.sin(th), 0]
    q0 = [mp.mpf(v) for v in q0]
    n = 8
    hq = mp.matrix(n, n)
    for i in range(n):
        for j in range(i, n):
            order = [0] * n
            order[i] += 1
            order[j] += 1
            hq[i, j] = hq[j, i] = mp.diff(U, q0, tuple(order))
    jac = mp.matrix(9, n)
    for j in range(n):
        for a in range(9):
            def comp(t, a=a, j=j):
                q = list(q0)
                q[j] += t
                xa, xb, xc = x_of(q)
                return (xa + xb + xc)[a]
            jac[a, j] = mp.diff(comp, 0)
    mass = mp.diag([mA] * 3 + [mB] * 3 + [mC] * 3)
    mq = jac.T * mass * jac
    inv = mp.inverse(mp.cholesky(mq))
    lam = mp.eigsy(inv * hq * inv.T, eigvals_only=True)
    return sorted((float(v) for v in lam), reverse=True)


def one_water(**create):
    """One flexible TIP3P molecule (OpenMM's ``amber14/tip3p.xml``, vacuum, no cutoff, no
    constraints unless ``create`` asks, no centre-of-mass remover) at the force field's
    equilibrium geometry, as (System, positions in nm). Needs OpenMM."""
    from openmm import app

    ff = app.ForceField("amber14/tip3p.xml")
    top = app.Topology()
    res = top.addResidue("HOH", top.addChain())
    o = top.addAtom("O", app.element.oxygen, res)
    for name in ("H1", "H2"):
        top.addBond(o, top.addAtom(name, app.element.hydrogen, res))
    system = ff.createSystem(top, nonbondedMethod=app.NoCutoff, removeCMMotion=False,
                             **{"rigidWater": False, "constraints": None, **create})
    r0, theta = TIP3P["r0"], TIP3P["theta0"]
    x = np.array([[0.0, 0.0, 0.0], [r0, 0.0, 0.0],
                  [r0 * math.cos(theta), r0 * math.sin(theta), 0.0]])
    return system, x


def water_cluster(directory, n_side=2, spacing=0.31, **create):
    """Write ``system.xml`` (flexible TIP3P waters from OpenMM's ``amber14/tip3p.xml``, in
    vacuum, no cutoff, no constraints unless ``create`` asks, no centre-of-mass remover) and
    ``structure.pdb`` (``n_side``^3 molecules on a cubic grid ``spacing`` nm apart, in three
    orientations) into ``directory``; returns the two paths. Needs OpenMM."""
    from pathlib import Path

    import openmm
    from openmm import app, unit

    r0, theta = 0.09572, 1.82421813418
    top = app.Topology()
    chain = top.addChain()
    positions = []
    for a in range(n_side):
        for b in range(n_side):
            for c in range(n_side):
                res = top.addResidue("HOH", chain)
                o = top.addAtom("O", app.element.oxygen, res)
                for name in ("H1", "H2"):
                    top.addBond(o, top.addAtom(name, app.element.hydrogen, res))
                local = np.array([[0.0, 0.0, 0.0], [r0, 0.0, 0.0],
                                  [r0 * math.cos(theta), r0 * math.sin(theta), 0.0]])
                local = np.roll(local, (a + b + c) % 3, axis=1)
                positions += list(local + spacing * np.array([a, b, c]))
    ff = app.ForceField("amber14/tip3p.xml")
    options = {"constraints": None, "rigidWater": False, **create}
    system = ff.createSystem(top, nonbondedMethod=app.NoCutoff, removeCMMotion=False,
                             **options)
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    (out / "system.xml").write_text(openmm.XmlSerializer.serialize(system))
    with open(out / "structure.pdb", "w") as fh:
        app.PDBFile.writeFile(top, np.array(positions) * unit.nanometer, fh)
    return out / "system.xml", out / "structure.pdb"


def tip3p_isolated_frequencies():
    """Closed forms (Wilson's G matrix) for one flexible TIP3P molecule (amber14/tip3p.xml:
    bond k_r = 462750.4 kJ/mol/nm^2, r0 = 0.09572 nm, angle k_theta = 836.8 kJ/mol/rad^2,
    theta0 = 1.82421813418 rad; masses 15.99943 and 1.007947 amu), in rad^2/ps^2:
    the antisymmetric stretch ``k_r (1/m_H + (1 - cos theta0)/m_O)`` (no stretch-bend
    coupling in this force field, so it is exact), and the bend with both bonds held rigid,
    ``k_theta / (G^-1)_theta,theta``: with the bond lengths fixed the kinetic energy is
    ``(G^-1)_tt theta'^2 / 2``, and the Schur complement of G over (r1, r2, theta) gives
    ``1/(G^-1)_tt = G_tt - 2 sin^2 theta0 / (m_O^2 r0^2 (1/m_H + (1 + cos theta0)/m_O))``,
    ``G_tt = (2/m_H + (2 - 2 cos theta0)/m_O) / r0^2``."""
    k_r, r0, k_t, theta = 462750.4, 0.09572, 836.8, 1.82421813418
    m_o, m_h = 15.99943, 1.007947
    stretch = k_r * (1 / m_h + (1 - math.cos(theta)) / m_o)
    g_tt = (2 / m_h + (2 - 2 * math.cos(theta)) / m_o) / r0 ** 2
    coupling = 2 * math.sin(theta) ** 2 / (m_o ** 2 * r0 ** 2
                                           * (1 / m_h + (1 + math.cos(theta)) / m_o))
    bend = k_t * (g_tt - coupling)
    return {"antisymmetric_stretch": stretch, "rigid_bend": bend}


#: amber14/tip3p.xml's flexible water: masses (amu), O-H bond (kJ/mol/nm^2, nm), H-O-H angle
#: (kJ/mol/rad^2, rad).
TIP3P = {"mO": 15.99943, "mH": 1.007947, "kb": 462750.4, "r0": 0.09572, "ka": 836.8,
         "theta0": 1.82421813418}


def single_water_hessian(x):
    """The analytic 9x9 Hessian of one flexible TIP3P molecule (O, H1, H2): two harmonic O-H
    bonds and the H-O-H angle (OpenMM excludes the intramolecular nonbonded pairs)."""
    p = TIP3P
    h = np.zeros((9, 9))
    for hyd in (1, 2):
        idx = np.r_[0:3, 3 * hyd:3 * hyd + 3]
        h[np.ix_(idx, idx)] += bond_hessian(x[0], x[hyd], p["kb"], p["r0"])
    h += angle_hessian(x[1], x[0], x[2], p["ka"], p["theta0"])[np.ix_(
        np.r_[3:6, 0:3, 6:9], np.r_[3:6, 0:3, 6:9])]
    return h
