"""The value a run reaches: the upper bound of the 1 - 1/N quantile covers the exact
quantile of known distributions (exponential, Gaussian, uniform; the extrapolated tail and
the empirical way) at least as often as its confidence says, within sampling slack, and a
constant sample gives its constant."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.extremes import run_extreme

DISTRIBUTIONS = {
    "exponential": (lambda rng, n: rng.exponential(1.0, n), lambda p: -math.log1p(-p)),
    "gaussian": (lambda rng, n: rng.standard_normal(n), lambda p: stats.norm.ppf(p)),
    "uniform": (lambda rng, n: rng.random(n), lambda p: p),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(DISTRIBUTIONS))
@pytest.mark.parametrize("n, N", [(1000, 1e4), (1000, 1e6), (20000, 100)])
def test_upper_bound_covers_the_exact_quantile(name, n, N):
    """Over 200 independent samples the bound lies above the exact quantile in at least 90%
    (its confidence is 95%; 90% is 3.2 binomial standard errors below)."""
    sample, quantile = DISTRIBUTIONS[name]
    truth = quantile(1 - 1 / N)
    rng = np.random.default_rng(17)
    covered = 0
    for _ in range(200):
        r = run_extreme(sample(rng, n), N, seed=int(rng.integers(2 ** 31)), bootstrap=200)
        covered += r.upper >= truth
        assert r.upper >= r.estimate
    assert covered >= 180
    assert ("empirical" in r.method) == (n / N >= 10)


def test_exponential_tail_is_extrapolated_conservatively_and_closely():
    """For an exponential sample the exact tail has shape 0; a fitted shape below 0 is
    raised to 0, so the estimate of the 1 - 1e-6 quantile (13.8) errs upward: its median
    over repeated samples lies between the truth and 15% above it."""
    rng = np.random.default_rng(3)
    est = [run_extreme(rng.exponential(1.0, 2000), 1e6, bootstrap=0).estimate
           for _ in range(100)]
    assert math.log(1e6) <= np.median(est) <= 1.15 * math.log(1e6)


def test_a_constant_sample_reaches_its_constant():
    r = run_extreme(np.full(500, 2.5), 1e9)
    assert r.estimate == r.upper == 2.5 and r.maximum == 2.5


def test_correlated_chains_lower_the_effective_size():
    rng = np.random.default_rng(2)
    chains, frames = 50, 40
    x = np.empty((chains, frames))
    x[:, 0] = rng.standard_normal(chains)
    for k in range(1, frames):  # AR(1) with coefficient 0.9: tau = 19
        x[:, k] = 0.9 * x[:, k - 1] + math.sqrt(1 - 0.81) * rng.standard_normal(chains)
    r = run_extreme(x.reshape(-1), 1e3, groups=np.repeat(np.arange(chains), frames))
    assert r.effective < x.size / 5
    assert r.upper >= stats.norm.ppf(1 - 1e-3)


@pytest.mark.parametrize("x, N, message", [
    ([], 10, "not empty"), ([1.0, np.nan], 10, "finite"), ([1.0] * 50, 1e6, "at least"),
    ([1.0] * 200, -1, "run_frames"), ([1.0] * 200, math.inf, "run_frames")])
def test_bad_samples_are_refused(x, N, message):
    with pytest.raises(StepsafeError, match=message):
        run_extreme(np.asarray(x, dtype=float), N)
