"""Every boundary, resonance and pole stepsafe reports, recomputed at 50 digits.

For each shipped method and family member and each model, the float64 region is found;
then each reported point is re-derived from the method's coefficients in mpmath (stage
equations solved directly, see reference_methods.py): a boundary must be a sign change of
``tr M -+ 2`` (or of the orientation) within 1e-12 relative of the float value, a pole a
sign change of the stage determinant, a resonance an extremum of ``tr M`` at +-2.
A dense float sampling, independent of the finder's logic, checks that no boundary was
missed.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_methods import mp_transfer
from support import method

from stepsafe.core.models import MODELS
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import has_form, transfer_jet
from stepsafe.methods import exact
from stepsafe.methods.library import builtin_names
from stepsafe.reference import highprec as mpref
from stepsafe.reference.verify import check_point
from stepsafe.reference.verify import points as _points

DPS = 50
REL = 1e-12
LIBRARY = [n for n in builtin_names(single_force=True) if n not in ("gauss", "lobatto3ab", "rk4")]
#: The collocation families; their largest members (seconds each at 50 digits) are in the
#: slow set, and the default run keeps every smaller member and the high-stage first points.
FAMILIES = [("gauss", s) for s in (1, 2, 3, 4)] + [("lobatto3ab", s) for s in (2, 3, 4)] + [
    pytest.param(family, s, marks=pytest.mark.slow)
    for family, s in (("gauss", 6), ("lobatto3ab", 5), ("lobatto3ab", 6))]


def _check_point(Mfun, model: str, p) -> None:
    check = check_point(Mfun, model, p, DPS)
    assert check.ok and check.discrepancy <= REL + p.uncertainty / p.z, check


def _dense_crossings(m, model, zmax, poles):
    """Sign changes of the type-deciding function on a fine grid, away from poles."""
    z = np.linspace(zmax / 200_000, zmax, 200_000)
    t = transfer_jet(m, z, model, scale=False).trace
    # tr M = -2 bounds the oscillator's region only; the hyperbolic ones need tr M > 2
    f = (2 - t) * (2 + t) if model == "oscillator" else t - 2
    cells = np.flatnonzero(f[:-1] * f[1:] < 0)
    across_pole = [any(z[c] <= p <= z[c + 1] for p in poles) for c in cells]
    cells = cells[~np.array(across_pole, dtype=bool)] if cells.size else cells
    return z[cells], z[cells + 1]


def _cross_check(m, Mfun, zmax: float = 10.0, most: int = 4):
    """At most ``most`` points per model (the smallest z) at 50 digits, all by sampling."""
    for model in MODELS:
        if not has_form(m, model):  # force-gradient methods: no saddle form
            continue
        region = find_region(m, model, zmax)
        with mp.workdps(DPS):
            for p in sorted(_points(region), key=lambda p: p.z)[:most]:
                _check_point(Mfun, model, p)
        reported = [p.z for p in _points(region) if p.kind in ("root", "resonance")]
        lo, hi = _dense_crossings(m, model, zmax, [p.z for p in region.poles])
        for a, b in zip(lo, hi):
            assert any(a - 1e-9 <= r <= b + 1e-9 for r in reported), (model, a, b)


@pytest.mark.parametrize("name", LIBRARY)
def test_library_method_points_at_50_digits(name):
    _cross_check(method(name), mp_transfer(name, dps=DPS))


@pytest.mark.parametrize("family, s", FAMILIES)
def test_family_points_at_50_digits(family, s):
    _cross_check(method(family, s), mp_transfer(family, s, dps=DPS))


def _floats(X):
    if isinstance(X, mp.matrix):
        return np.array([[float(X[i, j]) for j in range(X.cols)] for i in range(X.rows)])
    return np.array([float(x) for x in X])


@pytest.mark.parametrize("s", [2, 7, 13, 20])
def test_family_tableaux_match_mpmath(s):
    """Stable float construction (no Vandermonde solve) vs mpmath at 40 digits."""
    with mp.workdps(40):
        A, b, c = mpref.gauss_tableau(s)
        A_a, b_l, _ = mpref.lobatto_IIIA_tableau(s)
        A_b, _, _ = mpref.lobatto_IIIB_tableau(s)
    g, lob = method("gauss", s), method("lobatto3ab", s)
    for got, want in ((g.A, A), (g.b, b), (g.c, c), (lob.A_q, A_a), (lob.b_q, b_l),
                      (lob.A_p, A_b)):
        np.testing.assert_allclose(got, _floats(want), rtol=0, atol=4e-16)


@pytest.mark.parametrize("family, s", [("gauss", 15), ("gauss", 20), ("lobatto3ab", 15),
                                       ("lobatto3ab", 20)])
def test_high_stage_first_points_at_50_digits(family, s):
    """The first two reported points of the oscillator region, recomputed at 50 digits."""
    m = method(family, s)
    Mfun = mp_transfer(family, s, dps=DPS)
    region = find_region(m, "oscillator")
    with mp.workdps(DPS):
        for p in sorted(_points(region), key=lambda p: p.z)[:2]:
            _check_point(Mfun, "oscillator", p)


@pytest.mark.parametrize("seed", range(5))
def test_splitting_on_the_saddles_equals_its_prk_stage_solve(seed):
    """The product form used for splittings on the diagonal models against the stacked
    symplectic-Euler PRK solved as a full stage system."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 7))
    with mp.workdps(DPS):
        a = [mp.mpf(float(x)) for x in rng.uniform(-1.5, 1.5, n)]
        k = [mp.mpf(float(x)) for x in rng.uniform(-1.5, 1.5, n)]
        a[-1] += 1 - mp.fsum(a)
        k[-1] += 1 - mp.fsum(k)
        a.append(mp.mpf(0))
        for z in rng.uniform(0.1, 5.0, 3):
            for model in ("saddle", "saddle-p"):
                want = mpref.transfer_matrix_prk(*mpref.splitting_to_prk(a, k), z, model)
                got = mpref.transfer_matrix_splitting(a, k, z, model)
                assert mp.mnorm(got - want, 1) <= mp.mpf(10) ** (8 - DPS) * (
                    1 + mp.mnorm(want, 1))


@pytest.mark.parametrize("s", [1, 2, 3, 4, 7, 12, 21])
def test_legendre_nodes_by_newton_are_the_polynomial_roots(s):
    """The Gauss nodes (roots of P_s) and Lobatto's interior nodes (roots of P_s'), found
    by Newton's method and certified by sign changes, against mpmath.polyroots on the
    shifted Legendre polynomial's coefficients, at 60 digits."""
    with mp.workdps(60):
        gauss = [(1 + x) / 2 for x in exact._gauss_nodes(s)]
        lobatto = [(1 + x) / 2 for x in exact._lobatto_interior(s)]
        leg = exact._shifted_legendre(s)
        for found, roots, count in (
                (gauss, exact._real_roots(leg, s), s),
                (lobatto, exact._real_roots([k * leg[k] for k in range(1, len(leg))], s),
                 s - 1)):
            assert len(found) == len(roots) == count
            assert all(abs(a - b) < mp.mpf(10) ** -55 for a, b in zip(found, roots))


@settings(max_examples=40, deadline=None)
@given(s=st.integers(1, 8), seed=st.integers(0, 2 ** 32 - 1),
       model=st.sampled_from(sorted(MODELS)), z=st.floats(0.05, 20.0),
       explicit=st.booleans())
def test_prk_transfer_equals_the_dense_stage_solve(s, seed, model, z, explicit):
    """M(z) of prk_transfer (a Householder-Hessenberg form, or forward substitution for
    explicit tableaux) against the full 2s x 2s stage system of Q and P solved by mpmath's
    LU, at 50 digits, within the rounding the system's condition allows."""
    rng = np.random.default_rng(seed)
    with mp.workdps(DPS):
        def tableau():
            A = rng.uniform(-1, 1, (s, s))
            return [[mp.mpf(float(A[i, j])) if not explicit or j < i else mp.mpf(0)
                     for j in range(s)] for i in range(s)]

        A_q, A_p = tableau(), tableau()
        b_q, b_p = ([mp.mpf(float(x)) for x in rng.uniform(0, 1, s)] for _ in range(2))
        (lqq, lqp), (lpq, lpp) = mpref.MODELS[model]
        z = mp.mpf(z)
        S = mp.matrix(2 * s, 2 * s)  # unknowns (Q, P): Q = q0 e + z A_q (lqq Q + lqp P), ...
        for i in range(s):
            for j in range(s):
                S[i, j] = (i == j) - z * A_q[i][j] * lqq
                S[i, s + j] = -z * A_q[i][j] * lqp
                S[s + i, j] = -z * A_p[i][j] * lpq
                S[s + i, s + j] = (i == j) - z * A_p[i][j] * lpp
        try:
            inverse = mp.inverse(S)
        except ZeroDivisionError:
            return
        want = mp.matrix(2, 2)
        for col, (q0, p0) in enumerate(((1, 0), (0, 1))):
            X = inverse * mp.matrix([q0] * s + [p0] * s)
            Q, P = X[:s], X[s:]
            want[0, col] = q0 + z * mp.fsum(b_q[j] * (lqq * Q[j] + lqp * P[j]) for j in range(s))
            want[1, col] = p0 + z * mp.fsum(b_p[j] * (lpq * Q[j] + lpp * P[j]) for j in range(s))
        try:
            got = mpref.prk_transfer(A_q, b_q, A_p, b_p)(z, model)
        except ZeroDivisionError:
            return
        condition = mp.mnorm(S, 1) * mp.mnorm(inverse, 1)
        assert mp.mnorm(got - want, 1) <= mp.mpf(10) ** (10 - DPS) * condition * (
            1 + mp.mnorm(want, 1))
