"""Impulse / r-RESPA: the outer step as a splitting, checked against closed forms and an
independent 50-digit product of the slow kicks and fast substeps in (q, p)."""

from __future__ import annotations

import json
import math

import mpmath as mp
import numpy as np
import pytest
from support import respa_mp, respa_stable_mp

from stepsafe import impulse
from stepsafe.exceptions import StepsafeError


def test_one_substep_is_verlet_on_the_total_force():
    report = impulse("verlet", "verlet", substeps=1, fast_beta=3.0, slow_beta=4.0)
    assert report.h_max == pytest.approx(2.0 / 5.0, rel=1e-12)


def test_no_slow_force_is_the_inner_method_with_its_own_step():
    """Five Verlet substeps of the fast force alone: stable up to Omega H / 5 = 2, passing
    M = -I or +I wherever 5 theta = j pi (theta = 2 arcsin(Omega H / 10)): exact touches,
    excluded as resonances since float64 cannot tell them from narrow gaps."""
    report = impulse("verlet", "verlet", substeps=5, fast_beta=2.0, slow_beta=0.0)
    assert report.safe_h[-1][1] == pytest.approx(5.0, rel=1e-12)
    touches = [5.0 * math.sin(j * math.pi / 10) for j in range(1, 5)]
    assert [b["kind"] for b in report.bands] == ["resonance"] * 4 + ["unstable"]
    for band, h in zip(report.bands, touches):
        assert band["lo"] < h < band["hi"] and band["hi"] - band["lo"] < 1e-5


@pytest.mark.parametrize("fast, slow, k", [(10.0, 1.0, 4), (0.697, 0.0565, 8),
                                           (1e6, 3e4, 3), (1e-5, 1e-7, 16),
                                           (1.0, 1e-9, 2)])
def test_bands_and_safe_steps_at_50_digits(fast, slow, k):
    report = impulse("verlet", "verlet", substeps=k, fast_beta=fast, slow_beta=slow)
    rng = np.random.default_rng(k)
    for lo, hi in report.safe_h:
        top = report.horizon if hi is None else hi
        for H in lo + (top - lo) * rng.uniform(0.0, 1.0, 12):
            if H > 0:
                assert respa_stable_mp(fast, slow, k, H), (lo, hi, H)
    for band in report.bands:
        if band["hi"] is None or band["kind"] == "resonance":
            continue
        mid = 0.5 * (band["lo"] + band["hi"])
        assert not respa_stable_mp(fast, slow, k, mid), band
    # every band sits just below a half-period resonance of the inner method (k theta_in =
    # j pi, theta_in = 2 arcsin(Omega H / 2k))
    for band in report.bands[:-1]:
        if band["kind"] == "resonance":
            continue
        theta = 2 * math.asin(min(1.0, fast * band["hi"] / (2 * k)))
        j = k * theta / math.pi
        assert abs(j - round(j)) < 0.05, (band, j)


def test_structure_is_stricter_than_stability():
    both = [impulse("verlet", "verlet", substeps=4, fast_beta=10.0, slow_beta=1.0,
                    criterion=c)
            for c in ("structure", "stability")]
    assert both[0].h_max == both[1].h_max
    assert len(both[1].safe_h) > len(both[0].safe_h)


def test_a_check_of_a_step():
    ok = impulse(fast_beta=0.696951079904, slow_beta=0.0565095470193, substeps=4, step=2.0)
    assert ok.safe is True
    bad = impulse(fast_beta=10.0, slow_beta=1.0, substeps=4, step=0.304)
    assert bad.safe is False and bad.reason


def test_other_outer_and_inner_splittings():
    report = impulse("pefrl", "mclachlan2-min", substeps=3, fast_beta=5.0, slow_beta=1.0)
    assert 0 < report.h_max < 3 * 2.55 / 5.0


@pytest.mark.parametrize("kwargs, match", [
    ({"substeps": 0}, "substeps"),
    ({"substeps": 2.5}, "substeps"),
    ({"fast_beta": 0.0, "slow_beta": 0.0}, "both 0"),
    ({"fast_beta": float("nan")}, "fast"),
    ({"slow_beta": -1.0}, "slow"),
    ({"inner": "gauss:2"}, "splitting"),
    ({"outer": "midpoint"}, "splitting"),
    ({"step": -1.0}, "step"),
    ({"criterion": "both"}, "criterion"),
])
def test_bad_arguments(kwargs, match):
    args = {"fast_beta": 10.0, "slow_beta": 1.0, "substeps": 4, **kwargs}
    with pytest.raises(StepsafeError, match=match):
        impulse(**args)


def test_cli(run):
    code, out, err = run("respa", "--fast-wavenumber", "3700", "--slow-wavenumber", "300",
                         "--time-unit", "fs", "--substeps", "4", "--step", "2", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["safe"] is True and data["time_unit"] == "fs"
    assert data["criterion"] == "stability"
    code, out, _ = run("respa", "--fast-beta", "10", "--slow-beta", "1", "--step", "0.304")
    assert code == 1 and "UNSAFE" in out
    code, _, err = run("respa", "--slow-beta", "1")
    assert code == 2 and "fast" in err
    code, _, err = run("respa", "--fast-beta", "1", "--slow-beta", "1", "--inner", "rk4")
    assert code == 2 and "splitting" in err


def test_the_third_of_a_period_resonance_at_50_digits():
    """Ma, Izaguirre & Skeel (2003): impulse methods are limited near a third of the fast
    period by a nonlinear resonance; the outer step's 3:1 (tr M = 2 cos(2 pi / 3) = -1)."""
    fast, slow, k = 0.696951079904, 0.0565095470193, 8
    report = impulse(fast_beta=fast, slow_beta=slow, substeps=k, resonance_order=3)
    with mp.workdps(50):
        ref = mp.findroot(lambda H: (lambda M: M[0, 0] + M[1, 1] + 1)(
            respa_mp(fast, slow, k, H)), (2.9, 3.1), solver="anderson")
    assert report.h_max == pytest.approx(float(ref), rel=1e-10)
    assert abs(float(ref) - 2 * math.pi / fast / 3) < 0.1  # about T/3
    assert report.bands[0]["kind"] == "nonlinear"
    three = next(r for r in report.nonlinear if r["resonance"] == "3:1")
    assert three["h"] == pytest.approx(float(ref), rel=1e-10)
    assert impulse(fast_beta=fast, slow_beta=slow, substeps=k, step=3.1,
                   resonance_order=3).safe is False


def test_the_chart_is_the_trace_of_the_equivalent_splitting():
    from stepsafe import method
    from stepsafe.core.impulse import impulse_method, impulse_splitting, stability_chart
    from stepsafe.core.transfer import transfer_matrix

    outer, inner = method("verlet").tableau, method("pefrl").tableau
    x, y = np.array([0.7, 2.9, 3.3, 6.0]), np.array([0.2, 1.1])
    chart = stability_chart(impulse_method(outer, inner, 3), x, y)
    for i, yy in enumerate(y):
        for j, xx in enumerate(x):
            split = impulse_splitting(impulse_method(outer, inner, 3), xx, yy)
            M = transfer_matrix(split, [math.hypot(xx, yy)], "oscillator")[0]
            assert chart[i, j] == pytest.approx(abs(M[0, 0] + M[1, 1]) / 2, rel=1e-12)
    with mp.workdps(30):  # and the mp product in (q, p) for verlet/verlet
        for xx, yy in ((3.05, 0.3), (2.0, 0.5)):
            M = respa_mp(xx, yy, 4, 1.0)
            ref = abs(M[0, 0] + M[1, 1]) / 2
            assert stability_chart(impulse_method(outer, outer, 4), np.array([xx]),
                                   np.array([yy]))[0, 0] \
                == pytest.approx(float(ref), rel=1e-12)


def test_cli_chart(run, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "chart.png"
    code, _, err = run("respa", "--fast-beta", "10", "--slow-beta", "1", "--plot", str(out))
    assert code == 0, err
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_extreme_ratios_and_scales():
    """Ratios beyond 1e154 do not overflow the force fractions (the slow force alone binds:
    outer Verlet, omega H < 2); frequencies leaving float64 are refused."""
    report = impulse(fast_beta=1e-160, slow_beta=1.0, substeps=4)
    assert report.h_max == pytest.approx(2.0, rel=1e-10)
    report = impulse(fast_beta=1e-200, slow_beta=1e200, substeps=4)
    assert report.h_max == pytest.approx(2e-200, rel=1e-10)
    for fast, slow in ((1e-310, 0.0), (1e-320, 1e-320)):
        with pytest.raises(StepsafeError, match="float64"):
            impulse(fast_beta=fast, slow_beta=slow)


def test_wide_structure_failures_are_not_called_resonances():
    report = impulse(fast_beta=10.0, slow_beta=1e-6, substeps=4, criterion="structure")
    wide = [b for b in report.bands if b["hi"] is not None and b["hi"] - b["lo"] > 1e-3]
    assert wide and all(b["kind"] == "unstable" for b in wide)


def test_the_work_is_bounded():
    with pytest.raises(StepsafeError, match="operations"):
        impulse("pefrl", "yoshida8", substeps=200, fast_beta=10.0, slow_beta=1.0)
