"""A stiffness split into a fast and a slow part, for impulse (multiple time stepping)
methods: ``system: {stiffness_fast: K_f, stiffness_slow: K_s, mass: M}`` in a scene.

``H = p^T M^-1 p / 2 + q^T (K_f + K_s) q / 2``, the fast force ``-K_f q`` and the slow one
``-K_s q``. In mass-weighted coordinates ``A_f = L^-1 K_f L^-T``, ``A_s = L^-1 K_s L^-T``
(``M = L L^T``) the impulse method decouples into independent modes exactly when one
orthogonal basis diagonalises both, that is when ``A_f A_s = A_s A_f``; mode i then has
the fast frequency ``sqrt(v_i^T A_f v_i)`` and the slow one ``sqrt(v_i^T A_s v_i)``. Parts
that do not commute couple the modes through the impulse step (the slow kicks mix the
fast modes) and are refused rather than analysed mode by mode, which would be wrong.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError, unknown_key

KEYS = ("stiffness_fast", "stiffness_slow", "mass")
#: Largest dense system decoupled here (each mode is then a region of its own).
MAX_DOF = 200
#: Relative size of what a common eigenbasis leaves off the diagonals of A_f and A_s
#: (rounding of the eigensolver is ~n eps): above it the parts do not commute.
COMMUTE_TOL = 1e-9
#: A generic weight: eigenvectors of A_f + GENERIC A_s split the degenerate eigenspaces of
#: A_f + A_s that A_f and A_s do not share.
GENERIC = 0.7548776662466927


def impulse_pairs(tree: Any, where: str, folder: Path) -> np.ndarray:
    """``(fast, slow)`` angular frequencies of the modes of a split stiffness (rows), in
    ascending total frequency."""
    from scipy.linalg import eigh

    from stepsafe.systems.linear import check_square, is_positive_definite
    from stepsafe.systems.loader import _matrix

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
            raise fail(key, f"{parts[key].shape[0]} rows; a split stiffness is decoupled "
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
        A_f = _whitened(K_f, L)
        A_s = _whitened(K_s, L)
    else:
        A_f, A_s = K_f, K_s
    scale_f, scale_s = float(np.abs(A_f).max()), float(np.abs(A_s).max())
    if not (np.isfinite(scale_f) and np.isfinite(scale_s)) or scale_f + scale_s == 0:
        raise fail("stiffness_fast", "the stiffness is zero or beyond float64 once "
                                     "mass-weighted; rescale the units")
    unit = max(scale_f, scale_s)
    _, V = eigh((A_f + GENERIC * A_s) / unit)
    D_f, D_s = V.T @ (A_f / unit) @ V, V.T @ (A_s / unit) @ V
    off = max(float(np.abs(D - np.diag(np.diag(D))).max()) for D in (D_f, D_s))
    if off > COMMUTE_TOL * max(1.0, n / 10):
        raise fail("stiffness_slow", "the fast and slow parts do not commute (once "
                                     "mass-weighted): the impulse step couples the modes, "
                                     f"off-diagonal {off:.2g} of the largest entry; give "
                                     "parts with common normal modes")
    w2 = np.column_stack([np.diag(D_f), np.diag(D_s)]) * unit
    floor = 64 * n * np.finfo(float).eps * unit
    if np.any(w2 < -floor):
        i, j = np.argwhere(w2 < -floor)[0]
        raise fail(KEYS[j], f"mode {i} has a negative {'fast' if j == 0 else 'slow'} "
                            f"stiffness {w2[i, j]:.6g}: both parts must be positive "
                            "semi-definite for the oscillator model")
    w2 = np.clip(w2, 0.0, None)
    w2 = w2[np.argsort(w2.sum(axis=1))]
    if np.any(w2.sum(axis=1) == 0):
        raise fail("stiffness_fast", "a mode has neither a fast nor a slow force (a zero "
                                     "mode): nothing limits its step, remove it")
    return np.sqrt(w2)


def _whitened(K: np.ndarray, L: np.ndarray) -> np.ndarray:
    """``L^-1 K L^-T``, symmetrised."""
    from scipy.linalg import solve_triangular

    X = solve_triangular(L, K, lower=True)
    A = solve_triangular(L, X.T, lower=True)
    return 0.5 * (A + A.T)
