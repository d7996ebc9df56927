"""Langevin splittings (BAOAB, ABOBA, OBABO, OpenMM's LangevinMiddle = BAOA) on vibrations.

On the harmonic oscillator (scaled so that the exact stationary law is N(0, I), z = omega h,
friction g = gamma / omega) one step is ``x' = M x + N xi``; the covariance follows
``Sigma' = M Sigma M^T + N N^T``. The stationary variances in closed form
(:data:`stepsafe.core.langevin.CLOSED_FORMS`) are checked against the fixed point of that
recursion solved at 50 digits here (mpmath, the matrices built in this file from the
letters), and against a simulation written here (numpy, fixed seed) within five standard
errors. The mean map's stability for every friction (z < 2 for all four) is checked on
matrices built here, and what region, advise, check and the other analyses report for
such a method.
"""

from __future__ import annotations

import json

import mpmath as mp
import numpy as np
import pytest

import stepsafe
from stepsafe.core import langevin as L
from stepsafe.core.transfer import transfer_matrix
from stepsafe.exceptions import MethodError, StepsafeError
from stepsafe.methods.langevin import Langevin
from stepsafe.methods.library import resolve

FILES = {"baoab": "BAOAB", "aboba": "ABOBA", "obabo": "OBABO", "langevin-middle": "BAOA"}


def closed_form(word: str, z):
    """``(Sigma_qq, Sigma_pp, Sigma_qp)`` as stated in stepsafe.core.langevin, written
    again here (exact in mpmath when z is an mpf)."""
    x = z * z
    return {"BAOAB": (1, 1 - x / 4, 0), "ABOBA": (1, 1 / (1 - x / 4), 0),
            "OBABO": (1 / (1 - x / 4), 1, 0), "BAOA": (1, 1, z / 2)}[word]


def mp_moments(word: str, z, g):
    """``(M, Q)`` at mpmath precision from the letters: A_t q += t z p, B_t p -= t z q,
    O_t p <- c p + sqrt(1 - c^2) xi with c = exp(-g t z); each letter's t is 1 over its
    count."""
    M, Q = mp.eye(2), mp.zeros(2, 2)
    for ch in word:
        t = mp.mpf(1) / word.count(ch)
        if ch == "A":
            F = mp.matrix([[1, t * z], [0, 1]])
        elif ch == "B":
            F = mp.matrix([[1, 0], [-t * z, 1]])
        else:
            F = mp.matrix([[1, 0], [0, mp.exp(-g * t * z)]])
        M, Q = F * M, F * Q * F.T
        if ch == "O":
            Q[1, 1] += 1 - F[1, 1] ** 2
    return M, Q


def mp_fixed_point(word: str, z, g):
    """``Sigma = M Sigma M^T + Q`` solved for ``(s_qq, s_qp, s_pp)`` by mpmath's LU."""
    M, Q = mp_moments(word, z, g)
    a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
    A = mp.matrix([[1 - a * a, -2 * a * b, -b * b],
                   [-a * c, 1 - (a * d + b * c), -b * d],
                   [-c * c, -2 * c * d, 1 - d * d]])
    s = mp.lu_solve(A, mp.matrix([Q[0, 0], Q[0, 1], Q[1, 1]]))
    return s[0], s[2], s[1]


Z = ["0.1", "0.7", "1.3", "1.9", "1.999"]
FRICTIONS = ["0.001", "0.5", "3", "50"]


@pytest.mark.parametrize("word", sorted(FILES.values()))
def test_closed_forms_are_the_covariance_fixed_point_at_50_digits(word):
    """Every closed form equals the fixed point of the Lyapunov recursion solved at 50
    digits, to 40 (near z = 2 at small friction the 3x3 system's condition number reaches
    1e5), at steps from 0.1 to 1.999 and frictions from 1e-3 to 50 per unit of frequency:
    none depends on the friction."""
    with mp.workdps(50):
        for z in map(mp.mpf, Z):
            for g in map(mp.mpf, FRICTIONS):
                got = mp_fixed_point(word, z, g)
                for value, stated in zip(got, closed_form(word, z)):
                    assert abs(value - stated) <= mp.mpf("1e-40") * (1 + abs(stated)), \
                        (word, z, g)


@pytest.mark.parametrize("name, word", sorted(FILES.items()))
def test_float_stationary_covariance_is_the_50_digit_fixed_point(name, word):
    """stepsafe's float64 covariance recursion (the mean map from the one engine, the noise
    from the friction steps) has the 50-digit fixed point to the rounding of its 3x3 solve:
    16 eps times that system's condition number, relative (1e-10 near z = 2 at small
    friction, 1e-14 elsewhere)."""
    m = resolve(name)[0]
    for g in (0.001, 0.5, 3.0, 50.0):
        z = np.array([float(x) for x in Z])
        M, Q = L.step_moments(m, z, g)
        S = L.stationary_covariance(M, Q)
        with mp.workdps(50):
            for k, zk in enumerate(Z):
                qq, pp, qp = mp_fixed_point(word, mp.mpf(zk), mp.mpf(g))
                want = np.array([[float(qq), float(qp)], [float(qp), float(pp)]])
                a, b, c, d = M[k].ravel()
                system = np.eye(3) - np.array([[a * a, 2 * a * b, b * b],
                                               [a * c, a * d + b * c, b * d],
                                               [c * c, 2 * c * d, d * d]])
                bound = 16 * np.finfo(float).eps * np.linalg.cond(system)
                assert np.abs(S[k] - want).max() <= bound * (1 + np.abs(want).max()), (zk, g)


def _simulate(word: str, z: float, gamma: float, walkers: int, rng) -> np.ndarray:
    """Walkers of the oscillator (omega = m = kT = 1) stepped by the word's substeps from
    the exact law N(0, I); returns the states at 5 snapshots 60 steps apart, after 120
    steps of burn-in, as an array (5 * walkers, 2). Written here from the definitions:
    A_t q += t h p, B_t p -= t h q, O_t p <- c p + sqrt(1 - c^2) xi, c = exp(-gamma t h);
    LangevinMiddle as OpenMM states it (v += h F, x += v h/2, O, x += v h/2)."""
    q, p = rng.standard_normal(walkers), rng.standard_normal(walkers)
    counts = {ch: word.count(ch) for ch in "ABO"}
    out = []
    for step in range(1, 120 + 5 * 60 + 1):
        for ch in word:
            t = z / counts[ch]
            if ch == "A":
                q = q + t * p
            elif ch == "B":
                p = p - t * q
            else:
                c = np.exp(-gamma * t)
                p = c * p + np.sqrt(1 - c * c) * rng.standard_normal(walkers)
        if step > 120 and (step - 120) % 60 == 0:
            out.append(np.stack([q, p], axis=1))
    return np.concatenate(out)


def _simulate_openmm_middle(z: float, gamma: float, walkers: int, rng) -> np.ndarray:
    """OpenMM's LangevinMiddle step as its documentation writes it, state (x_n,
    v_{n+1/2}); the same snapshots as :func:`_simulate`."""
    x, v = rng.standard_normal(walkers), rng.standard_normal(walkers)
    a = np.exp(-gamma * z)
    out = []
    for step in range(1, 120 + 5 * 60 + 1):
        v = v + z * (-x)
        x = x + v * z / 2
        v = a * v + np.sqrt(1 - a * a) * rng.standard_normal(walkers)
        x = x + v * z / 2
        if step > 120 and (step - 120) % 60 == 0:
            out.append(np.stack([x, v], axis=1))
    return np.concatenate(out)


@pytest.mark.parametrize("word", sorted(FILES.values()))
def test_simulation_samples_the_closed_form_variances(word):
    """20,000 walkers, 5 snapshots 60 steps apart (the mean's correlation decays by
    ``rho^60``, below 1e-10 here) at z = 1.2, gamma = 1: each of <q^2>, <p^2>, <q p> is
    within five standard errors (the snapshots' sample standard deviation over the root of
    their number, about 0.5% of a variance) of its closed form, whose departures from 1
    (OBABO's 1.5625, ABOBA's 1.5625, BAOAB's 0.64, BAOA's correlation 0.6) are 30 to 100
    such errors."""
    rng = np.random.default_rng(20240611)
    z, walkers = 1.2, 20_000
    x = (_simulate_openmm_middle(z, 1.0, walkers, rng) if word == "BAOA"
         else _simulate(word, z, 1.0, walkers, rng))
    products = {"qq": x[:, 0] ** 2, "pp": x[:, 1] ** 2, "qp": x[:, 0] * x[:, 1]}
    qq, pp, qp = closed_form(word, z)
    for key, stated in (("qq", qq), ("pp", pp), ("qp", qp)):
        sample = products[key]
        error = sample.std() / np.sqrt(sample.size)
        assert abs(sample.mean() - stated) <= 5 * error, (key, sample.mean(), stated, error)
    # and the simulation tells the closed forms apart from exact sampling
    if word in ("OBABO", "ABOBA", "BAOAB"):
        key = "qq" if word == "OBABO" else "pp"
        sample = products[key]
        assert abs(sample.mean() - 1.0) > 20 * sample.std() / np.sqrt(sample.size)


def _mean_map(word: str, z: float, c: float) -> np.ndarray:
    M = np.eye(2)
    for ch in word:
        t = z / word.count(ch)
        F = {"A": [[1, t], [0, 1]], "B": [[1, 0], [-t, 1]],
             "O": [[1, 0], [0, c ** (1 / word.count("O"))]]}[ch]
        M = np.array(F, dtype=float) @ M
    return M


@pytest.mark.parametrize("word", sorted(FILES.values()))
def test_mean_map_is_stable_below_2_at_every_friction_and_not_beyond(word):
    """The mean map (built here) has spectral radius < 1 for every c = exp(-gamma h) in
    (0, 1) when z < 2; for every z > 2 some friction makes it unstable (as c -> 1 it is
    Verlet's, hyperbolic there): friction leaves the limit where Verlet has it."""
    cs = np.concatenate([np.geomspace(1e-12, 0.5, 40), 1 - np.geomspace(0.5, 1e-9, 40)])
    for z in np.concatenate([np.linspace(0.01, 1.99, 60), [1.999999]]):
        radius = [np.abs(np.linalg.eigvals(_mean_map(word, z, c))).max() for c in cs]
        assert max(radius) < 1.0, z
    for z in (2.000001, 2.3, 3.0, 5.0):
        radius = [np.abs(np.linalg.eigvals(_mean_map(word, z, c))).max() for c in cs]
        assert max(radius) > 1.0, z


@pytest.mark.parametrize("name, word", sorted(FILES.items()))
def test_region_is_the_mean_maps_stability_at_every_friction(name, word):
    """The region (stability criterion) ends at z* = 2 within its stated uncertainty, is
    not called symplectic, and the engine's mean map has det M = exp(-gamma h) and is the
    product of the letters' matrices built here."""
    m = resolve(name)[0]
    region = stepsafe.region(name, "oscillator", criterion="stability")
    data = region.to_dict()["models"]["oscillator"]
    assert data["symplectic"] is False and data["criterion"] == "stability"
    assert abs(data["first_boundary"] - 2.0) <= data["first_boundary_uncertainty"] + 1e-12
    assert [iv[0] for iv in data["intervals"]] == [0.0]
    z = np.array([0.3, 1.1, 1.9, 2.5])
    M = transfer_matrix(m, z, "oscillator")
    assert np.allclose(np.linalg.det(M), np.exp(-m.friction * z), rtol=1e-13)
    for zk, Mk in zip(z, M):
        c = np.exp(-m.friction * zk)
        assert np.abs(Mk - _mean_map(word, zk, c)).max() <= 1e-14 * (1 + np.abs(Mk).max())


def test_advise_and_check_give_the_mean_maps_limit():
    """advise: h_max = 2 / beta_max less the boundary's uncertainty; check: safe just below,
    unsafe just above (exit codes 0 and 1 on the command line)."""
    advice = stepsafe.advise("baoab", beta=[1.0, 4.0], criterion="stability")
    assert advice.h_max == pytest.approx(0.5, rel=1e-12) and advice.h_max <= 0.5
    assert stepsafe.check("obabo", 0.499, beta=[4.0], criterion="stability").safe
    assert not stepsafe.check("obabo", 0.501, beta=[4.0], criterion="stability").safe
    from click.testing import CliRunner

    from stepsafe.cli import main

    runner = CliRunner()
    for h, code in (("0.49", 0), ("0.51", 1)):
        res = runner.invoke(main, ["check", "--method", "langevin-middle", "--beta", "4",
                                   "--step", h, "--criterion", "stability"],
                            catch_exceptions=False)
        assert res.exit_code == code, res.output


def test_the_structure_criterion_is_refused_with_what_applies():
    """A Langevin splitting keeps no Hamiltonian structure: the structure criterion, asked
    for, is refused naming the method and the criterion that applies, exit 2 in one line
    (without a criterion, stability is used); errors, resonance orders and saddle or
    barrier models are refused too."""
    for call in (lambda: stepsafe.advise("baoab", beta=[1.0], criterion="structure"),
                 lambda: stepsafe.check("baoab", 0.1, beta=[1.0], criterion="structure"),
                 lambda: stepsafe.region("baoab", criterion="structure")):
        with pytest.raises(StepsafeError, match="baoab.*--criterion stability"):
            call()
    with pytest.raises(StepsafeError, match="Hamiltonian map"):
        stepsafe.errors("obabo", [0.5])
    with pytest.raises(StepsafeError, match="oscillator model only"):
        stepsafe.region("obabo", "inverted", criterion="stability")
    with pytest.raises(StepsafeError, match="Hamiltonian map"):
        stepsafe.advise("obabo", beta=[1.0], criterion="stability", resonance_order=4)
    report = stepsafe.region("aboba", criterion="stability").to_dict()
    assert set(report["models"]["saddle"]) == {"not_analysed"}
    from click.testing import CliRunner

    from stepsafe.cli import main

    res = CliRunner().invoke(main, ["advise", "--method", "baoab", "--beta", "1",
                                    "--criterion", "structure"])
    assert res.exit_code == 2
    assert len(res.output.strip().splitlines()) == 1 and "--criterion stability" in res.output


def test_a_langevin_method_is_refused_where_it_has_no_meaning():
    """Not a base of a composition, not run by the deterministic engine, not analysed on a
    coupled 2n x 2n system."""
    from stepsafe.core.integrator import Engine, System
    from stepsafe.methods.tableaux import Composition
    from stepsafe.systems.coupled import one_step_matrix

    m = resolve("baoab")[0]
    with pytest.raises(MethodError, match="Langevin"):
        Composition(m, [0.5, 0.5])
    system = System(lambda q, p: q, lambda q, p: p, lambda q, p: 0 * q, True, 1)
    with pytest.raises(ValueError, match="random numbers"):
        Engine(m, system)
    with pytest.raises(StepsafeError, match="coupled"):
        one_step_matrix(m, np.eye(4), 0.1)


@pytest.mark.parametrize("letters, message", [
    ("BAXAB", "A \\(drift\\), B \\(kick\\) and O"), ("BAB", "no O"), ("BOAOB", "one run"),
    ("", "A \\(drift\\)"), ("B" * 65, "at most 64")])
def test_a_bad_word_is_refused(letters, message):
    with pytest.raises(MethodError, match=message):
        Langevin(letters)


def test_a_word_not_symmetric_about_its_friction_step_has_no_region():
    """BAOBA's drifts and kicks from the O step, B A B A, are not a palindrome: where its
    mean map is stable for every friction is not their region, so it is refused; its
    mean map and covariance are still computed."""
    m = Langevin("BAOBA", name="baoba")
    with pytest.raises(MethodError, match="not symmetric"):
        stepsafe.core.regions.find_region(m, "oscillator")
    S = L.stationary_covariance(*L.step_moments(m, [0.5], 1.0))
    assert np.all(np.isfinite(S))


def test_method_file_of_kind_langevin(tmp_path):
    """A method file gives the word, the friction and kT; a bad value names its key."""
    path = tmp_path / "mine.yaml"
    path.write_text("name: mine\nkind: langevin\norder: 2\nsource: test\n"
                    "letters: OBABO\nfriction: '2.5'\nkT: '1/2'\n")
    m = stepsafe.method(str(path))
    assert (m.kind, m.tableau.letters, m.tableau.friction, m.tableau.kT) == \
        ("langevin", "OBABO", 2.5, 0.5)
    assert m.evaluations is None and m.tableau.forces_per_step == 1
    from click.testing import CliRunner

    from stepsafe.cli import main

    for text, key in (("letters: OBXBO\n", "letters"), ("letters: OBABO\nfriction: '-1'\n",
                                                          "friction"),
                      ("letters: OBABO\nkT: '0'\n", "kT"),
                      ("letters: OBABO\ndrift: [1]\n", "drift")):
        bad = tmp_path / "bad.yaml"
        bad.write_text("name: bad\nkind: langevin\norder: 2\nsource: test\n" + text)
        res = CliRunner().invoke(main, ["validate", str(bad)])
        assert res.exit_code == 2 and f"{bad}::$.{key}" in res.output, res.output


@pytest.mark.parametrize("name, word", sorted(FILES.items()))
def test_sampling_report_gives_the_closed_forms_at_any_friction(name, word):
    """stepsafe.core.langevin.sampling: the numeric fixed point equals the closed form (1e-12)
    at frictions 0.01, 1 and 100 per time unit; the mean decays per step by at most 1
    below the limit; h_stable = 2 / beta_max (less the boundary's uncertainty); unstable
    modes have no variances."""
    betas = [0.5, 2.0, 3.5]
    for friction in (0.01, 1.0, 100.0):
        report = L.sampling(name, betas, 0.5, friction=friction)
        assert report.h_stable == pytest.approx(2.0 / 3.5, rel=1e-12)
        for mode in report.modes:
            if mode.z < 2.0:
                assert mode.stable and mode.decay < 1.0
                got = (mode.configurational, mode.kinetic, mode.correlation)
                assert np.allclose(got, closed_form(word, mode.z), rtol=1e-12, atol=1e-12)
                assert np.allclose(got, mode.closed_form, rtol=1e-12, atol=1e-12)
            else:
                assert not mode.stable and mode.configurational is None
    data = json.loads(json.dumps(report.to_dict()))
    assert data["letters"] == word and len(data["modes"]) == 3


def test_largest_step_for_a_sampling_tolerance():
    """The step a tolerance on the temperature ratio allows, against the closed forms:
    OBABO's configurational 1 / (1 - z^2/4) - 1 <= tol at z = 2 sqrt(tol / (1 + tol));
    BAOAB's kinetic z^2 / 4 <= tol at z = 2 sqrt(tol); BAOAB's configurational ratio is
    exact, so stability binds (None)."""
    for tol in (1e-3, 0.05):
        z = L.step_for_tolerance("obabo", tol, "configurational")
        assert z == pytest.approx(2 * np.sqrt(tol / (1 + tol)), rel=1e-9)
        assert L.step_for_tolerance("baoab", tol, "kinetic") == \
            pytest.approx(2 * np.sqrt(tol), rel=1e-9)
    assert L.step_for_tolerance("baoab", 1e-6, "configurational") is None


def test_advise_and_check_say_what_the_verdict_of_a_langevin_splitting_means():
    """Without a criterion a Langevin splitting is judged by the stability of its mean map
    (stated in the output with the friction and kT it was read with); check adds how the
    fastest vibration is sampled at the step, equal to the closed forms written here."""
    from click.testing import CliRunner

    from stepsafe.cli import main

    runner = CliRunner()
    res = runner.invoke(main, ["advise", "--method", "baoab", "--beta", "1", "--beta", "4"],
                        catch_exceptions=False)
    assert res.exit_code == 0 and "stability is that of the mean map" in res.output
    assert "friction gamma = 1" in res.output
    res = runner.invoke(main, ["check", "--method", "obabo", "--beta", "4", "--step", "0.3",
                               "--json"], catch_exceptions=False)
    assert res.exit_code == 0
    sampled = json.loads(res.output)["checks"][0]["stochastic"]["sampling"]
    qq, pp, qp = closed_form("OBABO", 1.2)
    assert sampled["configurational_temperature_ratio"] == pytest.approx(qq, rel=1e-12)
    assert sampled["kinetic_temperature_ratio"] == pytest.approx(pp, rel=1e-12)
    res = runner.invoke(main, ["show", "langevin-middle"], catch_exceptions=False)
    assert res.exit_code == 0 and "<q p> omega/kT = z/2" in " ".join(res.output.split())


def test_a_langevin_method_file_without_its_word_is_refused(tmp_path):
    """``letters`` is required: its absence is one line naming the file and the key, exit 2."""
    from click.testing import CliRunner

    from stepsafe.cli import main

    bad = tmp_path / "noword.yaml"
    bad.write_text("name: noword\nkind: langevin\norder: 2\nsource: test\nfriction: 2\n")
    for args in (["validate", str(bad)], ["advise", "--method", str(bad), "--beta", "1"]):
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 2 and "letters" in res.output and str(bad) in res.output, \
            res.output
        assert len(res.output.strip().splitlines()) == 1


def test_langevin_outputs_follow_their_schemas():
    """show, region, advise and check of a Langevin splitting (with the keys only it has:
    ``note``, ``harmonic_sampling``, ``stochastic``) are valid under the published output
    schemas."""
    jsonschema = pytest.importorskip("jsonschema")
    from click.testing import CliRunner

    from stepsafe.api.schemas import output_schema
    from stepsafe.cli import main

    runner = CliRunner()
    for command, args in (("show", ["show", "baoab"]), ("region", ["region", "obabo"]),
                          ("advise", ["advise", "--method", "aboba", "--beta", "2"]),
                          ("check", ["check", "--method", "langevin-middle", "--beta", "2",
                                     "--step", "0.5"])):
        res = runner.invoke(main, [*args, "--json"], catch_exceptions=False)
        assert res.exit_code == 0, res.output
        jsonschema.validate(json.loads(res.output), output_schema(command))
