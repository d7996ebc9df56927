"""Instantaneous normal modes: the extreme eigenvalues of the mass-weighted Hessian by the
three ways (analytic Hessian, difference Hessian, Lanczos) against the generalized
eigenproblem and closed forms, unstable directions, and the distribution over a 1-D
Boltzmann ensemble against the exact quadrature of omega(q)^2 = U''(q)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import eigh
from thermal_support import boltzmann_quantile, cubic, fpu, fpu_hessian, quartic

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.inm import frequencies, modes
from stepsafe.systems.thermal.potential import from_callables
from stepsafe.systems.thermal.sampling import draw


def _generalized(q, masses, alpha=0.25):
    """Largest and smallest eigenvalue of K v = lambda M v at each configuration."""
    out = [eigh(H, np.diag(masses), eigvals_only=True) for H in fpu_hessian(q, alpha)]
    return np.array([w[-1] for w in out]), np.array([w[0] for w in out])


@pytest.mark.parametrize("analytic, exact_up_to", [(True, 256), (False, 256), (True, 0),
                                                   (False, 0)])
def test_extreme_eigenvalues_agree_with_the_generalized_eigenproblem(analytic, exact_up_to):
    masses = np.array([1.0, 16.0, 1.0, 2.0, 1.0, 12.0])
    pot = fpu(6, masses=masses, analytic=analytic)
    q = np.random.default_rng(7).uniform(-0.4, 0.4, (12, 6))
    got = frequencies(pot, q, exact_up_to=exact_up_to)
    top, low = _generalized(q, masses)
    assert np.all(np.abs(got.lambda_max - top) <= got.error + 1e-14 * np.abs(top))
    assert np.all(np.abs(got.lambda_min - low) <= got.error + 1e-14 * np.abs(top))
    if not analytic:
        assert np.all(got.error < 1e-6 * np.abs(top))
    assert ("Lanczos" in got.how) == (exact_up_to == 0)


def test_fpu_chain_at_rest_has_its_closed_form_frequencies():
    n = 8
    found = modes(fpu(n), np.zeros(n))
    expected = [2 * math.sin(k * math.pi / (2 * (n + 1))) for k in range(1, n + 1)]
    assert found.omegas == pytest.approx(expected, rel=1e-13)


def test_negative_curvature_is_reported_as_an_imaginary_frequency():
    # a double well U = (q^2 - 1)^2 / 4 on two coordinates, the second harmonic: at the
    # barrier top q1 = 0 the curvature is -1 (rate 1), elsewhere as U'' = 3 q1^2 - 1
    pot = from_callables(lambda q: (q[:, 0] ** 2 - 1) ** 2 / 4 + q[:, 1] ** 2,
                         lambda q: np.stack([q[:, 0] ** 3 - q[:, 0], 2 * q[:, 1]], axis=1),
                         [1.0, 1.0], minimum=[1.0, 0.0])
    q = np.array([[0.0, 0.1], [0.3, 0.0], [1.0, 0.0]])
    got = frequencies(pot, q)
    assert got.lambda_min == pytest.approx([-1.0, 3 * 0.09 - 1, 2.0], rel=1e-6)
    assert got.unstable.tolist() == [True, True, False]
    assert got.imaginary[0] == pytest.approx(1.0, rel=1e-6)
    assert got.imaginary[2] == 0.0


@pytest.mark.parametrize("kind, coefficient, kT", [
    ("cubic", 0.1, 0.05), ("cubic", 0.1, 0.5), ("quartic", 0.5, 0.05), ("quartic", 0.5, 0.5)])
def test_distribution_of_omega_max_matches_the_boltzmann_quadrature(kind, coefficient, kT):
    """For one coordinate omega^2 = U''(q) is monotone in q (cubic) or in |q| (quartic), so
    its distribution function is that of q under exp(-U/kT), found here by quadrature. The
    draws are exact and independent: by the Dvoretzky-Kiefer-Wolfowitz inequality the
    sample distribution function is within 0.031 of the exact one everywhere, except with
    probability 2 e^(-2 n 0.031^2) < 1e-3 (n = 4000)."""
    a = coefficient
    pot = cubic(a) if kind == "cubic" else quartic(a)
    ens = draw(pot, kT, 4000, seed=11)
    omega = frequencies(pot, ens.q).omega_max
    U = (lambda s: s * s / 2 + a * s ** 3 / 3) if kind == "cubic" else (
        lambda s: s * s / 2 + a * s ** 4 / 4)
    lo, hi = (-1 / a + 1e-9, 40 * math.sqrt(kT)) if kind == "cubic" else (
        -40 * math.sqrt(kT), 40 * math.sqrt(kT))
    for level in (0.05, 0.25, 0.5, 0.75, 0.95, 0.99):
        if kind == "cubic":  # omega^2 = 1 + 2 a q, increasing in q
            q_l = boltzmann_quantile(U, kT, level, lo, hi)
            w = math.sqrt(1 + 2 * a * q_l)
        else:  # omega^2 = 1 + 3 a q^2: P(|q| <= x) = level, symmetric
            x = boltzmann_quantile(U, kT, 0.5 + level / 2, lo, hi)
            w = math.sqrt(1 + 3 * a * x * x)
        sample_cdf = float(np.mean(omega <= w))
        assert abs(sample_cdf - level) <= 0.031


def test_configurations_of_the_wrong_shape_are_refused():
    with pytest.raises(StepsafeError, match="coordinates"):
        frequencies(fpu(4), np.zeros((3, 5)))
    with pytest.raises(StepsafeError, match="finite"):
        frequencies(fpu(4), np.full((3, 4), np.nan))
