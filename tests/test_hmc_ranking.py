"""What ``hmc`` ranks methods by, checked against figures computed here independently.

* Gaussian targets of n modes of one frequency: a proposal's energy error is
  ``a X + b Y`` with X, Y independent chi^2_n (``a = (E + r) / 2``, ``b = -E / (E + r)``,
  ``r = sqrt(E^2 + 2E)``, E the expected error of one mode after L steps), so the
  acceptance ``2 P(Delta < 0)`` is ``2 I_x(n/2, n/2)`` with ``x = |b| / (a + |b|)`` (X / Y
  is F(n, n)): a regularized incomplete beta at 50 digits, E from the 50-digit L-th power of
  the one-step matrix. Gradients per step are counted here from each splitting's kicks, the
  last and the first of consecutive steps merged (first same as last) where the step starts
  and ends with a kick.
* The ranking criterion is named (``ranked_by``) in the report, the JSON and the text, for
  Gaussian targets and targets given by a potential.
"""

from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest
from support import method

from stepsafe import hmc
from stepsafe.core.hmc import Trajectory
from stepsafe.core.hmc_target.advice import TargetRow, _ranked, hmc_on_target
from stepsafe.core.hmc_target.draws import find_mode, sample
from stepsafe.core.hmc_target.potential import CallablePotential, target
from stepsafe.exceptions import StepsafeError
from stepsafe.reference import highprec as R

SPLITTINGS = ["verlet", "mclachlan2-min", "bcss2", "bcss3", "pefrl"]


def kicks_per_step(m) -> int:
    """Gradient evaluations per step of a splitting ``drift(a1) kick(b1) drift(a2) ...``:
    its nonzero kicks, one fewer when the step starts and ends with a kick (the last kick's
    gradient is the next step's first)."""
    ops = []
    for i, b in enumerate(m.kick):
        ops += [("d", float(m.drift[i])), ("k", float(b))]
    if len(m.drift) > len(m.kick):
        ops.append(("d", float(m.drift[-1])))
    ops = [op for op in ops if op[1] != 0.0]
    kicks = sum(kind == "k" for kind, _ in ops)
    return kicks - (1 if ops[0][0] == "k" and ops[-1][0] == "k" else 0)


def acceptance_mp(m, z: float, steps: int, n: int) -> float:
    """The acceptance of L = ``steps`` steps of splitting ``m`` on n modes at z = beta h, at
    50 digits (module docstring)."""
    with mp.workdps(50):
        d = [mp.mpf(float(x)) for x in m.drift]
        k = [mp.mpf(float(x)) for x in m.kick]
        d, k = [x / sum(d) for x in d], [x / sum(k) for x in k]  # exactly consistent
        M = R.transfer_matrix_splitting(d, k, mp.mpf(z), "oscillator")
        P = M ** steps
        E = (sum(P[i, j] ** 2 for i in range(2) for j in range(2)) - 2) / 2
        if E == 0:
            return 1.0
        r = mp.sqrt(E * E + 2 * E)
        a, b = (E + r) / 2, E / (E + r)
        return float(2 * mp.betainc(mp.mpf(n) / 2, mp.mpf(n) / 2, 0, b / (a + b),
                                    regularized=True))


@pytest.mark.parametrize("trajectory", [{"trajectory_steps": 12}, {"length": 3.0}],
                         ids=["steps", "length"])
def test_gaussian_ranking_is_gradients_per_accepted_proposal_at_the_L_run(trajectory):
    sigma, n = 0.5, 4
    report = hmc(SPLITTINGS, sigma=[sigma] * n, **trajectory)
    assert report.ranked_by == "gradients_per_accepted"
    independent, per_time = {}, {}
    for row in report.rows:
        m = method(row.method)
        L = trajectory.get("trajectory_steps") or max(1, math.floor(3.0 / row.h_target))
        assert row.steps == L
        acc = acceptance_mp(m, row.h_target / sigma, L, n)
        assert row.acceptance == pytest.approx(acc, rel=1e-9, abs=1e-12)
        assert row.evaluations == kicks_per_step(m)
        independent[row.method] = L * kicks_per_step(m) / acc
        per_time[row.method] = kicks_per_step(m) / (acc * row.h_target)
        assert row.gradients_per_accepted == pytest.approx(independent[row.method], rel=1e-9)
    # costs equal to 5 digits tie (h at target is searched to 1e-6): the cost per accepted
    # unit of time orders them
    order = sorted(independent, key=lambda name: (float(f"{independent[name]:.5g}"),
                                                  per_time[name]))
    assert [r.method for r in report.rows] == order
    assert [r.rank for r in report.rows] == list(range(1, len(order) + 1))


def test_without_a_trajectory_length_the_ranking_is_per_accepted_time():
    report = hmc(SPLITTINGS, sigma=[0.5] * 4)
    assert report.ranked_by == "gradients_per_time"
    costs = [r.gradients_per_time for r in report.rows]
    assert costs == sorted(costs)
    for row in report.rows:  # the bound over L: acceptance of sin^2(L theta) = 1
        assert row.gradients_per_time == pytest.approx(
            kicks_per_step(method(row.method)) / (row.acceptance * row.h_target), rel=1e-12)


def test_the_criterion_is_named_in_json_and_text(run, run_json):
    data = run_json("hmc", "--sigma", "1", "--sigma", "0.2", "--steps", "10",
                    "--methods", "verlet,bcss2")
    assert data["ranked_by"] == "gradients_per_accepted"
    ranked = sorted((r for r in data["methods"] if r["rank"]), key=lambda r: r["rank"])
    assert [r["gradients_per_accepted"] for r in ranked] == sorted(
        r["gradients_per_accepted"] for r in ranked)
    code, text, _ = run("hmc", "--sigma", "1", "--sigma", "0.2", "--steps", "10",
                        "--methods", "verlet,bcss2")
    assert code == 0
    assert "Ranked by gradients_per_accepted: gradient evaluations per accepted proposal " \
           "at the L run (L = 10)" in " ".join(text.split())
    text = run("hmc", "--sigma", "1", "--methods", "verlet,bcss2")[1]
    assert "Ranked by gradients_per_time" in " ".join(text.split())
    assert run_json("hmc", "--sigma", "1")["ranked_by"] == "gradients_per_time"


def standard_gaussian_2d() -> CallablePotential:
    return CallablePotential(lambda q: 0.5 * np.sum(q * q, axis=-1), lambda q: q, 2,
                             hessian=lambda q: np.broadcast_to(np.eye(2), q.shape[:-1] + (2, 2)))


def test_target_ranking_and_laplace_ranking_use_the_same_criterion():
    """On a potential (here the standard Gaussian in 2 d, whose mode's Gaussian is itself)
    the estimate's ranking and the Laplace ranking are both by gradients per accepted
    proposal at L: the Laplace figures checked at 50 digits, the estimate's cost from its
    own acceptance and the kicks counted here."""
    t = target(standard_gaussian_2d())
    laplace = find_mode(t, np.array([0.3, -0.2]))
    draws = sample(t, laplace=laplace, keep=100)
    L = 8
    report = hmc_on_target(t, [method("verlet"), method("bcss2")], Trajectory(steps=L),
                           draws=draws, laplace=laplace, onset=False)
    data = report.to_dict()
    assert data["ranked_by"] == "gradients_per_accepted"
    for row in report.rows:
        m = method(row.method)
        acc = acceptance_mp(m, row.laplace_h_target, L, 2)  # beta = 1 at the mode
        assert row.laplace_gradients_per_accepted == pytest.approx(
            L * kicks_per_step(m) / acc, rel=1e-9)
        assert row.estimate.gradients_per_accepted == pytest.approx(
            L * kicks_per_step(m) / row.estimate.acceptance, rel=1e-12)
    est = sorted(report.rows, key=lambda r: r.estimate.gradients_per_accepted)
    lap = sorted(report.rows, key=lambda r: r.laplace_gradients_per_accepted)
    assert [r.rank for r in est] == [1, 2] and [r.laplace_rank for r in lap] == [1, 2]
    assert data["ranking_differs"] == [
        {"method": r.method, "rank": r.rank, "laplace_rank": r.laplace_rank}
        for r in report.rows if r.rank != r.laplace_rank]


def test_where_the_rankings_differ_is_listed():
    """Two methods whose costs on the target and at the mode are in opposite orders."""
    def row(name, on_target, at_mode):
        est = type("E", (), {"gradients_per_accepted": on_target})()
        return TargetRow(name, 1, True, 2.0, 1.0, 1.0, 1.0, None, est,
                         laplace_gradients_per_accepted=at_mode)

    rows = _ranked([row("a", 10.0, 20.0), row("b", 12.0, 15.0), row("c", 30.0, 40.0)])
    assert [(r.method, r.rank, r.laplace_rank) for r in rows] == [
        ("a", 1, 2), ("b", 2, 1), ("c", 3, 3)]


# --------------------------------------------------------------------------- seeds

def test_a_seed_with_a_gaussian_target_is_refused_not_ignored(run):
    """The Gaussian figures draw no random numbers: the same with any seed, so a seed given
    is refused (exit 2, one line) rather than silently ignored; --help says so."""
    with pytest.raises(StepsafeError, match="deterministic"):
        hmc(["verlet"], sigma=[1.0], trajectory_steps=10, seed=3)
    code, _, err = run("hmc", "--sigma", "1", "--steps", "10", "--seed", "3")
    assert code == 2 and "deterministic" in err and len(err.strip().splitlines()) == 1
    code, out, _ = run("hmc", "--help")
    assert code == 0 and "Refused for a Gaussian target" in " ".join(out.split())


def test_the_seed_of_a_target_drives_its_momenta_and_is_stated():
    """On a potential the estimate's momenta come from the seed: one seed twice gives the
    same figures, another seed others (within Monte Carlo error), and the report states
    it."""
    rng = np.random.default_rng(5)
    draws = rng.standard_normal((400, 2))
    kwargs = dict(logdensity=lambda q: -0.5 * np.sum(q * q, axis=-1),
                  gradient=lambda q: -q, start=np.zeros(2), draws=draws,
                  trajectory_steps=6, step=1.2)
    first = hmc(["verlet"], seed=11, **kwargs)
    again = hmc(["verlet"], seed=11, **kwargs)
    other = hmc(["verlet"], seed=12, **kwargs)
    at = [r.rows[0].at_step for r in (first, again, other)]
    assert at[0].acceptance == at[1].acceptance
    assert at[0].acceptance != at[2].acceptance
    assert abs(at[0].acceptance - at[2].acceptance) < 4 * np.hypot(at[0].acceptance_se,
                                                                    at[2].acceptance_se)
    assert first.to_dict()["seed"] == 11 and other.to_dict()["seed"] == 12
    assert hmc(["verlet"], **kwargs).to_dict()["seed"] == 20240611
