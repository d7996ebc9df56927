"""Property tests (hypothesis): random symplectic tableaux, splittings and compositions."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stepsafe.core.models import MODELS
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import poles, transfer_matrix
from stepsafe.methods.residuals import residuals
from stepsafe.methods.tableaux import Composition, PartitionedRK, Splitting

SETTINGS = settings(max_examples=25, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])
coef = st.floats(-1.5, 1.5, allow_nan=False, allow_infinity=False)


@st.composite
def symplectic_prk(draw):
    """A_q random, b random (|b_i| >= 0.1), A_p from b_i A_p[i,j] + b_j A_q[j,i] = b_i b_j."""
    s = draw(st.integers(1, 4))
    A_q = np.array(draw(st.lists(st.lists(coef, min_size=s, max_size=s), min_size=s,
                                 max_size=s)))
    b = np.array(draw(st.lists(st.floats(0.1, 1.0), min_size=s, max_size=s)))
    b = b / b.sum()
    A_p = b[None, :] * (1.0 - A_q.T / b[:, None])
    return PartitionedRK(A_q, b, A_p, b.copy())


@st.composite
def splitting(draw):
    n = draw(st.integers(1, 5))
    a = np.array(draw(st.lists(coef, min_size=n, max_size=n)))
    k = np.array(draw(st.lists(coef, min_size=n, max_size=n)))
    a[-1] += 1.0 - a.sum()  # consistent: sums 1
    k[-1] += 1.0 - k.sum()
    return Splitting(np.append(a, 0.0), k)


def _away_from_poles(m, model, z):
    p = poles(m, model)
    return z[np.all(np.abs(z[:, None] - p[None, :]) > 1e-3 * (1 + np.abs(p)), axis=1)] \
        if p.size else z


Z = np.linspace(0.05, 4.0, 60)


@SETTINGS
@given(symplectic_prk())
def test_random_symplectic_prk_has_det_one(m):
    assert residuals(m).symplectic
    for model in MODELS:
        z = _away_from_poles(m, model, Z)
        M = transfer_matrix(m, z, model)
        big = np.abs(M).max(axis=(1, 2))
        ok = big < 1e6
        det = np.linalg.det(M[ok])
        assert np.all(np.abs(det - 1) <= 1e-10 * np.maximum(1, big[ok] ** 2))


@SETTINGS
@given(splitting(), st.lists(st.floats(-1.0, 1.5), min_size=1, max_size=3))
def test_random_splittings_and_compositions_have_det_one(m, weights):
    w = np.array(weights)
    w[-1] += 1.0 - w.sum()
    comp = Composition(m, w)
    for method in (m, comp):
        for model in MODELS:
            z = _away_from_poles(method, model, Z)
            M = transfer_matrix(method, z, model)
            big = np.abs(M).max(axis=(1, 2))
            ok = big < 1e6
            assert np.all(np.abs(np.linalg.det(M[ok]) - 1) <= 1e-9 * np.maximum(1, big[ok] ** 2))


def _adjoint(m: Splitting) -> Splitting:
    """The adjoint Phi*_h = Phi_{-h}^{-1}: the same operations in reverse order."""
    ops = m.operations[::-1]
    drift, kick = [], []
    for kind, c in ops:
        if kind == "drift":
            if len(drift) > len(kick):
                drift[-1] += c
            else:
                drift.append(c)
        else:
            if len(drift) == len(kick):
                drift.append(0.0)
            kick.append(c)
    return Splitting(drift, kick)


def _crossings(m, model, zmax, n=40_000):
    z = np.linspace(zmax / n, zmax, n)
    t = transfer_matrix(m, z, model)
    t = t[:, 0, 0] + t[:, 1, 1]
    f = (2 - t) * (2 + t)
    return z, np.flatnonzero(f[:-1] * f[1:] < 0)


@SETTINGS
@given(splitting())
def test_region_misses_nothing_wider_than_its_resolution(m):
    """Every sign change of (2 - tr)(2 + tr) seen by dense sampling that is separated from
    its neighbours by more than the stated resolution is a reported boundary."""
    region = find_region(m, "oscillator", zmax=6.0)
    reported = [p.z for iv in region.intervals + region.reversed
                for p in (iv.lo_point, iv.hi_point) if p is not None]
    reported += [p.z for p in region.resonances]
    z, cells = _crossings(m, "oscillator", 6.0)
    crossings = z[cells]
    isolated = [c for c in crossings if np.all(np.abs(crossings[crossings != c] - c)
                                               > region.resolution)]
    for c in isolated:
        assert any(abs(r - c) <= 2 * (z[1] - z[0]) for r in reported), (c, reported)


@SETTINGS
@given(splitting())
def test_method_and_adjoint_have_the_same_oscillator_region(m):
    a = find_region(m, "oscillator", zmax=6.0)
    b = find_region(_adjoint(m), "oscillator", zmax=6.0)
    assert len(a.intervals) == len(b.intervals)
    for x, y in zip(a.intervals, b.intervals):
        assert abs(x.lo - y.lo) <= 1e-9 * (1 + x.lo)
        assert (x.hi is None) == (y.hi is None)
        if x.hi is not None:
            assert abs(x.hi - y.hi) <= 1e-9 * (1 + x.hi)


@SETTINGS
@given(st.one_of(splitting(), symplectic_prk()))
def test_composition_with_weight_one_is_the_base(m):
    comp = Composition(m, [1.0])
    for model in ("oscillator", "inverted"):
        a = find_region(m, model, zmax=5.0)
        b = find_region(comp, model, zmax=5.0)
        assert len(a.intervals) == len(b.intervals)
        for x, y in zip(a.intervals, b.intervals):
            # the same ends, each within the uncertainty it states (one of the two may have
            # been escalated to mpmath and the other not)
            _same_end(x.lo, x.lo_point, y.lo, y.lo_point)
            _same_end(x.hi, x.hi_point, y.hi, y.hi_point)


def _same_end(z1, p1, z2, p2):
    assert (z1 is None) == (z2 is None)
    if z1 is None or z1 == z2:
        return
    slack = sum(p.uncertainty for p in (p1, p2) if p is not None)
    assert abs(z1 - z2) <= slack + 4 * np.spacing(max(abs(z1), abs(z2)))
