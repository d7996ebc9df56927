"""Every number the paper prints, confirmed or refuted at 50 digits (mpmath, stage
equations solved directly), and stepsafe's float64 answer checked against the truth.

Each test states the claim, where it is in the paper, and the verdict. docs/validation.md carries
the same table.
"""

from __future__ import annotations

import functools
import math

import mpmath as mp
import pytest
from reference_methods import mp_transfer
from support import method

from stepsafe.core.regions import find_region
from stepsafe.reference import highprec as mpref

DPS = 50
REL = 1e-12


def tr(M):
    return M[0, 0] + M[1, 1]


def root(f, lo, hi):
    with mp.workdps(DPS):
        return mpref.refine_root(f, mp.mpf(lo), mp.mpf(hi))


def osc(name, stages=None):
    Mfun = mp_transfer(name, stages, DPS)
    return lambda z: Mfun(z, "oscillator")


# ---- Table 1: Lobatto IIIA-IIIB s = 2, 3, 4 (confirmed) -------------------------------

TABLE1 = {
    2: (lambda z: 1 - z**2 / 2, "2"),
    3: (lambda z: (1 - mp.mpf(11) / 24 * z**2 + z**4 / 48) / (1 + z**2 / 24), "sqrt(8)"),
    4: (lambda z: (1 - mp.mpf(7) / 15 * z**2 + mp.mpf(23) / 900 * z**4 - z**6 / 3600)
        / (1 + z**2 / 30 + z**4 / 1800), "sqrt(42 - 6*sqrt(29))"),
}


@pytest.mark.parametrize("s", [2, 3, 4])
def test_table1_a1_is_half_the_trace(s):
    """Confirmed: the paper's a_1(z) equals M_qq = M_pp = tr M / 2."""
    a1, _ = TABLE1[s]
    M = osc("lobatto3ab", s)
    with mp.workdps(DPS):
        for z in ("0.3", "1.1", "2.7", "4.2"):
            m = M(mp.mpf(z))
            assert abs(m[0, 0] - a1(mp.mpf(z))) < mp.mpf(10) ** -45
            assert abs(m[1, 1] - m[0, 0]) < mp.mpf(10) ** -45


@pytest.mark.parametrize("s", [2, 3, 4])
def test_table1_boundaries(s):
    """Confirmed: 2, sqrt 8, sqrt(42 - 6 sqrt 29); stepsafe to 1e-12."""
    exact = {2: 2.0, 3: math.sqrt(8), 4: math.sqrt(42 - 6 * math.sqrt(29))}[s]
    M = osc("lobatto3ab", s)
    true = root(lambda z: tr(M(z)) + 2, exact * 0.999, exact * 1.001)
    assert abs(true - exact) < 1e-15
    assert abs(find_region(method("lobatto3ab", s), "oscillator").first_boundary - exact) \
        <= REL * exact


def test_s5_boundary_paper_is_wrong():
    """Paper: 0 < z < 3.140328 for s = 5. Refuted: tr M + 2 = 2.5e-7 > 0 there (still
    elliptic); the boundary is 3.14044510083094259045."""
    M = osc("lobatto3ab", 5)
    with mp.workdps(DPS):
        assert tr(M(mp.mpf("3.140328"))) + 2 > mp.mpf("2e-7")
    true = root(lambda z: tr(M(z)) + 2, "3.1403", "3.1415")
    assert mp.nstr(true, 21) == "3.14044510083094259045"
    z_star = find_region(method("lobatto3ab", 5), "oscillator").first_boundary
    assert abs(z_star - float(true)) <= REL * float(true)


def test_s10_boundary_paper_is_wrong_and_is_a_near_double_root():
    """Paper: 0 < z < 3.141590 for s = 10. Refuted: tr M + 2 = 7.0e-12 > 0 there. The
    structure is lost only on a gap of width ~1e-12 just below pi (tr M + 2 = -1.9e-25),
    far below float64 resolution: stepsafe reports it as a resonance with an uncertainty
    that covers both true boundaries."""
    M = osc("lobatto3ab", 10)
    with mp.workdps(DPS):
        assert tr(M(mp.mpf("3.141590"))) + 2 > mp.mpf("7e-12")
        z_mid = mp.mpf("3.141592653589793")
        assert tr(M(z_mid)) + 2 < 0
    lo = root(lambda z: tr(M(z)) + 2, "3.14159265358", "3.141592653589793")
    hi = root(lambda z: tr(M(z)) + 2, "3.141592653589793", "3.1415926536")
    assert 0 < hi - lo < 1e-11
    region = find_region(method("lobatto3ab", 10), "oscillator")
    res = region.first_boundary_point
    assert res.kind == "resonance"
    assert res.z - res.uncertainty <= float(lo) and float(hi) <= res.z + res.uncertainty


@functools.cache
def true_gap(s: int):
    """The 50-digit boundaries (first boundary, island start) around stepsafe's point."""
    M = osc("lobatto3ab", s)
    p = find_region(method("lobatto3ab", s), "oscillator").first_boundary_point
    with mp.workdps(DPS):
        f = lambda z: tr(M(z)) + 2  # noqa: E731
        z = mp.mpf(p.z)
        if f(z) >= 0:  # a resolved root: the minimum of tr M lies just beyond it
            z = mp.findroot(lambda x: (f(x + mp.mpf("1e-20")) - f(x - mp.mpf("1e-20")))
                            / mp.mpf("2e-20"), z + mp.mpf("1e-3"), tol=mp.mpf(10) ** -40)
        assert f(z) < 0
        return p, root(f, z - mp.mpf("0.01"), z), root(f, z, z + mp.mpf("0.01"))


@pytest.mark.parametrize("s", [5, 6, 7, 8, 9, 10])
def test_conjecture_boundary_tends_to_pi(s):
    """Conjecture (s -> inf): z*(s) -> pi. Supported: the first boundary and the start of
    the next (reversed) island close in on pi from both sides (gap and pi - z* shrink by
    orders of magnitude per stage; the table in docs/validation.md). Where the gap is below float64
    resolution (s >= 7) stepsafe's resonance and its uncertainty cover both boundaries."""
    p, lo, hi = true_gap(s)
    assert lo < mp.pi < hi or lo < hi < mp.pi
    if p.kind == "root":  # near a double root: as close as float64 can tell (its uncertainty)
        assert abs(p.z - float(lo)) <= max(REL * float(lo), p.uncertainty) and p.uncertainty < 1e-8
    else:
        assert p.kind == "resonance"
        assert p.z - p.uncertainty <= float(lo) and float(hi) <= p.z + p.uncertainty
    if s > 5:
        _, lo_prev, hi_prev = true_gap(s - 1)
        assert hi - lo < (hi_prev - lo_prev) / 10 and mp.pi - lo < (mp.pi - lo_prev) / 10


# ---- Compositions of the 2-stage Lobatto IIIA-IIIB pair (= Verlet) --------------------

def _gammas():
    r3 = mp.cbrt(2)
    return 1 / (2 - r3), r3 / (2 - r3)


def test_composition_polynomial_paper_is_wrong():
    """Paper: a_1 = 1 - z^2/2 + g1^2 g2^2 (5 g1 + 4 g2) z^4 / 4 - g1^3 g2 (g1+g2)^2 z^6 / 8
    for the 4th-order composition. Refuted with either sign of g2 (printed positive; the
    triple jump's middle weight is negative): at z = 1 the truth is M_qq = 0.60642086617,
    the polynomial gives 13.55 (g2 > 0) or 0.4938 (g2 < 0)."""
    M = osc("yoshida4")
    with mp.workdps(DPS):
        g1, g2 = _gammas()
        for sign in (1, -1):
            g = sign * g2
            poly = (1 - mp.mpf(1) / 2 + g1**2 * g**2 * (5 * g1 + 4 * g) / 4
                    - g1**3 * g * (g1 + g) ** 2 / 8)
            assert abs(poly - M(mp.mpf(1))[0, 0]) > mp.mpf("0.1")
        assert mp.nstr(M(mp.mpf(1))[0, 0], 11) == "0.60642086617"


def test_composition4_boundary_paper_is_wrong():
    """Paper: 0 < z < sqrt(2.48) = 1.57480 for the 4th-order composition. Refuted: the
    boundary (tr M = +2) is 1.57340194743454005663."""
    M = osc("yoshida4")
    true = root(lambda z: tr(M(z)) - 2, "1.5", "1.6")
    assert mp.nstr(true, 21) == "1.57340194743454005663"
    assert abs(true - mp.sqrt(mp.mpf("2.48"))) > 1e-3
    z_star = find_region(method("yoshida4"), "oscillator").first_boundary
    assert abs(z_star - float(true)) <= REL * float(true)


def test_composition6_boundary_paper_is_wrong():
    """Paper: 0 < z < 1.1034 for the 6th-order composition. Refuted: tr M / 2 = 0.415 at
    1.1034 (nothing happens there); the boundary is 1.59537312778446556603 -- larger than
    the 4th-order one, so the conjecture that composing to higher order shrinks the region
    fails for this sequence (2 -> 1.5734 -> 1.5954)."""
    M = osc("triple-jump6")
    with mp.workdps(DPS):
        assert abs(tr(M(mp.mpf("1.1034"))) / 2 - mp.mpf("0.4154057")) < 1e-6
    true = root(lambda z: tr(M(z)) - 2, "1.59", "1.6")
    assert mp.nstr(true, 21) == "1.59537312778446556603"
    z_star = find_region(method("triple-jump6"), "oscillator").first_boundary
    assert abs(z_star - float(true)) <= REL * float(true)
    assert z_star > find_region(method("yoshida4"), "oscillator").first_boundary


def test_midpoint_composition_saddle_paper_is_wrong():
    """Paper: 0 < z < (2 - 2^(1/3))/2^(1/3) = 0.587401 for the 4th-order composition of the
    midpoint rule on the saddle. Refuted twice: the paper's R drops the midpoint's 1/2
    (R(z) = (1 + z/2)/(1 - z/2)), and the region ends where R_q(z) returns to 1 (M = +I,
    after which the expanding direction swaps), not at a zero of a factor. True boundary
    1.13442400410752489129 (a resonance); the factor's zero is at 1.1748."""
    with mp.workdps(DPS):
        g1, g2 = _gammas()

        def Rq(z):
            r = 1
            for g in (g1, -g2, g1):
                r *= (1 + g * z / 2) / (1 - g * z / 2)
            return r

        assert Rq(mp.mpf("0.587401")) > mp.mpf("1.7")  # well inside: preserved there
        true = mp.findroot(lambda z: Rq(z) - 1, mp.mpf("1.134"))
        assert mp.nstr(true, 21) == "1.13442400410752489129"
        Mfun = mp_transfer("yoshida4", dps=DPS)  # base swapped below in float
    region = find_region(method("yoshida4", base="midpoint"), "saddle")
    assert abs(region.first_boundary - float(true)) <= 1e-12 * float(true) + \
        region.first_boundary_point.uncertainty
    assert region.first_boundary_point.kind == "resonance"
    assert Mfun is not None


# ---- Small cases (confirmed) ----------------------------------------------------------


def test_small_cases_confirmed():
    """Symplectic Euler: elliptic z < 2, saddle z < 1 (a pole); midpoint: saddle z < 2
    (a pole); the paper's Sec. 3 example: 0 < alpha h < 1."""
    se = method("symplectic-euler")
    assert find_region(se, "oscillator").first_boundary == pytest.approx(2.0, rel=REL)
    assert find_region(se, "saddle").first_boundary == pytest.approx(1.0, rel=REL)
    assert find_region(method("midpoint"), "saddle").first_boundary == pytest.approx(2.0,
                                                                                    rel=REL)
    with mp.workdps(DPS):
        M = mp_transfer("symplectic-euler", dps=DPS)(mp.mpf("0.5"), "saddle")
        assert M[0, 0] == 2 and M[1, 1] == mp.mpf("0.5")  # 1/(1-z), 1-z: the paper's (3.x)


# ---- Printed formulas (helper-checked with exact sympy as well) -----------------------


def test_gamma2_sign_printed_wrong():
    """Paper: gamma_2 = 2^(1/3)/(2 - 2^(1/3)). The triple jump needs 2 gamma_1 + gamma_2 = 1,
    so gamma_2 = -2^(1/3)/(2 - 2^(1/3)) < 0: the printed sign is wrong."""
    with mp.workdps(DPS):
        g1, g2 = _gammas()
        assert abs(2 * g1 - g2 - 1) < mp.mpf(10) ** -45  # with the corrected sign
        assert abs(2 * g1 + g2 - 1) > 1


def test_composition_polynomial_z4_coefficient_is_one_24th():
    """M_qq(z) of the triple jump of Verlet is a polynomial of degree 6; its z^2 and z^6
    coefficients match the paper's (-1/2 and -g1^3 g2 (g1+g2)^2 / 8 with the corrected
    g2), but the z^4 coefficient is exactly 1/24, not g1^2 g2^2 (5 g1 + 4 g2) / 4."""
    M = osc("yoshida4")
    with mp.workdps(DPS):
        g1, g2 = _gammas()
        g2 = -g2
        zs = [mp.mpf(k) / 7 for k in range(1, 8)]
        V = mp.matrix([[z**j for j in range(7)] for z in zs])
        coef = mp.lu_solve(V, mp.matrix([M(z)[0, 0] for z in zs]))
        assert abs(coef[0] - 1) < mp.mpf(10) ** -40
        assert abs(coef[2] + mp.mpf(1) / 2) < mp.mpf(10) ** -40
        assert abs(coef[4] - mp.mpf(1) / 24) < mp.mpf(10) ** -40
        assert abs(coef[6] + g1**3 * g2 * (g1 + g2) ** 2 / 8) < mp.mpf(10) ** -40
        assert abs(coef[4] - g1**2 * g2**2 * (5 * g1 + 4 * g2) / 4) > mp.mpf("0.1")


@pytest.mark.parametrize("s", [3, 4, 6])
def test_lobatto_iiib_w_transform_corner_printed_wrong(s):
    """Eq. (2.18): X of Lobatto IIIB has -xi_{s-1} in its corner (row s-1, column s). With
    W[i, k] = sqrt(2k+1) P_k(2 c_i - 1) the corner is -xi_{s-1} (2s-1)/(s-1) (the rest of X
    as printed), computed here as W^-1 A W at 50 digits; IIIA's X (2.17) is confirmed."""
    with mp.workdps(DPS):
        A_a, b, c = mpref.lobatto_IIIA_tableau(s)
        A_b, _, _ = mpref.lobatto_IIIB_tableau(s)
        W = mp.matrix(s, s)
        for i in range(s):
            for k in range(s):
                W[i, k] = mp.sqrt(2 * k + 1) * mp.legendre(k, 2 * c[i] - 1)
        X_a = mp.inverse(W) * A_a * W
        X_b = mp.inverse(W) * A_b * W
        xi = 1 / (2 * mp.sqrt(4 * (s - 1) ** 2 - 1))
        tiny = mp.mpf(10) ** -40
        assert abs(X_a[s - 1, s - 2] - xi) < tiny and abs(X_a[s - 2, s - 1]) < tiny
        assert abs(X_b[s - 1, s - 2]) < tiny
        assert abs(X_b[s - 2, s - 1] + xi * (2 * s - 1) / (s - 1)) < tiny
        assert abs(X_b[s - 2, s - 1] + xi) > mp.mpf("0.01")
