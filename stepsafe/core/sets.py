"""Sorted sets of numbers held in 1-D numpy arrays.

numpy's own set routines (``np.unique`` without indices, and ``union1d``, ``setdiff1d``
and ``isin``, which call it) import ``numpy.ma`` the first time they run (numpy 2.x): about
a tenth of the start-up of ``stepsafe check``. These do the same by sorting, for the
arrays of z values and indices the region finder uses.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # (numpy.typing is a module of its own to load: annotations only)
    from numpy.typing import ArrayLike


def distinct(values: ArrayLike) -> np.ndarray:
    """The values in increasing order, each once (``np.unique``; NaNs, which equal
    nothing, are each kept, at the end)."""
    v = np.sort(np.asarray(values).ravel())
    keep = np.ones(v.size, dtype=bool)
    np.not_equal(v[1:], v[:-1], out=keep[1:])
    return v[keep]


def union(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """The values of either array, in increasing order, each once (``np.union1d``)."""
    return distinct(np.concatenate([np.ravel(a), np.ravel(b)]))


def contains(members: ArrayLike, values: ArrayLike) -> np.ndarray:
    """For each of ``values``, whether it equals one of ``members`` (``np.isin(values,
    members)``)."""
    m = np.sort(np.asarray(members, dtype=float).ravel())
    v = np.asarray(values)
    if m.size == 0:
        return np.zeros(v.shape, dtype=bool)
    at = np.minimum(np.searchsorted(m, v), m.size - 1)
    return m[at] == v


def difference(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """The values of ``a`` that are not in ``b``, in increasing order, each once
    (``np.setdiff1d``)."""
    v = distinct(a)
    return v[~contains(b, v)]
