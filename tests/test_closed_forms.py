"""Regions against exact closed forms (the paper's Table 1 and Prop. 2; docs/theory.md#regions)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support import method

from stepsafe.core.regions import find_region
from stepsafe.methods.families import gauss, lobatto3ab

REL = 1e-12


def close(a: float | None, b: float, rel: float = REL) -> bool:
    return a is not None and abs(a - b) <= rel * abs(b)


@pytest.mark.parametrize("s, exact", [(2, 2.0), (3, math.sqrt(8)),
                                      (4, math.sqrt(42 - 6 * math.sqrt(29)))])
def test_lobatto_table1_first_boundary(s, exact):
    region = find_region(lobatto3ab(s), "oscillator")
    assert close(region.first_boundary, exact)


def test_lobatto3_island_sqrt12_sqrt24_is_reversed():
    region = find_region(lobatto3ab(3), "oscillator")
    (island, same), = region.islands
    assert close(island.lo, math.sqrt(12)) and close(island.hi, math.sqrt(24))
    # past the flip interval the map rotates the other way: elliptic but not preserved
    assert same is False
    assert len(region.intervals) == 1


def test_gauss2_resonance_at_2_sqrt3():
    region = find_region(gauss(2), "oscillator")
    (res,) = region.resonances
    assert close(res.z, 2 * math.sqrt(3)) and res.detail == "M = -I"
    assert close(region.first_boundary, 2 * math.sqrt(3))
    # elliptic on both sides: the rest of (0, zmax) is one reversed island
    (island, same), = region.islands
    assert island.lo_point == res and island.lo == res.z + res.uncertainty
    assert island.hi is None and same is False


def test_symplectic_euler():
    m = method("symplectic-euler")
    assert close(find_region(m, "oscillator").first_boundary, 2.0)
    saddle = find_region(m, "saddle")
    assert close(saddle.first_boundary, 1.0)
    assert saddle.first_boundary_point.kind == "pole"


def test_midpoint_saddle_pole_at_2_and_oscillator_unconditional():
    m = method("midpoint")
    saddle = find_region(m, "saddle")
    assert close(saddle.first_boundary, 2.0) and [p.z for p in saddle.poles] == [2.0]
    osc = find_region(m, "oscillator", zmax=1e3)
    assert osc.first_boundary is None and len(osc.intervals) == 1


@pytest.mark.parametrize("name", ["verlet", "verlet-position"])
def test_verlet_inverted_preserved_for_all_z(name):
    region = find_region(method(name), "inverted", zmax=1e3)
    assert region.first_boundary is None
    assert [(iv.lo, iv.hi) for iv in region.intervals] == [(0.0, None)]


def test_verlet_is_lobatto3ab_2():
    z = np.linspace(0.01, 5, 50)
    from stepsafe.core.transfer import transfer_matrix

    for model in ("oscillator", "saddle", "inverted"):
        a = transfer_matrix(method("verlet"), z, model)
        b = transfer_matrix(lobatto3ab(2), z, model)
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)


def test_rk4_never_preserved_classical_interval_2_sqrt2():
    region = find_region(method("rk4"), "oscillator")
    assert not region.symplectic and region.intervals == () and region.first_boundary == 0.0
    (classical,) = region.classical
    assert classical.lo == 0.0 and close(classical.hi, 2 * math.sqrt(2))


def test_rk_saddle_equals_inverted():
    """For an RK method both hyperbolic models see R(z), R(-z) (same eigenvectors)."""
    for m in (gauss(3), method("midpoint")):
        a = find_region(m, "saddle")
        b = find_region(m, "inverted")
        assert len(a.intervals) == len(b.intervals) == 1
        assert a.intervals[0].lo == b.intervals[0].lo == 0.0
        assert close(a.intervals[0].hi, b.intervals[0].hi)


def test_published_stability_thresholds():
    """Every method file that cites a published oscillator threshold agrees with the
    computed classical stability limit (|tr M| <= 2, either orientation)."""
    from stepsafe.methods.library import builtin_dir, load_file

    checked = 0
    for path in sorted(builtin_dir().glob("*.yaml")):
        data = load_file(path)
        if data.published_stability is None:
            continue
        region = find_region(method(data.name), "oscillator")
        assert close(region.stability_limit, data.published_stability["value"]), data.name
        checked += 1
    assert checked >= 3


def test_gauss3_resonances_closed_form():
    """R(iz) = N(iz)/N(-iz), N(iz) = 1 - z^2/10 + i (z/2 - z^3/120): the rotation reaches pi
    at sqrt 10 (M = -I) and 2 pi at sqrt 60 (M = +I); the orientation flips at each."""
    region = find_region(gauss(3), "oscillator", zmax=20)
    res = [(p.z, p.detail) for p in region.resonances]
    assert len(res) == 2
    assert close(res[0][0], math.sqrt(10)) and res[0][1] == "M = -I"
    assert close(res[1][0], math.sqrt(60)) and res[1][1] == "M = +I"
    assert [same for _, same in region.islands] == [False, True]


@pytest.mark.parametrize("s", [2, 4, 6])
def test_gauss_has_s_minus_1_resonances(s):
    region = find_region(gauss(s), "oscillator", zmax=200)
    assert len(region.resonances) == s - 1
    assert all(p.detail in ("M = -I", "M = +I") for p in region.resonances)
