"""Classical (imaginary-axis) stability intervals of non-symplectic RK methods.

stepsafe takes its candidate boundaries from the roots of ``|Q(iy)|^2 - |P(iy)|^2``
(stepsafe.core.rkstability) and decides the status between them from M(z). Here every reported
boundary is re-derived at 50 digits from ``R(iy) = 1 + iy b^T (I - iy A)^-1 e`` with the
stage system solved in mpmath (the float tableau taken exactly), and a dense 50-digit
sampling of ``|R(iy)|`` checks that nothing was missed; closed forms where known.
"""

from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest

from stepsafe.core.regions import classical_interval
from stepsafe.core.rkstability import stability_function, stability_polynomials
from stepsafe.methods.families import gauss, lobatto3a
from stepsafe.methods.tableaux import RungeKutta

DPS = 50
ZMAX = 10.0


def _rk(A, b, name):
    return RungeKutta(np.array(A, dtype=float), np.array(b, dtype=float), name=name)


def _random_explicit(seed: int, s: int) -> RungeKutta:
    rng = np.random.default_rng(seed)
    A = np.tril(rng.uniform(-0.2, 0.8, (s, s)), -1)
    b = rng.uniform(0.05, 1.0, s)
    return _rk(A, b / b.sum(), f"explicit-random-{seed}")


def _random_implicit(seed: int, s: int) -> RungeKutta:
    rng = np.random.default_rng(seed)
    A = rng.uniform(-0.3, 0.6, (s, s))
    b = rng.uniform(0.05, 1.0, s)
    return _rk(A, b / b.sum(), f"implicit-random-{seed}")


CLOSED = [  # (method, first boundary of the interval starting at 0; None = unbounded)
    (_rk([[0, 0, 0, 0], [.5, 0, 0, 0], [0, .5, 0, 0], [0, 0, 1, 0]], [1 / 6, 1 / 3, 1 / 3, 1 / 6],
         "rk4"), 2 * math.sqrt(2)),
    (_rk([[0, 0, 0], [1 / 3, 0, 0], [0, 2 / 3, 0]], [.25, 0, .75], "heun3"), math.sqrt(3)),
    (_rk([[.5, -.5], [.5, .5]], [.5, .5], "lobatto3c-s2"), None),
    (_rk([[5 / 12, -1 / 12], [.75, .25]], [.75, .25], "radau2a-s2"), None),
]
NO_INTERVAL = [_rk([[0]], [1], "euler"), _rk([[0, 0], [.5, 0]], [0, 1], "rk2-midpoint")]
OTHERS = ([gauss(s) for s in (2, 3)]
          + [RungeKutta(*lobatto3a(s)[:2], name=f"lobatto3a-s{s}") for s in (3, 4, 5)]
          + [_random_explicit(k, s) for k, s in ((1, 5), (2, 6), (3, 7), (4, 8))]
          + [_random_implicit(k, s) for k, s in ((5, 2), (6, 3), (7, 4))]
          # islands: a second stable interval, bounded or not
          + [_rk([[0, .5], [-.5, 0]], [.5, .5], "pole-on-axis")]  # singular at z = 2
          + [_random_explicit(111, 6), _random_explicit(150, 9), _random_implicit(147, 3)])


def _mp_excess(m: RungeKutta, y) -> mp.mpf:
    """``|R(iy)|^2 - 1`` from the stage equations in mpmath."""
    s = m.stages
    A = mp.matrix([[mp.mpf(float(a)) for a in row] for row in m.A])
    w = mp.mpc(0, y)
    X = mp.lu_solve(mp.eye(s) - w * A, mp.matrix([1] * s))
    R = 1 + w * sum(mp.mpf(float(m.b[i])) * X[i] for i in range(s))
    return abs(R) ** 2 - 1


def _check(m: RungeKutta) -> None:
    intervals = classical_interval(m, zmax=ZMAX)
    with mp.workdps(DPS):
        for iv in intervals:
            for z, inside in ((iv.lo, +1), (iv.hi, -1)):
                if z in (0.0, None):
                    continue
                d = mp.mpf(z) * mp.mpf("1e-9")
                lo, hi = mp.mpf(z) - inside * d, mp.mpf(z) + inside * d
                assert _mp_excess(m, lo) > 0 > _mp_excess(m, hi), (m.name, z)
                exact = mp.findroot(lambda y: _mp_excess(m, y), (lo, hi), solver="anderson")
                assert abs(z - exact) <= 1e-14 * exact, (m.name, z, exact)
        # dense sampling: |R| <= 1 exactly where reported (away from boundaries and from
        # places where |R| - 1 is within rounding of zero)
        for y in np.linspace(0.013, ZMAX - 0.013, 400):
            if any(abs(y - z) < 1e-6 for iv in intervals for z in (iv.lo, iv.hi) if z):
                continue
            e = _mp_excess(m, mp.mpf(y))
            if abs(e) < 1e-12:
                continue
            reported = any(iv.lo <= y and (iv.hi is None or y <= iv.hi) for iv in intervals)
            assert reported == (e < 0), (m.name, y, float(e))


@pytest.mark.parametrize("m,first", CLOSED, ids=lambda v: getattr(v, "name", ""))
def test_closed_form_intervals(m, first):
    iv = classical_interval(m, zmax=ZMAX)[0]
    assert iv.lo == 0.0
    if first is None:
        assert iv.hi is None
    else:
        assert abs(iv.hi - first) <= 2e-16 * first
    _check(m)


@pytest.mark.parametrize("m", NO_INTERVAL, ids=lambda m: m.name)
def test_methods_unstable_on_the_whole_axis_have_no_interval(m):
    assert classical_interval(m, zmax=ZMAX) == ()
    _check(m)


@pytest.mark.parametrize("m", OTHERS, ids=lambda m: m.name)
def test_intervals_match_50_digit_stage_solves(m):
    _check(m)


def test_islands_are_found():
    assert [len(classical_interval(m, zmax=ZMAX)) for m in OTHERS[-3:]] == [2, 2, 2]


def test_stability_polynomials_match_mpmath_determinants():
    m = _random_implicit(11, 4)
    p, q = stability_polynomials(m)
    with mp.workdps(DPS):
        A = mp.matrix([[mp.mpf(float(a)) for a in row] for row in m.A])
        eb = mp.matrix([[mp.mpf(float(bj)) for bj in m.b] for _ in range(4)])
        for w in (mp.mpf("0.3"), mp.mpf("-1.7"), mp.mpf("2.5")):
            Q = mp.det(mp.eye(4) - w * A)
            P = mp.det(mp.eye(4) - w * A + w * eb)
            assert abs(np.polyval(q[::-1], float(w)) - Q) < 1e-13 * (1 + abs(Q))
            assert abs(np.polyval(p[::-1], float(w)) - P) < 1e-13 * (1 + abs(P))


@pytest.mark.parametrize("m", [CLOSED[0][0], gauss(4), OTHERS[4], _random_implicit(8, 5)],
                         ids=lambda m: m.name)
def test_stability_function_matches_stage_solves(m):
    y = np.linspace(0.05, 8.0, 17)
    R = stability_function(m, 1j * y)
    with mp.workdps(DPS):
        A = mp.matrix([[mp.mpf(float(a)) for a in row] for row in m.A])
        for yk, Rk in zip(y, R):
            w = mp.mpc(0, float(yk))
            X = mp.lu_solve(mp.eye(m.stages) - w * A, mp.matrix([1] * m.stages))
            ref = 1 + w * sum(mp.mpf(float(m.b[i])) * X[i] for i in range(m.stages))
            assert abs(Rk - complex(ref)) <= 1e-14 * abs(ref)


def test_a_pole_on_the_axis_is_nan_not_an_error():
    R = stability_function(OTHERS[-4], [2j, 1j])
    assert np.isnan(R[0]) and abs(R[1] - (1 + 4j / 3)) < 1e-15
