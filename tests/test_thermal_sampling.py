"""Thermal configurations: exact Gaussian draws and BAOAB Langevin on a quadratic potential
against the covariance kT K^-1, Langevin on an FPU chain against a Metropolis sampler
written in the test, 1-D wells with barriers and plateaus, reproducibility, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from thermal_support import cubic, fpu, fpu_energy, fpu_hessian, metropolis, morse

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.inm import frequencies
from stepsafe.systems.thermal.potential import quadratic
from stepsafe.systems.thermal.sampling import draw, langevin, well

K = np.array([[2.0, -1.0, 0.0], [-1.0, 2.5, -0.7], [0.0, -0.7, 1.2]])


def _covariance_within(q, Sigma, sigmas, n_eff):
    """Every entry of the sample covariance within ``sigmas`` standard errors of Sigma
    (for Gaussian data: var(S_ij) = (S_ii S_jj + S_ij^2) / n)."""
    S = np.cov(q.T)
    se = np.sqrt((np.outer(np.diag(Sigma), np.diag(Sigma)) + Sigma ** 2) / n_eff)
    return np.all(np.abs(S - Sigma) <= sigmas * se)


def test_gaussian_draws_have_the_boltzmann_covariance():
    kT = 0.7
    pot = quadratic(K, [1.0, 5.0, 0.3], minimum=[1.0, -2.0, 0.5])
    ens = draw(pot, kT, 20000, seed=3)
    assert ens.how == "exact Gaussian"
    se = np.sqrt(kT * np.diag(np.linalg.inv(K)) / 20000)
    assert np.all(np.abs(ens.q.mean(0) - pot.minimum) <= 5 * se)
    assert _covariance_within(ens.q, kT * np.linalg.inv(K), 5, 20000)


def test_langevin_samples_a_quadratic_potential_exactly():
    """BAOAB's configurations are exact for a quadratic U at every stable step."""
    kT = 0.7
    pot = quadratic(K, [1.0, 5.0, 0.3], minimum=[1.0, -2.0, 0.5])
    ens = langevin(pot, kT, 4096, np.random.default_rng(4), 4)
    assert ens.how == "Langevin (BAOAB)" and ens.thin >= 1 and ens.tau >= 1
    assert _covariance_within(ens.q, kT * np.linalg.inv(K), 5, 4096)


def test_langevin_on_an_fpu_chain_agrees_with_metropolis():
    """Two independent samplers of exp(-U/kT) on a 4-mass FPU-alpha chain: the mean energy
    and the distribution of the largest instantaneous frequency agree (two-sample
    Kolmogorov-Smirnov distance below its 0.1% critical value 1.95 sqrt(2/n))."""
    n, kT, alpha = 4, 0.08, 0.25
    pot = fpu(n, alpha)
    ens = draw(pot, kT, 2048, seed=5)
    ref, acceptance = metropolis(lambda q: fpu_energy(q, alpha), kT, np.zeros(n), 256, 4000,
                                 0.7 * math.sqrt(kT), np.random.default_rng(6), 250)
    assert 0.2 < acceptance < 0.8
    ref = ref[np.linspace(0, ref.shape[0] - 1, 2048).round().astype(int)]
    u_l, u_m = pot.energy(ens.q), fpu_energy(ref, alpha)
    se = math.hypot(u_l.std() / math.sqrt(u_l.size), u_m.std() / math.sqrt(u_m.size))
    assert abs(u_l.mean() - u_m.mean()) <= 4 * se
    w_l = frequencies(pot, ens.q).omega_max
    w_m = np.sqrt(np.linalg.eigvalsh(fpu_hessian(ref, alpha))[:, -1])
    grid = np.sort(np.concatenate([w_l, w_m]))
    D = np.max(np.abs(np.searchsorted(np.sort(w_l), grid, "right") / w_l.size
                      - np.searchsorted(np.sort(w_m), grid, "right") / w_m.size))
    assert D <= 1.95 * math.sqrt(2 / 2048)


def test_same_seed_same_configurations_bit_for_bit():
    pot = fpu(5)
    a, b = draw(pot, 0.05, 256, seed=9), draw(pot, 0.05, 256, seed=9)
    assert np.array_equal(a.q, b.q) and a.thin == b.thin and a.seed == 9
    c = draw(pot, 0.05, 256, seed=10)
    assert not np.array_equal(a.q, c.q)


def test_wells_end_at_a_barrier_or_a_plateau_and_unconfined_ones_are_refused():
    lo, hi, notes = well(cubic(0.1), 0.4)  # barrier 1/(6 a^2) = 16.7 = 42 kT: cut at 40 kT
    assert lo > -10 and not notes
    lo, hi, notes = well(cubic(0.1), 1.0)  # 16.7 kT: the well ends at the barrier top
    assert lo == pytest.approx(-10.0, abs=math.sqrt(1.0) / 8) and "barrier" in notes[0]
    lo, hi, notes = well(morse(), 0.03)  # the plateau D = 1/2 is 16.7 kT up
    assert hi > 10 and "thermal amplitudes" in notes[0]
    with pytest.raises(StepsafeError, match="not confined"):
        draw(cubic(0.1), 2.0, 10)  # a barrier of 8 kT
    with pytest.raises(StepsafeError, match="not confined"):
        draw(morse(), 0.1, 10)  # a plateau 5 kT up


@pytest.mark.parametrize("kT, count, message", [(-1.0, 10, "kT"), (0.0, 10, "kT"),
                                                (math.inf, 10, "kT"), (0.1, 0, "count")])
def test_bad_temperatures_and_counts_are_refused(kT, count, message):
    with pytest.raises(StepsafeError, match=message):
        draw(fpu(3), kT, count)
