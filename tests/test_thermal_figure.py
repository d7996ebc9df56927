"""The Morse figure of the guide "Safe at temperature" (``docs/figures/morse-thermal.png``)
is drawn from ``docs/figures/morse-thermal.json`` alone (``docs/figures/morse_thermal.py``);
these tests check that data, not the pixels:

* it is what the analysis reports today: ``advise`` gives the same h_max, criterion, linear
  limit at temperature and bands (edges within the 2% a band edge may move by on another
  machine, a step of the scan's grid), ``region`` the same resonance points and 0 K limit,
  and the check's verdicts along the curve agree with them;
* its failure fractions are what velocity Verlet written here sees from its own exact
  Boltzmann draws of the bond (2000 trajectories, as many steps as the check ran): between
  the fraction that escapes (energy past 0.9 D, or not finite) and the fraction that
  escapes or whose energy grows past ``4 rho0^2`` times its start (``rho0 = 1 / (1 -
  z^2/4)``, Verlet's invariant ellipse at omega_0), within 4 binomial standard errors plus
  2 of 500; a step the figure shows SAFE loses no more than the 1% threshold allows."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from thermal_support import boltzmann_1d, morse_energy, morse_force

import stepsafe
from stepsafe.systems.thermal.bands import clopper_pearson

ROOT = Path(__file__).resolve().parent.parent
DATA = json.loads((ROOT / "docs" / "figures" / "morse-thermal.json").read_text())
SCENE = str(ROOT / DATA["scene"])
PANELS = {panel["kT"]: panel for panel in DATA["panels"]}
#: The test's own trajectories.
OWN = 2000
#: Energy past which a Morse trajectory of H = p^2/2 + (1 - e^-q)^2/2 counts as escaped.
ESCAPE = 0.9 * DATA["D"]
#: A band edge may move by a step of the scan's grid on another machine.
EDGE = 0.02


def test_figure_is_of_the_guide_s_bond_and_temperatures():
    assert DATA["scene"] == "examples/morse.yaml" and DATA["method"] == "verlet"
    assert (DATA["D"], DATA["omega_0"], DATA["run_steps"]) == (0.5, 1.0, 10000)
    assert sorted(p["kT_over_D"] for p in DATA["panels"]) == [0.006, 0.03]
    # as the guide says: a band near 5:1 sets h_max; in the hotter panel the 6:1 band's
    # failures, which the confirmation's fresh ensemble still sees below its edge
    assert PANELS[0.003]["limited_by"].startswith("resonance band 5:1")
    assert PANELS[0.015]["limited_by"].startswith("resonance band")
    hot = PANELS[0.015]
    assert [b["name"] for b in hot["bands"]][0] == "6:1"
    assert hot["h_max"] < hot["bands"][0]["lower"]
    assert "![" in (ROOT / "docs" / "guides" / "thermal.md").read_text() and \
        "figures/morse-thermal.png" in (ROOT / "docs" / "guides" / "thermal.md").read_text()
    assert (ROOT / "docs" / "figures" / "morse-thermal.png").read_bytes()[:8] == \
        b"\x89PNG\r\n\x1a\n"


def test_resonance_points_and_0K_limit_are_region_s():
    osc = stepsafe.region("verlet", model="oscillator").to_dict()["models"]["oscillator"]
    assert DATA["z_star"] == osc["first_boundary"] == pytest.approx(2.0, rel=1e-13)
    shown = {r["name"]: r["z"] for r in DATA["resonances"]}
    for r in osc["nonlinear_resonances"]:
        n, m = r["n"], r["m"]
        assert shown[r["resonance"]] == r["z"] == pytest.approx(2 * math.sin(math.pi * m / n),
                                                                rel=1e-13)
    assert {"4:1", "3:1"} <= set(shown)


@pytest.mark.slow  # an analysis at temperature and two checks, over the run's 1e4 steps
@pytest.mark.parametrize("kT", sorted(PANELS))
def test_figure_shows_what_the_analysis_reports(kT):
    """advise at kT over 1e4 steps gives the panel's h_max (within a grid step), its
    criterion, linear limit and bands; check gives the curve's verdict, trajectories and
    steps at two of its steps, and its failures but for a few a different rounding may
    tip; along the curve every step up to h_max is SAFE,
    every step at or above the linear limit at temperature UNSAFE, and so is every step
    inside a band."""
    panel = PANELS[kT]
    advice = stepsafe.advise(scene=SCENE, kT=kT, steps=DATA["run_steps"]).to_dict()
    t = advice["thermal"]
    m = t["minima"][0]
    assert t["limited_by"] == panel["limited_by"]
    assert abs(t["h_max"] - panel["h_max"]) <= EDGE * panel["h_max"]
    assert m["h_linear"] == pytest.approx(panel["h_linear"], rel=1e-6)
    bands = [b for sc in m["scans"] for b in sc["bands"]]
    assert [b["name"] for b in bands] == [b["name"] for b in panel["bands"]]
    for now, shown in zip(bands, panel["bands"]):
        for side in ("lower", "upper"):
            if shown[side] is None:
                assert now[side] is None
            else:
                assert abs(now[side]["clear"] - shown[side]) <= EDGE * shown[side]
    for z in (1.2, 1.5):  # the check's own ensemble today, at two steps of the curve
        point = next(p for p in panel["curve"] if p["z"] == z)
        now = stepsafe.check(scene=SCENE, h=z, kT=kT, steps=DATA["run_steps"]).to_dict()
        thermal = now["checks"][0]["thermal"]
        (probe,) = thermal["minima"][0]["probes"]
        assert (thermal["safe"], probe["trajectories"], probe["steps"]) == \
            (point["safe"], point["trajectories"], point["steps"])
        # the same draws: only trajectories a rounding can tip (a chaotic edge) may differ
        k = point["failures"]
        m = point["trajectories"]
        assert abs(probe["failures"] - k) <= 4 * math.sqrt(k * (1 - k / m)) + 2
    for point in panel["curve"]:
        z = point["z"]
        if z <= panel["h_max"]:
            assert point["safe"], z
        if z >= panel["h_linear"]:
            assert not point["safe"], z
        for b in panel["bands"]:
            lo = b["lower"] if b["lower"] is not None else panel["scanned"][0]
            hi = b["upper"] if b["upper"] is not None else panel["scanned"][1]
            if lo < z < hi:
                assert not point["safe"], z


def _own_fractions(kT, z, steps, seed=13):
    """The escaped and the grown fractions (module docstring) of the test's own velocity
    Verlet on the bond, from its own exact Boltzmann draws."""
    rng = np.random.default_rng(seed)
    q = boltzmann_1d(morse_energy, kT, OWN, rng, -1.5, 12.0)
    p = rng.standard_normal(OWN) * math.sqrt(kT)
    H0 = morse_energy(q) + p * p / 2
    rho0 = 1 / (1 - min(z, 1.999) ** 2 / 4)
    escaped = np.zeros(OWN, dtype=bool)
    grown = np.zeros(OWN, dtype=bool)
    f = morse_force(q)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            p = p + 0.5 * z * f
            q = q + z * p
            f = morse_force(q)
            p = p + 0.5 * z * f
            H = morse_energy(q) + p * p / 2
            escaped |= ~(H < ESCAPE)
            grown |= ~(H <= 4 * rho0 ** 2 * H0)
    return float(escaped.mean()), float((escaped | grown).mean())


def _tolerance(p, m):
    p = min(max(p, 0.25 / OWN), 1 - 0.25 / OWN)
    return 4 * math.sqrt(p * (1 - p) * (1 / m + 1 / OWN)) + 2 / m


def _agrees(point, kT):
    m = point["trajectories"]
    shown = point["failures"] / m
    escaped, grown = _own_fractions(kT, point["z"], point["steps"])
    assert escaped - _tolerance(escaped, m) <= shown <= grown + _tolerance(grown, m), \
        (point, escaped, grown)
    if point["safe"]:
        assert grown <= 0.01 + 2.3 * math.sqrt(0.01 * 0.99 / OWN), (point, grown)
    if clopper_pearson(round(grown * OWN), OWN)[0] > 0.01:
        assert not point["safe"], (point, grown)
    return escaped


#: Steps checked in the default run: a safe one, near 5:1 and 6:1, the issue's steps.
CHOSEN = (0.8, 1.0, 1.2, *DATA["measured"])


@pytest.mark.parametrize("kT", sorted(PANELS))
def test_figure_fractions_at_chosen_steps_match_the_tests_own_verlet(kT):
    """The issue's steps (2% below 3:1, 0.5% below 4:1, z = 1.5) are UNSAFE in both panels,
    and the test's own run loses more than the 1% threshold at each (most of its
    trajectories 2% below 3:1 and 0.5% below 4:1 at kT/D = 0.006); z = 0.8 is SAFE and
    the test's own run loses none there."""
    points = {p["z"]: p for p in PANELS[kT]["curve"]}
    seen = {z: _agrees(points[z], kT) for z in CHOSEN}
    assert points[0.8]["safe"] and seen[0.8] == 0.0
    for z in DATA["measured"]:
        assert not points[z]["safe"]
        assert clopper_pearson(round(seen[z] * OWN), OWN)[0] > 0.01, (z, seen[z])
    if kT == 0.003:
        assert seen[1.40784] > 0.5 and seen[1.70056] > 0.5


@pytest.mark.slow  # every third step of the curves, 2000 trajectories each
@pytest.mark.parametrize("kT", sorted(PANELS))
def test_figure_fractions_along_the_curve_match_the_tests_own_verlet(kT):
    for point in PANELS[kT]["curve"][::3]:
        _agrees(point, kT)
