"""The statistics of ``check --kT`` on ``hamiltonian:`` scenes against an independent
simulation.

The reference here is written from the methods' published coefficients and nothing else:
velocity Verlet (kick h/2, drift h, kick h/2), thermal starts drawn from the Boltzmann
distribution of the well by inverse transform on a fine grid (p normal with variance m kT),
and the run length the scene states. A trajectory *escapes* when its energy or position
stops being finite or, for a bond, when it dissociates (q > 10 for a Morse well of range 1).
An exact Hamiltonian flow started below the well's rim never does either, so every escape is
the integrator's.

A step whose thermal ensemble escapes at a rate the sample resolves (the lower end of a 95%
Clopper-Pearson interval above zero) is unsafe; ``check`` must not exit 0 on it.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from stepsafe.cli import main

# each example runs check and a simulation: report the first failing one without shrinking
NO_SHRINK = (Phase.explicit, Phase.reuse, Phase.generate)


def _check(scene: str, *args: str) -> tuple[int, str, str]:
    """Run ``stepsafe check`` in-process on a scene written to a temporary file."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "scene.yaml"
        path.write_text(scene)
        result = CliRunner().invoke(main, ["check", str(path), *args])
        return result.exit_code, result.stdout, result.stderr


def _boltzmann(potential, kT: float, lo: float, hi: float, n: int,
               rng: np.random.Generator) -> np.ndarray:
    """Draws from exp(-U/kT) on [lo, hi] by inverse transform on a 2e5-point grid."""
    x = np.linspace(lo, hi, 200_001)
    u = potential(x)
    w = np.exp(-(u - u.min()) / kT)
    c = np.cumsum(w)
    c /= c[-1]
    return np.interp(rng.random(n), c, x)


def _verlet_escapes(force, energy, q, p, h: float, steps: int, mass: float = 1.0,
                    escaped=None) -> np.ndarray:
    """Velocity Verlet from (q, p); True where the trajectory escapes within ``steps``."""
    out = np.zeros(q.shape, bool)
    with np.errstate(all="ignore"):
        f = force(q)
        for n in range(steps):
            p = p + 0.5 * h * f
            q = q + h * p / mass
            f = force(q)
            p = p + 0.5 * h * f
            if n % 10 == 9 or n == steps - 1:
                bad = ~np.isfinite(energy(q, p)) | ~np.isfinite(q)
                if escaped is not None:
                    bad |= escaped(q)
                out |= bad
    return out


def _clopper_pearson_lower(k: int, n: int, level: float = 0.95) -> float:
    """Lower end of the two-sided Clopper-Pearson interval for k successes in n."""
    if k == 0:
        return 0.0
    from scipy.stats import beta
    return float(beta.ppf((1 - level) / 2, k, n - k + 1))


# ---------------------------------------------------------------- quartic (hardening) well

def _quartic_scene(g: float, kT: float, steps: int, energy: float, length: float,
                   mass: float) -> str:
    """H = p^2/(2m) + E (x^2/2 + g x^4), x = q/L: the unit well in scaled units."""
    return (
        "method: verlet\n"
        f"kT: {kT * energy!r}\n"
        f"steps: {steps}\n"
        "system:\n"
        '  hamiltonian: "p**2/(2*m) + E*((q/L)**2/2 + g*(q/L)**4)"\n'
        f"  parameters: {{m: {mass!r}, E: {energy!r}, L: {length!r}, g: {g!r}}}\n"
        f"  box: {{q: [{-8 * length!r}, {8 * length!r}], "
        f"p: [{-8 * math.sqrt(mass * energy)!r}, {8 * math.sqrt(mass * energy)!r}]}}\n"
    )


def _quartic_escape_count(g: float, kT: float, h: float, steps: int, n: int,
                          seed: int) -> int:
    """Escapes of a Boltzmann ensemble of the unit quartic well (m = E = L = 1) under Verlet."""
    rng = np.random.default_rng(seed)

    def potential(x):
        return x * x / 2 + g * x ** 4

    amp = (kT / g) ** 0.25 + math.sqrt(kT)
    q = _boltzmann(potential, kT, -6 * amp, 6 * amp, n, rng)
    p = rng.normal(0.0, math.sqrt(kT), n)
    escaped = _verlet_escapes(lambda x: -(x + 4 * g * x ** 3),
                              lambda x, v: v * v / 2 + potential(x), q, p, h, steps)
    return int(escaped.sum())


def test_reference_verlet_keeps_a_harmonic_ensemble_below_its_stability_limit():
    """The reference integrator itself: a harmonic ensemble never escapes at h = 1.99 and
    always does at h = 2.01 (|tr M| = |2 - h^2| crosses 2 at h = 2)."""
    rng = np.random.default_rng(0)
    q = rng.normal(size=200)
    p = rng.normal(size=200)

    def force(x):
        return -x

    def energy(x, v):
        return (x * x + v * v) / 2

    assert not _verlet_escapes(force, energy, q, p, 1.99, 20_000).any()
    assert _verlet_escapes(force, energy, q, p, 2.01, 20_000).all()


@pytest.mark.slow  # a 2e4-trajectory reference and three checks at temperature
@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck),
          phases=NO_SHRINK)
@given(
    frac=st.floats(1.085, 1.1),
    energy_exp=st.integers(-30, 30),
    length_exp=st.integers(-30, 30),
    mass_exp=st.integers(-30, 30),
)
def test_check_is_not_safe_where_the_thermal_quartic_ensemble_blows_up(
        frac, energy_exp, length_exp, mass_exp):
    """U = E (x^2/2 + 0.1 x^4), x = q/L, at kT = 0.1 E over 10^4 steps; h = frac tau with
    tau = L sqrt(m/E). The dimensionless run is simulated (exactly equivalent under the
    scaling); where it shows escapes, the scaled check must not say SAFE."""
    g, kT = 0.1, 0.1
    energy, length, mass = 10.0 ** energy_exp, 10.0 ** length_exp, 10.0 ** mass_exp
    tau = length * math.sqrt(mass / energy)
    n = 20_000
    k = _quartic_escape_count(g, kT, frac, 200, n, seed=5)
    assert _clopper_pearson_lower(k, n) > 0.001, (frac, k)
    code, out, err = _check(_quartic_scene(g, kT, 10_000, energy, length, mass),
                            "--step", repr(frac * tau))
    assert code != 0, (f"SAFE at h = {frac} tau, but {k} of {n} thermal trajectories of the "
                       f"reference escaped (non-finite) within 200 steps\n{out}{err}")


# ---------------------------------------------------------------------------- Morse bond

MORSE_SCENE = (
    "method: verlet\n"
    "kT: 0.015\n"
    "steps: 10000\n"
    "system:\n"
    '  hamiltonian: "p**2/2 + (1 - exp(-q))**2/2"\n'
    "  box: {q: [-1, 5], p: [-1, 1]}\n"
)


def _morse_dissociations(h: float, kT: float, steps: int, n: int, seed: int) -> int:
    rng = np.random.default_rng(seed)

    def potential(x):
        return 0.5 * (1 - np.exp(-x)) ** 2

    q = _boltzmann(potential, kT, -1.0, 5.0, n, rng)
    p = rng.normal(0.0, math.sqrt(kT), n)
    bound = p * p / 2 + potential(q) < 0.5          # below the rim: the exact flow stays bound
    q, p = q[bound], p[bound]
    escaped = _verlet_escapes(lambda x: -(1 - np.exp(-x)) * np.exp(-x),
                              lambda x, v: v * v / 2 + potential(x), q, p, h, steps,
                              escaped=lambda x: (x > 10) | (x < -3))
    return int(escaped.sum())


@pytest.mark.slow
def test_check_is_not_safe_where_thermal_morse_bonds_dissociate_within_the_run():
    """Morse bond D = 1/2 at kT/D = 0.03, velocity Verlet, 10^4 steps, scanned across the
    band below the advised h_max (0.964): wherever the reference resolves dissociations
    (4000 bound starts), check must not exit 0."""
    n = 4000
    safe_but_failing = []
    for h in np.arange(0.945, 0.9626, 0.0025):
        k = _morse_dissociations(float(h), 0.015, 10_000, n, seed=7)
        if _clopper_pearson_lower(k, n) <= 0.002:
            continue
        code, out, err = _check(MORSE_SCENE, "--step", repr(float(h)))
        if code == 0:
            safe_but_failing.append((float(h), k))
    assert not safe_but_failing, (
        f"SAFE at (h, dissociations of {n} in 10^4 steps): {safe_but_failing}")


# --------------------------------------------------------- every verdict is printed (exit 3)

@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck),
          phases=NO_SHRINK)
@given(h=st.floats(1.99, 3.0), g=st.floats(0.05, 0.2))
def test_check_at_temperature_reports_a_step_whose_whole_ensemble_fails(h, g):
    """U = q^2/2 + g q^4 at kT = 1: at h >= 1.99 the reference loses every trajectory, so the
    verdict is UNSAFE, exit 1 (never 3)."""
    k = _quartic_escape_count(g, 1.0, h, 200, 200, seed=1)
    assert k >= 150, k
    code, out, err = _check(_quartic_scene(g, 1.0, 1000, 1.0, 1.0, 1.0), "--step", repr(h))
    assert code == 1, (code, err)


@pytest.mark.slow  # a 2e4-trajectory reference and three checks at temperature
@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck),
          phases=NO_SHRINK)
@given(energy_exp=st.integers(230, 300), frac=st.floats(0.3, 0.6))
def test_check_at_temperature_decides_a_safe_step_at_large_energy_scales(energy_exp, frac):
    """U = E (q^2/2 + 0.1 q^4) at kT = 0.1 E, h = frac / sqrt(E): the dimensionless reference
    loses no trajectory, and the verdict is exit 0 at every scale (never 3)."""
    assert _quartic_escape_count(0.1, 0.1, frac, 2000, 2000, seed=2) == 0
    energy = 10.0 ** energy_exp
    code, out, err = _check(_quartic_scene(0.1, 0.1, 10_000, energy, 1.0, 1.0),
                            "--step", repr(frac / math.sqrt(energy)))
    assert code == 0, (code, err)


# ----------------------------------------------------------------------------- --max-drift

@pytest.mark.slow  # a 2e4-trajectory reference and three checks at temperature
@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck),
          phases=NO_SHRINK)
@given(h=st.floats(1.09, 1.1), log_drift=st.floats(-6, -1))
def test_max_drift_is_not_met_where_thermal_trajectories_blow_up(h, log_drift):
    """A run whose ensemble energy goes to infinity has no finite drift: any max_drift fails."""
    n = 20_000
    k = _quartic_escape_count(0.1, 0.1, h, 200, n, seed=5)
    assert _clopper_pearson_lower(k, n) > 0.002, k
    code, out, err = _check(_quartic_scene(0.1, 0.1, 10_000, 1.0, 1.0, 1.0),
                            "--step", repr(h), "--max-drift", repr(10.0 ** log_drift))
    assert code != 0, (f"SAFE with --max-drift 1e{log_drift:.2f}, but {k} of {n} reference "
                       f"trajectories went non-finite within 200 steps\n{out}")


# ------------------------------------------------------------------ refusals name file and key

@settings(max_examples=4, deadline=None, suppress_health_check=list(HealthCheck),
          phases=NO_SHRINK)
@given(which=st.sampled_from(["morse", "quartic"]), kt_morse=st.floats(0.05, 0.5),
       kt_exp=st.integers(200, 300), in_scene=st.booleans())
def test_a_refused_temperature_names_the_scene_file_and_key(which, kt_morse, kt_exp,
                                                            in_scene):
    """A kT the well cannot confine (Morse at kT/D >= 0.1) or that overflows U: exit 2, one
    line naming the scene file, its Hamiltonian and where kT came from (option or key)."""
    if which == "morse":
        scene, kT = MORSE_SCENE, repr(kt_morse)
    else:
        scene, kT = _quartic_scene(0.1, 0.1, 1000, 1.0, 1.0, 1.0), f"1e{kt_exp}"
    if in_scene:
        scene = "\n".join(f"kT: {kT}" if line.startswith("kT:") else line
                          for line in scene.splitlines()) + "\n"
        code, out, err = _check(scene, "--step", "0.5")
    else:
        code, out, err = _check(scene, "--step", "0.5", "--kT", kT)
    assert code == 2, (code, err)
    line = err.strip()
    assert "\n" not in line, line
    assert "scene.yaml::$.system.hamiltonian" in line, line
    assert ("($.kT)" if in_scene else "--kT") in line, line


def test_a_kT_that_is_no_number_is_quoted_in_its_refusal():
    scene = MORSE_SCENE.replace("kT: 0.015", 'kT: "abc"')
    code, out, err = _check(scene, "--step", "0.5")
    assert code == 2
    assert "scene.yaml::$.kT" in err and "'abc'" in err, err


# ------------------------------------------------------------ the rule a clear step meets

@settings(max_examples=60, deadline=None)
@given(m=st.integers(1, 10 ** 7), data=st.data(),
       threshold=st.floats(1e-7, 0.999, exclude_max=True))
def test_a_step_with_an_observed_failure_is_never_clear(m, data, threshold):
    """Whatever the sample size and the threshold, one failed trajectory makes the step not
    clear; with none, it is clear exactly when the zero-failure bound
    ``1 - 0.05^(1/m)`` (closed form) lies below the threshold."""
    from stepsafe.systems.thermal.bands import judge
    from stepsafe.systems.thermal.trajectories import Outcome

    k = data.draw(st.integers(1, m))
    probe = judge(Outcome(1.0, m, k, 100, 0.0, 0.0, 0.0), threshold)
    assert not probe.clear
    assert probe.verdict in ("band", "failures observed")
    none = judge(Outcome(1.0, m, 0, 100, 0.0, 0.0, 0.0), threshold)
    bound = -math.expm1(math.log(0.05) / m)
    if abs(bound - threshold) > 1e-9 * threshold:
        assert none.clear == (bound < threshold)


@settings(max_examples=60, deadline=None)
@given(threshold=st.floats(1e-6, 0.5))
def test_the_trajectory_count_is_the_fewest_whose_zero_failures_show_the_threshold(
        threshold):
    """``trajectories_for(P)``: zero failures in m show ``P`` (the 95% bound
    ``1 - 0.05^(1/m)``, in 50-digit arithmetic, below P) and in m - 1 do not."""
    import mpmath

    from stepsafe.systems.thermal.bands import trajectories_for

    m = trajectories_for(threshold)
    mpmath.mp.dps = 50

    def bound(n):
        return 1 - mpmath.mpf("0.05") ** (mpmath.mpf(1) / n)

    assert bound(m) < threshold
    assert m == 1 or bound(m - 1) >= threshold
    assert m <= 1.01 * math.log(20) / threshold + 1


def test_a_drift_with_a_failed_trajectory_or_an_overflow_meets_no_tolerance():
    """The drift of an ensemble that lost a trajectory, or whose rate is not finite, is
    unbounded: no max_drift is met by it."""
    from stepsafe.systems.thermal.drift import Drift

    kept = Drift(1.0, 1e-9, 1e-10, 1e-3, 0.1, 1, 500, 0, 100, 0)
    assert kept.bound() == pytest.approx(1.2e-9)
    assert Drift(**{**kept.__dict__, "failed": 1}).bound() == math.inf
    assert Drift(**{**kept.__dict__, "rate": math.inf}).bound() == math.inf
    assert Drift(**{**kept.__dict__, "error": math.nan}).bound() == math.inf


@pytest.mark.parametrize("where, value", [("option", "0"), ("option", "0.5"),
                                          ("option", "nan"), ("scene", "-1"),
                                          ("scene", "1e-9"), ("scene", "abc")])
def test_a_bad_failure_threshold_is_refused_naming_its_key(where, value):
    scene = _quartic_scene(0.1, 0.1, 1000, 1.0, 1.0, 1.0)
    args: tuple[str, ...] = ("--step", "0.5")
    if where == "scene":
        scene += f"max_failure: {value}\n"
    else:
        args += ("--max-failure", value)
    code, out, err = _check(scene, *args)
    assert code == 2, (code, out, err)
    line = err.strip()
    assert "\n" not in line
    assert ("scene.yaml::$.max_failure" in line) if where == "scene" else \
        ("max_failure" in line or "--max-failure" in line), line


def test_check_states_the_failure_threshold_and_the_trajectories_it_needs():
    """The record of a check at temperature states max_failure, the trajectories that can
    show it (ln 20 / P for P = 0.01: 299) and, for the step, the failures and the bound."""
    import json

    code, out, err = _check(_quartic_scene(0.1, 0.1, 1000, 1.0, 1.0, 1.0), "--step", "0.5",
                            "--max-failure", "0.01", "--json")
    assert code == 0, err
    t = json.loads(out)["checks"][0]["thermal"]
    assert t["max_failure"] == 0.01 and t["trajectories"] == 299
    probe = t["minima"][0]["probes"][0]
    assert probe["trajectories"] == 299 and probe["failures"] == 0
    assert probe["upper"] == pytest.approx(1 - 0.05 ** (1 / 299), rel=1e-9)
    assert probe["max_failure"] == 0.01


@pytest.mark.slow  # an analysis at temperature, its scans and confirmations
def test_advice_at_temperature_is_confirmed_on_a_fresh_ensemble(tmp_path):
    """advise(max_failure=P) states the confirmation of its answer: ln(20)/P trajectories
    (P = 0.01: 299) drawn with a seed of their own, none failed at h_max; every step
    rejected above it lost one or more. Against the independent Verlet reference (4000
    Boltzmann starts of the quartic well at the advised step, the run's 1000 steps): a
    failure probability below 1% loses fewer than 2% of them (the chance of 80 or more
    at 1% is below 1e-9)."""
    import stepsafe

    path = tmp_path / "scene.yaml"
    path.write_text(_quartic_scene(0.1, 0.1, 1000, 1.0, 1.0, 1.0))
    r = stepsafe.advise(scene=str(path), max_failure=0.01).record
    t = r["thermal"]
    assert t["max_failure"] == 0.01 and t["trajectories"] == 299
    m = t["minima"][0]
    c = m["confirmation"]
    assert c["trajectories"] == 299 and c["failures"] == 0 and c["seed"] != m["seed"]
    assert c["h"] == pytest.approx(m["h_max"], rel=1e-12)
    assert all(k >= 1 and h > c["h"] for h, k in
               ((x["h"], x["failures"]) for x in c["rejected"]))
    k = _quartic_escape_count(0.1, 0.1, c["h"], 1000, 4000, seed=11)
    assert k / 4000 < 0.02, k
