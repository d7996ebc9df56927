"""Configurations of a potential at temperature: draws from ``exp(-U(q) / kT)``.

Three ways, the most exact that applies:

* **quadratic U** (``U = U0 + x^T K x / 2``, ``x = q - q0``, K positive definite): exact
  Gaussian draws ``x = sqrt(kT) L^-T xi`` with ``K = L L^T`` (Cholesky), ``xi ~ N(0, I)``;
* **one coordinate**: exact draws by the inverse of the distribution function, tabulated by
  the trapezoid rule on a uniform grid over the well of the minimum up to ``U - U(q0) =
  cut kT`` on both sides (the mass beyond is below ``e^-cut`` relative); a barrier below
  that is crossed, and the grid covers the basins beyond it up to the wall where U rises
  ``cut kT`` above the lowest of them (:func:`well`);
* otherwise **Langevin dynamics**, BAOAB (Leimkuhler & Matthews 2013): with ``F = -grad U``
  and ``c = exp(-gamma h)``, one step is ``p += h F / 2; q += h M^-1 p / 2;
  p = c p + sqrt((1 - c^2) kT) M^1/2 xi; q += h M^-1 p / 2; p += h F / 2``. Its
  configurations sample ``exp(-U / kT)`` exactly for a quadratic U at every stable step and
  with an O(h^2) bias otherwise; the step is conservative, ``h = z_sample / omega_max`` with
  ``omega_max`` the largest 0 K frequency at the minimum (default ``z_sample = 0.1``), and the
  friction ``gamma = 2 omega_min`` damps the slowest 0 K mode critically (every other mode is
  underdamped and relaxes at the rate gamma). Chains start from the harmonic
  approximation's exact draws (a configuration near equilibrium; at the minimum where U
  exceeds that approximation by more than ``CUT`` kT, as in a curved valley whose
  harmonic draws run into its wall) with thermal momenta, are
  run ``burn_in`` steps (``burn_damping / (gamma h)``: that many relaxation times), and
  ``U`` along the second half of the burn-in gives its integrated autocorrelation time
  ``tau`` (in steps; Sokal's automatic window, ``W >= 5 tau``; the burn-in is doubled, up
  to six times, until that record spans ``SPAN tau``, else a note says so). Frames are then
  taken every ``thin = ceil(2 tau)`` steps, several chains advancing together as rows of
  one array. The minimum's curvature may misjudge the slowest motion (a narrow dimple in
  a wide flat region), so ``FAR`` more chains start dispersed (:func:`dispersed`: where
  the profiles along the coordinates and the normal modes first rise ``RISE`` kT) with a
  generator of their own, and at the end of the burn-in both groups must agree on the
  mean and spread of every coordinate and of U (:func:`disagreement` below ``AGREE``).
  When they do not, the friction of the coordinates whose profiles rise slowly is lowered
  to the frequency those profiles suggest and the burn-in is run again, doubled up to
  ``DOUBLINGS`` times, until they do (with a note), else the draws are refused.

Every draw comes from ``numpy.random.default_rng(seed)`` in a fixed order: the same seed
gives the same configurations, bit for bit, on one machine.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.systems.thermal.extremes import integrated_time
from stepsafe.systems.thermal.inm import EXACT_UP_TO, Modes, modes
from stepsafe.systems.thermal.potential import Potential, mode_direction, profile

#: The well is tabulated up to this many kT above the minimum (1-D exact draws).
CUT = 40.0
#: A side of a 1-D well where U levels off ends this many thermal amplitudes out ...
REACH = 64
#: ... where U must be at least this many kT above the minimum.
PLATEAU = 12.0
#: Past a barrier below the cut, the walk goes on this many times further for the wall
#: that confines the basins beyond it.
BEYOND = 4
#: A normal mode whose mass-weighted unit vector has a component whose square exceeds
#: ``1 - AXIS_ALONG`` lies along that coordinate (its profile is the coordinate's).
AXIS_ALONG = 1e-9
#: Beyond ``EXACT_UP_TO`` coordinates, the profiles along this many of the fastest modes are
#: walked for exits (Lanczos finds no more at a bounded cost).
MODE_EXITS_LARGE = 3
#: Relaxed profiles (:func:`relaxed_exits`) are walked for at most this many coordinates
#: (every direction's walk costs ``O(n^2)`` a step: ``O(n^3)`` in all).
RELAXED_UP_TO = 128
#: A relaxed valley whose floor at its exit lies along a straight exit's direction (squared
#: cosine above ``1 - ALONG_LINE``) at no lower energy is that exit, walked already.
ALONG_LINE = 1e-4
#: A floor that moves more than this many times the step in s jumped to another branch of
#: the hyperplane's minima (a fall there is no barrier).
JUMP = 8.0
#: Newton steps on the floor of a relaxed profile at each of its points ...
RELAX_STEPS = 2
#: ... and its points, a quarter of the thermal spread of s apart (out to ``REACH`` spreads).
RELAX_POINTS = 4 * REACH
#: Points of the walk's first look out from the minimum (16 thermal amplitudes; a side
#: rising to the cut within them is settled by them).
FIRST = 128
#: Points over +-4 thermal amplitudes where a 1-D U must be resolved in float64 ...
RESOLVE = 801
#: ... its rounding noise below this many kT.
NOISE = 1e-5
#: Grid points of the 1-D distribution function.
GRID = 20001
#: Langevin step in units of the fastest 0 K period: ``h = Z_SAMPLE / omega_max``.
Z_SAMPLE = 0.1
#: Burn-in, in relaxation times ``1 / gamma``.
BURN_DAMPING = 10.0
#: The burn-in's record of U must span this many autocorrelation times (per chain; the
#: chains' autocorrelations are averaged).
SPAN = 20
#: Chains run side by side.
CHAINS = 64
#: Largest n whose quadratic potential is drawn exactly (a dense Cholesky factor).
GAUSSIAN_UP_TO = 4096
#: Dispersed chains start where a profile through the minimum first rises this many kT ...
RISE = 4.0
#: ... and this many of them run beside the chains started near the minimum.
FAR = 32
#: The near and the dispersed chains must agree on the mean and the spread of every
#: coordinate and of U within this many standard errors (:func:`disagreement`) ...
AGREE = 6.0
#: ... and while it is not, the burn-in is doubled, at most this many times.
DOUBLINGS = 5
#: ... and the steps run to mix are bounded by this (or eight times the first burn-in).
MIX_STEPS = 1 << 18
#: The profiles of the dispersed starts are walked geometrically up to 2^FARTHEST times
#: their linear reach.
FARTHEST = 30
#: Snapshots of the chains kept per burn-in stage for :func:`disagreement`.
SNAPSHOTS = 64


@dataclass(frozen=True)
class Ensemble:
    """Configurations drawn at temperature and how they were made.

    Attributes
    ----------
    q : ndarray
        Configurations ``(m, n)``.
    chain : ndarray
        The chain each configuration comes from ``(m,)`` (all different for independent
        draws): resampling whole chains keeps their correlation in a bootstrap.
    kT : float
    how : str
        ``"exact Gaussian"``, ``"exact 1-D (inverse distribution function)"`` or
        ``"Langevin (BAOAB)"``.
    seed : int
    h, friction : float or None
        Langevin's step and friction gamma.
    burn_in, thin : int
        Langevin steps before the first frame and between frames.
    tau : float or None
        Integrated autocorrelation time of U along the chains, in steps.
    chains : int
    notes : tuple of str
    """

    q: np.ndarray
    chain: np.ndarray
    kT: float
    how: str
    seed: int
    h: float | None = None
    friction: float | None = None
    burn_in: int = 0
    thin: int = 0
    tau: float | None = None
    chains: int = 0
    notes: tuple[str, ...] = ()

    @property
    def size(self) -> int:
        return int(self.q.shape[0])


def momenta(pot: Potential, kT: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """``p ~ N(0, kT M)``: thermal momenta ``(count, n)``."""
    return rng.standard_normal((count, pot.dimension)) * np.sqrt(kT * pot.masses)


def minimum_modes(pot: Potential) -> Modes:
    """The normal modes at the potential's minimum (all of them for small n, the fastest
    otherwise); a :class:`StepsafeError` if there is no minimum or it is not one."""
    if pot.minimum is None:
        raise StepsafeError("the thermal analysis needs the potential's minimum")
    found = modes(pot, pot.minimum)
    if not (np.all(np.isfinite(found.eigenvalues)) and np.isfinite(found.error)):
        raise StepsafeError("the curvature at the minimum is not finite (it overflows "
                            "float64)")
    if found.eigenvalues[-1] <= found.error:
        raise StepsafeError("the Hessian at the minimum has no positive curvature: no "
                            "frequency to start from")
    return found


def draw(pot: Potential, kT: float, count: int, seed: int = 0, chains: int = CHAINS,
         z_sample: float = Z_SAMPLE, friction: float | None = None,
         burn_damping: float = BURN_DAMPING) -> Ensemble:
    """At least ``count`` configurations of ``exp(-U / kT)`` (see the module docstring for
    which way and its conventions).

    Parameters
    ----------
    pot : Potential
        With its minimum.
    kT : float
        The thermal energy (> 0).
    count : int
        Configurations wanted (Langevin rounds up to a multiple of ``chains``).
    seed : int
        Of the random generator.
    chains : int
        Langevin chains.
    z_sample : float
        Langevin step times the fastest 0 K frequency.
    friction : float, optional
        Langevin's gamma (default: twice the slowest 0 K frequency).
    burn_damping : float
        Burn-in in relaxation times.

    Returns
    -------
    Ensemble
    """
    kT = positive_finite(kT, "kT")
    count = int(count)
    if count < 1:
        raise StepsafeError(f"count must be at least 1, got {count}")
    rng = np.random.default_rng(seed)
    if pot.quadratic and pot.dimension <= GAUSSIAN_UP_TO:
        return Ensemble(gaussian(pot, kT, count, rng), np.arange(count), kT, "exact Gaussian",
                        seed)
    if pot.dimension == 1:
        q, notes = one_dimensional(pot, kT, count, rng)
        return Ensemble(q, np.arange(count), kT, "exact 1-D (inverse distribution function)",
                        seed, notes=notes)
    return langevin(pot, kT, count, rng, seed, chains, z_sample, friction, burn_damping)


def gaussian(pot: Potential, kT: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """Exact draws of a quadratic potential: ``q0 + sqrt(kT) L^-T xi`` (``K = L L^T``)."""
    from scipy.linalg import solve_triangular

    q0 = pot.minimum if pot.minimum is not None else np.zeros(pot.dimension)
    if pot.hessian is None:
        raise StepsafeError("exact Gaussian draws need the quadratic potential's Hessian")
    K = np.asarray(pot.hessian(q0[None, :])[0], dtype=float)
    try:
        L = np.linalg.cholesky(0.5 * (K + K.T))
    except np.linalg.LinAlgError:
        raise StepsafeError("the quadratic potential is not positive definite: its "
                            "Boltzmann distribution does not exist") from None
    xi = rng.standard_normal((pot.dimension, count))
    return q0[None, :] + math.sqrt(kT) * solve_triangular(L, xi, trans="T", lower=True).T


@dataclass(frozen=True)
class Exit:
    """A side of a 1-D well that does not confine: U levels off (a dissociation plateau) or
    falls past a barrier before it rises ``cut kT`` (:func:`well`); for a system of several
    coordinates, a side of its profile along a coordinate (:func:`axis_exits`), a normal
    mode at the minimum (:func:`mode_exits`) or a split of the coordinates in two groups
    (:func:`split_exits`).

    Attributes
    ----------
    side : float
        -1 (below the minimum) or +1 (above).
    at : float
        Where the well ends on that side: the barrier's top, or where U levels off.
    energy : float
        ``U(at) - U(q0)``: the energy above the minimum that leaves the well there.
    edge : float
        The first point out from the minimum where ``U - U(q0)`` reaches ``energy - kT``:
        beyond it a trajectory of energy above ``energy`` is not turned back by the well.
    axis : int
        The coordinate (0 for one; -1 along a mode or a split); for a system of several
        coordinates ``at`` and ``edge`` are positions ``s`` on the profile
        ``u(s) = U(q0 + s M^-1/2 e)``: ``s = e . M^1/2 (q - q0)``, for a coordinate
        ``sqrt(m) (q - q0)`` of that coordinate.
    direction : tuple of float, optional
        The mass-weighted unit vector e of the profile (None along a coordinate).
    omega : float
        Along a normal mode, its frequency at the minimum (else NaN).
    split : int
        Along :func:`split_direction`, the first coordinate of the second group (else 0).
    valley : ndarray, optional
        Along a relaxed profile (:func:`relaxed_exits`), the displacement ``q - q0`` of its
        floor ``(k, n)`` at ``s = side * j * spacing``, ``j = 0..k-1`` (None along a straight
        profile, whose displacement is ``s M^-1/2 e``).
    spacing : float
        The spacing of ``valley`` in s (NaN along a straight profile).
    """

    side: float
    at: float
    energy: float
    edge: float
    axis: int = 0
    direction: tuple[float, ...] | None = None
    omega: float = math.nan
    split: int = 0
    valley: np.ndarray | None = field(default=None, compare=False, repr=False)
    spacing: float = math.nan


def well(pot: Potential, kT: float, cut: float = CUT
         ) -> tuple[float, float, tuple[str, ...]]:
    """The interval around a 1-D minimum where ``U - U_low < cut kT`` (``U_low`` the lowest
    U met so far: ``U(q0)``, or a lower basin's), found by walking out from ``q0`` in steps
    of an eighth of the thermal amplitude ``a = sqrt(kT / U'')``, up to ``REACH a`` (and
    ``BEYOND`` times further once U has fallen past a barrier).

    A side where U falls before ``cut kT`` (a barrier to another basin) goes on over the
    barrier: when U rises again ``cut kT`` above the lowest U met, the side ends there and
    the interval holds both basins (the distribution is confined by the walls beyond; a
    barrier of a few kT is crossed by every run). A side where U never rises that far ends
    at the barrier's top, one where U levels off (a dissociation plateau) at ``REACH a``;
    there ``U - U(q0)`` must be at least ``PLATEAU kT`` (the density left out is below
    ``e^-PLATEAU`` of the peak there), else the distribution is not confined at this
    temperature (a :class:`StepsafeError`). Returns ``(lo, hi, notes)``.
    """
    lo, hi, notes, _ = _walk(pot, kT, cut)
    return lo, hi, notes


def exits(pot: Potential, kT: float, cut: float = CUT) -> tuple[Exit, ...]:
    """The sides of a 1-D well at ``kT`` that end at a plateau or a barrier's top, not at
    a wall (:func:`well`, :class:`Exit`): where a trajectory leaves the well."""
    return _walk(pot, kT, cut)[3]


def axis_exits(pot: Potential, kT: float, cut: float = CUT) -> tuple[Exit, ...]:
    """The exits of the profiles along each coordinate through the minimum,
    ``u(s) = U(q0 + s e_i / sqrt(m_i))`` (:func:`exits`; positions in s): where a
    trajectory leaves along one coordinate. A profile whose well the walk cannot bound
    (not confined, not resolved, not finite) gives none."""
    if pot.minimum is None:
        return ()
    out: list[Exit] = []
    for i in range(pot.dimension):
        e = np.zeros(pot.dimension)
        e[i] = 1.0
        out += [dataclasses.replace(x, axis=i) for x in _profile_exits(pot, e, kT, cut)]
    return tuple(out)


def mode_exits(pot: Potential, kT: float, cut: float = CUT) -> tuple[Exit, ...]:
    """The exits of the profiles along the normal modes at the minimum,
    ``u(s) = U(q0 + s M^-1/2 e)`` for each unit eigenvector e of the mass-weighted Hessian
    (:func:`exits`; positions in s): where a trajectory leaves along a combination of
    coordinates, as a bond written as the difference of two of them dissociates. Every
    mode for ``n <= EXACT_UP_TO`` (one eigendecomposition), the ``MODE_EXITS_LARGE``
    fastest beyond (Lanczos); a mode of curvature not above its error bound (a free
    direction) is left out, and so is one that lies along a coordinate (``e_i^2 > 1 -
    AXIS_ALONG``: :func:`axis_exits` walks that profile). None for one coordinate, or where
    the modes at the minimum cannot be found."""
    return _directed_exits(pot, kT, cut, [(e, {"omega": omega})
                                          for e, omega in _mode_directions(pot)])


def _directed_exits(pot: Potential, kT: float, cut: float,
                    directed: list[tuple[np.ndarray, dict[str, Any]]]) -> tuple[Exit, ...]:
    """The exits of the profiles along each unit mass-weighted direction e given, each
    with e and the given fields recorded."""
    out: list[Exit] = []
    for e, fields in directed:
        out += [dataclasses.replace(x, axis=-1, direction=tuple(float(v) for v in e),
                                    **fields) for x in _profile_exits(pot, e, kT, cut)]
    return tuple(out)


def _minimum_modes(pot: Potential) -> Modes | None:
    """The normal modes at the minimum that :func:`mode_exits` walks (every mode for
    ``n <= EXACT_UP_TO``, the ``MODE_EXITS_LARGE`` fastest beyond); None for one
    coordinate, without a minimum, or where they cannot be found."""
    n = pot.dimension
    if pot.minimum is None or n == 1:
        return None
    try:
        found = modes(pot, pot.minimum, count=None if n <= EXACT_UP_TO else MODE_EXITS_LARGE)
    except StepsafeError:
        return None
    return found


def _mode_directions(pot: Potential) -> list[tuple[np.ndarray, float]]:
    """The unit mass-weighted directions :func:`mode_exits` walks, with their frequencies."""
    found = _minimum_modes(pot)
    if found is None or not (np.all(np.isfinite(found.eigenvalues))
                             and np.isfinite(found.error)):
        return []
    out = []
    for j in range(found.eigenvalues.size):
        e = found.vectors[:, j] / np.linalg.norm(found.vectors[:, j])
        if not found.eigenvalues[j] > found.error or np.max(e * e) > 1.0 - AXIS_ALONG:
            continue
        out.append((e, math.sqrt(float(found.eigenvalues[j]))))
    return out


def split_direction(masses: np.ndarray, k: int) -> np.ndarray:
    """The mass-weighted unit vector e that moves coordinates ``0..k-1`` rigidly against
    ``k..n-1`` at a fixed centre of mass: ``q - q0 = s M^-1/2 e`` shifts the first group by
    ``-s t M_B`` and the second by ``s t M_A`` (``M_A``, ``M_B`` their masses, ``M`` the
    sum, ``t = 1 / sqrt(M_A M_B M)``), so that ``s = e . M^1/2 (q - q0) = t (M_A S_B -
    M_B S_A)`` with ``S = sum m_j (q_j - q0_j)`` over each group: ``sqrt(M_A M_B / M)``
    times the distance between the groups' centres of mass."""
    m = np.asarray(masses, dtype=float)
    return split_shifts(m, k) * np.sqrt(m)


def split_shifts(masses: np.ndarray, k: int) -> np.ndarray:
    """``M^-1/2 e`` of :func:`split_direction`: ``-t M_B`` on the first k coordinates,
    ``t M_A`` on the others."""
    m = np.asarray(masses, dtype=float)
    a, b = float(np.sum(m[:k])), float(np.sum(m[k:]))
    # (t M_B and t M_A as ratios: M_A M_B M may overflow or underflow)
    whole = a + b
    return np.where(np.arange(m.size) < k, -math.sqrt(b / whole) / math.sqrt(a),
                    math.sqrt(a / whole) / math.sqrt(b))


def split_exits(pot: Potential, kT: float, cut: float = CUT) -> tuple[Exit, ...]:
    """The exits of the profiles along :func:`split_direction` for ``k = 1..n-1``: where
    the coordinates before k and from k on part, as a chain of bonds written
    ``q[i+1] - q[i]`` dissociates at one of its bonds (a direction no normal mode of the
    chain follows: each stretches some bonds and compresses others). Directions that lie
    along a coordinate or a normal mode at the minimum (squared cosine above ``1 -
    AXIS_ALONG``) are left out: those profiles are walked already."""
    return _directed_exits(pot, kT, cut, [(e, {"split": k})
                                          for e, k in _split_directions(pot)])


def _split_directions(pot: Potential) -> list[tuple[np.ndarray, int]]:
    """The unit mass-weighted directions :func:`split_exits` walks, with their k."""
    n = pot.dimension
    if pot.minimum is None or n == 1:
        return []
    found = _minimum_modes(pot)
    walked = np.zeros((n, 0)) if found is None else found.vectors
    out = []
    for k in range(1, n):
        e = split_direction(pot.masses, k)
        e = e / np.linalg.norm(e)
        if np.max(e * e) > 1.0 - AXIS_ALONG or (
                walked.shape[1] and np.max((e @ walked) ** 2) > 1.0 - AXIS_ALONG):
            continue
        out.append((e, k))
    return out


def well_exits(pot: Potential, kT: float, cut: float = CUT) -> tuple[Exit, ...]:
    """Where a trajectory leaves the well of the minimum: :func:`axis_exits`,
    :func:`mode_exits` and :func:`split_exits`, and :func:`relaxed_exits` along the same
    directions where their valleys leave lower."""
    straight = axis_exits(pot, kT, cut) + mode_exits(pot, kT, cut) + split_exits(pot, kT, cut)
    return straight + relaxed_exits(pot, kT, straight, cut)


def relaxed_exits(pot: Potential, kT: float, straight: tuple[Exit, ...] = (),
                  cut: float = CUT) -> tuple[Exit, ...]:
    """The exits of the *relaxed* profiles along the directions of :func:`axis_exits`,
    :func:`mode_exits` and :func:`split_exits`: where a trajectory leaves the well along a
    curved valley, which no straight line through the minimum follows.

    In mass-weighted coordinates ``y = M^1/2 (q - q0)`` the relaxed profile along a unit
    vector e is ``u(s) = min U(q0 + M^-1/2 (s e + w))`` over ``w`` orthogonal to e: the
    lowest U on the hyperplane ``e . y = s``, never above the straight profile (``w = 0``).
    A trajectory that crosses that hyperplane has at least ``u(s)`` there, so a barrier top
    or plateau E of u is the least energy that leaves the well along e, whatever the path.
    The walk goes out from the minimum in steps of a quarter of the thermal spread of s,
    ``a = sqrt(kT e^T W^-1 e)`` (W the mass-weighted Hessian at the minimum: the standard
    deviation of s in the harmonic approximation), up to ``RELAX_POINTS = 4 REACH`` steps.
    At each s the floor ``w`` starts from the lowest of the previous s's floor, its linear
    extrapolation and 0 (so u never exceeds the straight profile), and takes
    ``RELAX_STEPS`` Newton steps of the minimum's curvature restricted to the hyperplane,
    ``dw = -(W^-1 - c c^T / (e . c)) g`` with ``c = W^-1 e`` and ``g = M^-1/2 grad U`` (the
    exact minimiser of a quadratic U in one step; ``e . dw = 0``), each halved until U does
    not rise. A minimum not reached gives a u above the true one: the walk then finds an
    exit no lower than the true valley's, or none, as a straight profile would.

    A side ends at a wall where ``u - min(0, lowest u met)`` reaches ``cut kT`` with no fall
    of more than kT before it (confined), or, past such a fall (a barrier), where u rises
    again that far above the lowest u met (the basins beyond are drawn: no exit); otherwise
    a barrier's top, or where u levels off at ``RELAX_POINTS`` steps, is an exit when it is at
    least ``PLATEAU kT`` above the minimum (a lower one is left to the straight walks and
    the draws). Its ``edge`` is the first point where u reaches ``energy - kT``, and
    ``valley`` holds the floor's displacement up to the exit.

    Only exits below those of the straight walk of the same direction and side by more than
    kT are returned (``straight``: the exits found so; a relaxed profile is never above
    the straight one, and where they agree the straight exit stands), and of those only
    the ones whose floor at the exit does not lie along a straight exit's direction
    (squared cosine ``1 - ALONG_LINE``) at an energy above that exit's less kT (the same
    straight valley, reached from another direction). The walks of every
    direction and side run together as rows of one array: per step, ``1 + 2 RELAX_STEPS``
    evaluations of U or its gradient on up to ``6 n`` rows (the first on three times as
    many) and ``RELAX_STEPS`` products with an ``n x n`` matrix; beyond ``RELAXED_UP_TO``
    coordinates (or where the Hessian at the minimum is not positive definite) no relaxed
    walk is made.

    Parameters
    ----------
    pot : Potential
        With its minimum.
    kT : float
    straight : tuple of Exit
        The straight profiles' exits of the same directions.
    cut : float
        The wall, in kT.

    Returns
    -------
    tuple of Exit
        With ``axis`` (the coordinate, -1 for a mode or a split), ``direction`` (always set),
        ``omega``, ``split``, ``valley`` and ``spacing``.
    """
    n = pot.dimension
    if pot.minimum is None or n == 1 or n > RELAXED_UP_TO:
        return ()
    try:
        found = modes(pot, pot.minimum)
    except StepsafeError:
        return ()
    lam = found.eigenvalues
    if not (lam.size == n and np.all(np.isfinite(lam)) and np.isfinite(found.error)
            and lam[0] > found.error):
        return ()
    directions: list[tuple[np.ndarray, int, float, int]] = []  # (e, axis, omega, split)
    for i in range(n):
        e = np.zeros(n)
        e[i] = 1.0
        directions.append((e, i, math.nan, 0))
    directions += [(e, -1, omega, 0) for e, omega in _mode_directions(pot)]
    directions += [(e, -1, math.nan, k) for e, k in _split_directions(pot)]
    walks = [(d, sign) for d in range(len(directions)) for sign in (-1.0, 1.0)]
    unit = np.array([directions[d][0] * sign for d, sign in walks])
    u, jumped, spacing, _ = _relax(pot, kT, lam, found.vectors, unit, cut, record=False)
    keep: list[tuple[int, tuple[int, float, int]]] = []
    for w in range(len(walks)):
        end = _relaxed_end(u[w], jumped[w], cut)
        if end is None:
            continue
        d, sign = walks[w]
        e, axis = directions[d][0], directions[d][1]
        rival = [x.energy for x in straight if x.side == sign and _same(x, e, axis)]
        if rival and not end[1] * kT < min(rival) - kT:
            continue
        keep.append((w, end))
    if not keep:
        return ()
    chosen = np.array([w for w, _ in keep])
    _, _, _, path = _relax(pot, kT, lam, found.vectors, unit[chosen], cut, record=True)
    out = []
    root = np.sqrt(pot.masses)
    lines = [(x.side * _unit_of(x, n), x.energy) for x in straight]
    for j, (w, (top, energy, edge)) in enumerate(keep):
        floor = path[j, top] / np.linalg.norm(path[j, top])
        if any(float(line @ floor) ** 2 > 1.0 - ALONG_LINE and energy * kT >= low - kT
               for line, low in lines if float(line @ floor) > 0):
            continue  # (a valley that runs straight out along a walked exit: that exit)
        d, sign = walks[w]
        e, axis, omega, split = directions[d]
        ds = float(spacing[w])
        out.append(Exit(sign, sign * top * ds, energy * kT, sign * edge * ds, axis,
                        tuple(float(v) for v in e), omega, split,
                        path[j, :top + 1] / root[None, :], ds))
    return tuple(out)


def _unit_of(x: Exit, n: int) -> np.ndarray:
    """The mass-weighted unit vector of a straight exit's direction."""
    if x.direction is not None:
        return np.asarray(x.direction, dtype=float)
    e = np.zeros(n)
    e[x.axis] = 1.0
    return e


def _same(x: Exit, e: np.ndarray, axis: int) -> bool:
    """Whether the straight exit x is along the direction e (coordinate ``axis``, or -1)."""
    if x.direction is None:
        return axis >= 0 and x.axis == axis
    return axis < 0 and bool(np.array_equal(np.asarray(x.direction), e))


def _relax(pot: Potential, kT: float, lam: np.ndarray, vectors: np.ndarray,
           unit: np.ndarray, cut: float, record: bool
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The relaxed walks of :func:`relaxed_exits` along the rows of ``unit`` (signed unit
    directions ``(w, n)``; ``lam``, ``vectors``: every mode at the minimum): ``(u, jumped,
    spacing, path)``, ``u`` the profiles in kT above the minimum at ``s = j * spacing``, ``j =
    0..RELAX_POINTS`` (``(w, RELAX_POINTS + 1)``, NaN past a walk's wall), ``jumped``
    where the floor moved more than ``JUMP`` steps in s (same shape), ``spacing``
    ``(w,)``, and, when ``record``, the floors ``y = s e + w`` ``(w, RELAX_POINTS + 1, n)``
    (else empty)."""
    q0 = np.asarray(pot.minimum, dtype=float)
    root = np.sqrt(pot.masses)
    count, n = unit.shape
    top = float(lam[-1])
    rel = lam / top
    eV = unit @ vectors  # (e in the modes' basis)
    spread = np.sqrt(np.sum(eV * eV / rel[None, :], axis=1))
    step = math.sqrt(kT / top) * spread / 4.0  # (a quarter of the thermal spread of s)
    # W^-1 top and c / (e . c) with c = W^-1 e, in y: scale-free
    inverse = (vectors / rel[None, :]) @ vectors.T
    lead = ((eV / rel[None, :]) @ vectors.T) / (spread ** 2)[:, None]
    u0 = float(pot.energy(q0[None, :])[0])
    last = RELAX_POINTS

    def level(y: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            v = (pot.energy(q0[None, :] + y / root[None, :]) - u0) / kT
        return np.where(np.isnan(v), np.inf, v)

    u = np.full((count, last + 1), np.nan)
    u[:, 0] = 0.0
    jump = np.zeros((count, last + 1), dtype=bool)
    path = np.zeros((count, last + 1, n) if record else (0, 0, 0))
    w = np.zeros((count, n))
    before = np.zeros((count, n))
    low = np.zeros(count)
    live = np.arange(count)
    for j in range(1, last + 1):
        if not live.size:
            break
        base = (j * step[live])[:, None] * unit[live]
        guesses = np.stack([w[live], 2.0 * w[live] - before[live], np.zeros((live.size, n))])
        values = level((base[None] + guesses).reshape(-1, n)).reshape(3, live.size)
        pick = np.argmin(values, axis=0)
        cur = values[pick, np.arange(live.size)]
        floor = guesses[pick, np.arange(live.size)]
        before[live] = w[live]
        eta = np.ones(live.size)
        for _ in range(RELAX_STEPS):
            with np.errstate(all="ignore"):
                g = pot.gradient(q0[None, :] + (base + floor) / root[None, :]) / root[None, :]
                m = (g / top) @ inverse
                move = m - lead[live] * np.sum(unit[live] * m, axis=1)[:, None]
                trial = floor - eta[:, None] * move
            value = level(base + trial)
            better = value < cur
            floor = np.where(better[:, None], trial, floor)
            cur = np.where(better, value, cur)
            eta = np.where(better, np.minimum(1.0, 2.0 * eta), 0.5 * eta)
        with np.errstate(invalid="ignore"):
            jump[live, j] = np.linalg.norm(floor - w[live], axis=1) > JUMP * step[live]
        w[live] = floor
        u[live, j] = cur
        if record:
            path[live, j] = base + floor
        low[live] = np.minimum(low[live], cur)
        with np.errstate(invalid="ignore"):
            done = ~np.isfinite(cur) | (cur - low[live] >= cut)
        live = live[~done]
    return u, jump, step, path


def _relaxed_end(u: np.ndarray, jumped: np.ndarray, cut: float
                 ) -> tuple[int, float, int] | None:
    """The exit of one relaxed walk's ``u`` (:func:`_relax`, in kT; ``jumped`` where its
    floor jumped): ``(index of the exit point, its u, index of the edge)``, or None
    (:func:`relaxed_exits`)."""
    u = u[:int(np.flatnonzero(~np.isnan(u))[-1]) + 1]
    if not np.all(np.isfinite(u)):
        return None
    highest = np.maximum.accumulate(u)
    low = np.minimum.accumulate(np.minimum(u, 0.0))
    falls = np.flatnonzero(u < highest - 1.0)
    if falls.size and np.any(jumped[int(np.argmax(u[:falls[0]])):falls[0] + 1]):
        falls = falls[:0]  # (the floor jumped to a lower branch: no barrier, the u before
        # it was above the hyperplane's least U)
    if falls.size:
        end = int(np.argmax(u[:falls[0]]))
        if np.any(u[falls[0]:] - low[falls[0]:] >= cut):
            return None  # (the basins beyond are confined by a wall: drawn)
    elif u[-1] - low[-1] >= cut or u.size < RELAX_POINTS + 1:
        return None  # (a wall)
    else:
        end = u.size - 1
    if not u[end] >= PLATEAU:
        return None
    edge = int(np.flatnonzero(u[:end + 1] >= u[end] - 1.0)[0])
    return end, float(u[end]), edge


def _profile_exits(pot: Potential, e: np.ndarray, kT: float, cut: float
                   ) -> tuple[Exit, ...]:
    """:func:`exits` of the profile along the mass-weighted unit vector e (none where the
    walk cannot bound its well)."""
    if pot.minimum is None:
        return ()
    try:
        return exits(profile(pot, pot.minimum, mode_direction(pot, e)), kT, cut)
    except StepsafeError:
        return ()


def _walk(pot: Potential, kT: float, cut: float
          ) -> tuple[float, float, tuple[str, ...], tuple[Exit, ...]]:
    """:func:`well` and :func:`exits` from one walk each side."""
    s0 = float(pot.minimum[0]) if pot.minimum is not None else 0.0
    u0 = float(pot.energy(np.array([[s0]]))[0])
    found = modes(pot, np.array([s0]))
    curvature = float(found.eigenvalues[-1]) * float(pot.masses[0])
    if not curvature > 0:
        raise StepsafeError("the potential has no positive curvature at its minimum")
    if curvature < sys.float_info.min:
        raise StepsafeError(f"the curvature at the minimum, {curvature:.3g}, is below "
                            f"float64's normal numbers (it keeps fewer digits than the "
                            f"analysis needs): give the potential in units where it is "
                            f"larger")
    amplitude = math.sqrt(kT / curvature)
    resolved(pot, s0, u0, amplitude, kT)
    step = amplitude / 8.0
    ends = []
    notes = []
    out: list[Exit] = []
    last = 8 * REACH
    for sign in (-1.0, 1.0):
        # the first FIRST points decide a side that rises to the cut (or stops being
        # finite) without falling on the way, the usual wall; any other side is walked
        # whole, as if that look had not been taken
        for size in (FIRST, BEYOND * last):
            k = np.arange(1, size + 1)
            s = s0 + sign * step * k
            with np.errstate(all="ignore"):
                u = pot.energy(s[:, None]) - u0
            bad = ~np.isfinite(u)
            near = slice(0, last)
            hit = np.flatnonzero((u[near] >= cut * kT) | bad[near])
            end = int(hit[0]) if hit.size else last - 1
            if hit.size and (bad[end] or not np.any(np.diff(u[:end + 1]) < 0)):
                break
        if hit.size and bad[end]:
            raise StepsafeError(f"U is not finite at {s[end]:.6g}, inside the well at "
                                f"kT = {kT:.6g}")
        falls = np.flatnonzero(np.diff(u[:end + 1]) < 0)
        if falls.size:  # a barrier below the cut: over it, does U rise again?
            low = np.minimum.accumulate(np.minimum(u, 0.0))
            with np.errstate(invalid="ignore"):  # (-inf - -inf where U falls without bound)
                wall = np.flatnonzero(bad | (u - low >= cut * kT))
            if wall.size and not bad[wall[0]] and low[wall[0]] < u[falls[0]]:
                ends.append(float(s[wall[0]]))
                notes.append(f"a barrier {u[falls[0]] / kT:.3g} kT above the minimum, at "
                             f"{s[falls[0]]:.6g}, below the {cut:g} kT drawn: the "
                             f"distribution is drawn over the basins beyond it too, up to "
                             f"{s[wall[0]]:.6g} where U rises {cut:g} kT above the lowest "
                             f"U met")
                continue
            end = int(falls[0])
        elif hit.size:
            ends.append(float(s[end]))
            continue
        if not u[end] >= PLATEAU * kT:
            raise StepsafeError(f"U rises only {u[end] / kT:.3g} kT above its minimum before "
                                f"it levels off or falls: the distribution at kT = {kT:.6g} "
                                f"is not confined")
        ends.append(float(s[end]))
        edge = int(np.flatnonzero(u[:end + 1] >= u[end] - kT)[0])
        out.append(Exit(sign, float(s[end]), float(u[end]), float(s[edge])))
        what = "a barrier" if falls.size else f"{REACH} thermal amplitudes"
        notes.append(f"U levels off or falls {u[end] / kT:.3g} kT above the minimum: the "
                     f"distribution is taken up to {what} (the density left out is below "
                     f"e^-{u[end] / kT:.3g} of the peak there)")
    return ends[0], ends[1], tuple(notes), tuple(out)


def resolved(pot: Potential, s0: float, u0: float, amplitude: float, kT: float) -> None:
    """A :class:`StepsafeError` unless float64 resolves the 1-D U at this kT: on ``RESOLVE``
    points over ``q0 +- 4 a`` (``a`` the thermal amplitude) U must vary (the curvature
    predicts 8 kT at the ends; a U that float64 holds constant there, as
    ``(1 - exp(-q))^2 / 2`` at kT below about 1e-32, is not resolved), and the rounding
    noise of the computed U, estimated from its fourth differences
    (``sqrt(mean(d4^2) / 70)``: the variance of a fourth difference of independent errors
    is 70 times theirs; a smooth U's fourth difference is ``(a / 100)^4 U^(4)``, far
    below), must stay below ``NOISE kT``. Beyond that the energy's rounding, not the
    dynamics, decides which trajectories seem to fail. Where U falls more than kT below
    its value at the minimum within that window, its differences are the fall, not
    rounding: the walk of :func:`well` judges it (a barrier, or not confined)."""
    x = s0 + amplitude * np.linspace(-4.0, 4.0, RESOLVE)
    with np.errstate(all="ignore"):
        u = pot.energy(x[:, None]) - u0
    if not np.all(np.isfinite(u)):
        return  # (the walk says where U is not finite)
    with np.errstate(all="ignore"):
        w = u / kT  # (in kT: nothing overflows at any scale)
    if np.all(np.isfinite(w)) and float(np.min(w)) < -1.0:
        return  # (U falls below the minimum's value nearby: the walk says it is not confined)
    spread = float(np.max(np.abs(w))) if np.all(np.isfinite(w)) else math.inf
    noise = math.sqrt(float(np.mean(np.diff(w, 4) ** 2)) / 70.0) if spread < math.inf else 0.0
    if not spread > 1e-3 or noise > NOISE:
        raise StepsafeError(
            f"float64 does not resolve U at kT = {kT:.3g}: over 4 thermal amplitudes "
            f"({4 * amplitude:.3g}) each side of the minimum its computed value varies by "
            f"{spread:.3g} kT (the curvature predicts 8) with rounding noise about "
            f"{noise:.2g} kT, so rounding, not the dynamics, would decide which "
            f"trajectories fail: no verdict at this kT (write U to keep its digits near the "
            f"minimum, e.g. expm1(-q) for 1 - exp(-q), or give a larger kT)")


def one_dimensional(pot: Potential, kT: float, count: int, rng: np.random.Generator,
                    cut: float = CUT, points: int = GRID) -> tuple[np.ndarray, tuple[str, ...]]:
    """Exact draws ``(count, 1)`` of a 1-D ``exp(-U / kT)`` on the well of the minimum
    (:func:`well`): the distribution function by the trapezoid rule on ``points`` nodes,
    inverted by linear interpolation of uniform draws; with the well's notes."""
    lo, hi, notes = well(pot, kT, cut)
    s = np.linspace(lo, hi, points)
    u = pot.energy(s[:, None])
    w = np.exp(-(u - np.min(u)) / kT)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(s))])
    cdf /= cdf[-1]
    return np.interp(rng.random(count), cdf, s)[:, None], notes


def disagreement(record: np.ndarray, near: int) -> np.ndarray:
    """How far chains started apart disagree, per recorded quantity.

    ``record`` ``(snapshots, chains, k)`` holds k quantities along the chains; the first
    ``near`` chains started near the minimum, the others dispersed. For each quantity x and
    for ``x`` and ``(x - xbar)^2`` (``xbar`` the mean over every chain), each chain's mean
    over its record is one value; chains are independent, so when the dispersed chains
    sample what the near ones do the two groups' means of these values differ by
    ``|m_near - m_far|`` with standard error ``s sqrt(1 / C_near + 1 / C_far)`` (``s^2`` the
    variance of the near chains' means, ``C`` a group's chains) whatever the autocorrelation
    along a chain. Returns that difference in standard errors ``(k,)``, the larger of the
    two moments: large where dispersed chains still sit where they started (the spread
    differs) or drift apart (the mean differs); ``inf`` where the groups differ and the
    near chains do not vary. Unchanged by ``x -> a x + b``, so at every scale."""
    x = record - record.mean(axis=(0, 1))[None, None, :]
    size = np.max(np.abs(x), axis=(0, 1))
    x = x / np.where(np.isfinite(size) & (size > 0), size, 1.0)[None, None, :]
    out = np.zeros(x.shape[2])
    for moment in (x, x * x):
        m = moment.mean(axis=0)  # (chains, k): each chain's mean
        a, b = m[:near], m[near:]
        if a.shape[0] < 2 or b.shape[0] < 2:
            return np.full(x.shape[2], math.inf)
        diff = np.abs(a.mean(axis=0) - b.mean(axis=0))
        se = np.sqrt(a.var(axis=0, ddof=1) * (1.0 / a.shape[0] + 1.0 / b.shape[0]))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(se > 0, diff / se, np.where(diff > 0, math.inf, 0.0))
        out = np.maximum(out, np.where(np.isfinite(size), z, math.inf))
    return out


@dataclass(frozen=True)
class Dispersed:
    """Starts far from the minimum for the mixing diagnostic (:func:`dispersed`).

    Attributes
    ----------
    q : ndarray
        Configurations ``(k, n)``.
    omegas : ndarray
        Per coordinate ``(n,)``, the slowest frequency its profiles suggest:
        ``min sqrt(2 RISE kT) / s`` over the sides walked along directions ``e`` with
        ``e_i^2 >= 1/2`` (``s`` where the side starts, mass-weighted: a harmonic direction
        of frequency omega gives omega), ``inf`` where none is.
    omega : float
        The same over every side walked.
    """

    q: np.ndarray
    omegas: np.ndarray
    omega: float


def dispersed(pot: Potential, kT: float, found: Modes, count: int,
              rng: np.random.Generator, rise: float = RISE) -> Dispersed:
    """``count`` starts away from the minimum, chosen without trusting its curvature.

    Along each mass-weighted coordinate axis and each known normal mode ``e`` (for
    ``n > EXACT_UP_TO``, ``count`` axes drawn at random), the profile
    ``u(s) = U(q0 + s M^-1/2 e) - U(q0)`` is walked out on both sides in steps of half the
    thermal amplitude ``a = sqrt(kT / e^T W e)`` (W the mass-weighted Hessian at the
    minimum) up to ``BEYOND REACH a``, then in steps of a factor ``2^1/4`` up to
    ``2^FARTHEST`` times that (a region flat far beyond the curvature's scale); the side
    starts where u first reaches ``rise kT`` (on the geometric part, or where U stops
    being finite, at the point before), or at ``BEYOND REACH a`` when it never does. The
    starts kept are those farthest out in units of their own ``a``: where the curvature at
    the minimum says least about how far the distribution extends (a harmonic direction
    rises ``rise kT`` at ``sqrt(2 rise) a``)."""
    n = pot.dimension
    if count < 1:
        return Dispersed(np.empty((0, n)), np.full(n, math.inf), math.inf)
    q0 = np.asarray(pot.minimum, dtype=float)
    u0 = float(pot.energy(q0[None, :])[0])
    if n <= EXACT_UP_TO:
        axes = np.eye(n)
    else:
        axes = np.eye(n)[rng.choice(n, size=min(count, n), replace=False)]
    e = np.concatenate([axes, found.vectors.T], axis=0)
    lam = found.eigenvalues
    if found.vectors.shape[1] == n:  # e^T W e from the complete modes
        curv = (e @ found.vectors) ** 2 @ lam
    else:
        d = e / np.sqrt(pot.masses)[None, :]
        curv = np.einsum("kn,kn->k", d, pot.product(np.broadcast_to(q0, d.shape), d).value)
    positive = lam[lam > found.error]
    floor = float(positive[0]) if positive.size else float(lam[-1])
    curv = np.where(np.isfinite(curv) & (curv > found.error), curv, floor)
    linear = 2 * BEYOND * REACH  # (points of the walk in steps of a / 2; then geometric)
    k = np.concatenate([np.arange(1, linear + 1, dtype=float),
                        linear * 2.0 ** (np.arange(1, 4 * FARTHEST + 1) / 4.0)])
    starts, reach, omegas = [], [], np.full(n, math.inf)
    omega = math.inf
    for row, c in zip(e, curv):
        a = math.sqrt(kT / float(c))
        d = row / np.sqrt(pot.masses)
        for sign in (-1.0, 1.0):
            s = sign * 0.5 * a * k
            with np.errstate(all="ignore"):
                u = (pot.energy(q0[None, :] + s[:, None] * d[None, :]) - u0) / kT
            stop = np.flatnonzero(~(u < rise))
            j = int(stop[0]) if stop.size else linear - 1
            if stop.size and (j >= linear or not np.isfinite(u[j])):
                j -= 1  # (the last point below: the geometric steps overshoot a steep wall)
            if j < 0:
                continue
            starts.append(q0 + s[j] * d)
            reach.append(abs(float(s[j])) / a)
            w = math.sqrt(2.0 * rise * kT) / abs(float(s[j]))
            omega = min(omega, w)
            along = row * row >= 0.5
            omegas[along] = np.minimum(omegas[along], w)
    if not starts:
        return Dispersed(np.empty((0, n)), omegas, math.inf)
    order = np.argsort(-np.asarray(reach), kind="stable")[:count]
    q = np.asarray(starts)[order]
    return Dispersed(np.asarray(q[np.arange(count) % q.shape[0]]), omegas, omega)


def langevin(pot: Potential, kT: float, count: int, rng: np.random.Generator, seed: int,
             chains: int = CHAINS, z_sample: float = Z_SAMPLE, friction: float | None = None,
             burn_damping: float = BURN_DAMPING, far: int = FAR) -> Ensemble:
    """Configurations by BAOAB Langevin dynamics (module docstring), ``chains`` at once,
    beside ``far`` chains started dispersed (:func:`dispersed`) that judge the mixing."""
    n = pot.dimension
    found = minimum_modes(pot)
    q0 = np.asarray(pot.minimum, dtype=float)
    lam = found.eigenvalues
    omega_max = math.sqrt(float(lam[-1]))
    positive = lam[lam > found.error]
    if n <= EXACT_UP_TO and positive.size < n:
        raise StepsafeError("the Hessian at the minimum is not positive definite: the point "
                            "is not a minimum")
    omega_min = math.sqrt(float(positive[0]))
    gamma = 2.0 * omega_min if friction is None else positive_finite(friction, "friction")
    h = z_sample / omega_max
    chains = max(1, min(int(chains), count))
    frames = -(-count // chains)
    masses = pot.masses
    r = 1.0 / np.sqrt(masses)
    # start: exact draws of the harmonic approximation where every mode is known; a draw
    # where U exceeds its quadratic approximation by more than CUT kT (a curved valley: the
    # harmonic draw runs into the wall) starts at the minimum instead
    if found.vectors.shape[1] == n:
        xi = rng.standard_normal((chains, n))
        q = q0[None, :] + (xi * np.sqrt(kT / lam)[None, :]) @ found.vectors.T * r[None, :]
        with np.errstate(all="ignore"):
            excess = (pot.energy(q) - float(pot.energy(q0[None, :])[0])) / kT \
                - 0.5 * np.sum(xi * xi, axis=1)
        q[~(excess <= CUT)] = q0
    else:
        q = np.broadcast_to(q0, (chains, n)).copy()
    p = momenta(pot, kT, chains, rng)
    # the dispersed chains draw from a generator of their own: the near chains' draws are
    # those they would be without them
    rng_far = np.random.default_rng([seed, 1])
    spread = dispersed(pot, kT, found, far, rng_far)
    far = spread.q.shape[0]
    q = np.concatenate([q, spread.q])
    p = np.concatenate([p, momenta(pot, kT, far, rng_far)])
    half = 0.5 * h
    state = {"q": q, "p": p, "F": -pot.gradient(q)}
    kept: list[np.ndarray] = []  # snapshots (rows, n + 1): coordinates and U

    def run(steps: int, record: bool = False) -> np.ndarray:
        """``steps`` BAOAB steps at the frictions ``rates``; U of the near chains at each
        step when ``record`` (else an empty array), with about ``SNAPSHOTS`` snapshots of
        every chain kept."""
        c = np.array([math.exp(-g * h) for g in rates])[None, :]
        noise = np.sqrt((1.0 - c * c) * kT * masses[None, :])
        q, p, F = state["q"], state["p"], state["F"]
        out = np.empty((steps if record else 0, chains))
        every = max(1, steps // SNAPSHOTS)
        with np.errstate(all="ignore"):
            for k in range(steps):
                p = p + half * F
                q = q + half * p / masses
                xi = rng.standard_normal((chains, n))
                if far:
                    xi = np.concatenate([xi, rng_far.standard_normal((far, n))])
                p = c * p + noise * xi
                q = q + half * p / masses
                F = -pot.gradient(q)
                p = p + half * F
                if record:
                    u = pot.energy(q)
                    out[k] = u[:chains]
                    if k % every == every - 1:
                        kept.append(np.concatenate([q, u[:, None]], axis=1))
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
            raise StepsafeError(f"the Langevin chains at kT = {kT:.6g} left every finite "
                                f"value (h = {h:.6g}): the distribution is not confined, "
                                f"or U is too rough for this step")
        state.update(q=q, p=p, F=F)
        return out

    def mixing() -> tuple[float, int]:
        """The largest disagreement over the coordinates and U (index n) on the snapshots
        kept, with where it is."""
        values = disagreement(np.asarray(kept), chains)
        worst = int(np.argmax(values))
        return float(values[worst]), worst

    rates = np.full(n, gamma)  # (per coordinate: lowered where the profiles say it is slow)
    burn = math.ceil(burn_damping / (float(np.max(rates)) * h))
    notes: list[str] = []
    run(burn - burn // 2)
    trace = run(burn // 2, record=True)
    tau = integrated_time(trace)
    total = burn
    for _ in range(6):  # the record must span SPAN tau: doubled up to 6 times
        if SPAN * tau <= trace.shape[0]:
            break
        kept.clear()
        more = run(trace.shape[0], record=True)
        trace = np.concatenate([trace, more])
        total += more.shape[0]
        tau = integrated_time(trace)
    gap, worst = mixing() if far else (1.0, 0)
    if gap >= AGREE:
        # the chains started apart disagree: the minimum's curvature misjudged the slowest
        # motion. Its friction is set from the profiles' slowest frequency instead (when
        # lower) and the burn-in doubled, with every chain, until they agree
        first = gap
        if friction is None:
            lowered = np.minimum(rates, spread.omegas)
            if np.array_equal(lowered, rates):  # (no coordinate stands out: all of them)
                lowered = np.minimum(rates, spread.omega)
            rates = lowered
        stage = max(total, math.ceil(burn_damping / (float(np.min(rates)) * h)))
        budget = max(MIX_STEPS, 8 * total)
        for _ in range(DOUBLINGS):
            if total + stage > budget:
                break
            kept.clear()
            trace = run(stage, record=True)
            total += stage
            gap, worst = mixing()
            if gap < AGREE:
                break
            stage = total
        what = "U" if worst == n else f"coordinate {worst}"
        low = float(np.min(rates))
        if gap >= AGREE:
            raise StepsafeError(
                f"the Langevin draws at kT = {kT:.6g} have not mixed: chains started "
                f"{RISE:g} kT up the profiles through the minimum still disagree about "
                f"the mean or spread of {what} ({gap:.3g} standard errors apart) after "
                f"{total} steps of h = {h:.6g} at friction down to {low:.3g}, so draws near "
                f"the minimum would miss part of the distribution: no verdict on them (make "
                f"the slow coordinate's well narrower, or its walls steeper, or analyse it on "
                f"its own)")
        tau = integrated_time(trace)
        notes.append(f"chains started {RISE:g} kT up the profiles through the minimum "
                     f"disagreed with those started near it ({first:.3g} standard errors "
                     f"apart); the draws are taken at friction down to {low:.3g} after a "
                     f"burn-in of {total} steps, when they agree ({gap:.2g})")
    if SPAN * tau > trace.shape[0]:
        notes.append(f"the autocorrelation time of U ({tau:.3g} steps) is not resolved "
                     f"by {trace.shape[0]} steps of burn-in")
    thin = max(1, math.ceil(2 * tau))
    far = 0  # (the frames come from the near chains)
    state.update(q=state["q"][:chains], p=state["p"][:chains], F=state["F"][:chains])
    configs = np.empty((frames, chains, n))
    for f in range(frames):
        run(thin)
        configs[f] = state["q"]
    q_out = configs.transpose(1, 0, 2).reshape(chains * frames, n)
    chain = np.repeat(np.arange(chains), frames)
    return Ensemble(q_out, chain, kT, "Langevin (BAOAB)", seed, h, float(np.min(rates)), total,
                    thin, tau, chains, tuple(notes))
