"""``measure --ensemble``: many pendulum trajectories at once, each trajectory's largest
energy error against a plain numpy Verlet written here from the same initial states, the
draws against their definitions, the seed's effect, and bad input refused naming the
option."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe

PENDULUM = "examples/pendulum.yaml"


def _numpy_verlet_errors(X0: np.ndarray, h: float, steps: int) -> np.ndarray:
    """Velocity Verlet on H = p^2/2 - cos(q) for every row of X0 at once, the force
    ``-sin q`` by hand: each row's max_k |H_k - H_0| over |H_0 - (-1)|."""
    q, p = X0[:, 0].copy(), X0[:, 1].copy()

    def energy(q, p):
        return p * p / 2 - np.cos(q)

    e0 = energy(q, p)
    worst = np.zeros_like(q)
    for _ in range(steps):
        p = p - 0.5 * h * np.sin(q)
        q = q + h * p
        p = p - 0.5 * h * np.sin(q)
        worst = np.maximum(worst, np.abs(energy(q, p) - e0))
    return worst / np.abs(e0 + 1.0)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**63 - 1), energy=st.floats(-0.99, 0.9),
       h=st.floats(0.05, 1.5), count=st.integers(1, 60))
def test_every_trajectory_matches_an_independent_numpy_verlet(seed, energy, h, count):
    """The shell lies at p^2/2 + q^2/2 = E + 1 (the pendulum's quadratic model at q = 0,
    H_e = -1); each trajectory's error equals the independent run's from the same state
    (to 1e-9: the same arithmetic up to rounding), and the median, 90 and 99 percent
    quantiles and maximum are those of the independent errors."""
    r = stepsafe.measure("verlet", h, scene=PENDULUM, time=20 * h, ensemble=count,
                         energy=energy, seed=seed)
    X0 = np.array(r.states)
    assert X0.shape == (count, 2) and r.seed == seed and r.centre_energy == -1.0
    np.testing.assert_allclose(X0[:, 0] ** 2 / 2 + X0[:, 1] ** 2 / 2, energy + 1, rtol=1e-12)
    independent = _numpy_verlet_errors(X0, h, 20)
    row = r.rows[0]
    assert row.steps == 20 and row.unstable == 0
    np.testing.assert_allclose(row.errors, independent, rtol=1e-9, atol=1e-15)
    expected = np.quantile(independent, [0.5, 0.9, 0.99])
    assert [row.median, row.q90, row.q99] == pytest.approx(list(expected), rel=1e-9,
                                                             abs=1e-15)
    assert row.max == pytest.approx(independent.max(), rel=1e-9, abs=1e-15)
    assert row.median <= row.q90 <= row.q99 <= row.max


def test_thermal_draw_has_the_boltzmann_variance_and_matches_numpy_verlet():
    """At kT = 0.2 the pendulum's quadratic model gives q and p each of variance 0.2
    (4000 draws: 10 percent is over four standard errors of a variance), and every
    trajectory's error is the independent run's."""
    r = stepsafe.measure("verlet", [0.3], scene=PENDULUM, time=6.0, ensemble=4000, kT=0.2,
                         seed=11)
    X0 = np.array(r.states)
    assert r.draw == "thermal" and r.kT == 0.2
    np.testing.assert_allclose(X0.var(axis=0), 0.2, rtol=0.1)
    assert abs(X0.mean(axis=0)).max() < 0.05
    np.testing.assert_allclose(r.rows[0].errors, _numpy_verlet_errors(X0, 0.3, 20),
                               rtol=1e-9, atol=1e-15)


def test_a_composition_of_verlet_runs_as_its_substeps():
    """yoshida4 is Verlet at w1 h, w0 h, w1 h (the triple jump): the same errors as the
    independent Verlet's substeps, the energy taken after each whole step."""
    w1 = 1 / (2 - 2 ** (1 / 3))
    w0 = 1 - 2 * w1
    r = stepsafe.measure("yoshida4", 0.6, scene=PENDULUM, time=6.0, ensemble=40,
                         energy=0.3, seed=5)
    X = np.array(r.states)
    q, p = X[:, 0].copy(), X[:, 1].copy()
    e0, worst = p * p / 2 - np.cos(q), np.zeros(len(X))
    for _ in range(10):
        for w in (w1, w0, w1):
            p = p - 0.5 * w * 0.6 * np.sin(q)
            q = q + w * 0.6 * p
            p = p - 0.5 * w * 0.6 * np.sin(q)
        worst = np.maximum(worst, np.abs(p * p / 2 - np.cos(q) - e0))
    np.testing.assert_allclose(r.rows[0].errors, worst / np.abs(e0 + 1), rtol=1e-8,
                               atol=1e-15)


def test_an_explicit_runge_kutta_ensemble_matches_an_independent_rk4():
    """rk4 (not a splitting) on the pendulum: each trajectory's error equals that of the
    classical RK4 tableau written here, run from the same states."""
    r = stepsafe.measure("rk4", 0.4, scene=PENDULUM, time=8.0, ensemble=30, energy=0.3,
                         seed=2)
    X = np.array(r.states)
    q, p = X[:, 0].copy(), X[:, 1].copy()
    e0, worst = p * p / 2 - np.cos(q), np.zeros(len(X))
    h = 0.4

    def f(q, p):
        return p, -np.sin(q)

    for _ in range(20):
        k1 = f(q, p)
        k2 = f(q + h / 2 * k1[0], p + h / 2 * k1[1])
        k3 = f(q + h / 2 * k2[0], p + h / 2 * k2[1])
        k4 = f(q + h * k3[0], p + h * k3[1])
        q = q + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        p = p + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        worst = np.maximum(worst, np.abs(p * p / 2 - np.cos(q) - e0))
    assert r.rows[0].steps == 20
    np.testing.assert_allclose(r.rows[0].errors, worst / np.abs(e0 + 1), rtol=1e-8,
                               atol=1e-15)


def test_the_cli_prints_the_api_distribution_and_the_seed(run_json, run):
    args = ("measure", PENDULUM, "--h", "0.5", "--h", "0.2", "--time", "10",
            "--ensemble", "50", "--energy", "-0.5", "--seed", "7")
    data = run_json(*args)
    r = stepsafe.measure("verlet", [0.5, 0.2], scene=PENDULUM, time=10.0, ensemble=50,
                         energy=-0.5, seed=7)
    assert data == r.to_dict()
    assert data["seed"] == 7 and data["ensemble"] == 50 and data["draw"] == "shell"
    code, out, _ = run(*args)
    assert code == 0 and "seed 7" in out
    assert f"{data['rows'][0]['q99']:.3g}" in out.splitlines()[-2]
    default = run_json("measure", PENDULUM, "--h", "0.5", "--time", "10", "--ensemble", "5",
                       "--kT", "0.1")
    assert default["seed"] == stepsafe.measure("verlet", 0.5, scene=PENDULUM, time=10.0,
                                               ensemble=5, kT=0.1).seed == 0


def test_the_same_seed_reproduces_and_different_seeds_differ():
    def draw(seed):
        return stepsafe.measure("leapfrog", 0.4, scene=PENDULUM, time=8.0, ensemble=30,
                                kT=0.3, seed=seed)

    a, b, c = draw(3), draw(3), draw(4)
    assert a.states == b.states and a.rows == b.rows and a.rows[0].errors == b.rows[0].errors
    assert a.states != c.states and a.rows[0].errors != c.rows[0].errors


@pytest.mark.parametrize("extra, option", [
    (["--ensemble", "0", "--kT", "0.1"], "--ensemble"),
    (["--ensemble", "5", "--kT", "0.1", "--energy", "0"], "--energy"),
    (["--ensemble", "5", "--energy", "-1.5"], "--energy"),
    (["--ensemble", "5", "--energy", "-1"], "--energy"),
    (["--ensemble", "5"], "--energy"),
    (["--ensemble", "5", "--kT", "0"], "--kT"),
    (["--ensemble", "5", "--kT", "0.1", "--seed", "-1"], "--seed"),
    (["--kT", "0.1"], "--ensemble"),
    (["--ensemble", "5", "--kT", "0.1", "--method", "baoab"], "--ensemble"),
    (["--ensemble", "5", "--kT", "0.1", "--initial", "0,1"], "--initial"),
])
def test_bad_ensemble_input_exits_2_naming_the_option(run, extra, option):
    code, out, err = run("measure", PENDULUM, "--h", "0.5", "--time", "5", *extra)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and option in lines[0], err


def _chain(tmp_path, n: int = 10):
    K = [[2.0 if i == j else -1.0 if abs(i - j) == 1 else 0.0 for j in range(n)]
         for i in range(n)]
    path = tmp_path / "chain.yaml"
    path.write_text(f"method: verlet\nsystem:\n  stiffness: {K}\n")
    return str(path)


def test_a_chain_past_verlets_limit_counts_its_unstable_trajectories(tmp_path, run):
    """The 10-mass fixed chain's fastest mode has beta = 2 sin(10 pi / 22) = 1.98: at
    h = 1.9 (z > 2) every thermal trajectory grows past 1e6 times its energy, at h = 0.5
    none does; an ensemble too large for memory is refused naming --ensemble."""
    chain = _chain(tmp_path)
    r = stepsafe.measure("verlet", [0.5, 1.9], scene=chain, time=60.0, ensemble=30, kT=0.1)
    assert [row.unstable for row in r.rows] == [0, 30]
    assert r.rows[0].max < 1
    code, _, err = run("measure", chain, "--h", "0.5", "--time", "5", "--ensemble", "600000",
                       "--kT", "0.1")
    assert code == 2 and "--ensemble" in err and len(err.strip().splitlines()) == 1


def test_the_python_keywords_refuse_bad_values():
    for kwargs in ({"ensemble": 0, "kT": 0.1}, {"ensemble": True, "kT": 0.1},
                   {"ensemble": 3, "kT": 0.1, "seed": 1.5}, {"ensemble": 3},
                   {"ensemble": 3, "kT": 0.1, "energy": 0.0}, {"kT": 0.1}):
        with pytest.raises(stepsafe.StepsafeError):
            stepsafe.measure("verlet", 0.5, scene=PENDULUM, time=5.0, **kwargs)
    assert json.dumps(stepsafe.measure("verlet", 0.5, scene=PENDULUM, time=5.0, ensemble=2,
                                       kT=0.1).to_dict())
