"""The certified smallest eigenvalue (stepsafe.systems.smallest): a completed Cholesky
factorisation proves lambda_min(W) > floor; the value is the eigensolver's or a Lanczos
upper bound at its tolerance."""

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.systems import smallest as module
from stepsafe.systems.smallest import allowance, smallest


def _symmetric_with(rng, N: int, low: float, scale: float) -> np.ndarray:
    """A symmetric N x N matrix with smallest eigenvalue ``low`` (before rounding) and the
    others in (low, low + scale), in a random orthogonal basis."""
    U, _ = np.linalg.qr(rng.normal(size=(N, N)))
    lam = np.concatenate([[low], low + scale * rng.uniform(1e-3, 1.0, N - 1)])
    W = (U * lam) @ U.T
    return 0.5 * (W + W.T)


def _lambda_min_mp(W: np.ndarray) -> mp.mpf:
    with mp.workdps(40):
        return min(mp.eigsy(mp.matrix(W.tolist()), eigvals_only=True))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), N=st.integers(1, 7),
       log_scale=st.floats(-150.0, 150.0), offset=st.floats(-40.0, 40.0),
       lanczos=st.booleans())
def test_a_certified_floor_holds_at_40_digits(seed, N, log_scale, offset, lanczos):
    """Matrices whose smallest eigenvalue sits within a few allowances of the floor, at
    every scale: whenever the factorisation is taken as proof, lambda_min(W) > floor at
    40 digits."""
    with pytest.MonkeyPatch.context() as patch:
        if lanczos:
            patch.setattr(module, "LANCZOS_FROM", 1)
        _check_certified_floor(seed, N, log_scale, offset)


def _check_certified_floor(seed, N, log_scale, offset):
    rng = np.random.default_rng(seed)
    scale = 10.0**log_scale
    W = _symmetric_with(rng, N, 0.0, scale)
    floor = float(rng.uniform(0, 1e-3)) * scale
    W[np.diag_indices(N)] += floor + offset * allowance(W, floor)
    found = smallest(W, floor)
    truth = _lambda_min_mp(W)
    if found.certified:
        assert truth > floor, (truth, floor, found)
    # the value is lambda_min(W) - shift: the eigensolver's to its accuracy, or a Ritz
    # value, never below the truth by more than rounding
    assert found.value + found.shift >= float(truth) - 8 * N * 2.0**-53 * scale * (1 + N)


@pytest.mark.parametrize("seed", range(3))
def test_lanczos_value_agrees_with_the_eigensolver(seed):
    """At N = 300 (Lanczos): the value matches lambda_min from a full eigensolver to
    1e-9, also with clustered smallest eigenvalues."""
    rng = np.random.default_rng(seed)
    N = 300
    W = _symmetric_with(rng, N, 0.4, 1.0)
    if seed == 2:  # a cluster at the bottom: 0.4, 0.4045, 0.409, ...
        U, _ = np.linalg.qr(rng.normal(size=(N, N)))
        lam = 0.4 + np.concatenate([0.0045 * np.arange(8), rng.uniform(0.1, 1.0, N - 8)])
        W = (U * lam) @ U.T
        W = 0.5 * (W + W.T)
    assert N >= module.LANCZOS_FROM
    truth = float(np.linalg.eigvalsh(W)[0])
    found = smallest(W, 0.0)
    assert found.certified
    assert found.value + found.shift == pytest.approx(truth, rel=1e-9)
    assert found.value + found.shift >= truth - 1e-13


@pytest.mark.parametrize("seed", range(20))
def test_a_singular_matrix_of_subnormal_entries_is_not_certified(seed):
    """W = B B^T 2^-1074 with B an integer N x r matrix, r < N: lambda_min = 0 exactly, and
    every term of the allowance underflows to 0 unscaled; W is scaled by a power of two
    first, and nothing is certified."""
    rng = np.random.default_rng(seed)
    N = int(rng.integers(2, 12))
    B = rng.integers(-3, 4, size=(N, N - 1)).astype(float)
    for power in (-1074, -1000, 0, 900):
        W = np.ldexp(B @ B.T, power)
        if not np.all(np.isfinite(W)):
            continue
        assert not smallest(W, 0.0).certified, (N, power)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(module, "LANCZOS_FROM", 1)
            assert not smallest(W, 0.0).certified


def test_an_indefinite_matrix_is_not_certified_and_its_value_is_exact():
    rng = np.random.default_rng(5)
    W = _symmetric_with(rng, 300, -0.1, 1.0)
    found = smallest(W, 0.0)
    assert not found.certified
    assert found.value + found.shift == pytest.approx(-0.1, rel=1e-10)


def test_an_extreme_eigenvalue_of_a_tight_cluster():
    """LAPACK's syevr for one eigenvalue can fail on a cluster within rounding (a 200 x 200
    Hessian that is the identity rotated): the coupled analysis then takes every
    eigenvalue, never an internal error, and verlet's limit on S = I is 2."""
    from stepsafe.methods.library import resolve
    from stepsafe.systems.coupled import coupled_safe_steps

    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.standard_normal((200, 200)))
    S = Q @ Q.T
    S = 0.5 * (S + S.T)
    h_max = coupled_safe_steps(resolve("verlet")[0], S, 4.0).h_max
    assert 2 * (1 - 1e-6) < h_max <= 2


def test_extreme_eigenvalue_falls_back_to_every_eigenvalue(monkeypatch):
    import scipy.linalg as sla

    A = _symmetric_with(np.random.default_rng(1), 6, 0.5, 2.0)
    want = np.linalg.eigvalsh(A)
    original = sla.eigh

    def failing_subset(*args, **kwargs):
        if "subset_by_index" in kwargs:
            raise np.linalg.LinAlgError("Internal Error.")
        return original(*args, **kwargs)

    monkeypatch.setattr(sla, "eigh", failing_subset)
    assert module.extreme_eigenvalue(A) == pytest.approx(want[0], rel=1e-14)
    assert module.extreme_eigenvalue(A, highest=True) == pytest.approx(want[-1], rel=1e-14)
