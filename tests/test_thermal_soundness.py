"""Verdicts at temperature cover every step they speak for: a margin (every step from h to
h/F) is refused by ``check`` at temperature, since a resonance band is an island in h; a
trajectory that leaves the well counts as failed whatever its start's energy.

The references are the test's own: velocity Verlet written here (kick h/2, drift h, kick
h/2) on the Morse bond H = p^2/2 + (1 - e^-q)^2/2 (well depth D = 1/2), from exact Boltzmann
draws of the 1-D well (inverse transform of the distribution function on a fine grid) and
N(0, kT) momenta, with fixed seeds; failure probabilities are bounded by Clopper-Pearson at
95%.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.exceptions import StepsafeError

ROOT = Path(__file__).resolve().parent.parent
MORSE = str(ROOT / "examples" / "morse.yaml")


def _morse_energy(q, p):
    return 0.5 * p * p + 0.5 * np.expm1(-q) ** 2


def _morse_force(q):
    e = np.exp(-q)
    return e * np.expm1(-q)


def _boltzmann(kT: float, count: int, rng: np.random.Generator, lo: float = -1.5,
               hi: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact draws of exp(-H / kT) on [lo, hi] (q by the inverse of the distribution
    function on 400001 points, p ~ N(0, kT))."""
    s = np.linspace(lo, hi, 400001)
    w = np.exp(-(0.5 * np.expm1(-s) ** 2) / kT)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    q = np.interp(rng.random(count), cdf / cdf[-1], s)
    return q, rng.standard_normal(count) * math.sqrt(kT)


def _verlet_escapes(q, p, h, steps, out_at=8.0):
    """Velocity Verlet for every row; a row has left the well when q > ``out_at`` at any
    step (U(8) > 0.9993 D) or when at the end it is unbound outside it (H > D, q > 3).
    Returns the boolean mask of rows that left."""
    q, p = q.copy(), p.copy()
    gone = np.zeros(q.size, dtype=bool)
    f = _morse_force(q)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            p += 0.5 * h * f
            q += h * p
            f = _morse_force(q)
            p += 0.5 * h * f
            gone |= ~(np.isfinite(q) & (q <= out_at))
    unbound = (_morse_energy(q, p) > 0.5) & (q > 3.0)
    return gone | unbound


def _clopper_pearson(k: int, m: int) -> tuple[float, float]:
    from scipy.stats import beta

    lo = 0.0 if k == 0 else float(beta.ppf(0.025, k, m - k + 1))
    hi = 1.0 if k == m else float(beta.ppf(0.975, k + 1, m - k))
    return lo, hi


def _cli(*args: str) -> tuple[int, str, str]:
    from click.testing import CliRunner

    from stepsafe.cli import main

    result = CliRunner().invoke(main, list(args), catch_exceptions=False)
    return result.exit_code, result.stdout, result.stderr


# --- a margin at temperature ------------------------------------------------------------


def test_a_band_lies_inside_the_steps_a_margin_stands_for_so_one_ensemble_cannot_judge_them():
    """The cold Morse bond (kT = 3e-4, 10^4 steps) at h = 1.41421, just inside the 4:1
    band, dissociates in most of the test's own runs while h / 0.95 loses none: the steps
    a margin 0.95 stands for are not all judged by a run at h / F, and check refuses the
    margin there instead of calling h safe."""
    rng = np.random.default_rng(2024)
    q, p = _boltzmann(3e-4, 300, rng, -0.5, 1.0)
    h = 1.41421
    inside = _verlet_escapes(q, p, h, 10_000, out_at=4.0)
    beside = _verlet_escapes(q, p, h / 0.95, 10_000, out_at=4.0)
    assert _clopper_pearson(int(inside.sum()), q.size)[0] > 0.5
    assert not beside.any()
    with pytest.raises(StepsafeError, match="margin"):
        stepsafe.check(scene=MORSE, h=h, kT=3e-4, steps=10_000, margin=0.95)


@settings(max_examples=5, deadline=None)
@given(margin=st.floats(1e-6, 1.0, exclude_max=True), h=st.floats(1e-3, 3.0),
       kT=st.floats(1e-4, 0.02))
def test_check_never_judges_a_margin_below_one_at_temperature(margin, h, kT):
    with pytest.raises(StepsafeError, match="margin"):
        stepsafe.check(scene=MORSE, h=h, kT=kT, steps=100, margin=margin)


def test_the_command_line_refuses_a_margin_at_temperature_in_one_line_with_exit_2(tmp_path):
    code, out, err = _cli("check", MORSE, "--kT", "0.0003", "--steps", "10000", "--step",
                          "1.41421", "--margin", "0.95")
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "--margin" in err
    scene = tmp_path / "morse.yaml"
    scene.write_text(Path(MORSE).read_text() + "margin: 0.9\n")
    code, out, err = _cli("check", str(scene), "--step", "1.41421")
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and f"{scene}::$.margin" in err


def test_a_harmonic_system_keeps_its_margin_at_temperature():
    """A linear system's answer at temperature is the 0 K one, where failure grows with
    the step and h / F is the worst of the steps the margin stands for: Verlet on omega =
    1 is preserved for z < 2."""
    assert stepsafe.check("verlet", beta=[1.0], h=1.5, margin=0.9, kT=0.1, steps=100).safe
    assert not stepsafe.check("verlet", beta=[1.0], h=1.85, margin=0.9, kT=0.1,
                              steps=100).safe


# --- a trajectory that leaves the well fails ----------------------------------------------


def _reference_escapes(h: float, seeds=(11, 12), count: int = 4000, kT: float = 0.0357,
                       steps: int = 50) -> tuple[int, int]:
    """Bonds that leave the Morse well in the test's own runs: (left, trajectories)."""
    left = total = 0
    for seed in seeds:
        q, p = _boltzmann(kT, count, np.random.default_rng(seed))
        left += int(_verlet_escapes(q, p, h, steps).sum())
        total += count
    return left, total


def _scene(tmp_path: Path, energy: float = 1.0, length: float = 1.0, mass: float = 1.0) -> str:
    """The Morse bond with its energy, length and mass scaled (time unit
    ``length sqrt(mass / energy)``)."""
    path = tmp_path / f"morse-{energy:g}-{length:g}-{mass:g}.yaml"
    momentum = math.sqrt(mass * energy)
    path.write_text("method: verlet\nsystem:\n  hamiltonian: "
                    f"\"p**2/(2*{mass!r}) + {energy!r}*(1 - exp(-q/{length!r}))**2/2\"\n"
                    f"  box: {{q: [{-length!r}, {5 * length!r}], "
                    f"p: [{-momentum!r}, {momentum!r}]}}\n")
    return str(path)


def test_a_bond_that_leaves_the_well_in_a_short_run_is_a_failure():
    """kT/D = 0.071, 50 steps at h = 0.87: the test's own runs lose about 0.4% of the bonds
    (they leave the well: their energy passes the well depth out beyond it), whose
    ceiling relative to the start's energy and distance ceiling a short run does not
    reach; check's 2995 trajectories see as many and say UNSAFE for max_failure 0.001."""
    left, total = _reference_escapes(0.87)
    lo, hi = _clopper_pearson(left, total)
    assert lo > 0.002  # well above max_failure: 2995 trajectories see ~10
    r = stepsafe.check(scene=MORSE, h=0.87, kT=0.0357, steps=50)
    assert not r.safe
    (probe,) = r.thermal["minima"][0]["probes"]
    k, m = probe["failures"], probe["trajectories"]
    assert m == 2995 and probe["h"] == 0.87
    # the same probability: stepsafe's count within the two-sided 99.9% range a binomial of
    # the reference's fraction gives
    from scipy.stats import binom

    assert binom.ppf(0.0005, m, lo) <= k <= binom.ppf(0.9995, m, hi)


def test_a_step_whose_bonds_stay_bound_is_clear_of_escapes():
    """At h = 0.5 none of the test's own 8000 bonds leaves in 50 steps, nor does any of
    check's: the escape test counts no bound trajectory."""
    assert _reference_escapes(0.5)[0] == 0
    r = stepsafe.check(scene=MORSE, h=0.5, kT=0.0357, steps=50)
    assert r.safe
    assert r.thermal["minima"][0]["probes"][0]["failures"] == 0


@pytest.mark.slow  # one check per example, about 1.5 s of CPU each
@settings(max_examples=6, deadline=None)
@given(log_energy=st.floats(-100.0, 100.0), log_length=st.floats(-100.0, 100.0),
       log_mass=st.floats(-50.0, 50.0))
def test_escapes_are_counted_at_every_scale(tmp_path_factory, log_energy, log_length,
                                            log_mass):
    """The bond with energy, length and mass scaled by powers of ten loses its escaping
    trajectories as the bond in its own units does (the reference: about 0.4% at h =
    0.87, none at 0.5)."""
    energy, length, mass = 10.0 ** log_energy, 10.0 ** log_length, 10.0 ** log_mass
    scene = _scene(tmp_path_factory.mktemp("scaled"), energy, length, mass)
    unit = length * math.sqrt(mass / energy)
    kT = 0.0357 * energy
    hot = stepsafe.check(scene=scene, h=0.87 * unit, kT=kT, steps=50)
    assert not hot.safe
    assert hot.thermal["minima"][0]["probes"][0]["failures"] >= 4
    cool = stepsafe.check(scene=scene, h=0.5 * unit, kT=kT, steps=50)
    assert cool.safe


def _bond_with_spectators(tmp_path: Path, omegas: list[float]) -> str:
    """The Morse bond q_1 beside harmonic coordinates of the given frequencies (separable:
    the bond's dynamics is the bond's alone)."""
    n = 1 + len(omegas)
    springs = "".join(f" + {0.5 * w * w!r}*q[{i + 2}]**2" for i, w in enumerate(omegas))
    kinetic = " + ".join(f"p[{i + 1}]**2/2" for i in range(n))
    path = tmp_path / f"morse-{n}.yaml"
    path.write_text("method: verlet\nsystem:\n"
                    f"  hamiltonian: \"{kinetic} + (1 - exp(-q[1]))**2/2{springs}\"\n"
                    f"  q: \"q[1..{n}]\"\n  p: \"p[1..{n}]\"\n"
                    "  box: {q: [-1, 5], p: [-1, 1]}\n")
    return str(path)


def test_a_bond_that_leaves_its_well_beside_other_coordinates_is_a_failure(tmp_path):
    """The bond beside a slow harmonic coordinate (omega = 0.5), 50 steps at h = 0.85:
    the test's own runs of the bond lose 0.13-0.36% (95%) of it, more than max_failure
    0.001; check's whole-system ensemble sees the bonds leave and says UNSAFE; at h = 0.5
    none leaves in either."""
    left, total = _reference_escapes(0.85)
    assert _clopper_pearson(left, total)[0] > 0.001
    scene = _bond_with_spectators(tmp_path, [0.5])
    r = stepsafe.check(scene=scene, h=0.85, kT=0.0357, steps=50)
    assert not r.safe
    assert r.thermal["minima"][0]["probes"][0]["failures"] >= 3
    assert _reference_escapes(0.5)[0] == 0
    assert stepsafe.check(scene=scene, h=0.5, kT=0.0357, steps=50).safe


@pytest.mark.slow  # one check of a Langevin-drawn system per example
@settings(max_examples=4, deadline=None)
@given(omegas=st.lists(st.floats(0.2, 0.9), min_size=1, max_size=3))
def test_escapes_are_counted_beside_any_spectators(tmp_path_factory, omegas):
    scene = _bond_with_spectators(tmp_path_factory.mktemp("spectators"), omegas)
    r = stepsafe.check(scene=scene, h=0.87, kT=0.0357, steps=50)
    assert not r.safe
    assert r.thermal["minima"][0]["probes"][0]["failures"] >= 3


# --- a step limited by the drift ----------------------------------------------------------


def _drift_limited(steps: int, max_drift: float) -> tuple[float, dict, dict]:
    r = stepsafe.advise(scene=MORSE, kT=0.015, steps=steps, max_drift=max_drift)
    assert r.h_max_limited_by == "drift"
    (m,) = r.thermal["minima"]
    return r.h_max, m["confirmation"], m["drift"]


def _assert_confirmed_and_checked(steps: int, max_drift: float) -> float:
    """advise's drift-limited step is the one its fresh ensemble ran: all of its
    trajectories_for(max_failure) trajectories clear and the drift bound within
    max_drift there; check of that step (the same initial conditions) agrees."""
    from stepsafe.systems.thermal.bands import trajectories_for

    h, confirmation, drift = _drift_limited(steps, max_drift)
    m = trajectories_for(1e-3)
    assert confirmation["h"] == h and confirmation["trajectories"] == m
    assert confirmation["failures"] == 0 and confirmation["steps"] == steps
    assert drift["h"] == h and drift["trajectories"] == m and drift["failed"] == 0
    assert drift["seed"] == confirmation["seed"]
    assert abs(drift["rate"]) + 2.0 * drift["error"] <= max_drift
    c = stepsafe.check(scene=MORSE, h=h, kT=0.015, steps=steps, max_drift=max_drift)
    assert c.safe
    assert c.thermal["minima"][0]["drift"]["rate"] == drift["rate"]
    # the test's own Verlet from its own exact draws loses none of as many bonds there
    q, p = _boltzmann(0.015, m, np.random.default_rng(7))
    assert not _verlet_escapes(q, p, h, steps).any()
    return h


def test_a_step_limited_by_the_drift_is_confirmed_on_the_fresh_ensemble_and_checked_safe():
    _assert_confirmed_and_checked(500, 2e-9)


@pytest.mark.slow  # two analyses over 10^4 steps with a drift bisection on 2995 trajectories
def test_the_drift_limit_of_a_ten_thousand_step_run_is_confirmed_and_checked_safe():
    """kT/D = 0.03, 10^4 steps, max_drift 1e-10 (near the drift's own noise): the step
    given is confirmed and checked safe; 0.7, inside the range a bisection on 500
    trajectories gave, is not in it."""
    assert _assert_confirmed_and_checked(10_000, 1e-10) < 0.7


# --- the range advise states is the range check judges -----------------------------------


@settings(max_examples=200, deadline=None)
@given(length=st.floats(1e-200, 1e200), follow=st.integers(2, 10 ** 8))
def test_the_steps_advise_states_from_are_exactly_those_whose_runs_are_followed(length,
                                                                                 follow):
    """``h_min`` (the lower end of advise's range for a run given by its length) is the
    smallest step check does not refuse as a run longer than followed: every step from it
    is followed, and a step 1e-9 below it is not."""
    from stepsafe.api.temperature import Request
    from stepsafe.api.thermal import followed, followed_from

    req = Request(1.0, None, None, length, None, follow_steps=follow, run_key="--length")
    low = followed_from(req)
    for h in (low, low * (1 + 1e-12), low * 1.5, low * 1e3):
        followed(req, h)
    with pytest.raises(StepsafeError, match="more than the thermal trajectories follow"):
        followed(req, low * (1 - 1e-9))
    assert followed_from(Request(1.0, None, None, None, 100.0)) is None


@pytest.mark.slow  # an analysis at 300 K and two checks
def test_advise_states_no_step_whose_run_is_longer_than_followed():
    r = stepsafe.advise(scene=str(ROOT / "examples" / "morse-300K.yaml"))
    (low, high), = r.safe_h
    assert low == r.thermal["h_min"] > 0 and high == r.h_max
    scene = str(ROOT / "examples" / "morse-300K.yaml")
    assert stepsafe.check(scene=scene, h=low).safe
    with pytest.raises(StepsafeError, match="more than the thermal trajectories follow"):
        stepsafe.check(scene=scene, h=low * (1 - 1e-6))


# --- a curved valley is drawn -------------------------------------------------------------


def test_a_curved_valley_is_drawn_from_chains_that_start_inside_it():
    """U = (1 - e^-(x - 3y^2))^2/2 + 0.005 y^2 at kT = 0.003: a Morse bond along the curved
    s = x - 3y^2 beside a soft y, confined. The harmonic approximation at the minimum
    (Hessian diag(1, 0.01)) draws y ~ 0.55 and so s ~ -0.9, deep in the wall; the chains
    start inside the valley instead, and their draws match the exact ones (with s as a
    coordinate the density factorises: s from the Morse Boltzmann distribution, y ~
    N(0, kT/0.01), unit Jacobian)."""
    from stepsafe.systems.thermal.potential import from_callables
    from stepsafe.systems.thermal.sampling import draw

    def energy(q):
        x, y = q[:, 0], q[:, 1]
        return 0.5 * np.expm1(-(x - 3 * y * y)) ** 2 + 0.005 * y * y

    def gradient(q):
        x, y = q[:, 0], q[:, 1]
        s = x - 3 * y * y
        d = -np.exp(-s) * np.expm1(-s)
        return np.stack([d, -6 * y * d + 0.01 * y], 1)

    kT = 0.003
    pot = from_callables(energy, gradient, [1.0, 1.0], minimum=[0.0, 0.0])
    found = draw(pot, kT, 1024, 0)
    y = found.q[:, 1]
    s = found.q[:, 0] - 3 * y * y
    exact_s, _ = _boltzmann(kT, 200_000, np.random.default_rng(3), -1.0, 8.0)
    assert np.std(s) == pytest.approx(np.std(exact_s), rel=0.1)
    assert np.mean(s) == pytest.approx(np.mean(exact_s), abs=0.01)
    assert np.mean(y * y) == pytest.approx(kT / 0.01, rel=0.25)  # 64 chains


# --- refusals say what can be done and why ------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(steps=st.floats(1.0000001e8, 1e300))
def test_a_run_beyond_what_can_be_followed_is_told_to_be_shorter_only(steps):
    """No advice to follow more steps than follow_steps accepts (1e8)."""
    from stepsafe.api.temperature import Request
    from stepsafe.api.thermal import followed

    req = Request(1.0, None, None, None, steps, run_key="--steps")
    with pytest.raises(StepsafeError) as info:
        followed(req, 0.5)
    message = info.value.message
    assert "give --follow-steps" not in message and "give a shorter run (--steps)" in message
    assert len(message) < 400


@pytest.mark.parametrize("kT", [0.5, 1.3575, 3.0])
def test_a_potential_that_falls_below_its_minimum_nearby_is_refused_as_not_confined(
        tmp_path, kT):
    """U = q^2/2 - 0.3 (1 - e^-q)^2 falls without bound as q -> -inf: within a few thermal
    amplitudes of its minimum at these kT U drops below U(0), and the refusal says the
    distribution is not confined (its steep differences are not rounding)."""
    scene = tmp_path / "falls.yaml"
    scene.write_text("method: verlet\nsystem:\n  hamiltonian: \"p**2/2 + q**2/2 - "
                     "0.3*(1 - exp(-q))**2\"\n  box: {q: [-3, 10], p: [-1, 1]}\n")
    with pytest.raises(StepsafeError, match="not confined"):
        stepsafe.check(scene=str(scene), h=1.3, kT=kT, steps=2)


# --- a draw over several basins -----------------------------------------------------------


def test_the_upper_minimum_of_a_tilted_double_well_is_judged_by_what_its_runs_do(tmp_path):
    """U = (q^2 - 1)^2/4 + 0.05 q at kT = 0.02 (barriers 10 and 15 kT, below the 40 kT
    drawn): the draws for either minimum cover both basins, most of them in the lower one.
    The test's own Verlet from exact draws over [-2, 2] loses no trajectory (|q| > 3 or
    not finite) in 1000 steps at h = 0.3; check at the upper minimum finds none either
    (the growth test measures energies from the lowest U of the region drawn, not from the
    upper minimum's U, which most starts lie below)."""
    rng = np.random.default_rng(5)
    s = np.linspace(-2.0, 2.0, 400001)
    w = np.exp(-((s * s - 1.0) ** 2 / 4 + 0.05 * s) / 0.02)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    q = np.interp(rng.random(2995), cdf / cdf[-1], s)
    p = rng.standard_normal(2995) * math.sqrt(0.02)
    with np.errstate(all="ignore"):
        for _ in range(1000):
            p -= 0.15 * ((q * q - 1.0) * q + 0.05)
            q += 0.3 * p
            p -= 0.15 * ((q * q - 1.0) * q + 0.05)
    assert np.all(np.isfinite(q) & (np.abs(q) <= 3.0))
    scene = tmp_path / "tilt.yaml"
    scene.write_text("method: verlet\nkT: 0.02\nsteps: 1000\nsystem:\n  hamiltonian: "
                     "\"p**2/2 + (q**2 - 1)**2/4 + 0.05*q\"\n  box: {q: [-2, 2], p: [-1, 1]}\n")
    r = stepsafe.check(scene=str(scene), h=0.3)
    assert r.safe
    assert len(r.thermal["minima"]) == 2
    assert all(m["probes"][0]["failures"] == 0 for m in r.thermal["minima"])
