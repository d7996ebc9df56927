"""Langevin draws are judged on chains started away from the minimum: a narrow dimple in
a wide flat box (the minimum's curvature says nothing of the spread) is drawn from its
exact marginal, or refused, and the judgement is the same at every scale."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal import sampling
from stepsafe.systems.thermal.potential import from_callables
from stepsafe.systems.thermal.sampling import disagreement, draw


def flat_box(energy: float = 1.0, length: float = 1.0, width: float = 0.02):
    """``U = E (-exp(-x^2 / w) + (x / 10)^8 + 200 (1 + (x / 10)^2) y^2)`` with
    ``(x, y) = q / L``: a dimple of curvature ``2 E / (w L^2)``, one E deep, in a box
    |x| < 10 L, and a stiff y (unit masses)."""
    def energy_of(q):
        x, y = q[:, 0] / length, q[:, 1] / length
        return energy * (-np.exp(-x * x / width) + (x / 10) ** 8
                         + 200 * (1 + (x / 10) ** 2) * y * y)

    def gradient(q):
        x, y = q[:, 0] / length, q[:, 1] / length
        gx = 2 * x / width * np.exp(-x * x / width) + 8 * x ** 7 / 1e8 + 4 * x * y * y
        gy = 400 * (1 + (x / 10) ** 2) * y
        return (energy / length) * np.stack([gx, gy], axis=1)

    return from_callables(energy_of, gradient, [1.0, 1.0], minimum=[0.0, 0.0])


def exact_marginal_quantiles(probabilities, width: float = 0.02):
    """Quantiles of x under ``exp(-U / kT)`` at kT = E = 1, L = 1: y integrates to
    ``(1 + (x/10)^2)^-1/2``; the distribution function of x by the trapezoid rule on a fine
    grid (the dimple resolved by it), inverted by interpolation."""
    x = np.linspace(-16.0, 16.0, 4000001)
    w = np.exp(np.exp(-x * x / width) - (x / 10) ** 8) / np.sqrt(1 + (x / 10) ** 2)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(x))])
    return np.interp(probabilities, cdf / cdf[-1], x)


def _matches_the_exact_marginal(width):
    ens = draw(flat_box(width=width), 1.0, 2995, seed=0)
    x = np.sort(ens.q[:, 0])
    # the exact spread: sd about 5.3, a sixth of the mass beyond |x| > 7.5 (the dimple
    # alone gives sd sqrt(w / 2))
    p = (np.arange(x.size) + 0.5) / x.size
    exact = exact_marginal_quantiles(p, width)
    ks = float(np.max(np.abs(np.interp(exact, x, p) - p)))
    # (frames of one chain are correlated in x: the draws are worth a few hundred
    # independent ones, whose Kolmogorov distance stays below 0.1; draws confined to the
    # dimple are 0.3 to 0.4 away)
    assert ks < 0.1, ks
    reference_sd = float(np.sqrt(np.mean(exact_marginal_quantiles(
        (np.arange(100000) + 0.5) / 100000, width) ** 2)))
    assert abs(x.std() / reference_sd - 1.0) < 0.06
    assert any("disagreed" in note for note in ens.notes)


def test_flat_box_draws_match_the_exact_marginal():
    _matches_the_exact_marginal(0.02)


@pytest.mark.slow
def test_flat_box_draws_match_the_exact_marginal_far_beyond_the_dimples_reach():
    """A dimple 100 times narrower: the box's wall is 1000 of its thermal amplitudes out,
    past the linear walk (256 of them), found by the geometric one."""
    _matches_the_exact_marginal(0.0002)


def test_unmixed_draws_are_refused_naming_the_coordinate(monkeypatch):
    monkeypatch.setattr(sampling, "DOUBLINGS", 0)
    with pytest.raises(StepsafeError, match="have not mixed.*coordinate 0"):
        draw(flat_box(), 1.0, 640, seed=0)


def test_disagreement_sees_dispersed_chains_that_stay_where_they_started():
    rng = np.random.default_rng(5)
    near = rng.standard_normal((50, 64, 1))
    mixed = rng.standard_normal((50, 32, 1))
    stuck = 8.0 + 0.1 * rng.standard_normal((50, 32, 1))
    assert disagreement(np.concatenate([near, mixed], axis=1), 64)[0] < 4.0
    assert disagreement(np.concatenate([near, stuck], axis=1), 64)[0] > 50.0
    # two stuck halves on either side: the means agree, the spread does not
    sides = np.concatenate([stuck[:, :16], -stuck[:, 16:]], axis=1)
    assert disagreement(np.concatenate([near, sides], axis=1), 64)[0] > 50.0


@pytest.mark.slow
@settings(max_examples=4, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(e=st.integers(-100, 100), l_=st.integers(-50, 50))
def test_mixing_judgement_is_the_same_at_every_scale(e, l_):
    energy, length = 10.0 ** e, 10.0 ** l_
    ens = draw(flat_box(energy, length), energy, 640, seed=2)
    base = draw(flat_box(), 1.0, 640, seed=2)
    assert [n.split("(")[0] for n in ens.notes] == [n.split("(")[0] for n in base.notes]
    assert abs(ens.burn_in / base.burn_in - 1.0) < 0.01
    # time runs in units of L / sqrt(E): the friction scales by sqrt(E) / L
    assert math.isclose(ens.friction * length / math.sqrt(energy), base.friction,
                        rel_tol=1e-6)
    sd = float(np.std(ens.q[:, 0])) / length
    assert 4.5 < sd < 6.0
