"""Hamiltonian Monte Carlo on a Gaussian target: energy error, acceptance rate, cost.

Model. A Gaussian target with precision ``P`` and mass (preconditioner) ``M_mass``: in the
normal coordinates of ``M_mass^-1 P`` every mode is an oscillator of frequency ``beta_k``
(its standard deviation is ``1 / beta_k`` for unit mass), and one step of a splitting or
Runge-Kutta method acts on ``x = (beta q, p)`` by the 2x2 matrix ``M(z)``, ``z = beta h``
(:mod:`stepsafe.core.transfer`). HMC draws ``x ~ N(0, I)`` (the stationary state), runs
``L`` steps and accepts with probability ``min(1, exp(-Delta))``, ``Delta = H(end) - H(start)``.

Energy error of one mode after L steps, ``P_L = M^L``:
``Delta = x^T (P_L^T P_L - I) x / 2``, so ``E[Delta] = (|P_L|_F^2 - 2) / 2``. By
Cayley-Hamilton ``M^L = U_{L-1}(c) M - U_{L-2}(c) I`` (``c = tr M / 2``, ``U`` Chebyshev
polynomials of the second kind), and with ``det M = 1``

    E[Delta_L] = U_{L-1}(c)^2 E_1,   E_1 = ((M_qq - M_pp)^2 + (M_qp + M_pq)^2) / 2.

On the elliptic range ``c = cos theta`` and ``U_{L-1} = sin(L theta) / sin theta``:
``E[Delta_L] = rho(z) sin^2(L theta)`` with ``rho = E_1 / sin^2 theta`` the bound over all
trajectory lengths (``rho(h)`` of Blanes, Casas & Sanz-Serna, SIAM J. Sci. Comput. 36
(2014) A1556, for palindromic methods; this form holds for any symplectic one-step map).
Where M is hyperbolic ``U_{L-1}`` grows like ``e^{L phi}``: acceptance collapses.

Acceptance. ``P_L^T P_L`` has eigenvalues ``s^2, 1/s^2`` with ``s^2 + s^-2 = 2 + 2 E_k``,
so ``Delta = sum_k (a_k u_k^2 + b_k v_k^2)`` with independent standard normals,
``a_k = (E_k + r_k) / 2``, ``b_k = -E_k / (E_k + r_k)``, ``r_k = sqrt(E_k^2 + 2 E_k)``.
Its moment generating function satisfies ``E[e^{t Delta}] = E[e^{-(1 + t) Delta}]``
(true mode by mode since ``(1 + 2 a)(1 + 2 b) = 1``), hence
``E[min(1, e^-Delta)] = 2 P(Delta < 0)`` exactly, and ``P(Delta < 0)`` is the Gil-Pelaez
inversion ``1/2 - (1/pi) int_0^inf Im phi(u) / u du`` of the characteristic function
``phi(u) = prod_k (1 - 2 i a_k u)^(-1/2) (1 - 2 i b_k u)^(-1/2)``, integrated by a
double-exponential rule in ``log u`` (vectorised over nodes and modes).

Many modes. A mode's factor is ``(1 - 2 i a u)(1 - 2 i b u) = 1 - 2 i E u + 2 E u^2``, an
analytic function of its E, which is a smooth function of ``z = beta h`` on the stable
range: sums over a spectrum of more than :data:`MAX_EXACT_MODES` distinct frequencies are
taken by a Gauss rule of the spectrum, bin by bin (:func:`_mode_rule`), used only where it
reproduces the exact ``sum E`` and ``sum E^2`` over every mode to :data:`RULE_RTOL`. Where
it cannot (a trajectory so long that the energy errors oscillate across every few modes,
or a mode past its stability limit), the smallest energy errors beyond
:data:`MAX_EXACT_MODES` are lumped into one normal variable of the same mean and variance
(their sum is then nearly Gaussian: about 1e-6 off in acceptance for 10^5 modes) and the
result says so (``approximate``).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from stepsafe.core.accuracy import offsets
from stepsafe.core.resonances import rotations
from stepsafe.core.roots import EPS, narrowed
from stepsafe.core.sets import distinct
from stepsafe.methods.tableaux import Method

#: Stan's default target for the average acceptance statistic (``adapt_delta``).
DEFAULT_TARGET = 0.8
#: Distinct per-mode energy errors treated exactly; the rest are lumped (module docstring).
MAX_EXACT_MODES = 2048
#: Double-exponential rule for int_0^inf f(u) du/u in t, u = exp(pi/2 sinh t).
_DE_STEP = 1.0 / 16.0
_DE_T = np.arange(-4.5, 4.5 + _DE_STEP / 2, _DE_STEP)


class OneStep(NamedTuple):
    """At each z: ``E_1``, the expected energy error of one step from the stationary state
    (inf where M overflows or the stage equations are singular), ``sin2 = 1 - c^2``
    (negative where M is hyperbolic) and ``c = tr M / 2``."""

    e1: np.ndarray
    sin2: np.ndarray
    half_trace: np.ndarray


def one_step(method: Method, z) -> OneStep:
    """:class:`OneStep` at each ``z = beta h``."""
    with np.errstate(all="ignore"):
        off = offsets(method, z)
        e1 = 0.5 * (off.b_plus_c ** 2 + off.a_minus_d ** 2)
        bad = ~np.isfinite(e1) | ~np.isfinite(off.sin2)
        half_trace = 0.5 * (off.M[:, 0, 0] + off.M[:, 1, 1])
        return OneStep(np.where(bad, np.inf, e1), np.where(bad, -np.inf, off.sin2), half_trace)


def _chebyshev_u_squared(sin2: np.ndarray, half_trace: np.ndarray, steps: int) -> np.ndarray:
    """``U_{L-1}(c)^2`` from ``sin2 = 1 - c^2`` without cancellation: ``sin^2(L theta) /
    sin^2 theta`` (theta measured from the nearer of 0 and pi, so M near -I loses nothing)
    or ``sinh^2(L phi) / sinh^2 phi`` where |c| > 1."""
    with np.errstate(all="ignore"):
        root = np.sqrt(np.abs(sin2))
        elliptic = sin2 > 0
        # each branch on its own entries only (the same operations, entry by entry): the
        # common all-elliptic case pays no arcsinh and sinh
        if elliptic.all():
            u2 = (np.sin(steps * np.arctan2(root, np.abs(half_trace))) / root) ** 2
        else:
            u2 = np.empty_like(root)
            e, r = root[elliptic], root[~elliptic]
            u2[elliptic] = (np.sin(steps * np.arctan2(e, np.abs(half_trace[elliptic])))
                            / e) ** 2
            u2[~elliptic] = (np.sinh(steps * np.arcsinh(r)) / np.where(r > 0, r, 1.0)) ** 2
        # where sin2 rounds to 0 (z -> 0, or M = +-I): the limit L^2
        return np.where(root == 0, np.square(np.float64(steps)), u2)


def energy_errors(method: Method, z, steps: int | None = None) -> np.ndarray:
    """Expected energy error ``E[Delta]`` of each mode at ``z = beta h`` after ``steps``
    steps from the stationary state; with ``steps=None`` the bound over every trajectory
    length, ``rho(z) = E_1 / sin^2 theta`` (inf where M is not elliptic)."""
    return errors_after(one_step(method, z), steps)


def errors_after(first: OneStep, steps: int | None) -> np.ndarray:
    """:func:`energy_errors` from the one-step figures (steps None: the bound rho)."""
    e1, sin2 = first.e1, first.sin2
    with np.errstate(all="ignore"):
        if steps is None:
            out = np.where(sin2 > 0, e1 / np.where(sin2 > 0, sin2, 1.0), np.inf)
        else:
            out = e1 * _chebyshev_u_squared(sin2, first.half_trace, int(steps))
        out = np.where(e1 == 0, 0.0, out)
        return np.where(np.isnan(out), np.inf, out)


@dataclass(frozen=True)
class Acceptance:
    """Expected acceptance probability ``E[min(1, e^-Delta)]`` and the expected energy
    error ``E[Delta]`` of a proposal; ``approximate`` when small modes were lumped."""

    rate: float
    expected_error: float
    approximate: bool = False


def acceptance(errors: np.ndarray, counts: np.ndarray | None = None) -> Acceptance:
    """The acceptance of a proposal whose modes have expected energy errors ``errors``
    (``counts[i]`` modes with ``errors[i]``; see the module docstring)."""
    errors = np.asarray(errors, dtype=float).ravel()
    counts = (np.ones(errors.size) if counts is None
              else np.asarray(counts, dtype=float).ravel())
    return acceptances(errors[None, :], counts)[0]


def acceptances(errors: np.ndarray, counts: np.ndarray) -> list[Acceptance]:
    """:func:`acceptance` for each row of ``errors`` (shape (n, k), the same ``counts``
    for every row), vectorised over rows when ``k <= MAX_EXACT_MODES``."""
    errors = np.asarray(errors, dtype=float)
    if np.isnan(errors).any() or (errors < 0).any():
        raise ValueError("energy errors must be >= 0")
    counts = np.asarray(counts, dtype=float)
    totals = np.where(np.isinf(errors).any(axis=1), np.inf,
                      np.nan_to_num(errors, posinf=0.0) @ counts)
    if errors.shape[1] > MAX_EXACT_MODES:
        return [_lumped(row, counts, total) for row, total in zip(errors, totals)]
    finite = np.where(np.isfinite(errors), errors, 0.0)
    a, b = _weights(finite)
    rates = _gil_pelaez(a, b, counts, np.zeros(len(errors)), np.zeros(len(errors)))
    rates = np.where(np.isinf(totals), 0.0, rates)
    return [Acceptance(float(r), float(t)) for r, t in zip(rates, totals)]


def _weights(errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weights ``a, b`` of ``Delta = a u^2 + b v^2`` for each expected error E:
    ``a = (E + r) / 2``, ``b = -E / (E + r) = -1 / (1 + sqrt(1 + 2/E))``, ``r = sqrt(E^2 +
    2E)``, in forms that neither overflow (E up to the largest float) nor cancel."""
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        root = np.sqrt(errors) * np.sqrt(errors + 2.0)
        a = 0.5 * errors + 0.5 * root
        b = np.where(errors > 0, -1.0 / (1.0 + np.sqrt(1.0 + 2.0 / errors)), 0.0)
    return a, b


def _lumped(errors: np.ndarray, counts: np.ndarray, total: float) -> Acceptance:
    """One row with more distinct modes than :data:`MAX_EXACT_MODES`: the largest exactly,
    the rest as one normal variable of their mean and variance."""
    if not np.isfinite(total):
        return Acceptance(0.0, np.inf, True)
    cut = errors.size - MAX_EXACT_MODES
    order = np.argpartition(errors, cut)  # the cut smallest first (a partition, not a sort)
    small, large = order[:cut], order[cut:]
    a, b = _weights(errors[large])
    # the lumped modes' mean and variance: a + b = E and a^2 + b^2 = E^2 + E exactly
    # ((1 + 2a)(1 + 2b) = 1 gives ab = -E/2), so their weights are not needed
    e, c = errors[small], counts[small]
    mean_g = float(np.sum(c * e))
    var_g = float(np.sum(c * 2.0 * (e * e + e)))
    rate = _gil_pelaez(a[None, :], b[None, :], counts[large], np.array([mean_g]),
                       np.array([var_g]))[0]
    return Acceptance(float(rate), total, True)


#: Nodes whose contribution is provably below this are skipped (see :func:`_gil_pelaez`).
NEGLIGIBLE = 1e-20
#: How many of the largest weights bound the modulus of the characteristic function.
BOUND_TERMS = 32


def _gil_pelaez(a: np.ndarray, b: np.ndarray, counts: np.ndarray, mean_g: np.ndarray,
                var_g: np.ndarray) -> np.ndarray:
    """``2 P(Delta < 0)`` per row, ``Delta = sum_k counts_k (a_k u^2 + b_k v^2) + N(mean_g,
    var_g)``: ``1 - (2/pi) int_0^inf Im phi(u) du / u`` by the double-exponential rule, u
    scaled by each row's largest weight. A node is skipped where its term is provably below
    :data:`NEGLIGIBLE`: ``|Im phi(u)| <= |arg phi(u)| <= u (sum |a| + |b| + |mean_g|)`` near
    0, and ``|phi(u)| <= prod (1 + 4 a^2 u^2)^(-1/4)`` over the largest weights alone."""
    scale = np.maximum(a.max(axis=1, initial=0.0), np.sqrt(var_g))  # no 2a: a may be 1e308
    rates = np.ones(len(a))
    live_rows = np.flatnonzero(scale > 0)
    if not live_rows.size:
        return rates
    weight = 0.5 * np.pi * np.cosh(_DE_T) * _DE_STEP
    u = np.exp(0.5 * np.pi * np.sinh(_DE_T))[None, :] / scale[live_rows][:, None]
    a, b = a[live_rows], b[live_rows]
    mean_g, var_g = mean_g[live_rows], var_g[live_rows]
    # bounds that decide which nodes matter
    spread = (np.abs(a) + np.abs(b)) @ counts + np.abs(mean_g)
    small = weight[None, :] * u * spread[:, None] < NEGLIGIBLE
    top = min(BOUND_TERMS, a.shape[1])
    biggest = np.argsort(-np.abs(a), axis=1)[:, :top]
    a_top = np.take_along_axis(a, biggest, axis=1)
    c_top = counts[biggest]
    log_bound = -0.25 * np.einsum("rnk,rk->rn", np.log1p(4.0 * (a_top[:, None, :] * u[:, :, None])
                                                            ** 2), c_top)
    log_bound -= 0.5 * var_g[:, None] * u ** 2
    live = ~small & (log_bound + np.log(weight)[None, :] > np.log(NEGLIGIBLE))
    integral = np.zeros(len(live_rows))
    for row in np.flatnonzero(live.any(axis=1)):
        nodes = np.flatnonzero(live[row])
        uu = u[row, nodes]
        log_mod, arg = _log_characteristic(a[row], b[row], counts, uu)
        log_mod -= 0.5 * var_g[row] * uu ** 2
        arg += mean_g[row] * uu
        integral[row] = math.fsum(weight[nodes] * np.exp(log_mod) * np.sin(arg))
    rates[live_rows] = np.clip(1.0 - 2.0 / np.pi * integral, 0.0, 1.0)
    return rates


def _log_characteristic(a: np.ndarray, b: np.ndarray, counts: np.ndarray, u: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``(log |phi(u)|, arg phi(u))`` of ``sum_k counts_k (a_k u^2 + b_k v^2)`` at the nodes
    u of one row: ``-1/4 sum counts log(1 + x^2)`` and ``1/2 sum counts atan(x)`` over
    ``x = 2 a u`` and ``x = 2 b u`` (a row at a time keeps the (nodes, modes) arrays in
    cache: 3.4x faster than all rows' live nodes at once for 1000 modes)."""
    log_mod = np.zeros(u.size)
    arg = np.zeros(u.size)
    for coef in (a, b):
        x = coef[None, :] * (2.0 * u)[:, None]  # (nodes, k); 2 c first could overflow
        log_mod -= 0.25 * (np.log1p(x * x) @ counts)
        arg += 0.5 * (np.arctan(x) @ counts)
    return log_mod, arg


#: L from an integration time is capped here (no sampler takes more steps; beyond, L theta
#: has no digits left in float64 anyway).
MAX_TRAJECTORY_STEPS = 10**12


@dataclass(frozen=True)
class Trajectory:
    """How a sampler sets the number of steps L: fixed (``steps``), from an integration time
    (``length``: ``L = max(1, floor(length / h))`` at the nominal step, as Stan's static
    HMC), or unknown (neither: the bound over every L). ``jitter`` j draws each step
    uniformly from ``h (1 - j, 1 + j)`` with L kept, as Stan's ``stepsize_jitter``."""

    steps: int | None = None
    length: float | None = None
    jitter: float = 0.0

    def capped(self, h: float) -> float | None:
        """``length / h`` where it exceeds :data:`MAX_TRAJECTORY_STEPS` (the L that
        :meth:`steps_at` caps), else None."""
        if self.steps is not None or self.length is None:
            return None
        with np.errstate(over="ignore"):
            wanted = self.length / h
        return float(wanted) if wanted > MAX_TRAJECTORY_STEPS else None

    def steps_at(self, h: float) -> int | None:
        """L at nominal step h (capped at :data:`MAX_TRAJECTORY_STEPS`, see
        :meth:`capped`); None when the trajectory length is not given."""
        if self.steps is not None:
            return self.steps
        if self.length is not None:
            with np.errstate(over="ignore"):
                return max(1, int(min(self.length / h, MAX_TRAJECTORY_STEPS)))
        return None


#: What methods are ranked by (a report's ``ranked_by``, a row's key of that name): with the
#: trajectory given (L steps, or an integration time T and ``L = floor(T / h)`` at each
#: method's step), the gradient evaluations per accepted proposal at the L the sampler runs,
#: ``(L e + overhead) / alpha`` (``e`` per step, ``alpha`` the acceptance); without one,
#: per accepted unit of simulated time, ``e / (alpha h)`` (no L to count a proposal by).
RANKINGS = {
    "gradients_per_accepted": "gradient evaluations per accepted proposal at the L run",
    "gradients_per_time": "gradient evaluations per accepted unit of simulated time",
}


def ranked_by(trajectory: Trajectory) -> str:
    """The key of :data:`RANKINGS` that methods on ``trajectory`` are ranked by."""
    given = trajectory.steps is not None or trajectory.length is not None
    return "gradients_per_accepted" if given else "gradients_per_time"


def _distinct(betas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    values, counts = np.unique(np.asarray(betas, dtype=float), return_counts=True)
    keep = values > 0
    return values[keep], counts[keep].astype(float)


def acceptance_at(method: Method, betas: np.ndarray, h: float,
                  trajectory: Trajectory = Trajectory()) -> Acceptance:
    """Predicted acceptance of HMC with ``method`` at nominal step ``h`` on the Gaussian
    whose modes have frequencies ``betas`` (jittered steps: the average over the jitter
    interval, see :func:`acceptance_curve`)."""
    return acceptance_curve(method, betas, np.array([float(h)]), trajectory)[0]


#: The jitter average is a composite 8-point Gauss-Legendre rule: at least this many panels
#: for a jitter of 1/2, in proportion to J with one at least (the bound over L, smooth in h)
#: or four times as many (a given L, whose energy error turns like sin^2(L theta)), halved
#: where L theta turns by more than
#: :data:`PANEL_TURN` across one, and at most :data:`MAX_JITTER_NODES` nodes (beyond, the
#: result says ``approximate``).
JITTER_PANELS = 2
MAX_JITTER_NODES = 2048
_GL8 = np.polynomial.legendre.leggauss(8)


#: Samples across a jitter interval that locate the stability edges; the edges and the
#: turns of L theta are followed for at most this many of the fastest modes.
JITTER_SAMPLES = 129
JITTER_MODES = 32
#: Levels of geometric refinement of the panels next to a stability edge.
EDGE_LEVELS = 12


def _jitter_rule(method: Method, values: np.ndarray, h: float, jitter: float,
                 steps: int | None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Nodes u in [-1, 1] and weights (summing to 2) for the average over h (1 + jitter u):
    the interval is split where a fast mode crosses a stability edge (sin^2 theta changes
    sign: a cliff), each piece gets panels graded towards its cliffs, and for a given L
    panels are halved until L theta turns little across each (:func:`_follow_turns`)."""
    u = np.linspace(-1.0, 1.0, JITTER_SAMPLES)
    top = values[-JITTER_MODES:]
    first = one_step(method, np.outer(h * (1.0 + jitter * u), top).ravel())
    sin2 = first.sin2.reshape(u.size, top.size)
    # stability edges: where sin2 changes sign between samples, located to rounding (a cut
    # off the edge leaves the kink inside a panel: 1e-3 of acceptance at L = 20)
    cuts = {-1.0, 1.0}
    cliffs: set[float] = set()  # the cuts at stability edges (panels graded towards them)
    # the fastest mode's edges (the others' cliffs are lower: fewer modes fall off them)
    flips = np.argwhere(np.sign(sin2[:-1, -1:]) * np.sign(sin2[1:, -1:]) < 0)
    for i, _ in flips[:4]:
        a, b = sin2[i, -1], sin2[i + 1, -1]
        if np.isfinite(a) and np.isfinite(b):
            cliff = _edge(method, h * top[-1], jitter, float(u[i]), float(u[i + 1]))
            cuts.add(cliff)
            cliffs.add(cliff)
    # zeros of the bound rho: a symmetric method's M = [[a, b], [c, a]] is a pure rotation
    # where b + c = 0, and there rho ~ (z - z0)^2 puts a kink |z - z0| in the bound's
    # acceptance (1 - sqrt(2 E) / (pi/2)...); a cut there keeps it off a panel's interior
    # (for a given L the panels follow the turns of L theta, which resolves it anyway)
    zero = np.zeros(0, dtype=int)
    if steps is None:
        fast = offsets(method, h * top[-1] * (1.0 + jitter * u))
        zero = np.argwhere((np.sign(fast.b_plus_c[:-1]) * np.sign(fast.b_plus_c[1:]) < 0)
                           & (sin2[:-1, -1] > 0) & (sin2[1:, -1] > 0)).ravel()
    for i in zero[:4]:
        cut = _rotation(method, h * top[-1], jitter, float(u[i]), float(u[i + 1]))
        if cut is not None:
            cuts.add(cut)
    cuts_sorted = sorted(cuts)
    # panels in proportion to the width of the jitter interval (JITTER_PANELS for
    # J = 1/2): the bound is smooth in h; a given L turns like sin^2(L theta), whose fast
    # modes are followed below and whose slow ones turn by 2 J theta at most across it
    base = max(1.0, JITTER_PANELS * 2.0 * jitter) * (1 if steps is None else 4)
    x, w = _GL8
    grading = 0.5 ** np.arange(1, EDGE_LEVELS + 1)
    pieces: list[np.ndarray] = []
    for lo, hi in zip(cuts_sorted[:-1], cuts_sorted[1:]):
        n = max(1, int(np.ceil(base * (hi - lo) / 2.0)))
        piece = [np.linspace(lo, hi, n + 1)]
        # an energy error that grows like e^(2 L phi) past an edge turns the acceptance in a
        # layer of width ~ 1/L^2 at it: panels shrink geometrically towards each edge
        # (a rotation's kink needs only the cut: either side of it is smooth)
        if lo in cliffs:
            piece.append(lo + (hi - lo) * grading / n)
        if hi in cliffs:
            piece.append(hi - (hi - lo) * grading / n)
        pieces.append(np.concatenate(piece))
    edges = distinct(np.concatenate(pieces))
    approximate = False
    if steps is not None:
        edges, approximate = _follow_turns(method, top, h, jitter, steps, edges)
    half = 0.5 * np.diff(edges)
    nodes = ((0.5 * (edges[:-1] + edges[1:]))[:, None] + half[:, None] * x).ravel()
    return nodes, (half[:, None] * w[None, :]).ravel(), approximate


#: A panel of the jitter rule is split until ``L theta`` turns by at most this (radians)
#: across it, for every mode sampled: the acceptance of a given L goes like sin^2(L theta),
#: and 8 Gauss-Legendre nodes integrate a turn of 2 rad to ~1e-9.
PANEL_TURN = 1.0
#: Past a stability edge the energy error grows like sinh^2(L phi): beyond L phi = this,
#: the acceptance it leaves is below e^-GROWTH_CAP and needs no finer panels.
GROWTH_CAP = 30.0


def _follow_turns(method: Method, top: np.ndarray, h: float, jitter: float, steps: int,
                  edges: np.ndarray) -> tuple[np.ndarray, bool]:
    """``edges`` with panels halved until ``steps * theta`` of each mode of ``top`` turns by
    at most :data:`PANEL_TURN` across each (theta has a square-root edge where a mode
    turns unstable, so the panels shrink towards it), within :data:`MAX_JITTER_NODES`;
    and whether that budget cut it short."""
    def angle(first: OneStep) -> np.ndarray:
        """``L theta`` of each one-step matrix (0 where it is not stable)."""
        with np.errstate(invalid="ignore"):
            t = np.arctan2(np.sqrt(np.maximum(first.sin2, 0.0)), first.half_trace)
        return steps * np.nan_to_num(np.where(first.sin2 > 0, t, 0.0))

    def at(us: np.ndarray, betas: np.ndarray) -> OneStep:
        return one_step(method, h * (1.0 + jitter * us) * betas)

    def turning(us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``L theta`` and ``L theta + L phi``: past its edge a mode's growth (capped where
        the acceptance it leaves is nil) turns the acceptance too."""
        first = at(np.repeat(us, top.size), np.tile(top, us.size))
        with np.errstate(invalid="ignore", over="ignore"):
            growth = np.minimum(steps * np.arcsinh(np.sqrt(np.maximum(-first.sin2, 0.0))),
                                GROWTH_CAP)
        t = angle(first).reshape(us.size, top.size)
        return t, t + np.nan_to_num(growth).reshape(us.size, top.size)

    panels = MAX_JITTER_NODES // 8
    turns, total = turning(edges)
    short = False
    while True:
        mids = 0.5 * (edges[:-1] + edges[1:])
        turns_mid, total_mid = turning(mids)
        turn = (np.abs(total_mid - total[:-1]) + np.abs(total[1:] - total_mid)).max(axis=1)
        split = (turn > PANEL_TURN) & (mids > edges[:-1]) & (mids < edges[1:])
        if not split.any():
            break
        if edges.size - 1 + int(split.sum()) > panels:
            short = True
            break
        order = np.argsort(np.concatenate([edges, mids[split]]), kind="stable")
        edges = np.concatenate([edges, mids[split]])[order]
        total = np.concatenate([total, total_mid[split]])[order]
        turns = np.concatenate([turns, turns_mid[split]])[order]
    # the acceptance of a given L depends on |sin(L theta)|: it has a kink wherever
    # L theta = k pi. An edge there, found by bisection, leaves every panel smooth
    k_lo, k_hi = np.floor(turns[:-1] / np.pi), np.floor(turns[1:] / np.pi)
    panel, mode = np.nonzero((k_lo != k_hi) & (turns[:-1] > 0) & (turns[1:] > 0))
    if panel.size == 0 or edges.size - 1 + panel.size > panels:
        return edges, short or panel.size > 0
    target = np.pi * np.maximum(k_lo, k_hi)[panel, mode]
    a, b, betas = edges[panel], edges[panel + 1], top[mode]
    f_a, f_b = turns[panel, mode] - target, turns[panel + 1, mode] - target
    # regula falsi with the Illinois rule (a retained end's value halved), every fourth
    # round a bisection: the bracket closes to rounding in a few rounds where L theta is
    # smooth, and at worst halves every four near a square-root edge
    side = np.zeros(a.size)
    for round_ in range(4 * 60):
        open_ = (b - a) > 4.0 * EPS
        if not open_.any():
            break
        with np.errstate(invalid="ignore", divide="ignore"):
            x = np.where(round_ % 4 == 3, 0.5 * (a + b), a - f_a * (b - a) / (f_b - f_a))
        x = np.where(np.isfinite(x) & (x > a) & (x < b), x, 0.5 * (a + b))
        f_x = angle(at(x, betas)) - target
        with_a = np.sign(f_x) == np.sign(f_a)  # the root lies in (x, b)
        f_b = np.where(with_a & (side == 1), 0.5 * f_b, f_b)
        f_a = np.where(~with_a & (side == -1), 0.5 * f_a, f_a)
        a, f_a = np.where(open_ & with_a, x, a), np.where(open_ & with_a, f_x, f_a)
        b, f_b = np.where(open_ & ~with_a, x, b), np.where(open_ & ~with_a, f_x, f_b)
        side = np.where(with_a, 1, -1)
    return distinct(np.concatenate([edges, 0.5 * (a + b)])), short


def _rotation(method: Method, z: float, jitter: float, lo: float, hi: float
              ) -> float | None:
    """The u in (lo, hi) where ``b + c`` of M at ``z (1 + jitter u)`` changes sign (Brent),
    if M is a pure rotation there (``a - d`` within rounding of 0: a symmetric method);
    else None (the energy error has no zero, only a minimum)."""
    from scipy.optimize import brentq

    def b_plus_c(x: float) -> float:
        return float(offsets(method, np.array([z * (1.0 + jitter * x)])).b_plus_c[0])

    try:
        x = float(brentq(b_plus_c, lo, hi, xtol=1e-15, rtol=1e-15))
    except ValueError:
        return None
    at = offsets(method, np.array([z * (1.0 + jitter * x)]))
    size = float(np.abs(at.M[0]).max())
    return x if abs(float(at.a_minus_d[0])) <= 1e-12 * size else None


def _edge(method: Method, z: float, jitter: float, lo: float, hi: float) -> float:
    """The u in (lo, hi) where sin^2 theta at ``z (1 + jitter u)`` changes sign (Brent)."""
    from scipy.optimize import brentq

    def sin2(x: float) -> float:
        return float(one_step(method, np.array([z * (1.0 + jitter * x)])).sin2[0])

    try:
        return float(brentq(sin2, lo, hi, xtol=1e-15, rtol=1e-15))
    except ValueError:  # (no sign change at float precision: the sampled one is the edge)
        return 0.5 * (lo + hi)


#: Beyond :data:`MAX_EXACT_MODES` distinct frequencies the modes are replaced by a
#: quadrature rule of the spectrum (:func:`_mode_rule`): this many points per bin ...
RULE_POINTS = 8
#: ... bins across which ``L theta + log rho`` (at the jitter's longest step) changes by at
#: most this ...
RULE_VARIATION = 0.5
#: ... and the rule is used only if it reproduces ``sum E`` and ``sum E^2`` over the modes
#: to this relative error at the jitter's two ends (else every mode is evaluated).
RULE_RTOL = 1e-11


def _gauss_rules(t: np.ndarray, w: np.ndarray, starts: np.ndarray, points: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The ``points``-point Gauss rule of each discrete measure ``sum w_i delta(t_i)`` over
    the segments of ``t`` that begin at ``starts`` (t in [-1, 1] within each; shape
    (segments, points) nodes and positive weights, integrating every polynomial of degree
    below ``2 points`` as the measure does; meaningful for segments of more than
    ``points`` distinct t). The recurrence of the orthonormal polynomials by the discretised
    Stieltjes procedure (stable for a discrete measure when ``points`` is small against its
    support), then the eigenvalues of each Jacobi matrix (Golub-Welsch)."""
    sizes = np.diff(np.append(starts, t.size))
    total = np.add.reduceat(w, starts)
    alpha, beta = np.zeros((starts.size, points)), np.zeros((starts.size, points))
    p_prev, p = np.zeros_like(t), np.repeat(1.0 / np.sqrt(total), sizes)
    wt = w * t
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(points):
            alpha[:, k] = np.add.reduceat(wt * p * p, starts)
            nxt = (t - np.repeat(alpha[:, k], sizes)) * p
            if k:
                nxt -= np.repeat(beta[:, k - 1], sizes) * p_prev
            if k + 1 < points:
                beta[:, k] = np.sqrt(np.add.reduceat(w * nxt * nxt, starts))
                p_prev, p = p, nxt / np.repeat(beta[:, k], sizes)
    jacobi = np.zeros((starts.size, points, points))
    index = np.arange(points)
    jacobi[:, index, index] = alpha
    jacobi[:, index[:-1], index[1:]] = beta[:, :-1]
    jacobi[:, index[1:], index[:-1]] = beta[:, :-1]
    good = np.isfinite(jacobi).all(axis=(1, 2))
    nodes, vectors = np.zeros((starts.size, points)), np.zeros((starts.size, points, points))
    nodes[good], vectors[good] = np.linalg.eigh(jacobi[good])
    return nodes, total[:, None] * vectors[:, 0, :] ** 2


#: Bins of the spectrum start at multiples of its size over this (see :func:`_mode_rule`).
RULE_GRAINS = 4096
#: The Gauss rules of the bins of the last spectrum seen: its digest and rule by bin.
_BIN_RULES: dict[str, Any] = {"digest": None, "rules": {}}


def _bin_rules(values: np.ndarray, counts: np.ndarray, starts: np.ndarray,
               stops: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and weights of the bins ``values[start:stop]``: each bin of more than
    ``2 RULE_POINTS`` modes by its :data:`RULE_POINTS`-point Gauss rule (in
    ``t = (beta - mid) / half``), the others as they are. Rules are kept for the spectrum
    last seen (identified by a digest of ``values`` and ``counts``): a search evaluates
    many steps on one spectrum, and bins recur. The digest samples a thousand values and
    counts: a stale rule can only fail :func:`_mode_rule`'s check against every mode,
    never pass for a wrong spectrum unchecked."""
    stride = max(1, values.size // 1024)
    digest = hashlib.blake2b(np.concatenate([values[::stride], counts[::stride],
                                             [values.size, values[-1], counts.sum()]]
                                            ).tobytes(), digest_size=16).hexdigest()
    if _BIN_RULES["digest"] != digest:
        _BIN_RULES["digest"], _BIN_RULES["rules"] = digest, {}
    known: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = _BIN_RULES["rules"]
    wanted = [(int(lo), int(hi)) for lo, hi in zip(starts, stops)
              if hi - lo > 2 * RULE_POINTS and (int(lo), int(hi)) not in known]
    if wanted:
        lo_, hi_ = np.array(wanted).T
        index = np.concatenate([np.arange(lo, hi) for lo, hi in wanted])
        mid = 0.5 * (values[lo_] + values[hi_ - 1])
        half = 0.5 * (values[hi_ - 1] - values[lo_])
        sizes = hi_ - lo_
        t = (values[index] - np.repeat(mid, sizes)) / np.repeat(half, sizes)
        t_rule, w_rule = _gauss_rules(t, counts[index],
                                      np.concatenate([[0], np.cumsum(sizes)[:-1]]),
                                      RULE_POINTS)
        for k, key in enumerate(wanted):
            known[key] = (mid[k] + half[k] * np.clip(t_rule[k], -1.0, 1.0), w_rule[k])
    nodes, weights = [], []
    for lo, hi in zip(starts, stops):
        if hi - lo > 2 * RULE_POINTS:
            nodes.append(known[(int(lo), int(hi))][0])
            weights.append(known[(int(lo), int(hi))][1])
        else:
            nodes.append(values[lo:hi])
            weights.append(counts[lo:hi])
    return np.concatenate(nodes), np.concatenate(weights)


def _mode_rule(method: Method, values: np.ndarray, counts: np.ndarray, h: float,
               jitter: float, steps: int | None) -> tuple[np.ndarray, np.ndarray] | None:
    """Frequencies and weights that stand for the modes ``values`` (sorted, with
    ``counts``) in every sum over modes at the steps ``h (1 + jitter u)``, or None where
    the modes are to be evaluated one by one.

    The energy error of a mode, ``E_L(z) = E_1(z) U_{L-1}(c(z))^2`` (``rho(z)`` for the
    bound over L), is a smooth function of ``z = beta h`` on the stable range (a polynomial
    in z for a splitting), and so is every per-mode term of the acceptance's characteristic
    function, ``-1/2 log(1 + 2 E (u^2 - i u))`` (``(1 - 2 i a u)(1 - 2 i b u) = 1 - 2 i E
    u + 2 E u^2``). The sorted spectrum is cut into bins across which ``L theta + log
    rho`` changes by at most :data:`RULE_VARIATION` at the longest step, and each bin's
    modes are replaced by the :data:`RULE_POINTS`-point Gauss rule of their counts (exact
    for polynomials of degree below 16 in beta: the error of a smooth term is that of its
    best such approximation on the bin, times the bin's count). The rule is used only where
    every mode is stable at the longest step and it reproduces the exact ``sum E`` and
    ``sum E^2`` over every mode to :data:`RULE_RTOL` at the shortest and longest steps, and
    where it has at most half as many points as there are modes."""
    if values.size <= MAX_EXACT_MODES:
        return None
    ends = sorted({h * (1.0 + jitter), h * (1.0 - jitter)}, reverse=True)
    first = _one_step(method, ends[0] * values)
    if not ((first.sin2 > 0).all() and np.isfinite(first.e1).all()):
        return None
    with np.errstate(divide="ignore"):
        theta = np.arctan2(np.sqrt(first.sin2), first.half_trace)
        log_rho = np.log(first.e1 / first.sin2)
    turn = (0 if steps is None else steps) * theta + np.maximum(log_rho, np.log(EPS))
    cumulative = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(turn)))])
    cuts = np.flatnonzero(np.diff(np.floor(cumulative / RULE_VARIATION))) + 1
    # cut points snapped down to a grain of the spectrum: nearby steps share bins, whose
    # rules are then computed once (the check below holds whatever the bins)
    grain = max(1, values.size // RULE_GRAINS)
    cuts = distinct(cuts // grain * grain)
    cuts = cuts[cuts > 0]
    starts = np.concatenate([[0], cuts])
    stops = np.concatenate([cuts, [values.size]])
    if RULE_POINTS * starts.size > values.size // 2:
        return None
    rule, rule_weights = _bin_rules(values, counts, starts, stops)
    if rule.size > values.size // 2:
        return None
    for s in ends:
        exact = errors_after(first, steps) if s == ends[0] else _errors(method, s * values,
                                                                         steps)
        approx = _errors(method, s * rule, steps)
        for power in (1, 2):
            want = float(np.sum(counts * exact ** power))
            got = float(np.sum(rule_weights * approx ** power))
            if not (np.isfinite(want) and abs(got - want) <= RULE_RTOL * want):
                return None
    return rule, rule_weights


def acceptance_curve(method: Method, betas: np.ndarray, hs: np.ndarray,
                     trajectory: Trajectory = Trajectory()) -> list[Acceptance]:
    """:func:`acceptance_at` at each nominal step of ``hs``."""
    values, counts = _distinct(betas)
    hs = np.asarray(hs, dtype=float).ravel()
    j = trajectory.jitter
    out = []
    for h in hs:
        steps = trajectory.steps_at(h)
        if j == 0.0:
            nodes, weights, rough = np.zeros(1), np.full(1, 2.0), False
        else:
            nodes, weights, rough = _jitter_rule(method, values, h, j, steps)
        rule = _mode_rule(method, values, counts, h, j, steps)
        modes, mode_counts = (values, counts) if rule is None else rule
        # rows of the jitter rule in pieces: (nodes x modes) matrices, and the
        # characteristic function's (rows x quadrature nodes x modes), stay bounded
        k = max(modes.size, 1)
        rows = max(1, min(CHUNK_ELEMENTS // k, (16 * CHUNK_ELEMENTS) // (_DE_T.size * k)))
        found = []
        for start in range(0, nodes.size, rows):
            z = np.outer(h * (1.0 + j * nodes[start:start + rows]), modes)
            found += acceptances(_errors(method, z, steps), mode_counts)
        rate = float(np.dot(weights, [a.rate for a in found])) / 2.0
        with np.errstate(invalid="ignore", over="ignore"):
            mean_error = float(np.dot(weights, [a.expected_error for a in found])) / 2.0
        # sin(L theta) from float64's L theta: an absolute error near eps L theta
        long = steps is not None and steps > EXACT_STEPS
        out.append(Acceptance(min(max(rate, 0.0), 1.0), mean_error,
                              rough or long or any(a.approximate for a in found)))
    return out


#: Above this many steps per trajectory, ``L theta`` carries an error beyond 1e-9 rad
#: (eps L pi) and the figures are marked approximate (L reaches 1e12 from a long length).
EXACT_STEPS = 10**6


#: The target step is searched on at least this many grid points below the upper end, then
#: narrowed
TARGET_GRID = 32
#: ... and on this many points per half-turn of what makes a given trajectory's acceptance
#: oscillate in h (:func:`target_grid`), up to :data:`MAX_TARGET_GRID` points.
HALF_TURN_POINTS = 4
MAX_TARGET_GRID = 1024


def target_grid(trajectory: Trajectory, h_hi: float, least: int = TARGET_GRID) -> np.ndarray:
    """The grid of steps in ``(0, h_hi]`` a search for the step at target walks.

    With L steps given, an oscillator's energy error after L steps carries the factor
    ``sin^2(L theta(h))``; over ``0 < h <= h_hi`` the per-step angle theta rises from 0 to
    at most pi, so the acceptance dips at most L times, once per half-turn of ``L theta``:
    the grid has :data:`HALF_TURN_POINTS` points per half-turn, ``4 L``. With an
    integration time T, ``L = floor(T / h)`` jumps at ``h = T / k``, teeth of width
    ``h^2 / T`` near h; the grid puts :data:`HALF_TURN_POINTS` points in each tooth from
    ``h_hi / 2`` up, ``16 T / h_hi`` points (where the acceptance is near 1 further down, a
    tooth's dip does not reach the target). Unknown L (the bound over every L): ``least``.
    Always at least ``least`` and at most :data:`MAX_TARGET_GRID` points.

    Parameters
    ----------
    trajectory : Trajectory
        L, or the integration time, and the jitter.
    h_hi : float
        The upper end (> 0).
    least : int
        The fewest points.

    Returns
    -------
    numpy.ndarray
        The steps, increasing, the last ``h_hi``.
    """
    turns = 0.0
    if trajectory.steps is not None:
        turns = float(trajectory.steps)
    elif trajectory.length is not None:
        with np.errstate(over="ignore"):
            turns = 4.0 * trajectory.length / h_hi
    wanted = HALF_TURN_POINTS * turns if math.isfinite(turns) else MAX_TARGET_GRID
    n = int(min(MAX_TARGET_GRID, max(least, math.ceil(wanted))))
    return h_hi * (np.arange(1, n + 1) / n)
#: ... to this relative width (a prediction: finer says nothing more).
TARGET_RTOL = 1e-6


#: The bound's local maxima between grid points are found on this finer grid of steps.
PEAK_GRID = 1024


def target_step(method: Method, betas: np.ndarray, target: float, h_hi: float,
                trajectory: Trajectory = Trajectory(), h_lo: float = 0.0) -> float | None:
    """The largest h below ``h_hi`` such that the predicted acceptance is at least
    ``target`` at every step from 0 to h, checked on the grid of :func:`target_grid` and
    at every local maximum of the total error bound ``sum_k rho(beta_k h)`` (located on
    :data:`PEAK_GRID` steps and refined by a parabola), then narrowed to
    :data:`TARGET_RTOL` (:func:`stepsafe.core.roots.narrowed`: regula falsi between the
    last step reaching the target and the first missing it); None when even
    ``h_hi / 2^60`` misses it. With an unknown trajectory length this uses the bound over
    every L, so the acceptance holds whatever L the sampler takes; with a given L (or an
    integration time), the acceptance of that L.

    The grid is walked upwards and the bound's maxima are looked for only below its first
    miss: the steps above it cannot change the answer. ``h_lo`` (below ``h_hi``) is a step
    up to which every step is known to reach the target, such as the step at target of the
    bound over every L when a given L is searched (an L-step trajectory's energy error is
    within the bound, so its acceptance is at least the bound's): the walk starts there."""
    def excess(h: float) -> float:
        return acceptance_at(method, betas, h, trajectory).rate - target

    lo, f_lo = 0.0, 1.0 - target
    if 0.0 < h_lo < h_hi:
        lo, f_lo = float(h_lo), excess(float(h_lo))
        if f_lo < 0:  # not so after all: search from 0
            lo, f_lo = 0.0, 1.0 - target
    known = lo  # every step up to it reaches the target
    bad: tuple[float, float] | None = None
    walked: list[tuple[float, float]] = [(lo, f_lo)] if lo > 0 else []
    for h in target_grid(trajectory, h_hi):
        if h <= known:
            continue
        f = excess(float(h))
        if f < 0:
            bad = (float(h), f)
            break
        walked.append((float(h), f))
        # a dip narrower than the grid's spacing: its lowest point, between the neighbours
        # of a grid step lower than both, or past the first step walked when it rises from it
        ends = None
        if len(walked) >= 3 and walked[-2][1] < min(walked[-3][1], f):
            ends = (walked[-3][0], walked[-1][0])
        elif len(walked) == 2 and known > 0 and walked[0][1] < f:
            ends = (walked[0][0], walked[1][0])
        if ends is not None:
            dip = _lowest(excess, *ends)
            if dip[1] < 0:
                bad = dip
                lo, f_lo = max(w for w in walked if w[0] < dip[0])
                break
        lo, f_lo = float(h), f
    reach = h_hi if bad is None else bad[0]
    good = [(lo, f_lo)] if lo > 0 else []
    for peak in np.unique(_bound_peaks(method, betas, h_hi, reach)):
        if not known < peak <= reach or (bad is not None and peak >= bad[0]):
            continue
        f = excess(float(peak))
        if f < 0:
            bad = (float(peak), f)
            break
        good.append((float(peak), f))
    if bad is None:
        return float(h_hi)
    hi, f_hi = bad
    below = [g for g in good if g[0] < hi]
    lo, f_lo = max(below) if below else (0.0, 1.0 - target)
    if lo == 0.0:
        for _ in range(60):  # below the first grid step: geometric
            f = excess(hi / 2.0)
            if f >= 0:
                lo, f_lo = hi / 2.0, f
                break
            hi, f_hi = hi / 2.0, f
        else:
            return None
    return narrowed(excess, lo, f_lo, hi, f_hi, TARGET_RTOL)


def _lowest(f: Callable[[float], float], a: float, b: float,
            rtol: float = TARGET_RTOL) -> tuple[float, float]:
    """The lowest point of ``f`` on ``[a, b]`` by golden-section search (f with one minimum
    there), to a bracket ``rtol * b`` wide: ``(h, f(h))``."""
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = f(c), f(d)
    while b - a > rtol * b:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = f(d)
    return (c, fc) if fc < fd else (d, fd)


def _bound_peaks(method: Method, betas: np.ndarray, h_hi: float,
                 reach: float | None = None) -> np.ndarray:
    """The steps below ``h_hi`` (and, if given, up to about ``reach``) where
    ``sum_k rho(beta_k h)`` has a local maximum on the grid of :data:`PEAK_GRID` steps up to
    ``h_hi``: a dip of the acceptance that a coarse grid could step over. Beyond
    :data:`PEAK_MODES` distinct frequencies the fastest are kept and the others merged
    into :data:`PEAK_BINS` geometric bins (each at its largest beta, with the bin's count):
    the peaks are only extra steps at which the acceptance is then evaluated in full, so
    this bounds the search's cost (``PEAK_GRID`` times at most ``PEAK_MODES + PEAK_BINS``
    matrices) without changing any reported figure's definition."""
    values, counts = _binned(*_distinct(betas))
    h = h_hi * (np.arange(1, PEAK_GRID + 1) / PEAK_GRID)
    if reach is not None:  # the grid's steps up to reach, and one beyond (a maximum there)
        h = h[:min(PEAK_GRID, int(np.searchsorted(h, reach, side="right")) + 2)]
    total = np.zeros(h.size)
    rows = max(1, CHUNK_ELEMENTS // max(values.size, 1))
    with np.errstate(invalid="ignore", over="ignore"):
        for start in range(0, h.size, rows):
            part = h[start:start + rows]
            total[start:start + rows] = errors_after(
                one_step(method, np.outer(part, values).ravel()), None).reshape(
                part.size, values.size) @ counts
    i = np.flatnonzero((total[1:-1] > total[:-2]) & (total[1:-1] >= total[2:])
                       & np.isfinite(total[1:-1])) + 1
    if not i.size:
        return i.astype(float)
    y0, y1, y2 = total[i - 1], total[i], total[i + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = 0.5 * (y0 - y2) / (y0 - 2.0 * y1 + y2)
    shift = np.where(np.isfinite(shift), np.clip(shift, -1.0, 1.0), 0.0)
    step = h_hi / PEAK_GRID
    return np.concatenate([h[i] + shift * step, h[i]])


#: The peak search keeps this many of the fastest distinct frequencies exactly ...
PEAK_MODES = 1024
#: ... and merges the slower ones into this many geometric bins.
PEAK_BINS = 1024
#: Arrays of z are evaluated in pieces of at most this many elements (memory bound).
CHUNK_ELEMENTS = 2**18


def _binned(values: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted distinct ``values`` with ``counts``: the :data:`PEAK_MODES` largest as they
    are, the rest merged into at most :data:`PEAK_BINS` geometric bins (largest value,
    summed count)."""
    if values.size <= PEAK_MODES + PEAK_BINS:
        return values, counts
    cut = values.size - PEAK_MODES
    slow, slow_counts = values[:cut], counts[:cut]
    edges = np.geomspace(slow[0], slow[-1], PEAK_BINS + 1)
    index = np.clip(np.searchsorted(edges, slow, side="right") - 1, 0, PEAK_BINS - 1)
    top = np.zeros(PEAK_BINS)
    np.maximum.at(top, index, slow)
    summed = np.bincount(index, weights=slow_counts, minlength=PEAK_BINS)
    keep = summed > 0
    return (np.concatenate([top[keep], values[cut:]]),
            np.concatenate([summed[keep], counts[cut:]]))


def _one_step(method: Method, z: np.ndarray) -> OneStep:
    """:func:`one_step` of a 1-D array of z in pieces, as :func:`_errors` evaluates."""
    piece = min(ERROR_CHUNK, CHUNK_ELEMENTS)
    parts = [one_step(method, z[start:start + piece]) for start in range(0, z.size, piece)]
    return OneStep(*(np.concatenate(field) for field in zip(*parts)))


def _errors(method: Method, z: np.ndarray, steps: int | None) -> np.ndarray:
    """:func:`energy_errors` of an array of z, evaluated in pieces of
    :data:`CHUNK_ELEMENTS` (the one-step matrices of 10^7 modes at once would take
    gigabytes)."""
    flat = z.ravel()
    out = np.empty(flat.size)
    piece = min(ERROR_CHUNK, CHUNK_ELEMENTS)
    for start in range(0, flat.size, piece):
        out[start:start + piece] = errors_after(one_step(method, flat[start:start + piece]),
                                                steps)
    return out.reshape(z.shape)


#: :func:`_errors` evaluates z in pieces of this many elements (at most
#: :data:`CHUNK_ELEMENTS`): each of the few dozen
#: temporaries of the one-step matrices is then 128 KiB, which stays in cache and in the
#: allocator's reused memory (2^18 elements per piece took twice the CPU time, much of it
#: in page faults of fresh 2 MiB arrays). Elementwise work: the pieces change no value.
ERROR_CHUNK = 2**14


@dataclass(frozen=True)
class ModeError:
    """The expected energy error of the ``count`` modes of frequency ``beta``."""

    beta: float
    count: int
    expected_error: float


def largest_errors(method: Method, betas: np.ndarray, h: float, steps: int | None,
                   keep: int = 5) -> tuple[ModeError, ...]:
    """The ``keep`` distinct frequencies whose modes add most to the expected energy error
    at step h (L steps; None: the bound over every L), largest first."""
    values, counts = _distinct(betas)
    errs = _errors(method, values * h, steps)
    order = np.argsort(-(errs * counts), kind="stable")[:keep]
    return tuple(ModeError(float(values[i]), int(counts[i]), float(errs[i] * counts[i]))
                 for i in order)


def stall_steps(method: Method, region, beta: float, steps: int, h_near: float,
                window: float) -> tuple[tuple[int, float], ...]:
    """The steps h within ``h_near (1 +- window)`` where L steps turn the mode of frequency
    ``beta`` by a whole number m of turns, ``L theta(beta h) = 2 pi m``: its proposal is its
    starting point (a fixed-L sampler does not move that mode; jitter avoids it). At most
    :data:`MAX_STALLS` values of m nearest the middle are located."""
    if steps < 3 or beta <= 0:
        return ()
    first = one_step(method, beta * h_near * np.array([1.0 - window, 1.0 + window]))
    with np.errstate(invalid="ignore"):
        theta = np.arctan2(np.sqrt(np.maximum(first.sin2, 0.0)), first.half_trace)
    turns = steps * theta / (2.0 * np.pi)
    lo, hi = int(np.floor(turns.min())), int(np.ceil(turns.max()))
    start = max(lo, 1, (lo + hi) // 2 - MAX_STALLS // 2)
    pairs = [(steps, m) for m in range(start, min(hi, start + MAX_STALLS - 1) + 1)
             if 2 * m < steps]
    found = rotations(method, region, pairs)
    return tuple((r.m, r.z / beta) for r in found
                 if abs(r.z / beta / h_near - 1.0) <= window)


#: How many stall steps (values of m) are located around a step.
MAX_STALLS = 16
