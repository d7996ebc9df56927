"""Every library method reaches its claimed order on a nonlinear problem (the pendulum).

Linear-problem phase error alone does not prove order (a table transcribed with kicks and
drifts swapped can look right on the oscillator and be 3rd order on the pendulum), so the
global error at T of H = p^2/2 - cos q is measured in 40-digit arithmetic against the
exact solution (Jacobi elliptic functions at 50 digits), and the observed order
log2(e(h)/e(h/2)) at the finest step pair must be within 0.3 of the claim.
"""

from __future__ import annotations

from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from integrate import integrate, mp_method

from stepsafe.methods.library import builtin_names

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = [n for n in builtin_names(single_force=True) if n not in ("gauss", "lobatto3ab")]
T = 1
Q0, P0 = 1, "0.5"
DPS = 40


def force(q):
    return -mp.sin(q)


def pendulum(q0, p0, t):
    """The exact pendulum flow of H = p^2/2 - cos q on a libration (E = H < 1) started
    with p0 > 0: with m = k^2 = (E + 1)/2, sin(q/2) = k sn(u, m) and p = 2k cn(u, m), where
    u = u0 + t and sn(u0) = sin(q0/2)/k with cn(u0) > 0 (u0 = F(asin(sin(q0/2)/k) | m))."""
    E = p0 ** 2 / 2 - mp.cos(q0)
    assert E < 1 and p0 > 0
    m = (E + 1) / 2
    k = mp.sqrt(m)
    u = mp.ellipf(mp.asin(mp.sin(q0 / 2) / k), m) + t
    return [2 * mp.asin(k * mp.ellipfun("sn", u, m=m)), 2 * k * mp.ellipfun("cn", u, m=m)]


def test_exact_pendulum_flow_solves_the_equations_of_motion():
    """The closed form starts at (q0, p0) and solves q' = p, p' = -sin q (derivatives by
    mpmath's numerical differentiation) along [0, T], so by uniqueness it is the flow."""
    with mp.workdps(DPS + 10):
        q0, p0 = mp.mpf(Q0), mp.mpf(P0)
        start = pendulum(q0, p0, 0)
        assert abs(start[0] - q0) < mp.mpf(10) ** -(DPS + 5) and abs(start[1] - p0) < \
            mp.mpf(10) ** -(DPS + 5)
        for t in mp.linspace(0, T, 5):
            q, p = pendulum(q0, p0, t)
            dq = mp.diff(lambda s: pendulum(q0, p0, s)[0], t)
            dp = mp.diff(lambda s: pendulum(q0, p0, s)[1], t)
            assert abs(dq - p) < mp.mpf(10) ** -DPS and abs(dp + mp.sin(q)) < mp.mpf(10) ** -DPS


@pytest.fixture(scope="module")
def reference():
    with mp.workdps(DPS + 10):
        return pendulum(mp.mpf(Q0), mp.mpf(P0), T)


def observed_order(m, reference, steps) -> float:
    with mp.workdps(DPS):
        errors = []
        for n in steps:
            q, p = integrate(m, Q0, P0, T, n, force)
            errors.append(mp.sqrt((q - reference[0]) ** 2 + (p - reference[1]) ** 2))
        return float(mp.log(errors[-2] / errors[-1], 2))


def steps_for(order: int) -> tuple[int, int]:
    # the finest pair keeps the error well above 1e-40 and in the asymptotic regime; at
    # order 10 it stays far above the ~1e-20 to which kahan-li10's published 20-digit
    # weights satisfy the order conditions (its error at h = 1/16 is 7e-20)
    if order >= 10:
        return (4, 8)
    return {1: (512, 1024), 2: (128, 256), 3: (64, 128), 4: (32, 64)}.get(order, (16, 32))


@pytest.mark.parametrize("name", LIBRARY)
def test_claimed_order_on_the_pendulum(name, reference):
    with mp.workdps(DPS):
        m = mp_method(name)
    assert abs(observed_order(m, reference, steps_for(m.order)) - m.order) <= 0.3


@pytest.mark.parametrize("family, s", [("gauss", 1), ("gauss", 2), ("gauss", 3),
                                       ("lobatto3ab", 2), ("lobatto3ab", 3),
                                       ("lobatto3ab", 4)])
def test_family_order(family, s, reference):
    with mp.workdps(DPS):
        m = mp_method(family, s)
    assert abs(observed_order(m, reference, steps_for(m.order)) - m.order) <= 0.3


def test_kahan_li10_error_floor(reference):
    """kahan-li10's published 20 digits hold its order conditions to about 1e-20: in
    40-digit arithmetic the error stops falling near 3e-20 (stated in the file and in
    docs/methods.md), which is why order 10 is measured at h = 1/4, 1/8."""
    with mp.workdps(DPS):
        m = mp_method("kahan-li10")
        errors = []
        for n in (16, 32):
            q, p = integrate(m, Q0, P0, T, n, force)
            errors.append(mp.sqrt((q - reference[0]) ** 2 + (p - reference[1]) ** 2))
    assert 1e-20 < errors[1] < 1e-19 and errors[0] / errors[1] < 4


@pytest.mark.parametrize("name, order", [("calvo-sanz-serna4", 3), ("mclachlan-atela4", 3),
                                         ("mclachlan-atela5", 3), ("ruth3", 3)])
def test_drift_kick_swapped_assignment(name, order, reference):
    """The files' comments state the order of the drift/kick-swapped assignment (what
    OrdinaryDiffEq.jl runs): RKN methods lose an order on the pendulum, Ruth's general
    splitting keeps its order 3. Swapped: the kicks become drifts, the drifts after the
    opening zero drift become kicks."""
    from integrate import MPMethod

    with mp.workdps(DPS):
        m = mp_method(name)
        drift, kick = m.data["drift"], m.data["kick"]
        assert drift[0] == 0
        swapped = MPMethod("splitting", order, {"drift": list(kick), "kick": list(drift[1:])})
    assert abs(observed_order(swapped, reference, steps_for(order)) - order) <= 0.3


def test_method_files_carry_facts_not_development_notes():
    """Sources and comments of the shipped files are third-person facts: no first-person
    notes, no reminders of what was not checked."""
    import re

    notes = re.compile(r"\bI [a-z]|\b(we|We|our)\b|brief|re-checked|not checked|TODO|FIXME"
                       r"|scratch|computed here|[Vv]erified|FOUND")
    for path in sorted((ROOT / "methods").glob("*.yaml")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            assert not notes.search(line), f"{path.name}:{number}: {line.strip()[:80]}"


@pytest.mark.parametrize("k", [-42, -10, 0, 10, 42])
def test_symmetry_does_not_depend_on_the_scale_of_the_coefficients(k):
    """drift 0.3, kick 1, drift 0.7 is not its own adjoint at any step: every coefficient
    times 2^-42 is not symmetric either (no absolute tolerance such as 1e-12); Verlet is,
    at every scale."""
    from stepsafe.methods.families import is_symmetric
    from stepsafe.methods.tableaux import Splitting

    s = 2.0 ** k
    assert not is_symmetric(Splitting(np.array([0.3, 0.7]) * s, np.array([1.0]) * s))
    assert is_symmetric(Splitting(np.array([0.5, 0.5]) * s, np.array([1.0]) * s))
    # a large palindromic coefficient does not hide a mismatch between two small ones
    hidden = np.array([0.5 - 1e-10, 1e3, -2e3, 1e3, 0.5 + 1e-10]) * s
    assert not is_symmetric(Splitting(hidden, np.full(4, 0.25) * s))


def test_a_huge_coefficient_does_not_hide_a_non_symplectic_entry():
    """b = (0.999, 0.001), a21 = 1e15, a12 cancelling entry (1, 2) of the condition: entry
    (1, 1), 2 b1 a11 - b1^2 = -0.998, is as far from 0 as it can be, though only 5e-13 of
    the largest product: each entry is judged on its own terms. Scaled Gauss s = 2 stays
    symplectic."""
    from support import method

    from stepsafe.methods.residuals import residuals
    from stepsafe.methods.tableaux import RungeKutta

    b = np.array([0.999, 0.001])
    a21, a22 = 1e15, b[1] / 2
    a12 = (b[0] * b[1] - b[1] * a21) / b[0]
    assert not residuals(RungeKutta(np.array([[0.0, a12], [a21, a22]]), b)).symplectic
    gauss = method("gauss", 2)
    for s in (2.0 ** -40, 1.0, 2.0 ** 40):
        assert residuals(RungeKutta(gauss.A * s, gauss.b * s)).symplectic
