"""The fixed-point solver model counts what a real fixed-point solver does."""

from __future__ import annotations

import math

import numpy as np
import pytest

import stepsafe
from stepsafe.core.solver import DEFAULT_TOL, fixed_point_cost

#: The methods whose last stage ends at the step's q (Lobatto IIIA: collocation at c = 1),
#: so that its force is the next step's first: known from the method's construction.
ENDS_AT_THE_STEP = {"lobatto3ab"}


def _solve(method: stepsafe.Integrator, q: float, p: float, h: float, tol: float,
           order: str = "gauss-seidel", reuse: bool = False):
    """A real fixed-point solver on q'' = -q (beta = 1), counting force evaluations,
    written independently from the tableau: ``gauss-seidel`` order (positions from the
    momenta, forces at the new positions, momenta from those forces; the update reuses the
    last forces) or ``jacobi`` order (every stage from the previous pass; the update
    evaluates the forces once more). ``reuse``: the stage fixed at q takes its force from
    the previous step."""
    t = method.partitioned_tableau
    s = t.stages
    calls = {"n": 0}
    fixed = ~np.any(t.A_q != 0, axis=1)

    def force(Q, which):
        calls["n"] += int(np.count_nonzero(which))
        return -Q

    f_fixed = -q  # force at the stages fixed at q: reused (FSAL) or one evaluation
    if fixed.any() and not reuse:
        calls["n"] += 1
    Q, P = np.full(s, q), np.full(s, p)
    for iteration in range(1, 2000):
        if order == "jacobi":
            F = np.where(fixed, f_fixed, force(Q, ~fixed))
            Q_new, P_new = q + h * t.A_q @ P, p + h * t.A_p @ F
        else:
            Q_new = q + h * t.A_q @ P
            F = np.where(fixed, f_fixed, force(Q_new, ~fixed))
            P_new = p + h * t.A_p @ F
        change = max(np.abs(Q_new - Q).max(), np.abs(P_new - P).max())
        Q, P = Q_new, P_new
        if change <= tol * max(1.0, np.abs(Q).max(), np.abs(P).max()):
            if order == "jacobi":
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
    runs = [_solve(method, q, p, z, DEFAULT_TOL, reuse=name in ENDS_AT_THE_STEP)
            for q, p in ((1.0, 0.0), (0.0, 1.0))]
    if model.iterations is None:
        assert all(r[0] is None for r in runs) or z >= model.limit * 0.9
        return
    worst = max(runs, key=lambda r: r[0])
    assert (model.iterations, model.evaluations) == (worst[0], worst[1])
    # and the converged step is the step: M(z) applied to the state
    M = stepsafe.transfer_matrices(method, [z])[0]
    np.testing.assert_allclose(np.array(runs[0][2]), M[:, 0], atol=1e-12)


@pytest.mark.parametrize("name, stages, z", [("gauss", 2, 0.164), ("lobatto3ab", 3, 0.2316),
                                             ("gauss", 3, 1.0), ("lobatto3ab", 4, 0.5)])
def test_gauss_seidel_order_needs_fewer_evaluations_than_jacobi(name, stages, z):
    """The sweep that takes the forces at the new positions converges at the square of the
    Jacobi order's rate: Gauss s = 2 at z = 0.164 needs 14 force evaluations per step (7
    passes, the update reusing the last forces) where the Jacobi order needs 24 (11 passes
    and the update), Lobatto IIIA-IIIB s = 3 at 0.2316 14 where Jacobi needs 26."""
    method = stepsafe.method(name, stages=stages)
    reuse = name in ENDS_AT_THE_STEP
    worst = {order: max(_solve(method, q, p, z, DEFAULT_TOL, order, reuse)[:2]
                        for q, p in ((1.0, 0.0), (0.0, 1.0)))
             for order in ("gauss-seidel", "jacobi")}
    model = fixed_point_cost(method.tableau, z)
    assert (model.iterations, model.evaluations) == worst["gauss-seidel"]
    assert worst["gauss-seidel"][1] < worst["jacobi"][1]
    if (name, stages) == ("gauss", 2):
        assert (worst["gauss-seidel"][1], worst["jacobi"][1]) == (14, 24)
    if (name, stages) == ("lobatto3ab", 3):
        assert (worst["gauss-seidel"][1], worst["jacobi"][1]) == (14, 26)


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
                         "gauss:2,lobatto3ab:3,pefrl", "--solver", "fixed-point", "--json")
    assert code == 0, err
    rows = {r["method"]: r for r in json.loads(out)["methods"]}
    for name, s in (("gauss", 2), ("lobatto3ab", 3)):
        r = rows[f"{name}-s{s}"]
        cost = fixed_point_cost(stepsafe.method(name, stages=s).tableau, r["h"])
        assert (r["evaluations"], r["solver_iterations"]) == (cost.evaluations,
                                                              cost.iterations)
        assert r["cost"] == pytest.approx(cost.evaluations / r["h"])
    assert rows["pefrl"]["solver_iterations"] is None and rows["pefrl"]["evaluations"] == 4
    code, out, _ = run("compare", "--beta", "1", "--methods", "gauss:1", "--solver",
                       "fixed-point", "--json")
    row = json.loads(out)["methods"][0]
    assert row["bound_by"] == "solver" and row["h"] == pytest.approx(0.9 * 2.0)
    code, out, _ = run("compare", "--beta", "1", "--methods", "gauss:2", "--solver", "nominal",
                       "--json")
    assert json.loads(out)["methods"][0]["evaluations"] == 2


def test_advise_names_the_fixed_point_limit(run_json):
    data = run_json("advise", "--method", "gauss", "-s", "2", "--beta", "2")
    assert data["fixed_point_limit"] == pytest.approx(math.sqrt(3), rel=1e-12)  # 2 sqrt 3 / 2
    assert run_json("advise", "--method", "pefrl", "--beta", "2")["fixed_point_limit"] is None


@pytest.mark.parametrize("jacobian_cost", [0.0, 1.0, 4.0, 100.0])
@pytest.mark.parametrize("tol", [1e-3, 1e-6, 1e-9])
def test_compare_ranks_implicit_methods_with_the_cheaper_solver(run_json, jacobian_cost, tol):
    """By default each implicit method is costed with whichever solver is cheaper per unit
    time at the step it allows: fixed-point iteration (counted by the independent solver
    above at its step, capped at 0.9 of its limit) or simplified Newton (2 passes on the
    oscillator and the update, s (2 + 1) forces for s varying stages, plus the Jacobian's
    cost); the row says which, and the ranking follows those costs."""
    names = {"gauss-s1": ("gauss", 1), "gauss-s2": ("gauss", 2),
             "lobatto3ab-s3": ("lobatto3ab", 3)}
    data = run_json("compare", "--beta", "1", "--tol-phase", str(tol), "--methods",
                    "gauss:1,gauss:2,lobatto3ab:3", "--jacobian-cost", str(jacobian_cost))
    fixed_point = {r["method"]: r for r in run_json(
        "compare", "--beta", "1", "--tol-phase", str(tol), "--methods",
        "gauss:1,gauss:2,lobatto3ab:3", "--solver", "fixed-point")["methods"]}
    assert data["solver"] == "best" and data["jacobian_cost"] == jacobian_cost
    for r in data["methods"]:
        name, s = names[r["method"]]
        method = stepsafe.method(name, stages=s)
        h_fp = fixed_point[r["method"]]["h"]
        evals = max(_solve(method, q, p, h_fp, DEFAULT_TOL, reuse=name in ENDS_AT_THE_STEP)[1]
                    for q, p in ((1.0, 0.0), (0.0, 1.0)))
        varying = s - 1 if name == "lobatto3ab" else s
        h_newton = r["h_tol"] if r["h_tol"] < r["h_max"] else r["h_max"]
        costs = {"fixed-point": evals / h_fp,
                 "newton": (varying * 3 + jacobian_cost) / h_newton}
        cheaper = min(costs, key=costs.get)
        assert r["solver"] == cheaper or costs["fixed-point"] == pytest.approx(costs["newton"])
        assert r["cost"] == pytest.approx(min(costs.values()), rel=1e-12)
        assert r["jacobians"] == (1 if r["solver"] == "newton" else None)
    ranked = [r["cost"] for r in data["methods"]]
    assert ranked == sorted(ranked)
