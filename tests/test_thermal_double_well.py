"""A 1-D well whose barrier lies below the thermal cut is confined by the walls beyond it:
the exact 1-D draws cover both basins (against 50-digit quadratures of the Boltzmann
density), the verdicts at temperature agree with the same well given a spectator
coordinate (drawn by Langevin dynamics) and with the test's own integration from exact
draws; a barrier followed by a fall, or a plateau (dissociation), is still not confined."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_thermal_conservative import _cli

import stepsafe
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.thermal.potential import from_callables
from stepsafe.systems.thermal.sampling import draw, well

KT = 0.05  # the barrier (q^2 - 1)^2/4 at q = 0 is 1/4 = 5 kT


def _tilted(c: float, minimum: float):
    """U = (q^2 - 1)^2/4 + c q, unit mass, analysed at the minimum near ``minimum``."""
    q0 = float(mp.findroot(lambda q: q ** 3 - q + c, minimum))
    return from_callables(lambda q: (q[:, 0] ** 2 - 1) ** 2 / 4 + c * q[:, 0],
                          lambda q: q ** 3 - q + c, [1.0], minimum=[q0],
                          hessian=lambda q: (3 * q * q - 1)[:, :, None],
                          description=f"double well c = {c}")


@pytest.mark.parametrize("c, start", [(0.0, 1.0), (0.0, -1.0), (0.02, 1.0), (-0.03, 1.0)])
def test_a_low_barrier_s_draws_cover_both_basins_with_the_boltzmann_weights(c, start):
    """At kT = 0.05 the barrier is about 5 kT: the walk from either minimum goes over it to
    the far wall, where U rises 40 kT above the lower basin's bottom (to the grid's step
    a/8), and 20000 exact draws put the Boltzmann share in the left basin (to 4.5 binomial
    standard errors) and give its <q^2> (to 4.5 standard errors), both from 50-digit
    quadratures; the tilt c moves the weight to the lower basin."""
    pot = _tilted(c, start)
    lo, hi, notes = well(pot, KT)

    def u(q):
        return (q * q - 1) ** 2 / 4 + c * q

    with mp.workdps(50):
        bottom = min(u(mp.findroot(lambda q: q ** 3 - q + c, x)) for x in (-1, 1))
        edges = [float(mp.findroot(lambda q: u(q) - bottom - 40 * KT, x)) for x in (-2, 2)]

        def density(q):
            return mp.exp(-(u(q) - bottom) / KT)

        z = mp.quad(density, [-3, 0, 3])
        left = float(mp.quad(density, [-3, 0]) / z)
        q2 = float(mp.quad(lambda q: q * q * density(q), [-3, 0, 3]) / z)
        q4 = float(mp.quad(lambda q: q ** 4 * density(q), [-3, 0, 3]) / z)
    a = math.sqrt(KT / (3 * float(pot.minimum[0]) ** 2 - 1))
    assert lo == pytest.approx(edges[0], abs=a / 8) and hi == pytest.approx(edges[1], abs=a / 8)
    assert any("barrier" in n and "basins beyond" in n for n in notes)
    n = 20000
    q = draw(pot, KT, n, seed=4).q[:, 0]
    share = float(np.mean(q < 0))
    assert abs(share - left) <= 4.5 * math.sqrt(left * (1 - left) / n)
    assert abs(float(np.mean(q * q)) - q2) <= 4.5 * math.sqrt((q4 - q2 * q2) / n)


def test_a_barrier_followed_by_a_fall_or_a_plateau_is_still_not_confined():
    """U = q^2/2 - q^3/3 falls without bound past its barrier (1/6 = 3.3 kT at kT =
    0.05); a Lennard-Jones dimer 4 (r^-12 - r^-6) levels off 10 kT above its minimum at kT
    = 0.1: neither distribution exists, and both are refused."""
    cubic = from_callables(lambda q: q[:, 0] ** 2 / 2 - q[:, 0] ** 3 / 3,
                           lambda q: q - q * q, [1.0], minimum=[0.0],
                           hessian=lambda q: (1 - 2 * q)[:, :, None])
    with pytest.raises(StepsafeError, match="not confined"):
        well(cubic, KT)
    r0 = 2.0 ** (1 / 6)
    lj = from_callables(lambda r: 4 * (r[:, 0] ** -12 - r[:, 0] ** -6),
                        lambda r: 4 * (-12 * r ** -13 + 6 * r ** -7), [1.0], minimum=[r0],
                        hessian=lambda r: (4 * (156 * r ** -14 - 42 * r ** -8))[:, :, None])
    with pytest.raises(StepsafeError, match="not confined"):
        well(lj, 0.1)


def _own_failures(h: float, count: int, seed: int) -> int:
    """The test's own ensemble: exact draws of the 1-D double well at kT = 0.05 (inverse
    distribution function on a fine grid), p ~ N(0, kT), Yoshida's fourth-order triple jump
    of velocity Verlet (weights w1 = 1/(2 - 2^(1/3)), w0 = 1 - 2 w1) for 2000 steps; a
    trajectory fails when its energy leaves float64 or q leaves |q| < 10."""
    rng = np.random.default_rng(seed)
    s = np.linspace(-2.5, 2.5, 400001)
    energy = (s * s - 1) ** 2 / 4
    w = np.exp(-(energy - energy.min()) / KT)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    q = np.interp(rng.random(count), cdf / cdf[-1], s)
    p = rng.standard_normal(count) * math.sqrt(KT)
    w1 = 1 / (2 - 2 ** (1 / 3))
    dead = np.zeros(count, dtype=bool)
    with np.errstate(all="ignore"):
        for _ in range(2000):
            for a in (w1, 1 - 2 * w1, w1):
                p = p - 0.5 * a * h * (q * q - 1) * q
                q = q + a * h * p
                p = p - 0.5 * a * h * (q * q - 1) * q
            dead |= ~np.isfinite(p * p / 2 + (q * q - 1) ** 2 / 4) | (np.abs(q) > 10)
    return int(np.count_nonzero(dead))


SCENES = {"1-D": ('"p**2/2 + (q**2 - 1)**2/4"', "{q: [-2, 2], p: [-1, 1]}", ""),
          "2-D": ('"(px**2 + py**2)/2 + (x**2 - 1)**2/4 + y**2/2"',
                  "{x: [-2, 2], y: [-2, 2], px: [-1, 1], py: [-1, 1]}",
                  "  q: [x, y]\n  p: [px, py]\n")}


@pytest.mark.slow  # six checks at temperature and the test's own 10^4 trajectories
def test_the_1d_double_well_s_verdicts_are_its_2d_twin_s_and_the_own_integration_s(
        tmp_path: Path):
    """Yoshida4 on the double well at kT = 0.05 (barrier 5 kT), 2000 steps: the 1-D scene
    and its twin with a spectator coordinate + y^2/2 (drawn by Langevin dynamics) give the
    same verdict at h = 0.5 (SAFE), 0.62 (UNSAFE, a few failures in 2995) and 0.9 (UNSAFE);
    at 0.9 the failure fractions agree with each other and with the test's own
    integration from exact draws (10^4 trajectories) to 4.5 standard errors."""
    paths = {}
    for name, (hamiltonian, box, coordinates) in SCENES.items():
        path = tmp_path / f"{name}.yaml"
        path.write_text(f"method: yoshida4\nkT: {KT}\nsteps: 2000\nsystem:\n"
                        f"  hamiltonian: {hamiltonian}\n{coordinates}  box: {box}\n")
        paths[name] = str(path)
    own = {h: _own_failures(h, 10000, seed=3) for h in (0.5, 0.62, 0.9)}
    assert own[0.5] == 0 and 0 < own[0.62] < 30 and own[0.9] > 800
    fractions = {}
    for h in (0.5, 0.62, 0.9):
        verdicts = {name: stepsafe.check(scene=path, h=h) for name, path in paths.items()}
        assert verdicts["1-D"].safe is verdicts["2-D"].safe is (h == 0.5)
        for name, r in verdicts.items():
            probes = [m["probes"][0] for m in r.record["thermal"]["minima"]]
            fractions[name, h] = (sum(pr["failures"] for pr in probes),
                                  sum(pr["trajectories"] for pr in probes))
    for name in SCENES:
        k, m = fractions[name, 0.9]
        f, g = k / m, own[0.9] / 10000
        se = math.sqrt(f * (1 - f) / m + g * (1 - g) / 10000)
        assert abs(f - g) <= 4.5 * se, (name, k, m, own[0.9])


def _morse(scale_e: float, scale_l: float, kept: bool):
    """U = E (1 - e^(-q/L))^2 / 2, unit mass; ``kept`` writes 1 - e^-x as -expm1(-x), which
    keeps its digits near the minimum."""
    def one_minus(x):
        return -np.expm1(-x) if kept else 1.0 - np.exp(-x)

    return from_callables(lambda q: 0.5 * scale_e * one_minus(q[:, 0] / scale_l) ** 2,
                          lambda q: scale_e / scale_l * one_minus(q / scale_l)
                          * np.exp(-q / scale_l),
                          [1.0], minimum=[0.0],
                          hessian=lambda q: (scale_e / scale_l ** 2 * (
                              2 * np.exp(-2 * q / scale_l) - np.exp(-q / scale_l)))[:, :, None])


@settings(max_examples=40, deadline=None)
@given(log_e=st.floats(-250, 250), log_l=st.floats(-100, 100), kept=st.booleans(),
       log_ratio=st.floats(-6, -1.5))
def test_a_resolved_well_is_drawn_at_every_scale(log_e, log_l, kept, log_ratio):
    """Morse at kT/E from 1e-6 to 0.03, E and L over 500 and 200 decades: float64 resolves U
    (its rounding is about 1e-16 of E (1 - e^-x) ~ 1e-16 sqrt(kT E), far below kT), so the
    well is drawn, the same in units of L at every scale (a curvature E/L^2 beyond float64's
    normal range is refused, saying so)."""
    e, length = 10.0 ** log_e, 10.0 ** log_l
    kT = 10.0 ** log_ratio * e
    if e / length ** 2 < sys.float_info.min:  # no normal float64 curvature (or none): refused
        with pytest.raises(StepsafeError, match="curvature at (the|its) minimum"):
            well(_morse(e, length, kept), kT)
        return
    if log_e - 2 * log_l > 306:  # at float64's edge: refused as not finite, or drawn right
        try:
            lo, hi, _ = well(_morse(e, length, kept), kT)
        except StepsafeError as exc:
            assert "not finite" in exc.message
            return
    else:
        lo, hi, _ = well(_morse(e, length, kept), kT)
    lo1, hi1, _ = well(_morse(1.0, 1.0, kept), 10.0 ** log_ratio)
    assert lo / length == pytest.approx(lo1, rel=1e-6)
    assert hi / length == pytest.approx(hi1, rel=1e-6)


@pytest.mark.parametrize("kT", [1e-24, 1e-28, 1e-40, 1e-100, 4.9e-324])
def test_a_well_float64_does_not_resolve_at_kT_is_refused_as_such(kT):
    """U = (1 - e^-q)^2/2 at kT <= 1e-24: 1 - e^-q near q ~ sqrt(kT) keeps only
    1e-16 / sqrt(kT) of its digits (at 1e-28 the energy's noise is 1.6% of kT; from about
    1e-32 on e^-q rounds to 1 and U to 0): refused as unresolved, not as a band or as
    "not confined". Written with expm1 the same well is resolved down to kT = 1e-100."""
    with pytest.raises(StepsafeError, match="^float64 does not resolve U at kT"):
        well(_morse(1.0, 1.0, kept=False), kT)
    if kT >= 1e-100:
        lo, hi, _ = well(_morse(1.0, 1.0, kept=True), kT)
        assert lo < 0 < hi


def test_check_at_a_kT_float64_cannot_resolve_exits_2_naming_it():
    morse = str(Path(__file__).parent.parent / "examples" / "morse.yaml")
    code, out, err = _cli("check", morse, "--step", "0.8", "--kT", "1e-28")
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "$.system.hamiltonian" in err and "float64 does not resolve U" in err
