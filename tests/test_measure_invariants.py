"""``measure`` beyond the energy: declared invariants, the error against time fitted, wall
time, and ``--tol-trajectory`` on an orbit with no vibration, each against an integration
written here (Kepler's problem: RK4 and splittings in numpy, the exact orbit from Kepler's
equation)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from test_reference_floor import KEPLER, kepler_state, splitting_run

import stepsafe

INVARIANTS = KEPLER + """\
  invariants:
    angular momentum: "x*py - y*px"
"""


@pytest.fixture
def kepler(tmp_path: Path) -> Path:
    path = tmp_path / "kepler.yaml"
    path.write_text(INVARIANTS)
    return path


def _force(q: np.ndarray) -> np.ndarray:
    return -q / np.dot(q, q) ** 1.5


def _rk4_states(h: float, n: int) -> np.ndarray:
    """Every state k = 0 .. n of classical RK4 on Kepler from periapsis."""
    def f(x):
        return np.concatenate([x[2:], _force(x[:2])])

    x = kepler_state(0.0)
    out = [x]
    for _ in range(n):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(x)
    return np.array(out)


def _verlet_states(h: float, n: int) -> np.ndarray:
    """Every state of kick-drift-kick Verlet on Kepler from periapsis."""
    x = kepler_state(0.0)
    q, p = x[:2].copy(), x[2:].copy()
    out = [x]
    for _ in range(n):
        p = p + h / 2 * _force(q)
        q = q + h * p
        p = p + h / 2 * _force(q)
        out.append(np.concatenate([q, p]))
    return np.array(out)


def _fit(t: np.ndarray, e: np.ndarray) -> tuple[float, float, float]:
    """(spread, least-squares slope, R^2) of e against t, by numpy."""
    slope = np.polyfit(t, e, 1)[0]
    r2 = np.corrcoef(t, e)[0, 1] ** 2
    return float(e.max() - e.min()), float(slope), float(r2)


def _energy(X: np.ndarray) -> np.ndarray:
    return 0.5 * (X[:, 2] ** 2 + X[:, 3] ** 2) - 1 / np.hypot(X[:, 0], X[:, 1])


def _momentum(X: np.ndarray) -> np.ndarray:
    return X[:, 0] * X[:, 3] - X[:, 1] * X[:, 2]


@pytest.mark.slow
@pytest.mark.parametrize("name, states, behaviour", [("rk4", _rk4_states, "drift"),
                                                      ("verlet", _verlet_states, "bounded")])
def test_invariants_and_the_fit_against_time(kepler, name, states, behaviour):
    """RK4 drifts in energy and angular momentum over four orbits at h = T/600, Verlet's
    energy oscillates: the reported spread, slope and R^2 of each relative error are those
    of numpy's fit through every step of the run written here."""
    T = 8 * math.pi
    n = 600
    row = stepsafe.measure(name, [T / n], scene=str(kepler), time=T,
                           initial=list(kepler_state(0.0))).rows[0]
    X = states(T / n, n)
    t = T / n * np.arange(n + 1)
    e = _energy(X)
    spread, slope, r2 = _fit(t, (e - e[0]) / abs(e[0]))
    assert row.energy_error == pytest.approx(spread, rel=1e-6)
    assert row.energy_drift == pytest.approx(slope, rel=1e-6)
    assert row.energy_r2 == pytest.approx(r2, rel=1e-6, abs=1e-9)
    assert row.energy_behaviour == behaviour == ("drift" if r2 >= 0.5 else "bounded")
    (inv,) = row.invariants
    L = _momentum(X)
    spread, slope, r2 = _fit(t, (L - L[0]) / abs(L[0]))
    assert inv.name == "angular momentum"
    if name == "rk4":
        assert inv.spread == pytest.approx(spread, rel=1e-6)
        assert inv.drift == pytest.approx(slope, rel=1e-6)
        assert inv.r2 == pytest.approx(r2, rel=1e-6) and inv.behaviour == "drift"
    else:  # a splitting keeps q x p exactly: rounding only, on both sides
        assert inv.spread < 1e-13 and spread < 1e-13


@pytest.mark.slow
def test_wall_time_is_the_runs_own(kepler):
    """The seconds per unit time, times T, are at most the wall time of the whole call."""
    T = 2 * math.pi
    began = time.perf_counter()
    row = stepsafe.measure("verlet", [T / 100], scene=str(kepler), time=T,
                           initial=list(kepler_state(0.0))).rows[0]
    elapsed = time.perf_counter() - began
    assert 0 < row.seconds_per_time * row.time <= elapsed


@pytest.mark.parametrize("text, key", [("x*py - z*px", "invariants.angular momentum"),
                                       ("x*py - ", "invariants.angular momentum")])
def test_bad_invariants_name_their_key(tmp_path, run, text, key):
    path = tmp_path / "k.yaml"
    path.write_text(KEPLER + f'  invariants:\n    angular momentum: "{text}"\n')
    code, _, err = run("measure", str(path), "--method", "verlet", "--h", "0.1", "--time",
                       "1", "--initial", "0.5,0,0,1.7")
    assert code == 2 and err.count("\n") == 1 and key in err
    path.write_text(KEPLER + "  invariants: [x]\n")
    code, _, err = run("measure", str(path), "--method", "verlet", "--h", "0.1", "--time",
                       "1", "--initial", "0.5,0,0,1.7")
    assert code == 2 and "$.system.invariants" in err


@pytest.mark.slow
def test_tol_trajectory_on_an_orbit_with_no_vibration(kepler):
    """Kepler has no equilibrium, so no linear prediction: the refinement starts at T/1000
    and brackets by runs. Its h meets the tolerance against the exact orbit (the run
    written here) and a step 1% longer does not, up to the reference's floor."""
    T = 2 * math.pi
    tol = 1e-4
    result = stepsafe.refine("verlet", "trajectory", tol, scene=str(kepler), time=T,
                             initial=list(kepler_state(0.0)))
    assert result.predicted is None and result.limited_by == "tolerance"
    h = result.h
    exact = kepler_state(T)

    def true_error(step: float) -> tuple[float, float]:
        n = math.ceil(T / step * (1 - 1e-12))
        return (np.linalg.norm(splitting_run("verlet", step, n) - kepler_state(n * step))
                / np.linalg.norm(kepler_state(n * step)), n * step)

    error, _ = true_error(h)
    assert error <= tol * (1 + 1e-6) and result.error == pytest.approx(error, rel=1e-6)
    assert any(r.h > h and r.trajectory_error > tol for r in result.runs.rows)
    assert true_error(h * 1.01)[0] > tol
    assert np.linalg.norm(exact) > 0


PENDULUM = {"hamiltonian": "p**2/2 - cos(q)", "box": {"q": [-4, 4], "p": [-1, 1]},
            "invariants": {"twice the energy": "p**2 - 2*cos(q)"}}


def _pendulum_states(name: str, h: float, n: int) -> np.ndarray:
    """Every (q, p) of RK4 or kick-drift-kick Verlet on the pendulum from (1, 0)."""
    x = np.array([1.0, 0.0])
    out = [x]
    for _ in range(n):
        if name == "rk4":
            def f(y):
                return np.array([y[1], -math.sin(y[0])])
            k1 = f(x)
            k2 = f(x + h / 2 * k1)
            k3 = f(x + h / 2 * k2)
            k4 = f(x + h * k3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        else:
            p = x[1] - h / 2 * math.sin(x[0])
            q = x[0] + h * p
            x = np.array([q, p - h / 2 * math.sin(q)])
        out.append(x)
    return np.array(out)


@pytest.mark.parametrize("name", ["rk4", "verlet"])
def test_the_fit_on_the_pendulum(name):
    """The pendulum from (1, 0) at h = 0.2 for T = 40: RK4's energy drifts (the line
    explains nearly all its variance), Verlet's oscillates; the spread, slope and R^2 of
    the energy error and of a declared invariant (2H, relative to its own start) are
    numpy's fit through every step of the run written here."""
    row = stepsafe.measure(name, [0.2], system=PENDULUM, initial=[1.0, 0.0],
                           time=40.0).rows[0]
    X = _pendulum_states(name, 0.2, 200)
    t = 0.2 * np.arange(201)
    H = X[:, 1] ** 2 / 2 - np.cos(X[:, 0])
    spread, slope, r2 = _fit(t, (H - H[0]) / abs(H[0] + 1))  # (over H(0) - H_e, H_e = -1)
    assert row.energy_drift == pytest.approx(slope, rel=1e-6)
    assert row.energy_r2 == pytest.approx(r2, rel=1e-6, abs=1e-9)
    assert row.energy_behaviour == ("drift" if name == "rk4" else "bounded")
    assert (r2 >= 0.5) is (name == "rk4")
    (inv,) = row.invariants
    twice = X[:, 1] ** 2 - 2 * np.cos(X[:, 0])
    spread, slope, r2 = _fit(t, (twice - twice[0]) / abs(twice[0]))
    assert (inv.spread, inv.drift) == (pytest.approx(spread, rel=1e-6),
                                       pytest.approx(slope, rel=1e-6))
    assert inv.r2 == pytest.approx(r2, rel=1e-6, abs=1e-9)
    assert inv.behaviour == row.energy_behaviour


def test_wall_time_is_a_part_of_the_call():
    """The run's seconds per unit time, times T, are at most the whole call's wall time."""
    began = time.perf_counter()
    row = stepsafe.measure("verlet", [0.1], system=PENDULUM, initial=[1.0, 0.0],
                           time=20.0).rows[0]
    elapsed = time.perf_counter() - began
    assert 0 < row.seconds_per_time * row.time <= elapsed
