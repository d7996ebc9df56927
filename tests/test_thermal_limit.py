"""The step limit at temperature: exactly the 0 K answer at kT = 0 and for a quadratic
potential, FPU chains at two temperatures against a Metropolis sampler and a Verlet
integration written in the test, the drift against the test's own fit over every step,
reproducibility, the large-system path, bad input."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import method
from thermal_support import (
    fpu,
    fpu_energy,
    fpu_force,
    fpu_hessian,
    metropolis,
    morse,
    morse_energy,
    morse_force,
    verlet,
)

from stepsafe.core.regions import find_region
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.drift import measure
from stepsafe.systems.thermal.extremes import run_extreme
from stepsafe.systems.thermal.limit import thermal_limit
from stepsafe.systems.thermal.potential import quadratic
from stepsafe.systems.thermal.trajectories import thermal_start

SMALL = dict(frames=512, trajectories=300, band_steps=500, grid_points=16, bisections=3)


@pytest.mark.parametrize("name", ["verlet", "pefrl", "yoshida4"])
def test_zero_temperature_gives_exactly_the_zero_kelvin_limit(name):
    n = 4
    omega = 2 * math.sin(n * math.pi / (2 * (n + 1)))
    z_star = find_region(method(name)).first_boundary
    r = thermal_limit(method(name), fpu(n), 0.0)
    assert r.limited_by == "0 K" and r.h_max == r.zero.h_zero and r.linear is None
    assert r.h_max == pytest.approx(z_star / omega, rel=1e-13)
    assert r.h_range == (r.h_max, r.h_max)
    if name == "verlet":
        assert r.h_max == pytest.approx(1 / math.sin(0.4 * math.pi), rel=1e-13)


def test_quadratic_potential_at_temperature_keeps_the_zero_kelvin_limit():
    """Where U is quadratic every configuration has the frequencies of the minimum and the
    map is linear: no band below the linear limit, which is the 0 K one."""
    K = np.array([[2.0, -1.0, 0.0], [-1.0, 2.0, -1.0], [0.0, -1.0, 2.0]])
    pot = quadratic(K, [1.0, 2.0, 1.0])
    r = thermal_limit(method("verlet"), pot, 0.3, steps=1e4, **SMALL)
    assert r.limited_by == "linear at temperature"
    assert r.h_linear == pytest.approx(r.zero.h_zero, rel=1e-12)
    assert r.h_max == r.confirmation.h == pytest.approx(r.h_linear, rel=2e-3)
    assert not r.scans[0].bands
    assert all(p.failures == 0 for p in r.scans[0].probes)
    # just below the limit the energy oscillates widely and slowly (theta near pi); a
    # least-squares slope over a finite window of a bounded oscillation A can reach 3 A
    # over the run; what it shows is a small part of that, no secular drift
    d = r.drift
    assert d.h == r.h_max and d.failed == 0
    assert abs(d.rate) * d.steps * d.h <= 0.2 * d.fluctuation


@pytest.mark.slow
@pytest.mark.parametrize("kT", [0.02, 0.08])
def test_fpu_chain_limit_against_metropolis_and_a_direct_integration(kT):
    """FPU-alpha, 4 masses. (a) The distribution of omega_max over the thermal ensemble
    against Metropolis sampling written here: the median and the 99% quantile (the
    empirical way, N = 100) land at those levels of the Metropolis sample within 3
    standard errors of the levels; the run's bound (N = 1e4 z*/pi frames) lies above the
    Metropolis 99.9% quantile. (b) At the thermal limit the test's own velocity Verlet
    from Metropolis configurations fails no more often than the 1% threshold allows (2.3
    standard errors), and a step inside the band found above it fails more often."""
    n, alpha = 4, 0.25
    pot = fpu(n, alpha)
    r = thermal_limit(method("verlet"), pot, kT, steps=1e4, frames=1024, trajectories=300,
                      band_steps=1000, grid_points=24)
    ref, _ = metropolis(lambda q: fpu_energy(q, alpha), kT, np.zeros(n), 400, 6000,
                        0.7 * math.sqrt(kT), np.random.default_rng(21), 30)
    w_ref = np.sqrt(np.linalg.eigvalsh(fpu_hessian(ref, alpha))[:, -1])
    omega = r.linear.omega
    assert abs(np.mean(w_ref <= omega.median) - 0.5) <= 3 * math.sqrt(0.25 / 1024)
    q99 = run_extreme(r.linear.frequencies.omega_max, 100, r.linear.ensemble.chain)
    assert "empirical" in q99.method
    assert abs(np.mean(w_ref <= q99.estimate) - 0.99) <= 3 * math.sqrt(0.0099 / 1024)
    assert omega.upper >= np.quantile(w_ref, 0.999)
    assert r.h_max <= r.h_linear <= r.zero.h_zero

    rng = np.random.default_rng(22)
    q0 = ref[rng.choice(ref.shape[0], 2000, replace=False)]
    p0 = rng.standard_normal(q0.shape) * math.sqrt(kT)
    extent = np.max(np.abs(q0), axis=0)
    E0 = fpu_energy(q0, alpha) + 0.5 * np.sum(p0 * p0, axis=1)

    def fraction(h):
        z = min(h * omega.upper, 1.999)
        rho = 1 / (1 - z * z / 4)

        def fail(q, p):
            return (~np.all(np.abs(q) <= 10 * math.sqrt(rho) * extent, axis=1)
                    | ~(fpu_energy(q, alpha) + 0.5 * np.sum(p * p, 1) <= 4 * rho ** 2 * E0))
        return verlet(lambda q: fpu_force(q, alpha), q0.copy(), p0.copy(), h, 1000,
                      fail).mean()

    assert fraction(r.h_max) <= 0.01 + 2.3 * math.sqrt(0.01 * 0.99 / 2000)
    first = r.scans[0].bands[0].lower
    if first is not None and first.band is not None:
        assert fraction(first.band) > 0.01


def _own_drift(q0, p0, h, steps):
    """Per-trajectory least-squares slope of H_n - H_0 against t = n h over every step, by
    the test's own Verlet on Morse; mean, standard error, and the RMS of each trajectory's
    standard deviation of H_n - H_0."""
    q, p = q0.copy(), p0.copy()
    H0 = morse_energy(q) + p * p / 2
    f = morse_force(q)
    dH = np.empty((steps, q.size))
    for n in range(steps):
        p = p + 0.5 * h * f
        q = q + h * p
        f = morse_force(q)
        p = p + 0.5 * h * f
        dH[n] = morse_energy(q) + p * p / 2 - H0
    t = h * np.arange(1, steps + 1)
    slope = np.polyfit(t, dH, 1)[0]
    return slope.mean(), slope.std(ddof=1) / math.sqrt(q.size), math.sqrt(dH.var(0).mean())


@pytest.mark.parametrize("h", [0.5, 1.2, 1.9])
def test_drift_matches_the_tests_own_fit_over_every_step(h):
    pot = morse()
    start = thermal_start(pot, 0.006, 200, seed=12)
    d = measure(method("verlet"), pot, start, h, 1500)
    rate, error, fluct = _own_drift(start.q[:, 0], start.p[:, 0], h, 1500)
    assert d.failed == 0
    assert d.rate == pytest.approx(rate, rel=1e-6, abs=1e-9 * error)
    assert d.error == pytest.approx(error, rel=1e-6)
    assert d.fluctuation == pytest.approx(fluct, rel=1e-9)


def test_drift_of_a_harmonic_oscillator_is_its_orbits_own_over_every_step():
    """Verlet at z = sqrt 2 rotates by a quarter turn per step: every fourth step the energy
    error is 0, so a stride of 4 would see none; over every step it oscillates along the
    invariant ellipse. Drift and fluctuation against the test's own fit of the 2x2 map's
    iterates; the drift over the whole run is a tiny fraction of the fluctuation (what is
    left is the least-squares slope of a periodic signal over a finite window)."""
    pot = quadratic(np.eye(1), [1.0])
    start = thermal_start(pot, 1.0, 400, seed=13)
    h, steps = math.sqrt(2), 4000
    d = measure(method("verlet"), pot, start, h, steps)
    M = np.array([[1 - h * h / 2, h], [-h * (1 - h * h / 4), 1 - h * h / 2]])
    x = np.stack([start.q[:, 0], start.p[:, 0]])
    H0 = 0.5 * np.sum(x * x, 0)
    dH = []
    for _ in range(steps):
        x = M @ x
        dH.append(0.5 * np.sum(x * x, 0) - H0)
    dH = np.array(dH)
    slope = np.polyfit(h * np.arange(1, steps + 1), dH, 1)[0]
    assert d.rate == pytest.approx(slope.mean(), rel=1e-6)
    assert d.fluctuation == pytest.approx(math.sqrt(dH.var(0).mean()), rel=1e-9)
    assert abs(d.rate) * steps * h <= 1e-3 * d.fluctuation
    assert np.abs(dH[3::4]).max() < 1e-9 * d.fluctuation  # what a stride of 4 sees


def test_same_seed_same_limit_and_another_seed_within_the_stated_range():
    a = thermal_limit(method("verlet"), morse(), 0.006, steps=1e4, seed=1, **SMALL)
    b = thermal_limit(method("verlet"), morse(), 0.006, steps=1e4, seed=1, **SMALL)
    assert (a.h_max, a.h_linear, a.limited_by, a.h_range) == \
        (b.h_max, b.h_linear, b.limited_by, b.h_range)
    assert a.scans[0].probes == b.scans[0].probes
    assert np.array_equal(a.linear.frequencies.lambda_max, b.linear.frequencies.lambda_max)
    c = thermal_limit(method("verlet"), morse(), 0.006, steps=1e4, seed=2, **SMALL)
    assert c.scans[0].probes != a.scans[0].probes
    assert max(a.h_range[0], c.h_range[0]) <= min(a.h_range[1], c.h_range[1])


@pytest.mark.slow
def test_large_system_path_profiles_and_a_coarse_whole_system_scan():
    """A chain treated as large (whole system above 3 dof): profiles along the two fastest
    modes, tabulated, and the whole system on a coarse grid; the limit is safe by the
    test's own integration of the whole chain."""
    n, kT, alpha = 6, 0.05, 0.25
    pot = fpu(n, alpha)
    r = thermal_limit(method("verlet"), pot, kT, steps=1e4, whole_up_to=3, modes_profiled=2,
                      frames=512, trajectories=300, band_steps=800, grid_points=16,
                      bisections=3)
    assert [s.target.split(" ")[0] for s in r.scans] == ["whole", "profile", "profile"]
    assert len(r.tables) == 2 and all(t.relative_error < 1e-10 for t in r.tables)
    assert r.drift is not None and r.drift.dimension == n
    rng = np.random.default_rng(31)
    ref, _ = metropolis(lambda q: fpu_energy(q, alpha), kT, np.zeros(n), 200, 4000,
                        0.6 * math.sqrt(kT), rng, 40)
    q0 = ref[rng.choice(ref.shape[0], 1500, replace=False)]
    p0 = rng.standard_normal(q0.shape) * math.sqrt(kT)
    dead = verlet(lambda q: fpu_force(q, alpha), q0, p0, r.h_max, 800,
                  lambda q, p: ~np.all(np.abs(q) <= 10, axis=1))
    assert dead.mean() <= 0.01 + 2.3 * math.sqrt(0.01 * 0.99 / 1500)


def _morse_scaled(E, L, m, analytic):
    """``U = E (1 - e^(-q/L))^2 / 2`` with mass m: omega_0 = sqrt(E / (m L^2))."""
    def energy(q):
        return E * 0.5 * (1 - np.exp(-q[:, 0] / L)) ** 2

    def gradient(q):
        e = np.exp(-q / L)
        return (E / L) * (1 - e) * e

    def hessian(q):
        e = np.exp(-q / L)
        return ((E / L ** 2) * (2 * e * e - e))[:, :, None]

    from stepsafe.systems.thermal.potential import from_callables

    return from_callables(energy, gradient, [m], minimum=[0.0],
                          hessian=hessian if analytic else None)


@functools.lru_cache(maxsize=1)
def _unscaled():
    return thermal_limit(method("verlet"), morse(), 0.006, steps=1e4, **SMALL)


@settings(max_examples=6, deadline=None)
@given(st.integers(-100, 100), st.integers(-60, 60), st.booleans())
def test_limit_in_units_of_the_frequency_holds_at_every_scale(ex_L, ex_m, analytic):
    """Energy, length and mass scaled by up to 1e100 (kT with the energy): h_max omega_0 is
    the unscaled one (the draws are the same numbers scaled); from a difference Hessian it
    is never above the analytic one and within 1e-8 of it."""
    L, m = 10.0 ** ex_L, 10.0 ** ex_m
    E = L * L  # keeps U'' = E / L^2 = 1 representable whatever L
    base = _unscaled()
    r = thermal_limit(method("verlet"), _morse_scaled(E, L, m, analytic), 0.006 * E,
                      steps=1e4, **SMALL)
    z_base, z = base.h_max * base.zero.omega_zero, r.h_max * math.sqrt(E / (m * L * L))
    assert r.limited_by == base.limited_by
    if analytic:
        assert z == pytest.approx(z_base, rel=1e-9)
    else:
        assert z_base * (1 - 1e-8) <= z <= z_base * (1 + 1e-12)


@pytest.mark.parametrize("kwargs, message", [
    (dict(kT=-1.0, steps=100), "negative"), (dict(kT=0.1), "length"),
    (dict(kT=0.1, steps=10, length=5.0), "one of them"), (dict(kT=0.1, steps=-5), "steps"),
    (dict(kT=math.nan, steps=10), "kT"), (dict(kT=0.1, steps=10, orders=(2,)), "orders")])
def test_bad_requests_are_refused(kwargs, message):
    with pytest.raises(StepsafeError, match=message):
        thermal_limit(method("verlet"), morse(), **kwargs)
