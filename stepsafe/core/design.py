"""Palindromic 2- and 3-stage splittings designed for a Gaussian target and a step.

Families (velocity form, kicks outside, first same as last so s gradient evaluations per
step; Blanes, Casas & Sanz-Serna, SIAM J. Sci. Comput. 36 (2014) A1556, section 4):

* 2 stages, one parameter b: ``K(b h) D(h/2) K((1 - 2b) h) D(h/2) K(b h)``;
* 3 stages, two parameters (b, a): ``K(b h) D(a h) K((1/2 - b) h) D((1 - 2a) h)
  K((1/2 - b) h) D(a h) K(b h)``.

Every member is symmetric, symplectic and of order 2. The design chooses the parameters that
minimise the expected energy error of the target at the user's step h, summed over its modes:
``sum_k rho(beta_k h)`` with ``rho`` the bound over trajectory lengths
(:mod:`stepsafe.core.hmc`; averaged over L it is ``rho / 2``, so this is the average error
a sampler sees), each term averaged over the step interval ``h (1 +- j)`` of a jittered
sampler. Every mode must stay stable (M elliptic) for every step up to ``h (1 + j)``, checked
on the modes' own z and :data:`SWEEP` points of that range. The search is a
grid over the parameters (every candidate with an unstable mode discarded) refined by
Nelder-Mead; the figures of the result are recomputed by the general path
(:func:`stepsafe.core.hmc.one_step`).

2 stages, exactly (:func:`stable_b`): with ``tr M / 2 = 1 - z^2/2 + b (1 - 2b) z^4 / 4``,
``tr M / 2 - 1 = -z^2 (2 - b (1 - 2b) z^2) / 4`` and
``tr M / 2 + 1 = -(b z^2 - 2) (2 b z^2 - z^2 + 4) / 4``. As ``b (1 - 2b) <= 1/8``, the first
never vanishes for z < 4; the second vanishes at ``b = 2 / z^2`` and ``b = 1/2 - 2 / z^2``,
so the members with ``|tr M| < 2`` for every z in (0, Z] are ``1/2 - 2/Z^2 < b < 2/Z^2``
(all of (0, 1/2) for Z <= 2), an interval shrinking to b = 1/4 at Z = 2 sqrt 2. There the
member b = 1/4, two half-step leapfrogs (``M(z) = V(z/2)^2``), has ``tr M / 2 + 1 =
(z^2 - 8)^2 / 32 >= 0`` and ``M = V(sqrt 2)^2 = -I`` exactly at z = 2 sqrt 2 (bounded: its
powers are +-I and the energy error is 0, the literature's stability interval, as ``hmc``
counts it); it is stable on (0, 4) and the only member stable up to any Z in
[2 sqrt 2, 4), and none is for Z >= 4. The search runs on that interval; for
Z >= 2 sqrt 2 the answer is b = 1/4 (exact in binary, so the written method file is
that member). Its rho is ``z^4 / (32 (16 - z^2))``, the leapfrog's at z/2, through the
resonance.

3 stages: ``tr M / 2 + 1`` and ``tr M / 2 - 1`` factor into polynomials of degree <= 2 in
z^2, whose exact roots over a 1500 x 1500 grid of (b, a) leave no member with ``|tr M| < 2``
beyond z = 3: that end is approached at (b, a) = (1/6, 1/3), three third-step leapfrogs,
whose M = -I at z = 3 exactly. Past z = 3 only members whose ``tr M`` touches -2 (an
M = -I point, a curve in (b, a)) stay stable: bcss3 (M = -I at z = 2.97632, stable to
4.66185) and (1/6, 1/3) itself, stable to z = 6 through M = -I at 3 and M = +I at
3 sqrt 3. 6 = 2s is the end for every s-stage member: ``tr M / 2`` is a polynomial of
degree s in z^2 with slope -1/2 at 0, and the Chebyshev polynomial ``T_s(1 - 2 z^2 / Z^2)``
is the one that stays within [-1, 1] longest, up to ``Z^2 = 4 s^2``.

Rounding gaps. Stability is the rule ``hmc`` uses (:func:`stepsafe.core.regions.stable_run`,
:data:`~stepsafe.core.regions.ROUNDING_GAP_RULE`): a touch of ``tr M`` to ``+-2`` within the
rounding of the coefficients is a resonance, which does not end the stable steps. The
float coefficients of a member on the touching curve miss it by their rounding: bcss3's
``tr M`` dips 3.2e-27 below -2 over a width of 1e-13 at 50 digits, (1/6, 1/3)'s 1e-33 at
z = 3. Under the rule both are stable past those points, as ``hmc`` ranks them. A
parameter search in the plane cannot follow a curve: past z = 3 the design is the best of
the known members on it (bcss3 and (1/6, 1/3), :data:`KNOWN`) that is stable up to
h (1 + j).
With more distinct frequencies than :data:`MAX_DESIGN_MODES` the search uses that many
log-spaced bins (each bin's largest frequency, weighted by its count): an approximation
of the objective, said in the result; the final figures use every mode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stepsafe.core.hmc import OneStep, acceptances, errors_after
from stepsafe.core.regions import find_region, stable_run
from stepsafe.methods.tableaux import Splitting

#: Parameter names of each family, by stage count.
PARAMETERS = {2: ("b",), 3: ("b", "a")}
#: The search grid: this many values per parameter in (0, 1/2).
GRID = {2: 200, 3: 48}
MAX_DESIGN_MODES = 128
#: At most this many grid points are confirmed by the region finder when no local optimum is.
CONFIRM_LIMIT = 400
#: Local searches start from this many of the best grid points ...
STARTS = 6
#: ... and from the published members: verlet as 2 or 3 substeps, BCSS 2014 (bcss2,
#: bcss3), McLachlan's minimum-error 2-stage method in velocity form.
KNOWN = {2: ((0.25,), (0.21178,), (0.19318332750378357,)),
         3: ((1 / 6, 1 / 3), (0.11888010966548, 0.29619504261126))}


def family_member(stages: int, params: tuple[float, ...], name: str = "designed") -> Splitting:
    """The family member with parameters ``params`` (see the module docstring)."""
    if stages == 2:
        (b,) = params
        return Splitting(np.array([0.0, 0.5, 0.5, 0.0]), np.array([b, 1.0 - 2.0 * b, b]),
                         name=name, order=2, evaluations=2)
    b, a = params
    return Splitting(np.array([0.0, a, 1.0 - 2.0 * a, a, 0.0]),
                     np.array([b, 0.5 - b, 0.5 - b, b]), name=name, order=2, evaluations=3)


def _operations(stages: int, params: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The kick/drift sequence for a batch of parameter rows (shape (n, p))."""
    if stages == 2:
        b = params[:, 0]
        return [("k", b), ("d", np.full_like(b, 0.5)), ("k", 1.0 - 2.0 * b),
                ("d", np.full_like(b, 0.5)), ("k", b)]
    b, a = params[:, 0], params[:, 1]
    return [("k", b), ("d", a), ("k", 0.5 - b), ("d", 1.0 - 2.0 * a), ("k", 0.5 - b),
            ("d", a), ("k", b)]


#: Points of (0, max z] besides the modes' own z where stability is required.
SWEEP = 256
#: Midpoints of the average over a jitter interval (rho can peak sharply near M = -I
#: inside it, which a few Gauss nodes would step over).
JITTER_NODES = 32


def error_bounds(stages: int, params: np.ndarray, z: np.ndarray, weights: np.ndarray,
                 jitter: float = 0.0) -> np.ndarray:
    """``sum_k weights_k mean_{|u| <= 1} rho(z_k (1 + jitter u))`` for each parameter row;
    inf where some mode is not elliptic at some step up to ``z (1 + jitter)``."""
    z = np.asarray(z, dtype=float)
    if jitter:
        nodes = (np.arange(JITTER_NODES) + 0.5) / JITTER_NODES * 2.0 - 1.0
        scaled = (z[None, :] * (1.0 + jitter * nodes[:, None])).ravel()
        weights = (np.full(JITTER_NODES, 1.0 / JITTER_NODES)[:, None]
                   * weights[None, :]).ravel()
    else:
        scaled = z
    top = float(z.max()) * (1.0 + jitter)
    sweep = top * np.arange(1, SWEEP + 1) / SWEEP
    rho = rho_values(stages, params, np.concatenate([scaled, sweep]))
    total = rho[:, :scaled.size] @ weights
    return np.where(np.isfinite(rho[:, scaled.size:]).all(axis=1), total, np.inf)


def one_step_values(stages: int, params: np.ndarray, z: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each parameter row and z: ``E_1`` (the one-step energy error from the
    stationary state), ``sin2 = 1 - (tr M / 2)^2`` in the cancellation-free form
    ``-M_qp M_pq - (M_qq - M_pp)^2 / 4``, ``tr M / 2`` and whether M is elliptic; the
    one-step matrices multiplied out in float64, vectorised over both."""
    params = np.atleast_2d(np.asarray(params, dtype=float))
    n = params.shape[0]
    m00 = np.ones((n, z.size))
    m01 = np.zeros((n, z.size))
    m10 = np.zeros((n, z.size))
    m11 = np.ones((n, z.size))
    for kind, c in _operations(stages, params):
        cz = c[:, None] * z[None, :]
        if kind == "d":  # [[1, c z], [0, 1]] @ M
            m00, m01 = m00 + cz * m10, m01 + cz * m11
        else:  # [[1, 0], [-c z, 1]] @ M
            m10, m11 = m10 - cz * m00, m11 - cz * m01
    half = 0.5 * (m00 + m11)
    sin2 = -m01 * m10 - 0.25 * (m00 - m11) ** 2
    e1 = 0.5 * ((m00 - m11) ** 2 + (m01 + m10) ** 2)
    # (below z = 1e-4 every member is elliptic, and tr M / 2 = 1 - O(z^2) rounds to 1
    # below z ~ 1e-8: there sin2 ~ z^2, free of cancellation, decides alone)
    elliptic = (sin2 > 0) & ((np.abs(half) < 1) | (z < 1e-4)[None, :])
    return e1, sin2, half, elliptic


def rho_values(stages: int, params: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``rho(z)`` for each parameter row and z (inf where M is not elliptic): the one-step
    matrices multiplied out in float64, vectorised over both."""
    params = np.atleast_2d(np.asarray(params, dtype=float))
    e1, sin2, _, elliptic = one_step_values(stages, params, z)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(elliptic, e1 / sin2, np.inf)
        # rho = O(z^4) (C z^4 with C of order 1 for the family): below z = 1e-80 it is
        # below the smallest float, where sin2 ~ z^2 itself underflows to 0
        rho[:, z < RESOLVED_Z] = 0.0
        if stages == 2:  # b = 1/4: the leapfrog's rho at z/2, through M = -I at 2 sqrt 2
            quarter = params[:, 0] == 0.25
            if quarter.any():
                z2 = z * z
                rho[quarter] = np.where(z2 < 16.0, z2 * z2 / (32.0 * (16.0 - z2)), np.inf)
    return rho


#: Below this z a mode's rho is 0 in float64 (see :func:`rho_values`).
RESOLVED_Z = 1e-80
#: The end of each family's stable range in z (module docstring): no member beyond (2s).
STABLE_LIMIT = {2: 4.0, 3: 6.0}
#: The 2-stage member that alone stays stable beyond z = 2 sqrt 2 (module docstring).
QUARTER = 0.25


def stable_b(top: float) -> tuple[float, float] | None:
    """The 2-stage members stable (``|tr M| < 2``, or ``M = -I`` exactly) for every z in
    (0, top], exactly (module docstring): the open interval ``(lo, hi)`` of b, ``(1/4,
    1/4)`` when b = 1/4 alone is (``2 sqrt 2 <= top < 4``), None when none is
    (``top >= 4``). Endpoints are moved 1e-15 inwards."""
    w = top * top
    if w >= 16.0:
        return None
    if w >= 8.0:
        return QUARTER, QUARTER
    if w <= 4.0:
        return 0.0, 0.5
    # 1e-15 inwards: more than the few ulps of 1/2 that w, 2/w and 1/2 - 2/w round by
    return 0.5 - 2.0 / w + 1e-15, 2.0 / w - 1e-15


@dataclass(frozen=True)
class Design:
    """The chosen parameters and the objective they reach (module docstring)."""

    stages: int
    params: tuple[float, ...]
    error_bound: float
    binned: bool


def _stable_up_to(stages: int, params: np.ndarray, top: float) -> bool:
    """Whether the member keeps |tr M| <= 2 for every z in (0, top], by the region finder
    (float64 uncertainties included), under the rule for rounding gaps that ``hmc`` uses
    (:func:`stepsafe.core.regions.stable_run`: an M = +-I resonance does not end it)."""
    return stable_run(find_region(family_member(stages, tuple(params)), "oscillator",
                                  top * 1.001)).reaches(top)


def _binned(betas: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    if betas.size <= MAX_DESIGN_MODES:
        return betas, counts, False
    edges = np.geomspace(betas.min(), betas.max(), MAX_DESIGN_MODES + 1)
    index = np.clip(np.searchsorted(edges, betas, side="right") - 1, 0, MAX_DESIGN_MODES - 1)
    top = np.zeros(MAX_DESIGN_MODES)
    np.maximum.at(top, index, betas)
    weight = np.bincount(index, weights=counts, minlength=MAX_DESIGN_MODES)
    keep = weight > 0
    return top[keep], weight[keep], True


#: What the design minimises: the error bound of the module docstring, or the gradient
#: evaluations per accepted proposal that ``hmc`` ranks by (:func:`acceptance_values`).
OBJECTIVES = ("error-bound", "acceptance")
#: Exact-objective Nelder-Mead polish of the acceptance design (iterations).
POLISH_ITERATIONS = 120


def _stable_rows(stages: int, params: np.ndarray, top: float) -> np.ndarray:
    """Whether each parameter row keeps M elliptic at :data:`SWEEP` points of (0, top]."""
    sweep = top * np.arange(1, SWEEP + 1) / SWEEP
    return np.isfinite(rho_values(stages, params, sweep)).all(axis=1)


def _node_errors(stages: int, params: np.ndarray, z: np.ndarray, weights: np.ndarray,
                 jitter: float, steps: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Each mode's expected energy error at each jitter node (shape (rows, nodes, modes))
    after ``steps`` steps (None: its bound rho over every L), and the modes' weights."""
    nodes = ((np.arange(JITTER_NODES) + 0.5) / JITTER_NODES * 2.0 - 1.0 if jitter
             else np.zeros(1))
    scaled = (z[None, :] * (1.0 + jitter * nodes[:, None])).ravel()
    params = np.atleast_2d(np.asarray(params, dtype=float))
    if steps is None:
        errors = rho_values(stages, params, scaled)
    else:
        e1, sin2, half, _ = one_step_values(stages, params, scaled)
        errors = errors_after(OneStep(e1, sin2, half), steps)
        errors[:, scaled < RESOLVED_Z] = 0.0
    return errors.reshape(params.shape[0], nodes.size, z.size), weights


def acceptance_values(stages: int, params: np.ndarray, z: np.ndarray, weights: np.ndarray,
                      jitter: float = 0.0, steps: int | None = None,
                      exact: bool = True) -> np.ndarray:
    """The predicted HMC acceptance of each parameter row on the Gaussian whose modes sit at
    ``z`` (``weights`` modes each) with L = ``steps`` (None: each mode's error at its bound
    over L), averaged over the step interval ``z (1 +- jitter)`` by the :data:`JITTER_NODES`
    midpoint rule; 0 where some mode is not elliptic up to ``z (1 + jitter)``. ``exact``:
    the Gaussian acceptance ``2 P(Delta < 0)`` of :mod:`stepsafe.core.hmc`; else its normal
    approximation ``2 Phi(-sqrt(mu / 2))``, ``mu`` the total expected error (for the grid
    of the search only)."""
    params = np.atleast_2d(np.asarray(params, dtype=float))
    top = float(z.max()) * (1.0 + jitter)
    stable = _stable_rows(stages, params, top)
    errors, weights = _node_errors(stages, params, z, weights, jitter, steps)
    out = np.zeros(params.shape[0])
    with np.errstate(invalid="ignore", over="ignore"):
        if exact:
            for r in np.flatnonzero(stable):
                rows = np.where(np.isfinite(errors[r]), errors[r], np.inf)
                out[r] = float(np.mean([a.rate for a in acceptances(rows, weights)]))
        else:
            from scipy.special import erfc

            mu = np.where(np.isfinite(errors), errors, np.inf) @ weights  # (rows, nodes)
            # 2 Phi(-x) = erfc(x / sqrt 2), x = sqrt(mu / 2)
            out = np.where(stable, erfc(np.sqrt(np.maximum(mu, 0.0)) / 2.0).mean(axis=1), 0.0)
    return out


def minimax(stages: int, top: float) -> tuple[float, ...] | None:
    """The member minimising ``max_{0 < z <= top} rho(z)``: the choice of the adaptive
    integrators of Fernandez-Pendas, Akhmatskaya & Sanz-Serna (J. Comput. Phys. 2016; s-AIA
    for HMC, Nagar et al. 2024) for a largest dimensionless step ``top``, found on a grid of
    the parameters and refined by Nelder-Mead on the maximum over :data:`MINIMAX_Z` steps;
    None when no member is stable up to ``top``. For 2 stages at ``top = 2`` it is bcss2
    (b = 0.21178), as Blanes, Casas & Sanz-Serna define that method."""
    from scipy.optimize import minimize

    z = top * np.arange(1, MINIMAX_Z + 1) / MINIMAX_Z
    lo, hi = 0.0, 0.5
    if stages == 2:
        interval = stable_b(top)
        if interval is None:
            return None
        lo, hi = interval
        if lo >= hi:
            return (QUARTER,)
    n = 400 if stages == 2 else 64
    axis = lo + (np.arange(n) + 0.5) / n * (hi - lo)
    grid = (axis[:, None] if stages == 2 else
            np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2))
    worst = np.concatenate([rho_values(stages, chunk, z).max(axis=1)
                            for chunk in np.array_split(grid, max(1, grid.size * z.size
                                                                  // 4_000_000))])

    def objective(x: np.ndarray) -> float:
        if np.any(x <= lo) or np.any(x >= hi):
            return np.inf
        return float(rho_values(stages, x[None, :], z).max())

    finite = np.flatnonzero(np.isfinite(worst))
    candidates = [grid[i] for i in finite[np.argsort(worst[finite], kind="stable")][:STARTS]]
    candidates += [np.array(m) for m in KNOWN[stages] if np.isfinite(objective(np.array(m)))]
    step = (hi - lo) / n
    found = []
    for start in candidates:
        simplex = np.vstack([start] + [start + step * np.eye(start.size)[i]
                                       for i in range(start.size)])
        res = minimize(objective, start, method="Nelder-Mead",
                       options={"initial_simplex": simplex, "xatol": 1e-12, "fatol": 0.0,
                                "maxiter": 600})
        found += [res.x, start]
    ranked = sorted(((objective(x), k) for k, x in enumerate(found)), key=lambda t: t[0])
    best = next((found[k] for value, k in ranked
                 if np.isfinite(value) and _stable_up_to(stages, found[k], top)), None)
    return None if best is None else tuple(float(x) for x in best)


#: Steps of (0, top] over which :func:`minimax` takes the maximum of rho.
MINIMAX_Z = 1024


def design(stages: int, betas: np.ndarray, counts: np.ndarray, h: float,
           jitter: float = 0.0, objective: str = "error-bound",
           steps: int | None = None,
           starts: Sequence[tuple[float, ...]] = ()) -> Design | None:
    """The family member of ``stages`` stages minimising ``objective`` at step ``h`` for the
    frequencies ``betas`` (``counts`` modes each); None when no member keeps every mode
    stable up to ``h (1 + jitter)``.

    ``error-bound`` (the module docstring's sum of rho) or ``acceptance``: the gradient
    evaluations per accepted proposal, ``stages L / alpha`` at a fixed step, that is the
    reciprocal of the acceptance :func:`acceptance_values` predicts for L = ``steps`` (None:
    each mode at its bound over L) averaged over the jitter. The acceptance design searches
    its grid on the normal approximation of the acceptance, refines by Nelder-Mead on it,
    ranks every candidate by the exact acceptance and polishes the best by Nelder-Mead on
    the exact one; ``Design.error_bound`` is then ``1 / alpha``. ``starts`` are further
    members to start from (such as the minimax member of :func:`minimax`): each is a
    candidate too, so the result's objective is at most theirs among those confirmed
    stable."""
    from scipy.optimize import minimize

    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    starts_given = tuple(starts)
    betas, counts, binned = _binned(np.asarray(betas, float), np.asarray(counts, float))
    z = betas * h
    top = float(z.max()) * (1.0 + jitter)
    if objective == "acceptance":
        def rough(rows: np.ndarray) -> np.ndarray:
            with np.errstate(divide="ignore"):
                return 1.0 / acceptance_values(stages, rows, z, counts, jitter, steps,
                                               exact=False)

        def exact(rows: np.ndarray) -> np.ndarray:
            with np.errstate(divide="ignore"):
                return 1.0 / acceptance_values(stages, rows, z, counts, jitter, steps)
    else:
        def rough(rows: np.ndarray) -> np.ndarray:
            return error_bounds(stages, rows, z, counts, jitter)

        exact = rough
    lo, hi = 0.0, 0.5
    if stages == 2:  # the stable members, exactly (module docstring)
        interval = stable_b(top)
        if interval is None:
            return None
        lo, hi = interval
        if lo >= hi:  # b = 1/4 alone (or the interval narrower than its rounding)
            return _quarter(exact, binned)
    axis = lo + (np.arange(GRID[stages]) + 0.5) / GRID[stages] * (hi - lo)
    grid = (axis[:, None] if stages == 2 else
            np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2))
    values = np.concatenate([rough(chunk) for chunk in
                             np.array_split(grid, max(1, grid.size * z.size // 4_000_000))])
    if stages == 2 and not np.isfinite(values).any():
        # (near top = 2 sqrt 2 the interval's members are stable, but too close to their
        # M = -I point for float64's error bound: b = 1/4 is stable on all of (0, 4))
        return _quarter(exact, binned)

    def inside(x: np.ndarray) -> bool:
        return not (np.any(x <= lo) or np.any(x >= hi))

    def searched(x: np.ndarray) -> float:
        return float(rough(x[None, :])[0]) if inside(x) else np.inf

    def final(x: np.ndarray) -> float:
        return float(exact(x[None, :])[0]) if inside(x) else np.inf

    # Nelder-Mead from the best grid points and from the published members (the landscape
    # has narrow valleys: bcss3 lies in one)
    order = np.argsort(values, kind="stable")[:STARTS]
    begins = [grid[i] for i in order if np.isfinite(values[i])]
    begins += [np.array(m) for m in KNOWN[stages] if np.isfinite(searched(np.array(m)))]
    given = [np.array(m, dtype=float) for m in starts_given]
    begins += [m for m in given if np.isfinite(searched(m))]
    step = (hi - lo) / GRID[stages]
    found_points = [m for m in given if inside(m)]
    for start in begins:
        simplex = np.vstack([start] + [start + step * np.eye(start.size)[i]
                                       for i in range(start.size)])
        found = minimize(searched, start, method="Nelder-Mead",
                         options={"initial_simplex": simplex, "xatol": 1e-10, "fatol": 0.0,
                                  "maxiter": 400})
        found_points += [found.x, start]
    if objective == "acceptance" and found_points:
        # the exact acceptance, polished from the best candidate
        first = min(found_points, key=final)
        simplex = np.vstack([first] + [first + 0.1 * step * np.eye(first.size)[i]
                                       for i in range(first.size)])
        polish = minimize(final, first, method="Nelder-Mead",
                          options={"initial_simplex": simplex, "xatol": 1e-10, "fatol": 0.0,
                                   "maxiter": POLISH_ITERATIONS})
        found_points.append(polish.x)
    # the sampled stability check can step over a narrow gap (|tr M| > 2 on 1e-3 of z):
    # the best candidate the region finder confirms stable up to the top z wins
    ranked = sorted(((final(x), i) for i, x in enumerate(found_points)), key=lambda t: t[0])
    best = next((found_points[i] for value, i in ranked
                 if np.isfinite(value) and _stable_up_to(stages, found_points[i], top)), None)
    if best is None:  # then the best grid points the region finder confirms
        finite = [i for i in np.argsort(values, kind="stable") if np.isfinite(values[i])]
        best = next((grid[i] for i in finite[:CONFIRM_LIMIT]
                     if _stable_up_to(stages, grid[i], top)), None)
    if best is None:
        return _quarter(exact, binned) if stages == 2 else None
    return Design(stages, tuple(float(x) for x in best), final(best), binned)


def _quarter(exact, binned: bool) -> Design:
    """The member b = 1/4 (two half-step leapfrogs), stable for every z < 4."""
    value = float(exact(np.array([[QUARTER]]))[0])
    return Design(2, (QUARTER,), value, binned)
