"""The reference of ``measure`` has a known error: its floor (the difference of two
DOP853 runs at 2.5e-14 and 1e-13) bounds the reference's true error, measured here on
Kepler's problem against the solution of Kepler's equation, and no trajectory error below
that floor is reported as a number."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import stepsafe

E = 0.5  # eccentricity; a = 1, period 2 pi, starting at periapsis

KEPLER = """\
system:
  hamiltonian: "(px**2 + py**2)/2 - 1/sqrt(x**2 + y**2)"
  q: [x, y]
  p: [px, py]
  box: {x: [-2, 2], y: [-2, 2], px: [-2, 2], py: [-2, 2]}
"""


def kepler_state(t: float) -> np.ndarray:
    """The exact state at t from Kepler's equation ``E - e sin E = t`` (Newton's method to
    convergence in float64)."""
    anomaly = t
    for _ in range(100):
        step = (anomaly - E * math.sin(anomaly) - t) / (1 - E * math.cos(anomaly))
        anomaly -= step
        if abs(step) < 1e-16 * max(1.0, abs(anomaly)):
            break
    rate = 1 / (1 - E * math.cos(anomaly))
    root = math.sqrt(1 - E * E)
    return np.array([math.cos(anomaly) - E, root * math.sin(anomaly),
                     -math.sin(anomaly) * rate, root * math.cos(anomaly) * rate])


def splitting_run(name: str, h: float, n: int) -> np.ndarray:
    """n steps of the splitting ``name`` (its drift and kick coefficients) on Kepler,
    written here: drift q += a h p, kick p -= b h q / |q|^3."""
    tableau = stepsafe.method(name).tableau
    if tableau.kind == "composition":
        tableau = tableau.as_splitting()
    x = kepler_state(0.0)
    q, p = x[:2].copy(), x[2:].copy()
    drift, kick = tableau.drift, tableau.kick
    for _ in range(n):
        for i in range(len(drift)):
            q = q + drift[i] * h * p
            if i < len(kick):
                p = p - kick[i] * h * q / np.dot(q, q) ** 1.5
    return np.concatenate([q, p])


@pytest.fixture
def kepler(tmp_path: Path) -> Path:
    path = tmp_path / "kepler.yaml"
    path.write_text(KEPLER)
    return path


def test_the_floor_bounds_the_reference_and_hides_errors_below_it(kepler):
    """One orbit with kahan-li8 at h = T/250 (true error about 1e-13, below the floor) and
    at h = T/40 (about 1e-7): the floor is at least the DOP853 reference's true error and
    at most 20 times it; the large error is reported within the floor of its true value,
    the small one as below the floor."""
    from scipy.integrate import solve_ivp

    from stepsafe.systems.measurement import REFERENCE_TOL

    T = 2 * math.pi
    x0 = kepler_state(0.0)
    ns = (250, 40)
    report = stepsafe.measure("kahan-li8", [T / n for n in ns], scene=str(kepler), time=T,
                              initial=list(x0))
    exact = kepler_state(T)
    size = np.linalg.norm(exact)

    def rhs(_, y):
        return [y[2], y[3], *(-y[:2] / np.dot(y[:2], y[:2]) ** 1.5)]

    reference = solve_ivp(rhs, (0, T), x0, method="DOP853", rtol=REFERENCE_TOL,
                          atol=REFERENCE_TOL * np.abs(x0).max()).y[:, -1]
    reference_error = np.linalg.norm(reference - exact) / size
    for n, row in zip(ns, report.rows):
        assert row.status == "ok" and row.steps == n and row.time == pytest.approx(T)
        floor = row.reference_error
        assert reference_error <= floor <= 20 * reference_error
        true = np.linalg.norm(splitting_run("kahan-li8", T / n, n) - exact) / size
        if true > 10 * floor:
            assert not row.below_reference
            assert abs(row.trajectory_error - true) <= 1.01 * floor + 1e-3 * true
        else:
            assert true < floor and row.below_reference and row.trajectory_error is None
    assert report.rows[0].below_reference and not report.rows[1].below_reference
    assert "tolerance 2.5e-14" in report.reference


def test_the_text_prints_the_floor(kepler, run):
    T = 2 * math.pi
    x0 = ",".join(repr(float(v)) for v in kepler_state(0.0))
    code, out, err = run("measure", str(kepler), "--method", "kahan-li8", "--h",
                         repr(T / 250), "--time", repr(T), "--initial", x0)
    assert code == 0, err
    assert "The reference's own error at T" in out
    lines = out.splitlines()
    row = lines[lines.index(next(line for line in lines if line.lstrip().startswith("h "))) + 1]
    assert row.split()[7].startswith("<")  # the trajectory error column


@pytest.mark.slow
def test_ten_kepler_orbits_as_the_readme_says(kepler):
    """Kepler at e = 0.5 over 10 orbits: the floor is 3.5e-10 (a DOP853 reference at
    2.5e-14 is about 1e-10 off), and kahan-li8 at h = T/2000, whose true error is 4.8e-11,
    is reported below the floor rather than as the reference's error."""
    T = 20 * math.pi
    row = stepsafe.measure("kahan-li8", [T / 2000], scene=str(kepler), time=T,
                           initial=list(kepler_state(0.0))).rows[0]
    exact = kepler_state(T)
    true = np.linalg.norm(splitting_run("kahan-li8", T / 2000, 2000) - exact) \
        / np.linalg.norm(exact)
    assert f"{true:.2g}" == "4.8e-11" and f"{row.reference_error:.2g}" == "3.5e-10"
    assert row.below_reference and row.trajectory_error is None
