"""A minimum of U without curvature in some direction (a purely quartic well) is not
sampled by the analysis at temperature, whose ensembles and limits start from the
curvature at the minimum; such a scene is refused at temperature, not judged on its other
minima alone. A degenerate equilibrium where U falls along its flat direction (an
inflection, a saddle) is not a well and is left out, as before."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from test_thermal_conservative import _cli
from thermal_support import boltzmann_1d, verlet

from stepsafe.systems.thermal_scene import _degenerate_minimum

TWO_BASINS = """\
method: verlet
kT: 0.02
steps: 100
system:
  hamiltonian: "(px**2 + py**2)/2 + 2500*x**4*(1 - y/5)**2 + x**2*(y/5)**2/2
    + 0.1*y**2*(y - 5)**2"
  q: [x, y]
  p: [px, py]
  box: {x: [-1, 1], y: [-1, 6], px: [-1, 1], py: [-1, 1]}
"""


def quartic_basin_failures(h: float, count: int = 4000) -> float:
    """The fraction of Verlet runs of 100 steps from exact draws of the quartic basin's
    x (U = 1e4 x^4 / 4 at y = 0, kT = 0.02, the flat direction) whose energy grows past
    100 kT: the unsafe steps the scene's degenerate minimum holds."""
    rng = np.random.default_rng(11)
    kT = 0.02

    def energy(x):
        return 2500.0 * x ** 4

    x = boltzmann_1d(energy, kT, count, rng, -0.2, 0.2)[:, None]
    p = rng.normal(0.0, np.sqrt(kT), x.shape)
    e0 = energy(x[:, 0]) + 0.5 * p[:, 0] ** 2

    def failed(q, p):
        with np.errstate(all="ignore"):
            e = energy(q[:, 0]) + 0.5 * p[:, 0] ** 2
        return ~(e - e0 <= 100 * kT)
    return float(verlet(lambda q: -1e4 * q ** 3, x, p, h, 100, failed).mean())


def test_a_degenerate_minimum_is_refused_at_temperature_where_its_well_is_unsafe(tmp_path):
    """At h = 0.3 (the ordinary basin's own 0 K limit is 0.894) runs in the quartic basin
    blow up far above the failure bound; the check does not say SAFE: it refuses, naming
    the degenerate minimum."""
    assert quartic_basin_failures(0.3) > 0.2  # (the reference: 78% in an 8000-run estimate)
    assert quartic_basin_failures(0.01) == 0.0
    scene = tmp_path / "two-basins.yaml"
    scene.write_text(TWO_BASINS)
    code, out, err = _cli("check", str(scene), "--step", "0.3")
    assert code == 2, out + err
    assert "system.hamiltonian" in err and "degenerate minimum at x = 0, y = 0" in err
    assert len(err.strip().splitlines()) == 1


def _system(energy, hessian):
    """A 2-dof system ``U(q)`` (the kinetic part is not used)."""
    return SimpleNamespace(energy=lambda q, p: energy(q), hessian=lambda q, p: (hessian(q),))


exponents = st.integers(-100, 100)


@settings(max_examples=40, deadline=None)
@given(log_e=exponents, log_l=st.integers(-50, 50), power=st.sampled_from([3, 4, 5, 6]),
       sign=st.sampled_from([1.0, -1.0]), q0=st.sampled_from([0.0, 0.75]))
def test_a_flat_direction_is_a_well_exactly_when_u_rises_on_both_sides(log_e, log_l, power,
                                                                          sign, q0):
    """U = E (sign ((x - x0)/L)^k + ((y - y0)/L)^2) at any energy and length scale: a
    possible minimum when k is even and sign positive, else not (U falls on a side)."""
    E, L = 10.0 ** log_e, 10.0 ** log_l
    centre = np.array([q0 * L, -q0 * L])

    def energy(q):
        u = (q - centre[None, :]) / L
        return E * (sign * u[:, 0] ** power + u[:, 1] ** 2)

    def hessian(q):
        return np.array([[0.0, 0.0], [0.0, 2.0 * E / L ** 2]])[None]

    well = power % 2 == 0 and sign > 0
    assert _degenerate_minimum(_system(energy, hessian), centre) is well


def test_negative_curvature_is_not_a_well():
    def energy(q):
        return q[:, 0] ** 4 - q[:, 1] ** 2

    def hessian(q):
        return np.array([[0.0, 0.0], [0.0, -2.0]])[None]
    assert _degenerate_minimum(_system(energy, hessian), np.zeros(2)) is False
