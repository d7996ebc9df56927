"""The coupled analysis where float64 cannot place the boundary (a nearly semidefinite S:
a charged particle in a strong magnetic field): small systems are decided at 40 digits
(stepsafe/systems/coupled_exact.py), larger ones state the band float64 leaves open. Truth
is the 40-60 digit criterion of tests/test_frame.py (the Euler factors solved at that
precision from the exact floats of S, an mpmath Cholesky of Q)."""

from __future__ import annotations

import json

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import block_diag
from support import method
from test_frame import _kept_mp

from stepsafe.systems import coupled_exact
from stepsafe.systems.coupled import coupled_safe_steps


def _trap(B: float, k: float = 1.0) -> np.ndarray:
    """Hessian of H = ((px + B y/2)^2 + (py - B x/2)^2)/2 + k (x^2 + y^2)/2 in
    (x, y, px, py): positive definite, frequencies about B and k/B (condition ~ B^4/k^2)."""
    return np.array([[B * B / 4 + k, 0, 0, -B / 2], [0, B * B / 4 + k, B / 2, 0],
                     [0, B / 2, 1, 0], [-B / 2, 0, 0, 1.0]])


def _traps(*blocks: np.ndarray) -> np.ndarray:
    """Uncoupled traps as one S ordered (all q, all p)."""
    S = block_diag(*blocks)
    order = ([4 * b + i for b in range(len(blocks)) for i in (0, 1)]
             + [4 * b + i for b in range(len(blocks)) for i in (2, 3)])
    return S[np.ix_(order, order)]


@settings(max_examples=8, deadline=None)
@given(log_B=st.floats(3.0, 7.5), k=st.floats(0.1, 10.0),
       name=st.sampled_from(["verlet", "pefrl", "symplectic-euler"]))
def test_a_strong_magnetic_trap_is_decided_at_high_precision(log_B, k, name):
    """h_max is kept and h_max (1 + 1e-8) is not, at 60 digits (where float64 decides, it
    falls short by its rounding bound, which carries the stage matrices' condition: 1.6e-9
    at B = 1e3 with pefrl). Float64 alone gave 6% low at B = 1e6 (Verlet) and no step at
    all at B = 1e7."""
    S = _trap(10.0 ** log_B, k)
    m = method(name)
    result = coupled_safe_steps(m, S, 10.0)
    assert result.undecided_to is None
    assert result.h_max > 0
    assert _kept_mp(m, S, result.h_max, 60, sign=1)
    # (symplectic Euler keeps this trap to zmax: its h_max is the horizon, to rounding)
    if result.h_max < result.horizon * (1 - 1e-12):
        assert not _kept_mp(m, S, result.h_max * (1 + 1e-8), 60, sign=1)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 3), log_h=st.floats(-3.0, 0.7),
       name=st.sampled_from(["verlet", "pefrl", "yoshida4", "symplectic-euler"]),
       sign=st.sampled_from([1, -1]))
def test_the_high_precision_criterion_agrees_with_an_independent_one(seed, n, log_h, name,
                                                                      sign):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(2 * n, 2 * n))
    S = sign * (A @ A.T / (2 * n) + 0.1 * np.eye(2 * n))
    m = method(name)
    factors = coupled_exact.euler_factors(m)
    h = 10.0 ** log_h
    assert coupled_exact.kept_exactly(factors, S, sign, h) == _kept_mp(m, S, h, 60, sign)


def test_a_large_nearly_semidefinite_system_states_the_band_float64_leaves_open(tmp_path, run):
    """Five traps (20 x 20, beyond the high-precision size): the certified h_max is kept,
    the end of the band is lost (60 digits); advise says so, check of a step in the band
    fails (exit 1) saying float64 cannot decide, the JSON lists the band."""
    S = _traps(*(_trap(1e6 * f) for f in (1.0, 0.9, 0.8, 0.7, 0.6)))
    assert S.shape[0] > coupled_exact.EXACT_SIZE
    m = method("verlet")
    result = coupled_safe_steps(m, S, 10.0)
    assert result.undecided_to is not None and result.undecided_to > result.h_max > 0
    assert _kept_mp(m, S, result.h_max, 60, sign=1)
    assert not _kept_mp(m, S, result.undecided_to, 60, sign=1)
    scene = tmp_path / "traps.json"
    scene.write_text(json.dumps({"method": "verlet", "system": {"hessian": S.tolist()}}))
    code, out, _ = run("advise", str(scene))
    assert code == 0
    text = " ".join(out.split())
    assert f"float64 cannot decide the coupled {S.shape[0]}x{S.shape[0]} analysis" in text
    assert "Undecided: float64 cannot decide" in text
    data = json.loads(run("advise", str(scene), "--json")[1])
    assert data["undecided_h"] == [[result.h_max, result.undecided_to]]
    import stepsafe

    assert stepsafe.advise("verlet", system={"hessian": S}).undecided_h == (
        (result.h_max, result.undecided_to),)
    step = 0.5 * (result.h_max + result.undecided_to)
    code, out, _ = run("check", str(scene), "--step", repr(step))
    assert code == 1
    assert "float64 cannot decide whether" in " ".join(out.split())


def test_check_certifies_a_step_float64_alone_could_not():
    """At B = 1e6 float64 certified Verlet only to z = 3.75 (the truth is z = 4 - 1e-11):
    a step at z = 3.9 is now certified, one past the boundary is not."""
    S = _trap(1e6)
    from stepsafe.systems.coupled import CoupledSystem

    system = CoupledSystem(method("verlet"), S)
    assert not system.preserved(3.9e-6)
    assert system.certified(3.9e-6) and _kept_mp(method("verlet"), S, 3.9e-6, 60, sign=1)
    assert not system.certified(4.0000001e-6)
    assert not _kept_mp(method("verlet"), S, 4.0000001e-6, 60, sign=1)


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rows=st.sampled_from([8, 10]),
       name=st.sampled_from(["verlet", "yoshida4", "kahan-li8"]))
def test_a_well_conditioned_boundary_is_decided_by_float64(seed, rows, name):
    """Every boundary has a band of the size of the rounding bound (about 1e-11 here):
    on a well-conditioned S it is not reported as undecided, nor sent to 40 digits."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(rows, rows))
    S = X @ X.T / rows + 0.5 * np.eye(rows)
    result = coupled_safe_steps(method(name), S, 10.0)
    assert result.undecided_to is None
    assert "digits" not in result.analysis


def _singular_to_rounding(seed: int) -> np.ndarray:
    """An 8-row S whose float Cholesky succeeds while its exact floats are not definite
    (its smallest eigenvalue removed, to rounding)."""
    rng = np.random.default_rng(seed)
    for _ in range(3000):
        X = rng.normal(size=(8, 8))
        A = X @ X.T / 8 + 0.3 * np.eye(8)
        w, V = np.linalg.eigh(A)
        S = A - w[0] * np.outer(V[:, 0], V[:, 0])
        S = 0.5 * (S + S.T)
        try:
            np.linalg.cholesky(S / np.abs(S).max())
        except np.linalg.LinAlgError:
            continue
        if coupled_exact.definite_sign(S) == 0:
            return S
    raise AssertionError("no such S found")


def test_an_s_not_definite_in_its_exact_floats_is_not_decided_at_high_precision(monkeypatch):
    """float64 calls it definite, its exact floats are not: nothing is certified at 40
    digits (the criterion there assumes a definite S, so it is not tried), the band
    float64 leaves is reported, and no step in it is certified."""
    S = _singular_to_rounding(0)
    calls = []
    monkeypatch.setattr(coupled_exact, "_kept", lambda *a: calls.append(a))
    m = method("kahan-li8")
    result = coupled_safe_steps(m, S, 10.0)
    assert not calls
    assert result.undecided_to is not None and result.undecided_to > result.h_max
    from stepsafe.systems.coupled import CoupledSystem

    system = CoupledSystem(m, S)
    inside = result.h_max + 0.5 * (result.undecided_to - result.h_max)
    assert not system.certified(inside) and not calls


def test_a_trap_float64_calls_indefinite_is_decided_at_high_precision():
    """The exact floats of S are definite though float64's Cholesky fails (B ~ 1e8: the
    2 x 2 blocks are singular to rounding): the safe interval is decided at 40 digits
    instead of h_max = 0; 60-digit truth at h_max (1 -+ 1e-9)."""
    from stepsafe.systems.coupled import CoupledSystem

    rng = np.random.default_rng(0)
    decided = 0
    for _ in range(400):
        S = _trap(10 ** rng.uniform(6, 9), 10 ** rng.uniform(-1, 3)) * 10 ** rng.uniform(-50, 50)
        sign = coupled_exact.definite_sign(S)
        if CoupledSystem(method("verlet"), S).definite or sign == 0:
            continue  # float64 decides, or the exact floats are semidefinite
        result = coupled_safe_steps(method("verlet"), S, 10.0)
        assert "definite at 40 digits" in result.analysis
        assert _kept_mp(method("verlet"), S, result.h_max, 60, sign=sign)
        assert not _kept_mp(method("verlet"), S, result.h_max * (1 + 1e-9), 60, sign=sign)
        system = CoupledSystem(method("verlet"), S)  # check agrees
        assert system.certified(0.5 * result.h_max)
        assert not system.certified(result.h_max * (1 + 1e-9))
        decided += 1
        if decided == 3:
            break
    assert decided == 3
