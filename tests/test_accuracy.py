"""Accuracy model: closed forms, mpmath at tiny z, simulated oscillators, orders, compare."""

from __future__ import annotations

import json
import math

import mpmath as mp
import numpy as np
import pytest
from support import method

from stepsafe.core.accuracy import errors, z_for_tolerance
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import transfer_matrix
from stepsafe.methods.tableaux import Composition, Splitting

ZS = [1e-8, 1e-6, 1e-4, 1e-2, 0.3, 0.49, 0.51, 1.0, 1.9]


def rel(a, b):
    return abs(a - b) / abs(b)


def test_verlet_phase_error_closed_form():
    e = errors(method("verlet"), ZS).phase
    with mp.workdps(80):
        for z, got in zip(ZS, e):
            zz = mp.mpf(z)
            exact = mp.acos(1 - zz**2 / 2) / zz - 1
            assert rel(got, float(exact)) < 1e-12, z


def test_midpoint_phase_error_closed_form():
    e = errors(method("midpoint"), ZS).phase
    with mp.workdps(80):
        for z, got in zip(ZS, e):
            zz = mp.mpf(z)
            assert rel(got, float(2 * mp.atan(zz / 2) / zz - 1)) < 1e-12, z


def test_symplectic_rk_conserves_energy_exactly():
    assert np.all(np.abs(errors(method("gauss", 2), ZS).energy) <= 1e-15)


def _mp_errors(name, z, model="oscillator"):
    """theta/z - 1 and kappa(S) - 1 from a 100-digit M(z) (reference_methods)."""
    from reference_methods import mp_transfer

    with mp.workdps(100):
        M = mp_transfer(name, dps=100)(mp.mpf(z), model)
        a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
        if model != "oscillator":
            mu = (a + d) / 2 + mp.sqrt(((a + d) / 2) ** 2 - 1)
            return float(mp.log(mu) / z - 1), None
        theta = mp.atan2(mp.sqrt(-b * c - (a - d) ** 2 / 4), (a + d) / 2)
        S = mp.matrix([[-c, (a - d) / 2], [(a - d) / 2, b]])
        lam = sorted(mp.eigsy(S)[0])
        return float(theta / z - 1), float(lam[1] / lam[0] - 1)


@pytest.mark.parametrize("name, zmin", [("yoshida4", 1e-6), ("ruth3", 1e-6),
                                        ("mclachlan4", 1e-6), ("symplectic-euler", 1e-6),
                                        ("pefrl", 1e-2), ("blanes-moan6", 0.6)])
def test_errors_match_mpmath_down_to_tiny_z(name, zmin):
    """Exact coefficients: to z = 1e-6. Published decimals satisfy the order conditions only
    to ~1e-17; the error-series terms that this leaves are below float64 rounding and are
    treated as zero (the ideal method's error), which the 100-digit reference of the
    decimal coefficients resolves below z ~ 1e-3."""
    m = method(name)
    z = np.array([zmin, 1e-3, 0.2, 0.45, 0.6, 1.2])
    z = z[z >= zmin]
    e = errors(m, z)
    h = errors(m, z, "inverted")
    for i, zz in enumerate(z):
        phase, energy = _mp_errors(name, zz)
        assert rel(e.phase[i], phase) < 1e-9, (zz, e.phase[i], phase)
        if energy != 0:
            assert rel(e.energy[i], energy) < 1e-9, (zz, e.energy[i], energy)
        rate, _ = _mp_errors(name, zz, "inverted")
        assert rel(h.phase[i], rate) < 1e-9, (zz, h.phase[i], rate)


def _run(m, q, p, h, steps):
    """Real integration of q' = p, p' = -q with the method's own drifts and kicks."""
    ops = (m.as_splitting() if isinstance(m, Composition) else m).operations
    energies = [0.5 * (q * q + p * p)]
    for _ in range(steps):
        for kind, c in ops:
            if kind == "drift":
                q = q + c * h * p
            else:
                p = p - c * h * q
        energies.append(0.5 * (q * q + p * p))
    return np.array(energies)


@pytest.mark.parametrize("name", ["verlet", "pefrl", "yoshida4", "blanes-moan4",
                                  "symplectic-euler"])
@pytest.mark.parametrize("m", [8, 12, 20])
def test_simulated_energy_error_matches_prediction(name, m):
    meth = method(name)
    assert isinstance(meth, (Splitting, Composition))
    target = 2 * math.pi / m  # rotation per step: the orbit closes after m steps

    def theta(z):
        M = transfer_matrix(meth, np.atleast_1d(z))
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        return np.arctan2(np.sqrt(-b * c - (a - d) ** 2 / 4), (a + d) / 2) - target

    lo, hi = target * 0.5, min(target * 1.5, find_region(meth, "oscillator").first_boundary)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if theta(mid)[0] < 0 else (lo, mid)
    z = 0.5 * (lo + hi)
    M = transfer_matrix(meth, [z])[0]
    S = np.array([[-M[1, 0], (M[0, 0] - M[1, 1]) / 2], [(M[0, 0] - M[1, 1]) / 2, M[0, 1]]])
    w, v = np.linalg.eigh(S)
    x0 = v[:, 0]  # smallest eigenvalue of S: the farthest point of the ellipse, max energy
    energies = _run(meth, x0[0], x0[1], z, m)
    measured = energies.max() / energies.min() - 1
    predicted = errors(meth, [z]).energy[0]
    # the float64 run loses a few eps of the energy per step: that is the measurement floor
    assert rel(measured, predicted) < 4 * m * np.finfo(float).eps / predicted + 1e-12


@pytest.mark.parametrize("name, slope", [("verlet", 2), ("symplectic-euler", 2), ("ruth3", 4),
                                         ("pefrl", 4), ("yoshida4", 4), ("yoshida6", 6),
                                         ("blanes-moan6", 6), ("kahan-li8", 8),
                                         ("calvo-sanz-serna4", 4)])
def test_observed_order_of_phase_error(name, slope):
    """log-log slope at small z: the order for symmetric methods; one more for the
    odd-order ones (symplectic Euler, ruth3), whose oscillator trace is even in z."""
    e = errors(method(name), [1e-3, 2e-3]).phase
    assert abs(math.log2(e[1] / e[0]) - slope) < 0.05


def test_tolerance_inverse_problem():
    verlet = method("verlet")
    step = z_for_tolerance(verlet, 1e-6, 2.0)
    assert step.limited_by == "tolerance"
    assert abs(errors(verlet, [step.z]).phase[0] - 1e-6) < 1e-15
    assert z_for_tolerance(verlet, 10.0, 2.0).limited_by == "boundary"
    assert z_for_tolerance(verlet, 1e-300, 2.0).limited_by == "unreachable"


def test_compare_ranks_by_the_cost_it_prints(run):
    code, out, err = run("compare", "--beta", "3.2", "--tol-phase", "1e-6", "--json")
    assert code == 0, err
    data = json.loads(out)
    rows = data["methods"]
    costs = [r["cost"] for r in rows]
    assert costs == sorted(costs) and [r["rank"] for r in rows] == list(range(1, len(rows) + 1))
    for r in rows:
        assert r["h"] == pytest.approx(min(r["h_max"], r["h_tol"]))
        jacobians = r["jacobians"] or 0  # (Newton's, each at --jacobian-cost forces)
        assert r["cost"] == pytest.approx((r["evaluations"] + data["jacobian_cost"] * jacobians)
                                          / r["h"])
        assert r["bound_by"] == ("accuracy" if r["h_tol"] < r["h_max"] else "safety")


def test_advise_with_tolerances_says_what_binds(run_json):
    loose = run_json("advise", "--method", "verlet", "--beta", "2", "--tol-phase", "1")
    assert loose["bound_by"] == "safety" and loose["accuracy"][0]["limited_by"] == "boundary"
    tight = run_json("advise", "--method", "verlet", "--beta", "2", "--tol-phase", "1e-8")
    assert tight["bound_by"] == "accuracy"
    assert tight["h"] == pytest.approx(tight["accuracy"][0]["h"])
    never = run_json("advise", "--method", "verlet", "--beta", "2", "--tol-energy", "1e-300")
    assert never["accuracy"][0]["limited_by"] == "unreachable"


def test_error_command_and_bad_input(run_json, run):
    data = run_json("error", "verlet", "--z", "0.1", "--z", "2.5")
    assert data["rows"][0]["phase_error"] == pytest.approx(
        math.acos(1 - 0.005) / 0.1 - 1, rel=1e-12)
    assert data["rows"][1]["phase_error"] is None  # beyond z* = 2: not preserved
    for args in (["error", "verlet"], ["error", "verlet", "--z", "-1"],
                 ["error", "verlet", "--zmin", "2", "--zmax", "1"],
                 ["advise", "--method", "verlet", "--beta", "1", "--tol-phase", "0"],
                 ["compare", "--beta", "1", "--tol-phase", "nan"]):
        code, _, err = run(*args)
        assert code == 2 and "Traceback" not in err, args


def test_plot_writes_a_png_or_names_the_extra(run, tmp_path):
    out = tmp_path / "p.png"
    code, stdout, err = run("plot", "verlet", "-o", str(out), "--phase")
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert code == 2 and "pip install '.[plot]'" in err
        return
    assert code == 0 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_tradeoff_example_measures_what_it_predicts(tmp_path):
    """examples/tradeoff.py on two methods: measured oscillator phase and energy errors
    agree with the predictions (the numerical analysis guide's claim)."""
    import csv
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    out = tmp_path / "t.csv"
    subprocess.run([sys.executable, str(root / "examples" / "tradeoff.py"), "--methods",
                    "verlet,pefrl", "--steps", "0.1,0.4", "--T", "60", "--out", str(out)],
                   check=True, capture_output=True, cwd=tmp_path)
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 4
    for r in rows:
        assert rel(float(r["osc_phase"]), float(r["pred_phase"])) < 1e-5
        # max/min over a finite run approaches kappa - 1 from below (sampling of the
        # ellipse); the exact comparison is test_simulated_energy_error_matches_prediction
        assert 0 <= 1 - float(r["osc_energy"]) / float(r["pred_energy"]) < 5e-3
        assert rel(float(r["top_rate"]), float(r["pred_rate"])) < 1e-3


def test_energy_bound_is_not_reached_on_a_rational_rotation():
    """kappa - 1 bounds the energy error of every orbit; on Verlet at z = 1 (rotation
    pi/3, period 6) the worst start over a fine scan gives 0.2832 < 1/3, while at an
    irrational rotation (z = 1.1) the scan approaches the bound."""
    import stepsafe

    for z, reached in ((1.0, False), (1.1, True)):
        M = stepsafe.transfer_matrices("verlet", [z])[0]
        bound = stepsafe.errors("verlet", [z]).energy[0]
        worst = 0.0
        for phi in np.linspace(0.0, np.pi, 2001):
            x = np.array([np.cos(phi), np.sin(phi)])
            energies = []
            for _ in range(400):
                energies.append(x @ x)
                x = M @ x
            worst = max(worst, max(energies) / min(energies) - 1)
        assert worst <= bound * (1 + 1e-12)
        if reached:
            assert worst > 0.999 * bound
        else:
            assert bound == pytest.approx(1 / 3) and worst == pytest.approx(0.28320, abs=1e-4)


@pytest.mark.parametrize("args", [
    ["advise", "--method", "gauss", "-s", "2", "--beta", "1", "--tol-energy", "1e-4"],
    ["advise", "--method", "midpoint", "--beta", "1", "--tol-energy", "1e-4"],
    ["compare", "--beta", "1", "--tol-energy", "1e-4"],
])
def test_energy_tolerance_alone_is_refused_for_energy_exact_methods(run, args):
    """Exact energy on the linear model is not a recommendation: a phase tolerance is
    required alongside; with it the answer comes back."""
    code, out, err = run(*args)
    assert code == 2 and "--tol-phase" in err and len(err.strip().splitlines()) == 1
    code, _, err = run(*args, "--tol-phase", "1e-6")
    assert code == 0, err


def test_energy_tolerance_alone_is_accepted_for_methods_that_do_not_conserve_quadratics(
        run_json):
    """An energy tolerance without a phase tolerance applies to a method whose energy error
    on the linear model is not 0 (Lobatto IIIA-IIIB s = 3): it binds."""
    data = run_json("advise", "--method", "lobatto3ab", "-s", "3", "--beta", "1",
                    "--tol-energy", "1e-4")
    assert data["bound_by"] == "accuracy"


# --- independent high-precision references: Gauss from its stability function
# (the diagonal Pade approximant of exp), Lobatto IIIA-IIIB from its stage equations with a
# tableau built here (Legendre nodes, collocation by Vandermonde solve at raised precision)

def _gauss_phase(s, z):
    """theta / z - 1 of Gauss s: R(iz) = P(iz) / P(-iz), theta = 2 arg P(iz)."""
    w = 1j * z
    P = mp.fsum(mp.factorial(2 * s - k) * mp.factorial(s)
                / (mp.factorial(2 * s) * mp.factorial(k) * mp.factorial(s - k)) * w ** k
                for k in range(s + 1))
    theta = 2 * mp.atan2(P.imag, P.real)
    if mp.sin(theta) <= 0:  # rotates against the flow's sense: not preserved (b < 0)
        return None
    theta += 2 * mp.pi * mp.nint((z - theta) / (2 * mp.pi))  # M^n sees theta mod 2 pi
    return theta / z - 1



def _roots(ascending: list) -> list:
    """The roots of sum ascending[k] x^k (mpmath 1.4 wants asc=True, older the reverse)."""
    import inspect

    if "asc" in inspect.signature(mp.polyroots).parameters:
        return mp.polyroots(ascending, asc=True, maxsteps=400, extraprec=400)
    return mp.polyroots(ascending[::-1], maxsteps=400, extraprec=400)

def _lobatto_tableau(s):
    n = s - 1  # nodes 0, 1 and the roots of P'_n(2x - 1)
    leg = [mp.mpf(0)] * (n + 1)  # P_n(x) = 2^-n sum (-1)^k C(n,k) C(2n-2k, n) x^(n-2k)
    for k in range(n // 2 + 1):
        leg[n - 2 * k] = (-1) ** k * mp.binomial(n, k) * mp.binomial(2 * n - 2 * k, n) / 2 ** n
    dleg = [j * leg[j] for j in range(1, n + 1)]  # P'_n, ascending powers
    inner = sorted((mp.re(r) + 1) / 2 for r in _roots(dleg)) if n > 1 else []
    c = [mp.mpf(0)] + inner + [mp.mpf(1)]
    V = mp.matrix([[ci ** k for k in range(s)] for ci in c])
    Vinv = V ** -1
    A = mp.matrix([[ci ** (k + 1) / (k + 1) for k in range(s)] for ci in c]) * Vinv
    b = [mp.fsum(Vinv[k, j] / (k + 1) for k in range(s)) for j in range(s)]
    B = [[b[j] * (1 - A[j, i] / b[i]) for j in range(s)] for i in range(s)]
    return [[A[i, j] for j in range(s)] for i in range(s)], B, b


def _prk_errors(tableau, z):
    """(phase, energy) of the PRK on q' = p, p' = -q from its stage equations; None where
    the step does not preserve the vibration."""
    Aq, Ap, b = tableau
    s = len(b)
    cols = []
    for q0, p0 in ((1, 0), (0, 1)):
        N = mp.eye(2 * s)
        rhs = mp.matrix([q0] * s + [p0] * s)
        for i in range(s):
            for j in range(s):
                N[i, s + j] -= z * Aq[i][j]  # Q_i = q0 + z sum Aq_ij P_j
                N[s + i, j] += z * Ap[i][j]  # P_i = p0 - z sum Ap_ij Q_j
        X = mp.lu_solve(N, rhs)
        cols.append((q0 + z * mp.fsum(b[j] * X[s + j] for j in range(s)),
                     p0 - z * mp.fsum(b[j] * X[j] for j in range(s))))
    a, c = cols[0]
    bb, d = cols[1]
    sin2 = -bb * c - (a - d) ** 2 / 4
    if sin2 <= 0 or bb <= 0:
        return None, None
    theta = mp.atan2(mp.sqrt(sin2), (a + d) / 2)
    theta += 2 * mp.pi * mp.nint((z - theta) / (2 * mp.pi))  # M^n sees theta mod 2 pi
    spread = mp.sqrt((bb + c) ** 2 + (a - d) ** 2)
    return theta / z - 1, spread / ((bb - c - spread) / 2)


ZS_FAMILY = [0.1, 1.0, 2.0, 2.9, 3.1, 3.13, 3.1415, 7.0, 8.0]


def _agree(got, truth):
    if truth is None:
        return np.isnan(got)
    t = float(truth)
    if abs(t) < 1e-290:  # below float64's normal range: only its size can be checked
        return abs(got) <= 1e-290 and not np.isnan(got)
    return abs(got - t) <= 1e-9 * abs(t)


def test_gauss_phase_matches_its_pade_form_to_the_boundary_and_tiny_z():
    import stepsafe

    tiny = [1e-300, 1e-200, 1e-150]
    for s in range(1, 13):
        e = stepsafe.errors(stepsafe.method("gauss", stages=s), ZS_FAMILY + tiny)
        # a Runge-Kutta method keeps the oscillator's energy
        assert np.all((e.energy == 0) | np.isnan(e.phase)), s
        for z, got in zip(ZS_FAMILY + tiny, e.phase):
            with mp.workdps(60 if z > 0.5 else 100 if z > 1e-3 else 700):
                truth = _gauss_phase(s, mp.mpf(z))
            assert _agree(got, truth), (s, z, got, mp.nstr(truth, 12))


@pytest.mark.slow
def test_lobatto_errors_match_its_stage_equations_on_islands_and_at_tiny_z():
    """Lobatto IIIA-IIIB s = 2..12 (s >= 10 printed energy 0 where the truth is 2e-16 to
    3e-6; the phase had the wrong sign on islands beyond 2 pi)."""
    import stepsafe

    for s in range(2, 13):
        with mp.workdps(100):  # the phase error at z = 0.1 is 2.5e-52 for s = 12
            tableau = _lobatto_tableau(s)
            truths = [_prk_errors(tableau, mp.mpf(z)) for z in ZS_FAMILY[:1]]
        with mp.workdps(45):
            truths += [_prk_errors(tableau, mp.mpf(z)) for z in ZS_FAMILY[1:]]
        e = stepsafe.errors(stepsafe.method("lobatto3ab", stages=s), ZS_FAMILY)
        for i, (z, (phase, energy)) in enumerate(zip(ZS_FAMILY, truths)):
            assert _agree(e.phase[i], phase), (s, z, e.phase[i], phase and mp.nstr(phase, 12))
            assert _agree(e.energy[i], energy), (s, z, e.energy[i],
                                                 energy and mp.nstr(energy, 12))
    for s in (2,):  # tiny z: preserved, and z^2/24 (Stormer-Verlet)
        with mp.workdps(700):
            tableau = _lobatto_tableau(s)
            truths = [_prk_errors(tableau, mp.mpf(z)) for z in (1e-300, 1e-150)]
        e = stepsafe.errors(stepsafe.method("lobatto3ab", stages=s), [1e-300, 1e-150])
        for i, (phase, energy) in enumerate(truths):
            assert _agree(e.phase[i], phase) and _agree(e.energy[i], energy), (s, i)


def test_advise_energy_tolerance_of_lobatto10_stops_where_the_truth_does(run_json):
    """The energy error of a high-stage implicit method is computed, not taken as 0: for
    Lobatto IIIA-IIIB s = 10 it reaches 1e-12 at z = 2.91907987402 (50-digit stage
    equations), where advise's energy tolerance stops."""
    data = run_json("advise", "--method", "lobatto3ab", "-s", "10", "--beta", "1",
                    "--tol-energy", "1e-12", "--tol-phase", "1e-3")
    energy = [a for a in data["accuracy"] if a["kind"] == "energy"][0]
    assert energy["limited_by"] == "tolerance"
    assert energy["h"] == pytest.approx(2.91907987402, rel=1e-10)
