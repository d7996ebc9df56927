"""The fixed-point solver model counts what a real fixed-point solver does."""

from __future__ import annotations

import math

import numpy as np
import pytest

import stepsafe
from stepsafe.core.solver import DEFAULT_TOL, fixed_point_cost


def _solve(method: stepsafe.Integrator, q: float, p: float, h: float, tol: float):
    """A real fixed-point solver on q'' = -q (beta = 1), counting force evaluations: the
    algorithm of stepsafe.core.solver, written independently from the tableau."""
    t = method.partitioned_tableau
    s = t.stages
    calls = {"n": 0}
    fixed = ~np.any(t.A_q != 0, axis=1)
    fsal = any(np.allclose(row, t.b_q, rtol=0, atol=1e-15) for row in t.A_q)

    def force(Q, which):
        calls["n"] += int(np.count_nonzero(which))
        return -Q

    f_fixed = -q  # force at the stages fixed at q: reused (FSAL) or one evaluation
    if fixed.any() and not fsal:
        calls["n"] += 1
    Q, P = np.full(s, q), np.full(s, p)
    for iteration in range(1, 2000):
        F = np.where(fixed, f_fixed, force(Q, ~fixed))
        Q_new, P_new = q + h * t.A_q @ P, p + h * t.A_p @ F
        change = max(np.abs(Q_new - Q).max(), np.abs(P_new - P).max())
        Q, P = Q_new, P_new
        if change <= tol * max(1.0, np.abs(Q).max(), np.abs(P).max()):
            F = np.where(fixed, f_fixed, force(Q, ~fixed))
            return iteration, calls["n"], (q + h * t.b_q @ P, p + h * t.b_p @ F)
    return None, None, None


@pytest.mark.parametrize("name, stages", [("gauss", 1), ("gauss", 2), ("gauss", 3),
                                          ("lobatto3ab", 2), ("lobatto3ab", 3),
                                          ("lobatto3ab", 4)])
@pytest.mark.parametrize("z", [0.05, 0.3, 1.0, 1.9])
def test_model_counts_the_real_solver(name, stages, z):
    method = stepsafe.method(name, stages=stages)
    model = fixed_point_cost(method.tableau, z)
    runs = [_solve(method, q, p, z, DEFAULT_TOL) for q, p in ((1.0, 0.0), (0.0, 1.0))]
    if model.iterations is None:
        assert all(r[0] is None for r in runs) or z >= model.limit * 0.9
        return
    worst = max(runs, key=lambda r: r[0])
    assert (model.iterations, model.evaluations) == (worst[0], worst[1])
    # and the converged step is the step: M(z) applied to the state
    M = stepsafe.transfer_matrices(method, [z])[0]
    np.testing.assert_allclose(np.array(runs[0][2]), M[:, 0], atol=1e-12)


def test_limits_are_where_the_iteration_diverges():
    """rho(z K) = 1: Gauss s = 2 at 2 sqrt 3, the midpoint rule at 2, Lobatto IIIA-IIIB
    s = 3 at sqrt 24; below the iteration converges (slowly), just above it does not."""
    for (name, s), limit in ((("gauss", 2), 2 * math.sqrt(3)), (("gauss", 1), 2.0),
                             (("lobatto3ab", 3), math.sqrt(24))):
        tableau = stepsafe.method(name, stages=s).tableau
        assert fixed_point_cost(tableau, 1.0).limit == pytest.approx(limit, rel=1e-12)
        assert fixed_point_cost(tableau, 0.9 * limit).iterations is not None
        assert fixed_point_cost(tableau, 1.01 * limit).iterations is None


def test_explicit_methods_cost_their_nominal_evaluations():
    cost = fixed_point_cost(stepsafe.method("pefrl").tableau, 1.0)
    assert cost.evaluations == 4 and cost.iterations == 0 and cost.limit == math.inf


def test_compare_costs_implicit_methods_by_their_solver(run):
    """compare's evaluations for an implicit method are the solver model's at the step it
    uses; nominal counting is one per stage; the solver's limit bounds h."""
    import json

    code, out, err = run("compare", "--beta", "1", "--tol-phase", "1e-6", "--methods",
                         "gauss:2,lobatto3ab:3,pefrl", "--json")
    assert code == 0, err
    rows = {r["method"]: r for r in json.loads(out)["methods"]}
    for name, s in (("gauss", 2), ("lobatto3ab", 3)):
        r = rows[f"{name}-s{s}"]
        cost = fixed_point_cost(stepsafe.method(name, stages=s).tableau, r["h"])
        assert (r["evaluations"], r["solver_iterations"]) == (cost.evaluations,
                                                              cost.iterations)
        assert r["cost"] == pytest.approx(cost.evaluations / r["h"])
    assert rows["pefrl"]["solver_iterations"] is None and rows["pefrl"]["evaluations"] == 4
    code, out, _ = run("compare", "--beta", "1", "--methods", "gauss:1", "--json")
    row = json.loads(out)["methods"][0]
    assert row["bound_by"] == "solver" and row["h"] == pytest.approx(0.9 * 2.0)
    code, out, _ = run("compare", "--beta", "1", "--methods", "gauss:2", "--solver", "nominal",
                       "--json")
    assert json.loads(out)["methods"][0]["evaluations"] == 2


def test_advise_names_the_fixed_point_limit(run_json):
    data = run_json("advise", "--method", "gauss", "-s", "2", "--beta", "2")
    assert data["fixed_point_limit"] == pytest.approx(math.sqrt(3), rel=1e-12)  # 2 sqrt 3 / 2
    assert run_json("advise", "--method", "pefrl", "--beta", "2")["fixed_point_limit"] is None
