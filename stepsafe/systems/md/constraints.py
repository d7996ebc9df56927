"""Holonomic distance constraints: the Hessian on the constraint manifold's tangent space in
the mass metric, and which constraints ``constraints: none | h-bonds | all-bonds | h-angles``
means for a system built from atoms.

Math. Coordinates x (the d = 3 n coordinates of the moving particles, nm), masses M
(diagonal, amu), potential U with Hessian H and forces F = -grad U. Constraints
``g_k(x) = |x_i - x_j| - d_k = 0`` with Jacobian G (K x d; row k is ``+e`` on particle i and
``-e`` on j, e the unit vector from j to i). The equations of motion are
``M x'' = F - G^T lambda`` with the multipliers fixed by ``G x'' = -G' x'``; at rest
(the instantaneous modes of a configuration) ``G M^-1 G^T lambda = G M^-1 F``. Linearised,
the motion keeps to the tangent space ``ker G`` and feels the curvature of the Lagrangian
``U + lambda^T g``:

    K = H + sum_k lambda_k d^2 g_k,    d^2 g_k = [[A, -A], [-A, A]] on (i, j),
    A = (I - e e^T) / |x_i - x_j|.

In mass-weighted coordinates ``y = M^(1/2) x`` the tangent space is ``ker J``, ``J = G M^(-1/2)``,
with the orthogonal projector ``P_y = I - J^T (J J^T)^-1 J = M^(1/2) P M^(-1/2)``, where
``P = I - M^-1 G^T (G M^-1 G^T)^-1 G`` is the mass-metric projector. The squared frequencies of
the constrained system are the eigenvalues of ``P_y M^(-1/2) K M^(-1/2) P_y`` on the range of
``P_y`` (d - K of them): the dense path takes an orthonormal basis Q of ``ker J`` and
diagonalises ``Q^T M^(-1/2) K M^(-1/2) Q``; the Hessian-vector path applies the projected operator,
which maps the K directions normal to the constraints to 0 (harmless for the largest
eigenvalues). Nothing is deleted by hand: a 2 fs step with h-bond constraints is analysed on the
motion that remains. The curvature term is what makes the result independent of how the
constraint is written (``|r| - d`` or ``(|r|^2 - d^2)/2`` give other lambda and d^2 g, the same
K on ``ker J``) and of any force along a constrained bond (a stretched harmonic bond that is
also constrained contributes ``k e e^T``, which the projection removes, and a transverse
``k (r - r0)/r (I - e e^T)`` that the multiplier's term cancels). At finite temperature the
multipliers carry a velocity term ``G M^-1 G^T lambda_v = G' x'`` as well; this module takes
configurations at rest (instantaneous normal modes). Constraint algorithms (SHAKE, RATTLE,
SETTLE, LINCS, CCMA) all solve these equations to a tolerance; the Verlet-type integrators built
on them keep Verlet's linear stability on the reduced system, so its limit is
``2 / omega_max`` with omega_max from this spectrum.

Constraint rules for systems built from atoms (OpenMM's ``ForceField.createSystem``,
:func:`constraints_for`):

==============  ===========================================================================
``none``        no constraints
``h-bonds``     every bond with a hydrogen at either end
``all-bonds``   every bond
``h-angles``    every bond, and every angle i-j-k whose two ends are hydrogens or that has one
                hydrogen end and an oxygen centre, as the distance i-k
                ``sqrt(l1^2 + l2^2 - 2 l1 l2 cos theta0)`` from the two bonds' equilibrium
                lengths and the equilibrium angle
==============  ===========================================================================

A rigid water (residue ``HOH``; OpenMM's default for its water models) has its O-H bonds and
its H-O-H angle constrained whatever the rule. The bond and angle terms of constrained bonds and
angles leave the force field (OpenMM does so unless ``flexibleConstraints``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.md.engine import DistanceConstraints, Topology, mobile_particles
from stepsafe.systems.md.hessian import (
    SAFETY,
    Hessian,
    HessianVectorProduct,
    Spectrum,
    extreme_eigenvalues,
    spectral_radius_bound,
)

#: Positions must satisfy every constraint to this relative tolerance (|g_k| / d_k).
POSITION_TOLERANCE = 1e-6
#: The rule names of ``constraints:``.
KINDS = ("none", "h-bonds", "all-bonds", "h-angles")


class ConstrainedSpace:
    """The tangent space of the constraints at a configuration, the multipliers there, and the
    constraint curvature, over the moving coordinates.

    Parameters
    ----------
    constraints : DistanceConstraints
    positions : ndarray, shape (N, 3)
        nm; must satisfy the constraints to :data:`POSITION_TOLERANCE`.
    masses : ndarray, shape (N,)
        amu (mass 0: the particle does not move; a constraint to it acts as one to a wall).
    forces : ndarray, shape (d,)
        Forces on the moving coordinates (kJ/mol/nm), for the multipliers.
    """

    def __init__(self, constraints: DistanceConstraints, positions: np.ndarray,
                 masses: np.ndarray, forces: np.ndarray) -> None:
        from scipy import sparse
        from scipy.sparse.linalg import splu

        x = np.asarray(positions, dtype=float)
        masses = np.asarray(masses, dtype=float)
        constraints.check_indices(len(masses))
        self.particles = mobile_particles(masses)
        n = len(self.particles)
        self.dim = 3 * n
        inv_m = np.repeat(1.0 / masses[self.particles], 3)
        self.inv_sqrt_m = np.sqrt(inv_m)
        where = np.full(len(masses), -1, dtype=np.int64)
        where[self.particles] = np.arange(n)
        pairs = constraints.pairs
        keep = (where[pairs[:, 0]] >= 0) | (where[pairs[:, 1]] >= 0)
        residual = np.abs(constraints.residuals(x)) / constraints.distances
        if len(residual) and residual.max() > POSITION_TOLERANCE:
            k = int(np.argmax(residual))
            raise StepsafeError(
                f"the positions violate the constraint between particles {pairs[k, 0]} and "
                f"{pairs[k, 1]} by {residual[k]:.1e} (relative); put them on the constraints "
                f"first (the OpenMM engine does so when it is built)")
        self.pairs = pairs[keep]
        self.distances = constraints.distances[keep]
        rvec = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
        self.r = np.linalg.norm(rvec, axis=1)
        self.e = rvec / self.r[:, None]
        self.loc = where[self.pairs]           # -1 for a particle that does not move
        K = len(self.pairs)
        self.removed = K
        rows, cols, vals = [], [], []
        for side, sign in ((0, 1.0), (1, -1.0)):
            ok = self.loc[:, side] >= 0
            for a in range(3):
                rows.append(np.flatnonzero(ok))
                cols.append(3 * self.loc[ok, side] + a)
                vals.append(sign * self.e[ok, a])
        self.G = sparse.csr_matrix((np.concatenate(vals) if vals else np.zeros(0),
                                    (np.concatenate(rows) if rows else np.zeros(0, int),
                                     np.concatenate(cols) if cols else np.zeros(0, int))),
                                   shape=(K, self.dim))
        #: J = G M^(-1/2), the Jacobian in mass-weighted coordinates.
        self.J = self.G @ sparse.diags(self.inv_sqrt_m)
        self._lu = None
        if K:
            S = (self.J @ self.J.T).tocsc()
            try:
                self._lu = splu(S)
            except RuntimeError:
                raise StepsafeError("the constraints are redundant at this configuration "
                                    "(G M^-1 G^T is singular)") from None
        f = np.asarray(forces, dtype=float).reshape(-1)
        #: The multipliers lambda in kJ/mol/nm (G M^-1 G^T lambda = G M^-1 F).
        self.multipliers = self._solve(self.G @ (inv_m * f)) if K else np.zeros(0)

    def _solve(self, b: np.ndarray) -> np.ndarray:
        assert self._lu is not None
        return self._lu.solve(np.asarray(b, dtype=float))

    def tangent_forces(self, forces: np.ndarray) -> np.ndarray:
        """``F - G^T lambda``: the forces that remain once the constraint forces balance the
        rest (zero at a constrained equilibrium), over the moving coordinates."""
        f = np.asarray(forces, dtype=float).reshape(-1)
        return f - self.G.T @ self.multipliers if len(self.pairs) else f

    def project(self, y: np.ndarray) -> np.ndarray:
        """``P_y y = y - J^T (J J^T)^-1 J y`` (mass-weighted coordinates)."""
        if self._lu is None:
            return np.asarray(y, dtype=float)
        return y - self.J.T @ self._solve(self.J @ y)

    def curvature(self, u: np.ndarray) -> np.ndarray:
        """``sum_k lambda_k d^2 g_k u`` for a Cartesian vector u over the moving coordinates
        (kJ/mol/nm^2 times u's units)."""
        out = np.zeros(self.dim)
        if not len(self.pairs):
            return out
        u3 = np.asarray(u, dtype=float).reshape(-1, 3)
        du = np.zeros((len(self.pairs), 3))
        for side, sign in ((0, 1.0), (1, -1.0)):
            ok = self.loc[:, side] >= 0
            du[ok] += sign * u3[self.loc[ok, side]]
        a = (du - self.e * np.einsum("ka,ka->k", self.e, du)[:, None]) / self.r[:, None]
        a *= self.multipliers[:, None]
        out3 = out.reshape(-1, 3)
        for side, sign in ((0, 1.0), (1, -1.0)):
            ok = self.loc[:, side] >= 0
            np.add.at(out3, self.loc[ok, side], sign * a[ok])
        return out

    def curvature_matrix(self) -> np.ndarray:
        """``sum_k lambda_k d^2 g_k`` as a dense (d, d) matrix (kJ/mol/nm^2)."""
        c = np.zeros((self.dim, self.dim))
        for k in range(len(self.pairs)):
            block = self.multipliers[k] * (np.eye(3) - np.outer(self.e[k], self.e[k])) / self.r[k]
            for s1, g1 in ((0, 1.0), (1, -1.0)):
                i = self.loc[k, s1]
                if i < 0:
                    continue
                for s2, g2 in ((0, 1.0), (1, -1.0)):
                    j = self.loc[k, s2]
                    if j >= 0:
                        c[3 * i:3 * i + 3, 3 * j:3 * j + 3] += g1 * g2 * block
        return c

    def basis(self) -> np.ndarray:
        """An orthonormal basis Q (d, d - rank J) of the tangent space ``ker J`` in
        mass-weighted coordinates (dense; from the SVD of J)."""
        from scipy.linalg import null_space

        if not len(self.pairs):
            return np.eye(self.dim)
        return null_space(self.J.toarray())


def constrained_spectrum(h: Hessian, constraints: DistanceConstraints,
                         k: int | None = None, exclude: np.ndarray | None = None) -> Spectrum:
    """The spectrum of the constrained system from a dense Hessian: eigenvalues of
    ``Q^T M^(-1/2) (H + sum lambda_k d^2 g_k) M^(-1/2) Q`` (d - K of them), fastest first, with
    eigenvectors ``Q z`` in the full mass-weighted coordinates (so
    :meth:`~stepsafe.systems.md.hessian.Spectrum.participation` names the moving atoms).
    Error estimates: first order ``|v|^T E |v|`` and the bound ``rho(E)`` of the unconstrained
    W (an orthonormal Q cannot enlarge an error).

    Parameters
    ----------
    h : Hessian
        Taken at positions on the constraints.
    constraints : DistanceConstraints
    k : int, optional
        Keep the k largest.
    exclude : ndarray, shape (d, r), optional
        Orthonormal mass-weighted directions in the tangent space to leave out (the
        rigid-body motions, :func:`rigid_body_basis`): the spectrum is that of the
        compression to the rest, and the coupling between the two, ``||Q'^T K R||_2``, is
        added to the bound (by Weyl's inequality no eigenvalue of the whole moves further
        from one of the two blocks'; with no force on the system the coupling vanishes).

    Returns
    -------
    Spectrum
    """
    masses = np.zeros(len(h.positions))
    masses[h.particles] = h.masses
    w, e = h.mass_weighted()
    if len(constraints):
        space = ConstrainedSpace(constraints, h.positions, masses, h.forces)
        s = space.inv_sqrt_m
        kw = w + s[:, None] * space.curvature_matrix() * s[None, :]
        q = space.basis()
    else:
        kw, q = w, np.eye(len(w))
    removed = q.shape[0] - q.shape[1]
    coupling = 0.0
    if exclude is not None and exclude.shape[1]:
        from scipy.linalg import null_space

        q = q @ null_space((q.T @ exclude).T)
        coupling = float(np.linalg.norm(q.T @ kw @ exclude, 2))
    lam, z = np.linalg.eigh(q.T @ kw @ q)
    lam, z = lam[::-1], z[:, ::-1]
    if k is not None:
        lam, z = lam[:k], z[:, :k]
    vec = q @ z
    av = np.abs(vec)
    errors = SAFETY * np.einsum("ik,ij,jk->k", av, e, av) + coupling
    return Spectrum(lam, vec, errors, h.particles,
                    SAFETY * spectral_radius_bound(e) + coupling, 0, removed)


def rigid_body_basis(positions: np.ndarray, masses: np.ndarray, particles: np.ndarray, *,
                     rotations: bool = True) -> np.ndarray:
    """An orthonormal basis of the rigid-body motions of the moving particles in
    mass-weighted coordinates: translations ``sqrt(m_i) e_a`` and (``rotations``: a system
    without periodic boundaries) rotations about the centre of mass
    ``sqrt(m_i) e_a x (x_i - c)``; 6 columns, 5 for a linear molecule, 3 without rotations.
    They keep every distance, so they lie in the constraints' tangent space, and the
    energy of an isolated system does not change along them.

    Parameters
    ----------
    positions : ndarray, shape (N, 3)
    masses : ndarray, shape (N,)
    particles : ndarray of int
        The moving particles (their coordinates, in order, are the d = 3 n dimensions).
    rotations : bool

    Returns
    -------
    ndarray, shape (d, r)
    """
    x = np.asarray(positions, dtype=float)[particles]
    m = np.asarray(masses, dtype=float)[particles]
    root = np.sqrt(m)
    c = (m[:, None] * x).sum(axis=0) / m.sum()
    cols = []
    for a in range(3):
        t = np.zeros((len(m), 3))
        t[:, a] = root
        cols.append(t.reshape(-1))
    if rotations:
        for a in range(3):
            axis = np.zeros(3)
            axis[a] = 1.0
            cols.append((root[:, None] * np.cross(axis, x - c)).reshape(-1))
    u, sv, _ = np.linalg.svd(np.array(cols).T, full_matrices=False)
    return u[:, sv > 1e-10 * sv.max()]


class ConstrainedProduct:
    """``y -> P_y M^(-1/2) (H + sum lambda_k d^2 g_k) M^(-1/2) P_y y`` by Hessian-vector
    products (memory linear in the particles; one sparse factorisation of ``G M^-1 G^T``).

    Parameters
    ----------
    hvp : HessianVectorProduct
    constraints : DistanceConstraints
    """

    def __init__(self, hvp: HessianVectorProduct, constraints: DistanceConstraints) -> None:
        fd = hvp.fd
        self.hvp = hvp
        self.dim = hvp.dim
        self.particles = hvp.particles
        self.space = ConstrainedSpace(constraints, fd.x0, fd.engine.masses, fd.f0)

    def with_error(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The product and its element-wise error estimate (that of W's product)."""
        s = self.space.inv_sqrt_m
        py = self.space.project(np.asarray(y, dtype=float).reshape(-1))
        wy, err = self.hvp.with_error(py)
        out = wy + s * self.space.curvature(s * py)
        return self.space.project(out), err

    def __call__(self, y: np.ndarray) -> np.ndarray:
        return self.with_error(y)[0]


def constrained_modes(hvp: HessianVectorProduct, constraints: DistanceConstraints, *,
                      k: int = 1, tol: float = 1e-6, which: str = "largest") -> Spectrum:
    """The ``k`` fastest modes of the constrained system by Lanczos on
    :class:`ConstrainedProduct` (see :func:`~stepsafe.systems.md.hessian.extreme_eigenvalues`).

    Parameters
    ----------
    hvp : HessianVectorProduct
    constraints : DistanceConstraints
    k : int
    tol : float
        ARPACK's relative tolerance.
    which : {"largest", "magnitude"}
        As in :func:`~stepsafe.systems.md.hessian.extreme_eigenvalues` (the K directions
        normal to the constraints are eigenvectors of eigenvalue 0 and never come first).

    Returns
    -------
    Spectrum
    """
    op = ConstrainedProduct(hvp, constraints)
    sp = extreme_eigenvalues(op, op.dim, k=k, tol=tol, which=which, with_error=op.with_error,
                             particles=op.particles)
    return Spectrum(sp.eigenvalues, sp.vectors, sp.errors, sp.particles, sp.bound, sp.products,
                    op.space.removed)


def constraints_for(kind: str, topology: Topology, bond_lengths: Sequence[float] | np.ndarray,
                    angles: Sequence[Sequence[int]] | np.ndarray = (),
                    angle_values: Sequence[float] | np.ndarray = (), *,
                    rigid_water: bool = False) -> DistanceConstraints:
    """The distance constraints ``kind`` means for a system built from atoms, with OpenMM's
    ``createSystem`` rules (module docstring).

    Parameters
    ----------
    kind : {"none", "h-bonds", "all-bonds", "h-angles"}
    topology : Topology
        Elements and bonds.
    bond_lengths : sequence of float
        Equilibrium length (nm) of each bond of ``topology.bonds``, in order.
    angles : (A, 3) int
        Angles i-j-k (j the centre) of the force field; needed for ``h-angles`` and rigid water.
    angle_values : (A,) float
        Their equilibrium angles in radians.
    rigid_water : bool
        Constrain water (``HOH``) completely whatever ``kind``.

    Returns
    -------
    DistanceConstraints
        In the order bonds first (in ``topology.bonds`` order), then angles.
    """
    if kind not in KINDS:
        raise StepsafeError(f"unknown constraints {str(kind)[:20]!r}; choose one of "
                            f"{', '.join(KINDS)}")
    bonds = topology.bonds
    lengths = np.asarray(bond_lengths, dtype=float).reshape(-1)
    if len(lengths) != len(bonds):
        raise StepsafeError(f"{len(lengths)} bond lengths for {len(bonds)} bonds")
    angles_a = np.asarray(angles, dtype=np.int64).reshape(-1, 3)
    values = np.asarray(angle_values, dtype=float).reshape(-1)
    if len(values) != len(angles_a):
        raise StepsafeError(f"{len(values)} angle values for {len(angles_a)} angles")
    el = topology.elements

    def is_h(i: int) -> bool:
        return el[i] == "H"

    def water(*atoms: int) -> bool:
        return rigid_water and all(topology.residues[a] == "HOH" for a in atoms)

    pairs: list[tuple[int, int]] = []
    dist: list[float] = []
    seen: dict[tuple[int, int], float] = {}

    def add(i: int, j: int, d: float) -> None:
        key = (min(i, j), max(i, j))
        if key in seen:
            if seen[key] != d:
                raise StepsafeError(f"particles {i} and {j} are constrained to two distances")
            return
        seen[key] = d
        pairs.append((i, j))
        dist.append(d)

    length_of: dict[tuple[int, int], float] = {}
    for (i, j), d in zip(bonds.tolist(), lengths.tolist()):
        length_of[(min(i, j), max(i, j))] = d
        constrained = (kind in ("all-bonds", "h-angles")
                       or (kind == "h-bonds" and (is_h(i) or is_h(j))) or water(i, j))
        if constrained:
            add(i, j, d)
    for (i, j, k), theta in zip(angles_a.tolist(), values.tolist()):
        n_h = int(is_h(i)) + int(is_h(k))
        constrained = (kind == "h-angles" and (n_h == 2 or (n_h == 1 and el[j] == "O"))) \
            or water(i, j, k)
        if not constrained:
            continue
        l1 = length_of.get((min(i, j), max(i, j)))
        l2 = length_of.get((min(j, k), max(j, k)))
        if l1 is None or l2 is None:
            continue
        add(i, k, math.sqrt(l1 * l1 + l2 * l2 - 2.0 * l1 * l2 * math.cos(theta)))
    return DistanceConstraints(np.array(pairs, dtype=np.int64).reshape(-1, 2),
                               np.array(dist, dtype=float))


def angles_of(topology: Topology) -> np.ndarray:
    """Every angle i-j-k (i < k) of bonded triples of ``topology``, centre j, sorted.

    Parameters
    ----------
    topology : Topology

    Returns
    -------
    ndarray of int, shape (A, 3)
    """
    neighbours: list[list[int]] = [[] for _ in range(len(topology))]
    for i, j in topology.bonds.tolist():
        neighbours[i].append(j)
        neighbours[j].append(i)
    out = [(i, j, k) for j, nb in enumerate(neighbours) for i in nb for k in nb if i < k]
    return np.array(sorted(out), dtype=np.int64).reshape(-1, 3)

