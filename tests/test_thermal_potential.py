"""The potential of the thermal analysis: difference Hessian-vector products and their error
estimates at every scale, potentials read from a system's equations of motion, 1-D
profiles and their tables, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from thermal_support import fpu, fpu_hessian, morse

from stepsafe.core.integrator import System
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.potential import (
    fd_hessian_vector,
    from_callables,
    mode_direction,
    of_system,
    profile,
    quadratic,
    system_of,
    tabulate,
)


def _scaled(n, L, E):
    """``U(q) = E u(q / L)``, ``u(x) = sum(x^2/2 + x^4/4 + cosh(x/3)) + 0.3 sum x_i x_i+1``:
    value, gradient and the exact Hessian."""
    def u_grad(x):
        g = x + x ** 3 + np.sinh(x / 3) / 3
        g[:, :-1] += 0.3 * x[:, 1:]
        g[:, 1:] += 0.3 * x[:, :-1]
        return g

    def u_hess(x):
        m = x.shape[0]
        H = np.zeros((m, n, n))
        i = np.arange(n)
        H[:, i, i] = 1 + 3 * x ** 2 + np.cosh(x / 3) / 9
        H[:, i[:-1], i[1:]] = 0.3
        H[:, i[1:], i[:-1]] = 0.3
        return H

    def energy(q):
        x = q / L
        return E * (np.sum(x ** 2 / 2 + x ** 4 / 4 + np.cosh(x / 3), axis=1)
                    + 0.3 * np.sum(x[:, :-1] * x[:, 1:], axis=1))

    return energy, (lambda q: (E / L) * u_grad(q / L)), (lambda q: (E / L ** 2) * u_hess(q / L))


@settings(max_examples=40, deadline=None)
@given(st.integers(-100, 100), st.integers(-100, 100), st.integers(1, 6), st.integers(0, 2 ** 31))
def test_difference_product_within_its_error_estimate_at_every_scale(ex_L, ex_E, n, seed):
    L, E = 10.0 ** ex_L, 10.0 ** ex_E
    energy, gradient, hessian = _scaled(n, L, E)
    rng = np.random.default_rng(seed)
    q = L * rng.uniform(-2, 2, (8, n))
    v = rng.standard_normal((8, n)) * 10.0 ** rng.integers(-3, 4, (8, 1))
    exact = np.einsum("mij,mj->mi", hessian(q), v)
    got = fd_hessian_vector(gradient, q, v, scale=L)
    actual = np.max(np.abs(got.value - exact), axis=1)
    size = np.max(np.abs(exact), axis=1)
    assert np.all(actual <= got.error)          # the estimate is honest
    assert np.all(got.error <= 1e-6 * size)     # and the product accurate


def test_difference_product_of_a_quadratic_is_exact_to_rounding():
    K = np.array([[2.0, -1.0, 0.0], [-1.0, 2.0, -1.0], [0.0, -1.0, 2.0]])
    pot = quadratic(K, np.ones(3))
    q = np.random.default_rng(1).standard_normal((5, 3))
    v = np.random.default_rng(2).standard_normal((5, 3))
    got = fd_hessian_vector(pot.gradient, q, v, scale=1.0)
    assert np.allclose(got.value, v @ K, rtol=0, atol=1e-9)
    assert np.all(np.max(np.abs(got.value - v @ K), axis=1) <= got.error)


def test_potential_read_from_a_separable_system_with_masses():
    masses = np.array([2.0, 3.0, 0.5])
    alpha = 0.25

    chain = fpu(3, alpha)
    system = System(dH_dq=lambda q, p: chain.gradient(q), dH_dp=lambda q, p: p / masses,
                    energy=lambda q, p: chain.energy(q) + 0.5 * np.sum(p * p / masses, 1),
                    separable=True, dimension=3,
                    hessian=lambda q, p: (fpu_hessian(q, alpha), 0 * fpu_hessian(q, alpha),
                                          np.broadcast_to(np.diag(1 / masses), (q.shape[0], 3, 3))))
    pot = of_system(system, minimum=np.zeros(3))
    assert np.array_equal(pot.masses, masses)
    q = np.random.default_rng(3).uniform(-0.5, 0.5, (4, 3))
    assert np.allclose(pot.energy(q), fpu(3, alpha).energy(q), rtol=1e-15, atol=0)
    assert np.allclose(pot.gradient(q), fpu(3, alpha).gradient(q), rtol=1e-15, atol=0)
    assert np.array_equal(pot.hessian(q), fpu_hessian(q, alpha))
    back = system_of(pot)
    p = np.random.default_rng(4).standard_normal((4, 3))
    assert np.allclose(back.energy(q, p), system.energy(q, p), rtol=1e-15, atol=0)


def _system(dH_dp, energy, separable=True, n=2):
    return System(dH_dq=lambda q, p: q, dH_dp=dH_dp, energy=energy, separable=separable,
                  dimension=n)


@pytest.mark.parametrize("system, message", [
    (_system(lambda q, p: p, lambda q, p: np.sum(q * q + p * p, 1) / 2, separable=False),
     "mixes q and p"),
    (_system(lambda q, p: p @ np.array([[1.0, 0.2], [0.2, 1.0]]),
             lambda q, p: np.sum(q * q, 1) / 2 + 0.5 * np.einsum(
                 "mi,ij,mj->m", p, np.array([[1.0, 0.2], [0.2, 1.0]]), p)),
     "diagonal mass matrix"),
    (_system(lambda q, p: p ** 3, lambda q, p: np.sum(q * q + p ** 4 / 2, 1) / 2),
     "kinetic energy is not"),
    (_system(lambda q, p: -p, lambda q, p: np.sum(q * q - p * p, 1) / 2), "positive"),
    (_system(lambda q, p: p, lambda q, p: np.sum(q * q + 2 * p * p, 1) / 2),
     "kinetic energy is not"),
])
def test_systems_the_thermal_analysis_cannot_use_are_refused(system, message):
    with pytest.raises(StepsafeError, match=message):
        of_system(system)


def test_callables_with_wrong_shapes_are_refused():
    with pytest.raises(StepsafeError, match="energy has shape"):
        from_callables(lambda q: q, lambda q: q, [1.0, 1.0])
    with pytest.raises(StepsafeError, match="gradient has shape"):
        from_callables(lambda q: q[:, 0], lambda q: q[:, :1], [1.0, 1.0])
    with pytest.raises(StepsafeError, match="not finite"):
        from_callables(lambda q: np.full(q.shape[0], np.nan), lambda q: q, [1.0], minimum=[0.0])
    with pytest.raises(StepsafeError, match="masses"):
        from_callables(lambda q: q[:, 0], lambda q: q, [0.0])
    with pytest.raises(StepsafeError, match="minimum"):
        from_callables(lambda q: q[:, 0], lambda q: q, [1.0], minimum=[0.0, 1.0])


def test_profile_along_a_mode_has_unit_mass_and_the_mode_frequency():
    masses = np.array([1.0, 2.0, 3.0, 4.0])
    pot = fpu(4, masses=masses)
    from scipy.linalg import eigh

    w2, vec = eigh(fpu_hessian(np.zeros((1, 4)), 0.25)[0], np.diag(masses))
    e = np.sqrt(masses) * vec[:, -1]  # the fastest mode in mass-weighted coordinates
    prof = profile(pot, np.zeros(4), mode_direction(pot, e))
    assert prof.masses.tolist() == [1.0]
    assert prof.hessian(np.zeros((1, 1)))[0, 0, 0] == pytest.approx(w2[-1], rel=1e-13)
    s = np.linspace(-0.5, 0.5, 11)[:, None]
    d = mode_direction(pot, e)
    assert np.allclose(prof.energy(s), pot.energy(s * d[None, :]), rtol=1e-15, atol=0)


def test_table_of_a_profile_matches_the_potential_within_its_stated_error():
    pot = morse()
    table = tabulate(pot, -0.8, 3.0)
    x = np.random.default_rng(5).uniform(-0.8, 3.0, (1000, 1))
    assert np.max(np.abs(table.potential.gradient(x) - pot.gradient(x))) <= 2 * table.error
    assert table.relative_error < 1e-12
    assert np.allclose(table.potential.energy(x), pot.energy(x), rtol=0, atol=1e-12)
    assert table.potential.energy(np.zeros((1, 1)))[0] == pot.energy(np.zeros((1, 1)))[0]
    outside = np.array([[-0.81], [3.01]])
    assert np.all(np.isnan(table.potential.gradient(outside)))
    assert np.all(np.isnan(table.potential.energy(outside)))


def test_thermal_package_imports_only_numpy_scipy_and_the_layers_below():
    """Every import in stepsafe/systems/thermal, at module level or inside functions, is
    numpy, scipy, the standard library, or stepsafe's exceptions, methods, core and the
    package itself: never the API, the CLI or the scene readers."""
    import ast
    import sys
    from pathlib import Path

    folder = Path(__file__).resolve().parent.parent / "stepsafe/systems/thermal"
    allowed = ("numpy", "scipy", "stepsafe.exceptions", "stepsafe.methods", "stepsafe.core",
               "stepsafe.systems.thermal", "__future__")
    for path in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            for name in names:
                top = name.split(".")[0]
                assert name.startswith(allowed) or top in sys.stdlib_module_names, \
                    f"{path.name} imports {name}"
