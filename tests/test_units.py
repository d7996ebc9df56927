"""Physical units: conversions against exact values at 50 digits, and units on every h."""

from __future__ import annotations

import json
import math

import mpmath
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.exceptions import StepsafeError
from stepsafe.units import FREQUENCY_UNITS, TIME_UNITS, angular_frequency, quantity

C = mpmath.mpf(299792458)  # m/s, exact since 1983
SECONDS = {"s": 0, "ms": -3, "us": -6, "ns": -9, "ps": -12, "fs": -15, "as": -18}
HERTZ = {"Hz": 0, "kHz": 3, "MHz": 6, "GHz": 9, "THz": 12, "PHz": 15,
         **{f"{t}-1": -e for t, e in SECONDS.items()}}


def exact(form: str, value: float, unit: str | None, time: str | None):
    """beta at 50 digits, from the definitions (not from stepsafe's factors)."""
    with mpmath.workdps(50):
        v, two_pi = mpmath.mpf(value), 2 * mpmath.pi
        t = None if time is None else mpmath.mpf(10) ** SECONDS[time]
        if form == "wavenumber":  # k in 1/cm: c in cm/s times k, cycles per second
            return two_pi * C * 100 * v * t
        if form == "frequency":
            return two_pi * v * (1 if unit is None else mpmath.mpf(10) ** HERTZ[unit] * t)
        if form == "period":
            scale = 1 if unit is None else mpmath.mpf(10) ** SECONDS[unit] / t
            return two_pi / (v * scale)
        raise AssertionError(form)


def test_tables_match_the_reference_tables():
    assert set(TIME_UNITS) == set(SECONDS) and set(FREQUENCY_UNITS) == set(HERTZ)


def test_water_stretch():
    """3700 cm^-1 is 0.69695 rad/fs (2 pi c k); Verlet's linear limit 2/beta = 2.8696 fs."""
    beta = quantity(3700, "wavenumber", "fs")
    assert beta == pytest.approx(float(exact("wavenumber", 3700, None, "fs")), rel=1e-15)
    assert f"{beta:.5f}" == "0.69695"
    advice = stepsafe.advise("verlet", wavenumber=[3700], time_unit="fs")
    with mpmath.workdps(50):
        limit = 2 / exact("wavenumber", 3700, None, "fs")
    assert advice.h_max == pytest.approx(float(limit), rel=1e-13)
    assert advice.h_max < limit
    assert advice.to_dict()["time_unit"] == "fs"


@settings(max_examples=300, deadline=None)
@given(form=st.sampled_from(["wavenumber", "frequency", "period"]),
       mantissa=st.floats(1.0, 10.0), exponent=st.integers(-12, 12),
       unit=st.one_of(st.none(), st.sampled_from(sorted(HERTZ)), st.sampled_from(sorted(SECONDS))),
       time=st.sampled_from(sorted(SECONDS)))
def test_conversions_within_a_few_ulps_of_exact(form, mantissa, exponent, unit, time):
    value = mantissa * 10.0 ** exponent
    if form == "wavenumber":
        unit = None if unit is None else "cm-1"
    elif form == "frequency" and unit in SECONDS:
        unit = None
    elif form == "period" and unit in HERTZ:
        unit = None
    try:
        got = angular_frequency(form, value, unit, time)
    except StepsafeError as exc:
        assert "overflow" in str(exc)
        return
    assert float(abs(got / exact(form, value, unit, time) - 1)) < 1e-15


@pytest.mark.parametrize("text, form, time, expected", [
    ("3700 cm-1", "wavenumber", "fs", ("wavenumber", 3700, None)),
    ("3700cm^-1", "wavenumber", "ps", ("wavenumber", 3700, None)),
    ("100 THz", "frequency", "fs", ("frequency", 100, "THz")),
    ("3 1/ps", "frequency", "fs", ("frequency", 3, "ps-1")),
    ("3 ps^-1", "frequency", "ns", ("frequency", 3, "ps-1")),
    ("9 fs", "period", "ps", ("period", 9, "fs")),
    ("0.25", "period", None, ("period", 0.25, None)),
])
def test_texts_with_units(text, form, time, expected):
    f, value, unit = expected
    assert quantity(text, form, time) == pytest.approx(float(exact(f, value, unit, time)),
                                                       rel=2e-16)


@pytest.mark.parametrize("text, form, time, message", [
    ("3700", "wavenumber", None, "needs a time unit"),
    ("100 THz", "frequency", None, "needs a time unit"),
    ("100 furlongs", "frequency", "fs", "unknown frequency unit"),
    ("9 lightyears", "period", "fs", "unknown time unit"),
    ("3700 THz", "wavenumber", "fs", "in cm-1"),
    ("-3", "frequency", "fs", ">= 0"),
    ("0", "period", "fs", "> 0"),
    ("nan THz", "frequency", "fs", "not a number"),
    ("1e999 THz", "frequency", "fs", "finite"),
    ("1e308 Hz", "frequency", "s", "overflows"),
    ("1e-320", "period", "fs", "overflows"),
    ("__import__('os')", "frequency", "fs", "not a number"),
    ("٣ THz", "frequency", "fs", "not a number"),
])
def test_bad_quantities_are_refused(text, form, time, message):
    with pytest.raises(StepsafeError, match=message):
        quantity(text, form, time)


def test_command_line_units(run):
    code, out, err = run("check", "--method", "verlet", "--wavenumber", "3700", "--time-unit",
                         "fs", "--step", "3")
    assert code == 1, err
    assert "h = 3 fs" in out and "largest safe h for it: 2.86964186966 fs" in out
    code, out, _ = run("advise", "--method", "verlet", "--wavenumber", "3700",
                       "--time-unit", "fs")
    assert "Safe: 0 < h < 2.86964186966 fs" in out and "(rad/fs)" in out
    code, out, _ = run("advise", "--method", "verlet", "--beta", "1")
    assert "time unit of 1/beta" in out
    # the same vibration in four forms: one limit
    forms = [["--beta", str(quantity(100, "frequency", "ps") / 1000)],
             ["--frequency", "100THz"], ["--period", "10fs"], ["--frequency", "0.1"]]
    limits = set()
    for args in forms:
        code, out, err = run("advise", "--method", "verlet", *args, "--time-unit", "fs",
                             "--json")
        assert code == 0, err
        limits.add(round(json.loads(out)["h_max"], 12))
    assert len(limits) == 1


@pytest.mark.parametrize("args, message", [
    (["--beta", "3700cm-1"], "use --wavenumber"),
    (["--beta", "100THz"], "use --frequency"),
    (["--beta", "9fs"], "use --period"),
    (["--wavenumber", "3700"], "needs a time unit"),
    (["--frequency", "100 furlongs", "--time-unit", "fs"], "--frequency 100 furlongs"),
    (["--wavenumber", "3700", "--time-unit", "minutes"], "--time-unit"),
])
def test_command_line_unit_errors(run, args, message):
    code, out, err = run("advise", "--method", "verlet", *args)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert message in err


def test_scene_with_units(run, tmp_path):
    scene = tmp_path / "water.yaml"
    scene.write_text("method: verlet\ntime_unit: fs\nh: 1.0\nmodes:\n"
                     "  - {wavenumber: 3700, label: O-H stretch}\n"
                     "  - {wavenumber: 1600, label: H-O-H bend}\n"
                     "  - {frequency: 30 THz}\n  - {period: 0.5 ps}\n")
    code, out, err = run("check", str(scene), "--json")
    assert code == 0, err
    entry = json.loads(out)["checks"][0]
    assert entry["time_unit"] == "fs" and entry["h"] == 1.0
    with mpmath.workdps(50):
        top = exact("wavenumber", 3700, None, "fs")
    assert entry["h_max"] == pytest.approx(float(2 / top), rel=1e-13)
    code, out, err = run("check", str(scene), "--time-unit", "ps")
    assert code == 2 and "time_unit" in err and "--time-unit ps" in err
    bad = tmp_path / "no-unit.yaml"
    bad.write_text("method: verlet\nmodes:\n  - {wavenumber: 3700}\n")
    code, out, err = run("advise", str(bad))
    assert code == 2 and "modes[0].wavenumber" in err and "time unit" in err
    code, out, err = run("advise", str(bad), "--time-unit", "fs", "--json")
    assert code == 0 and json.loads(out)["time_unit"] == "fs"
    two = tmp_path / "two-forms.yaml"
    two.write_text("method: verlet\nmodes:\n  - {beta: 1, wavenumber: 3700}\n")
    code, out, err = run("advise", str(two), "--time-unit", "fs")
    assert code == 2 and "modes[0]" in err and "one of beta" in err


@pytest.mark.parametrize("scene, limits", [
    ("protein-flexible.yaml", (2.949, 2.085, 2.554)),
    ("protein-constrained.yaml", (6.434, 4.550, 5.572)),
])
def test_md_examples_as_the_md_guide_states(run, scene, limits):
    """The MD guide's table (rounded down): linear limit, below the 4:1 and the 3:1
    resonance, fs (each the closed form 2 sin(pi m / n) / beta for Verlet, beta = 2 pi c k)."""
    from pathlib import Path

    path = str(Path(__file__).resolve().parent.parent / "examples" / scene)
    got = []
    for order in (None, 4, 3):
        extra = [] if order is None else ["--resonance-order", str(order)]
        code, out, err = run("advise", path, *extra, "--json")
        assert code == 0, err
        got.append(json.loads(out)["h_max"])
    assert [math.floor(h * 1000) / 1000 for h in got] == list(limits)
    beta = quantity(json.loads(run("advise", path, "--json")[1])["limiting"]["beta"], "beta",
                    None)
    for h, z in zip(got, (2.0, math.sqrt(2), math.sqrt(3))):
        assert h == pytest.approx(z / beta, rel=1e-12)
    assert run("check", path, "--resonance-order", "4")[0] == 0


@pytest.mark.parametrize("args, message", [
    (["advise", "--method", "verlet", "--sigma", "abc"], "--sigma abc"),
    (["advise", "--method", "verlet", "--sigma", "-1"], "--sigma -1"),
    (["advise", "--method", "verlet", "--sigma", "0"], "> 0"),
    (["region", "verlet", "--resonance-orders", "x"], "--resonance-orders"),
    (["region", "verlet", "--resonance-orders", "2"], "3 to 50"),
    (["compare", "--beta", "1", "--solver", "bogus"], "--solver"),
])
def test_new_options_refuse_bad_values(run, args, message):
    code, out, err = run(*args)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and message in err


def test_scene_time_unit_must_be_known(run, tmp_path):
    path = tmp_path / "tu.yaml"
    path.write_text("method: verlet\ntime_unit: minutes\nmodes: [{beta: 1}]\n")
    code, out, err = run("advise", str(path))
    assert code == 2 and "tu.yaml::$.time_unit" in err


@pytest.mark.parametrize("form, unit_text", [("wavenumber", "cm-1"), ("frequency", None),
                                             ("period", None), ("sigma", None)])
def test_a_modes_csv_column_in_any_form_gives_the_same_betas_as_the_command_line(
        run, tmp_path, form, unit_text):
    """A CSV spectrum in cm-1 (or frequencies, periods, standard deviations) is read as the
    same modes given one by one: identical betas, hence identical advice."""
    from stepsafe.systems.scene import load_modes
    from stepsafe.units import quantity

    values = [3700.0, 1600.5, 0.25, 1e-3] if form != "period" else [9.0, 20.0, 1e3, 0.5]
    path = tmp_path / "spectrum.csv"
    path.write_text(f"{form},label\n" + "".join(f"{v!r},m{i}\n" for i, v in enumerate(values)))
    loaded = load_modes(path, "fs")
    want = sorted(quantity(v, form, "fs") for v in values)
    assert sorted(loaded.betas["oscillator"].tolist()) == want
    code, out, _ = run("advise", "--method", "verlet", "--modes", str(path), "--time-unit",
                       "fs", "--json")
    assert code == 0
    assert json.loads(out)["h_max"] == pytest.approx(2 / max(want), rel=1e-9)


def test_a_wavenumber_csv_needs_a_time_unit_and_names_a_bad_line(run, tmp_path):
    path = tmp_path / "spectrum.csv"
    path.write_text("wavenumber\n3700\n")
    code, _, err = run("advise", "--method", "verlet", "--modes", str(path))
    assert code == 2 and "needs a time unit" in err
    path.write_text("wavenumber\n3700\n-3\n")
    code, _, err = run("advise", "--method", "verlet", "--modes", str(path), "--time-unit", "fs")
    assert code == 2 and "spectrum.csv::$.line 3.wavenumber" in err


def _t0_squared_mp(energy: str, length: str, mass: str) -> mpmath.mpf:
    """t0^2 = mass length^2 / energy in s^2, from the SI definitions and CODATA 2022
    values written out here (independent of stepsafe.units)."""
    with mpmath.workdps(50):
        avogadro = mpmath.mpf("6.02214076e23")
        joules = {"J": 1, "kJ/mol": 1000 / avogadro, "kcal/mol": mpmath.mpf(4184) / avogadro,
                  "eV": mpmath.mpf("1.602176634e-19"), "hartree": mpmath.mpf("4.3597447222060e-18")}
        metres = {"m": 1, "nm": mpmath.mpf("1e-9"), "angstrom": mpmath.mpf("1e-10"),
                  "pm": mpmath.mpf("1e-12"), "bohr": mpmath.mpf("5.29177210544e-11")}
        kilograms = {"kg": 1, "amu": mpmath.mpf("1.66053906892e-27"),
                     "g/mol": mpmath.mpf("1e-3") / avogadro, "me": mpmath.mpf("9.1093837139e-31")}
        return kilograms[mass] * metres[length] ** 2 / joules[energy]


@pytest.mark.parametrize("energy, length, mass, unit", [
    ("kcal/mol", "angstrom", "amu", "fs"), ("kJ/mol", "nm", "g/mol", "ps"),
    ("eV", "angstrom", "amu", "fs"), ("hartree", "bohr", "me", "as"), ("J", "m", "kg", "s")])
def test_a_stiffness_in_md_units_gives_h_in_the_scene_time_unit(run_json, tmp_path, energy,
                                                                length, mass, unit):
    """K = 900 and M = 0.94 in the given units: verlet's h_max = 2 / omega with
    omega^2 = (K / M) / t0^2 converted to the scene's time unit, against 50 digits
    (kcal/mol, angstrom, amu: t0 = 48.888212934 fs, h_max = 3.1619022 fs)."""
    K, M = 900.0, 0.9411764705882353
    path = tmp_path / "scene.yaml"
    path.write_text(f"method: verlet\ntime_unit: {unit}\nsystem:\n  stiffness: [[{K!r}]]\n"
                    f"  mass: [[{M!r}]]\n  units: {{energy: {energy}, length: {length}, "
                    f"mass: {mass}}}\n")
    seconds = {"fs": mpmath.mpf("1e-15"), "ps": mpmath.mpf("1e-12"),
               "as": mpmath.mpf("1e-18"), "s": 1}
    with mpmath.workdps(50):
        omega = mpmath.sqrt(mpmath.mpf(K) / mpmath.mpf(M)
                            / _t0_squared_mp(energy, length, mass))
        want = 2 / (omega * seconds[unit])
    got = run_json("advise", str(path))["h_max"]
    assert got == pytest.approx(float(want), rel=1e-12) and got <= want
    if (energy, length, mass) == ("kcal/mol", "angstrom", "amu"):
        assert float(mpmath.sqrt(_t0_squared_mp(energy, length, mass))) == \
            pytest.approx(48.888212934e-15, rel=1e-10)


@pytest.mark.parametrize("units, key", [
    ("{energy: kcal/mol, length: angstrom, mass: amu}", "units"),  # no time_unit
    ("{energy: kcal, length: angstrom, mass: amu}", "units.energy"),
    ("{energy: eV, length: A, mass: amu}", "units.length"),
    ("{energy: eV, length: nm}", "units")])
def test_bad_units_name_the_key(run, tmp_path, units, key):
    path = tmp_path / "scene.yaml"
    unit = "" if key == "units" and "mass" in units else "time_unit: fs\n"
    path.write_text(f"method: verlet\nh: 1\n{unit}system:\n  stiffness: [[900.0]]\n"
                    f"  units: {units}\n")
    code, _, err = run("check", str(path))
    assert code == 2 and f"$.system.{key}:" in err and len(err.strip().splitlines()) == 1, err


def _decimal(digits: int, point: int, exponent: int) -> str:
    """``digits`` with the decimal point ``point`` places from the right, times 10^exponent."""
    text = str(digits).zfill(point + 1)
    return f"{text[:len(text) - point]}.{text[len(text) - point:] or '0'}e{exponent}"


#: Decimal texts ``ddd.ddde±n`` with up to 16 significant digits.
DECIMALS = st.builds(_decimal, st.integers(1, 10**16 - 1), st.integers(0, 16),
                     st.integers(-30, 30))


@settings(max_examples=300, deadline=None)
@given(text=DECIMALS, unit=st.sampled_from(sorted(SECONDS)),
       time=st.sampled_from(sorted(SECONDS)), space=st.sampled_from(["", " "]))
def test_a_duration_is_converted_exactly(text, unit, time, space):
    """A time with its unit ('0.5fs', '0.5 fs', '2e-15 s') in another time unit: the
    correctly rounded value of the decimal times the power of ten between the units."""
    from fractions import Fraction

    from stepsafe.units import duration

    expected = float(Fraction(text) * Fraction(10) ** (SECONDS[unit] - SECONDS[time]))
    assert duration(f"{text}{space}{unit}", "h", time) == expected


@pytest.mark.parametrize("args, h, unit, beta", [
    (["--wavenumber", "3700", "--step", "0.5fs"], 0.5, "fs", ("wavenumber", 3700, "fs")),
    (["--wavenumber", "3700", "--step", "0.5 fs"], 0.5, "fs", ("wavenumber", 3700, "fs")),
    (["--wavenumber", "3700", "--time-unit", "fs", "--step", "5e-16s"], 0.5, "fs",
     ("wavenumber", 3700, "fs")),
    (["--wavenumber", "3700", "--step", "5e-16s"], 5e-16, "s", ("wavenumber", 3700, "s")),
    (["--wavenumber", "3700", "--time-unit", "ps", "--step", "500fs"], 0.5, "ps",
     ("wavenumber", 3700, "ps")),
    (["--period", "9fs", "--step", "2"], 2.0, "fs", ("period", 9, "fs")),
    (["--period", "9fs", "--step", "2.87fs"], 2.87, "fs", ("period", 9, "fs")),
    (["--frequency", "100THz", "--step", "0.0009ps"], 0.0009, "ps",
     ("frequency100", 100, "ps")),
])
def test_a_step_or_period_with_its_unit(run, args, h, unit, beta):
    """The step and the periods may carry their unit; it names the time unit when none is
    given. h, beta (50 digits from the SI definitions) and the verdict (Verlet: safe for
    beta*h < 2) of `check --json` agree with the values converted by hand, and the API
    gives the same dict."""
    code, out, err = run("check", "--method", "verlet", *args, "--json")
    (entry,) = json.loads(out)["checks"]
    form, value, time = beta
    with mpmath.workdps(50):
        expected = exact("frequency", value, "THz", time) if form == "frequency100" else \
            exact(form, value, "fs" if form == "period" else None, time)
        z = expected * mpmath.mpf(entry["h"])
        assert code == (0 if z < 2 else 1), err
        limit = 2 / expected  # Verlet's h_max, the open end of the safe steps
        assert entry["h_max"] < limit
        assert entry["h_max"] == pytest.approx(float(limit), rel=1e-13)
    assert (entry["h"], entry["time_unit"]) == (h, unit)


def test_a_scene_step_with_its_unit(run, tmp_path):
    """h: with a unit, quoted or not, in the scene's time_unit or naming it; a conflict of
    two units with no time unit to settle it, and a unit of another kind, are refused
    naming the key."""
    for h, unit, expected in (('"0.5 fs"', None, 0.5), ("0.5 fs", None, 0.5),
                              ("0.0005 ps", "fs", 0.5), ("500 as", "fs", 0.5),
                              ('"5e-16 s"', "fs", 0.5)):
        scene = tmp_path / "s.yaml"
        scene.write_text(f"method: verlet\n{'' if unit is None else f'time_unit: {unit}'}\n"
                         f"h: {h}\nmodes: [{{wavenumber: 3700}}]\n")
        code, out, err = run("check", str(scene), "--json")
        (entry,) = json.loads(out)["checks"]
        assert code == 0 and (entry["h"], entry["time_unit"]) == (expected, "fs"), err
        assert stepsafe.check(scene=str(scene)).to_dict() == json.loads(out)
    for text, key in (("h: 0.5 fs\nmodes: [{period: 9 ps}]", "time_unit"),
                      ("h: 0.5 THz\nmodes: [{beta: 1}]", "h")):
        scene = tmp_path / "bad.yaml"
        scene.write_text(f"method: verlet\n{text}\n")
        code, out, err = run("check", str(scene))
        assert code == 2 and len(err.strip().splitlines()) == 1 and f"::$.{key}" in err, err


@pytest.mark.parametrize("args, message", [
    (["--step", "3THz"], "not a time"),
    (["--step", "3 cm-1"], "not a time"),
    (["--step", "0.5fs", "--period", "9ps"], "fs and ps"),
    (["--step", "1_0fs"], "not a valid"),
])
def test_step_unit_errors(run, args, message):
    code, out, err = run("check", "--method", "verlet", "--beta", "1", *args)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert message in err


def test_period_with_its_unit_names_the_time_unit(run):
    """--period 9fs alone: beta = 2 pi / 9 rad/fs, h in fs."""
    code, out, err = run("advise", "--method", "verlet", "--period", "9fs", "--json")
    data = json.loads(out)
    assert code == 0 and data["time_unit"] == "fs", err
    with mpmath.workdps(50):
        limit = 2 / (2 * mpmath.pi / 9)
    assert data["h_max"] == pytest.approx(float(limit), rel=1e-13) and data["h_max"] < limit
    assert stepsafe.advise("verlet", period=["9 fs"]).h_max == data["h_max"]


def test_times_with_units_in_hmc_design_respa_and_measure(run):
    """The other commands that take a time take its unit too, with the same answer as the
    number in the time unit."""
    for plain, with_unit in (
            (["hmc", "--sigma", "1", "--methods", "verlet", "--length", "5", "--step", "0.5",
              "--time-unit", "fs"],
             ["hmc", "--sigma", "1", "--methods", "verlet", "--length", "5fs", "--step",
              "500as", "--time-unit", "fs"]),
            (["design", "--sigma", "1", "--step", "0.5", "--time-unit", "fs"],
             ["design", "--sigma", "1", "--step", "0.0005ps", "--time-unit", "fs"]),
            (["respa", "--fast-beta", "10", "--slow-beta", "1", "--step", "0.2",
              "--time-unit", "fs"],
             ["respa", "--fast-beta", "10", "--slow-beta", "1", "--step", "0.2fs"]),
            (["measure", "examples/pendulum.yaml", "--h", "0.5", "--time", "20",
              "--time-unit", "fs"],
             ["measure", "examples/pendulum.yaml", "--h", "0.0005ps", "--time", "0.02ps",
              "--time-unit", "fs"])):
        a, b = run(*plain, "--json"), run(*with_unit, "--json")
        assert a[0] == b[0] == 0, (a[2], b[2])
        A, B = json.loads(a[1]), json.loads(b[1])
        for row in A.get("rows", []) + B.get("rows", []):
            if isinstance(row, dict):  # (a run's wall time is its own)
                assert row.pop("seconds_per_time", 1.0) > 0
        assert A == B
