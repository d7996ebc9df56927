"""HMC predictions checked against their definitions and against real sampling runs.

* The expected energy error after L steps, ``E[Delta_L] = (|M^L|_F^2 - 2) / 2``, recomputed
  at 50 digits from the one-step matrix of the independent mpmath path (matrix powers, no
  Chebyshev identity), and its bound over L against the maximum over L = 1..400.
* The acceptance ``2 P(Delta < 0)`` against an mpmath quadrature of the Gil-Pelaez integral
  (30 digits) for generated sets of energy errors, and against the definition
  ``E[min(1, exp(-Delta))]`` by sampling the quadratic form.
* A numpy HMC sampler (Markov chains started in the target, each integrator as its
  drift/kick sequence, gradient P q) on Gaussian targets from d = 10 to 1000, isotropic and
  ill-conditioned, dense with a mass matrix, with fixed L, an integration time and jitter:
  measured acceptance within Monte Carlo error of the prediction.
"""

from __future__ import annotations

import json

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import method
from test_safe_property import _mp_function

import stepsafe
from stepsafe import hmc
from stepsafe.core import hmc as H
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Splitting
from stepsafe.reference import highprec as R

METHODS = ["verlet", "bcss2", "bcss3", "mclachlan2-min", "pefrl", "yoshida4",
           "symplectic-euler", "gauss:2", "lobatto3ab:3"]


def _method(name):
    family, _, s = name.partition(":")
    return method(family, int(s)) if s else method(name)


def _ideal(m):
    """The mp one-step matrix of ``m``; a splitting's drift and kick coefficients are
    rescaled to sum to exactly 1 (the float sums miss by ~1e-16, which stepsafe treats as
    the rounding of an exactly consistent method)."""
    if not isinstance(m, Splitting):
        return _mp_function(m)

    def M(z, model):
        d = [mp.mpf(float(x)) for x in m.drift]
        k = [mp.mpf(float(x)) for x in m.kick]
        d = [x / sum(d) for x in d]
        k = [x / sum(k) for x in k]
        return R.transfer_matrix_splitting(d, k, z, model)

    return M


@pytest.mark.parametrize("name", METHODS)
def test_energy_error_of_L_steps_at_50_digits(name):
    m = _method(name)
    Mfun = _ideal(m)
    rng = np.random.default_rng(len(name))
    zs = np.concatenate([[1e-3, 0.05], rng.uniform(0.1, 2.4, 6)])
    with mp.workdps(50):
        for z in zs:
            M = Mfun(mp.mpf(float(z)), "oscillator")
            for L in (1, 2, 7, 50):
                P = M ** L
                ref = (sum(P[i, j] ** 2 for i in range(2) for j in range(2)) - 2) / 2
                got = H.energy_errors(m, [z], L)[0]
                if not mp.isfinite(ref) or abs(ref) > 1e300:
                    assert got == np.inf or got > 1e250
                    continue
                # the float coefficients are symplectic to rounding only: |M^L|^2 - 2 moves
                # by about 2 L (det M - 1), which the formula (det M = 1) leaves out
                defect = 2 * L * abs(mp.det(M) - 1)
                assert abs(got - float(ref)) <= 1e-9 * float(abs(ref)) + float(defect) \
                    + 1e-30, (z, L)


@pytest.mark.parametrize("name", ["verlet", "bcss2", "bcss3", "pefrl", "gauss:2"])
def test_the_bound_is_the_largest_error_over_trajectory_lengths(name):
    m = _method(name)
    Mfun = _ideal(m)
    for z in (0.4, 1.3, 1.9):
        bound = H.energy_errors(m, [z])[0]
        if not np.isfinite(bound):
            continue
        with mp.workdps(30):
            M = Mfun(mp.mpf(z), "oscillator")
            P, worst = mp.eye(2), mp.mpf(0)
            for _ in range(400):
                P = M * P
                worst = max(worst, (sum(P[i, j] ** 2 for i in range(2) for j in range(2))
                                    - 2) / 2)
            # see the test above; plus the 30-digit rounding of 400 products, which is all
            # there is for a method that keeps the oscillator's energy exactly (Gauss: bound 0)
            defect = float(2 * 400 * abs(mp.det(M) - 1)) + 400 * 1e-29
        assert float(worst) <= bound * (1 + 1e-10) + defect
        assert float(worst) >= 0.95 * bound - defect  # 400 steps come close to sin^2 = 1


def _gil_pelaez_mp(errors):
    with mp.workdps(30):
        es = [mp.mpf(float(e)) for e in errors]
        a = [(e + mp.sqrt(e * e + 2 * e)) / 2 for e in es]
        b = [-e / (e + mp.sqrt(e * e + 2 * e)) for e in es]

        def f(u):
            mod = mp.mpf(0)
            arg = mp.mpf(0)
            for c in a + b:
                mod -= mp.log1p(4 * c * c * u * u) / 4
                arg += mp.atan(2 * c * u) / 2
            return mp.exp(mod) * mp.sin(arg) / u

        s = 2 * max(a)
        cuts = [0] + [mp.mpf(10) ** k / s for k in range(-3, 4)] + [mp.inf]
        return float(1 - 2 / mp.pi * mp.quad(f, cuts))


@pytest.mark.slow
@settings(max_examples=12, deadline=None, derandomize=True)
@given(st.lists(st.floats(-12.0, 1.5), min_size=1, max_size=5))
def test_acceptance_matches_a_30_digit_quadrature(log_errors):
    errors = 10.0 ** np.array(log_errors)
    assert abs(H.acceptance(errors).rate - _gil_pelaez_mp(errors)) < 1e-12


def test_acceptance_is_the_mean_of_min_1_exp_minus_delta():
    rng = np.random.default_rng(3)
    errors = rng.exponential(0.05, 40)
    a, b = H._weights(errors)
    n = 400_000
    delta = (rng.standard_normal((n, errors.size)) ** 2) @ a + \
        (rng.standard_normal((n, errors.size)) ** 2) @ b
    measured = np.minimum(1.0, np.exp(-delta))
    se = measured.std() / np.sqrt(n)
    assert abs(measured.mean() - H.acceptance(errors).rate) < 5 * se
    assert abs(delta.mean() - errors.sum()) < 5 * delta.std() / np.sqrt(n)


def test_many_distinct_modes_are_lumped_and_say_so():
    errors = np.geomspace(1e-6, 1e-2, 5000)
    lumped = H.acceptance(errors)
    assert lumped.approximate
    exact = H._gil_pelaez(*[w[None, :] for w in H._weights(errors)], np.ones(errors.size),
                          np.zeros(1), np.zeros(1))[0]
    assert abs(lumped.rate - exact) < 1e-3


def test_no_error_accepts_always_and_an_unstable_mode_never():
    assert H.acceptance([0.0, 0.0]).rate == 1.0
    assert H.acceptance([0.1, np.inf]).rate == 0.0
    m = method("verlet")
    # beyond the limit: E[Delta] ~ 6e11, P(Delta < 0) = P(a u^2 < v^2 / 2) ~ 1e-6, not 0
    far = H.acceptance_at(m, np.array([1.0]), 2.5, H.Trajectory(steps=10))
    assert far.expected_error > 1e11 and 0 < far.rate < 1e-5


# --------------------------------------------------------------------------- sampling


def _run_hmc(integrator, precision, h, steps, chains, iterations, rng, inv_mass=None,
             jitter=0.0, length=None):
    """Measured acceptance of HMC chains (started from the target) on N(0, precision^-1);
    a 1-d ``precision`` is a diagonal one (unit mass then)."""
    ops = integrator.operations
    if precision.ndim == 1:
        def force(q):
            return q * precision

        def velocity(p):
            return p

        def energy(q, p):
            return 0.5 * (q * q * precision).sum(axis=1) + 0.5 * (p * p).sum(axis=1)

        q = rng.standard_normal((chains, precision.size)) / np.sqrt(precision)
        draw_p = lambda: rng.standard_normal((chains, precision.size))  # noqa: E731
    else:
        minv = np.eye(len(precision)) if inv_mass is None else inv_mass
        chol = np.linalg.cholesky(np.linalg.inv(precision))
        mass_chol = np.linalg.cholesky(np.linalg.inv(minv))

        def force(q):
            return q @ precision.T

        def velocity(p):
            return p @ minv.T

        def energy(q, p):
            return 0.5 * np.einsum("ci,ci->c", q, force(q)) + \
                0.5 * np.einsum("ci,ci->c", p, velocity(p))

        q = rng.standard_normal((chains, len(precision))) @ chol.T
        draw_p = lambda: rng.standard_normal((chains, len(precision))) @ mass_chol.T  # noqa
    accepted = []
    L = steps if steps is not None else max(1, int(length / h))
    for _ in range(iterations):
        p = draw_p()
        # each chain draws its own step (shared draws would correlate the chains)
        step = h * (1.0 + jitter * (2.0 * rng.random((chains, 1)) - 1.0))
        h0 = energy(q, p)
        qn, pn = q.copy(), p.copy()
        for _ in range(L):
            for kind, c in ops:
                if kind == "drift":
                    qn += c * step * velocity(pn)
                else:
                    pn -= c * step * force(qn)
        prob = np.minimum(1.0, np.exp(np.minimum(h0 - energy(qn, pn), 0.0)))
        accept = rng.random(chains) < prob
        q = np.where(accept[:, None], qn, q)
        accepted.append(prob)
    # chains are independent, iterations within one are not: the error from chain means
    per_chain = np.mean(accepted, axis=0)
    return per_chain.mean(), per_chain.std(ddof=1) / np.sqrt(chains)


CASES = [
    # (name, sigmas, h, steps, length, jitter)
    ("verlet", np.ones(10), 1.2, 8, None, 0.0),
    ("bcss2", np.linspace(0.01, 1.0, 100), 0.02, None, 1.0, 0.2),
    ("bcss3", np.linspace(0.05, 1.0, 100), 0.2, 10, None, 0.1),
    ("mclachlan2-min", np.ones(1000), 1.6, 5, None, 0.0),
    ("pefrl", np.geomspace(0.1, 1.0, 300), 0.25, None, 2.0, 0.0),
    ("yoshida4", np.linspace(0.5, 1.0, 50), 0.75, 6, None, 0.0),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_measured_acceptance_matches_the_prediction(case):
    name, sigmas, h, steps, length, jitter = case
    rng = np.random.default_rng(11)
    predicted = hmc([name], sigma=list(sigmas), trajectory_steps=steps, length=length,
                    jitter=jitter, step=h).rows[0].at_step["acceptance"]
    precision = 1.0 / sigmas ** 2
    measured, se = _run_hmc(stepsafe.method(name), precision, h, steps, 64, 120, rng,
                            jitter=jitter, length=length)
    assert 0.05 < predicted < 0.99  # a case that tests something
    assert abs(measured - predicted) < 4 * se, (measured, predicted, se)


def test_dense_target_with_a_mass_matrix():
    """A correlated target (precision P, condition ~100) preconditioned by a diagonal mass:
    the frequencies are those of M^-1 P, computed by stepsafe from the matrices."""
    rng = np.random.default_rng(5)
    d = 30
    Q, _ = np.linalg.qr(rng.standard_normal((d, d)))
    precision = Q @ np.diag(np.geomspace(1.0, 100.0, d)) @ Q.T
    mass = np.diag(np.diag(precision))
    h, steps = 0.7, 12
    report = hmc(["verlet"], system={"precision": precision.tolist(), "mass": mass.tolist()},
                 trajectory_steps=steps, step=h)
    predicted = report.rows[0].at_step["acceptance"]
    measured, se = _run_hmc(stepsafe.method("verlet"), precision, h, steps, 64, 120, rng,
                            inv_mass=np.linalg.inv(mass))
    assert 0.05 < predicted < 0.99
    assert abs(measured - predicted) < 4 * se, (measured, predicted, se)


# --------------------------------------------------------------------------- the report


def test_step_at_target_reaches_it_for_every_trajectory_length():
    sigmas = list(np.linspace(0.2, 1.0, 20))
    for row in hmc(["verlet", "bcss2", "pefrl"], sigma=sigmas, target_accept=0.9).rows:
        m = stepsafe.method(row.method).tableau
        betas = 1.0 / np.array(sigmas)
        bound = H.acceptance_at(m, betas, row.h_target).rate
        assert abs(bound - 0.9) < 1e-5
        for L in (1, 3, 17, 64, 250):
            assert H.acceptance_at(m, betas, row.h_target, H.Trajectory(steps=L)).rate \
                >= 0.9 - 1e-9


def test_bcss_integrators_beat_verlet_per_gradient_on_a_gaussian():
    """The ranking the BCSS design predicts for a well-conditioned Gaussian (and which the
    sampling tests above confirm figure by figure)."""
    rows = {r.method: r for r in hmc(None, sigma=list(np.linspace(0.5, 1.0, 50)),
                                     length=3.0).rows}
    assert rows["bcss2"].gradients_per_time < rows["verlet"].gradients_per_time
    assert rows["bcss3"].gradients_per_time < rows["yoshida4"].gradients_per_time
    assert rows["bcss3"].stability_h == pytest.approx(4.6618460782303 / 2.0, rel=1e-12)
    # the structure limit is the M = -I point less its float64 uncertainty, as advise has it
    advised = stepsafe.advise("bcss3", sigma=list(np.linspace(0.5, 1.0, 50))).h_max
    assert rows["bcss3"].structure_h == pytest.approx(advised, rel=1e-15)
    assert rows["bcss3"].structure_h <= advised < 2.9763246405798 / 2.0
    assert [r.rank for r in hmc(None, sigma=[1.0]).rows] == list(range(1, 7))


def test_non_symplectic_and_non_symmetric_methods_are_flagged():
    rows = {r.method: r for r in hmc(["rk4", "symplectic-euler"], sigma=[1.0]).rows}
    assert rows["rk4"].h_target is None and "not symplectic" in rows["rk4"].notes[0]
    assert rows["symplectic-euler"].h_target is not None
    assert "not symmetric" in rows["symplectic-euler"].notes[0]


@pytest.mark.parametrize("kwargs, match", [
    ({"target_accept": 1.0}, "target acceptance"),
    ({"target_accept": 0.0}, "target acceptance"),
    ({"trajectory_steps": 0}, "trajectory_steps"),
    ({"trajectory_steps": 2.5}, "trajectory_steps"),
    ({"trajectory_steps": 3, "length": 1.0}, "not both"),
    ({"steps": 3}, "did you mean"),
    ({"length": -1.0}, "length"),
    ({"jitter": 1.0}, "jitter"),
    ({"jitter": True}, "jitter"),
    ({"step": float("inf")}, "step"),
    ({"criterion": "type"}, "criterion"),
    ({"curve": -1}, "curve"),
])
def test_bad_arguments(kwargs, match):
    with pytest.raises(StepsafeError, match=match):
        hmc(["verlet"], sigma=[1.0], **kwargs)


def test_a_target_with_saddles_is_refused():
    with pytest.raises(StepsafeError, match="only vibrations"):
        hmc(["verlet"], beta=[1.0], inverted_beta=[1.0])


def test_cli_json_and_text(run, run_json):
    code, out, err = run("hmc", "--sigma", "1", "--sigma", "0.1", "--steps", "10",
                         "--methods", "verlet,bcss2", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["target_accept"] == 0.8 and data["steps"] == 10
    assert data["criterion"] == "stability" and data["cost_unit"] == "gradient evaluations"
    assert {r["method"] for r in data["methods"]} == {"verlet", "bcss2"}
    code, out, _ = run("hmc", "--sigma", "1", "--length", "4", "--time-unit", "ps")
    assert code == 0 and "T = 4 ps" in out and "Ranked by" in out
    assert run_json("hmc", "--sigma", "1", "--time-unit", "ps")["time_unit"] == "ps"
    code, _, err = run("hmc", "--sigma", "1", "--margin", "0.9")
    assert code == 2 and "margin" in err
    code, _, err = run("hmc", "--sigma", "1", "--jitter", "2")
    assert code == 2 and "jitter" in err


def test_cli_plot(run, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "acceptance.png"
    code, _, err = run("hmc", "--sigma", "1", "--steps", "10", "--methods", "verlet",
                       "--plot", str(out))
    assert code == 0, err
    assert out.read_bytes()[:4] == b"\x89PNG"


# ------------------------------------------------------- extreme errors, kinks and limits


def test_huge_energy_errors_accept_almost_never():
    """E up to the largest float: the weights neither overflow nor turn into NaN (exact
    acceptance for E = 1e200 is about 1e-100; the quadrature computes it as 1 - (2/pi) I
    with I within rounding of pi/2, so to a few ulps of 1)."""
    for e in (1e100, 1e154, 1e200, 1e308):
        rate = H.acceptance(np.array([e])).rate
        assert 0.0 <= rate <= 4 * np.finfo(float).eps
    row = hmc(["verlet"], sigma=[1.0], trajectory_steps=180, step=2.5).rows[0]
    assert 0.0 <= row.at_step["acceptance"] <= 4 * np.finfo(float).eps


@pytest.mark.parametrize("name, steps, jitter, h", [
    ("verlet", 10, 0.9, 1.5), ("verlet", 10, 0.5, 1.9), ("verlet", 300, 0.2, 1.5),
    ("verlet", 3000, 0.01, 1.5),
    # jitter intervals across stability edges (cliffs in the integrand)
    ("bcss2", 10, 0.8, 3.2462), ("kahan-li6", 5, 0.95, 1.6807)])
def test_jitter_average_against_a_dense_uniform_average(name, steps, jitter, h):
    """The composite Gauss rule against the plain mean over 40000 uniform steps of the
    jitter interval (each acceptance exact for its step)."""
    m = method(name)
    hs = h * (1.0 + jitter * np.linspace(-1.0, 1.0, 40001))
    errs = H.errors_after(H.one_step(m, hs), steps)
    a, b = H._weights(np.where(np.isfinite(errs), errs, 0.0)[:, None])
    rates = H._gil_pelaez(a, b, np.ones(1), np.zeros(hs.size), np.zeros(hs.size))
    mean = np.mean(np.where(np.isinf(errs), 0.0, rates))
    got = H.acceptance_at(m, np.array([1.0]), h, H.Trajectory(steps=steps, jitter=jitter))
    assert abs(got.rate - mean) < (2e-3 if got.approximate else 3e-4)


@pytest.mark.parametrize("name, jitter, h", [("bcss2", 0.5, 1.5), ("bcss3", 0.3, 2.2)])
def test_jitter_average_of_the_bound_across_a_zero_of_the_energy_error(name, jitter, h):
    """The bound over every L (no L given): where a symmetric method's step is a pure
    rotation its energy error has a double zero and the acceptance a kink; against the
    midpoint mean of the one-mode closed form (4/pi) atan sqrt(|b|/a) over 40000 steps,
    to 1e-7."""
    m = method(name)
    hs = h * (1.0 + jitter * ((np.arange(40000) + 0.5) / 20000 - 1.0))  # midpoints
    a, b = H._weights(H.errors_after(H.one_step(m, hs), None))
    with np.errstate(divide="ignore", invalid="ignore"):
        closed = np.where(a > 0, 4 / np.pi * np.arctan(np.sqrt(np.abs(b) / a)), 1.0)
    got = H.acceptance_at(m, np.array([1.0]), h, H.Trajectory(jitter=jitter))
    assert abs(got.rate - closed.mean()) < 1e-7, (got.rate, closed.mean())


def test_a_bump_of_rho_between_grid_steps_is_not_stepped_over():
    """triple-jump6's rho has a local maximum at z = 1.2347 (0.016980) between grid steps: a
    target just above the acceptance there must stop h below it."""
    row = hmc(["triple-jump6"], sigma=[1.0], target_accept=0.9416).rows[0]
    assert row.h_target < 1.2347
    m = method("triple-jump6")
    for L in (1, 139, 1000):
        for h in np.linspace(row.h_target / 50, row.h_target, 200):
            assert H.acceptance_at(m, np.array([1.0]), h, H.Trajectory(steps=L)).rate \
                >= 0.9416 - 1e-9


def test_unstable_steps_and_huge_lengths_on_the_command_line(run):
    code, out, err = run("hmc", "--sigma", "1", "--step", "2.5", "--methods", "verlet")
    assert code == 0, err
    assert "overflow (unstable)" in out
    code, out, err = run("hmc", "--sigma", "1", "--length", "1e300", "--methods", "verlet",
                         "--json")
    assert code == 0, err
    assert json.loads(out)["methods"][0]["steps"] == H.MAX_TRAJECTORY_STEPS


def test_targets_hmc_cannot_answer_exactly_are_refused():
    with pytest.raises(StepsafeError, match="every mode"):
        hmc(["verlet"], system={"precision": np.diag(1.0 + 0.001 * np.arange(2500))})
    with pytest.raises(StepsafeError, match="singular"):
        hmc(["verlet"], system={"precision": [[1.0, 0.0], [0.0, 0.0]]})
    with pytest.raises(StepsafeError, match="negative eigenvalue"):
        hmc(["verlet"], system={"precision": [[1.0, 0.0], [0.0, -1.0]]})


@pytest.mark.parametrize("name, steps, jitter, h", [
    ("verlet", 10, 0.5, 1.9), ("verlet", 20, 0.2, 1.8), ("kahan-li6", 5, 0.95, 1.6807)])
def test_jitter_average_to_1e7_where_the_rule_says_exact(name, steps, jitter, h):
    """The acceptance of a given L goes like |sin(L theta)|: kinks at L theta = k pi, which
    the panels end on (a rule across a kink is off by about 1e-4). Reference: the
    midpoint rule on 40000 steps of the exact fixed-step acceptance."""
    m = method(name)
    n = 40000
    hs = h * (1.0 + jitter * ((np.arange(n) + 0.5) / n * 2 - 1))
    errs = H.errors_after(H.one_step(m, hs), steps)
    a, b = H._weights(np.where(np.isfinite(errs), errs, 0.0)[:, None])
    rates = H._gil_pelaez(a, b, np.ones(1), np.zeros(hs.size), np.zeros(hs.size))
    mean = np.mean(np.where(np.isinf(errs), 0.0, rates))
    got = H.acceptance_at(m, np.array([1.0]), h, H.Trajectory(steps=steps, jitter=jitter))
    assert not got.approximate and abs(got.rate - mean) < 1e-7, (got.rate, mean)


def test_a_stability_limit_beyond_zmax_is_said_to_be_the_analysed_end(tmp_path):
    """Eight Verlet substeps of h/8 are stable to z = 16: at zmax 10 the stability h shown
    is the analysed end, and the row says so."""
    path = tmp_path / "verlet8.yaml"
    path.write_text("name: verlet8\nkind: composition\nbase: verlet\norder: 2\n"
                    "source: \"eight Verlet substeps of h/8\"\n"
                    "weights: [0.125, 0.125, 0.125, 0.125, 0.125, 0.125, 0.125, 0.125]\n")
    row = hmc([str(path)], sigma=[1.0]).rows[0]
    assert row.stability_h == pytest.approx(10.0, rel=1e-6)
    assert any("as far as analysed" in note for note in row.notes)
    assert not any("as far as analysed" in note
                   for note in hmc(["verlet"], sigma=[1.0]).rows[0].notes)


@pytest.mark.parametrize("log_error", [-3.0, 0.0, 1.0, 2.0, 4.0, 6.5, 7.2, 9.0, 12.0])
def test_one_mode_acceptance_against_its_closed_form(log_error):
    """One mode: Delta H = a X - |b| Y with X, Y independent chi^2_1, so the acceptance
    2 P(Delta H < 0) = (4 / pi) atan sqrt(|b| / a) (X / Y is F(1, 1)). The HMC guide's
    accuracy: 1e-12 up to an expected error of 100, 2e-8 absolute beyond."""
    e = 10.0 ** log_error
    with mp.workdps(40):
        E = mp.mpf(e)
        root = mp.sqrt(E * E + 2 * E)
        exact = float(4 / mp.pi * mp.atan(mp.sqrt((E / (E + root)) / ((E + root) / 2))))
    assert abs(H.acceptance(np.array([e])).rate - exact) < (1e-12 if e <= 100 else 2e-8)
