"""The coupled analysis against the straightforward one: a dense scan of the one-step
matrix with eigenvectors (every multiplier classified, Krein signs from v^H J v) and a
bisection of the first change, on random definite, indefinite, gyroscopic and loxodromic
systems."""

from __future__ import annotations

import numpy as np
import pytest
from support import method

from stepsafe.systems.coupled import (
    CoupledSystem,
    continuous_signature,
    coupled_safe_steps,
    discrete_signature,
    one_step_matrix,
)
from stepsafe.systems.linear import hamiltonian_matrix

METHODS = [("verlet", None), ("pefrl", None), ("yoshida4", None), ("lobatto3ab", 3),
           ("symplectic-euler", None)]


def _kept(m, S, h, ref) -> bool:
    sig = discrete_signature(one_step_matrix(m, S, h))
    return sig is not None and sig.flips == 0 and sig == ref


def _straightforward_h_max(m, S, zmax: float, samples: int = 3000) -> float:
    ref = continuous_signature(S)
    top = float(np.abs(np.linalg.eigvals(hamiltonian_matrix(S))).max())
    hs = np.linspace(0, zmax / top, samples + 1)[1:]
    good = 0.0
    for h in hs:
        if not _kept(m, S, h, ref):
            bad = h
            break
        good = h
    else:
        return zmax / top
    while bad - good > 1e-13 * bad:
        mid = 0.5 * (good + bad)
        good, bad = (mid, bad) if _kept(m, S, mid, ref) else (good, mid)
    return good


def _definite(rng, n):
    A = rng.normal(size=(2 * n, 2 * n))
    return A @ A.T / (2 * n) + 0.2 * np.eye(2 * n)


def _indefinite(rng, n):
    # a definite kinetic part and a potential with some negative curvatures, coupled by
    # a small mixed block: centres and saddles together
    S = _definite(rng, n)
    S[:n, :n] -= 1.5 * np.diag(rng.uniform(0, 1, n) > 0.5)
    return 0.5 * (S + S.T)


def _gyroscopic(rng, n):
    # H = |p - G q|^2 / 2 + q^T K q / 2 with G antisymmetric (a magnetic field, a rotating
    # frame): S_qp = -G^T... non-separable in a way no change of q alone removes
    G = rng.normal(size=(n, n))
    G = G - G.T
    K = _definite(rng, n)[:n, :n]
    return np.block([[K + G.T @ G, -G.T], [-G, np.eye(n)]])


def _loxodromic(rng, n):
    # a Krein collision of opposite signatures: x' = J S x with eigenvalues +-a +-ib
    a, b = 0.3, 1.0
    A = np.array([[a, b], [-b, a]])  # q' = A q, p' = -A^T p
    S = np.zeros((4, 4))
    S[2:, :2] = A  # dH/dp = A q
    S[:2, 2:] = A.T
    if n > 2:
        rest = _definite(rng, n - 2)
        m = n - 2
        big = np.zeros((2 * n, 2 * n))
        big[:2, :2], big[:2, n:n + 2] = S[:2, :2], S[:2, 2:]
        big[n:n + 2, :2], big[n:n + 2, n:n + 2] = S[2:, :2], S[2:, 2:]
        big[2:n, 2:n], big[2:n, n + 2:] = rest[:m, :m], rest[:m, m:]
        big[n + 2:, 2:n], big[n + 2:, n + 2:] = rest[m:, :m], rest[m:, m:]
        return big
    return S


KINDS = {"definite": _definite, "indefinite": _indefinite, "gyroscopic": _gyroscopic,
         "loxodromic": _loxodromic}


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("name, stages", METHODS)
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_h_max_equals_the_straightforward_analysis(kind, name, stages, seed):
    """Every method on every kind of system at seed 0 in the default run, a second draw
    of each in the slow set (the straightforward scan takes up to 3000 eigensolves)."""
    rng = np.random.default_rng(seed)
    S = KINDS[kind](rng, 3)
    m = method(name, stages)
    zmax = 8.0
    got = coupled_safe_steps(m, S, zmax).h_max
    want = _straightforward_h_max(m, S, zmax)
    # never beyond the straightforward answer (its own precision is ~1e-8 where a pair
    # meets at -1: eigenvalues of a nearly defective M); below it only by the rounding
    # estimate, which grows near a pole, where the entries of M blow up and the stage
    # matrices' condition amplifies every solve's rounding (a few 1e-6 there)
    assert want * (1 - 1e-5) <= got <= want * (1 + 1e-8), (kind, got, want)
    ref = continuous_signature(S)
    if got > 0:
        assert _kept(m, S, got * (1 - 1e-9), ref)


@pytest.mark.parametrize("seed", range(6))
def test_definite_criterion_matches_the_eigenvector_classification(seed):
    """Q(h) > 0 exactly when the multipliers keep type and Krein signature."""
    rng = np.random.default_rng(seed)
    S = _definite(rng, 4) * (-1) ** seed
    m = method("pefrl")
    system = CoupledSystem(m, S)
    assert system.definite
    ref = continuous_signature(S)
    top = system.top
    for z in np.linspace(0.05, 6.0, 60):
        h = z / top
        kept = _kept(m, S, h, ref)
        if abs(system.margin(h)) > 1e-6:  # away from the boundary itself
            assert system.preserved(h) == kept, (z, system.margin(h))


def test_types_swapping_between_samples_are_not_missed():
    """A vibration turning hyperbolic while a barrier turns elliptic leaves the counts
    unchanged: the trace margin still sees both crossings."""
    K = np.diag([3.4773723509726358 ** 2, -3.646250558942921 ** 2])
    S = np.block([[K, np.zeros((2, 2))], [np.zeros((2, 2)), np.eye(2)]])
    S[0, 3] = S[3, 0] = 1e-3  # not separable
    m = method("yoshida4")
    got = coupled_safe_steps(m, S, 50.0).h_max
    assert got == pytest.approx(_straightforward_h_max(m, S, 50.0, samples=20000), rel=1e-8)


@pytest.mark.parametrize("unit", [1e-300, 1e-200, 1e-12, 1e12, 1e200, 1e300])
@pytest.mark.parametrize("kind", ["definite", "indefinite"])
def test_h_max_scales_with_the_units_of_s(kind, unit):
    """h_max(c S) = h_max(S) / c: the analysis never over- or underflows with S's units."""
    S = KINDS[kind](np.random.default_rng(0), 3)
    m = method("pefrl")
    base = coupled_safe_steps(m, S, 8.0).h_max
    scaled = coupled_safe_steps(m, unit * S, 8.0).h_max
    assert scaled * unit == pytest.approx(base, rel=1e-11)
    assert CoupledSystem(m, unit * S).preserved(0.999 * base / unit)
    assert not CoupledSystem(m, unit * S).preserved(1.001 * base / unit)


def test_progress_is_reported_and_a_deadline_stops_at_a_preserved_horizon():
    """progress(fraction) rises to 1; a deadline already past stops the scan after its
    first sample, whose h becomes both h_max and the horizon (and is preserved)."""
    import time

    rng = np.random.default_rng(3)
    A = rng.normal(size=(8, 8))
    S = A @ A.T / 8 + np.eye(8)
    m = method("pefrl")
    seen: list[float] = []
    full = coupled_safe_steps(m, S, progress=seen.append)
    assert seen and seen == sorted(seen) and seen[-1] == 1.0
    cut = coupled_safe_steps(m, S, deadline=time.monotonic())
    assert 0 < cut.h_max == cut.horizon < full.h_max
    assert "time budget" in cut.analysis
    assert CoupledSystem(m, S).preserved(cut.h_max)


def test_budget_on_the_command_line_caps_the_analysed_steps(tmp_path, run, run_json):
    """advise --budget: h_max is the h the analysis reached (preserved, below the full
    answer); check still decides its own step exactly."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(8, 8))
    np.save(tmp_path / "S.npy", A @ A.T / 8 + np.eye(8))
    scene = tmp_path / "scene.yaml"
    scene.write_text("method: pefrl\nsystem:\n  hessian: S.npy\n")
    full = run_json("advise", str(scene))
    cut = run_json("advise", str(scene), "--budget", "1e-9")
    assert 0 < cut["h_max"] < full["h_max"]
    assert "time budget" in cut["system"]["analysis"]
    assert cut["h_max_limited_by"] == "horizon" and full["h_max_limited_by"] == "boundary"
    code, out, err = run("advise", str(scene))  # the text report (once exit 3)
    assert code == 0 and "limited by the coupled analysis" in out, err
    for step, code in ((0.5 * (cut["h_max"] + full["h_max"]), 0), (1.01 * full["h_max"], 1)):
        assert run("check", str(scene), "--step", str(step), "--budget", "1e-9")[0] == code


@pytest.mark.parametrize("h", [-1.0, 0.0, float("nan"), float("inf"), -1e-300])
def test_a_step_that_is_not_positive_is_refused_on_a_coupled_system(h):
    """A step h <= 0 (where the coupled criterion holds trivially), nan or inf on a
    coupled Hessian is bad input, as for modes: never SAFE."""
    import stepsafe

    with pytest.raises(stepsafe.StepsafeError, match="positive finite"):
        stepsafe.check("verlet", h, system={"hessian": [[2.0, 0.3], [0.3, 1.0]]})


def test_a_singular_hessian_at_1e300_ends_with_no_safe_step():
    """(q + p)^2 1e300 / 2, singular and huge: the boundary search from 0 ends (its
    bisection must stop where REL_TOL * h underflows to 0) with no safe step."""
    S = np.full((2, 2), 1e300)
    result = coupled_safe_steps(method("verlet"), S)
    assert result.h_max == 0.0


@pytest.mark.parametrize("kind", ["definite", "indefinite", "loxodromic"])
@pytest.mark.parametrize("k", [-40, -12, 12, 40])
def test_h_max_in_other_units_of_q_and_p(kind, k):
    """S_pp times 2^(2k) and S_qp times 2^k: S' = D S D with D = diag(I, 2^k I), and
    J S' = 2^k D^-1 (J S) D, the same system in other units of p and time, whose step
    limits are exactly 2^-k times: rounding bounds made of |S| must not swamp the small
    block (an indefinite system would then be "never safe")."""
    S = KINDS[kind](np.random.default_rng(3), 3)
    n = 3
    scaled = S.copy()
    scaled[n:, n:] *= 2.0 ** (2 * k)
    scaled[:n, n:] *= 2.0 ** k
    scaled[n:, :n] *= 2.0 ** k
    m = method("yoshida4")
    base = coupled_safe_steps(m, S).h_max
    other = coupled_safe_steps(m, scaled).h_max
    assert base > 0 and other == pytest.approx(base * 2.0 ** -k, rel=1e-9), (base, other)


def test_no_certified_step_is_not_called_never_preserved(run, tmp_path):
    """Two pairs of opposite Krein sign 2e-6 apart: the coupled analysis certifies no step
    (pairs that close are undecided), which is not "never preserves" (the exact system
    keeps the structure up to h = 2.92564)."""
    S = [[11.021789487585378, 1.7918652946710565, -0.49636227185660786, -1.3996632628869785],
         [1.7918652946710565, -2.326987080311353, 0.12990600967649873, 0.522245307202353],
         [-0.49636227185660786, 0.12990600967649873, 0.08542399419854464, 0.06433478850948521],
         [-1.3996632628869785, 0.522245307202353, 0.06433478850948521, -0.41594351150809433]]
    scene = tmp_path / "close.yaml"
    scene.write_text("method: bcss3\nsystem:\n  hessian: " + repr(S) + "\n")
    code, out, _ = run("advise", str(scene))
    assert code == 0 and "could be certified" in out and "never preserves" not in out


def test_check_at_the_coupled_h_max_is_in_the_primary_interval(run_json, tmp_path):
    """The coupled analysis's h_max is a certified step: check there is SAFE, and in the
    interval from 0, not "in an island"."""
    scene = tmp_path / "c.yaml"
    scene.write_text("method: verlet\nsystem:\n  hessian: [[1.0, 0.3], [0.3, 2.0]]\n")
    h_max = run_json("advise", str(scene))["h_max"]
    (data,) = run_json("check", str(scene), "--step", repr(h_max))["checks"]
    assert data["safe"] and data["in_primary_interval"]
