"""Every shipped method through the method protocol, and the one linear step map.

Each method kind implements :class:`stepsafe.methods.protocol.MethodKind`; these tests ask
every built-in method (and family members) the same questions: it is consistent (one step
is the flow to first order), its transfer matrix has determinant 1 on every model where its
residuals say it is symplectic, a method that says it is symmetric is its own adjoint
(``M(-z) M(z) = I``) and one that says it is not, is not; its float64 transfer matrix agrees
with the independent mpmath reference built from its own definition.

The 2x2 transfer matrix (:mod:`stepsafe.core.transfer`) and the 2n x 2n one-step matrix
(:mod:`stepsafe.systems.coupled`) are one routine (:func:`stepsafe.core.engine.step_jet`)
over one block decomposition; the 2x2 map must be the one-degree-of-freedom case of the
2n x 2n one, a system of n decoupled modes (rotated by a random orthogonal point
transformation) must step mode by mode, and a step of several blocks must be the product of
its blocks.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.core.transfer import has_form, pole_locations, transfer_jet, transfer_matrix
from stepsafe.methods.exact import high_precision
from stepsafe.methods.library import FAMILIES, builtin_names, resolve
from stepsafe.methods.protocol import Block, Friction, MethodKind, Stages
from stepsafe.methods.tableaux import Composition
from stepsafe.systems.coupled import _Steps, one_step_matrix
from stepsafe.systems.linear import hamiltonian_matrix

FAMILY_MEMBERS = [("gauss", 1), ("gauss", 2), ("gauss", 3), ("lobatto3ab", 2),
                  ("lobatto3ab", 3)]
SHIPPED = [(name, None) for name in builtin_names() if name not in FAMILIES] + FAMILY_MEMBERS
#: The flow's generator L of each model (x' = beta L x, z = beta h).
GENERATOR = {"oscillator": [[0, 1], [-1, 0]], "saddle": [[1, 0], [0, -1]],
             "inverted": [[0, 1], [1, 0]], "saddle-p": [[-1, 0], [0, 1]]}


def _method(name: str, stages: int | None) -> MethodKind:
    return resolve(name, stages)[0]


def _single_force(m: MethodKind) -> bool:
    return m.kind != "impulse"


def _generator(m: MethodKind, model: str) -> np.ndarray:
    """The generator of the flow one step approximates: the model's, damped by the
    friction (per unit of frequency) for a Langevin splitting's mean map."""
    L = np.array(GENERATOR[model], dtype=float)
    if not m.hamiltonian:
        L[1, 1] -= m.friction
    return L


def _ids(item) -> str:
    name, stages = item
    return name if stages is None else f"{name}-s{stages}"


def _models(m: MethodKind) -> list[str]:
    return [model for model in m.models if has_form(m, model)]


def _away_from_poles(m: MethodKind, model: str, z: np.ndarray) -> np.ndarray:
    poles, _ = pole_locations(m, model)
    if not poles.size:
        return z
    return z[np.all(np.abs(z[:, None] - poles[None, :]) > 1e-2 * np.abs(poles), axis=1)]


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_every_shipped_method_answers_the_protocol(item):
    """Identity and decomposition of every shipped method, asked of the method itself."""
    m = _method(*item)
    assert isinstance(m, MethodKind)
    assert isinstance(m.kind, str) and m.name
    assert isinstance(m.stages, int) and m.stages >= 1
    assert isinstance(m.explicit, bool) and isinstance(m.symmetric(), bool)
    assert m.order is None or m.order >= 1
    res = m.residuals()
    assert res.consistent, res
    assert m.reach >= 1.0 and m.sample_work >= 1.0
    if not _single_force(m):
        return
    blocks = m.decomposition()
    assert blocks and all(isinstance(b, Block) and b.weight != 0 for b in blocks)
    if m.hamiltonian:
        # the weights of the blocks are the fractions of the step: they sum to 1 for a
        # consistent method (a splitting is one block of weight 1)
        assert sum(b.weight for b in blocks) == pytest.approx(1.0, rel=1e-12)
    else:  # a Langevin splitting: its friction steps' fractions sum to 1
        assert sum(b.weight for b in blocks if isinstance(b, Friction)) == pytest.approx(1.0)
    assert m.gradient_evaluations >= 0 and isinstance(m.force_gradient, bool)
    step = m.splitting()
    if step is not None:  # the step as one drift/kick sequence, consistent as the method
        assert step.residuals().consistent
    if m.rk_form() is not None:  # a Runge-Kutta kind is one stage block
        assert len(blocks) == 1 and isinstance(blocks[0], Stages)


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_one_step_is_the_flow_to_first_order(item):
    """``(M(z) - I) / z -> L`` as z -> 0 on every model the method is analysed on (L damped
    by the friction for a Langevin splitting's mean map): the error at z is O(z) (checked
    at z = 1e-4 and 1e-5, from D = M - I, which the engine accumulates without forming
    I + small)."""
    m = _method(*item)
    if not _single_force(m):
        pytest.skip("an impulse method steps two forces (tests/test_impulse_methods.py)")
    for model in _models(m):
        L = _generator(m, model)
        for z in (1e-4, 1e-5):
            D = transfer_jet(m, [z], model, scale=False, order=0).D[0]
            assert np.abs(D / z - L).max() <= 200 * z * max(1.0, m.reach) ** 2, (model, z)


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_symplectic_methods_have_determinant_one(item):
    """Where the residuals say the method is symplectic on a model, ``det M(z) = 1`` to
    rounding at every z (away from poles, where M is not huge); ``det M - 1 = tr D +
    det D`` from ``D = M - I``."""
    m = _method(*item)
    if not _single_force(m):
        pytest.skip("an impulse method steps two forces")
    res = m.residuals()
    z = np.linspace(0.01, 6.0, 120)
    checked = 0
    for model in _models(m):
        if not res.symplectic_for(model):
            continue
        zz = _away_from_poles(m, model, z)
        D = transfer_jet(m, zz, model, scale=False, order=0).D
        size = np.abs(D).sum(axis=(1, 2))
        ok = size < 1e4
        det_minus_1 = D[:, 0, 0] + D[:, 1, 1] + D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
        assert np.all(np.abs(det_minus_1[ok]) <= 1e-11 * (1 + size[ok]) ** 2), model
        checked += 1
    assert checked or not res.symplectic_for_separable


def test_a_method_that_is_not_symplectic_has_determinant_other_than_one():
    """The determinant test can fail: RK4's M(z) has ``det = |R(iz)|^2 != 1``."""
    D = transfer_jet(_method("rk4", None), [1.0], "oscillator", scale=False, order=0).D[0]
    assert abs(D[0, 0] + D[1, 1] + D[0, 0] * D[1, 1] - D[0, 1] * D[1, 0]) > 1e-3


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_symmetric_methods_and_only_they_are_their_own_adjoint(item):
    """``symmetric()`` is true exactly when ``M(-z) M(z) = I`` (on the oscillator, at a few
    z away from poles): a symmetric method run backwards undoes its step."""
    m = _method(*item)
    if not _single_force(m):
        assert m.symmetric() == (m.outer.symmetric() and m.inner.symmetric())
        return
    z = _away_from_poles(m, "oscillator", np.array([0.3, 0.7, 1.1]))
    M = transfer_matrix(m, z, "oscillator")
    back = transfer_matrix(m, -z, "oscillator")
    defect = np.abs(back @ M - np.eye(2)).max(axis=(1, 2))
    size = 1 + np.abs(M).max(axis=(1, 2)) * np.abs(back).max(axis=(1, 2))
    if m.symmetric():
        assert np.all(defect <= 1e-12 * size), defect
    else:
        assert np.any(defect > 1e-8 * size), defect


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_transfer_matrix_agrees_with_the_independent_reference(item):
    """The float64 M(z) of every method against its mpmath reference at 40 digits
    (:func:`stepsafe.methods.exact.high_precision`: its own definition, or its parts, in
    mpmath code that shares nothing with the float path)."""
    import mpmath as mp

    m = _method(*item)
    if not _single_force(m):
        pytest.skip("an impulse method steps two forces")
    reference = high_precision(m)
    for model in _models(m):
        z = _away_from_poles(m, model, np.array([0.25, 0.9, 1.7]))
        M = transfer_matrix(m, z, model)
        with mp.workdps(40):
            for zk, Mk in zip(z, M):
                R = reference(mp.mpf(float(zk)), model)
                exact = np.array([[float(R[i, j]) for j in range(2)] for i in range(2)])
                assert np.abs(Mk - exact).max() <= 1e-11 * (1 + np.abs(exact).max()), \
                    (model, zk)


def _model_system(model: str, beta: float) -> tuple[np.ndarray, np.ndarray]:
    """``(S, T)``: the Hessian of the model's H at frequency beta and the scaling
    ``x = T x~`` from the model's variables ``(q, p~)`` (p~ = p / beta for the kinetic +
    potential models) to ``(q, p)``."""
    if model == "oscillator":
        return np.diag([beta * beta, 1.0]), np.diag([1.0, beta])
    if model == "inverted":
        return np.diag([-beta * beta, 1.0]), np.diag([1.0, beta])
    sign = 1.0 if model == "saddle" else -1.0
    return sign * beta * np.array([[0.0, 1.0], [1.0, 0.0]]), np.eye(2)


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_the_2x2_map_is_the_one_degree_of_freedom_case_of_the_2n_map(item):
    """One step of size h on ``x' = J S x`` with the 2x2 Hessian of each model equals the
    model's transfer matrix at ``z = beta h`` (in the model's scaled variables), to
    rounding: the two maps read one decomposition of the method."""
    m = _method(*item)
    if not _single_force(m) or not m.hamiltonian:
        pytest.skip("an impulse method steps two forces; a Langevin splitting is analysed "
                    "on vibrations one at a time")
    beta = 1.7
    for model in _models(m):
        S, T = _model_system(model, beta)
        for h in (0.05, 0.4, 0.9):
            if not _away_from_poles(m, model, np.array([beta * h])).size:
                continue
            M2 = T @ transfer_matrix(m, [beta * h], model)[0] @ np.linalg.inv(T)
            Mn = one_step_matrix(m, S, h)
            assert np.abs(Mn - M2).max() <= 1e-12 * (1 + np.abs(M2).max()), (model, h)


@pytest.mark.parametrize("item", SHIPPED, ids=_ids)
def test_decoupled_modes_step_mode_by_mode(item):
    """``H = (p^T p + q^T K q) / 2`` with ``K = Q^T diag(+-beta_i^2) Q`` (Q a random
    orthogonal matrix: a point transformation, under which every method here is
    invariant) steps as its modes: ``M = diag(Q, Q)^T blockdiag(M_i) diag(Q, Q)`` with
    ``M_i`` each mode's 2x2 matrix (vibrations and barrier tops), to rounding."""
    m = _method(*item)
    if not _single_force(m) or not m.hamiltonian:
        pytest.skip("an impulse method steps two forces; a Langevin splitting is analysed "
                    "on vibrations one at a time")
    rng = np.random.default_rng(zlib.crc32(_ids(item).encode()))
    for n in (2, 3, 5):
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        beta = rng.uniform(0.2, 2.0, n)
        sign = rng.choice([-1.0, 1.0], n) if "inverted" in _models(m) else np.ones(n)
        S = np.zeros((2 * n, 2 * n))
        S[:n, :n] = Q.T @ np.diag(sign * beta * beta) @ Q
        S[n:, n:] = np.eye(n)
        h = 0.6
        z = beta * h
        modes = np.zeros((2 * n, 2 * n))
        for i in range(n):
            model = "oscillator" if sign[i] > 0 else "inverted"
            if not _away_from_poles(m, model, z[i:i + 1]).size:
                pytest.skip("a mode at a pole")
            _, T = _model_system(model, beta[i])
            Mi = T @ transfer_matrix(m, z[i:i + 1], model)[0] @ np.linalg.inv(T)
            modes[np.ix_([i, n + i], [i, n + i])] = Mi
        rotate = np.kron(np.eye(2), Q)
        expected = rotate.T @ modes @ rotate
        Mn = one_step_matrix(m, S, h)
        assert np.abs(Mn - expected).max() <= 1e-11 * (1 + np.abs(expected).max()), n


def _gauss2_exact(A, steps):
    """``prod_k R(g_k h A)`` at 50 digits, ``R(X) = (I - X/2 + X^2/12)^-1 (I + X/2 + X^2/12)``
    the (2,2) Padé approximant of exp: the step of the 2-stage Gauss method on ``x' = A x``
    (its stability function, which a linear system sees whole). ``steps`` in order."""
    mpmath = pytest.importorskip("mpmath")
    with mpmath.workdps(50):
        L = mpmath.matrix(A.tolist())
        eye = mpmath.eye(L.rows)
        M = eye
        for step in steps:
            X = L * mpmath.mpf(step)
            X2 = X * X / 12
            M = mpmath.inverse(eye - X / 2 + X2) * (eye + X / 2 + X2) * M
        D = M - eye
        return np.array([[float(D[i, j]) for j in range(D.cols)] for i in range(D.rows)])


@given(n=st.integers(1, 4), seed=st.integers(0, 2**32 - 1),
       h=st.floats(1e-3, 0.6), log_unit=st.integers(-40, 40))
@settings(max_examples=12, deadline=None)
def test_a_composition_of_an_implicit_method_is_the_product_of_its_substeps(n, seed, h,
                                                                              log_unit):
    """A composition of the 2-stage Gauss method (triple jump weights: negative substeps)
    on a random coupled ``x' = J S x`` (definite or not, S scaled by ``2^log_unit``) is the
    product of its substeps: the float ``M - I`` of the step engine agrees with the
    50-digit product of the exact substeps (Padé approximants of exp) within its own
    normwise rounding bound."""
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(2 * n, 2 * n))
    unit = 2.0 ** log_unit
    S = unit * (G + G.T) / 2
    w1 = 1 / (2 - 2 ** (1 / 3))
    weights = [w1, 1 - 2 * w1, w1]
    composition = Composition(base=resolve("gauss", 2)[0], weights=np.array(weights),
                              name="triple-jump-gauss2")
    step = h / unit
    D, err = _Steps(composition, S).deviation(step)
    exact = _gauss2_exact(hamiltonian_matrix(S), [g * step for g in weights])
    if not np.all(np.isfinite(exact)) or not np.all(np.isfinite(D)):
        return  # a substep at a pole of its stage system
    wrong = float(np.linalg.norm(D - exact))
    assert wrong <= err, (wrong, err)
