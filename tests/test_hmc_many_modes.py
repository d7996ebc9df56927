"""The acceptance of a Gaussian target with more distinct frequencies than are treated one by
one: the Gauss rule of the spectrum against every mode evaluated, node by node of the jitter
average, with the characteristic function of all modes (no lumping)."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stepsafe import method
from stepsafe.core import hmc as H

METHODS = ("verlet", "bcss2", "mclachlan2-min", "yoshida4", "pefrl")
#: Agreement asked of the rule: far below the Monte Carlo error of any sampler's measured
#: acceptance (1e-4 after 10^8 proposals).
TOLERANCE = 1e-8


def every_mode(m, betas, h, trajectory):
    """The jitter average over the same nodes as :func:`H.acceptance_at`, each node's
    acceptance from the energy errors of every distinct mode (plain numpy: one one-step
    matrix per mode) and the Gil-Pelaez integral of all of them."""
    values, counts = np.unique(betas, return_counts=True)
    j, steps = trajectory.jitter, trajectory.steps_at(h)
    if j:
        nodes, weights, _ = H._jitter_rule(m.tableau, values, h, j, steps)
    else:
        nodes, weights = np.zeros(1), np.full(1, 2.0)
    rates = []
    for u in nodes:
        errors = H.errors_after(H.one_step(m.tableau, h * (1.0 + j * u) * values), steps)
        a, b = H._weights(errors)
        rates.append(H._gil_pelaez(a[None, :], b[None, :], counts.astype(float),
                                   np.zeros(1), np.zeros(1))[0])
    return float(np.dot(weights, rates)) / 2.0


def compare(m, betas, h, trajectory, got):
    """Where the rule stands, ``got`` is every mode's acceptance within TOLERANCE; where it
    does not (its bins would hold more than half as many points as there are modes), the
    smallest errors are lumped and ``got`` says approximate."""
    values, counts = H._distinct(betas)
    rule = H._mode_rule(m.tableau, values, counts, h, trajectory.jitter,
                        trajectory.steps_at(h))
    if rule is None:
        assert got.approximate
        return
    assert rule[0].size <= values.size // 2 and not got.approximate
    want = every_mode(m, betas, h, trajectory)
    assert abs(got.rate - want) < TOLERANCE, (got.rate, want)


@st.composite
def spectra(draw, most=4000):
    """Frequencies with more distinct values than MAX_EXACT_MODES: log-uniform over a
    range of 1.5 to 1e4, or clustered, with repeats, at any overall scale."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.integers(H.MAX_EXACT_MODES + 1, most))
    spread = draw(st.floats(np.log(1.5), np.log(1e4)))
    scale = 10.0 ** draw(st.floats(-100, 100))
    if draw(st.booleans()):
        logs = rng.uniform(0.0, spread, n)
    else:  # a few clusters of different widths
        centres = rng.uniform(0.0, spread, 4)
        logs = centres[rng.integers(0, 4, n)] + rng.normal(0, 0.05, n) * spread
    betas = scale * np.exp(logs)
    repeats = rng.integers(1, 3, n)
    return np.repeat(betas, repeats)


def step_for(m, betas, total, jitter):
    """A step (bisected) whose jitter's longest draw keeps every mode stable and brings
    the bound over L of the summed energy errors to ``total``: the acceptances samplers
    run at, where the Gil-Pelaez integral itself is exact to 1e-9 and better."""
    values, counts = np.unique(betas, return_counts=True)

    def bound(h):
        return float(np.sum(counts * H.energy_errors(m.tableau, h * (1 + jitter) * values)))

    lo, hi = 0.0, 1.0 / values.max()
    while bound(hi) < total:
        lo, hi = hi, 2.0 * hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if bound(mid) < total else (lo, mid)
    return lo


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spectra(), st.sampled_from(METHODS), st.floats(0.01, 3.0),
       st.one_of(st.none(), st.integers(1, 30)))
def test_rule_of_the_spectrum_matches_every_mode_at_a_fixed_step(betas, name, total,
                                                                 steps):
    m = method(name)
    h = step_for(m, betas, total, 0.0)
    trajectory = H.Trajectory(steps=steps)
    got = H.acceptance_at(m.tableau, betas, h, trajectory)
    compare(m, betas, h, trajectory, got)


@pytest.mark.slow
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spectra(3000), st.sampled_from(METHODS), st.floats(0.01, 3.0),
       st.one_of(st.none(), st.integers(1, 20)), st.floats(0.02, 0.3))
def test_rule_of_the_spectrum_matches_every_mode_across_the_jitter(betas, name, total,
                                                                   steps, jitter):
    m = method(name)
    h = step_for(m, betas, total, jitter)
    trajectory = H.Trajectory(steps=steps, jitter=jitter)
    got = H.acceptance_at(m.tableau, betas, h, trajectory)
    compare(m, betas, h, trajectory, got)


def test_rule_across_a_narrow_jitter_matches_every_mode():
    m = method("bcss2")
    betas = np.exp(np.random.default_rng(5).uniform(0.0, np.log(10.0), 2500))
    h = step_for(m, betas, 0.3, 0.05)
    for trajectory in (H.Trajectory(jitter=0.05), H.Trajectory(steps=5, jitter=0.05)):
        got = H.acceptance_at(m.tableau, betas, h, trajectory)
        assert not got.approximate
        assert abs(got.rate - every_mode(m, betas, h, trajectory)) < TOLERANCE


def test_the_rule_stands_down_where_it_cannot_be_checked():
    """A trajectory of 10^5 steps turns the energy errors across every few modes, and a mode
    past its stability limit has no smooth error: every mode is evaluated then (the
    smallest lumped, the result marked approximate), as the rule returns None."""
    m = method("verlet")
    values = np.geomspace(1.0, 10.0, 3000)
    counts = np.ones(values.size)
    assert H._mode_rule(m.tableau, values, counts, 0.1, 0.0, 10**5) is None
    assert H._mode_rule(m.tableau, values, counts, 0.21, 0.0, 20) is None  # 10 * 0.21 > 2
    assert H._mode_rule(m.tableau, values, counts, 0.1, 0.0, 20) is not None
    assert H.acceptance_at(m.tableau, values, 0.1, H.Trajectory(steps=10**5)).approximate


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(17, 400), st.integers(1, 8))
def test_gauss_rules_of_discrete_measures_integrate_polynomials(seed, size, points):
    """Each segment's rule integrates t^k, k < 2 points, as its measure does."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([np.sort(rng.uniform(-1, 1, size)), np.sort(rng.uniform(-1, 1, size))])
    w = rng.integers(1, 5, t.size).astype(float)
    starts = np.array([0, size])
    nodes, weights = H._gauss_rules(t, w, starts, points)
    assert (weights > 0).all() and (np.abs(nodes) <= 1 + 1e-12).all()
    for k in range(2 * points):
        for seg in range(2):
            part = slice(seg * size, (seg + 1) * size)
            want = np.sum(w[part] * t[part] ** k)
            got = np.sum(weights[seg] * nodes[seg] ** k)
            assert abs(got - want) <= 1e-11 * np.sum(w[part]), (k, got, want)


def test_a_report_on_many_modes_is_exact_where_the_rule_stands():
    """3000 distinct standard deviations, L = 10: the rule stands for them at the step at
    target, so neither the row nor the report says approximate; the acceptance there is
    every mode's within TOLERANCE."""
    from stepsafe import hmc

    sigma = np.geomspace(0.1, 1.0, 3000)
    report = hmc(["verlet"], sigma=sigma, trajectory_steps=10)
    row = report.rows[0]
    assert not report.approximate and not any("approximate" in n for n in row.notes)
    m = method("verlet")
    want = every_mode(m, 1.0 / sigma, row.h_target, H.Trajectory(steps=10))
    assert abs(row.acceptance - want) < TOLERANCE
