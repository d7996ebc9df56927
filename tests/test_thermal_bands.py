"""Resonance bands at amplitude: failure fractions of the method's own map from thermal
initial conditions against integrations written in the test (velocity Verlet and PEFRL on
Morse, cubic and quartic oscillators, with their own Boltzmann draws), the verdicts the
issue measured on Morse bonds, the binomial bounds, and one step of many h at once."""

from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import method
from thermal_support import (
    boltzmann_1d,
    cubic,
    morse,
    morse_energy,
    morse_force,
    pefrl,
    quartic,
    verlet,
)

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal import trajectories
from stepsafe.systems.thermal.bands import (
    band_failures,
    clopper_pearson,
    grid,
    judge,
    probe,
    scan,
)
from stepsafe.systems.thermal.limit import thermal_check
from stepsafe.systems.thermal.trajectories import run, thermal_start

STEPS = 2000


@pytest.mark.parametrize("k, m", [(0, 500), (1, 500), (7, 300), (300, 300), (40, 41)])
def test_clopper_pearson_bounds_solve_the_binomial_tail_equations(k, m):
    """P(X <= k | upper) = 1 - c and P(X >= k | lower) = 1 - c, summed at 30 digits."""
    mp.mp.dps = 30
    lower, upper = clopper_pearson(k, m, 0.95)

    def cdf(j, p):
        return mp.fsum(mp.binomial(m, i) * mp.mpf(p) ** i * (1 - mp.mpf(p)) ** (m - i)
                       for i in range(j + 1))

    if k < m:
        assert float(cdf(k, upper)) == pytest.approx(0.05, rel=1e-8)
    else:
        assert upper == 1.0
    if k > 0:
        assert float(1 - cdf(k - 1, lower)) == pytest.approx(0.05, rel=1e-8)
    else:
        assert lower == 0.0


def test_many_steps_at_once_equal_each_step_alone_bit_for_bit():
    pot = morse()
    start = thermal_start(pot, 0.006, 64, seed=2)
    hs = [0.8, 1.40784, 1.70056]
    together = run(method("verlet"), pot, start, hs, 300, [3.0, 3.0, 3.0])
    alone = [run(method("verlet"), pot, start, [h], 300, [3.0])[0] for h in hs]
    assert together == alone


@pytest.mark.parametrize("m, threshold, confidence", [
    (1, 0.01, 0.95), (10, 0.01, 0.95), (300, 0.01, 0.95), (500, 0.01, 0.95),
    pytest.param(2995, 0.01, 0.95, marks=pytest.mark.slow), (299, 0.001, 0.99), (50, 0.3, 0.9),
    (5, 0.9, 0.95)])
def test_band_failures_are_the_fewest_whose_binomial_tail_at_the_threshold_is_rare(
        m, threshold, confidence):
    """``band_failures`` is the least k with ``P(X >= k | p = threshold) < 1 - confidence``
    (the lower bound above the threshold), summed at 30 digits; None when no k is."""
    mp.mp.dps = 30
    t = mp.mpf(threshold)

    def tail(k):
        return mp.fsum(mp.binomial(m, i) * t ** i * (1 - t) ** (m - i) for i in range(k, m + 1))

    alpha = 1 - mp.mpf(confidence)
    own = next((k for k in range(1, m + 1) if tail(k) < alpha), None)
    assert band_failures(m, threshold, confidence) == own
    if own is not None:
        assert clopper_pearson(own, m, confidence)[0] > threshold


@pytest.mark.parametrize("kT, hs", [(0.03, [0.8, 1.40784, 1.70056]), (0.006, [1.9, 1.5])])
def test_a_run_in_blocks_equals_the_run_in_one_block_bit_for_bit(monkeypatch, kT, hs):
    """Rows run block by block (7 rows a block here) follow the trajectories of one block:
    the same failures, drift, its error and fluctuation to the last bit."""
    pot = morse()
    start = thermal_start(pot, kT, 64, seed=3)
    monkeypatch.setattr(trajectories, "BLOCK_VALUES", 10 ** 9)
    whole = run(method("verlet"), pot, start, hs, 300, _verlet_rho(hs))
    monkeypatch.setattr(trajectories, "BLOCK_VALUES", 7)
    blocks = run(method("verlet"), pot, start, hs, 300, _verlet_rho(hs))
    assert blocks == whole
    assert any(o.failures for o in whole)  # (the test can fail: rows are dropped)


def test_a_run_stopped_at_its_failures_sees_failures_of_the_full_run(monkeypatch):
    """A run stopped at its s-th failure counts s failures or more (those of its last
    step), each one of the full run's, by a step the full run reaches; a run with no
    failure is not stopped and equals the full run."""
    pot = morse()
    start = thermal_start(pot, 0.006, 200, seed=5)
    monkeypatch.setattr(trajectories, "BLOCK_VALUES", 16)
    for h, stop in ((1.70056, 1), (1.70056, 5), (1.5, 3)):
        full, = run(method("verlet"), pot, start, [h], 400, _verlet_rho([h]))
        cut, = run(method("verlet"), pot, start, [h], 400, _verlet_rho([h]),
                   stop_failures=stop)
        assert full.failures >= stop, full
        # (rows failing at the same step as the s-th all count)
        assert stop <= cut.failures <= full.failures and 1 <= cut.steps <= 400
        assert judge(cut).verdict != "clear" and math.isnan(cut.drift)
    full, = run(method("verlet"), pot, start, [0.5], 400, _verlet_rho([0.5]))
    cut, = run(method("verlet"), pot, start, [0.5], 400, _verlet_rho([0.5]), stop_failures=1)
    assert full.failures == 0 and cut == full


def test_rows_run_first_change_no_value_of_a_full_run(monkeypatch):
    """A run with some rows first (blocks of 5 rows) has the failures, the failed rows,
    the drift, its error and fluctuation of the run in the start's order, bit for bit; a
    run stopped at its first failure with the failed rows first stops in the first
    block, at a row the full run lost."""
    pot = morse()
    start = thermal_start(pot, 0.006, 120, seed=8)
    monkeypatch.setattr(trajectories, "BLOCK_VALUES", 5)
    hs = [1.40784, 1.2]
    plain = run(method("verlet"), pot, start, hs, 300, _verlet_rho(hs))
    lost = plain[0].failed
    assert len(lost) == plain[0].failures >= 2  # (the test can fail: rows are lost)
    first = [lost[-1], 7, lost[0], 100]
    assert run(method("verlet"), pot, start, hs, 300, _verlet_rho(hs), first=first) == plain
    cut, = run(method("verlet"), pot, start, hs[:1], 300, _verlet_rho(hs[:1]),
               stop_failures=1, first=lost[::-1])
    assert cut.failed and set(cut.failed) <= set(lost[-5:])
    for bad in ([0, 0], [120], [-1]):
        with pytest.raises(StepsafeError, match="distinct rows of the 120 starts"):
            run(method("verlet"), pot, start, hs, 300, _verlet_rho(hs), first=bad)


def test_bisection_points_stopped_at_a_band_keep_the_full_runs_verdicts():
    """Every point of a bisected scan (stopped once its failures make a band) has the
    verdict of the ensemble run in full at that step."""
    pot = morse()
    start = thermal_start(pot, 0.03, 300, seed=7)
    got = scan(method("verlet"), pot, start, [0.7, 1.3], 300, _verlet_rho, bisections=3)
    # (the test can fail: a bisection point is a band, stopped before the run's end)
    assert any(p.verdict == "band" and p.steps < 300 for p in got.probes)
    for p in got.probes:
        full, = run(method("verlet"), pot, start, [p.h], 300, _verlet_rho([p.h]),
                    energy_every=8)
        assert judge(full).verdict == p.verdict, (p, full)
        assert p.failures <= full.failures


def _own_fractions(step, energy, force, kT, hs, rho, lo, hi, m=4000, seed=1):
    """Failure fractions by the test's own integrator and Boltzmann draws: failed when a
    state is not finite, |q| exceeds 10 sqrt(rho) times the start's largest |q| (10 times
    for an infinite rho), or the energy exceeds 4 rho^2 times the initial one (the
    conventions of the scan)."""
    rng = np.random.default_rng(seed)
    q0 = boltzmann_1d(energy, kT, m, rng, lo, hi)
    p0 = rng.standard_normal(m) * math.sqrt(kT)
    E0 = energy(q0) + p0 * p0 / 2
    out = []
    for h, r in zip(hs, rho):
        bound = 10 * np.max(np.abs(q0)) * (math.sqrt(r) if math.isfinite(r) else 1.0)

        def fail(q, p, r=r, bound=bound):
            return ~(np.abs(q) <= bound) | ~(energy(q) + p * p / 2 <= 4 * r * r * E0)
        out.append(float(step(force, q0.copy(), p0.copy(), h, STEPS, fail).mean()))
    return np.array(out)


def _agree(p_a, m_a, p_b, m_b):
    """Two failure fractions agree within 4 binomial standard errors (plus 2/m_a)."""
    p = 0.5 * (p_a + p_b)
    return np.abs(p_a - p_b) <= 4 * np.sqrt(p * (1 - p) * (1 / m_a + 1 / m_b)) + 2 / m_a


def _verlet_rho(h, omega=1.0):
    z = np.minimum(np.asarray(h) * omega, 1.999)
    return 1 / (1 - z * z / 4)


@pytest.mark.parametrize("kT", [0.006, 0.03])
def test_morse_failure_fractions_match_an_independent_verlet_integration(kT):
    pot = morse()
    hs = np.array([0.8, 1.2, 1.40784, 1.5, 1.70056, 1.9])
    rho = _verlet_rho(hs)
    start = thermal_start(pot, kT, 500, seed=4)
    got = scan(method("verlet"), pot, start, hs, STEPS, _verlet_rho, bisections=0)
    mine = np.array([p.probability for p in got.probes])
    own = _own_fractions(verlet, morse_energy, morse_force, kT, hs, rho, -1.5, 12.0)
    assert np.all(_agree(mine, 500, own, 4000)), (mine, own)
    assert own[hs == 1.70056][0] > 0.5  # the test can fail: the band is there


@pytest.mark.slow
@pytest.mark.parametrize("kind, coefficient, kT", [
    ("cubic", 0.1, 0.05), ("cubic", 0.1, 0.5), ("quartic", 0.1, 0.05), ("quartic", 0.1, 0.5)])
def test_cubic_and_quartic_bands_match_an_independent_verlet_integration(kind, coefficient,
                                                                          kT):
    a = coefficient
    if kind == "cubic":
        pot, lo, hi = cubic(a), -1 / a, 40 * math.sqrt(kT)

        def energy(s):
            return s * s / 2 + a * s ** 3 / 3

        def force(s):
            return -(s + a * s * s)
    else:
        pot, lo, hi = quartic(a), -40 * math.sqrt(kT), 40 * math.sqrt(kT)

        def energy(s):
            return s * s / 2 + a * s ** 4 / 4

        def force(s):
            return -(s + a * s ** 3)
    hs = np.array([1.0, 1.45, 1.6, 1.75, 1.9])
    start = thermal_start(pot, kT, 500, seed=6)
    got = scan(method("verlet"), pot, start, hs, STEPS, _verlet_rho, bisections=0)
    mine = np.array([p.probability for p in got.probes])
    own = _own_fractions(verlet, energy, force, kT, hs, _verlet_rho(hs), lo, hi, m=2000)
    assert np.all(_agree(mine, 500, own, 2000)), (mine, own)
    # every step the independent integration sees failing (lower bound above 1%) is
    # reported as not clear
    for p, f in zip(got.probes, own):
        if clopper_pearson(round(f * 2000), 2000)[0] > 0.01:
            assert not p.clear


def test_probe_of_a_safe_step_is_clear_and_of_a_band_step_is_not():
    pot = morse()
    start = thermal_start(pot, 0.006, 500, seed=8)
    assert probe(method("verlet"), pot, start, 0.8, 1000, 1.2).verdict == "clear"
    inside = probe(method("verlet"), pot, start, 1.70056, 1000, 4.0)
    assert inside.verdict == "band" and inside.lower > 0.5 and inside.steps == 1000


def test_grid_holds_the_resonance_points_and_their_neighbours():
    h = grid(0.5, 2.0, 16, [math.sqrt(2), 3.0])
    assert math.sqrt(2) in h and h.min() == 0.5 and h.max() == 2.0
    assert np.all(np.diff(h) > 0)
    for offset in (0.0025, 0.005, 0.01, 0.02, 0.04):
        assert np.any(np.isclose(h, math.sqrt(2) * (1 - offset), rtol=1e-15))
    assert not np.any(h > 2.0)


@pytest.mark.parametrize("name, kT, z, unsafe", [
    ("verlet", 0.003, 1.70056, True), ("verlet", 0.003, 1.40784, True),
    ("verlet", 0.003, 0.8, False), ("verlet", 0.015, 1.5, True),
    ("verlet", 0.006, 1.70056, True), ("verlet", 0.006, 1.40784, True),
    ("verlet", 0.006, 0.8, False), ("verlet", 0.03, 1.5, True),
    ("pefrl", 0.003, 2.0542, True), ("pefrl", 0.003, 0.8, False),
    ("pefrl", 0.006, 2.0542, True), ("pefrl", 0.006, 0.8, False),
    ("pefrl", 0.015, 1.5635, True), ("pefrl", 0.03, 1.5635, True)])
def test_morse_verdicts_at_thermal_energy(name, kT, z, unsafe):
    """The steps measured on Morse bonds (D = 1/2: kT = 0.003 is E/D = 0.006, kT = 0.015 is
    E/D = 0.03; twice those as well): velocity Verlet 2% below its 3:1 point and 0.5% below
    its 4:1 point at E/D = 0.006, and z = 1.5 at E/D = 0.03; PEFRL 2% below its own 3:1
    point (2.0961), and 0.5% below its 4:1 point (1.5713) at the higher temperatures. z =
    0.8 is safe for both. Each verdict is checked against the test's own integration: a
    step it sees failing is never SAFE, and an unsafe verdict at the points the issue
    measured rests on failures the test's own integration sees too."""
    check = thermal_check(method(name), morse(), kT, z, steps=1e4)
    assert check.safe is not unsafe, check.reasons
    step = verlet if name == "verlet" else pefrl
    own = _own_fractions(step, morse_energy, morse_force, kT, [z], [math.inf], -1.5, 12.0,
                         m=2000)[0]
    if clopper_pearson(round(own * 2000), 2000)[0] > 0.01:
        assert not check.safe
    if name == "verlet" and z != 0.8:  # the escapes: the test's integration too
        assert clopper_pearson(round(own * 2000), 2000)[0] > 0.01, own


def test_pefrl_4_to_1_step_at_low_temperature_is_safe_as_measured():
    """PEFRL 0.5% below its 4:1 point at kT = 0.006: no trajectory of 2000 fails within
    2000 steps in the test's own integration, and the check says SAFE (it is below the
    linear limit at temperature, about z = 1.8)."""
    own = _own_fractions(pefrl, morse_energy, morse_force, 0.006, [1.5635], [math.inf],
                         -1.5, 12.0, m=2000)[0]
    assert own == 0.0
    assert thermal_check(method("pefrl"), morse(), 0.006, 1.5635, steps=1e4).safe


def test_a_scan_and_a_probe_report_their_progress_in_order():
    """The progress of a scan (grid and bisections) and of a probe: fractions in [0, 1]
    that never go back, the last one 1."""
    pot = morse()
    start = thermal_start(pot, 0.006, 40, seed=3)
    for job in ("scan", "probe"):
        seen: list[float] = []
        if job == "scan":
            scan(method("verlet"), pot, start, np.array([0.8, 1.7]), 300, _verlet_rho,
                 bisections=2, progress=seen.append)
        else:
            probe(method("verlet"), pot, start, 0.8, 300, 1.2, progress=seen.append)
        assert seen and seen[-1] == 1.0
        assert all(0.0 <= a <= b <= 1.0 for a, b in zip(seen, seen[1:]))


def test_a_check_reports_the_progress_of_each_probe():
    """thermal_check reports ``(stage, fraction)`` for the ensemble it runs at h: the
    whole system's probe, fractions in [0, 1] that never go back, ending at 1."""
    seen: list[tuple[str, float]] = []
    c = thermal_check(method("verlet"), morse(), 0.003, 0.8, steps=300, trajectories=60,
                      max_failure=0.06, frames=256,
                      progress=lambda stage, f: seen.append((stage, f)))
    assert c.safe and {stage for stage, _ in seen} == {"probe (whole system)"}
    fractions = [f for _, f in seen]
    assert fractions[-1] == 1.0
    assert all(0.0 <= a <= b <= 1.0 for a, b in zip(fractions, fractions[1:]))


@settings(max_examples=50, deadline=None)
@given(rows=st.integers(1, 5000), block=st.integers(1, 700), stopping=st.booleans())
def test_a_run_s_blocks_cover_its_rows_once_in_order(rows, block, stopping):
    """The blocks are consecutive, cover every row once, hold at most ``block`` rows, and a
    run that stops at its failures starts with a quarter block, doubling."""
    from stepsafe.systems.thermal.trajectories import _blocks

    got = _blocks(rows, block, stopping)
    assert got[0].start == 0 and got[-1].stop == rows
    assert all(a.stop == b.start for a, b in zip(got, got[1:]))
    sizes = [b.stop - b.start for b in got]
    assert all(0 < s <= block for s in sizes)
    first = max(1, block // 4) if stopping else block
    assert sizes[0] == min(rows, first)
    assert all(s == min(block, 2 * p) for p, s in zip(sizes, sizes[1:-1]))
