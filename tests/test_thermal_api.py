"""advise and check at temperature, through the API and the command line: the inputs (kelvin
against the Boltzmann constant at 50 digits, kT, the run's length or steps, from keywords,
options and scene keys), bad input naming its key, nothing changed at T = 0 or for a
harmonic system, and the Morse verdicts of the issue against an integration written here."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.api.temperature import request
from stepsafe.api.thermal import followed
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.scene import load_scene
from stepsafe.systems.thermal.limit import run_steps

MORSE = """method: verlet
system:
  hamiltonian: "p**2/2 + (1 - exp(-q))**2/2"
  box: {q: [-1, 5], p: [-1, 1]}
"""


@pytest.fixture
def morse_scene(tmp_path):
    path = tmp_path / "morse.yaml"
    path.write_text(MORSE)
    return str(path)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stepsafe", *args], capture_output=True,
                          text=True, timeout=600)


def test_temperature_in_kelvin_is_the_boltzmann_energy_in_the_scenes_unit(tmp_path):
    """k_B T in kcal/mol, kJ/mol and eV at 50 digits (k_B = 1.380649e-23 J/K, N_A =
    6.02214076e23 /mol, the calorie 4.184 J, the electronvolt 1.602176634e-19 J)."""
    mp.mp.dps = 50
    kB, NA = mp.mpf("1.380649e-23"), mp.mpf("6.02214076e23")
    per = {"kcal/mol": mp.mpf(4184) / NA, "kJ/mol": mp.mpf(1000) / NA,
           "eV": mp.mpf("1.602176634e-19")}
    for unit, joules in per.items():
        path = tmp_path / "s.yaml"
        path.write_text(MORSE + f"energy_unit: {unit}\ntemperature: 300 K\nsteps: 100\n")
        r = request(scene=load_scene(path))
        assert r.kT == float(kB * 300 / joules)
        assert (r.temperature, r.energy_unit, r.steps, r.length) == (300.0, unit, 100.0, None)
    # 0.596 kcal/mol: kT at room temperature as chemists know it
    assert request(temperature="300K", steps=10, scene=load_scene(path)).kT == \
        pytest.approx(2.585e-2, rel=1e-3)


def test_a_temperature_keyword_wins_over_the_scenes_kT_and_kT_over_its_temperature(tmp_path):
    """The scene's ``kT:`` and a ``temperature=`` keyword (or its ``temperature:`` and
    ``kT=``) are not both given: the keyword wins, as every keyword over the scene's key."""
    path = tmp_path / "s.yaml"
    path.write_text(MORSE + "energy_unit: kJ/mol\nkT: 0.5\nsteps: 10\n")
    r = request(temperature="300K", scene=load_scene(path))
    assert r.temperature == 300.0 and r.kT == pytest.approx(2.494, rel=1e-3)
    path.write_text(MORSE + "energy_unit: kJ/mol\ntemperature: 300 K\nsteps: 10\n")
    r = request(kT=0.6, scene=load_scene(path))
    assert r.kT == 0.6 and r.temperature is None


def test_keywords_win_over_the_scenes_keys_and_a_length_takes_the_time_unit(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(MORSE + "time_unit: fs\nkT: 0.5\nlength: 2 ps\n")
    scene = load_scene(path)
    r = request(scene=scene, time_unit="fs")
    assert (r.kT, r.length, r.steps) == (0.5, 2000.0, None)
    r = request(kT=0.25, steps=300, scene=scene, time_unit="fs")
    assert (r.kT, r.steps, r.length) == (0.25, 300.0, None)


@pytest.mark.parametrize("keys, message, key", [
    ("temperature: hot\nsteps: 10\n", "not a number", "temperature"),
    ("temperature: 300 fs\nenergy_unit: eV\nsteps: 10\n", "kelvin", "temperature"),
    ("temperature: -5\nenergy_unit: eV\nsteps: 10\n", ">= 0", "temperature"),
    ("temperature: 300\nsteps: 10\n", "no unit", "temperature"),
    ("temperature: 300\nenergy_unit: furlong\nsteps: 10\n", "one of", "energy_unit"),
    ("kT: -1\nsteps: 10\n", "negative", "kT"),
    ("kT: .nan\nsteps: 10\n", "finite", "kT"),
    ("kT: 1\ntemperature: 3\nsteps: 10\n", "not both", "temperature"),
    ("kT: 1\n", "length", "length"),
    ("kT: 1\nlength: 10 THz\n", "time", "length"),
    ("kT: 1\nlength: -3\n", "positive", "length"),
    ("kT: 1\nsteps: 2.5\n", "whole number", "steps"),
    ("kT: 1\nsteps: 0\n", "whole number", "steps"),
    ("kT: 1\nsteps: 10\nlength: 3\n", "not both", "length"),
    ("steps: 10\n", "temperature", "steps"),
    ("kT: 1\nsteps: 10\nmax_drift: 0\n", "positive", "max_drift"),
    ("kT: 1\nsteps: 10\nmax_drift: .inf\n", "positive", "max_drift"),
])
def test_bad_scene_values_exit_2_naming_the_file_and_key(tmp_path, run, keys, message, key):
    path = tmp_path / "bad.yaml"
    path.write_text(MORSE + keys)
    with pytest.raises(StepsafeError, match=message) as info:
        request(scene=load_scene(path))
    assert info.value.where == f"{path}::$.{key}"
    code, out, err = run("check", str(path), "--step", "0.5")
    assert code == 2 and out == ""
    assert f"$.{key}" in err and len(err.strip().splitlines()) == 1


@settings(max_examples=60, deadline=None)
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**400, 10**400),
                 st.text(max_size=12), st.booleans(), st.none(), st.lists(st.floats(),
                                                                           max_size=2)),
       st.sampled_from(["kT", "temperature", "length", "steps", "max_drift"]))
def test_any_value_of_a_key_is_accepted_or_refused_naming_it(value, key):
    """A hostile value of each keyword: a request, None, or a StepsafeError whose message
    names the keyword; never another exception."""
    base = {"kT": 0.1, "steps": 10}
    if key == "temperature":
        base = {"temperature": None, "steps": 10}
    kwargs = {**base, key: value}
    if key in ("length",):
        kwargs.pop("steps")
    try:
        r = request(**kwargs, system={"units": {"energy": "eV"}}, time_unit="fs")
    except StepsafeError as exc:
        assert any(k in exc.message for k in kwargs), exc.message
        return
    if r is not None:
        assert math.isfinite(r.kT) and r.kT > 0
        assert (r.length is None) != (r.steps is None)


@pytest.mark.slow  # (several command-line runs, each analysing the scene)
def test_command_line_options_name_themselves_when_bad(morse_scene):
    for args, word in [(["--temperature", "300"], "temperature"),
                       (["--kT", "-1", "--steps", "5"], "kT"),
                       (["--kT", "1"], "length"), (["--kT", "1", "--length", "3THz"], "length"),
                       (["--kT", "1", "--steps", "5", "--length", "3"], "length")]:
        run = _cli("advise", morse_scene, *args)
        assert run.returncode == 2, run.stderr
        assert word in run.stderr and len(run.stderr.strip().splitlines()) == 1


@pytest.mark.slow  # (several command-line runs, each analysing the scene)
def test_zero_temperature_changes_no_answer(morse_scene):
    plain = stepsafe.advise(scene=morse_scene).to_dict()
    assert stepsafe.advise(scene=morse_scene, kT=0.0).to_dict() == plain
    assert stepsafe.advise(scene=morse_scene, kT=0, steps=10).to_dict() == plain
    checked = stepsafe.check(scene=morse_scene, h=1.7, resonance_order=3).to_dict()
    assert stepsafe.check(scene=morse_scene, h=1.7, resonance_order=3, kT=0.0).to_dict() == \
        checked
    run = _cli("advise", morse_scene, "--temperature", "0", "--json")
    assert run.returncode == 0 and json.loads(run.stdout) == plain


def test_harmonic_inputs_keep_their_answer_at_any_temperature():
    plain = stepsafe.advise("verlet", [1.0, 4.0])
    warm = stepsafe.advise("verlet", [1.0, 4.0], kT=3.0, steps=1000)
    assert (warm.h_max, warm.h_max_limited_by) == (plain.h_max, plain.h_max_limited_by)
    assert warm.record["thermal"]["harmonic"] is True
    assert warm.record["thermal"]["limited_by"] == "0 K"
    c = stepsafe.check("verlet", 0.49, [4.0], kT=3.0, steps=1000)
    assert c.safe and c.record["thermal"]["safe"]
    assert not stepsafe.check("verlet", 0.51, [4.0], kT=3.0, steps=1000).safe


def _U(q):
    return 0.5 * (1 - np.exp(-q)) ** 2


def _force(q):
    e = np.exp(-q)
    return -(1 - e) * e


def _boltzmann(kT, m, seed):
    """m draws of (q, p) from exp(-H / kT) for H = p^2/2 + (1 - e^-q)^2/2: q by rejection
    from N(0, 2 kT) (the well's density over that proposal is bounded), p ~ N(0, kT)."""
    rng = np.random.default_rng(seed)
    U = _U
    q = np.empty(0)
    while q.size < m:
        x = rng.standard_normal(4 * m) * math.sqrt(2 * kT) + 0.0
        # proposal N(0, 2 kT) covers exp(-U/kT) (U >= q^2/2 - q^3/2 near 0, bounded
        # well); accept with exp(-U/kT) / (c exp(-x^2 / 4kT)), c = max over the well
        w = np.exp(-U(x) / kT + x * x / (4 * kT))
        c = float(np.max(w)) * 1.01
        q = np.concatenate([q, x[rng.random(x.size) * c < w]])
    return q[:m], rng.standard_normal(m) * math.sqrt(kT)


def _own_escapes(h, kT, steps=2000, m=2000, seed=5):
    """Velocity Verlet on U = (1 - e^-q)^2 / 2 written here, from the test's own Boltzmann
    draws; the fraction whose energy leaves the well (above 0.45 = 0.9 D) or overflows
    within ``steps`` steps."""
    q, p = _boltzmann(kT, m, seed)
    U, force = _U, _force
    out = np.zeros(m, dtype=bool)
    with np.errstate(all="ignore"):
        f = force(q)
        for _ in range(steps):
            p = p + 0.5 * h * f
            q = q + h * p
            f = force(q)
            p = p + 0.5 * h * f
            out |= ~(U(q) + 0.5 * p * p < 0.45)
    return float(out.mean())


def _morse_advice(path: str, kT: float):
    return stepsafe.advise(scene=path, kT=kT, steps=10000)


@pytest.mark.slow
@pytest.mark.parametrize("kT", [0.003, 0.015])
def test_morse_advice_at_temperature_runs_clear_by_an_integration_written_here(
        morse_scene, kT):
    """At E/D = 0.006 and 0.03 (D = 1/2): h_max at temperature lies below the 0 K one and
    below the issue's failing steps; the test's own Verlet from its own Boltzmann draws
    loses no more than the 1% threshold allows (2.3 standard errors) at h_max, and the
    record says which criterion limits it, with the run quantile's method and the seeds."""
    r = _morse_advice(morse_scene, kT)
    t = r.record["thermal"]
    assert r.h_max == t["h_max"] < r.record["zero_kelvin"]["h_max"]
    assert t["limited_by"].split(" (")[0] in ("linear at temperature", "drift") or \
        t["limited_by"].startswith("resonance band")
    assert r.h_max < (1.40784 if kT == 0.003 else 1.5)
    m = t["minima"][0]
    assert "peaks over threshold" in m["frequencies"]["extrapolation"] or \
        "empirical" in m["frequencies"]["extrapolation"]
    assert t["seed"] == 0 and m["frequencies"]["seed"] == 0
    assert m["drift"]["h"] <= r.h_max and m["drift"]["fluctuation"] > 0
    assert _own_escapes(r.h_max, kT) <= 0.01 + 2.3 * math.sqrt(0.01 * 0.99 / 2000)


@pytest.mark.parametrize("h, kT, order", [
    (1.70056, 0.003, 3), (1.40784, 0.003, 4), (0.8, 0.003, 4), (1.5, 0.015, None)])
def test_morse_check_at_temperature_against_an_integration_written_here(
        morse_scene, h, kT, order):
    """check --temperature: the issue's failing steps (2% below Verlet's 3:1 point, 0.5%
    below its 4:1 point, z = 1.5 at E/D = 0.03) are UNSAFE at temperature while the 0 K
    check says SAFE, with --resonance-order 3 or 4 (the points, not the bands); z = 0.8 is
    SAFE. Each verdict agrees with the test's own integration: a step where it sees
    escapes is never SAFE."""
    zero = stepsafe.check(scene=morse_scene, h=h, resonance_order=order)
    assert zero.safe
    warm = stepsafe.check(scene=morse_scene, h=h, resonance_order=order, kT=kT, steps=10000)
    own = _own_escapes(h, kT)
    assert warm.safe is (h == 0.8), warm.record["thermal"]["reasons"]
    if own > 0.02:
        assert not warm.safe
    assert (h == 0.8) is (own == 0.0)


@pytest.mark.slow  # (several command-line runs, each analysing the scene)
def test_check_at_temperature_exits_1_and_reports_json(morse_scene):
    run = _cli("check", morse_scene, "--step", "1.70056", "--kT", "0.003", "--steps",
               "10000", "--json")
    assert run.returncode == 1, run.stderr
    entry = json.loads(run.stdout)["checks"][0]
    assert entry["safe"] is False and entry["thermal"]["safe"] is False
    assert entry["thermal"]["kT"] == 0.003 and entry["thermal"]["seed"] == 0
    probe = entry["thermal"]["minima"][0]["probes"][0]
    assert probe["failures"] > 0.5 * probe["trajectories"]
    text = _cli("check", morse_scene, "--step", "0.8", "--kT", "0.003", "--steps", "10000")
    assert text.returncode == 0 and "At kT = 0.003, a run of 10000 steps: SAFE" in text.stdout


def test_example_scene_at_temperature_is_in_the_examples():
    assert (Path(__file__).parent.parent / "examples" / "morse-300K.yaml").exists()


def _own_drift(h, kT, steps=2000, m=500, seed=7):
    """The test's own drift at h: each trajectory's least-squares slope of H_n - H_0
    against t = n h over every step (velocity Verlet written here, its own Boltzmann
    draws); the mean slope and its standard error over trajectories."""
    q, p = _boltzmann(kT, m, seed)
    H0 = _U(q) + 0.5 * p * p
    f = _force(q)
    dH = np.empty((steps, m))
    for n in range(steps):
        p = p + 0.5 * h * f
        q = q + h * p
        f = _force(q)
        p = p + 0.5 * h * f
        dH[n] = _U(q) + 0.5 * p * p - H0
    keep = np.all(np.isfinite(dH), axis=0) & (np.max(np.abs(dH), axis=0) < 0.1)
    slope = np.polyfit(h * np.arange(1, steps + 1), dH[:, keep], 1)[0]
    return float(slope.mean()), float(slope.std(ddof=1) / math.sqrt(keep.sum()))


@pytest.mark.slow  # two analyses at temperature and the test's own drift run
def test_max_drift_limits_the_step_where_the_measured_drift_meets_it():
    """advise with max_drift 1e-9 (energy per time unit, below the drift bound at the
    free limit) at kT/D = 0.006: the step is
    lowered until the measured drift (plus 2 standard errors) meets it and the record says
    so; the test's own Verlet drift at that step is within the tolerance (3 of its own
    standard errors allowed); check at that step with the tolerance is SAFE, and a
    tolerance a thousand times below the measured bound fails it."""
    scene = str(Path(__file__).parent.parent / "examples" / "morse.yaml")
    free = stepsafe.advise(scene=scene)
    r = stepsafe.advise(scene=scene, max_drift=1e-9)
    t = r.record["thermal"]
    assert t["limited_by"] == "drift" == r.h_max_limited_by and t["max_drift"] == 1e-9
    assert r.h_max < free.h_max
    d = t["minima"][0]["drift"]
    assert d["h"] == r.h_max and abs(d["rate"]) + 2 * d["error"] <= 1e-9
    rate, error = _own_drift(r.h_max, 0.003)
    assert abs(rate) <= 1e-9 + 3 * error
    ok = stepsafe.check(scene=scene, h=0.9 * r.h_max, max_drift=1e-9)
    assert ok.safe, ok.record["thermal"]["reasons"]
    probe = ok.record["thermal"]["minima"][0]["drift"]
    tight = (abs(probe["rate"]) + 2 * probe["error"]) / 1000
    bad = stepsafe.check(scene=scene, h=0.9 * r.h_max, max_drift=tight)
    assert not bad.safe and "max_drift" in " ".join(bad.record["thermal"]["reasons"])


def test_json_at_temperature_follows_the_output_schema():
    """advise and check --json at temperature (a harmonic system: quick) carry their
    thermal records as ``stepsafe schema output`` describes them."""
    import jsonschema

    from stepsafe.api.schemas import output_schema

    for command, args in (("advise", ()), ("check", ("--step", "0.5"))):
        run = _cli(command, "--method", "verlet", "--beta", "1", "--kT", "2", "--steps",
                   "100", "--json", *args)
        assert run.returncode == 0, run.stderr
        data = json.loads(run.stdout)
        jsonschema.validate(data, output_schema(command))
        record = data if command == "advise" else data["checks"][0]
        assert record["thermal"]["harmonic"] is True and record["thermal"]["kT"] == 2.0
    advice = stepsafe.advise("verlet", [1.0], kT=2.0, steps=100).to_dict()
    jsonschema.validate(advice, output_schema("advise"))
    assert advice["thermal"]["h_max"] == advice["h_max"] == advice["zero_kelvin"]["h_max"]


@settings(max_examples=50, deadline=None)
@given(st.lists(st.lists(st.lists(st.floats(0, 1), max_size=6), max_size=5), min_size=1,
                max_size=4))
def test_progress_at_temperature_never_goes_back_and_stays_in_the_unit_interval(minima):
    """Each minimum's stages, one after another, each reporting rising fractions: the whole
    stays in [0, 1] and never goes back, and each minimum ends within its share."""
    from stepsafe.api.thermal import _progress

    seen: list[float] = []
    of = _progress(seen.append, len(minima))
    for i, stages in enumerate(minima):
        report = of(i)
        for k, fractions in enumerate(stages):
            for f in sorted(fractions):
                report(f"stage {k}", f)
                assert i / len(minima) <= seen[-1] <= (i + 1) / len(minima)
    assert all(0.0 <= x <= 1.0 for x in seen)
    assert all(b >= a for a, b in zip(seen, seen[1:]))


@pytest.mark.slow  # an analysis at temperature, two checks and the test's own runs
def test_resonance_order_at_temperature_excludes_the_measured_band_and_the_point():
    """At kT/D = 2e-4 the 4:1 band of Verlet on the Morse bond is narrow: with
    --resonance-order 4 the 0 K answer stops at the point sqrt 2, the answer at
    temperature at the band's measured lower edge or, where the fresh ensemble that confirms
    it loses a trajectory, at most 10% below it; inside the band the
    test's own integration loses trajectories, at the answer it loses none beyond the
    threshold. A step past the band's upper edge, where the test's own integration loses no
    trajectory, is SAFE at temperature without the order and stays unsafe with it, as at
    0 K: a temperature never passes a step the 0 K check refuses."""
    scene = str(Path(__file__).parent.parent / "examples" / "morse.yaml")
    kT = 1e-4
    zero = stepsafe.advise(scene=scene, kT=0, resonance_order=4)
    assert zero.h_max_limited_by == "resonance 4:1"
    assert zero.h_max == pytest.approx(math.sqrt(2), rel=1e-12)
    warm = stepsafe.advise(scene=scene, kT=kT, resonance_order=4)
    band = next(b for sc in warm.record["thermal"]["minima"][0]["scans"]
                for b in sc["bands"] if b["name"] == "4:1")
    assert warm.h_max_limited_by.startswith("resonance band 4:1")
    assert 0.9 * band["lower"]["clear"] <= warm.h_max <= band["lower"]["clear"]
    assert warm.h_max <= zero.h_max
    assert band["lower"]["clear"] < math.sqrt(2) < band["upper"]["clear"]
    inside = 0.5 * (band["lower"]["unsafe"] + band["upper"]["unsafe"])
    assert _own_escapes(inside, kT) > 0.05
    assert _own_escapes(warm.h_max, kT) <= 0.01 + 2.3 * math.sqrt(0.01 * 0.99 / 2000)
    past = 1.01 * band["upper"]["clear"]
    assert not stepsafe.check(scene=scene, h=past, resonance_order=4).safe
    assert not stepsafe.check(scene=scene, h=past, resonance_order=4, kT=kT).safe
    assert stepsafe.check(scene=scene, h=past, kT=kT).safe
    assert _own_escapes(past, kT) == 0.0


@pytest.mark.parametrize("name", ["baoab", "langevin-middle"])
def test_langevin_splittings_are_refused_at_temperature_naming_it(name):
    with pytest.raises(StepsafeError, match="^temperature: .*Langevin"):
        stepsafe.advise(name, [1.0], kT=1.0, steps=10)
    with pytest.raises(StepsafeError, match="^temperature: .*Langevin"):
        stepsafe.check(name, 0.5, [1.0], kT=1.0, steps=10)
    assert stepsafe.advise(name, [1.0], kT=0.0).to_dict() == stepsafe.advise(name, [1.0]).to_dict()


@pytest.mark.openmm
@pytest.mark.parametrize("options, message", [
    (["--method", "pefrl", "--kT", "2.49", "--steps", "1000"], "runs verlet, langevin-middle only"),
    (["--temperature", "300K", "--length", "1ps", "--kT", "2.49"], "not both")])
def test_a_temperature_the_engine_cannot_answer_is_refused_not_answered_at_0K(run, options,
                                                                            message):
    """An OpenMM system at temperature is answered by runs of the method in OpenMM: a method
    OpenMM does not run is refused (exit 2, one line) before any sampling, never answered
    with the 0 K verdict as if the system were linear."""
    pytest.importorskip("openmm")
    scene = Path(__file__).resolve().parents[1] / "examples" / "water-cluster.yaml"
    code, out, err = run("check", str(scene), *options)
    assert code == 2 and "SAFE" not in out, (out, err)
    assert message in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("criterion", [
    "structure", pytest.param("stability", marks=pytest.mark.slow)])
def test_json_says_which_criterion_and_which_answer_was_applied(morse_scene, criterion):
    """The criterion keeps its name at temperature: the record's ``criterion`` and the
    thermal record's are the one given, and each minimum's z* and 0 K limit are the first
    boundary ``region`` gives under it (omega_0 = 1). The answer applied is named: advise's
    ``h_max`` and ``h_max_limited_by`` are the thermal answer's (the 0 K one under
    ``zero_kelvin``), and a step SAFE at 0 K but not at temperature fails with no mode
    failing and the reason under ``thermal_failure``. A harmonic system names its
    criterion too, and its answer at temperature is the 0 K one under that criterion,
    islands included."""
    import jsonschema

    from stepsafe.api.schemas import output_schema

    z_star = stepsafe.region("verlet", model="oscillator", criterion=criterion) \
        .to_dict()["models"]["oscillator"]["first_boundary"]
    advice = stepsafe.advise(scene=morse_scene, kT=0.003, steps=10000,
                             criterion=criterion).to_dict()
    jsonschema.validate(advice, output_schema("advise"))
    t = advice["thermal"]
    assert advice["criterion"] == t["criterion"] == criterion
    assert t["minima"][0]["z_star"] == z_star
    assert t["minima"][0]["h_zero"] == pytest.approx(z_star, rel=1e-12)
    assert (advice["h_max"], advice["h_max_limited_by"]) == (t["h_max"], t["limited_by"])
    assert t["limited_by"] != "0 K" and advice["h_max"] < advice["zero_kelvin"]["h_max"]
    assert advice["zero_kelvin"]["h_max_limited_by"] == "boundary"

    checked = stepsafe.check(scene=morse_scene, h=1.5, kT=0.003, steps=10000,
                             criterion=criterion).to_dict()
    jsonschema.validate(checked, output_schema("check"))
    entry = checked["checks"][0]
    assert entry["criterion"] == entry["thermal"]["criterion"] == criterion
    assert entry["safe"] is False and entry["failing"] == 0 and not entry["failures"]
    assert entry["thermal_failure"].startswith("at temperature ")
    assert entry["thermal"]["minima"][0]["h_zero"] == pytest.approx(z_star, rel=1e-12)

    linear = stepsafe.advise("bcss3", [1.0], kT=2.0, steps=100, criterion=criterion)
    plain = stepsafe.advise("bcss3", [1.0], criterion=criterion)
    assert linear.record["thermal"]["criterion"] == criterion
    assert linear.record["thermal"]["limited_by"] == "0 K"
    assert linear.h_max == plain.h_max and linear.safe_h == plain.safe_h


@settings(max_examples=60, deadline=None)
@given(scale=st.integers(-100, 100), x=st.floats(0.5, 2.0), n=st.integers(1, 10 ** 6),
       follow=st.integers(1, 10 ** 6), by_length=st.booleans())
def test_a_run_longer_than_the_trajectories_follow_is_refused_at_every_scale(
        scale, x, n, follow, by_length):
    """A run of n steps at h (given as steps, or as the length n h in any time unit from
    1e-100 to 1e100) passes when n <= follow_steps and is refused otherwise, with a
    StepsafeError naming the run's key, the steps and what to give instead."""
    h = x * 10.0 ** scale
    run = {"length": n * h} if by_length else {"steps": n}
    r = request(kT=0.1, follow_steps=follow, **run)
    assert r is not None and r.follow == follow
    assert run_steps(h, r.length, r.steps) == n
    if n <= follow:
        followed(r, h)
        return
    with pytest.raises(StepsafeError) as info:
        followed(r, h)
    key = "--length" if by_length else "--steps"
    assert info.value.message.startswith(f"{key}, ")
    assert f"the run's {n} steps" in info.value.message
    assert f"--follow-steps {n}" in info.value.message


def test_follow_steps_defaults_to_ten_thousand_and_refuses_bad_values(tmp_path):
    r = request(kT=0.1, steps=10)
    assert r is not None and r.follow == 10_000
    for bad in (0, -3, 1.5, "many", True, 10 ** 9):
        with pytest.raises(StepsafeError, match="follow_steps"):
            request(kT=0.1, steps=10, follow_steps=bad)
    path = tmp_path / "s.yaml"
    path.write_text(MORSE + "kT: 0.003\nsteps: 20000\nfollow_steps: 0\n")
    with pytest.raises(StepsafeError) as info:
        request(scene=load_scene(path))
    assert info.value.where == f"{path}::$.follow_steps"


def test_check_and_advise_refuse_a_run_longer_than_followed_naming_the_key(tmp_path):
    """``steps: 20000`` in a scene (trajectories follow 10000 by default): check and
    advise exit 2 with one line naming the file and key, before any ensemble runs; the
    same run on the command line names the option; ``--follow-steps`` at the run's length
    lets it be followed."""
    path = tmp_path / "long.yaml"
    path.write_text(MORSE + "h: 0.8\nkT: 0.003\nsteps: 20000\n")
    run = _cli("check", str(path))
    assert run.returncode == 2 and run.stdout == "", run.stderr
    assert run.stderr.count("\n") == 1 and f"{path}::$.steps" in run.stderr
    assert "--follow-steps 20000" in run.stderr
    with pytest.raises(StepsafeError, match="--follow-steps 20000") as info:
        stepsafe.advise(scene=str(path))
    assert info.value.where == f"{path}::$.steps"
    with pytest.raises(StepsafeError, match="^--steps, steps="):
        stepsafe.advise(scene=str(path), steps=30_000, follow_steps=29_999)
    with pytest.raises(StepsafeError, match="--length, length="):
        stepsafe.check(scene=str(path), length=2e4, follow_steps=24_999)
    r = stepsafe.check(scene=str(path), steps=60, follow_steps=60)
    assert r.safe and r.record["thermal"]["follow_steps"] == 60
    assert r.record["thermal"]["minima"][0]["probes"][0]["steps"] == 60


@pytest.mark.slow  # (an analysis at temperature whose 24 confirmations all fail: ~5 s)
def test_advise_says_plainly_when_no_step_is_confirmed_safe_at_temperature():
    """The 4-mass FPU chain at kT = 0.55 (its bonds' barrier is 4.8 kT high): a fresh
    ensemble loses trajectories at every step tried, so no step is safe at temperature.
    The text says so (never "0 < h < 0"), the JSON has ``h_max`` 0, ``confirmed`` false
    and no safe step, and advise exits 0 as it does for "No safe step" at 0 K."""
    scene = str(Path(__file__).resolve().parent.parent / "examples" / "fpu-alpha.yaml")
    args = ("advise", scene, "--kT", "0.55", "--steps", "100")
    text = _cli(*args)
    assert text.returncode == 0, text.stderr
    assert "No step confirmed safe at this temperature" in text.stdout
    assert "< 0," not in text.stdout and "h < 0 " not in text.stdout
    assert "no step confirmed (" in text.stdout
    run = _cli(*args, "--json")
    assert run.returncode == 0, run.stderr
    data = json.loads(run.stdout)
    t = data["thermal"]
    assert t["confirmed"] is False and t["h_max"] == 0 == data["h_max"]
    assert data["safe_h"] == []
    c = t["minima"][0]["confirmation"]
    assert c["h"] == 0 and len(c["rejected"]) == 24
    assert all(x["failures"] >= 1 and 1 <= x["steps"] <= 100 for x in c["rejected"])
    low = min(x["h"] for x in c["rejected"])
    assert f"down to h = {low:.6g}" in text.stdout
