"""Every z inside an interval that ``region`` lists (API, JSON) keeps what the interval
claims, confirmed at 50 digits from the method's definition: an interval ends where the
uncertainty band of its end point (a resonance, a root, a pole) or an undecided stretch
begins, so a script that reads the intervals alone takes no unsafe step."""

from __future__ import annotations

import math
from functools import cache

import mpmath as mp
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from reference_methods import mp_transfer

import stepsafe

FOUR_PI = 4 * math.pi
#: (method, stages, model, zmax): resonances M = +-I (Gauss, Lobatto, bcss3), a reversed
#: band after z* (sofroniou-spaletta10), poles and orientation switches (the barrier)
CASES = [("lobatto3ab", 12, "oscillator", FOUR_PI), ("lobatto3ab", 6, "oscillator", FOUR_PI),
         ("lobatto3ab", 3, "inverted", 10.0), ("gauss", 2, "oscillator", 10.0),
         ("gauss", 5, "oscillator", FOUR_PI), ("gauss", 3, "saddle", 10.0),
         ("bcss3", None, "oscillator", 10.0), ("sofroniou-spaletta10", None, "oscillator", 10.0),
         ("pefrl", None, "oscillator", 10.0), ("verlet", None, "inverted", 10.0),
         ("yoshida4", None, "saddle", 10.0), ("blanes-casas-ros764", None, "inverted", 40.0)]


@cache
def _report(name: str, stages: int | None, model: str, zmax: float, criterion: str):
    report = stepsafe.region(stepsafe.method(name, stages=stages), model, zmax=zmax,
                             criterion=criterion)
    return report.regions[model], report.to_dict()["models"][model]


@cache
def _reference(name: str, stages: int | None):
    return mp_transfer(name, stages, dps=50)


def _kept(name: str, stages: int | None, model: str, z: float) -> tuple[bool, bool]:
    """(the flow's type, its orientation) at z, from the transfer matrix at 50 digits, or
    more until each deciding quantity is resolved (2 - tr M = z^2 for Verlet: 1e-320 at
    z = 1e-160)."""
    digits = 50
    while True:
        with mp.workdps(digits):
            M = _reference(name, stages)(mp.mpf(z), model)
            tr = M[0, 0] + M[1, 1]
            if model == "oscillator":
                deciding = [2 - tr, 2 + tr, M[0, 1]]
                kept = (abs(tr) < 2, M[0, 1] > 0)
            elif model == "saddle":
                deciding = [M[0, 0] - 1, 1 - M[1, 1], M[1, 1], M[0, 0] - M[1, 1]]
                kept = (M[0, 0] > 1 > M[1, 1] > 0 or M[1, 1] > 1 > M[0, 0] > 0,
                        M[0, 0] > M[1, 1])
            else:
                mu = tr / 2 + mp.sqrt(max(tr * tr / 4 - 1, 0))
                orientation = M[0, 1] * (mu - M[0, 0]) + M[1, 0] * (mu - M[1, 1])
                deciding = [tr - 2, orientation]
                kept = (tr > 2, orientation > 0)
            size = 1 + max(abs(M[i, j]) for i in range(2) for j in range(2))
            if all(abs(g) > mp.mpf(10) ** (10 - digits) * size for g in deciding) \
                    or digits > 2000:
                return kept
        digits *= 2


#: where in (lo, hi) z is drawn: anywhere, or a relative 1e-16 ... 1e-1 from either end
FRACTION = st.one_of(st.floats(0.0, 1.0), st.integers(1, 16).map(lambda k: 10.0 ** -k),
                     st.integers(1, 16).map(lambda k: 1.0 - 10.0 ** -k))


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=st.sampled_from(CASES), criterion=st.sampled_from(["structure", "stability"]),
       data=st.data(), t=FRACTION)
def test_every_z_inside_a_listed_interval_is_preserved_at_50_digits(case, criterion, data, t):
    name, stages, model, zmax = case
    region, record = _report(name, stages, model, zmax, criterion)
    listed = [[iv.lo, iv.hi] for iv in region.intervals]
    assert record["intervals"] == listed  # the JSON lists what the API does
    claims = [(lo, hi, True) for lo, hi in listed]
    claims += [(i["lo"], i["hi"], False) for i in record["islands"]
               if i["orientation"] == "reversed"]
    assume(claims)
    lo, hi, same = data.draw(st.sampled_from(claims))
    hi = region.zmax if hi is None else hi
    z = lo + (hi - lo) * t
    assume(lo < z < hi)
    kept_type, orientation = _kept(name, stages, model, z)
    assert kept_type, (case, criterion, (lo, hi), z)
    if criterion == "structure":
        assert orientation == same, (case, (lo, hi), z)


def test_the_interval_before_lobatto12s_third_resonance_stops_at_its_band():
    """Lobatto IIIA-IIIB s = 12 (zmax 4 pi): tr M < -2 on [9.42477738, 9.42477848] at 50
    digits, within the band of the M = -I resonance at 9.424777929; the preserved interval
    that ends there stops before the band."""
    region, record = _report("lobatto3ab", 12, "oscillator", FOUR_PI, "structure")
    with mp.workdps(50):
        for z in ("9.4247774", "9.4247778", "9.4247784"):
            M = _reference("lobatto3ab", 12)(mp.mpf(z), "oscillator")
            assert M[0, 0] + M[1, 1] < -2
    (res,) = [p for p in region.resonances if 9.42 < p.z < 9.43]
    second = region.intervals[1]
    assert second.hi == res.z - res.uncertainty < 9.4247773793341397
    assert record["intervals"][1][1] == second.hi


def test_the_stable_run_ends_where_its_listed_interval_ends():
    """hmc's and design's run of stable steps stops its end's float64 uncertainty short of
    it, exactly where the interval listed under the stability criterion ends."""
    from support import method

    from stepsafe.core.regions import find_region, stable_run, under_criterion

    for name in ("bcss3", "verlet", "pefrl", "sofroniou-spaletta10"):
        region = find_region(method(name), "oscillator")
        run = stable_run(region)
        listed = under_criterion(region, "stability").intervals
        ends = [iv.hi for iv in listed if iv.hi_point is not None and iv.hi_point.z == run.end]
        assert run.uncertainty > 0 and ends == [run.first_unsafe], name
