"""A stiffness split into a fast and a slow part, for impulse (multiple time stepping)
methods: ``system: {stiffness_fast: K_f, stiffness_slow: K_s, mass: M}`` in a scene.

``H = p^T M^-1 p / 2 + q^T (K_f + K_s) q / 2``, the fast force ``-K_f q`` and the slow one
``-K_s q``. In mass-weighted coordinates ``A_f = L^-1 K_f L^-T``, ``A_s = L^-1 K_s L^-T``
(``M = L L^T``) the impulse method decouples into independent modes exactly when one
orthogonal basis diagonalises both, that is when ``A_f A_s = A_s A_f``; mode i then has
the fast frequency ``sqrt(v_i^T A_f v_i)`` and the slow one ``sqrt(v_i^T A_s v_i)``. Parts
that do not commute couple the modes through the impulse step (the slow kicks mix the
fast modes): a mode-by-mode answer would be wrong, and the coupled analysis of
:mod:`stepsafe.systems.coupled` runs on the 2n x 2n outer step instead, in the
mass-weighted coordinates ``(L^T q, L^-1 p)`` (a symplectic change of variables, so the
multipliers and their types are those of the step in ``(q, p)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.core.regions import find_region
from stepsafe.core.threads import blas_threads_for
from stepsafe.exceptions import StepsafeError, unknown_key
from stepsafe.systems.coupled import CoupledSystem, coupled_safe_steps
from stepsafe.systems.linear import _cond, check_square, is_positive_definite
from stepsafe.systems.loader import _matrix

EPS = float(np.finfo(float).eps)

KEYS = ("stiffness_fast", "stiffness_slow", "mass")
#: Largest dense split stiffness analysed (each mode a region of its own, or the coupled
#: 2n x 2n analysis).
MAX_DOF = 200
#: Relative size of what a common eigenbasis leaves off the diagonals of A_f and A_s
#: (rounding of the eigensolver is ~n eps): above it the parts are taken as not commuting
#: and the exact coupled analysis runs (parts that commute only nearly would shift the
#: decoupled band edges by about that much).
COMMUTE_TOL = 1e-12
#: Largest relative error of a decoupled mode's frequencies that is accepted.
MAX_RELATIVE_ERROR = 1e-3
#: The coupled scan's reach in z = H sqrt(lambda_max): 5e4 samples of the 2n x 2n step.
MAX_COUPLED_Z = 1e4
#: A generic weight: eigenvectors of A_f + GENERIC A_s split the degenerate eigenspaces of
#: A_f + A_s that A_f and A_s do not share.
GENERIC = 0.7548776662466927


@dataclass(frozen=True)
class SplitStiffness:
    """The mass-weighted fast and slow stiffness ``A_f``, ``A_s`` (n x n, symmetric) and,
    when they commute, their common modes as ``(fast, slow)`` rows (else None)."""

    A_f: np.ndarray
    A_s: np.ndarray
    pairs: np.ndarray | None
    where: str
    #: per mode (rows of ``pairs``), a bound on the relative error of its frequencies
    #: from the whitening and the eigensolver (grows with the mass's condition number)
    errors: np.ndarray | None = None
    #: the same bound for the fastest frequency of A_f + A_s (the coupled analysis)
    coupled_error: float = 0.0


def read_split(tree: Any, where: str, folder: Path) -> SplitStiffness:
    """Read ``system: {stiffness_fast:, stiffness_slow:, mass:}`` and decouple it when the
    mass-weighted parts commute (rows in ascending total frequency)."""
    def fail(key: str, message: str) -> StepsafeError:
        return StepsafeError(message, f"{where}::$.system.{key}" if key else where)

    if not isinstance(tree, dict):
        raise fail("", "system: must be a mapping {stiffness_fast:, stiffness_slow:, mass:}")
    unknown = sorted(set(tree) - set(KEYS))
    if unknown:
        raise fail(unknown[0], "for an impulse method, " + unknown_key(unknown[0], KEYS))
    for key in KEYS[:2]:
        if key not in tree:
            raise fail(key, "missing: an impulse method needs the stiffness split into "
                            "stiffness_fast and stiffness_slow")
    parts = {}
    for key in KEYS:
        if key not in tree:
            continue
        matrix = _matrix(tree[key], where, key, folder)
        try:
            parts[key] = check_square(matrix, key)
        except StepsafeError as exc:
            raise fail(key, exc.message) from None
        if parts[key].shape[0] > MAX_DOF:
            raise fail(key, f"{parts[key].shape[0]} rows; a split stiffness is analysed "
                            f"densely up to {MAX_DOF} dof")
    K_f, K_s = parts["stiffness_fast"], parts["stiffness_slow"]
    if K_s.shape != K_f.shape:
        raise fail("stiffness_slow", f"is {K_s.shape[0]}x{K_s.shape[0]}, stiffness_fast is "
                                     f"{K_f.shape[0]}x{K_f.shape[0]}")
    n = K_f.shape[0]
    M = parts.get("mass")
    if M is not None:
        if M.shape != K_f.shape:
            raise fail("mass", f"is {M.shape[0]}x{M.shape[0]}, the stiffness is {n}x{n}")
        if not is_positive_definite(M):
            raise fail("mass", "must be positive definite")
        L = np.linalg.cholesky(M)
        with np.errstate(all="ignore"):
            A_f, A_s = _whitened(K_f, L), _whitened(K_s, L)
    else:
        A_f, A_s = K_f, K_s
    scale_f, scale_s = float(np.abs(A_f).max()), float(np.abs(A_s).max())
    if not (np.isfinite(scale_f) and np.isfinite(scale_s)) or scale_f + scale_s == 0:
        raise fail("stiffness_fast", "the stiffness is zero or beyond float64 once "
                                     "mass-weighted; rescale the units")
    unit = max(scale_f, scale_s)
    floor = 64 * n * EPS
    for key, A in (("stiffness_fast", A_f), ("stiffness_slow", A_s)):
        low = float(np.linalg.eigvalsh(A / unit)[0])
        if low < -floor:
            raise fail(key, f"has a negative mode ({low * unit:.6g} once mass-weighted): both "
                            "parts must be positive semi-definite for the oscillator model")
    if float(np.linalg.eigvalsh((A_f + A_s) / unit)[0]) <= floor:
        raise fail("stiffness_fast", "fast plus slow stiffness is singular: a zero mode has "
                                     "no force and nothing limits its step; remove it")
    pairs = _common_modes(A_f, A_s, unit)
    errors = None
    # the fastest frequency (which sets h_max) to a relative 16 n eps cond(M) / 2
    coupled_error = 16 * n * EPS * _cond(M) / 2
    if coupled_error > MAX_RELATIVE_ERROR:
        raise fail("mass", "the frequencies are not determined to 1e-3 in float64 (the mass "
                           "is too badly conditioned): rescale")
    if pairs is not None:
        # absolute rounding of each part's eigenvalues (16 n eps |A|, times the mass's
        # condition), relative to each frequency squared, halved by the square root
        amplify = 16 * n * EPS * _cond(M)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.column_stack([amplify * scale_f / pairs[:, 0] ** 2,
                                   amplify * scale_s / pairs[:, 1] ** 2]) / 2
        rel = np.where(pairs > 0, rel, 0.0)  # an absent force has no error
        errors = rel.max(axis=1)
        if np.any(~np.isfinite(errors)) or np.any(errors > MAX_RELATIVE_ERROR):
            raise fail("mass", "a mode's frequencies are not determined to 1e-3 in float64 "
                               "(the mass is too badly conditioned, or a part's mode is at "
                               "rounding level): rescale, or give the modes as fast:/slow:")
    return SplitStiffness(A_f, A_s, pairs, where, errors, coupled_error)


def _common_modes(A_f: np.ndarray, A_s: np.ndarray, unit: float) -> np.ndarray | None:
    """``(fast, slow)`` of the common normal modes, or None if the parts do not commute."""
    from scipy.linalg import eigh

    n = A_f.shape[0]
    _, V = eigh((A_f + GENERIC * A_s) / unit)
    # each part's off-diagonal relative to its own size: a slow part 1e-9 of the fast one
    # that does not commute with it still couples the modes (combination resonances)
    for A in (A_f, A_s):
        size = float(np.abs(A).max())
        if size == 0.0:
            continue
        D = V.T @ (A / size) @ V
        if float(np.abs(D - np.diag(np.diag(D))).max()) > COMMUTE_TOL * max(1.0, n / 10):
            return None
    D_f, D_s = V.T @ (A_f / unit) @ V, V.T @ (A_s / unit) @ V
    w2 = np.clip(np.column_stack([np.diag(D_f), np.diag(D_s)]), 0.0, None) * unit
    return np.sqrt(w2[np.argsort(w2.sum(axis=1))])


def impulse_pairs(tree: Any, where: str, folder: Path) -> np.ndarray:
    """``(fast, slow)`` angular frequencies of the modes of a split stiffness whose parts
    commute (rows, in ascending total frequency); an error naming the key otherwise."""
    split = read_split(tree, where, folder)
    if split.pairs is None:
        raise StepsafeError("the fast and slow parts do not commute (once mass-weighted): the "
                            "impulse step couples the modes", f"{where}::$.system."
                                                              "stiffness_slow")
    return split.pairs


class ImpulseSteps:
    """``M(h) - I`` of one outer step of an impulse method on ``y'' = -(A_f + A_s) y`` (unit
    masses) for :class:`stepsafe.systems.coupled.CoupledSystem`, in its scaled units: S is
    ``blockdiag(A_f + A_s, I) / unit`` and h is ``h * unit``. Each drift adds
    ``c h S_pp p`` to q, each kick ``-c h A q / unit`` to p (A the fast or the slow part),
    accumulated on ``D = M - I`` as the splitting factors are."""

    pieces: tuple = ()  # no implicit stage equations: no poles

    def __init__(self, method: Any, A_f: np.ndarray, A_s: np.ndarray, unit: float) -> None:
        self.ops = method.operations
        self.A = {True: A_f / unit, False: A_s / unit}
        self.norm = {key: float(np.linalg.norm(A)) for key, A in self.A.items()}
        self.inv_unit = 1.0 / unit
        self.n = A_f.shape[0]

    def deviation(self, h: float) -> tuple[np.ndarray, float]:
        n = self.n
        D = np.zeros((2 * n, 2 * n))
        eye = np.eye(n)
        err = 0.0
        for kind, coef, fast in self.ops:
            if kind == "drift":
                P = D[n:].copy()
                P[:, n:] += eye
                c = coef * h * self.inv_unit
                D[:n] += c * P
                err += 2 * n * EPS * abs(c) * float(np.linalg.norm(P))
            else:
                Q = D[:n].copy()
                Q[:, :n] += eye
                c = coef * h
                D[n:] -= c * (self.A[fast] @ Q)
                err += 2 * n * EPS * abs(c) * self.norm[fast] * float(np.linalg.norm(Q))
            if not np.all(np.isfinite(D)):
                return np.full_like(D, np.nan), np.inf
        return D, err


def _coupled_matrix(split: SplitStiffness) -> np.ndarray:
    n = split.A_f.shape[0]
    zero = np.zeros((n, n))
    return np.block([[split.A_f + split.A_s, zero], [zero, np.eye(n)]])


def coupled_impulse(method: Any, split: SplitStiffness, zmax: float | None = None):
    """The safe interval from 0 of the impulse method on the coupled split stiffness
    (:class:`stepsafe.systems.coupled.CoupledResult`), the structure criterion: S is
    positive definite, so ``Q(h) = M^T J - J M > 0`` decides. ``zmax`` in
    ``z = H sqrt(lambda_max(A_f + A_s))`` (default: just past the inner method's own
    limit for the fastest fast frequency)."""
    if zmax is None:
        top = float(np.sqrt(np.linalg.eigvalsh(split.A_f + split.A_s)[-1]))
        fast = float(np.sqrt(max(np.linalg.eigvalsh(split.A_f)[-1], 0.0)))
        if fast > 0:
            z_in = find_region(method.inner, "oscillator", 40.0).first_boundary or 40.0
            zmax = 1.05 * method.substeps * z_in * top / fast
        else:
            zmax = 1.05 * (find_region(method.outer, "oscillator", 40.0).first_boundary
                           or 40.0)
        zmax = min(max(4.0, zmax), MAX_COUPLED_Z)
    return coupled_safe_steps(None, _coupled_matrix(split), zmax, steps=lambda unit:
                              ImpulseSteps(method, split.A_f, split.A_s, unit))


def coupled_impulse_preserved(method: Any, split: SplitStiffness, h: float) -> bool:
    """Whether one outer step H = h keeps the structure of the coupled system."""
    S = _coupled_matrix(split)
    with blas_threads_for(S.shape[0]):
        system = CoupledSystem(None, S, lambda unit: ImpulseSteps(method, split.A_f,
                                                                  split.A_s, unit))
        return system.preserved(h)


def _whitened(K: np.ndarray, L: np.ndarray) -> np.ndarray:
    """``L^-1 K L^-T``, symmetrised."""
    from scipy.linalg import solve_triangular

    X = solve_triangular(L, K, lower=True)
    A = solve_triangular(L, X.T, lower=True)
    return 0.5 * (A + A.T)
