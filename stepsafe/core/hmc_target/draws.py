"""Draws from the target: the mode and its Gaussian (Laplace) approximation, a short
adaptive HMC run of its own, or draws the user supplies.

Mode. ``U`` is minimised by BFGS (scipy) from the start given (the origin by default), in
coordinates scaled by the target's own length per coordinate there (from its curvature,
where positive: :func:`own_scale_hessian`), so that the search stops at the same relative
precision at every scale; the
Hessian there (the potential's own, else central differences of the gradient with widths
that follow the target's own scale, :func:`own_scale_hessian`) gives the Laplace approximation
``N(mode, (nabla^2 U)^-1)`` when it is positive definite. Its mass-weighted eigenvalues
``lambda_k`` (:mod:`stepsafe.core.hmc_target.potential`) are the squared frequencies
``beta_k^2`` of the Gaussian analysis at the mode.

Warm-up sampler. ``chains`` chains of HMC with kick-drift-kick Verlet under the target's
own mass matrix, vectorised over chains. They start over-dispersed, from
``N(mode, DISPERSION^2 (nabla^2 U)^-1)`` (around the start given, scaled by the curvature
there, when there is no positive definite Laplace approximation); a start where U or its
gradient is not finite (outside the support) is redrawn at half its distance from the centre
(:func:`starts`). Each iteration draws, per chain, the step ``h / R^u`` (u uniform on
(0, 1): smaller steps let chains cross regions stiffer than the typical one; R starts at
:data:`STEP_RANGE` and grows fourfold, up to :data:`MAX_STEP_RANGE`, after each warm-up
window in which a chain was stuck, and is fixed after warm-up) and the
number of steps ``ceil(T u' / h_i)`` (u' uniform, capped at :data:`MAX_WARMUP_STEPS`), so
that the integration time is uniform up to ``T = pi`` times the largest standard deviation
of the mass-weighted target (Laplace's at first, re-estimated from the chains' covariance at
the end of each eighth of the warm-up). Both are drawn independently of the state, so each
iteration is a valid Metropolis-Hastings step: a proposal is accepted with probability
``min(1, e^-Delta)`` and one with a non-finite energy is never accepted. During warm-up h is
adapted by dual averaging (Hoffman & Gelman, JMLR 15 (2014) 1593, algorithm 5: gamma =
0.05, t0 = 10, kappa = 0.75) so that the mean acceptance statistic over the chains
approaches :data:`WARMUP_ACCEPT`, a conservative 0.9; at the end of each eighth a chain whose
mean acceptance over it is below :data:`STUCK` times the median chain's (stuck where the
common step does not fit) is moved to the position of another chain. The warm-up iterations
are discarded; after them the step is frozen and every iteration of every chain is kept.
When the kept draws narrowly fail the diagnostics below (R-hat above :data:`RHAT_LIMIT` but
at most :data:`EXTEND_RHAT`, or too small an effective sample size), the chains run on at
the frozen step and the kept iterations double, up to :data:`EXTEND` times ``keep``: with
300 draws per chain the split R-hat of well-mixed chains scatters around 1.01 itself.

Divergent transitions. A kept transition whose energy error exceeds :data:`DIVERGENT` (or
whose trajectory stopped being finite) is divergent: the integrator could not follow the
trajectory, almost always through a region stiffer than the step allows, and the chain
rejected it, so the chains under-visit that region (a funnel's neck) while R-hat and the
effective sample size can read well. A kept run with one is made afresh, from where the
chains are, at the frozen step divided by :data:`REFIT_FACTOR`, up to :data:`REFITS` times;
a refit stops at its first divergent transition (so that a target where every step diverges
costs little more). The draws are those of the first kept run without a divergent
transition; when every refit diverged, those of the first run, with its count
(``divergent``), which the report then treats as unverified.

Diagnostics. Over the kept draws, the rank-normalised split R-hat and the effective sample
size (:mod:`stepsafe.core.hmc_target.statistics`) of every coordinate and of U; the draws
count as converged when the largest R-hat is at most :data:`RHAT_LIMIT` and the smallest
ESS at least :data:`ESS_LIMIT`. The Monte Carlo error of anything averaged over the draws
comes from the chains' autocorrelation (the same module). The seed is part of the result.

Improper targets (:func:`flat_direction`): along a direction where the Hessian at the mode
has (next to) no curvature, U is followed out by decades of the direction's own standard
deviation to the float64 range; if it never rises by 1, exp(-U) does not integrate and the
target is refused. Nor where U
grows only like ``alpha log r`` far out (:func:`slow_direction`): along a ray with
``alpha <= 1`` and a tube around it, or ``alpha <= d`` and a cone, the integral diverges.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import ClassVar

import numpy as np

from stepsafe.core.hmc_target.potential import Potential, Target, hessian_matrix
from stepsafe.core.hmc_target.statistics import effective_size, rhat
from stepsafe.exceptions import StepsafeError

#: The warm-up sampler's target for the mean acceptance statistic (conservative).
WARMUP_ACCEPT = 0.9
#: Cap on the warm-up sampler's steps per iteration.
MAX_WARMUP_STEPS = 256
#: Default chains, warm-up iterations and kept iterations per chain.
CHAINS = 32
WARMUP = 300
KEEP = 300
#: The warm-up chains start this many Laplace standard deviations out (over-dispersed) ...
DISPERSION = 2.0
#: ... and a start outside the support is redrawn nearer the centre up to this many times.
REDRAWS = 30
#: Each iteration's step is h / R**u, u uniform on (0, 1) (and the integration time uniform
#: up to pi times the largest standard deviation), R from STEP_RANGE ...
STEP_RANGE = 4.0
#: ... multiplied by 4 at the end of a warm-up window with a stuck chain, up to this.
MAX_STEP_RANGE = 64.0
#: During warm-up a chain whose acceptance over a window is below this fraction of the
#: median chain's is moved to another chain's position.
STUCK = 0.5
#: Converged draws: R-hat at most this, and an effective sample size at least ...
RHAT_LIMIT = 1.01
#: ... this (for every coordinate and U).
ESS_LIMIT = 400.0
#: Kept draws whose R-hat is above RHAT_LIMIT but at most this (or whose ESS is short) ...
EXTEND_RHAT = 1.05
#: ... are extended by running the chains on, doubling the kept iterations up to this many
#: times ``keep``.
EXTEND = 4
#: A transition whose energy error exceeds this is divergent (Stan's and BlackJAX's rule) ...
DIVERGENT = 1000.0
#: ... and a kept run with one is made afresh at the frozen step over this factor ...
REFIT_FACTOR = 2.0
#: ... up to this many times, until a kept run has none.
REFITS = 3
#: Default seed (stated in every result).
SEED = 20240611
#: Largest dimension for which the Laplace approximation's dense Hessian is formed.
LAPLACE_LIMIT = 2000


@dataclass(frozen=True)
class Laplace:
    """The mode of U and the Gaussian approximation there.

    ``hessian`` is ``nabla^2 U(mode)``; ``eigenvalues`` those of the mass-weighted Hessian
    (ascending); ``gradient_norm`` is ``|C^-1 grad U(mode)|`` (0 at an exact mode; compare
    with ``sqrt(d)``, its typical size at a draw)."""

    mode: np.ndarray
    hessian: np.ndarray
    eigenvalues: np.ndarray
    gradient_norm: float
    converged: bool

    @property
    def positive_definite(self) -> bool:
        return bool(self.eigenvalues.size and self.eigenvalues[0] > 0)

    @property
    def betas(self) -> np.ndarray:
        """The frequencies ``sqrt(lambda_k)`` of the Gaussian at the mode (only when the
        Hessian is positive definite)."""
        return np.sqrt(self.eigenvalues)


def find_mode(target: Target, start: np.ndarray | None = None) -> Laplace | None:
    """The mode of the target and its Laplace approximation (module docstring); None when
    the optimisation diverges or d exceeds :data:`LAPLACE_LIMIT`.

    Parameters
    ----------
    target
        The potential and mass.
    start
        Where the search starts (default: the origin).

    Returns
    -------
    Laplace or None
    """
    from scipy.optimize import minimize

    d = target.dimension
    if d > LAPLACE_LIMIT:
        return None
    x0 = np.zeros(d) if start is None else np.asarray(start, dtype=float).reshape(d)
    pot = target.potential

    def fun(x: np.ndarray) -> float:
        value = float(np.asarray(pot.energy(x[None, :]))[0])
        return value if math.isfinite(value) else math.inf

    def jac(x: np.ndarray) -> np.ndarray:
        return np.asarray(pot.gradient(x[None, :]), dtype=float)[0]

    with np.errstate(all="ignore"):
        # the search runs in z = (x - x0) / s, s the target's own length per coordinate at
        # the start (its curvature's, where positive), so that its tolerance on the
        # gradient means the same at every scale
        H0 = own_scale_hessian(pot, x0, np.ones(d))
        c0 = np.diag(H0) if H0 is not None else np.zeros(d)
        s = np.where((c0 > 0) & np.isfinite(c0), 1.0 / np.sqrt(np.where(c0 > 0, c0, 1.0)),
                     1.0)
        s = np.clip(s, 1e-300, 1e300)

        def scaled(z: np.ndarray) -> float:
            return fun(x0 + s * z)

        def scaled_jac(z: np.ndarray) -> np.ndarray:
            return s * jac(x0 + s * z)

        found = minimize(scaled, np.zeros(d), jac=scaled_jac, method="BFGS",
                         options={"gtol": 1e-10, "maxiter": 200 * max(d, 10)})
        mode = x0 + s * np.asarray(found.x, dtype=float)
        if not np.isfinite(mode).all() or not math.isfinite(float(found.fun)):
            return None
        inv = np.asarray(getattr(found, "hess_inv", np.eye(d)), dtype=float)
        spread = s * np.sqrt(np.clip(np.diag(inv), 1e-300, None)) if inv.shape == (d, d) \
            else s
        H = own_scale_hessian(pot, mode, spread)
        if H is None:
            return None
        W = target.mass.weighted(H)
        lam = np.linalg.eigvalsh(0.5 * (W + W.T))
        g = target.mass.unweigh_gradient(jac(mode)[None, :])[0]
    return Laplace(mode, H, lam, float(np.linalg.norm(g)), bool(found.success))


#: The difference width of the Hessian at the mode follows the target's own scale: at most
#: this many rounds ...
SCALE_ROUNDS = 60
#: ... until no coordinate's scale ``1 / sqrt(H_jj)`` changes by more than this factor.
SCALE_AGREE = 1.5


def own_scale_hessian(potential: Potential, q: np.ndarray, spread: np.ndarray
                      ) -> np.ndarray | None:
    """``nabla^2 U(q)`` by central differences whose widths follow U's own length scale.

    The width along coordinate j is ``FD_STEP * s_j``; the scale ``s_j`` starts at
    ``spread_j`` and is replaced by ``1 / sqrt(H_jj)`` of the Hessian taken with it,
    where that curvature is positive and finite, until no ``s_j`` changes by more than
    :data:`SCALE_AGREE` (at most :data:`SCALE_ROUNDS` rounds; each round is two batched
    gradient calls). A width far beyond the scale (a quasi-Newton search that stopped at
    once leaves ``spread`` = 1 whatever the target's size) averages the curvature over
    many standard deviations; one far below it is only rounding. Coordinates without
    positive curvature keep the width they had. With the potential's own ``hessian`` the
    widths play no part.

    Returns
    -------
    (d, d) array or None
        None when an entry is not finite.
    """
    s = np.asarray(spread, dtype=float).copy()
    with np.errstate(all="ignore"):
        for _ in range(SCALE_ROUNDS):
            H = hessian_matrix(potential, q[None, :], s)[0]
            if not np.isfinite(H).all():
                return None
            if getattr(potential, "hessian", None) is not None:
                return H
            c = np.diag(H)
            own = np.where((c > 0) & np.isfinite(c), 1.0 / np.sqrt(np.where(c > 0, c, 1.0)),
                           s)
            own = np.clip(own, 1e-300, 1e300)
            if (np.maximum(own / s, s / own) <= SCALE_AGREE).all():
                return H
            s = own
    return H


#: The gradient check: at most this many coordinates ...
GRADIENT_AXES = 8
#: ... at one of their own standard deviations from the point checked, where a central
#: difference of U of each of these widths (in standard deviations) ...
GRADIENT_WIDTHS = (1e-1, 1e-2, 1e-3, 1e-4)
#: ... differs from the gradient given by more than this fraction: inconsistent.
GRADIENT_TOLERANCE = 1e-2


@dataclass(frozen=True)
class Mismatch:
    """Where the gradient given disagrees with the energy: component ``axis`` of grad U is
    ``gradient`` at ``position``, central differences of U give ``difference``."""

    axis: int
    position: np.ndarray
    gradient: float
    difference: float


def gradient_mismatch(potential: Potential, q: np.ndarray) -> Mismatch | None:
    """Whether the potential's gradient disagrees with its own energy near ``q``.

    Along each of the first :data:`GRADIENT_AXES` coordinates j, with the length
    ``s_j = 1 / sqrt(max_k |H_jk|)`` from how the gradient given changes at q (the largest
    magnitude in row j of its Jacobian: a wrong gradient's diagonal may vanish where its
    row does not; ``|q_j| + 1`` where the row vanishes), the point ``x = q + s_j e_j`` is taken,
    where ``dU/dq_j`` is of the order of ``1 / s_j`` for a smooth target; the central
    difference ``(U(x + w e_j) - U(x - w e_j)) / 2w`` for each width ``w = c s_j`` of
    :data:`GRADIENT_WIDTHS` is compared with the gradient's j-th component there. The two
    are inconsistent when they differ by more than :data:`GRADIENT_TOLERANCE` of the larger
    at every width judged (the widths span truncation and rounding: a smooth U agrees at one
    of them); a width where U's rounding could move the difference by a tenth of the
    tolerance is not judged, nor a point where either is not finite.

    Returns
    -------
    Mismatch or None
        The first disagreement found; None.
    """
    d = q.size
    with np.errstate(all="ignore"):
        H = own_scale_hessian(potential, q, np.abs(q) + 1.0)
        c = np.max(np.abs(H), axis=1) if H is not None else np.zeros(d)
        s = np.where(np.isfinite(c) & (c > 0), 1.0 / np.sqrt(np.where(c > 0, c, 1.0)),
                     np.abs(q) + 1.0)
        for j in range(min(d, GRADIENT_AXES)):
            x = q.copy()
            x[j] += s[j]
            g = float(np.asarray(potential.gradient(x[None, :]), dtype=float)[0, j])
            widths = np.array(GRADIENT_WIDTHS) * s[j]
            shift = np.zeros((widths.size, d))
            shift[:, j] = widths
            up = np.asarray(potential.energy(x + shift), dtype=float)
            down = np.asarray(potential.energy(x - shift), dtype=float)
            fd = (up - down) / (2.0 * widths)
            # a width is judged where U's rounding cannot move the difference by a tenth of
            # the tolerance
            noise = np.finfo(float).eps * (np.abs(up) + np.abs(down)) / (2.0 * widths)
            fine = np.isfinite(fd) & (noise <= 0.1 * GRADIENT_TOLERANCE * np.maximum(
                np.abs(fd), abs(g)))
            if not math.isfinite(g) or not fine.any():
                continue
            gap = np.abs(fd[fine] - g)
            if (gap > GRADIENT_TOLERANCE * np.maximum(np.abs(fd[fine]), abs(g))).all() and \
                    (gap > 0).all():
                return Mismatch(j, x, g, float(fd[fine][np.argmin(gap)]))
    return None


#: A direction is flat when U rises by less than 1 along it (by decades) out to at least
#: this many of its own standard deviations ...
FLAT_REACH = 1e12
#: ... tested along the Hessian's eigenvectors at the mode whose eigenvalue is at most this
#: fraction of the largest (or not positive) ...
FLAT_CURVATURE = 1e-8
#: ... and followed out to this distance in q (the float64 range), or to the first point
#: where U is not finite.
FLOAT_REACH = 1e300


@dataclass(frozen=True)
class Flat:
    """A direction from the mode along which U rises by less than 1 out to ``distance``
    (``scales`` of its own standard deviation ``1 / sqrt(curvature)``, or of the largest
    standard deviation of the curved directions where ``curvature`` is not positive)."""

    distance: float
    curvature: float
    scales: float


def _own_scales(H: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """For unit directions ``V[:, k]`` in q: the curvature ``v^T H v`` along each, its own
    standard deviation ``1 / sqrt(curvature)`` where that is positive, and the largest such
    standard deviation (1 without any), which stands for the others."""
    with np.errstate(all="ignore"):
        c = np.einsum("ik,ij,jk->k", V, H, V)
        own = np.where(c > 0, 1.0 / np.sqrt(np.where(c > 0, c, 1.0)), np.nan)
    fine = np.isfinite(own) & (own > 0)
    fallback = float(own[fine].max()) if fine.any() else 1.0
    return c, np.where(fine, own, fallback), fallback


def _decades(first: float, last: float) -> np.ndarray:
    """``first * 10^k`` for k = 0, 1, ... while at most ``last`` (at least ``first``)."""
    lo = math.log10(first)
    n = max(int(math.floor(math.log10(last) - lo)), 0) if first < last else 0
    return 10.0 ** (lo + np.arange(n + 1))


def flat_direction(target: Target, laplace: Laplace) -> Flat | None:
    """Whether exp(-U) is improper along a direction of vanishing curvature at the mode.

    Along each eigenvector v (mass-weighted, then taken as a unit direction u in q) of the
    Hessian at the mode with eigenvalue at most :data:`FLAT_CURVATURE` times the largest,
    U is evaluated at ``mode +- t u`` for ``t = s 10^k``, from the direction's own standard
    deviation ``s = 1 / sqrt(u^T H u)`` (where that curvature is positive; else the largest
    standard deviation of the directions where it is) out to :data:`FLOAT_REACH`, each side
    up to its first point where U is not finite (+inf: outside the support, so U rises).
    A proper target's U grows without bound (or leaves the support) along every direction;
    a side where U rises by less than 1 at every finite point, out to at least
    :data:`FLAT_REACH` standard deviations, has a density that does not decay, and its
    integral diverges.

    Returns
    -------
    Flat or None
        The first such direction (its reach, curvature and reach in standard deviations),
        or None (none flat).
    """
    lam = laplace.eigenvalues
    if not lam.size or not np.isfinite(lam).all():
        return None
    top = float(np.abs(lam).max())
    W = target.mass.weighted(laplace.hessian)
    lam, V = np.linalg.eigh(0.5 * (W + W.T))
    flat = np.flatnonzero(~(lam > FLAT_CURVATURE * top))
    if not flat.size:
        return None
    H = 0.5 * (laplace.hessian + laplace.hessian.T)
    U = np.asarray(target.mass.weigh_vector(V.T), dtype=float).T
    U = U / np.linalg.norm(U, axis=0)
    curv, own, _ = _own_scales(H, U)
    u0, _, _ = _finite(target, laplace.mode[None, :])
    for k in flat:
        ts = _decades(float(own[k]), FLOAT_REACH)
        points = laplace.mode + np.concatenate([ts, -ts])[:, None] * U[:, k]
        with np.errstate(all="ignore"):
            rise = (np.asarray(target.potential.energy(points), dtype=float)
                    - u0[0]).reshape(2, -1)
        for side in rise:
            bad = ~np.isfinite(side)
            end = int(np.argmax(bad)) if bad.any() else side.size
            if side[:end].size and (side[:end] >= 1.0).any():
                continue
            if end < side.size and side[end] == np.inf:
                continue
            if end and ts[end - 1] >= FLAT_REACH * own[k] * (1 - 1e-12):
                return Flat(float(ts[end - 1]), float(curv[k]), float(ts[end - 1] / own[k]))
    return None


#: Slowly growing U: the growth of U per factor e in distance from the mode is measured over
#: the last :data:`SLOW_DECADES` decades up to :data:`FLAT_REACH` standard deviations ...
SLOW_DECADES = 3
#: ... along at most this many directions (each eigenvector of the Hessian at the mode,
#: both ways; beyond, this many of them spread over its spectrum) ...
SLOW_RAYS = 32
#: ... and the neighbourhood of each ray (a tube of one standard deviation, a cone of a
#: tenth of the distance) is sampled along at most this many other eigenvectors.
SLOW_SIDES = 8


@dataclass(frozen=True)
class SlowGrowth:
    """A direction from the mode along which exp(-U) does not integrate: U grows by
    ``slope`` per factor e in distance over ``[inner, outer]`` and stays within 1 of its
    value on the ray over a ``neighbourhood`` ("tube" of constant width, or "cone" widening
    with the distance) around it."""

    slope: float
    inner: float
    outer: float
    neighbourhood: str
    dimension: int


def slow_direction(target: Target, laplace: Laplace) -> SlowGrowth | None:
    """Whether exp(-U) is improper because U grows too slowly far from the mode.

    Along a ray ``mode + r v`` (v a unit eigenvector of the Hessian of U at the mode, both
    ways), ``U`` is evaluated at ``r = s 10^k`` up to ``s FLAT_REACH`` (s the ray's own
    standard deviation ``1 / sqrt(lambda)`` where its eigenvalue is positive, else the
    largest of the others'; the window ends at :data:`FLOAT_REACH` at most). Where it grows like
    ``alpha log r`` (every one of the last :data:`SLOW_DECADES` decades rises by at most
    ``alpha ln 10``), the density along the ray decays like ``r^-alpha``, and

    * if U stays within 1 of the ray's value at one standard deviation (of the Laplace
      approximation; s where it has none) on each side along the other eigenvectors (a
      tube of constant cross-section around the ray), the integral over
      that tube is at least ``e^-1`` times ``int r^-alpha dr``, which diverges for
      ``alpha <= 1``;
    * if U stays within 1 of it at distance r / 10 (a cone, whose cross-section grows like
      ``r^(d-1)``), the integral over the cone diverges for ``alpha <= d``.

    The neighbourhood is sampled at its extreme points along at most :data:`SLOW_SIDES`
    eigenvectors, not everywhere: a valley narrowing along the ray between the samples is
    not seen. A proper heavy tail (Student-t with nu > 0 degrees of freedom in d dimensions:
    ``alpha = nu + d``) is never below either bound.

    Returns
    -------
    SlowGrowth or None
        The first such direction found, or None.
    """
    lam = laplace.eigenvalues
    if not lam.size or not np.isfinite(lam).all():
        return None
    d = int(lam.size)
    # U's own geometry: the Hessian's eigenvectors in q (the mass plays no part in whether
    # exp(-U) integrates, and weighting by it would tilt the rays off a slow axis)
    H = np.asarray(laplace.hessian, dtype=float)
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    # each direction's own standard deviation (its curvature's, where positive)
    _, sd, _ = _own_scales(0.5 * (H + H.T), V)
    window = 10.0 ** np.arange(-SLOW_DECADES, 1)
    rays = (np.arange(d) if d <= SLOW_RAYS
            else np.linspace(0, d - 1, SLOW_RAYS).round().astype(int))
    for k in rays:
        ts = min(float(sd[k]) * FLAT_REACH, FLOAT_REACH) * window
        others = [j for j in range(min(d, SLOW_SIDES + 1)) if j != k][:SLOW_SIDES]
        sides = V[:, others].T
        for sign in (1.0, -1.0):
            v = sign * V[:, k]
            ray = laplace.mode + ts[:, None] * v
            with np.errstate(all="ignore"):
                u = np.asarray(target.potential.energy(ray), dtype=float)
                rise = np.diff(u) / math.log(10.0)
            if not np.isfinite(u).all():
                continue
            alpha = float(rise.max())
            for neighbourhood, width, bound in (("tube", np.ones_like(ts), 1.0),
                                                 ("cone", ts / 10.0, float(d))):
                if alpha > bound * (1.0 + 1e-9) or (neighbourhood == "cone" and d == 1):
                    continue
                if others:
                    # the tube: one standard deviation of each other direction
                    step = (width[:, None] * (sd[others][None, :] if neighbourhood == "tube"
                                              else 1.0))
                    side = np.concatenate([
                        ray[:, None, :] + sgn * step[:, :, None] * sides[None]
                        for sgn in (1.0, -1.0)], axis=1)
                    with np.errstate(all="ignore"):
                        u_side = np.asarray(target.potential.energy(
                            side.reshape(-1, d)), dtype=float).reshape(ts.size, -1)
                    if not (u_side - u[:, None] <= 1.0).all():
                        continue
                return SlowGrowth(alpha, float(ts[0]), float(ts[-1]), neighbourhood, d)
    return None


@dataclass(frozen=True)
class Draws:
    """Positions from the target, shape (chains, n, d), with where they came from.

    ``source`` is ``"warm-up"`` (this module's sampler) or ``"given"``; for the sampler,
    ``step``, ``max_steps`` and ``acceptance`` (its mean acceptance statistic after
    warm-up), ``divergent`` (divergent transitions after warm-up) and ``seed``."""

    positions: np.ndarray
    source: str
    seed: int | None = None
    step: float | None = None
    max_steps: int | None = None
    acceptance: float | None = None
    divergent: int = 0
    rhat: float | None = None
    effective_size: float | None = None
    #: chains whose draws are all one position (:func:`stuck_chains`)
    stuck: int = 0
    #: the sampler's first kept run: its frozen step and divergent transitions (the
    #: draws are that run's when no refit ran without any) ...
    first_step: float | None = None
    first_divergent: int = 0
    #: ... and the frozen steps of the refits tried after it, in order; each but the last
    #: had a divergent transition, the last too when ``divergent`` is not 0
    refit_steps: tuple[float, ...] = ()

    @property
    def converged(self) -> bool | None:
        """R-hat at most :data:`RHAT_LIMIT` and ESS at least :data:`ESS_LIMIT`, and no
        chain stuck at one position (None without diagnostics and no stuck chain)."""
        if self.stuck:
            return False
        if self.rhat is None or self.effective_size is None:
            return None
        return bool(self.rhat <= RHAT_LIMIT and self.effective_size >= ESS_LIMIT)

    #: the keys of ``hmc --json``'s ``draws`` record named after this sampler's attributes
    JSON_NAMES: ClassVar[Mapping[str, str]] = MappingProxyType({
        "sampler_step": "step", "sampler_max_steps": "max_steps",
        "sampler_acceptance": "acceptance", "sampler_divergent": "divergent",
        "stuck_chains": "stuck", "sampler_first_step": "first_step",
        "sampler_first_divergent": "first_divergent", "sampler_refit_steps": "refit_steps"})

    @property
    def chains(self) -> int:
        """How many chains."""
        return int(self.positions.shape[0])

    @property
    def per_chain(self) -> int:
        """Draws per chain."""
        return int(self.positions.shape[1])

    @property
    def flat(self) -> np.ndarray:
        """The draws as (chains * n, d), chain by chain."""
        return self.positions.reshape(-1, self.positions.shape[-1])


def given_draws(positions: np.ndarray, dimension: int, where: str = "draws") -> Draws:
    """User-supplied draws: shape (n, d) (one chain, in the order drawn) or (chains, n, d);
    finite, at least 2 per chain.

    Parameters
    ----------
    positions
        The draws.
    dimension
        d of the target.
    where
        Names the draws in errors.

    Returns
    -------
    Draws
    """
    try:
        arr = np.array(positions, dtype=float)
    except (TypeError, ValueError):
        raise StepsafeError("draws must be an array of numbers", where) from None
    if arr.ndim == 1 and dimension == 1:
        arr = arr[:, None]
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[-1] != dimension:
        raise StepsafeError(f"draws must have shape (n, {dimension}) or (chains, n, "
                            f"{dimension}), got {np.shape(positions)}", where)
    if arr.shape[1] < 2:
        raise StepsafeError("draws need at least 2 per chain", where)
    if not np.isfinite(arr).all():
        raise StepsafeError("draws have a non-finite entry", where)
    stuck = stuck_chains(arr)
    if arr.shape[1] >= 4:
        r, ess = diagnostics(arr)
        return Draws(arr, "given", rhat=r, effective_size=ess, stuck=stuck)
    return Draws(arr, "given", stuck=stuck)


def stuck_chains(positions: np.ndarray) -> int:
    """How many chains of the draws (chains, n, d) stay at one position throughout: a
    chain of HMC on a continuous target that never moves rejected every proposal, so its
    draws do not represent the target however well R-hat and the effective sample size of
    a constant series read (the same position repeated has no between- or within-chain
    variance)."""
    if positions.shape[1] < 2:
        return 0
    return int((positions == positions[:, :1]).all(axis=(1, 2)).sum())


def _leapfrog(target: Target, q: np.ndarray, p: np.ndarray, g: np.ndarray,
              h: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kick-drift-kick Verlet with a step and a number of steps per chain (rows stop
    moving after their own number of steps); non-finite rows are frozen."""
    pot, mass = target.potential, target.mass
    hcol = h[:, None]
    active = steps > 0
    q, p, g = q.copy(), p.copy(), g.copy()
    for k in range(int(steps.max(initial=0))):
        moving = active & (steps > k) & np.isfinite(q).all(axis=1) & np.isfinite(p).all(axis=1)
        if not moving.any():
            break
        idx = np.flatnonzero(moving)
        hk = hcol[idx]
        pk = p[idx] - 0.5 * hk * g[idx]
        qk = q[idx] + hk * mass.velocity(pk)
        gk = pot.gradient(qk)
        pk = pk - 0.5 * hk * gk
        q[idx], p[idx], g[idx] = qk, pk, gk
        bad = ~(np.isfinite(qk).all(axis=1) & np.isfinite(pk).all(axis=1) &
                np.isfinite(gk).all(axis=1))
        if bad.any():
            q[idx[bad]] = np.nan
    return q, p, g


def _where(where: str | None, key: str) -> str:
    """The file::key (or the keyword) an error about the target names."""
    return f"{where}::$.system.{key}" if where else key


def _finite(target: Target, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """U, grad U and which rows have both finite."""
    with np.errstate(all="ignore"):
        u = np.asarray(target.potential.energy(q), dtype=float)
        g = np.asarray(target.potential.gradient(q), dtype=float)
    return u, g, np.isfinite(u) & np.isfinite(g).all(axis=1)


def starts(target: Target, rng: np.random.Generator, chains: int,
           laplace: Laplace | None = None, start: np.ndarray | None = None,
           where: str | None = None) -> tuple[np.ndarray, float, float]:
    """Dispersed starting points inside the support, with a first step and spread.

    The chains start from ``centre + DISPERSION * S z`` (z standard normal), where the centre
    is the mode with ``S S^T = (nabla^2 U)^-1`` when the Laplace approximation is positive
    definite, else the start given (the origin) with S the mass-weighted inverse square
    roots of the curvature magnitudes there. A start where U or its gradient is not finite
    (outside the support) is redrawn at half the distance from the centre, up to
    :data:`REDRAWS` times, then put at the centre itself.

    Returns
    -------
    (positions (chains, d), first step, spread)
        The first step ``1 / (2 sqrt(lambda_max))`` and the largest standard deviation
        ``1 / sqrt(lambda_min)`` of the mass-weighted curvature at the centre.

    Raises
    ------
    StepsafeError
        When U or its gradient is not finite at the centre (naming the start).
    """
    d = target.dimension
    mass, pot = target.mass, target.potential
    if laplace is not None and laplace.positive_definite:
        W = mass.weighted(laplace.hessian)
        lam, V = np.linalg.eigh(0.5 * (W + W.T))
        centre = laplace.mode

        def offset(z: np.ndarray) -> np.ndarray:
            return np.asarray(mass.weigh_vector((z / np.sqrt(lam)) @ V.T))
        spread = float(1.0 / math.sqrt(lam[0]))
        h = 0.5 / math.sqrt(lam[-1])
    else:
        # the curvature where the chains start sets the first step and spread (its
        # magnitudes: the start need not be a minimum)
        centre = np.zeros(d) if start is None else np.asarray(start, float).reshape(d)
        with np.errstate(all="ignore"):
            lam = np.abs(np.linalg.eigvalsh(mass.weighted(
                hessian_matrix(pot, centre[None, :], 1e-3 * (np.abs(centre) + 1.0))[0])))
        lam = lam[np.isfinite(lam) & (lam > 0)]
        top = float(lam.max()) if lam.size else 1.0
        spread, h = 1.0 / math.sqrt(float(lam.min()) if lam.size else 1.0), 0.5 / math.sqrt(top)

        def offset(z: np.ndarray) -> np.ndarray:
            return np.asarray(spread * mass.weigh_vector(z))
    _, _, ok0 = _finite(target, centre[None, :])
    if not ok0[0]:
        raise StepsafeError("the target's energy or its gradient is not finite at "
                            + ("its mode" if laplace is not None and laplace.positive_definite
                               else "the start") + ": give a start inside the target's support",
                            _where(where, "start"))
    step = offset(DISPERSION * rng.standard_normal((chains, d)))
    q = centre + step
    for _ in range(REDRAWS):
        _, _, ok = _finite(target, q)
        if ok.all():
            break
        step = np.where(ok[:, None], step, 0.5 * step)
        q = centre + step
    else:
        _, _, ok = _finite(target, q)
        q = np.where(ok[:, None], q, centre)
    return q, h, spread


def sample(target: Target, *, chains: int = CHAINS, warmup: int = WARMUP, keep: int = KEEP,
           seed: int = SEED, laplace: Laplace | None = None,
           start: np.ndarray | None = None, where: str | None = None) -> Draws:
    """Draws from the target by the warm-up sampler of the module docstring, with their
    convergence diagnostics.

    Parameters
    ----------
    target
        The potential and mass.
    chains, warmup, keep
        Chains, warm-up iterations and kept iterations per chain.
    seed
        Seed of the random numbers (the result states it).
    laplace
        The Laplace approximation to start from (:func:`find_mode`), if any.
    start
        Where chains start when there is no (positive definite) Laplace approximation.
    where
        The scene file whose ``system:`` gives the target (named in errors), if any.

    Returns
    -------
    Draws
    """
    rng = np.random.default_rng(seed)
    d = target.dimension
    mass, pot = target.mass, target.potential
    q, h, spread = starts(target, rng, chains, laplace, start, where)
    u, g, _ = _finite(target, q)
    step_range = STEP_RANGE
    L_max = 1

    def iterate(h_now: float) -> tuple[np.ndarray, np.ndarray]:
        """One HMC iteration of every chain at nominal step ``h_now``: the acceptance
        probabilities and energy errors (inf where a trajectory stopped being finite)."""
        nonlocal q, g, u, L_max
        length = math.pi * spread
        hs = h_now * step_range ** -rng.uniform(size=chains)
        steps = np.minimum(np.ceil(rng.uniform(size=chains) * length / hs),
                           MAX_WARMUP_STEPS).astype(int)
        steps = np.maximum(steps, 1)
        L_max = max(L_max, int(steps.max()))
        p = mass.momenta(rng.standard_normal((chains, d)))
        with np.errstate(all="ignore"):
            q1, p1, g1 = _leapfrog(target, q, p, g, hs, steps)
            finite = np.isfinite(q1).all(axis=1)
            u1 = np.full(chains, np.inf)
            if finite.any():
                u1[finite] = pot.energy(q1[finite])
            delta = (u1 - u) + (mass.kinetic(np.where(finite[:, None], p1, 0.0))
                                - mass.kinetic(p))
            delta = np.where(np.isfinite(delta), delta, np.inf)
            accept_prob = np.exp(-np.maximum(delta, 0.0))
        accept = (rng.uniform(size=chains) < accept_prob) & np.isfinite(delta)
        q = np.where(accept[:, None], q1, q)
        g = np.where(accept[:, None], g1, g)
        u = np.where(accept, u1, u)
        return accept_prob, delta

    # dual averaging state
    mu, log_bar, s_bar, t0, gamma, kappa = math.log(10 * h), 0.0, 0.0, 10.0, 0.05, 0.75
    ends = {round(warmup * k / 8) for k in range(1, 8)}
    window = np.zeros(chains)
    window_len = 0
    for it in range(warmup):
        accept_prob, _ = iterate(h)
        t = it + 1
        s_bar = (1 - 1 / (t + t0)) * s_bar + (WARMUP_ACCEPT - accept_prob.mean()) / (t + t0)
        log_h = mu - math.sqrt(t) / gamma * s_bar
        log_bar = t ** -kappa * log_h + (1 - t ** -kappa) * log_bar
        h = math.exp(log_h)
        window += accept_prob
        window_len += 1
        if it + 1 in ends and it > 10:
            # chains whose acceptance over the window is far below the others' are
            # stuck where the common step does not fit: moved to another chain
            rate = window / window_len
            stuck = rate < STUCK * float(np.median(rate))
            if stuck.any():
                step_range = min(4.0 * step_range, MAX_STEP_RANGE)
            if stuck.any() and not stuck.all():
                donors = rng.choice(np.flatnonzero(~stuck), size=int(stuck.sum()))
                q[stuck], g[stuck], u[stuck] = q[donors], g[donors], u[donors]
            window[:], window_len = 0.0, 0
            centred = q - q.mean(axis=0)
            white = mass.whiten(centred)  # C^T (q - mean): unit-mass coordinates
            cov = white.T @ white / max(chains - 1, 1)
            top = float(np.linalg.eigvalsh(cov)[-1]) if d > 1 else float(cov[0, 0])
            if math.isfinite(top) and top > 0:
                spread = math.sqrt(top)
        if it + 1 == warmup:
            h = math.exp(log_bar)

    def run(h_now: float, stop_at_divergence: bool) -> _Kept | None:
        """The kept iterations at the frozen step ``h_now``, extended while the diagnostics
        narrowly fail (module docstring); None at the first divergent transition when
        ``stop_at_divergence``."""
        kept = np.empty((chains, keep, d))
        kept_u = np.empty((chains, keep))
        stats: list[float] = []
        divergent, i, total = 0, 0, keep
        while True:
            if i == total:
                r, ess = diagnostics(kept, kept_u)
                n = kept.shape[1]
                if (r <= RHAT_LIMIT and ess >= ESS_LIMIT) or not r <= EXTEND_RHAT or \
                        2 * n > EXTEND * keep:
                    return _Kept(kept, h_now, float(np.mean(stats)) if stats else None,
                                 divergent, r, ess)
                # near the limits: the chains run on at the frozen step, twice as long
                kept = np.concatenate([kept, np.empty_like(kept)], axis=1)
                kept_u = np.concatenate([kept_u, np.empty_like(kept_u)], axis=1)
                total += n
            accept_prob, delta = iterate(h_now)
            kept[:, i] = q
            kept_u[:, i] = u
            stats.append(float(accept_prob.mean()))
            divergent += int((delta > DIVERGENT).sum())
            if divergent and stop_at_divergence:
                return None
            i += 1

    first = run(h, False)
    assert first is not None
    found, refits = first, []
    if first.divergent:
        # divergent transitions: the frozen step is halved and the kept run made afresh
        # from where the chains are, until one runs without any (or REFITS tries)
        for k in range(1, REFITS + 1):
            refits.append(h / REFIT_FACTOR ** k)
            again = run(refits[-1], True)
            if again is not None:
                found = again
                break
    return Draws(found.positions, "warm-up", seed, found.step, L_max, found.acceptance,
                 found.divergent, found.rhat, found.effective_size,
                 stuck_chains(found.positions), first.step, first.divergent, tuple(refits))


@dataclass(frozen=True)
class _Kept:
    """One kept run of the warm-up sampler: positions (chains, n, d), its frozen step, mean
    acceptance statistic, divergent transitions and diagnostics."""

    positions: np.ndarray
    step: float
    acceptance: float | None
    divergent: int
    rhat: float
    effective_size: float


def diagnostics(positions: np.ndarray, energies: np.ndarray | None = None
                ) -> tuple[float, float]:
    """The largest rank-normalised split R-hat and the smallest effective sample size over
    the coordinates of the draws (chains, n, d) and their energies U, when given
    (:mod:`stepsafe.core.hmc_target.statistics`)."""
    series = [positions[..., k] for k in range(positions.shape[-1])]
    if energies is not None:
        series.append(energies)
    return (max(rhat(x) for x in series),
            min(effective_size(x) if np.isfinite(x).all() else 0.0 for x in series))
