"""Impulse (r-RESPA) method files, scenes with fast and slow frequencies, split stiffness
matrices: checked against an independent 50-digit product of the kicks and drifts in
(q, p), against real r-RESPA integrations, and for their errors on bad input."""

from __future__ import annotations

import json
import math

import mpmath as mp
import numpy as np
import pytest
from support import respa_mp, respa_stable_mp

from stepsafe import impulse, impulse_advice
from stepsafe.exceptions import StepsafeError


def _respa_run(q, p, H, steps, k, fast_force, slow_force):
    """Velocity Verlet r-RESPA on arrays (independent of stepsafe): the forces are
    callables of q; unit masses (the caller works in mass-weighted coordinates)."""
    h = H / k
    f_slow, f_fast = slow_force(q), fast_force(q)
    for _ in range(steps):
        p = p + 0.5 * H * f_slow
        for _ in range(k):
            p = p + 0.5 * h * f_fast
            q = q + h * p
            f_fast = fast_force(q)
            p = p + 0.5 * h * f_fast
        f_slow = slow_force(q)
        p = p + 0.5 * H * f_slow
    return q, p


# ---------------------------------------------------------------- the method file


def test_the_file_is_verlet_over_verlet_with_its_substeps():
    from stepsafe import method

    m = method("respa-verlet")
    assert (m.kind, m.order, m.tableau.substeps) == ("impulse", 2, 4)
    assert m.tableau.force_evaluations == (4, 1)
    for k in (4, 7):
        by_file = impulse("respa-verlet", substeps=k, fast_beta=10.0, slow_beta=1.0)
        by_parts = impulse("verlet", "verlet", substeps=k, fast_beta=10.0, slow_beta=1.0)
        assert by_file.safe_h == by_parts.safe_h and by_file.substeps == k
    assert method("verlet-i").name == "respa-verlet"


def test_force_evaluations_count_reused_forces():
    from stepsafe import method
    from stepsafe.core.impulse import impulse_method

    verlet, pefrl = method("verlet").tableau, method("pefrl").tableau
    assert impulse_method(verlet, verlet, 1).force_evaluations == (1, 1)
    # PEFRL starts and ends with a drift: 4 fresh fast forces per inner step
    assert impulse_method(verlet, pefrl, 2).force_evaluations == (8, 1)
    # outer PEFRL: each of its 4 slow kicks follows a drift
    assert impulse_method(pefrl, verlet, 3).force_evaluations == (15, 4)


def test_order_two_measured_on_a_split_pendulum():
    """H = p^2/2 - a cos q - b cos q, fast a = 25, slow b = 1: the error at t = 2 falls
    like H^2 (the file's order), against an independent adaptive reference."""
    from scipy.integrate import solve_ivp

    a, b, k, T = 25.0, 1.0, 4, 2.0
    ref = solve_ivp(lambda t, y: [y[1], -(a + b) * math.sin(y[0])], (0, T), [1.0, 0.0],
                    method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    errors = []
    for n in (40, 80, 160, 320):
        q, p = _respa_run(np.array([1.0]), np.array([0.0]), T / n, n, k,
                          lambda q: -a * np.sin(q), lambda q: -b * np.sin(q))
        errors.append(math.hypot(q[0] - ref[0], p[0] - ref[1]))
    orders = [math.log2(e1 / e2) for e1, e2 in zip(errors, errors[1:])]
    assert all(abs(o - 2.0) < 0.15 for o in orders[1:]), orders


def test_other_analyses_refuse_an_impulse_method(run):
    import stepsafe

    for call in (lambda: stepsafe.advise("respa-verlet", beta=[1.0]),
                 lambda: stepsafe.region("respa-verlet"),
                 lambda: stepsafe.compare(["verlet", "respa-verlet"], beta=[1.0],
                                          tol_phase=1e-3)):
        with pytest.raises(StepsafeError, match="impulse"):
            call()
    for args in (("advise", "--method", "respa-verlet", "--beta", "1"),
                 ("compare", "verlet", "respa-verlet", "--beta", "1", "--tol-phase", "1e-3"),
                 ("region", "respa-verlet"), ("region", "verlet", "--ratio", "0.1"),
                 ("advise", "--method", "verlet", "--beta", "1", "--substeps", "3")):
        code, _, err = run(*args)
        assert code == 2 and err.count("\n") == 1, (args, err)
    code, out, err = run("compare", "--beta", "1", "--tol-phase", "1e-3")
    assert code == 0 and "respa" not in out, err


# ---------------------------------------------------------------- several modes


@pytest.mark.parametrize("seed", range(4))
def test_modes_together_at_50_digits(seed):
    """H is reported safe exactly where every mode's outer step is stable (|tr M| < 2,
    50-digit products), away from the boundaries' rounding."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(2, 7))
    pairs = [(float(10 ** rng.uniform(-1, 1)), float(10 ** rng.uniform(-2, 0)))
             for _ in range(int(rng.integers(1, 4)))]
    report = impulse_advice("respa-verlet", pairs, substeps=k, criterion="stability")
    ends = [x for iv in report.safe_h for x in iv if x is not None]
    for H in np.linspace(0, report.horizon, 400)[1:-1]:
        if any(abs(H - e) < 1e-8 * e for e in ends):
            continue
        inside = any(lo < H < (report.horizon if hi is None else hi)
                     for lo, hi in report.safe_h)
        assert inside == all(respa_stable_mp(f, s, k, H) for f, s in pairs), (pairs, k, H)
    assert report.h_max == min(r.h_max for r in report.modes)
    assert report.modes[report.limiting].h_max == report.h_max


def test_a_step_is_checked_in_every_mode():
    pairs = [(10.0, 1.0), (4.0, 2.0)]
    ok = impulse_advice("respa-verlet", pairs, labels=["a", "b"], step=0.25)
    assert ok.safe is True and not ok.failures
    bad = impulse_advice("respa-verlet", pairs, labels=["a", "b"], step=0.304)
    assert bad.safe is False and [f["label"] for f in bad.failures] == ["a"]
    data = bad.to_dict()
    assert data["failures"][0]["reason"] and data["kind"] == "impulse"


# ---------------------------------------------------------------- scenes


WATER = """\
method: respa-verlet
time_unit: fs
substeps: 4
modes:
  - {fast: 3700 cm-1, slow: 300 cm-1, label: O-H stretch}
  - {fast: 1600 cm-1, slow: "300 cm-1", label: bend}
  - {fast: 0, slow: 60 cm-1}
"""


def test_a_scene_with_fast_and_slow_frequencies(tmp_path, run):
    from stepsafe.units import quantity

    scene = tmp_path / "water.yaml"
    scene.write_text(WATER)
    report = impulse_advice(scene=str(scene))
    oh = impulse("respa-verlet", fast_beta=quantity("3700", "wavenumber", "fs"),
                 slow_beta=quantity("300", "wavenumber", "fs"))
    assert report.h_max == oh.h_max and report.limiting == 0
    assert report.modes[2].fast == 0 and report.time_unit == "fs"
    code, out, err = run("advise", str(scene), "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["h_max"] == report.h_max and data["modes"][0]["label"] == "O-H stretch"
    code, out, _ = run("advise", str(scene))
    assert "limited by O-H stretch" in out and " fs" in out
    code, out, _ = run("check", str(scene), "--step", "2")
    assert code == 0 and "SAFE: H = 2 fs" in out
    code, out, _ = run("check", str(scene), "--step", "5")
    assert code == 1 and "UNSAFE" in out and "O-H stretch" in out
    code, out, _ = run("check", str(scene), "--step", "3.5", "--resonance-order", "3")
    assert code == 1 and "3:1" in out
    code, out, _ = run("check", str(scene), "--step", "5", "--substeps", "1")
    assert code == 1
    eight = impulse_advice(scene=str(scene), substeps=8)
    assert eight.substeps == 8 and eight.h_max != report.h_max


@pytest.mark.parametrize("text, key", [
    ("modes:\n  - {fast: 1, label: a}\n", "modes[0]"),
    ("modes:\n  - {fast: 1, slow: 1, model: inverted}\n", "modes[0].model"),
    ("modes:\n  - {fast: 0, slow: 0}\n", "modes[0]"),
    ("modes:\n  - {fast: -1, slow: 1}\n", "modes[0].fast"),
    ("modes:\n  - {fast: 1e400, slow: 1}\n", "modes[0].fast"),
    ("modes:\n  - {fast: 3700 cm-1, slow: 1}\n", "modes[0].fast"),  # no time unit
    ("modes:\n  - {fast: 1 furlong, slow: 1}\n", "modes[0].fast"),
    ("modes:\n  - {fast: 1, slow: 1, label: [x]}\n", "modes[0].label"),
    ("substeps: 0\nmodes:\n  - {fast: 1, slow: 1}\n", "substeps"),
    ("substeps: 2.5\nmodes:\n  - {fast: 1, slow: 1}\n", "substeps"),
    ("system: {stiffness_fast: [[1]], stiffnes_slow: [[1]]}\n", "system.stiffnes_slow"),
    ("system: {stiffness_fast: [[1]]}\n", "system.stiffness_slow"),
    ("system: {stiffness_fast: [[1, 0], [0, 2]], stiffness_slow: [[1]]}\n",
     "system.stiffness_slow"),
    ("system: {stiffness_fast: [[1]], stiffness_slow: [[-1]]}\n", "system.stiffness_slow"),
    ("system: {stiffness_fast: [[1]], stiffness_slow: [[1]], mass: [[-1]]}\n",
     "system.mass"),
])
def test_bad_scenes_name_the_key(tmp_path, run, text, key):
    scene = tmp_path / "bad.yaml"
    scene.write_text("method: respa-verlet\nh: 0.1\n" + text)
    code, out, err = run("check", str(scene))
    assert code == 2 and err.count("\n") == 1 and out == "", err
    assert f"bad.yaml::$.{key}" in err, err


def test_command_line_frequencies_do_not_apply(tmp_path, run):
    scene = tmp_path / "s.yaml"
    scene.write_text("method: respa-verlet\nmodes:\n  - {fast: 1, slow: 0.1}\n")
    for extra in (("--beta", "1"), ("--margin", "0.9"), ("--verify",), ("--zmax", "4"),
                  ("--tol-phase", "1e-3")):
        code, _, err = run("advise", str(scene), *extra)
        assert code == 2 and err.count("\n") == 1, (extra, err)
    code, _, err = run("advise", "--method", "respa-verlet")
    assert code == 2 and "scene" in err


# ---------------------------------------------------------------- split stiffness


def _split_system(rng, n):
    """Commuting mass-weighted parts with known modes: K = L Q diag(w^2) Q^T L^T."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    B = rng.normal(size=(n, n))
    M = B @ B.T + n * np.eye(n)
    L = np.linalg.cholesky(M)
    fast = 10 ** rng.uniform(0, 1, n)
    slow = 10 ** rng.uniform(-1.5, -0.5, n)
    K_f = L @ Q @ np.diag(fast ** 2) @ Q.T @ L.T
    K_s = L @ Q @ np.diag(slow ** 2) @ Q.T @ L.T
    return K_f, K_s, M, L, Q, fast, slow


def test_a_split_stiffness_decouples_into_its_modes(tmp_path):
    from stepsafe.systems.multiple import impulse_pairs

    rng = np.random.default_rng(3)
    K_f, K_s, M, _, _, fast, slow = _split_system(rng, 5)
    pairs = impulse_pairs({"stiffness_fast": K_f, "stiffness_slow": K_s, "mass": M}, "s",
                          tmp_path)
    expected = np.column_stack([fast, slow])[np.argsort(fast ** 2 + slow ** 2)]
    assert np.allclose(pairs, expected, rtol=1e-9)
    scene = tmp_path / "split.yaml"
    np.save(tmp_path / "kf.npy", K_f)
    np.save(tmp_path / "ks.npy", K_s)
    np.save(tmp_path / "m.npy", M)
    scene.write_text("method: respa-verlet\nsystem: {stiffness_fast: kf.npy, "
                     "stiffness_slow: ks.npy, mass: m.npy}\n")
    report = impulse_advice(scene=str(scene))
    direct = impulse_advice("respa-verlet", expected)
    assert report.h_max == pytest.approx(direct.h_max, rel=1e-9)


def test_the_predicted_limit_is_measured_in_a_real_integration():
    """r-RESPA on a 3-dof system with a mass matrix (forces -K_f q and -K_s q): the
    energy stays bounded at 0.97 h_max; inside the first unstable band it grows at the
    rate the 50-digit trace predicts (lam = |tr|/2 + sqrt(tr^2/4 - 1) per step)."""
    rng = np.random.default_rng(11)
    n, k = 3, 4
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    B = rng.normal(size=(n, n))
    L = np.linalg.cholesky(B @ B.T + n * np.eye(n))
    fast, slow = np.array([3.0, 2.0, 1.0]), np.array([1.2, 0.8, 0.5])
    K_f = L @ Q @ np.diag(fast ** 2) @ Q.T @ L.T
    K_s = L @ Q @ np.diag(slow ** 2) @ Q.T @ L.T
    report = impulse_advice("respa-verlet", np.column_stack([fast, slow]), substeps=k,
                            criterion="stability")
    Li = np.linalg.inv(L)  # mass-weighted coordinates y = L^T q have unit masses
    A_f, A_s = Li @ K_f @ Li.T, Li @ K_s @ Li.T
    A = A_f + A_s

    def energy(steps, H):
        y0 = np.ones(n)
        y, v = _respa_run(y0, np.zeros(n), H, steps, k, lambda y: -A_f @ y,
                          lambda y: -A_s @ y)
        return (0.5 * v @ v + 0.5 * y @ A @ y) / (0.5 * y0 @ A @ y0)

    assert report.limiting == 0 and energy(3000, 0.97 * report.h_max) < 3.0
    band = report.modes[0].bands[0]
    H = 0.5 * (band["lo"] + band["hi"])
    assert all(any(lo < H < hi for lo, hi in m.safe_h if hi) for m in report.modes[1:])
    with mp.workdps(50):
        M2 = respa_mp(fast[0], slow[0], k, H)
        half = abs(M2[0, 0] + M2[1, 1]) / 2
        lam = float(half + mp.sqrt(half ** 2 - 1))
    steps = max(10, min(2000, int(60 / math.log(lam))))  # e^120 in energy at most
    # the rate between N and 2N steps (the start's projection on the growing direction
    # cancels)
    measured = math.log(energy(2 * steps, H) / energy(steps, H)) / (2 * steps)
    assert measured == pytest.approx(math.log(lam), rel=0.05), (lam, steps)


def _mp_respa_step(A_f, A_s, k, H):
    """The 2n x 2n r-RESPA step (unit masses) at 50 digits, in (y, v)."""
    n = len(A_f)
    Af, As, H = mp.matrix(A_f.tolist()), mp.matrix(A_s.tolist()), mp.mpf(H)
    eye, zero = mp.eye(n), mp.zeros(n)

    def block(a, b, c, d):
        out = mp.zeros(2 * n)
        for i in range(n):
            for j in range(n):
                out[i, j], out[i, n + j] = a[i, j], b[i, j]
                out[n + i, j], out[n + i, n + j] = c[i, j], d[i, j]
        return out

    def kick(A, c):
        return block(eye, zero, -c * A, eye)

    def drift(c):
        return block(eye, c * eye, zero, eye)

    h = H / k
    inner = kick(Af, h / 2) * drift(h) * kick(Af, h / 2)
    return kick(As, H / 2) * inner ** k * kick(As, H / 2)


def _structure_kept(A_f, A_s, k, H) -> bool:
    """Q = M^T J - J M positive definite at 50 digits (S definite: the structure)."""
    n = len(A_f)
    with mp.workdps(50):
        M = _mp_respa_step(A_f, A_s, k, H)
        J = mp.zeros(2 * n)
        for i in range(n):
            J[i, n + i], J[n + i, i] = 1, -1
        Q = M.T * J - J * M
        Q = (Q + Q.T) / 2
        return bool(min(mp.eigsy(Q, eigvals_only=True)) > 0)


@pytest.mark.parametrize("seed", range(3))
def test_parts_that_do_not_commute_get_the_coupled_analysis(seed, tmp_path, run):
    """The 2n x 2n outer step: kept just below h_max and lost just above it at 50 digits;
    for commuting parts the coupled answer is the decoupled one."""
    from stepsafe.api.md import impulse_method
    from stepsafe.systems.multiple import coupled_impulse, read_split

    rng = np.random.default_rng(seed)
    n, k = 3, int(rng.integers(2, 6))
    B, C = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    K_f = B @ B.T + n * np.eye(n) * 10 ** rng.uniform(0, 1)
    K_s = 0.05 * (C @ C.T + 0.1 * np.eye(n))
    split = read_split({"stiffness_fast": K_f, "stiffness_slow": K_s}, "s", tmp_path)
    assert split.pairs is None
    method = impulse_method("respa-verlet", substeps=k)
    result = coupled_impulse(method, split)
    assert result.h_max < result.horizon
    assert _structure_kept(K_f, K_s, k, result.h_max * (1 - 1e-6))
    assert not _structure_kept(K_f, K_s, k, result.h_max * (1 + 1e-6))
    K_cf, K_cs, M = _split_system(rng, n)[:3]
    commuting = read_split({"stiffness_fast": K_cf, "stiffness_slow": K_cs, "mass": M}, "s",
                           tmp_path)
    assert commuting.pairs is not None
    decoupled = impulse_advice(method, commuting.pairs, criterion="structure")
    assert coupled_impulse(method, commuting).h_max == pytest.approx(decoupled.h_max,
                                                                      rel=1e-9)
    scene = tmp_path / "coupled.yaml"

    def rows(A):
        return "[" + ", ".join("[" + ", ".join(repr(float(x)) for x in r) + "]"
                               for r in A) + "]"

    scene.write_text(f"method: respa-verlet\nsubsteps: {k}\nsystem:\n  stiffness_fast: "
                     f"{rows(K_f)}\n  stiffness_slow: {rows(K_s)}\n")
    code, out, err = run("advise", str(scene), "--json")
    assert code == 0, err
    printed = json.loads(out)["h_max"]  # less the matrices' float64 uncertainty
    assert printed <= result.h_max and printed == pytest.approx(result.h_max, rel=1e-10)
    assert run("check", str(scene), "--step", repr(0.99 * result.h_max))[0] == 0
    assert run("check", str(scene), "--step", repr(1.01 * result.h_max))[0] == 1
    for extra in (("--criterion", "stability"), ("--resonance-order", "3")):
        code, _, err = run("check", str(scene), "--step", "0.01", *extra)
        assert code == 2 and "coupled.yaml::$.system" in err, err


def test_coupled_limit_measured_in_a_real_integration(tmp_path):
    """r-RESPA on non-commuting parts: bounded energy at 0.97 h_max."""
    from stepsafe.api.md import impulse_method
    from stepsafe.systems.multiple import coupled_impulse, read_split

    rng = np.random.default_rng(5)
    n, k = 4, 4
    B, C = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    A_f, A_s = B @ B.T + n * np.eye(n), 0.3 * (C @ C.T + np.eye(n))
    split = read_split({"stiffness_fast": A_f, "stiffness_slow": A_s}, "s", tmp_path)
    h_max = coupled_impulse(impulse_method("respa-verlet", substeps=k), split).h_max
    A = A_f + A_s
    y0 = rng.normal(size=n)
    y, v = _respa_run(y0, np.zeros(n), 0.97 * h_max, 3000, k, lambda y: -A_f @ y,
                      lambda y: -A_s @ y)
    assert (0.5 * v @ v + 0.5 * y @ A @ y) / (0.5 * y0 @ A @ y0) < 5.0


def test_region_ratio_and_the_chart(run, tmp_path):
    code, out, err = run("region", "respa-verlet", "--ratio", "0.1", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["h_max"] == impulse("respa-verlet", fast_beta=1.0, slow_beta=0.1).h_max
    assert data["units"].startswith("Omega H")
    pytest.importorskip("matplotlib")
    png = tmp_path / "chart.png"
    code, _, err = run("plot", "respa-verlet", "--ratio", "0.1", "-o", str(png))
    assert code == 0 and png.read_bytes()[:4] == b"\x89PNG", err


def test_an_ill_conditioned_mass_widens_the_margin(tmp_path):
    """Mass condition 1e6: the whitened parts carry ~1e-10 relative errors, so the printed
    h_max sits below the analysis's boundary by that much, and the edge is not SAFE."""
    from stepsafe.api.md import impulse_method
    from stepsafe.systems.multiple import coupled_impulse, read_split

    rng = np.random.default_rng(4)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    M = Q @ np.diag([1.0, 1e3, 1e6]) @ Q.T
    K_f, K_s = np.diag([10.0, 20.0, 30.0]), np.diag([0.5, 0.2, 0.1]) + 0.05
    system = {"stiffness_fast": K_f, "stiffness_slow": K_s, "mass": M}
    split = read_split(system, "s", tmp_path)
    assert split.coupled_error > 1e-10
    scene = tmp_path / "m.yaml"
    np.save(tmp_path / "kf.npy", K_f)
    np.save(tmp_path / "ks.npy", K_s)
    np.save(tmp_path / "m.npy", M)
    scene.write_text("method: respa-verlet\nsystem: {stiffness_fast: kf.npy, stiffness_slow: "
                     "ks.npy, mass: m.npy}\n")
    report = impulse_advice(scene=str(scene), criterion="structure")
    if split.pairs is None:
        raw = coupled_impulse(impulse_method("respa-verlet"), split).h_max
        assert report.h_max < raw * (1 - split.coupled_error)
    assert impulse_advice(scene=str(scene), step=report.h_max * (1 + 1e-12),
                          criterion="structure").safe is False


@pytest.mark.slow
def test_impulse_inputs_at_the_edges_of_what_applies(run, tmp_path):
    """An impulse method as the base of a composition is refused (exit 2); substeps up to
    the merged-operation limit are accepted; a slow part 1e-9 of the fast one that does
    not commute with it goes to the coupled analysis; plot options that do not apply are
    refused."""
    from stepsafe.systems.multiple import read_split

    comp = tmp_path / "c.yaml"
    comp.write_text("name: c\nkind: composition\norder: 2\nsource: test\nbase: respa-verlet\n"
                    "weights: [1]\n")
    for args in (("region", str(comp)), ("region", "yoshida4", "--base", "respa-verlet"),
                 ("plot", "respa-verlet", "--ratio", "0.1", "--model", "saddle")):
        code, _, err = run(*args)
        assert code == 2 and err.count("\n") == 1, (args, err)
    assert impulse("respa-verlet", substeps=400, fast_beta=10.0, slow_beta=1.0).h_max > 0
    split = read_split({"stiffness_fast": np.diag([1.0, 4.0]),
                        "stiffness_slow": np.array([[1e-9, 0.9e-9], [0.9e-9, 1e-9]])},
                       "s", tmp_path)
    assert split.pairs is None


@pytest.mark.parametrize("text, key", [
    ("name: r\nkind: impulse\norder: 2\nsource: x\nouter: nosuch\ninner: verlet\n"
     "substeps: 2\n", "outer"),
    ("name: r\nkind: impulse\norder: 2\nsource: x\nouter: verlet\ninner: gauss\n"
     "substeps: 2\n", "inner"),
    ("name: r\nkind: composition\norder: 2\nsource: x\nbase: nosuch\nweights: [1]\n",
     "base"),
])
def test_unknown_referenced_methods_name_the_key(run, tmp_path, text, key):
    path = tmp_path / "m.yaml"
    path.write_text(text)
    code, _, err = run("show", str(path))
    assert code == 2 and f"m.yaml::$.{key}" in err, err


def test_a_mode_out_of_range_names_it(run, tmp_path):
    scene = tmp_path / "s.yaml"
    scene.write_text("method: respa-verlet\nh: 0.1\nmodes:\n  - {fast: 1, slow: 0}\n"
                     "  - {fast: 5e-324, slow: 0}\n")
    code, _, err = run("check", str(scene))
    assert code == 2 and "s.yaml::$.modes[1]" in err, err


@pytest.mark.parametrize("scale", [1e-150, 1e-20, 1e20, 1e150])
def test_modes_together_are_scale_free(scale):
    """Scaling every frequency by s scales every safe H by 1/s (the outer step depends on
    beta H only), from 1e-150 to 1e150; the edge stays unsafe at 50 digits."""
    pairs = [(10.0, 1.0), (4.0, 2.0), (0.0, 3.0)]
    base = impulse_advice("respa-verlet", pairs)
    scaled = impulse_advice("respa-verlet", [(f * scale, s * scale) for f, s in pairs])
    assert scaled.h_max == pytest.approx(base.h_max / scale, rel=1e-12)
    assert len(scaled.safe_h) == len(base.safe_h)
    scaled_pairs = [(f * scale, s * scale) for f, s in pairs]
    assert impulse_advice("respa-verlet", scaled_pairs,
                          step=scaled.h_max * (1 + 1e-9)).safe is False
    inside = scaled.h_max * (1 - 1e-6)
    assert impulse_advice("respa-verlet", scaled_pairs, step=inside).safe is True
    assert all(respa_stable_mp(f, s, 4, inside) for f, s in scaled_pairs)
