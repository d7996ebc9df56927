"""Gaussian targets for HMC: standard deviations, covariance, precision, mass matrix."""

from __future__ import annotations

import json

import numpy as np
import pytest

import stepsafe


def _spd(n: int, seed: int, spread: float = 1e3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Q * np.geomspace(1.0, spread, n)) @ Q.T


@pytest.mark.parametrize("seed", range(4))
def test_covariance_precision_and_sigma_agree(seed):
    """Verlet's h_max is 2 sigma_min: from the covariance, from its inverse (the
    precision, a stiffness), and from the standard deviations of its eigenbasis."""
    C = _spd(6, seed)
    sigmas = np.sqrt(np.linalg.eigvalsh(C))
    from_c = stepsafe.advise("verlet", system={"covariance": C}).h_max
    from_p = stepsafe.advise("verlet", system={"precision": np.linalg.inv(C)}).h_max
    from_s = stepsafe.advise("verlet", sigma=sigmas).h_max
    # the covariance path knows its smallest variance only to 16 n eps of the largest
    # (ratio 1e3 here): its h_max is lower by that much, never higher
    assert from_c <= 2 * sigmas.min() and from_c == pytest.approx(2 * sigmas.min(), rel=1e-9)
    assert from_p == pytest.approx(2 * sigmas.min(), rel=1e-12)
    assert from_s == pytest.approx(2 * sigmas.min(), rel=1e-12)


def test_mass_preconditions_the_covariance():
    """With the mass M = C^-1 (the ideal preconditioner) every frequency is 1."""
    C = _spd(5, 7)
    report = stepsafe.advise("verlet", system={"covariance": C, "mass": np.linalg.inv(C)})
    assert report.h_max == pytest.approx(2.0, rel=1e-9)


@pytest.mark.parametrize("seed", range(2))
def test_leapfrog_on_the_gaussian_measures_the_limit(seed):
    """A real integration: leapfrog on H = p^T p/2 + q^T C^-1 q/2 keeps the energy error
    bounded just below the predicted h_max and blows up just above it."""
    C = _spd(4, seed, spread=100.0)
    h_max = stepsafe.advise("verlet", system={"covariance": C}).h_max
    P = np.linalg.inv(C)

    def energy_growth(h: float) -> float:
        q, p = np.ones(4), np.zeros(4)
        e0 = 0.5 * (p @ p + q @ P @ q)
        worst = 0.0
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(2000):
                p = p - 0.5 * h * P @ q
                q = q + h * p
                p = p - 0.5 * h * P @ q
                worst = max(worst, abs(0.5 * (p @ p + q @ P @ q) - e0) / e0)
                if not worst < 1e12:
                    return np.inf
        return worst

    assert energy_growth(0.99 * h_max) < 1e2
    assert energy_growth(1.01 * h_max) > 1e6


def test_scene_and_command_line(run, tmp_path):
    C = _spd(3, 3)
    np.save(tmp_path / "cov.npy", C)
    scene = tmp_path / "hmc.yaml"
    scene.write_text("method: verlet\nh: 0.5\nsystem: {covariance: cov.npy}\n")
    code, out, err = run("advise", str(scene), "--json")
    assert code == 0, err
    assert json.loads(out)["h_max"] == pytest.approx(2 * np.sqrt(np.linalg.eigvalsh(C).min()),
                                                     rel=1e-10)
    code, out, _ = run("advise", "--method", "verlet", "--sigma", "0.5", "--sigma", "2",
                       "--json")
    assert json.loads(out)["h_max"] == pytest.approx(1.0, rel=1e-12)
    modes = tmp_path / "modes.yaml"
    modes.write_text("method: verlet\nmodes:\n  - {sigma: 0.25, label: narrow}\n")
    code, out, _ = run("advise", str(modes), "--json")
    assert json.loads(out)["limiting"]["label"] == "narrow"


@pytest.mark.parametrize("system, key", [
    ("{covariance: [[1, 2], [2, 1]]}", "covariance"),
    ("{covariance: [[1, 0], [0, 1]], hessian: [[1, 0], [0, 1]]}", "system"),
    ("{hessian: [[1, 0], [0, 1]], mass: [[1, 0], [0, 1]]}", "mass"),
    ("{covariance: [[1, 0], [0, 1]], mass: [[1, 0], [0, -1]]}", "mass"),
])
def test_bad_gaussians_are_refused(run, tmp_path, system, key):
    scene = tmp_path / "bad.yaml"
    scene.write_text(f"method: verlet\nh: 0.1\nsystem: {system}\n")
    code, out, err = run("check", str(scene))
    assert code == 2 and key in err and len(err.strip().splitlines()) == 1, err


def test_diagonal_covariance_at_extreme_scales():
    """A diagonal covariance holds its variances exactly: 1e300 and 1e-300 together."""
    report = stepsafe.advise("verlet", system={"covariance": [[1e300, 0.0], [0.0, 1e-300]]})
    assert report.h_max == pytest.approx(2e-150, rel=1e-12)


def test_a_csv_of_standard_deviations(tmp_path, run_json):
    path = tmp_path / "sigmas.csv"
    path.write_text("sigma,label\n0.5,a\n# a comment\n\n2,b\n")
    data = run_json("advise", "--method", "verlet", "--modes", str(path))
    same = run_json("advise", "--method", "verlet", "--sigma", "0.5", "--sigma", "2")
    assert data["h_max"] == same["h_max"] == pytest.approx(1.0, rel=1e-12)


@pytest.mark.parametrize("text, key", [
    ("sigma\n1\n0\n", "line 3.sigma"),
    ("sigma\n1\n\n-2\n", "line 4.sigma"),
    ("sigma\n1e-320\n", "line 2.sigma"),
    ("sigma\nx\n", "line 2.sigma"),
    ("sigma,beta\n1,1\n", "header"),
])
def test_bad_standard_deviations_in_a_csv(tmp_path, run, text, key):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    code, _, err = run("advise", "--method", "verlet", "--modes", str(path))
    assert code == 2 and err.count("\n") == 1
    assert key in err or (key == "header" and "CSV header" in err)


#: Every refusal of a standard deviation says what one may be.
SIGMA_SAYS = ("a standard deviation, a finite number > 0 (0, negative numbers, inf and nan "
              "are refused)")


def _not_a_standard_deviation():
    """Values no standard deviation can have, spelled as a user would: negative numbers
    of any size, zeros, infinities and nans in the spellings Python, YAML and spreadsheets
    use."""
    from hypothesis import strategies as st

    negative = st.floats(max_value=-5e-324, allow_infinity=False).map(repr)
    zero = st.sampled_from(["0", "-0", "0.0", "-0.0", "0e5", "0.000"])
    spelled = st.sampled_from(["inf", "-inf", "+inf", "Infinity", "-Infinity", "nan", "NaN",
                               "-nan"])
    return negative | zero | spelled


@pytest.mark.parametrize("route", ["option", "scene", "csv"])
def test_a_sigma_that_is_no_standard_deviation_is_refused_saying_what_is_allowed(
        tmp_path, run, route):
    """--sigma, a scene's modes: entry and a sigma column: one line naming the option or
    the file and key, exit 2, saying what a standard deviation may be (never '>= 0')."""
    from hypothesis import given, settings

    @settings(max_examples=25, deadline=None)
    @given(text=_not_a_standard_deviation())
    def check(text):
        yaml_text = {"inf": ".inf", "-inf": "-.inf", "+inf": ".inf", "nan": ".nan",
                     "NaN": ".nan", "-nan": ".nan", "Infinity": ".inf",
                     "-Infinity": "-.inf"}.get(text, text)
        if route == "option":
            code, _, err = run("hmc", "--sigma", "1", "--sigma", text, "--methods", "verlet")
            named = f"--sigma {text}:"
        elif route == "scene":
            scene = tmp_path / "target.yaml"
            scene.write_text(f"modes:\n  - {{sigma: 1}}\n  - {{sigma: {yaml_text}}}\n")
            code, _, err = run("hmc", str(scene), "--methods", "verlet")
            named = f"{scene}::$.modes[1].sigma:"
        else:
            table = tmp_path / "sigmas.csv"
            table.write_text(f"sigma\n1\n{text}\n")
            code, _, err = run("hmc", "--modes", str(table), "--methods", "verlet")
            named = f"{table}::$.line 3.sigma:"
        assert code == 2, err
        assert err.count("\n") == 1 and named in err and SIGMA_SAYS in err, err
        assert ">= 0" not in err

    check()


@pytest.mark.parametrize("value", [-1.0, 0.0, -0.0, float("inf"), float("-inf"), float("nan"),
                                   "-1", "inf", "nan"])
def test_the_api_says_what_a_standard_deviation_may_be(value):
    for call in (lambda: stepsafe.hmc(["verlet"], sigma=[1.0, value]),
                 lambda: stepsafe.advise("verlet", sigma=[value])):
        with pytest.raises(stepsafe.StepsafeError, match=r"sigma must be a standard "
                                                          r"deviation, a finite number > 0"):
            call()
