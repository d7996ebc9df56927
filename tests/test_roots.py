"""The vectorised root refinement: Newton on many brackets and levels, Hermite starts."""

from __future__ import annotations

import numpy as np

from stepsafe.core.roots import EPS, hermite_extremum, hermite_root, refine_brackets


def _solutions(level, lo, hi):
    """The solution of cos(3x) = level inside each bracket."""
    k = np.arange(-1, 4)
    cand = np.concatenate([(np.arccos(level) + 2 * np.pi * k) / 3,
                           (-np.arccos(level) + 2 * np.pi * k) / 3])
    inside = (cand[None, :] >= lo[:, None]) & (cand[None, :] <= hi[:, None])
    assert np.all(inside.sum(axis=1) == 1)
    return cand[np.argmax(inside, axis=1)]


def _cells(f, df, z):
    return z[:-1], z[1:], f(z[:-1]), f(z[1:]), df(z[:-1]), df(z[1:])


def test_hermite_starts_are_fourth_order_accurate():
    errors = []
    for n in (60, 120):
        z = np.linspace(0.05, 3.0, n)
        lo, hi, f0, f1, d0, d1 = _cells(lambda x: np.cos(3 * x) - 0.3,
                                        lambda x: -3 * np.sin(3 * x), z)
        cross = f0 * f1 < 0
        assert cross.sum() == 3
        start = hermite_root(lo[cross], hi[cross], f0[cross], f1[cross], d0[cross], d1[cross])
        errors.append(np.abs(start - _solutions(0.3, lo[cross], hi[cross])).max())
        turn = d0 * d1 < 0
        ext = hermite_extremum(lo[turn], hi[turn], f0[turn], f1[turn], d0[turn], d1[turn])
        np.testing.assert_allclose(ext, np.pi / 3 * np.arange(1, 3), atol=1e-5)
    assert errors[0] < 1e-6 and errors[0] / errors[1] > 12


def test_newton_refines_every_level_together_to_the_float_grid():
    z = np.linspace(0.05, 3.0, 40)
    f = lambda x: np.cos(3 * x)  # noqa: E731
    slope = lambda x: (np.cos(3 * x), -3 * np.sin(3 * x))  # noqa: E731
    lo, hi, levels = [], [], []
    for L in (0.5, -0.5):
        v = f(z) - L
        c = np.flatnonzero(v[:-1] * v[1:] < 0)
        lo += [z[c]]
        hi += [z[c + 1]]
        levels += [np.full(c.size, L)]
    lo, hi, lv = map(np.concatenate, (lo, hi, levels))
    roots = refine_brackets(f, lo, hi, f(lo) - lv, f(hi) - lv, slope=slope, level=lv)
    exact = np.concatenate([_solutions(L, lo[lv == L], hi[lv == L]) for L in (0.5, -0.5)])
    assert np.all(np.abs(roots - exact) <= 4 * EPS * exact)
    illinois = refine_brackets(f, lo, hi, f(lo) - lv, f(hi) - lv, level=lv)
    assert np.all(np.abs(illinois - exact) <= 4 * EPS * exact)


def test_newton_converges_on_a_root_at_the_float_floor_without_bisecting_forever():
    calls = []

    def slope(x):
        calls.append(x.size)
        return 1e4 * (x - 1.0 / 3.0) ** 1, np.full(x.shape, 1e4)

    root = refine_brackets(None, np.array([0.0]), np.array([5.0]), np.array([-1e4 / 3]),
                           np.array([1e4 * (5 - 1 / 3)]), slope=slope)
    assert abs(root[0] - 1 / 3) <= 2 * EPS
    assert len(calls) <= 4
