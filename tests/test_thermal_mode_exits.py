"""A bond that dissociates along a combination of coordinates leaves the well as a bond
along one coordinate does: escapes are seen along the normal modes at the minimum, whatever
the coordinates the bond is written in.

The systems: a Morse bond ``U = D expm1(-r / L)^2 / 2`` along ``r = c . q`` (between two
particles, ``c = (-1, 1)``; on a rotated axis, ``c = (1, 1)``; or along the first axis of
a random rotation of n coordinates) beside harmonic springs on the orthogonal combinations.
With equal masses the rotation keeps the kinetic energy diagonal, so r moves as the
one-coordinate bond ``H = p^2/2 + (1 - e^-q)^2/2`` of the same reduced mass (velocity
Verlet commutes with a linear change of coordinates that keeps the kinetic energy's form).

The reference is the test's own: velocity Verlet written here on all coordinates, from
exact Boltzmann draws (r by the inverse of its distribution function on a fine grid, the
springs' coordinates Gaussian, momenta N(0, kT M)); a trajectory has left when r passes
8 (U there is 0.9993 D) at any step, or ends unbound (bond energy above D) beyond r = 3.
Failure probabilities are bounded by Clopper-Pearson at 95%.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from thermal_support import boltzmann_1d, morse

from stepsafe.methods.library import resolve
from stepsafe.systems.thermal.bands import clopper_pearson
from stepsafe.systems.thermal.limit import thermal_check
from stepsafe.systems.thermal.potential import Potential, from_callables
from stepsafe.systems.thermal.sampling import axis_exits, mode_exits, split_exits, well_exits

VERLET = resolve("verlet")[0]
KT, STEPS, HOT, COOL = 0.0357, 50, 0.87, 0.5


def _bond(axes: np.ndarray, stiffness: np.ndarray, mass: float = 1.0, energy: float = 1.0,
          length: float = 1.0) -> Potential:
    """``U = energy (expm1(-x_0 / length)^2 + sum_k stiffness_k (x_k / length)^2) / 2`` with
    ``x = axes^T q`` (axes orthonormal columns), every mass ``mass``; its Hessian
    analytic."""
    n = axes.shape[0]
    k = np.concatenate([[0.0], stiffness])

    def energy_of(q):
        x = q @ axes / length
        return energy * 0.5 * (np.expm1(-x[:, 0]) ** 2 + np.sum(k * x * x, axis=1))

    def gradient(q):
        x = q @ axes / length
        g = k * x
        g[:, 0] = -np.exp(-x[:, 0]) * np.expm1(-x[:, 0])
        return energy / length * g @ axes.T

    def hessian(q):
        x = q @ axes / length
        c = np.broadcast_to(k, x.shape).copy()
        c[:, 0] = np.exp(-x[:, 0]) * (2.0 * np.exp(-x[:, 0]) - 1.0)
        return energy / length ** 2 * np.einsum("ik,mk,jk->mij", axes, c, axes)

    return from_callables(energy_of, gradient, np.full(n, mass), minimum=np.zeros(n),
                          hessian=hessian)


def _reference(axes: np.ndarray, stiffness: np.ndarray, h: float, count: int = 8000,
               seed: int = 5, kT: float = KT, steps: int = STEPS) -> tuple[int, int]:
    """(left, trajectories) of the test's own Verlet runs of :func:`_bond` in its units."""
    rng = np.random.default_rng(seed)
    n = axes.shape[0]
    x = np.empty((count, n))
    x[:, 0] = boltzmann_1d(lambda s: 0.5 * np.expm1(-s) ** 2, kT, count, rng, -1.5, 12.0)
    x[:, 1:] = rng.standard_normal((count, n - 1)) * np.sqrt(kT / stiffness)
    q = x @ axes.T
    p = rng.standard_normal((count, n)) * math.sqrt(kT)
    k = np.concatenate([[0.0], stiffness])

    def force(q):
        x = q @ axes
        f = -k * x
        f[:, 0] = np.exp(-x[:, 0]) * np.expm1(-x[:, 0])
        return f @ axes.T

    gone = np.zeros(count, dtype=bool)
    f = force(q)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            p += 0.5 * h * f
            q += h * p
            f = force(q)
            p += 0.5 * h * f
            r = q @ axes[:, 0]
            gone |= ~(np.isfinite(r) & (r <= 8.0))
    r, pr = q @ axes[:, 0], p @ axes[:, 0]
    unbound = (0.5 * pr * pr + 0.5 * np.expm1(-r) ** 2 > 0.5) & (r > 3.0)
    return int((gone | unbound).sum()), count


def _pair(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """The two-coordinate bonds in mass-weighted form: ``"difference"`` (r = q2 - q1 for
    masses 2, beside a weak spring on the centre of mass, omega 0.1) and ``"rotated"``
    (r = q1 + q2, a stiff spring on q1 - q2, omega 2)."""
    c = np.sqrt(0.5)
    if kind == "difference":
        return np.array([[-c, c], [c, c]]), np.array([0.01])
    return np.array([[c, c], [c, -c]]), np.array([4.0])


def _two_particles(kind: str) -> Potential:
    """The bond as written for two particles of mass 2 (``_pair`` in the coordinates
    ``q = y / sqrt(2)``)."""
    if kind == "difference":
        def energy(q):
            return 0.5 * np.expm1(q[:, 0] - q[:, 1]) ** 2 + 0.005 * (q[:, 0] + q[:, 1]) ** 2

        def gradient(q):
            r = q[:, 1] - q[:, 0]
            g = -np.exp(-r) * np.expm1(-r)
            centre = 0.01 * (q[:, 0] + q[:, 1])
            return np.stack([centre - g, centre + g], axis=1)
    else:
        def energy(q):
            return 0.5 * np.expm1(-(q[:, 0] + q[:, 1])) ** 2 + 2.0 * (q[:, 0] - q[:, 1]) ** 2

        def gradient(q):
            r = q[:, 0] + q[:, 1]
            g = -np.exp(-r) * np.expm1(-r)
            apart = 4.0 * (q[:, 0] - q[:, 1])
            return np.stack([g + apart, g - apart], axis=1)
    return from_callables(energy, gradient, [2.0, 2.0], minimum=[0.0, 0.0])


def test_the_two_particle_bonds_are_the_reference_bonds():
    """The bonds as written for two particles of mass 2 have the energy of the mass-weighted
    form at q = y / sqrt(2) (the reference integrates the latter)."""
    rng = np.random.default_rng(0)
    y = rng.normal(size=(50, 2))
    for kind in ("difference", "rotated"):
        axes, stiffness = _pair(kind)
        written = _two_particles(kind).energy(y / math.sqrt(2.0))
        assert np.allclose(written, _bond(axes, stiffness).energy(y), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("kind", ["difference", "rotated"])
def test_the_exit_of_a_bond_along_a_combination_is_found_along_its_mode(kind):
    """The bond's mode levels off at the one-coordinate bond's plateau, with the same
    energy. The coordinates' profiles do not, or (the difference, beside its weak spring)
    only where U has risen past the bond's depth, too far out for a short run to reach."""
    pot = _two_particles(kind)
    for axis in axis_exits(pot, KT):
        assert kind == "difference" and axis.energy > 2 * 0.5 and abs(axis.edge) > 16.0
    (found,) = mode_exits(pot, KT)
    (alone,) = axis_exits(morse(), KT)
    assert found.side * found.at > 0 and found.axis == -1
    assert math.isclose(abs(found.at), abs(alone.at), rel_tol=1e-9)
    assert math.isclose(found.energy, alone.energy, rel_tol=1e-6)
    assert math.isclose(found.omega, 1.0, rel_tol=1e-6)
    e = np.asarray(found.direction)
    assert math.isclose(abs(e @ _pair(kind)[0][:, 0]), 1.0, rel_tol=1e-9)


def test_a_mode_along_a_coordinate_is_walked_once():
    """The one-coordinate bond beside a spring, unrotated: its modes are the axes, so the
    exit is the axis's alone."""
    pot = _bond(np.eye(2), np.array([0.25]))
    assert len(axis_exits(pot, KT)) == 1
    assert mode_exits(pot, KT) == ()
    assert well_exits(pot, KT) == axis_exits(pot, KT)


@pytest.mark.parametrize("kind", ["difference", "rotated"])
def test_a_bond_along_a_combination_that_leaves_in_a_short_run_is_a_failure(kind):
    """kT/D = 0.071, 50 steps at h = 0.87: the test's own runs lose 0.3-0.4% of the bonds,
    above max_failure 0.001; thermal_check's 2995 trajectories see them leave (UNSAFE);
    at h = 0.5 none leaves in either."""
    axes, stiffness = _pair(kind)
    left, total = _reference(axes, stiffness, HOT)
    assert clopper_pearson(left, total)[0] > 0.0015
    pot = _two_particles(kind)
    hot = thermal_check(VERLET, pot, KT, HOT, steps=STEPS)
    assert not hot.safe
    (_, probe), = hot.probes
    assert probe.trajectories == 2995 and probe.failures >= 4
    assert _reference(axes, stiffness, COOL)[0] == 0
    cool = thermal_check(VERLET, pot, KT, COOL, steps=STEPS)
    assert cool.safe and cool.probes[0][1].failures == 0


def _rotation(n: int, seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((n, n)))
    return q * np.sign(np.diag(r))[None, :]


@pytest.mark.slow  # two checks per example, about 1.5 s of CPU each
@settings(max_examples=6, deadline=None)
@given(n=st.integers(2, 4), seed=st.integers(0, 2 ** 32 - 1),
       omegas=st.lists(st.sampled_from([0.3, 0.5, 0.7, 1.4, 2.0]), min_size=3, max_size=3),
       log_energy=st.floats(-100.0, 100.0), log_length=st.floats(-50.0, 50.0),
       log_mass=st.floats(-50.0, 50.0))
def test_a_rotated_bond_gets_the_one_coordinate_bonds_verdict_at_every_scale(
        n, seed, omegas, log_energy, log_length, log_mass):
    """The bond along the first axis of a random rotation of n coordinates, beside springs
    (frequencies apart from the bond's, so that its mode is one direction), with energy,
    length and mass scaled by powers of ten: at h = 0.87 (the reference loses 0.3-0.4%:
    about 11 of 2995 expected, none seen has probability near e^-11) UNSAFE, at h = 0.5 (no
    escape in the reference) SAFE, as the one-coordinate bond."""
    axes = _rotation(n, seed)
    stiffness = np.square(omegas[:n - 1])
    left, total = _reference(axes, stiffness, HOT)
    assert clopper_pearson(left, total)[0] > 0.001
    assert _reference(axes, stiffness, COOL)[0] == 0
    energy, length, mass = 10.0 ** log_energy, 10.0 ** log_length, 10.0 ** log_mass
    pot = _bond(axes, stiffness, mass, energy, length)
    unit = length * math.sqrt(mass / energy)
    for h, safe in ((HOT, False), (COOL, True)):
        alone = thermal_check(VERLET, morse(), KT, h, steps=STEPS)
        rotated = thermal_check(VERLET, pot, KT * energy, h * unit, steps=STEPS)
        assert alone.safe is safe and rotated.safe is safe


# --- a chain of bonds ---------------------------------------------------------------------


def _chain(bonds: int, spring: float = 0.005, energy: float = 1.0, length: float = 1.0,
           mass: float = 1.0) -> Potential:
    """``bonds`` Morse bonds ``q[i+1] - q[i]`` between particles of mass 2 (reduced mass 1
    each), a weak spring ``spring (sum q)^2`` on the centre of mass; energy, length and
    mass in units scaled by the given factors."""
    n = bonds + 1

    def energy_of(q):
        x = q / length
        return energy * (0.5 * np.sum(np.expm1(-np.diff(x, axis=1)) ** 2, axis=1)
                         + spring * np.sum(x, axis=1) ** 2)

    def gradient(q):
        x = q / length
        r = np.diff(x, axis=1)
        g = -np.exp(-r) * np.expm1(-r)
        out = np.zeros_like(q)
        out[:, :-1] -= g
        out[:, 1:] += g
        return energy / length * (out + 2 * spring * np.sum(x, axis=1)[:, None])

    return from_callables(energy_of, gradient, np.full(n, 2.0 * mass), minimum=np.zeros(n))


def _chain_starts(bonds: int, count: int, seed: int, kT: float = KT,
                  spring: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Exact draws of :func:`_chain` (the bond lengths are independent 1-D Boltzmann draws,
    the sum of q Gaussian: U is a sum over them and the change of variables is linear),
    momenta N(0, kT m)."""
    rng = np.random.default_rng(seed)
    n, m = bonds + 1, 2.0
    r = np.stack([boltzmann_1d(lambda s: 0.5 * np.expm1(-s) ** 2, kT, count, rng, -1.5, 12.0)
                  for _ in range(bonds)], axis=1)
    total = rng.standard_normal(count) * math.sqrt(kT / (2 * spring))
    q = np.concatenate([np.zeros((count, 1)), np.cumsum(r, axis=1)], axis=1)
    q += ((total - q.sum(axis=1)) / n)[:, None]
    return q, rng.standard_normal((count, n)) * math.sqrt(kT * m)


def _chain_leaves(q: np.ndarray, p: np.ndarray, h: float, steps: int = STEPS,
                  spring: float = 0.005) -> np.ndarray:
    """The test's own Verlet runs of :func:`_chain` from q, p: the mask of the trajectories
    that left (a bond passes 8, or ends unbound beyond 3: its pair's relative motion,
    reduced mass 1)."""
    m = 2.0
    pot = _chain(q.shape[1] - 1, spring)
    q, p = q.copy(), p.copy()
    gone = np.zeros(q.shape[0], dtype=bool)
    f = -pot.gradient(q)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            p += 0.5 * h * f
            q += h * p / m
            f = -pot.gradient(q)
            p += 0.5 * h * f
            gone |= ~(np.all(np.isfinite(q), axis=1) & np.all(np.diff(q, axis=1) <= 8.0,
                                                              axis=1))
    with np.errstate(all="ignore"):  # (rows that ran off overflow; they are gone already)
        r, v = np.diff(q, axis=1), np.diff(p / m, axis=1)
        unbound = np.any((0.5 * v * v + 0.5 * np.expm1(-r) ** 2 > 0.5) & (r > 3.0), axis=1)
    return gone | unbound


def _chain_reference(bonds: int, h: float, count: int = 8000, seed: int = 3
                     ) -> tuple[int, int]:
    """(left, trajectories) of the test's own runs of :func:`_chain`."""
    return int(_chain_leaves(*_chain_starts(bonds, count, seed), h).sum()), count


def test_the_failure_test_sees_the_chains_that_leave_in_the_reference():
    """The same 20000 exact starts of the two-bond chain (kT 0.04, 20 steps at h = 0.85)
    through stepsafe's run and the test's own: stepsafe's failures are the reference's
    (at least 80% of them seen, at most a fifth as many others)."""
    from stepsafe.systems.thermal.sampling import minimum_modes
    from stepsafe.systems.thermal.trajectories import Start, run

    kT, h, steps = 0.04, 0.85, 20
    q, p = _chain_starts(2, 20000, 3, kT)
    left = _chain_leaves(q, p, h, steps)
    assert left.sum() >= 20
    pot = _chain(2)
    rho = 1.0 / (1.0 - (h * float(minimum_modes(pot).omegas[-1])) ** 2 / 4.0)
    start = Start(q, p, kT, np.zeros(3), 0.0, np.max(np.abs(q), axis=0), 0, "exact",
                  well_exits(pot, kT))
    (out,) = run(VERLET, pot, start, [h], steps, [rho])
    seen = np.zeros(q.shape[0], dtype=bool)
    seen[list(out.failed)] = True
    assert (seen & left).sum() >= 0.8 * left.sum()
    assert (seen & ~left).sum() <= 0.2 * left.sum()


def test_a_chain_whose_bonds_leave_in_a_short_run_is_a_failure():
    """Two bonds in a chain: each can leave alone, along no normal mode (the symmetric
    stretch stretches both, the antisymmetric one compresses one). 50 steps at h = 0.87:
    the test's own runs lose 0.5-1% of the chains, check's trajectories see them leave
    where the groups part; at h = 0.5 the reference's failure probability is below
    max_failure (the rare leaving there is thermal: as many at h = 0.2) and check's runs
    lose none."""
    left, total = _chain_reference(2, HOT)
    assert clopper_pearson(left, total)[0] > 0.003
    pot = _chain(2)
    hot = thermal_check(VERLET, pot, KT, HOT, steps=STEPS)
    assert not hot.safe and hot.probes[0][1].failures >= 6
    left, total = _chain_reference(2, COOL)
    assert clopper_pearson(left, total)[1] < 0.001
    cool = thermal_check(VERLET, pot, KT, COOL, steps=STEPS)
    assert cool.safe and cool.probes[0][1].failures == 0


def test_the_chain_is_left_where_its_groups_part():
    """Every bond of a chain gives an exit where the particles before it part from those
    after, at the one-coordinate bond's plateau (energy and stretch; the bond's stretch is
    ``s / sqrt(mu)``, mu the reduced mass of the two groups)."""
    for bonds in (2, 3, 5):
        found = split_exits(_chain(bonds), KT)
        assert sorted(e.split for e in found) == list(range(1, bonds + 1))
        (alone,) = axis_exits(morse(), KT)
        for e in found:
            a, b = 2.0 * e.split, 2.0 * (bonds + 1 - e.split)
            stretch = abs(e.at) / math.sqrt(a * b / (a + b))
            assert math.isclose(e.energy, alone.energy, rel_tol=1e-6)
            assert math.isclose(stretch, abs(alone.at), rel_tol=1e-6)
            assert e.side * e.at > 0


@pytest.mark.parametrize("which", ["split", "mode"])
def test_a_row_leaves_past_the_exit_or_beyond_its_edge_with_more_energy_than_it(which):
    """Rows placed on the exit's direction: past ``at`` they have left; between the edge
    and ``at`` they have left with the outward speed that makes their energy along the
    direction exceed the exit's, not at rest; short of the edge they have not."""
    from stepsafe.systems.thermal.trajectories import leaving, thermal_start

    pot = _chain(2) if which == "split" else _two_particles("rotated")
    start = thermal_start(pot, KT, 8, configurations=np.zeros((8, pot.dimension)))
    exits = [e for e in start.exits if (e.split > 0) == (which == "split")
             and e.direction is not None]
    assert exits
    test = leaving(pot, start)
    for e in exits:
        d = np.asarray(e.direction) / np.sqrt(pot.masses)
        s = np.array([1.001 * e.at, 0.5 * (e.edge + e.at), 0.5 * (e.edge + e.at),
                      0.9 * e.edge])
        q = s[:, None] * d[None, :]
        u = pot.energy(q)
        p = np.zeros_like(q)
        speed = math.sqrt(2.0 * (e.energy - u[1]) + 2.0 * KT)
        p[1] = e.side * speed * d * pot.masses  # (s' = e . p / sqrt(m))
        assert test.leaves(q, p).tolist() == [True, True, False, False]


@pytest.mark.slow  # two checks of a Langevin-drawn chain per example, about 1 s each
@settings(max_examples=4, deadline=None)
@given(bonds=st.integers(2, 3), log_energy=st.floats(-100.0, 100.0),
       log_length=st.floats(-50.0, 50.0), log_mass=st.floats(-50.0, 50.0))
def test_a_chain_gets_its_verdicts_at_every_scale(bonds, log_energy, log_length, log_mass):
    """The chain with energy, length and mass scaled by powers of ten: UNSAFE at h = 0.87
    (the reference loses 0.5-1% of the chains: about 20 of 2995 expected) and SAFE at
    h = 0.5 (the reference's failure probability below max_failure), in its units."""
    for h in (HOT, COOL):
        left, total = _chain_reference(bonds, h)
        low, high = clopper_pearson(left, total)
        assert low > 0.003 if h == HOT else high < 0.001
    energy, length, mass = 10.0 ** log_energy, 10.0 ** log_length, 10.0 ** log_mass
    unit = length * math.sqrt(mass / energy)
    pot = _chain(bonds, energy=energy, length=length, mass=mass)
    assert not thermal_check(VERLET, pot, KT * energy, HOT * unit, steps=STEPS).safe
    assert thermal_check(VERLET, pot, KT * energy, COOL * unit, steps=STEPS).safe
