"""Monte Carlo error of averages over Markov chains.

Effective sample size of a scalar statistic x over m chains of n draws each (the
multi-chain estimator of Stan, without splitting chains): with ``W`` the mean within-chain
variance, ``B / n`` the variance of the chain means and ``var+ = (n - 1) W / n + B / n``,
the autocorrelation at lag t is ``rho_t = 1 - (W - mean_chains(gamma_t)) / var+``
(``gamma_t`` each chain's autocovariance, by FFT). The sum ``tau = -1 + 2 sum_k P_k`` runs
over Geyer's initial monotone sequence of pair sums ``P_k = rho_2k + rho_2k+1`` (stopped at
the first negative one, each made no larger than the one before), and ``ESS = m n / tau``,
capped at ``m n log10(m n)`` (antithetic chains may beat independent draws, but not
unboundedly). The standard error of the mean of x is ``sd(x) / sqrt(ESS)`` (infinite where x
has a non-finite entry or one beyond
:data:`HUGE`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def _autocovariance(x: np.ndarray) -> np.ndarray:
    """Autocovariance of each row (biased, divided by n) at lags 0..n-1, by FFT."""
    n = x.shape[-1]
    centred = x - x.mean(axis=-1, keepdims=True)
    size = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(centred, size, axis=-1)
    return np.fft.irfft(f * np.conj(f), size, axis=-1)[..., :n] / n


def effective_size(x: np.ndarray) -> float:
    """The effective sample size of ``x`` of shape (chains, n) (a 1-D array is one chain);
    ``m n`` when x is constant (its mean has no Monte Carlo error)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[None, :]
    m, n = x.shape
    total = m * n
    if total < 4 or n < 2:
        return float(total)
    gamma = _autocovariance(x)
    W = float(np.mean(gamma[:, 0]) * n / (n - 1))
    B_over_n = float(np.var(x.mean(axis=1), ddof=1)) if m > 1 else 0.0
    var_plus = (n - 1) / n * W + B_over_n
    if not var_plus > 0:
        return float(total)
    rho = 1.0 - (W - gamma.mean(axis=0) * n / (n - 1)) / var_plus
    rho[0] = 1.0
    tau = -1.0
    previous = math.inf
    for k in range(0, n - 1, 2):
        pair = float(rho[k] + rho[k + 1])
        if pair < 0:
            break
        pair = min(pair, previous)
        previous = pair
        tau += 2.0 * pair
    tau = max(tau, 1.0 / math.log10(max(total, 10)))
    return float(total / tau)


@dataclass(frozen=True)
class Mean:
    """A Monte Carlo average with its standard error and the effective sample size."""

    value: float
    se: float
    effective_size: float


def chain_mean(x: np.ndarray) -> Mean:
    """The mean of ``x`` (shape (chains, n), or one chain) with its standard error
    ``sd / sqrt(ESS)`` (module docstring); inf where x has a non-finite entry."""
    x = np.asarray(x, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        mean = float(np.mean(x))
        if not np.isfinite(x).all() or np.abs(x).max(initial=0.0) > HUGE:
            # (squares overflow: the mean is dominated by a few values, no error bar)
            return Mean(mean, math.inf, 0.0)
    ess = effective_size(x)
    sd = float(np.std(x, ddof=1)) if x.size > 1 else 0.0
    return Mean(mean, sd / math.sqrt(ess) if ess > 0 else math.inf, ess)


#: Beyond this size a statistic's squares may overflow: its mean gets no standard error.
HUGE = 1e150


def _normal_scores(x: np.ndarray) -> np.ndarray:
    """Rank-normalised values: ``Phi^-1((r - 3/8) / (S + 1/4))`` with r the rank of each
    entry among all S (ties share their mean rank)."""
    from scipy.special import ndtri
    from scipy.stats import rankdata

    r = rankdata(x, method="average").reshape(x.shape)
    return np.asarray(ndtri((r - 0.375) / (x.size + 0.25)), dtype=float)


def _split_rhat(x: np.ndarray) -> float:
    """The potential scale reduction of x (chains, n) with each chain split in halves."""
    m, n = x.shape
    half = n // 2
    s = np.concatenate([x[:, :half], x[:, n - half:]], axis=0)
    W = float(np.mean(np.var(s, axis=1, ddof=1)))
    B_over_n = float(np.var(s.mean(axis=1), ddof=1))
    if not W > 0:
        return 1.0 if not B_over_n > 0 else math.inf
    var_plus = (half - 1) / half * W + B_over_n
    return float(math.sqrt(var_plus / W))


def rhat(x: np.ndarray) -> float:
    """Rank-normalised split R-hat of x (shape (chains, n), n >= 4; one chain is split in
    halves too): the larger of the split potential scale reduction
    ``sqrt(((n'-1)/n' W + B/n') / W)`` of the rank-normalised values and of the
    rank-normalised distances from the median (W the mean within-half variance, ``B/n'``
    the variance of the half means, n' = n // 2; Vehtari, Gelman, Simpson, Carpenter and
    Buerkner, Bayesian Analysis 16 (2021) 667). Near 1 when the chains agree; above 1.01
    they have not mixed. inf where x has a non-finite entry."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[None, :]
    if x.shape[1] < 4:
        return math.inf
    if not np.isfinite(x).all():
        return math.inf
    bulk = _split_rhat(_normal_scores(x))
    tail = _split_rhat(_normal_scores(np.abs(x - np.median(x))))
    return max(bulk, tail)


#: The confidence of :func:`rate_bound`.
RATE_CONFIDENCE = 0.95


def rate_bound(count: int, n: int, confidence: float = RATE_CONFIDENCE) -> float:
    """The one-sided Clopper-Pearson upper bound on a rate seen ``count`` times in ``n``
    trials: the p with ``P(Binomial(n, p) <= count) = 1 - confidence``, the inverse of the
    regularised incomplete beta ``I_p(count + 1, n - count) = confidence``; for ``count =
    0`` it is ``1 - (1 - confidence)^(1/n)`` (about ``3 / n`` at 95%, the rule of three),
    and 1 for ``count = n``. The trials are taken as independent (proposals from
    correlated draws with fresh momenta are not quite: the bound is that of ``n``
    independent ones).

    Parameters
    ----------
    count
        How many times the event was seen, 0 <= count <= n.
    n
        Trials, at least 1.
    confidence
        In (0, 1).

    Returns
    -------
    float
    """
    if count >= n:
        return 1.0
    if count <= 0:
        return float(-math.expm1(math.log1p(-confidence) / n))
    from scipy.special import betaincinv

    return float(betaincinv(count + 1, n - count, confidence))
