"""stepsafe.core.sets against numpy's set routines, on arrays with repeats, zeros of both
signs (equal, so either may stand for both), infinities and subnormals."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from stepsafe.core.sets import contains, difference, distinct, union

VALUES = st.sampled_from([0.0, -0.0, 1.0, -1.0, 5e-324, 1e308, np.inf, -np.inf, 0.1, 3.0])
FLOATS = st.one_of(VALUES, st.floats(allow_nan=False))
ARRAYS = arrays(float, st.integers(0, 40), elements=FLOATS)


@given(ARRAYS, ARRAYS)
def test_as_numpy_does(a, b):
    np.testing.assert_array_equal(distinct(a), np.unique(a))
    np.testing.assert_array_equal(union(a, b), np.union1d(a, b))
    np.testing.assert_array_equal(difference(a, b), np.setdiff1d(a, b))
    np.testing.assert_array_equal(contains(b, a), np.isin(a, b))


def test_integers_and_nan():
    np.testing.assert_array_equal(distinct(np.array([3, 1, 3, 2, 1])), [1, 2, 3])
    assert not contains([np.nan, 1.0], np.array([np.nan])).any()
    assert contains([], np.array([1.0, 2.0])).tolist() == [False, False]
