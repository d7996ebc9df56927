"""``stepsafe design`` optimising what ``hmc`` ranks, on the command line: the designed
member against the AIA-style minimax member on that objective, recomputed here
independently (the family's one-step matrix multiplied out at 30 digits, its L-th power,
each mode's expected energy error ``(|M^L|_F^2 - 2) / 2`` and the acceptance
``2 P(Delta < 0)`` by an mpmath quadrature of the Gil-Pelaez integral); 3 stages wherever
``hmc`` ranks bcss3, under the one rule for rounding gaps both use."""

from __future__ import annotations

import mpmath as mp
import pytest
from test_hmc import _gil_pelaez_mp

from stepsafe import design, hmc


def family_matrix(params, z):
    """The one-step matrix of the palindromic 2-stage (b) or 3-stage (b, a) member on the
    oscillator at z, kicks first, at the working precision."""
    if len(params) == 1:
        b = mp.mpf(params[0])
        ops = [("k", b), ("d", mp.mpf(1) / 2), ("k", 1 - 2 * b), ("d", mp.mpf(1) / 2),
               ("k", b)]
    else:
        b, a = (mp.mpf(x) for x in params)
        ops = [("k", b), ("d", a), ("k", mp.mpf(1) / 2 - b), ("d", 1 - 2 * a),
               ("k", mp.mpf(1) / 2 - b), ("d", a), ("k", b)]
    M = mp.eye(2)
    for kind, c in ops:
        step = (mp.matrix([[1, c * z], [0, 1]]) if kind == "d" else
                mp.matrix([[1, 0], [-c * z, 1]]))
        M = step * M
    return M


def gradients_per_accepted(params, betas, h, steps):
    """``stages L / acceptance`` of the member at step h on the Gaussian of frequencies
    ``betas`` (module docstring)."""
    with mp.workdps(30):
        errors = []
        for beta in betas:
            P = family_matrix(params, mp.mpf(beta) * mp.mpf(h)) ** steps
            errors.append(float((sum(P[i, j] ** 2 for i in range(2) for j in range(2))
                                 - 2) / 2))
    return (len(params) + 1) * steps / _gil_pelaez_mp(errors)


CASES = [(2, [1.0, 0.5, 0.3], 0.5, 10), (2, [1.0, 0.4], 0.7, 25), (3, [1.0], 3.5, 10),
         (3, [1.0, 0.7], 2.5, 12)]


@pytest.mark.parametrize("stages, sigma, step, steps", CASES)
def test_designed_member_beats_or_ties_the_minimax_one_on_gradients_per_accepted(
        run_json, stages, sigma, step, steps):
    args = ["design", "--step", str(step), "--stages", str(stages), "--objective",
            "acceptance", "--steps", str(steps)]
    for s in sigma:
        args += ["--sigma", str(s)]
    data = run_json(*args)
    assert data["objective"] == "acceptance" and data["steps"] == steps
    rows = {r["method"]: r for r in data["comparison"]}
    ours, aia = rows[data["name"]], rows["aia-minimax"]
    betas = [1.0 / s for s in sigma]
    designed = gradients_per_accepted(tuple(data["params"].values()), betas, step, steps)
    minimax = gradients_per_accepted(tuple(data["aia_params"].values()), betas, step, steps)
    assert designed <= minimax * (1 + 1e-9)
    # the report's figures are these (hmc's exact Gaussian acceptance)
    assert ours["gradients_per_accepted"] == pytest.approx(designed, rel=1e-9)
    assert aia["gradients_per_accepted"] == pytest.approx(minimax, rel=1e-9)


def test_the_text_reports_both_members_on_the_objective(run):
    code, out, _ = run("design", "--sigma", "1", "--sigma", "0.5", "--step", "0.5",
                       "--objective", "acceptance", "--length", "5", "--jitter", "0.1")
    assert code == 0
    text = " ".join(out.split())  # (the table's cells fold at 80 columns: the sentence)
    assert "Objective, gradients per accepted proposal: designed-2stage" in text
    assert "AIA-style minimax (b = " in text and "AIA / designed = " in text


def test_the_default_objective_and_trajectory_flags(run_json):
    data = run_json("design", "--sigma", "1", "--step", "0.5", "--steps", "7")
    assert data["objective"] == "error-bound" and data["aia_params"] is None
    assert {r["method"] for r in data["comparison"]} == {
        "designed-2stage", "verlet", "bcss2", "bcss3", "mclachlan2-min"}


@pytest.mark.parametrize("sigma, jitter", [([1.0], 0.0), ([1.0, 0.7], 0.1)])
def test_three_stages_are_designed_wherever_hmc_ranks_bcss3(tmp_path, sigma, jitter):
    """Up to bcss3's stability limit as ``hmc`` computes it (past its M = -I point, a
    rounding gap both commands treat by the same rule), a 3-stage design exists and
    ``hmc`` finds it stable over the whole step distribution."""
    row = hmc(["bcss3"], sigma=sigma, trajectory_steps=10, jitter=jitter).rows[0]
    assert row.rank == 1 and row.resonance_h
    step = 0.97 * row.stability_h / (1 + jitter)
    report = design(sigma=sigma, step=step, stages=3, jitter=jitter,
                    objective="acceptance", trajectory_steps=10)
    path = tmp_path / "mine.yaml"
    path.write_text(report.method_file)
    mine = hmc([str(path)], sigma=sigma, trajectory_steps=10, jitter=jitter).rows[0]
    assert mine.rank == 1
    assert mine.stability_h >= step * (1 + jitter) * (1 - 1e-12)
