"""How far a run goes into the tail: the largest frequency a run of a given length meets.

A run of ``N`` independent frames reaches about the ``1 - 1/N`` quantile of the per-frame
distribution of ``omega_max`` (the maximum of N draws exceeds that quantile with probability
``1 - (1 - 1/N)^N ~ 63%``). From a sample of ``n`` frames (grouped by chain) it is estimated
in one of two ways, and only an upper confidence bound is meant to be used:

* **empirical** when the sample reaches the level, ``n_eff / N >= MIN_BEYOND`` (that many
  expected frames beyond it; ``n_eff`` the effective sample size, from the autocorrelation
  along the chains): the ``1 - 1/N`` sample quantile, and as upper bound the order
  statistic whose rank makes it a distribution-free ``confidence`` upper bound for
  independent draws (``P(Binom(n_eff, 1 - 1/N) <= k - 1) >= confidence``, the rank scaled
  from ``n_eff`` to ``n``);
* **peaks over a threshold** otherwise: the ``k = ceil(TAIL n)`` largest values minus the
  threshold ``u`` (the next value below them) are fitted by a generalized Pareto
  distribution ``P(Y > y) = (1 + xi y / sigma)^(-1/xi)`` by probability-weighted moments
  (Hosking & Wallis 1987: ``xi = 2 - a0 / (a0 - 2 a1)``, ``sigma = 2 a0 a1 / (a0 - 2 a1)``,
  ``a0`` the mean excess and ``a1 = mean(y_(j) (1 - (j - 0.35) / k))``). A fitted ``xi < 0``
  (a bounded tail) is replaced by the exponential tail ``xi = 0``, ``sigma = a0``: the
  extrapolation never assumes an upper end the sample only suggests. The quantile is
  ``u + sigma ((k N / n)^xi - 1) / xi`` (``u + sigma log(k N / n)`` at ``xi = 0``). Its
  upper bound is the ``confidence`` percentile of the same estimate over bootstrap
  resamples of whole chains (``bootstrap`` of them, seed stated), and never below the
  estimate itself nor, when ``N >= n``, below the sample maximum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stepsafe.exceptions import StepsafeError, positive_finite

#: Expected frames beyond the level for the empirical quantile.
MIN_BEYOND = 10.0
#: Fraction of the sample in the fitted tail.
TAIL = 0.1
#: Smallest sample the tail fit accepts.
MIN_FRAMES = 100
CONFIDENCE = 0.95
BOOTSTRAP = 1000


@dataclass(frozen=True)
class RunExtreme:
    """The distribution of a per-frame maximum and the value a run reaches.

    Attributes
    ----------
    median, maximum : float
        Of the sample.
    frames : int
        Sample size n.
    effective : float
        Effective sample size (n divided by the integrated autocorrelation time along the
        chains, at most n).
    run_frames : float
        N, independent frames in the run.
    level : float
        ``1 - 1/N``.
    estimate, upper : float
        The level's quantile and its ``confidence`` upper bound.
    confidence : float
    method : str
        ``"empirical quantile"`` or ``"peaks over threshold (generalized Pareto, ...)"``.
    shape, shape_fitted : float or None
        The tail shape xi used (>= 0) and the one fitted.
    threshold : float or None
        The peaks-over-threshold u.
    exceedances : int
        k, the values in the fitted tail (0 for the empirical way).
    bootstrap : int
        Resamples behind ``upper`` (0 for the empirical way).
    seed : int
    """

    median: float
    maximum: float
    frames: int
    effective: float
    run_frames: float
    level: float
    estimate: float
    upper: float
    confidence: float
    method: str
    shape: float | None
    shape_fitted: float | None
    threshold: float | None
    exceedances: int
    bootstrap: int
    seed: int


def run_extreme(x, run_frames: float, groups=None, confidence: float = CONFIDENCE,
                seed: int = 0, bootstrap: int = BOOTSTRAP, tail: float = TAIL) -> RunExtreme:
    """The value a run of ``run_frames`` independent frames reaches (module docstring).

    Parameters
    ----------
    x : array_like
        One value per frame ``(n,)``.
    run_frames : float
        N (>= 1).
    groups : array_like, optional
        The chain of each frame (frames of one chain contiguous and in order); default
        every frame its own chain.
    confidence : float
        Of the upper bound, in (0, 1).
    seed : int
        Of the bootstrap.
    bootstrap : int
        Resamples.
    tail : float
        Fraction of the sample in the fitted tail.

    Returns
    -------
    RunExtreme
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    n = x.size
    if n == 0 or not np.all(np.isfinite(x)):
        raise StepsafeError("the sample must be finite and not empty")
    N = positive_finite(run_frames, "run_frames")
    N = max(N, 1.0)
    if not 0 < confidence < 1:
        raise StepsafeError(f"confidence must lie in (0, 1), got {confidence}")
    groups = np.arange(n) if groups is None else np.asarray(groups).reshape(-1)
    if groups.size != n:
        raise StepsafeError("groups must give one chain per frame")
    effective = n / max(1.0, _chain_time(x, groups))
    level = 1.0 - 1.0 / N
    median, maximum = float(np.median(x)), float(np.max(x))
    if effective / N >= MIN_BEYOND:
        estimate = float(np.quantile(x, level))
        upper = _order_bound(np.sort(x), effective, level, confidence)
        if upper is not None:
            return RunExtreme(median, maximum, n, effective, N, level, estimate,
                              max(upper, estimate), confidence, "empirical quantile", None,
                              None, None, 0, 0, seed)
    if n < MIN_FRAMES:
        raise StepsafeError(f"extrapolating to a run of {N:.3g} frames needs at least "
                            f"{MIN_FRAMES} frames, got {n}")
    estimate, xi, xi_fit, u, k = _pot_quantile(x, N, tail)
    rng = np.random.default_rng(seed)
    labels, index, counts = np.unique(groups, return_inverse=True, return_counts=True)
    order = np.argsort(index, kind="stable")
    if counts.min() == counts.max():  # chains of one length: rows of a table
        table = x[order].reshape(labels.size, counts[0])

        def resample(pick: np.ndarray) -> np.ndarray:
            return table[pick].reshape(-1)
    else:
        members = np.split(order, np.cumsum(counts)[:-1])

        def resample(pick: np.ndarray) -> np.ndarray:
            return x[np.concatenate([members[g] for g in pick])]
    reps = np.empty(int(bootstrap))
    for b in range(reps.size):
        reps[b] = _pot_quantile(resample(rng.integers(0, labels.size, labels.size)), N,
                                tail)[0]
    upper = float(np.quantile(reps, confidence)) if reps.size else estimate
    upper = max(upper, estimate, maximum if N >= n else -math.inf)
    method = ("peaks over threshold (generalized Pareto by probability-weighted moments, "
              "shape >= 0; bootstrap over chains)")
    return RunExtreme(median, maximum, n, effective, N, level, estimate, upper, confidence,
                      method, xi, xi_fit, u, k, int(bootstrap), seed)


def _pot_quantile(x: np.ndarray, N: float, tail: float
                  ) -> tuple[float, float, float, float, int]:
    """``(quantile, xi used, xi fitted, threshold, k)`` of the tail fit."""
    y = np.sort(x)
    n = y.size
    k = max(1, min(n - 1, math.ceil(tail * n)))
    u = float(y[n - k - 1])
    excess = y[n - k:] - u
    a0 = float(np.mean(excess))
    j = np.arange(1, k + 1)
    a1 = float(np.mean(excess * (1.0 - (j - 0.35) / k)))
    denominator = a0 - 2.0 * a1
    xi_fit = 2.0 - a0 / denominator if denominator > 0 else 0.0
    if xi_fit > 0 and math.isfinite(xi_fit):
        xi, sigma = xi_fit, 2.0 * a0 * a1 / denominator
    else:
        xi, sigma = 0.0, a0
    ratio = max(k * N / n, 1.0)
    if xi > 1e-12:
        q = u + sigma * (ratio ** xi - 1.0) / xi
    else:
        q = u + sigma * math.log(ratio)
    return float(q), float(xi), float(xi_fit), u, k


def _order_bound(sorted_x: np.ndarray, effective: float, level: float, confidence: float
                 ) -> float | None:
    """The distribution-free upper confidence bound of the ``level`` quantile: the order
    statistic of rank k, the smallest with ``P(Binom(n_eff, level) <= k - 1) >=
    confidence``, rank scaled to the full sample; None when it lies beyond the sample."""
    from scipy.stats import binom

    n_eff = max(1, int(math.floor(effective)))
    k = int(binom.ppf(confidence, n_eff, level)) + 1
    if k > n_eff:
        return None
    n = sorted_x.size
    rank = min(n, math.ceil(k * n / n_eff))
    if rank >= n and k * n / n_eff > n:
        return None
    return float(sorted_x[rank - 1])


def _chain_time(x: np.ndarray, groups: np.ndarray) -> float:
    """The integrated autocorrelation time of x along the chains (1 when every chain has
    fewer than 4 frames or chains differ in length)."""
    labels, counts = np.unique(groups, return_counts=True)
    if counts.min() < 4 or counts.min() != counts.max():
        return 1.0
    order = np.argsort(groups, kind="stable")
    trace = x[order].reshape(labels.size, counts[0]).T
    return integrated_time(trace)


def integrated_time(trace: np.ndarray, window: float = 5.0) -> float:
    """The integrated autocorrelation time ``tau = 1 + 2 sum_t rho(t)`` (in samples) of a
    series recorded along several chains (``trace`` of shape ``(steps, chains)``), from the
    chain-averaged autocorrelation about the common mean, summed up to the first lag
    ``t >= window * tau(t)`` (Sokal's automatic window); at least 1."""
    x = trace - trace.mean()  # (the chains share the stationary mean: short chains keep
    # their correlation, which subtracting each chain's own mean would remove)
    size = float(np.max(np.abs(x))) if x.size else 0.0
    if size > 0 and np.isfinite(size):
        x = x / size  # (products of values near 1e200 overflow)
    steps = x.shape[0]
    if steps < 4:
        return 1.0
    size = 1 << (2 * steps - 1).bit_length()
    f = np.fft.rfft(x, n=size, axis=0)
    acf = np.fft.irfft(f * np.conj(f), n=size, axis=0)[:steps].mean(axis=1)
    if not acf[0] > 0:
        return 1.0
    rho = acf / acf[0]
    tau = 2.0 * np.cumsum(rho) - 1.0
    lags = np.arange(steps)
    ok = np.flatnonzero(lags >= window * tau)
    return float(max(1.0, tau[ok[0]] if ok.size else tau[-1]))
