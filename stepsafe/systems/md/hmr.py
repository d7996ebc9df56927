"""Hydrogen mass repartitioning (HMR), as OpenMM's ``ForceField.createSystem(hydrogenMass=m)``.

Rule (OpenMM): for every chemical bond, in the topology's order, joining a hydrogen to an atom
whose element is known and is not hydrogen, the hydrogen's mass is *set* to ``m`` and the
difference ``m - m_H`` (m_H its mass before) is taken from that bonded heavy atom. The total
mass is unchanged; a carbon with three hydrogens at m = 3 amu loses 3 (3 - 1.008) amu. Water
hydrogens are skipped only when the water is rigid (OpenMM's default for its water models: a
rigid molecule has no internal motion for the mass to slow down); flexible water is
repartitioned like any other molecule (the O of TIP3P ends at 12.015 amu with m = 3).

GROMACS does it differently: the mdp option ``mass-repartition-factor`` f (GROMACS 2024 and
later) sets m_min = f times the smallest atomic mass in the system and raises every lighter
atom to m_min, taking the difference from its single bonded partner, chemical bonds *and* SETTLE
water included. So f = 3 gives hydrogens 3.024 amu (3 x 1.008), not 3, and rigid water is
repartitioned too. ``pdb2gmx -heavyh`` instead multiplies hydrogen masses by 4 (taking the added
mass from the bonded heavy atom) and leaves water at its model's masses. Results for "4 fs with
HMR" therefore depend on which engine's rule was applied; this module applies OpenMM's.

A heavy atom that would end at zero or negative mass (OpenMM would build it) is refused.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.systems.md.engine import DistanceConstraints, Topology


@dataclass(frozen=True)
class Repartition:
    """The outcome of :func:`repartition`.

    Attributes
    ----------
    masses : ndarray, shape (N,)
        The new masses in amu.
    hydrogens : ndarray of int
        The hydrogens whose mass was set.
    donors : ndarray of int
        The heavy atoms that gave (or, for hydrogens already heavier than the target,
        received) mass.
    hydrogen_mass : float
        The target mass in amu.
    """

    masses: np.ndarray
    hydrogens: np.ndarray
    donors: np.ndarray
    hydrogen_mass: float


def repartition(masses: np.ndarray, topology: Topology, hydrogen_mass: float, *,
                keep_residues: Iterable[int] = ()) -> Repartition:
    """Hydrogen mass repartitioning with OpenMM's rule (module docstring).

    Parameters
    ----------
    masses : ndarray, shape (N,)
        Masses in amu.
    topology : Topology
        Elements and bonds (from the structure file).
    hydrogen_mass : float
        The hydrogens' new mass in amu.
    keep_residues : iterable of int
        Residue ids (``topology.residue_ids``) whose hydrogens keep their mass: the rigid
        waters (:func:`rigid_waters`).

    Returns
    -------
    Repartition
    """
    m_h = positive_finite(hydrogen_mass, "hydrogen mass")
    m = np.array(masses, dtype=float)
    if m.shape != (len(topology),):
        raise StepsafeError(f"{m.size} masses for a topology of {len(topology)} particles")
    keep = set(int(r) for r in keep_residues)
    el = topology.elements
    hydrogens: list[int] = []
    donors: list[int] = []
    for a, b in topology.bonds.tolist():
        if el[a] == "H":
            a, b = b, a
        if el[b] != "H" or el[a] in ("H", None) or int(topology.residue_ids[b]) in keep:
            continue
        transfer = m_h - m[b]
        m[b] = m_h
        m[a] -= transfer
        hydrogens.append(b)
        donors.append(a)
    if donors:
        bad = [i for i in dict.fromkeys(donors) if not m[i] > 0]
        if bad:
            raise StepsafeError(f"a hydrogen mass of {m_h:g} amu leaves atom {bad[0]} with mass "
                                f"{m[bad[0]]:.4g} amu; choose a smaller hydrogen mass")
    return Repartition(m, np.array(sorted(set(hydrogens)), dtype=np.int64),
                       np.array(sorted(set(donors)), dtype=np.int64), m_h)


def rigid_waters(topology: Topology, constraints: DistanceConstraints) -> set[int]:
    """Residue ids of the waters (``HOH``) whose atoms are all pairwise constrained (rigid
    water: O-H, O-H and H-H), i.e. the residues OpenMM's ``hydrogenMass`` leaves alone.

    Parameters
    ----------
    topology : Topology
    constraints : DistanceConstraints

    Returns
    -------
    set of int
    """
    pairs = {(min(i, j), max(i, j)) for i, j in constraints.pairs.tolist()}
    members: dict[int, list[int]] = {}
    for i, (name, rid) in enumerate(zip(topology.residues, topology.residue_ids.tolist())):
        if name == "HOH" and topology.elements[i] is not None:
            members.setdefault(rid, []).append(i)
    out = set()
    for rid, atoms in members.items():
        if all((min(a, b), max(a, b)) in pairs for k, a in enumerate(atoms)
               for b in atoms[k + 1:]):
            out.add(rid)
    return out
