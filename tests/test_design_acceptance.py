"""``design`` by what ``hmc`` ranks (gradient evaluations per accepted proposal for the
target, the trajectory and the jitter), the minimax (AIA) member it is compared with, and
the step at target for a given L.

* The minimax member against the closed form of rho for the 2-stage family (Blanes, Casas
  & Sanz-Serna 2014), written here: no other member of the family has a smaller maximum
  over (0, top]; at top = 2 it is bcss2.
* The acceptance design's member has the largest predicted acceptance of the family at its
  step (against a dense scan of b, each figure from the general path of
  :mod:`stepsafe.core.hmc`), at least that of the minimax and the error-bound designs, and
  a numpy HMC sampler measures it within Monte Carlo error.
* The step at target for a given L reaches the target, and a step a little longer does
  not (exact for a Gaussian).
"""

from __future__ import annotations

import numpy as np
import pytest
from support import method

from stepsafe.api.hmc import design as api_design
from stepsafe.api.hmc import hmc
from stepsafe.core import hmc as H
from stepsafe.core.design import design, family_member, minimax


def rho2(h: np.ndarray, b: float) -> np.ndarray:
    """rho of the 2-stage family (b, 1/2, 1 - 2b, 1/2, b) in closed form (BCSS 2014)."""
    num = h ** 4 * (2 * b * b * (0.5 - b) * h * h + 4 * b * b - 6 * b + 1) ** 2
    den = 8 * (2 - b * h * h) * (2 - (0.5 - b) * h * h) * (1 - b * (0.5 - b) * h * h)
    return num / den


@pytest.mark.parametrize("top", [0.5, 1.0, 2.0, 2.5])
def test_minimax_member_has_the_smallest_worst_rho(top):
    (b,) = minimax(2, top)
    z = np.linspace(top / 4000, top, 4000)
    worst = rho2(z, b).max()
    for other in np.linspace(0.19, 0.249, 237):
        values = rho2(z, other)
        if np.all(values >= 0):
            assert values.max() >= worst * (1 - 1e-6), (other, b)


def test_minimax_at_two_is_bcss2():
    (b,) = minimax(2, 2.0)
    assert b == pytest.approx(0.211781, abs=2e-6)


def test_minimax_of_three_stages_beats_its_neighbours():
    b, a = minimax(3, 2.4)
    z = np.linspace(0.001, 2.4, 2000)
    from stepsafe.core.design import rho_values

    worst = rho_values(3, np.array([[b, a]]), z).max()
    for db, da in ((1e-3, 0), (-1e-3, 0), (0, 1e-3), (0, -1e-3)):
        assert rho_values(3, np.array([[b + db, a + da]]), z).max() >= worst


BETAS = np.linspace(0.5, 2.0, 30)


@pytest.mark.parametrize("h, steps, jitter", [(1.2, None, 0.0), (1.2, 10, 0.0),
                                              (1.1, 25, 0.1)])
def test_acceptance_design_accepts_most_of_its_family(h, steps, jitter):
    found = design(2, BETAS, np.ones(BETAS.size), h, jitter, "acceptance", steps)
    traj = H.Trajectory(steps=steps, jitter=jitter)

    def rate(b):
        return H.acceptance_at(family_member(2, (b,)), BETAS, h, traj).rate

    best = rate(found.params[0])
    top = BETAS.max() * h * (1 + jitter)
    aia = minimax(2, top)[0]
    bound = design(2, BETAS, np.ones(BETAS.size), h, jitter)
    # the design's own jitter average is a midpoint rule: allow its error
    slack = 2e-4 if jitter else 1e-9
    assert best >= rate(aia) - slack and best >= rate(bound.params[0]) - slack
    for b in np.linspace(0.19, 0.25, 25 if jitter else 61):
        if b < 0.25 and 2 / top ** 2 > b > 0.5 - 2 / top ** 2:
            assert best >= rate(b) - slack, b


def test_acceptance_design_is_measured_by_a_sampler():
    """The designed member at L = 10 on a 30-mode Gaussian: a numpy sampler (its own
    drift/kick loop) measures the predicted acceptance."""
    h, L = 1.2, 10
    found = design(2, BETAS, np.ones(BETAS.size), h, 0.0, "acceptance", L)
    b = found.params[0]
    ops = [("kick", b), ("drift", 0.5), ("kick", 1 - 2 * b), ("drift", 0.5), ("kick", b)]
    rng = np.random.default_rng(12)
    chains, iters = 400, 30
    q = rng.standard_normal((chains, BETAS.size)) / BETAS
    probs = []
    for _ in range(iters):
        p = rng.standard_normal(q.shape)
        h0 = 0.5 * ((BETAS * q) ** 2).sum(1) + 0.5 * (p * p).sum(1)
        qn, pn = q.copy(), p.copy()
        for _ in range(L):
            for kind, c in ops:
                if kind == "drift":
                    qn = qn + c * h * pn
                else:
                    pn = pn - c * h * BETAS ** 2 * qn
        prob = np.exp(-np.maximum(0.5 * ((BETAS * qn) ** 2).sum(1) + 0.5 * (pn * pn).sum(1)
                                  - h0, 0.0))
        accept = rng.uniform(size=chains) < prob
        q = np.where(accept[:, None], qn, q)
        probs.append(prob)
    per_chain = np.mean(probs, axis=0)
    measured, se = per_chain.mean(), per_chain.std(ddof=1) / np.sqrt(chains)
    predicted = 1.0 / found.error_bound
    assert 0.5 < predicted < 0.97
    assert abs(measured - predicted) < 3 * se, (measured, predicted, se)


def test_the_design_report_compares_with_the_minimax_member():
    report = api_design(sigma=list(1 / BETAS), step=1.1, trajectory_steps=25, jitter=0.1,
                        objective="acceptance")
    rows = {r["method"]: r for r in report.comparison}
    assert {"designed-2stage", "aia-minimax", "verlet", "bcss2"} <= set(rows)
    assert rows["designed-2stage"]["acceptance"] >= rows["aia-minimax"]["acceptance"] - 2e-4
    assert rows["designed-2stage"]["gradients_per_accepted"] == pytest.approx(
        2 * 25 / rows["designed-2stage"]["acceptance"])
    assert "after L = 25 steps" in report.method_file
    with pytest.raises(Exception, match="objective"):
        api_design(sigma=[1.0], step=0.5, objective="speed")


@pytest.mark.parametrize("name, steps, jitter", [
    ("verlet", 20, 0.0), ("bcss2", 10, 0.2), ("bcss3", 25, 0.0),
    pytest.param("bcss2", 40, 0.05, marks=pytest.mark.slow)])
def test_step_at_target_for_a_given_L_reaches_it_and_no_more(name, steps, jitter):
    sigmas = np.geomspace(0.2, 1.0, 40)
    m = method(name)
    traj = H.Trajectory(steps=steps, jitter=jitter)
    row = hmc([name], sigma=list(sigmas), trajectory_steps=steps, jitter=jitter).rows[0]
    limit = row.stability_h / (1 + jitter) if jitter else row.stability_h
    h = H.target_step(m, 1 / sigmas, 0.8, limit, traj)
    assert H.acceptance_at(m, 1 / sigmas, h, traj).rate >= 0.8
    if h < limit:  # (else the target holds up to the limit itself)
        assert H.acceptance_at(m, 1 / sigmas, h * (1 + 2 * H.TARGET_RTOL), traj).rate < 0.8
    # every step of the grid below it reaches the target too
    for g in np.linspace(h / 16, h, 16):
        assert H.acceptance_at(m, 1 / sigmas, g, traj).rate >= 0.8
    # the bound over every L is more cautious than the given L
    assert row.h_target <= h * (1 + 1e-9)
