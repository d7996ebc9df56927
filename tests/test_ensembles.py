"""Ensembles of trajectories advanced together: the batched engine on a compiled
Hamiltonian against an independent Verlet loop written here, trajectory by trajectory; the
shell and thermal draws against their definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.core.ensemble import integrate, separable_system
from stepsafe.files.expressions import parse
from stepsafe.methods.library import resolve
from stepsafe.methods.tableaux import splitting_from_operations
from stepsafe.systems.compiler import FUNCTIONS, Compiled, from_tree
from stepsafe.systems.dynamics import compiled_system
from stepsafe.systems.integrate import shell_states, summary, thermal_states

FPU = ("(p1**2 + p2**2 + p3**2)/2 + q1**2/2 + a*q1**3/3 + (q2 - q1)**2/2 + a*(q2 - q1)**3/3"
       " + (q3 - q2)**2/2 + a*(q3 - q2)**3/3 + q3**2/2 - a*q3**3/3")
NAMES = ("q1", "q2", "q3", "p1", "p2", "p3")


def _fpu(alpha: float):
    e = parse(FPU, FUNCTIONS)
    compiled = Compiled(from_tree(e.tree, e.text, NAMES, {"a": alpha}), NAMES)
    return compiled, compiled_system(compiled, 3, True)


def _plain_verlet_energy_error(x0, h, steps, alpha):
    """Velocity Verlet on the 3-mass FPU-alpha chain, forces by hand, one trajectory in
    plain Python floats: max |H_k - H_0| / |H_0|."""
    def force(q):
        d = [q[0], q[1] - q[0], q[2] - q[1], -q[2]]
        f = [di + alpha * di * di for di in d]
        return [f[1] - f[0], f[2] - f[1], f[3] - f[2]]

    def energy(q, p):
        d = [q[0], q[1] - q[0], q[2] - q[1], -q[2]]
        return sum(v * v for v in p) / 2 + sum(di * di / 2 + alpha * di ** 3 / 3 for di in d)

    q, p = list(x0[:3]), list(x0[3:])
    e0, worst = energy(q, p), 0.0
    for _ in range(steps):
        f = force(q)
        p = [pi + 0.5 * h * fi for pi, fi in zip(p, f)]
        q = [qi + h * pi for qi, pi in zip(q, p)]
        f = force(q)
        p = [pi + 0.5 * h * fi for pi, fi in zip(p, f)]
        worst = max(worst, abs(energy(q, p) - e0))
    return worst / abs(e0)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), energy=st.floats(1e-4, 0.05),
       h=st.floats(0.01, 0.8), alpha=st.floats(0.0, 0.5))
def test_batched_verlet_matches_an_independent_loop_per_trajectory(seed, energy, h, alpha):
    """Every trajectory's energy error from the batched step equals the one from a plain
    per-trajectory Verlet loop (to 1e-9 relative: the same arithmetic up to rounding)."""
    compiled, system = _fpu(alpha)
    rng = np.random.default_rng(seed)
    S = compiled.hessian(np.zeros(6))
    X0 = shell_states(np.zeros(6), S, energy, 6, rng)
    ran = integrate(resolve("verlet")[0], system, X0[:, :3], X0[:, 3:], h, 60)
    errors = ran.worst / np.abs(ran.energy0)
    for x0, err in zip(X0, errors):
        assert err == pytest.approx(_plain_verlet_energy_error(x0, h, 60, alpha),
                                    rel=1e-9, abs=1e-15)
    d = summary(errors, seed)
    assert d.q05 <= d.q25 <= d.median <= d.q75 <= d.q95 <= d.max == errors.max()
    assert d.count == 6 and d.seed == seed


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), energy=st.floats(1e-6, 10.0))
def test_shell_states_lie_on_the_quadratic_shell(seed, energy):
    S = np.array([[2.0, 0.3, 0, 0], [0.3, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 0.5]])
    centre = np.array([0.1, -0.2, 0.0, 0.0])
    X = shell_states(centre, S, energy, 50, np.random.default_rng(seed))
    d = X - centre
    np.testing.assert_allclose(0.5 * np.einsum("bi,ij,bj->b", d, S, d), energy, rtol=1e-12)


def test_thermal_states_have_the_boltzmann_covariance():
    """kT S^-1 within the sampling error of 20000 draws (seeded: 1 percent is over ten
    standard errors of each entry)."""
    S = np.array([[4.0, 1.0], [1.0, 1.0]])
    X = thermal_states(np.zeros(2), S, 0.3, 20000, np.random.default_rng(7))
    np.testing.assert_allclose(np.cov(X.T), 0.3 * np.linalg.inv(S), rtol=0.05, atol=0.01)


def test_a_step_applies_the_operations_in_order():
    """kick(1) drift(1) on a free particle in a constant force g = 2: p -= g h, then
    q += p h (symplectic Euler, kick first); the start is not modified."""
    q, p = np.array([[0.0]]), np.array([[1.0]])
    euler = splitting_from_operations([("kick", 1.0), ("drift", 1.0)], name="euler-kd")
    system = separable_system(lambda q: np.full_like(q, 2.0), lambda q: 2.0 * q[:, 0], [1.0])
    ran = integrate(euler, system, q, p, 0.1, 1)
    assert ran.p[0, 0] == pytest.approx(0.8) and ran.q[0, 0] == pytest.approx(0.08)
    assert math.isclose(q[0, 0], 0.0) and ran.forces == 1
