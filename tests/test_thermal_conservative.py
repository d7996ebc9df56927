"""Verdicts at temperature are never less conservative than the inputs allow: a run longer
than the thermal trajectories follow is refused, not judged by its first steps (against the
test's own integrations of the scene: velocity Verlet written here, kick h/2, drift h, kick
h/2, from exact Boltzmann draws of a 1-D well by inverse transform on a fine grid); the 0 K
exclusions asked for (``resonance_order``) hold at every temperature; a run's length in a
time unit is converted only into a time unit the system states; bad keywords are refused
naming them, as at 0 K."""

from __future__ import annotations

import math
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.api.temperature import request
from stepsafe.exceptions import StepsafeError

ROOT = Path(__file__).resolve().parent.parent
MORSE = str(ROOT / "examples" / "morse.yaml")


def _morse_force(q):
    e = np.exp(-q)
    return -(1.0 - e) * e


def _morse_boltzmann(kT: float, count: int, rng: np.random.Generator) -> np.ndarray:
    """Exact draws of exp(-(1 - e^-q)^2 / (2 kT)) near its minimum (40 thermal amplitudes
    each side; the mass beyond is below e^-800)."""
    a = np.sqrt(kT)
    s = np.linspace(-40 * a, 40 * a, 200001)
    w = np.exp(-0.5 * (1.0 - np.exp(-s)) ** 2 / kT)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    return np.interp(rng.random(count), cdf / cdf[-1], s)


def _verlet_dissociations(q, p, h, steps, enough, every=100):
    """Velocity Verlet on H = p^2/2 + (1 - e^-q)^2/2 for every row; returns the step at
    which each row dissociated (q > 10, where U is within 2e-5 of the well depth D = 1/2,
    from an initial energy near kT) or -1. Stops once ``enough`` rows have."""
    q, p = q.copy(), p.copy()
    out = np.full(q.size, -1)
    f = _morse_force(q)
    with np.errstate(all="ignore"):
        for n in range(1, steps + 1):
            p += 0.5 * h * f
            q += h * p
            f = _morse_force(q)
            p += 0.5 * h * f
            if n % every == 0:
                gone = (out < 0) & ~(np.isfinite(q) & (q < 10.0))
                out[gone] = n
                if np.count_nonzero(out > 0) >= enough:
                    break
    return out


def _clopper_pearson_lower(k: int, m: int) -> float:
    from scipy.stats import beta

    return 0.0 if k == 0 else float(beta.ppf(0.05, k, m - k + 1))


@pytest.mark.slow  # the test's own 64 bonds over up to 10^6 steps
def test_a_run_longer_than_followed_is_refused_where_a_cold_bond_dissociates_late():
    """Verlet just below its 4:1 point on a cold Morse bond (kT = 1e-6): no bond of the
    test's own ensemble dissociates within 10^4 steps, yet most do within a run of 10^6
    (more than 1e-3 of them, at 95% confidence). Trajectories that follow 10^4 steps
    cannot see that: check and advise refuse the run (a StepsafeError naming the run's key
    and the --follow-steps that would follow it), the command line with exit 2."""
    kT, steps, h = 1e-6, 1_000_000, 1.41421356  # just below the 4:1 point sqrt(2)
    rng = np.random.default_rng(5)
    m = 64
    q0 = _morse_boltzmann(kT, m, rng)
    p0 = rng.standard_normal(m) * np.sqrt(kT)
    # the reference: none dissociates within the first 10^4 steps, most within the run
    early = _verlet_dissociations(q0, p0, h, 10_000, enough=m)
    assert np.count_nonzero(early > 0) == 0
    lost = _verlet_dissociations(q0, p0, h, steps, enough=12)
    k = int(np.count_nonzero(lost > 0))
    assert _clopper_pearson_lower(k, m) > 1e-3
    with pytest.raises(StepsafeError, match="^--steps, steps=: .*--follow-steps 1000000"):
        stepsafe.check(scene=MORSE, h=h, kT=kT, steps=steps)
    with pytest.raises(StepsafeError, match="^--steps, steps=: .*--follow-steps"):
        stepsafe.advise(scene=MORSE, kT=kT, steps=steps)
    code, out, err = _cli("check", MORSE, "--kT", str(kT), "--steps", str(steps),
                          "--step", str(h))
    assert code == 2 and "SAFE" not in out and err.count("\n") == 1 and "--steps" in err


def _first_point(order: int) -> float:
    """Verlet's first n:m resonance of order n <= N for omega_0 = 1: theta(z) = 2 asin(z/2),
    n theta = 2 pi m first at n = N, m = 1: z = 2 sin(pi / N)."""
    return 2.0 * math.sin(math.pi / order)


@pytest.mark.slow  # a check at 0 K and one at temperature per example
@settings(max_examples=12, deadline=None)
@given(order=st.integers(3, 6), log_kT=st.floats(-8.0, -3.0),
       where=st.one_of(st.floats(0.5, 1.99),
                       st.integers(1, 12).map(lambda k: 1.0 + 10.0 ** -k),
                       st.floats(1e-9, 0.2).map(lambda e: 1.0 + e)),
       relative=st.booleans())
def test_a_temperature_never_passes_a_step_the_0K_resonance_check_refuses(
        order, log_kT, where, relative):
    """With resonance_order N the 0 K check refuses Morse (omega_0 = 1) steps at or past
    Verlet's first point 2 sin(pi/N); the check at any temperature refuses every one of
    them too (it keeps the points besides the bands it measures), and advise at
    temperature stays at or below the point."""
    h = _first_point(order) * where if relative else where
    kT = 10.0 ** log_kT
    cold = stepsafe.check(scene=MORSE, h=h, kT=0, resonance_order=order)
    point = _first_point(order)
    if abs(h / point - 1.0) > 1e-12:
        assert cold.safe is (h < point)
    warm = stepsafe.check(scene=MORSE, h=h, kT=kT, steps=200, resonance_order=order)
    if not cold.safe:
        assert not warm.safe
    advice = stepsafe.advise(scene=MORSE, kT=kT, steps=200, resonance_order=order)
    assert advice.h_max <= point * (1.0 + 1e-12)


def _cli(*args: str) -> tuple[int, str, str]:
    from click.testing import CliRunner

    from stepsafe.cli import main

    result = CliRunner().invoke(main, list(args), catch_exceptions=False)
    return result.exit_code, result.stdout, result.stderr


#: Seconds per unit (exact), for the test's own conversions.
_SECONDS = {"s": 1, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "ps": 1e-12, "fs": 1e-15, "as": 1e-18}


@pytest.mark.slow  # each example analyses the scene
@settings(max_examples=20, deadline=None)
@given(unit=st.sampled_from(sorted(_SECONDS)), value=st.floats(1e-3, 1e6),
       spaced=st.booleans(), cli=st.booleans(), command=st.sampled_from(["check", "advise"]))
def test_a_length_in_a_time_unit_is_refused_where_the_system_states_none(
        unit, value, spaced, cli, command):
    """The Morse scene states no time unit (its frequency 1 is per its own time unit): a
    run's length with a unit has no unit to be converted into, and the unit is not taken
    as the scene's. check and advise refuse it naming the length (exit 2 and one line on
    the command line, a StepsafeError in Python), whatever the unit and value; a plain
    number is the length in the scene's own unit (length / h steps)."""
    text = f"{value!r}{' ' if spaced else ''}{unit}"
    if cli:
        args = ["--step", "0.5"] if command == "check" else []
        code, out, err = _cli(command, MORSE, *args, "--length", text)
        assert code == 2 and out == "" and err.count("\n") == 1, (out, err)
        assert "--length" in err and unit in err and "no time unit" in err
        return
    call = stepsafe.check if command == "check" else stepsafe.advise
    keywords = {"h": 0.5} if command == "check" else {}
    with pytest.raises(StepsafeError, match="^--length, length=: .*no time unit"):
        call(scene=MORSE, length=text, **keywords)


def test_check_refuses_ten_picoseconds_for_the_morse_scene_in_its_own_units():
    code, out, err = _cli("check", MORSE, "--step", "1.40784", "--length", "10ps")
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith("stepsafe: error: --length, length=: '10ps' is in ps")


def test_a_plain_length_is_in_the_systems_own_time_unit():
    r = stepsafe.check(scene=MORSE, h=0.5, length=10)
    t = r.record["thermal"]
    assert r.time_unit is None and t["run"] == {"length": 10.0, "steps": None}
    assert t["minima"][0]["probes"][0]["steps"] == 20


@settings(max_examples=20, deadline=None)
@given(unit=st.sampled_from(sorted(_SECONDS)), wavenumber=st.floats(10.0, 5000.0))
def test_a_length_names_the_time_unit_of_frequencies_that_have_a_unit(unit, wavenumber):
    """A wavenumber is a frequency with a unit: the length's unit is then the time unit of
    the answer, as --time-unit would be: Verlet's h_max = 2 / beta, beta = 2 pi c nu
    (c = 299792458 m/s), computed here in the length's unit with 50 digits."""
    warm = stepsafe.advise("verlet", wavenumber=[wavenumber], kT=1.0,
                           length=f"{10.0 * _SECONDS['ps'] / _SECONDS[unit]!r} {unit}")
    named = stepsafe.advise("verlet", wavenumber=[wavenumber], time_unit=unit)
    assert warm.time_unit == unit and warm.h_max == named.h_max
    with mp.workdps(50):
        beta = 2 * mp.pi * mp.mpf(29979245800) * mp.mpf(wavenumber) * mp.mpf(_SECONDS[unit])
        exact = float(2 / beta)
    assert warm.h_max == pytest.approx(exact, rel=1e-8)


@settings(max_examples=40, deadline=None)
@given(order=st.one_of(st.integers(-10 ** 6, 2), st.integers(51, 10 ** 30),
                       st.floats(allow_nan=True, allow_infinity=True),
                       st.booleans(), st.text(max_size=5),
                       st.integers(3, 50).map(float), st.integers(3, 50).map(str)))
def test_a_bad_resonance_order_is_refused_at_temperature_as_at_0K(order):
    """resonance_order must be a whole number from 3 to 50 (not a bool, a float, a text)
    with or without a temperature: a StepsafeError naming the key, before any ensemble
    runs."""
    for kT in (0.0, 0.003):
        with pytest.raises(StepsafeError, match="^--resonance-order, resonance_order="):
            stepsafe.check(scene=MORSE, h=0.5, kT=kT, steps=10, resonance_order=order)
    with pytest.raises(StepsafeError, match="^--resonance-order, resonance_order="):
        stepsafe.advise(scene=MORSE, kT=0.003, steps=10, resonance_order=order)


@pytest.mark.parametrize("order", ["2", "2.5", "51"])
def test_the_command_line_refuses_a_bad_resonance_order_at_the_scenes_temperature(order):
    code, out, err = _cli("check", MORSE, "--step", "0.5", "--resonance-order", order)
    assert code == 2 and out == "" and err.count("\n") == 1 and "--resonance-order" in err


def test_a_numpy_integer_resonance_order_is_the_integer():
    a = stepsafe.check(scene=MORSE, h=1.5, kT=0.003, steps=10, resonance_order=np.int64(4))
    b = stepsafe.check(scene=MORSE, h=1.5, kT=0.003, steps=10, resonance_order=4)
    assert a.to_dict() == b.to_dict() and not a.safe


@settings(max_examples=60, deadline=None)
@given(steps=st.integers(1, 10 ** 30), kT=st.floats(1e-300, 1e300),
       kind=st.sampled_from(["int64", "0-d", "float64"]))
def test_numpy_numbers_are_the_numbers_and_texts_are_refused(steps, kT, kind):
    """steps= and kT= (and max_drift=, max_failure=) as numpy scalars or 0-d arrays give
    the request their Python numbers give; a text given by keyword is refused naming the
    key, as every numeric keyword of the API refuses one (a scene's text is a number)."""
    def wrap(x, integer):
        if kind == "0-d":
            return np.array(x)
        return np.int64(x) if integer and kind == "int64" else np.float64(x)

    n = steps if steps < 2 ** 63 else 2 ** 62
    plain = request(kT=kT, steps=n, max_drift=kT, max_failure=0.01)
    wrapped = request(kT=wrap(kT, False), steps=wrap(n, True), max_drift=wrap(kT, False),
                      max_failure=wrap(0.01, False))
    assert wrapped == plain and plain is not None and plain.steps == float(n)
    for key, good in (("steps", {"kT": kT}), ("kT", {"steps": n}),
                      ("max_drift", {"kT": kT, "steps": n}),
                      ("max_failure", {"kT": kT, "steps": n}),
                      ("follow_steps", {"kT": kT, "steps": 1})):
        with pytest.raises(StepsafeError, match=f"^{key}|^--{key}"):
            request(**good, **{key: str(steps)})
        with pytest.raises(StepsafeError, match=f"^{key}|^--{key}"):
            request(**good, **{key: np.array([n, n])})


QUARTIC = """kT: 0.1
steps: 2000
system:
  hamiltonian: "p**2/2 + q**2/2 + 0.1*q**4"
  box: {q: [-3, 3], p: [-1, 1]}
"""


@pytest.mark.slow  # an analysis at temperature per case (about 8 s of CPU each)
@pytest.mark.parametrize("name, margin", [("bcss2", None), ("blanes-moan4", 0.9)])
def test_advise_at_temperature_gives_no_step_above_the_one_its_fresh_ensemble_ran(
        tmp_path, name, margin):
    """A quartic well at kT = 0.1 is limited by the linear limit at temperature, a
    supremum: the fresh ensemble that confirms the answer runs just below it, and h_max
    (times the margin) is that step, not the limit above it."""
    path = tmp_path / "quartic.yaml"
    path.write_text(QUARTIC)
    r = stepsafe.advise(name, scene=str(path), margin=margin)
    t = r.record["thermal"]
    m = t["minima"][0]
    assert t["limited_by"] == "linear at temperature"
    # (the record's steps, the confirmation's too, are in the time unit times the margin)
    assert r.h_max == t["h_max"] == m["confirmation"]["h"]
    assert m["confirmation"]["failures"] == 0 and m["drift"]["h"] == m["confirmation"]["h"]
    assert r.h_max < m["h_linear"] <= 1.002 * r.h_max
