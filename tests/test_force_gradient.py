"""Force-gradient splittings (``gradient:``): the exact M(z), refusals, the engine, cost.

Convention (Chin; Omelyan, Mryglod & Folk): kick i is ``p += b_i h F + c_i h^3 grad |F|^2``
(``F = -V'``, unit mass). On the oscillator the kick coefficient is ``b - 2 c z^2``.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.core.integrator import Engine
from stepsafe.core.transfer import transfer_jet, transfer_matrix
from stepsafe.exceptions import MethodError
from stepsafe.methods.library import resolve
from stepsafe.methods.tableaux import Composition, Splitting
from stepsafe.reference.verify import mp_method, mp_transfer
from stepsafe.systems.dynamics import linear_system

FG = ("chin-4a", "chin-4b", "omelyan4-fg-mn3f1gp", "chin-4a-hessian-free")


def _direct(name: str, z, sign: int):
    """M(z) at 50 digits by running the maps on the basis vectors, the force-gradient term
    from its definition d/dq (F^2) by numerical differentiation (V = -sign q^2/2)."""
    m = mp_method(name, dps=50)
    d, k = m.data["drift"], m.data["kick"]
    g = m.data["gradient"]

    def force(q):
        return sign * q

    cols = []
    for q, p in ((mp.mpf(1), mp.mpf(0)), (mp.mpf(0), mp.mpf(1))):
        for i, a in enumerate(d):
            q = q + a * z * p
            if i < len(k):
                p = p + k[i] * z * force(q) + g[i] * z ** 3 * mp.diff(lambda x: force(x) ** 2, q)
        cols.append((q, p))
    return mp.matrix([[cols[0][0], cols[1][0]], [cols[0][1], cols[1][1]]])


@pytest.mark.parametrize("name", FG)
@pytest.mark.parametrize("model, sign", [("oscillator", -1), ("inverted", 1)])
def test_transfer_matrix_is_the_product_of_the_maps(name, model, sign):
    with mp.workdps(50):
        exact = mp_transfer(mp_method(name, dps=50))
        for z in ("0.3", "1.7", "3.1"):
            zz = mp.mpf(z)
            direct = _direct(name, zz, sign)
            ref = exact(zz, model)
            assert mp.mnorm(ref - direct, 1) < mp.mpf(10) ** -40
            assert abs(mp.det(ref) - 1) < mp.mpf(10) ** -45
            M = transfer_matrix(resolve(name)[0], [float(zz)], model)[0]
            assert np.allclose(M, np.array(ref.tolist(), dtype=float), rtol=0, atol=1e-14)


def test_oscillator_kick_coefficient_and_barrier_sign():
    """One FG kick alone: [[1, 0], [-(b - 2 c z^2) z, 1]] on the oscillator and
    [[1, 0], [(b + 2 c z^2) z, 1]] on the barrier top (the oscillator's at z -> i z)."""
    kick = Splitting([0.0], [0.75], gradient=[0.125])
    z = np.array([0.5, 2.0])
    osc = transfer_matrix(kick, z, "oscillator")[:, 1, 0]
    inv = transfer_matrix(kick, z, "inverted")[:, 1, 0]
    assert np.allclose(osc, -(0.75 - 0.25 * z * z) * z, rtol=1e-15)
    assert np.allclose(inv, (0.75 + 0.25 * z * z) * z, rtol=1e-15)


@pytest.mark.parametrize("name", FG)
def test_consistent_and_fourth_order_on_the_oscillator(name):
    """tr M = 2 cos z + O(z^6) (4th order), det M = 1, dM/dz matches differences."""
    m = resolve(name)[0]
    jet = transfer_jet(m, np.array([0.05, 0.1, 0.8]), "oscillator", order=2)
    assert np.allclose(np.linalg.det(jet.M), 1.0, atol=1e-15)
    err = np.abs(jet.trace[:2] - 2 * np.cos([0.05, 0.1]))
    assert err[1] / err[0] == pytest.approx(64, rel=0.05)
    h = 1e-6
    up, down = (transfer_jet(m, np.array([0.8 + s]), "oscillator") for s in (h, -h))
    assert np.allclose((up.M - down.M) / (2 * h), jet.dM[2:], atol=1e-8)
    assert np.allclose((up.dM - down.dM) / (2 * h), jet.d2M[2:], atol=1e-7)


def test_composition_scales_the_gradient_by_the_cube():
    """A composition of an FG splitting is the product of the base at g z (the gradient
    term is h^3: it scales by g^3 when the substeps are multiplied out)."""
    base = resolve("chin-4b")[0]
    comp = Composition(base, [0.3, 0.4, 0.3], name="c")
    z = np.array([0.7, 2.2])
    product = [transfer_matrix(base, [0.3 * x])[0] @ transfer_matrix(base, [0.4 * x])[0]
               @ transfer_matrix(base, [0.3 * x])[0] for x in z]
    assert np.allclose(transfer_matrix(comp, z), product, atol=1e-14)
    assert comp.as_splitting().gradient_evaluations == 6


def test_no_prk_form_and_no_saddle():
    m = resolve("chin-4a")[0]
    with pytest.raises(MethodError, match="force-gradient"):
        m.as_prk()
    with pytest.raises(MethodError, match="saddle"):
        transfer_matrix(m, [1.0], "saddle")


def test_counts():
    assert resolve("chin-4a")[0].gradient_evaluations == 1
    assert resolve("chin-4b")[0].gradient_evaluations == 2
    assert resolve("chin-4a-hessian-free")[0].gradient_evaluations == 0  # forces instead
    wrapped = Splitting([0.0, 1.0], [0.5, 0.5], gradient=[0.01, 0.01])  # FSAL gradient
    assert wrapped.gradient_evaluations == 1


def _pendulum_error(name: str, n: int) -> float:
    from scipy.integrate import solve_ivp

    from stepsafe.core.integrator import System

    system = System(dH_dq=lambda q, p: np.sin(q), dH_dp=lambda q, p: p,
                    energy=lambda q, p: (p * p / 2 - np.cos(q))[:, 0], separable=True,
                    dimension=1, hessian=lambda q, p: (np.cos(q)[:, :, None],
                                                       np.zeros((1, 1, 1)),
                                                       np.ones((1, 1, 1))))
    engine = Engine(resolve(name)[0], system)
    q, p = np.array([[1.0]]), np.array([[0.5]])
    for _ in range(n):
        q, p = engine.step(q, p, 1.0 / n)
    ref = solve_ivp(lambda t, y: [y[1], -np.sin(y[0])], (0, 1), [1.0, 0.5], rtol=1e-13,
                    atol=1e-14, method="DOP853").y[:, -1]
    return float(np.hypot(q[0, 0] - ref[0], p[0, 0] - ref[1]))


@pytest.mark.parametrize("name", FG)
def test_engine_order_on_the_pendulum(name):
    """The integration engine (Hessian-vector product, or the displaced force) reaches
    order 4 on H = p^2/2 - cos q."""
    e8, e16 = _pendulum_error(name, 8), _pendulum_error(name, 16)
    assert abs(np.log2(e8 / e16) - 4) < 0.3


def _growth(name: str, S: np.ndarray, h: float, steps: int = 4000) -> float:
    system = linear_system(S)
    n = S.shape[0] // 2
    engine = Engine(resolve(name)[0], system)
    q, p = np.ones((1, n)), np.zeros((1, n))
    e0 = system.energy(q, p)[0]
    top = e0
    for _ in range(steps):
        q, p = engine.step(q, p, h)
        top = max(top, system.energy(q, p)[0])
    return top / e0


@settings(max_examples=5, deadline=None)
@given(st.floats(min_value=0.5, max_value=3.0))
def test_stable_just_inside_unstable_just_outside(beta):
    """chin-4b's z* (2.92694759996, a simple root of tr M = -2) seen by integration of the
    oscillator of frequency beta: bounded at 0.99 z*/beta, growing at 1.01 z*/beta."""
    z_star = 2.92694759996
    S = np.diag([beta * beta, 1.0])
    assert _growth("chin-4b", S, 0.99 * z_star / beta) < 1e3
    assert _growth("chin-4b", S, 1.01 * z_star / beta) > 1e6


def test_n_dof_limit_is_the_fastest_mode():
    """A 3-dof chain with a mass matrix: the coupled analysis (exact kick matrices
    K + 2 c h^2 K M^-1 K) and integration agree on the limit of chin-4a."""
    from stepsafe.systems.coupled import one_step_matrix

    K = np.array([[2.0, -1.0, 0.0], [-1.0, 2.0, -1.0], [0.0, -1.0, 2.0]])
    Minv = np.diag([1.0, 0.5, 2.0])
    S = np.block([[K, np.zeros((3, 3))], [np.zeros((3, 3)), Minv]])
    omega = float(np.sqrt(np.linalg.eigvals(Minv @ K).real.max()))
    h_star = 2 * np.sqrt(3) / omega
    for h, stable in ((0.97 * h_star, True), (1.03 * h_star, False)):
        M = one_step_matrix(resolve("chin-4a")[0], S, h)
        assert (np.abs(np.linalg.eigvals(M)).max() < 1 + 1e-9) == stable
        assert (_growth("chin-4a", S, h, 3000) < 1e3) == stable


def test_gradient_cost_changes_the_ranking_and_bad_values_are_refused():
    import stepsafe
    from stepsafe.exceptions import StepsafeError

    def order(cost):
        rows = stepsafe.compare(["chin-4b", "pefrl"], [1.0], tol_phase=1e-8,
                                gradient_cost=cost).rows
        return [r.method for r in rows]

    assert order(1.0) == ["chin-4b", "pefrl"]  # 2 forces + 2 gradients at 1 force each
    assert order(2.0) == ["pefrl", "chin-4b"]
    for bad in (-1.0, float("nan"), "x"):
        with pytest.raises(StepsafeError, match="gradient cost"):
            stepsafe.compare(["chin-4b"], [1.0], tol_phase=1e-8, gradient_cost=bad)


@pytest.mark.parametrize("text, where", [
    ("gradient: [0]\n", "$.gradient: has 1 entries; it needs one per kick (2)"),
    ("gradient_form: displaced-force\n", "$.gradient_form: applies only"),
    ('gradient: ["1/72", 0]\ngradient_form: displaced-force\n', "$.gradient[0]"),
])
def test_bad_gradient_keys_name_the_key(tmp_path, text, where):
    from stepsafe.exceptions import StepsafeError
    from stepsafe.methods.library import load_file

    path = tmp_path / "fg.yaml"
    path.write_text('name: fg\nkind: splitting\norder: 2\nsource: "test"\n'
                    'drift: [0, 1]\nkick: [0, 1]\n' + text)
    with pytest.raises(StepsafeError) as info:
        load_file(path)
    assert where in f"{info.value.where}: {info.value.message}"


def test_impulse_and_non_separable_systems_refuse_force_gradient_methods():
    from stepsafe.core.integrator import System
    from stepsafe.methods.tableaux import Impulse

    fg = resolve("chin-4a")[0]
    with pytest.raises(MethodError, match="force-gradient"):
        Impulse(fg, resolve("verlet")[0], 2)
    mixed = System(dH_dq=lambda q, p: p, dH_dp=lambda q, p: q, energy=lambda q, p: q[:, 0],
                   separable=False, dimension=1)
    with pytest.raises(ValueError, match="separable"):
        Engine(fg, mixed)


def test_a_triple_root_is_placed_and_its_uncertainty_is_honest():
    """Chin's 4A has M = -I at z* = 2 sqrt 3, where tr M + 2 has a triple root: 40 digits
    place it only to ~1e-14, so the escalation certifies the width it can vouch for and
    redoes the root at 120 digits; the reported z* is 2 sqrt 3 within its stated
    uncertainty, which is at most 4 ulps."""
    from stepsafe.core.regions import find_region

    point = find_region(resolve("chin-4a")[0], "oscillator", 10.0).first_boundary_point
    with mp.workdps(50):
        miss = abs(mp.mpf(point.z) - 2 * mp.sqrt(3))
    assert miss <= point.uncertainty <= 4 * np.spacing(point.z)


@settings(max_examples=12, deadline=None)
@given(exponent=st.integers(30, 300))
def test_huge_gradient_coefficients_keep_their_tiny_boundary(tmp_path_factory, exponent):
    """Chin 4A's shape with the gradient coefficient c = 10^k (k up to 300): the middle
    kick's coefficient 2/3 - 2 c z^2 and the outer ones sum to 1 - 2 c z^2, so tr M - 2 =
    -z^2 (1 - 2 c z^2) + O(z^4) changes sign at z = 1/sqrt(2c) (to 1e-60 relative here).
    The term 2 c z^3 must be formed without z^3 alone, which underflows at z ~ 1e-150
    (the boundary, 1e-150 for k = 300, would be lost)."""
    from stepsafe.core.regions import find_region

    folder = tmp_path_factory.mktemp("fg")
    path = folder / "fg.yaml"
    path.write_text("name: fgx\ntitle: x\nkind: splitting\norder: 4\nsource: test\n"
                    "symmetric: true\ndrift: [0, '1/2']\nkick: ['1/6', '2/3']\n"
                    f"gradient: [0, 1e{exponent}]\n")
    z = find_region(resolve(str(path))[0], "oscillator", 10.0).first_boundary
    with mp.workdps(30):
        want = 1 / mp.sqrt(2 * mp.mpf(10) ** exponent)
    assert z == pytest.approx(float(want), rel=1e-12)


@pytest.mark.parametrize("hamiltonian", ["p**2/2*(1 + q**2) + q**2/2",
                                         "p**2/2*exp(q**2) + q**2/2",
                                         "p**2/2 + q**2/2 + q**2*p**2"])
def test_a_hamiltonian_mixing_q_and_p_is_refused(tmp_path, run, hamiltonian):
    """Its linearisation at (0, 0) separates, but a force-gradient kick is not defined for
    such an H: check refuses (exit 2, naming the key) as measure does, never SAFE."""
    scene = tmp_path / "s.yaml"
    scene.write_text(f"method: chin-4a\nh: 0.5\nsystem:\n  hamiltonian: \"{hamiltonian}\"\n"
                     "  box: {q: [-1, 1], p: [-1, 1]}\n")
    code, _, err = run("check", str(scene))
    assert code == 2 and "$.system.hamiltonian" in err and "separable" in err
    scene.write_text("method: chin-4a\nh: 0.5\nsystem:\n  hamiltonian: \"p**2/2 + q**2/2\"\n"
                     "  box: {q: [-1, 1], p: [-1, 1]}\n")
    assert run("check", str(scene))[0] == 0


def test_a_processor_with_force_gradient_terms_is_refused(tmp_path, run):
    """The processor's cost and inverse are those of a plain drift/kick sequence."""
    path = tmp_path / "p.yaml"
    path.write_text("name: px\ntitle: x\nkind: processed\norder: 2\nsource: test\n"
                    "kernel: verlet\nprocessor: chin-4a\n")
    code, _, err = run("region", str(path))
    assert code == 2 and "::$.processor" in err and "force-gradient" in err


def test_a_force_gradient_outer_method_of_an_impulse_file_is_refused_naming_the_key(tmp_path,
                                                                                   run):
    path = tmp_path / "i.yaml"
    path.write_text("name: ix\ntitle: x\nkind: impulse\norder: 2\nsource: test\n"
                    "outer: chin-4a\ninner: verlet\nsubsteps: 4\n")
    code, _, err = run("show", str(path))
    assert code == 2 and "::$.outer" in err and "force-gradient" in err


def test_hmc_shows_the_step_cost_it_charges():
    """chin-4a: 2 forces and one force gradient per step; at --gradient-cost 3 a step
    costs 5 gradients, and that is the figure shown per step and used per proposal."""
    from stepsafe import hmc

    for cost, per_step in ((1.0, 3.0), (3.0, 5.0)):
        row = hmc(["chin-4a"], sigma=[1.0, 0.1], trajectory_steps=10, gradient_cost=cost).rows[0]
        assert row.evaluations == per_step
        assert row.gradients_per_proposal == 10 * per_step
