"""Where the region finder samples ``M(z)``: a grid that resolves every scale of z.

The grid on ``(0, z_end]`` has three parts:

* a geometric run towards 0 (12 points down to a thousandth of the first uniform step);
* uniform spacing ``dz`` (1/200 divided by how far the substeps reach) up to
  ``z_uniform = UNIFORM_SAMPLES * dz``;
* geometric spacing beyond, ratio ``1 + dz / z_uniform`` (the uniform part's relative
  resolution at its end), coarsened only if more than :data:`GEOMETRIC_SAMPLES` points would
  be needed, so that ``zmax = 1e12`` costs a bounded number of samples.

``z_end`` is ``zmax``, or less when nothing can change beyond a point: for a splitting
method on the ``oscillator`` and ``inverted`` models, ``tr M``, ``M_qp`` and ``M_pq`` are
polynomials in z whose roots (every boundary and every orientation switch) lie below
Fujiwara's bound, computed from the coefficients with their rounding bounds
(:func:`far_bound`). Beyond it the structure is that of the last sample.

The grid is split at the poles (singular stage systems): a cell never spans a pole, and a
segment between two close poles gets at least 16 points of its own.
"""

from __future__ import annotations

import numpy as np

from stepsafe.core.models import KICK_SIGN
from stepsafe.core.roots import EPS
from stepsafe.core.transfer import blocks_of, row_ops
from stepsafe.methods.protocol import Shears
from stepsafe.methods.tableaux import Method

UNIFORM_SAMPLES = 40_000
GEOMETRIC_SAMPLES = 40_000
MIN_SEGMENT_SAMPLES = 16


#: Float64 work per region (samples times the method's ``sample_work``: the flops of a stage
#: solve, (2s)^3 for an implicit s-stage (P)RK method, s^2 for an explicit one, the number
#: of factors of a splitting, times the substeps of a composition): a few seconds here. Gauss
#: s = 40 reaches it at zmax of about 50, Gauss s = 20 at about 1e80; beyond, refused.
SAMPLE_WORK_BUDGET = 5e9


def default_resolution(method: Method) -> float:
    """Uniform grid spacing: 1/200 in z, divided by how far the substeps reach."""
    return 5e-3 / method.reach


def far_bound(method: Method, model: str) -> float:
    """A z beyond which no boundary and no orientation switch exists (inf if unknown).

    For a splitting method (or a composition of one) on ``oscillator``/``inverted``,
    ``M(z)`` is a matrix polynomial: the product of ``I + c z N`` factors, expanded here
    with the absolute-value product alongside (its entries times ``4 K eps`` bound the
    rounding of each coefficient, K factors). Every root of ``tr M -+ 2``, ``M_qp`` and
    ``M_pq`` has modulus at most Fujiwara's bound
    ``2 max_j |q_(N-j) / q_N|^(1/j)`` (the j = N term halved), taken with the
    numerators' bounds and the leading coefficient's lower bound.
    """
    if model not in KICK_SIGN:
        return np.inf
    blocks = blocks_of(method, model)
    if len(blocks) != 1 or not isinstance(blocks[0], Shears) or blocks[0].weight != 1.0:
        return np.inf
    ops = row_ops(blocks[0].splitting, model)  # factors I + c z^k e_dst e_src^T
    if len(ops) > 4000:
        return np.inf
    degree = sum(k for _, _, _, k in ops)
    P = np.zeros((2, 2, degree + 1))
    P[0, 0, 0] = P[1, 1, 0] = 1.0
    A = P.copy()
    with np.errstate(over="ignore", invalid="ignore"):
        for src, dst, c, k in ops:
            P[dst, :, k:] += c * P[src, :, :-k]
            A[dst, :, k:] += abs(c) * A[src, :, :-k]
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(A))):
        return np.inf  # coefficients beyond float64: no bound
    err = 4.0 * (len(ops) + 1) * EPS * A
    trace, trace_err = P[0, 0] + P[1, 1], err[0, 0] + err[1, 1]
    bounds = [_fujiwara(trace - np.eye(1, trace.size, 0)[0] * level, trace_err)
              for level in (2.0, -2.0)]
    bounds += [_fujiwara(P[0, 1], err[0, 1]), _fujiwara(P[1, 0], err[1, 0])]
    return max(bounds)


def _fujiwara(coef: np.ndarray, err: np.ndarray) -> float:
    """Bound on the moduli of the roots of ``sum coef[k] z^k`` (coefficients known to
    ``err``); 0 for a nonzero constant, inf when the degree is uncertain."""
    known = np.flatnonzero(np.abs(coef) > err)
    if known.size == 0:
        return np.inf  # no coefficient is surely nonzero
    n = int(known[-1])
    if np.any(err[n + 1:] > 0):
        return np.inf  # higher coefficients may be nonzero below rounding: degree unknown
    if n == 0:
        return 0.0
    lead = abs(coef[n]) - err[n]
    upper = np.abs(coef[:n]) + err[:n]
    j = n - np.arange(n)
    with np.errstate(divide="ignore", over="ignore"):
        ratios = (upper / lead) ** (1.0 / j)
        ratios[0] = (upper[0] / (2.0 * lead)) ** (1.0 / n)
    return float(2.0 * ratios.max())


def sample_positions(lo: float, hi: float, dz: float, closed_hi: bool) -> np.ndarray:
    """The grid on ``(lo, hi)`` (``hi`` included if ``closed_hi``): geometric run from 0,
    uniform up to ``UNIFORM_SAMPLES * dz``, geometric beyond (see the module docstring)."""
    z_uniform = UNIFORM_SAMPLES * dz
    parts = []
    u_lo, u_hi = lo, min(hi, z_uniform)
    if u_hi > u_lo:
        n = max(MIN_SEGMENT_SAMPLES, int(np.ceil((u_hi - u_lo) / dz)))
        last = u_hi == hi and not closed_hi
        parts.append(u_lo + (u_hi - u_lo) * np.arange(1, n + (0 if last else 1)) / n)
    g_lo = max(lo, z_uniform)
    if hi > g_lo:
        ratio = np.log1p(dz / z_uniform)
        n = int(np.ceil(np.log(hi / g_lo) / ratio))
        n = max(MIN_SEGMENT_SAMPLES, min(n, GEOMETRIC_SAMPLES))
        k = np.arange(1, n + (1 if closed_hi else 0))
        parts.append(g_lo * (hi / g_lo) ** (k / n))
    z = np.concatenate(parts) if parts else np.empty(0)
    if lo == 0.0 and z.size:
        z = np.concatenate([np.geomspace(z[0] * 1e-3, z[0], 13)[:-1], z])
    return z


class Grid:
    """Samples over all pole-free segments of ``(0, z_end]`` at once; a cell
    ``(z[i], z[i+1])`` is usable only when both ends lie in the same segment."""

    def __init__(self, edges: list[float], dz: float, closed_hi: bool) -> None:
        self.edges = np.asarray(edges, dtype=float)
        last = len(edges) - 2
        parts = [sample_positions(lo, hi, dz, closed_hi and i == last)
                 for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])) if hi > lo]
        self.z = np.concatenate(parts) if parts else np.empty(0)

    @classmethod
    def between_poles(cls, pole_z: np.ndarray, z_end: float, dz: float) -> Grid:
        """The grid on ``(0, z_end]`` split at the poles in it (``z_end`` open if a pole)."""
        pole_z = pole_z[pole_z <= z_end]
        closed = not (pole_z.size and pole_z[-1] == z_end)
        return cls([0.0, *map(float, pole_z), z_end], dz, closed)

    def segment(self, z: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.edges, z, side="left") - 1

    def cells(self, z: np.ndarray) -> np.ndarray:
        """Mask of the usable cells between consecutive points of sorted ``z``."""
        seg = self.segment(z)
        return seg[:-1] == seg[1:]
