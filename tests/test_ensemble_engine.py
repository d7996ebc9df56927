"""The engine over trajectories (:func:`stepsafe.core.ensemble.integrate`) against plain
numpy integrations written here, one per kind: a splitting (velocity Verlet), a
composition (Yoshida's triple jump of Verlet), a processed method (kernel and processor
from the method's coefficients, ``P^-1 K^k P``), an explicit Runge–Kutta method (the
classical RK4 tableau) and an implicit one (the implicit midpoint rule, solved here by
its own fixed-point iteration).

The system: two coordinates of masses ``m_i`` in a cubic well of depth ``E_s``,
``U(q) = E_s u(q / L)`` with ``u(x) = sum_i x_i^2 / 2 - x_i^3 / 3 + x_0 x_1 / 10``
(barrier at about ``E_s / 6``), run in the units a hostile user might pick: L, ``E_s`` and
the masses scaled by powers of ten from 1e-100 to 1e100 together, the step by the time
unit ``L sqrt(m / E_s)``. Starts below the barrier stay bounded; starts far above it
escape over it (the state leaves the finite numbers, or the energy grows past the stated
multiple). At every scale the escape flags and the energy errors relative to the start's
energy agree with the independent integration.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.core.ensemble import integrate, separable_system
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.library import resolve

GROWTH = 50.0


class Scaled:
    """The cubic well in units ``L``, ``E_s``, masses ``m`` (see the module docstring)."""

    def __init__(self, L: float, E: float, m: np.ndarray) -> None:
        self.L, self.E, self.m = L, E, np.asarray(m, dtype=float)
        self.tau = L * math.sqrt(float(self.m.mean()) / E)  # the time unit

    def force(self, q: np.ndarray) -> np.ndarray:
        """``-grad U``."""
        x = q / self.L
        g = x - x * x
        g[:, 0] += 0.1 * x[:, 1]
        g[:, 1] += 0.1 * x[:, 0]
        return -(self.E / self.L) * g

    def potential(self, q: np.ndarray) -> np.ndarray:
        x = q / self.L
        return self.E * (np.sum(x * x / 2 - x ** 3 / 3, axis=1) + 0.1 * x[:, 0] * x[:, 1])

    def energy(self, q: np.ndarray, p: np.ndarray) -> np.ndarray:
        return self.potential(q) + 0.5 * np.sum(p * p / self.m, axis=1)

    def system(self):
        return separable_system(lambda q: -self.force(q), self.potential, self.m)


def _starts(well: Scaled, rng: np.random.Generator, count: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """Half the starts at energies ``0.01 .. 0.08 E_s`` (bounded: the barrier is at about
    ``E_s / 6``), half at ``1 .. 3 E_s`` (they escape)."""
    energy = np.where(np.arange(count) % 2 == 0, rng.uniform(0.01, 0.08, count),
                      rng.uniform(1.0, 3.0, count))
    direction = rng.standard_normal((count, 4))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    x = direction * np.sqrt(2 * energy)[:, None]  # quadratic energy = energy (x^2 / 2)
    q = x[:, :2] * well.L
    p = x[:, 2:] * np.sqrt(well.E * well.m)
    return q, p


# ---------------------------------------------------------------- independent integrators
# Each is one step on numpy rows; the loop around them (_reference) freezes a row when its
# state stops being finite or its energy passes GROWTH times the start's.


def _verlet(well, q, p, h):
    p = p + 0.5 * h * well.force(q)
    q = q + h * p / well.m
    p = p + 0.5 * h * well.force(q)
    return q, p


def _triple_jump(well, q, p, h):
    w1 = 1 / (2 - 2 ** (1 / 3))
    w0 = 1 - 2 * w1
    for w in (w1, w0, w1):
        q, p = _verlet(well, q, p, w * h)
    return q, p


def _rk4(well, q, p, h):
    """The classical tableau on ``q' = p / m``, ``p' = F(q)``."""
    def f(q, p):
        return p / well.m, well.force(q)

    k1 = f(q, p)
    k2 = f(q + 0.5 * h * k1[0], p + 0.5 * h * k1[1])
    k3 = f(q + 0.5 * h * k2[0], p + 0.5 * h * k2[1])
    k4 = f(q + h * k3[0], p + h * k3[1])
    return (q + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
            p + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]))


def _midpoint(well, q, p, h):
    """``x1 = x + h f((x + x1) / 2)`` by fixed-point iteration to 1e-15 of the state."""
    q1, p1 = q, p
    for _ in range(200):
        qm, pm = 0.5 * (q + q1), 0.5 * (p + p1)
        qn, pn = q + h * pm / well.m, p + h * well.force(qm)
        done = np.all(np.abs(qn - q1) <= 1e-15 * np.abs(qn)) and \
            np.all(np.abs(pn - p1) <= 1e-15 * np.abs(pn))
        q1, p1 = qn, pn
        if done:
            break
    return q1, p1


def _ops(well, ops, q, p, h):
    for kind, c in ops:
        if kind == "drift":
            q = q + (c * h) * p / well.m
        else:
            p = p + (c * h) * well.force(q)
    return q, p


def _processed(method):
    """``P^-1 K^k P`` from the method's coefficients: P once, the kernel every step, and
    P^-1 (P's operations reversed, their coefficients negated) at each output."""
    kernel = [(k, float(c)) for k, c in method.kernel_splitting.operations]
    P = [(k, float(c)) for k, c in method.processor_operations]
    P_inv = [(k, -c) for k, c in reversed(P)]
    return ((lambda well, q, p, h: _ops(well, P, q, p, h)),
            (lambda well, q, p, h: _ops(well, kernel, q, p, h)),
            (lambda well, q, p, h: _ops(well, P_inv, q, p, h)))


def _reference(well, step, q0, p0, h, steps, start=None, output=None):
    """Each row's escape flag and largest ``|H_k - H_0|`` over ``H_0`` (E_ref = 0)."""
    E0 = well.energy(q0, p0)
    q, p = (q0, p0) if start is None else start(well, q0, p0, h)
    live = np.ones(q0.shape[0], dtype=bool)
    worst = np.zeros(q0.shape[0])
    with np.errstate(all="ignore"):
        for _ in range(steps):
            q, p = step(well, q, p, h)
            qo, po = (q, p) if output is None else output(well, q, p, h)
            E = well.energy(qo, po)
            bad = ~np.isfinite(q).all(axis=1) | ~np.isfinite(p).all(axis=1) | \
                ~np.isfinite(E) | ~(E <= GROWTH * E0)
            worst = np.where(live, np.fmax(worst, np.abs(E - E0)), worst)
            live &= ~bad
            q = np.where(live[:, None], q, 0.0)  # frozen rows no longer matter
            p = np.where(live[:, None], p, 0.0)
    return ~live, np.where(live, worst / E0, np.inf)


CASES = {
    "verlet": (lambda m: (None, _verlet, None)),
    "yoshida4": (lambda m: (None, _triple_jump, None)),
    "blanes-casas-ros764": _processed,
    "rk4": (lambda m: (None, _rk4, None)),
}


@pytest.mark.parametrize("name", sorted(CASES))
@settings(max_examples=12, deadline=None)
@given(length=st.integers(-100, 100), energy=st.integers(-100, 100),
       mass=st.integers(-100, 100), ratio=st.floats(0.25, 4.0),
       h=st.floats(0.05, 0.6), seed=st.integers(0, 2**32 - 1))
def test_escapes_and_energy_errors_match_an_independent_integration_at_every_scale(
        name, length, energy, mass, ratio, h, seed):
    method = resolve(name)[0]
    well = Scaled(10.0 ** length, 10.0 ** energy, 10.0 ** mass * np.array([1.0, ratio]))
    q0, p0 = _starts(well, np.random.default_rng(seed), 12)
    step, steps = h * well.tau, math.ceil(12 / h)  # (12 time units)
    ran = integrate(method, well.system(), q0, p0, step, steps, growth=GROWTH)
    start, one, output = CASES[name](method)
    escaped, errors = _reference(well, one, q0, p0, step, steps, start, output)
    np.testing.assert_array_equal(ran.escaped, escaped)
    assert ran.worst is not None and ran.energy0 is not None
    mine = ran.worst / ran.energy0
    np.testing.assert_allclose(mine[~escaped], errors[~escaped], rtol=1e-7, atol=1e-14)
    assert np.all(np.isinf(mine[escaped]))
    assert escaped[1::2].any() and not escaped[0::2].any()  # both outcomes are tested


@settings(max_examples=12, deadline=None)
@given(length=st.integers(-100, 100), energy=st.integers(-100, 100),
       mass=st.integers(-100, 100), h=st.floats(0.05, 0.4), seed=st.integers(0, 2**32 - 1))
def test_the_implicit_midpoint_rule_matches_its_own_fixed_point_iteration_at_every_scale(
        length, energy, mass, h, seed):
    """Bounded starts (the stage iteration converges): the energy errors of the engine's
    stage solve agree with the test's own iteration, converged relative to each state, in
    any units."""
    well = Scaled(10.0 ** length, 10.0 ** energy, 10.0 ** mass * np.array([1.0, 2.0]))
    q0, p0 = _starts(well, np.random.default_rng(seed), 10)
    q0, p0 = q0[::2], p0[::2]
    step = h * well.tau
    ran = integrate(resolve("gauss", 1)[0], well.system(), q0, p0, step, 60, growth=GROWTH)
    escaped, errors = _reference(well, _midpoint, q0, p0, step, 60)
    assert not ran.escaped.any() and not escaped.any()
    assert ran.worst is not None and ran.energy0 is not None
    np.testing.assert_allclose(ran.worst / ran.energy0, errors, rtol=1e-6, atol=1e-13)


@pytest.mark.parametrize("name", ["verlet", "yoshida4"])
@settings(max_examples=10, deadline=None)
@given(length=st.integers(-100, 100), energy=st.integers(-100, 100),
       mass=st.integers(-100, 100), h=st.floats(0.05, 0.6), stop=st.integers(1, 4),
       seed=st.integers(0, 2**32 - 1))
def test_a_run_stopped_at_its_escapes_sees_the_escapes_of_the_full_run_up_to_then(
        name, length, energy, mass, h, stop, seed):
    """``stop_escapes`` s ends the run after the step of its s-th escape, at every scale:
    the rows that escaped by then, and when, are those of the test's own integration of
    the full run (each trajectory depends on its start alone); the steps reported are the
    step of the s-th escape; a run whose s-th escape never comes runs every step."""
    method = resolve(name)[0]
    well = Scaled(10.0 ** length, 10.0 ** energy, 10.0 ** mass * np.array([1.0, 1.5]))
    q0, p0 = _starts(well, np.random.default_rng(seed), 12)
    step, steps = h * well.tau, math.ceil(12 / h)
    start, one, output = CASES[name](method)
    full = integrate(method, well.system(), q0, p0, step, steps, growth=GROWTH)
    escaped, _ = _reference(well, one, q0, p0, step, steps, start, output)
    np.testing.assert_array_equal(full.escaped, escaped)
    ran = integrate(method, well.system(), q0, p0, step, steps, growth=GROWTH,
                    stop_escapes=stop)
    times = np.sort(full.escaped_at[full.escaped])
    if times.size >= stop and times[stop - 1] < steps:
        assert ran.steps == times[stop - 1]
    else:
        assert ran.steps == steps
    seen = full.escaped & (full.escaped_at <= ran.steps)
    np.testing.assert_array_equal(ran.escaped, seen)
    np.testing.assert_array_equal(ran.escaped_at[seen], full.escaped_at[seen])
    assert int(ran.escaped.sum()) >= min(stop, int(full.escaped.sum()))


def test_escaped_rows_are_frozen_and_ask_for_no_more_forces():
    """Two rows, one far above the barrier: it escapes at some step k; after it the force
    is asked for the other row alone. Verlet takes one force per step (first same as
    last) after the one at the start, so the forces counted row by row are exactly
    ``2 + 2 k + (steps - k)``."""
    well = Scaled(1.0, 1.0, np.array([1.0, 1.0]))
    calls = []

    def gradient(q):
        calls.append(q.shape[0])
        return -well.force(q)

    system = separable_system(gradient, well.potential, well.m)
    q0 = np.array([[0.1, 0.0], [3.0, 3.0]])
    p0 = np.zeros((2, 2))
    ran = integrate(resolve("verlet")[0], system, q0, p0, 0.2, 200, growth=GROWTH)
    assert list(ran.escaped) == [False, True]
    k = int(ran.escaped_at[1])
    assert 0 < k < 200 and calls[-1] == 1
    assert ran.forces == sum(calls) == 2 + 2 * k + (200 - k)
    assert math.isinf(ran.worst[1]) and math.isfinite(ran.worst[0])


def test_the_energy_fit_and_samples_are_those_of_the_measured_energies():
    """The slope and variance from the streamed sums equal numpy's least-squares line and
    variance of the sampled ``H_k - H_0`` (sampled every step)."""
    well = Scaled(1.0, 1.0, np.array([1.0, 1.5]))
    q0, p0 = _starts(well, np.random.default_rng(8), 6)
    q0, p0 = q0[::2], p0[::2]
    ran = integrate(resolve("verlet")[0], well.system(), q0, p0, 0.4, 300, fit=True,
                    sample_every=1, unit=0.5)
    assert ran.samples is not None and ran.samples.shape == (300, 3)
    k = np.arange(1, 301)
    for i in range(3):
        x = ran.samples[:, i] / 0.5
        slope = np.polyfit(k, x, 1)[0]
        assert ran.slopes()[i] == pytest.approx(slope, rel=1e-8, abs=1e-12)
        assert ran.variances()[i] == pytest.approx(x.var(), rel=1e-8, abs=1e-15)


def test_a_method_the_engine_cannot_run_is_refused_naming_it():
    well = Scaled(1.0, 1.0, np.array([1.0, 1.0]))
    q0, p0 = _starts(well, np.random.default_rng(1), 2)
    with pytest.raises(StepsafeError, match="baoab"):
        integrate(resolve("baoab")[0], well.system(), q0, p0, 0.1, 5)
    with pytest.raises(StepsafeError, match="chin-4a"):  # no Hessian
        integrate(resolve("chin-4a")[0], well.system(), q0, p0, 0.1, 5)
