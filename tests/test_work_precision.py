"""Work-precision diagrams with steps chosen per method: every run ends at T (h = T / n),
the first just inside the method's first boundary, each next with twice the steps; each
point is checked against an integration written here and a scipy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import stepsafe
from stepsafe.api.measure import work_precision

PENDULUM = {"hamiltonian": "p**2/2 - cos(q)", "box": {"q": [-4, 4], "p": [-1, 1]}}


def _splitting(name: str, h: float, n: int, x0: tuple[float, float]) -> np.ndarray:
    """n steps of the splitting ``name`` on the pendulum, from its drift/kick data."""
    tableau = stepsafe.method(name).tableau
    if tableau.kind == "composition":
        tableau = tableau.as_splitting()
    q, p = x0
    for _ in range(n):
        for i in range(len(tableau.drift)):
            q += tableau.drift[i] * h * p
            if i < len(tableau.kick):
                p -= tableau.kick[i] * h * math.sin(q)
    return np.array([q, p])


def test_points_and_their_steps_on_the_pendulum():
    """Verlet and PEFRL from (0.3, 0) over T = 20 (beta = 1): the first run takes
    ceil(T / (0.9 z*)) steps, each next twice as many, up to max_steps; every point's
    trajectory error is the error of the run written here against DOP853 at 1e-13 (in the
    energy norm of the centre's Hessian, the identity here), to the reference's floor."""
    T, x0 = 20.0, (0.3, 0.0)
    reports = work_precision(["verlet", "pefrl"], system=PENDULUM, time=T,
                             initial=list(x0), budget=600.0, max_steps=1000)
    reference = solve_ivp(lambda t, y: [y[1], -math.sin(y[0])], (0, T), x0,
                          method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    for report, name, z_star in zip(reports, ("verlet", "pefrl"), (2.0, 2.98945)):
        assert report.method == name
        steps = [row.steps for row in report.rows]
        first = math.ceil(T / (0.9 * z_star))
        assert steps == [first * 2 ** k for k in range(len(steps))]
        assert steps[-1] <= 1000 < 2 * steps[-1]
        for row in report.rows:
            assert row.status == "ok" and row.h == T / row.steps and row.time == T
            error = np.linalg.norm(_splitting(name, row.h, row.steps, x0) - reference) \
                / np.linalg.norm(reference)
            if row.below_reference:
                assert error < 2 * row.reference_error
            else:
                assert abs(row.trajectory_error - error) <= \
                    2 * row.reference_error + 1e-9 * error
    # PEFRL starts and ends with a drift: each of its kicks is a force, every step
    pefrl, kicks = reports[1].rows[0], len(stepsafe.method("pefrl").tableau.kick)
    assert kicks == 4
    assert pefrl.evaluations_per_time == pytest.approx(kicks * pefrl.steps / T)


def test_runs_stop_at_the_reference_floor():
    """kahan-li8 on the harmonic pendulum region reaches the floor within a few doublings:
    its last point is within 10 times the floor (or below it) and no run follows."""
    reports = work_precision(["kahan-li8"], system=PENDULUM, time=5.0, initial=[0.3, 0.0],
                             budget=600.0, max_steps=100000)
    rows = reports[0].rows
    last = rows[-1]
    assert last.below_reference or last.trajectory_error <= 10 * last.reference_error
    assert all(not r.below_reference and r.trajectory_error > 10 * r.reference_error
               for r in rows[:-1])


def test_the_plot_with_a_budget(run, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "wp.png"
    code, text, err = run("plot", "--work-precision", "examples/pendulum.yaml", "--methods",
                          "verlet,pefrl", "--time", "10", "--budget", "600", "-o", str(out))
    assert code == 0, err
    assert out.stat().st_size > 0 and "verlet: " in text and "pefrl: " in text
    code, _, err = run("plot", "--work-precision", "examples/pendulum.yaml", "--methods",
                       "verlet", "--budget", "5", "--h-range", "0.1,1,3", "-o", str(out))
    assert code == 2 and "--budget" in err


def test_compare_says_how_far_the_linear_ranking_is_from_the_measured(run_json):
    """compare --measure on the pendulum: each method's measured cost is the force rate at
    which a run written here, at h = forces per step / that cost, has the trajectory error
    the phase tolerance allows over T (within the interpolation between doublings); the
    ratios are those costs over the linear ranking's first."""
    T, tol_phase = 20.0, 1e-4
    data = run_json("compare", "--beta", "1", "--tol-phase", str(tol_phase), "--methods",
                    "verlet,pefrl", "--measure", "examples/pendulum.yaml", "--time", str(T),
                    "--budget", "600")
    measured = data["measured"]
    tol = 2 * math.sin(tol_phase * T / 2)
    assert measured["tolerance"] == pytest.approx(tol) and measured["time"] == T
    first = data["methods"][0]["method"]
    assert measured["first"] == first == "pefrl"
    x0 = (0.4, 0.0)  # the scene's default start: a tenth of the box from the centre
    reference = solve_ivp(lambda t, y: [y[1], -math.sin(y[0])], (0, T), x0,
                          method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    costs = {}
    for o in measured["methods"]:
        name = o["method"]
        kicks = len(stepsafe.method(name).tableau.as_splitting().kick
                    if stepsafe.method(name).tableau.kind == "composition"
                    else stepsafe.method(name).tableau.kick)
        forces = 1 if name == "verlet" else kicks  # (Verlet's last kick is the next first)
        n = round(T * o["measured_cost"] / forces)
        error = np.linalg.norm(_splitting(name, T / n, n, x0) - reference) \
            / np.linalg.norm(reference)
        assert tol / 1.5 <= error <= tol * 1.5, (name, error, tol)
        costs[name] = o["measured_cost"]
        predicted = next(r["cost"] for r in data["methods"] if r["method"] == name)
        assert o["predicted_cost"] == predicted
    for o in measured["methods"]:
        assert o["measured_ratio"] == pytest.approx(costs[o["method"]] / costs[first])
    assert measured["measured_order"] == sorted(costs, key=costs.get)
    verlet = next(o for o in measured["methods"] if o["method"] == "verlet")
    # as the README quotes them
    assert (f"{verlet['predicted_ratio']:.3g}", f"{verlet['measured_ratio']:.3g}") == \
        ("5.83", "5.55")
