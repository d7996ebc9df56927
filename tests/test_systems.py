"""Whole systems: linear n-dof (decoupled and coupled) and nonlinear 1-dof equilibria."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from support import method

from stepsafe.core.regions import find_region
from stepsafe.systems.coupled import (
    continuous_signature,
    coupled_safe_steps,
    discrete_signature,
    one_step_matrix,
)
from stepsafe.systems.linear import hessian_modes, separable_modes
from stepsafe.systems.nonlinear import find_equilibria, parse_hamiltonian

ROOT = Path(__file__).resolve().parent.parent


def scene(tmp_path, text: str) -> str:
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    return str(path)


def test_paper_section3_from_the_hamiltonian(run_json):
    data = run_json("advise", str(ROOT / "examples" / "paper-section3-system.yaml"))
    assert data["h_max"] == pytest.approx(0.5, rel=1e-12)  # 0 < alpha h < 1, alpha = 2
    items = {(round(i["q"], 9), round(i["p"], 9)): i for i in data["system"]["items"]}
    assert items[(0.0, 0.0)]["model"] == "saddle-p" and items[(0.0, 0.0)]["h_limit"] is None
    assert items[(0.0, 1.0)]["model"] == "saddle"
    assert items[(0.0, 1.0)]["h_limit"] == pytest.approx(0.5, rel=1e-12)  # the limiting one
    assert data["limiting"]["model"] == "saddle"


def test_paper_section3_check_exit_codes(run, tmp_path):
    base = (ROOT / "examples" / "paper-section3-system.yaml").read_text()
    assert run("check", scene(tmp_path, base))[0] == 0  # h = 0.4
    assert run("check", scene(tmp_path, base.replace("h: 0.4", "h: 0.5")))[0] == 1


def test_pendulum_centre_limits_saddles_never(run_json):
    data = run_json("advise", str(ROOT / "examples" / "pendulum.yaml"))
    assert data["h_max"] == pytest.approx(2.0, rel=1e-12)
    kinds = sorted((i["type"], i["model"], i["h_limit"]) for i in data["system"]["items"])
    assert kinds[0] == ("elliptic", "oscillator", pytest.approx(2.0, rel=1e-12))
    assert [k[2] for k in kinds[1:]] == [None, None]  # the tops (inverted) never limit


def test_non_separable_saddle_differs_for_a_partitioned_method():
    """The pendulum top (kinetic + potential) and H = q p have the same continuous
    eigenvalues, but symplectic Euler loses the second at z = 1 and never the first."""
    se = method("symplectic-euler")
    top, = find_equilibria(parse_hamiltonian("p**2/2 - cos(q)"), (2, 4), (-1, 1)).equilibria
    qp, = find_equilibria(parse_hamiltonian("q*p"), (-1, 1), (-1, 1)).equilibria
    assert (top.model, qp.model) == ("inverted", "saddle") and top.beta == qp.beta == 1
    assert find_region(se, "inverted").first_boundary is None
    assert find_region(se, "saddle").first_boundary == pytest.approx(1.0)


def test_double_well():
    H = parse_hamiltonian("p**2/2 + (q**2 - 1)**2/4")
    eqs = find_equilibria(H, (-2, 2), (-1, 1)).equilibria
    assert [(round(e.q, 12), e.model) for e in eqs] == [(-1.0, "oscillator"), (0.0, "inverted"),
                                                          (1.0, "oscillator")]
    assert eqs[0].beta == pytest.approx(math.sqrt(2), rel=1e-14)


def _random_separable(rng, n):
    A = rng.normal(size=(n, n))
    K = A + A.T
    B = rng.normal(size=(n, n))
    Minv = B @ B.T + n * np.eye(n)
    S = np.block([[K, np.zeros((n, n))], [np.zeros((n, n)), Minv]])
    return S, K, np.linalg.inv(Minv)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("name", ["verlet", "pefrl", "yoshida4"])
def test_coupled_analysis_agrees_with_decoupled(seed, name):
    rng = np.random.default_rng(seed)
    S, K, M = _random_separable(rng, 3)
    m = method(name)
    modes = separable_modes(K, M).modes
    limits = []
    for mode in modes:
        if mode.model == "free":
            continue
        z_star = find_region(m, mode.model, zmax=50).first_boundary
        limits.append(np.inf if z_star is None else z_star / mode.beta)
    decoupled = min(limits)
    coupled = coupled_safe_steps(m, S, zmax=50).h_max
    assert coupled == pytest.approx(decoupled, rel=1e-9)


@pytest.mark.parametrize("name", ["verlet", "pefrl", "lobatto3ab", "gauss"])
def test_one_step_matrix_is_symplectic(name):
    rng = np.random.default_rng(7)
    n = 3
    A = rng.normal(size=(2 * n, 2 * n))
    S = A @ A.T  # positive definite, non-separable
    m = method(name, 3 if name in ("lobatto3ab", "gauss") else None)
    J = np.block([[np.zeros((n, n)), np.eye(n)], [-np.eye(n), np.zeros((n, n))]])
    for h in (0.01, 0.1, 0.3):
        Mh = one_step_matrix(m, S, h)
        assert np.abs(Mh.T @ J @ Mh - J).max() <= 1e-11 * max(1.0, np.abs(Mh).max() ** 2)


def test_rk_decouples_partitioned_does_not():
    S = np.array([[2.0, 0.4], [0.4, 1.0]])
    assert hessian_modes(S, method("gauss", 2)) is not None
    assert hessian_modes(S, method("pefrl")) is None
    sig = continuous_signature(S)
    assert sig.elliptic_plus + sig.elliptic_minus == 1
    assert discrete_signature(one_step_matrix(method("pefrl"), S, 0.1)) == sig


def test_coupled_scene_says_which_analysis(run_json, tmp_path):
    text = ("method: pefrl\nh: 0.1\nsystem: {hessian: [[2, 0, 0.4, 0], [0, 1, 0, 0.1], "
            "[0.4, 0, 1, 0], [0, 0.1, 0, 1]]}\n")
    data = run_json("advise", scene(tmp_path, text))
    assert data["system"]["analysis"].startswith("coupled")
    assert data["h_max"] > 0
    rk = run_json("advise", scene(tmp_path, text.replace("pefrl", "{name: gauss, stages: 2}")))
    assert rk["system"]["analysis"].startswith("decoupled: RK")


def test_sparse_chain_of_1e5_dof(run_json, tmp_path):
    import scipy.sparse as sp

    n = 100_000
    K = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    sp.save_npz(tmp_path / "chain.npz", K)
    data = run_json("advise", scene(tmp_path, "method: verlet\nsystem: {stiffness: chain.npz}\n"))
    w_max = math.sqrt(2 - 2 * math.cos(n * math.pi / (n + 1)))
    assert data["h_max"] == pytest.approx(2 / w_max, rel=1e-10)
    assert "islands not analysed" in data["system"]["analysis"]


def test_matrix_files(run_json, tmp_path):
    K = np.array([[2.0, -1.0], [-1.0, 2.0]])
    np.save(tmp_path / "K.npy", K)
    np.savez(tmp_path / "M.npz", np.diag([1.0, 2.0]))
    import scipy.io
    import scipy.sparse as sp

    scipy.io.mmwrite(str(tmp_path / "K.mtx"), sp.csr_matrix(K))
    for stiff in ("K.npy", "K.mtx"):
        data = run_json("advise", scene(tmp_path, f"method: verlet\nsystem: {{stiffness: {stiff}, "
                                                   "mass: M.npz}\n"))
        w = max(np.sqrt(np.linalg.eigvals(np.linalg.solve(np.diag([1.0, 2.0]), K)).real))
        assert data["h_max"] == pytest.approx(2 / w, rel=1e-12)


@pytest.mark.parametrize("system, message", [
    ("{stiffness: [[1, 2], [3, 4]]}", "must be symmetric"),
    ("{stiffness: [[1, 2, 3], [2, 1, 3]]}", "square"),
    ("{stiffness: [[1, 0], [0, 1]], mass: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}", "mass is 3x3"),
    ("{stiffness: [[1, 0], [0, 1]], mass: [[1, 0], [0, -1]]}", "positive definite"),
    ("{stiffness: [[1, .nan], [.nan, 1]]}", "is not a number"),
    ("{stiffness: [[1, nan], [nan, 1]]}", "non-finite"),
    ("{hessian: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}", "2n x 2n"),
    ("{stiffness: missing.npy}", "no such file"),
    ('{hamiltonian: "p**2/2 + z*q", box: {q: [-1, 1], p: [-1, 1]}}', "unknown name 'z'"),
    ('{hamiltonian: "p**2/2 + q.real", box: {q: [-1, 1], p: [-1, 1]}}', "Attribute"),
    ('{hamiltonian: "p**2/2 + q**2", box: {q: [2, 3], p: [2, 3]}}', "no equilibrium of H found"),
    ('{hamiltonian: "p**2/2 + q**2", box: {q: [3, 2], p: [-1, 1]}}', "lo < hi"),
    ('{hamiltonian: "p**2/2 + q**2"}', "$.system.box"),
    ("{stiffness: [[1]], hessian: [[1, 0], [0, 1]]}", "exactly one of"),
    ("{springs: 3}", "unknown key"),
])
def test_bad_systems_exit_2(run, tmp_path, system, message):
    code, out, err = run("check", scene(tmp_path, f"method: verlet\nh: 0.1\nsystem: {system}\n"))
    assert code == 2 and message in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_json_lists_each_equilibrium(run, tmp_path):
    code, out, _ = run("check", str(ROOT / "examples" / "double-well.yaml"), "--json")
    (data,) = json.loads(out)["checks"]
    assert code == 0 and len(data["system"]["items"]) == 3
    for item in data["system"]["items"]:
        assert {"q", "p", "type", "beta", "model", "D"} <= set(item)


def test_coupled_check_fails_beyond_h_max(run, tmp_path):
    text = ("method: pefrl\nh: H\nsystem: {hessian: [[2, 0, 0.4, 0], [0, 1, 0, 0.1], "
            "[0.4, 0, 1, 0], [0, 0.1, 0, 1]]}\n")
    code, out, _ = run("check", scene(tmp_path, text.replace("H", "0.1")), "--json")
    assert code == 0 and json.loads(out)["safe"]
    code, out, _ = run("check", scene(tmp_path, text.replace("H", "5")), "--json")
    data = json.loads(out)
    assert code == 1 and not data["safe"]
    (fail,) = data["checks"][0]["failures"]
    assert fail["model"] == "coupled" and 0 < fail["largest_safe_h"] < 5


def _hamiltonian_scene(tmp_path, text: str, box: str = "{q: [-1, 1], p: [-1, 1]}",
                       method: str = "verlet", h: float = 0.5) -> str:
    path = tmp_path / "h.yaml"
    path.write_text(f'method: {method}\nh: {h}\nsystem:\n  hamiltonian: "{text}"\n'
                    f"  box: {box}\n")
    return str(path)


@pytest.mark.parametrize("text, model, beta", [
    ("1e-6*p**2 + 1e6*q**2", "oscillator", 2.0),  # beta^2 = H_qq H_pp = 2e6 * 2e-6
    ("1e300*q**2 + 1e-300*p**2", "oscillator", 2.0),
    ("p**2 + 1e-32*q**2", "oscillator", 2e-16),
    ("(q - 0.3)**2*1e-300 + p**2", "oscillator", 2e-150),
    ("1e12*p**2 + 1e12*q**2", "oscillator", 2e12),
    ("sin(q)/q + p**2", "inverted", math.sqrt(2 / 3)),  # removable singularity at 0
    ("p**2/2 - cos(q)", "oscillator", 1.0),
    # a stiff quartic term: Newton creeps towards 0 before it converges quadratically
    ("p**2/2 + q**2/2 + 1e30*q**4", "oscillator", 1.0),
    ("p**2/2 + 1e20*(q - 0.3)**2 + 1e40*(q - 0.3)**4", "oscillator", math.sqrt(2e20)),
])
def test_hamiltonians_at_any_scale(tmp_path, text, model, beta):
    """The linearisation at the equilibrium, whatever the units: beta^2 = |H_qq H_pp|."""
    from stepsafe.core.advice import Modes
    from stepsafe.systems.loader import analyse_system

    report = analyse_system({"hamiltonian": text, "box": {"q": ["-1", "1"], "p": ["-1", "1"]}},
                            "h.yaml", tmp_path, method("verlet"))
    (item,) = report.items
    assert item["model"] == model and item["beta"] == pytest.approx(beta, rel=1e-12)
    assert isinstance(report.modes, Modes)


def test_stiff_hamiltonian_limits_the_step(run, tmp_path):
    """beta = 2e12: Verlet is safe below h = 2/beta = 1e-12 (the largest safe h is not 0)."""
    code, out, _ = run("check", _hamiltonian_scene(tmp_path, "1e12*p**2 + 1e12*q**2"))
    shown = float(out.split("largest safe h for it: ")[1].split()[0])
    assert code == 1 and 0.999e-12 < shown < 2 / 2e12
    code, _, _ = run("check", _hamiltonian_scene(tmp_path, "1e12*p**2 + 1e12*q**2", h=shown))
    assert code == 0  # the step shown is one that may be taken


@pytest.mark.parametrize("text, message", [
    ("q**4 + p**2", "degenerate"),
    ("q**4 + p**4", "degenerate"),
    ("q**3 + p**2", "degenerate"),
    ("1", "flat"),
    ("0*q + 0*p", "flat"),
    ("exp(1000*q) + p**2", "cannot be evaluated"),
    ("1/q + p**2", "no equilibrium"),
])
def test_nothing_analysed_is_not_safe(run, tmp_path, text, message):
    """No mode or equilibrium could be analysed: exit 2 with the reason, never SAFE."""
    code, out, err = run("check", _hamiltonian_scene(tmp_path, text))
    assert code == 2 and message in err and "SAFE" not in out, (out, err)
    assert len(err.strip().splitlines()) == 1


def test_degenerate_equilibrium_beside_an_analysed_one(run_json, tmp_path):
    """H = p^2/2 + q^4/4 - q^3/3 (from V' = q^2 (q - 1)): a degenerate point at 0 and a
    centre at q = 1 (V'' = 1): the centre is analysed, the other reported as having no
    linear model."""
    data = run_json("advise", _hamiltonian_scene(tmp_path, "p**2/2 + q**4/4 - q**3/3",
                                                 "{q: [-0.5, 1.5], p: [-1, 1]}"))
    kinds = {round(item["q"], 9): item["type"] for item in data["system"]["items"]}
    assert kinds == {0.0: "degenerate", 1.0: "elliptic"}
    assert data["h_max"] == pytest.approx(2.0, rel=1e-12)
    assert any("no linear model" in note for note in data["system"]["notes"])


def test_stiff_matrix_keeps_its_slow_barrier(run, tmp_path):
    """K = diag(1e12, -1): the barrier of rate 1 is far above rounding (~1e-3) and limits
    the midpoint rule (pole at z = 2) to h < 2: it is not taken for a 'free' mode."""
    path = tmp_path / "k.yaml"
    path.write_text("method: midpoint\nh: 3\nsystem: {stiffness: [[1e12, 0], [0, -1]]}\n")
    code, out, _ = run("check", str(path))
    assert code == 1 and "inverted beta = 1:" in out


def test_eigenvalue_within_rounding_of_zero_is_analysed_as_both_types():
    from stepsafe.systems.linear import separable_modes

    c, s = np.cos(0.3), np.sin(0.3)
    Q = np.array([[c, -s], [s, c]])
    K = Q @ np.diag([1e12, 1e-9]) @ Q.T  # 1e-9 is far below the rounding of 1e12 (~3e-3)
    modes = separable_modes(K).modes
    undecided = [m for m in modes if not m.decided]
    assert {m.model for m in undecided} == {"oscillator", "inverted"}
    assert all(m.beta >= np.sqrt(1e-9) for m in undecided)
    # a diagonal K is decoupled already: its entries are the eigenvalues, exactly
    modes = separable_modes(np.diag([1e12, 1e-9]), np.diag([2.0, 1e-300])).modes
    assert all(m.decided and m.model == "oscillator" for m in modes)
    assert sorted(m.beta for m in modes) == [np.sqrt(1e12 / 2.0), np.sqrt(1e-9 / 1e-300)]


def test_large_sparse_system_is_safe_only_from_zero(run, tmp_path):
    """Only the extreme modes of a > 2000-dof sparse system are computed, so a step in an
    island of the fastest mode (Gauss s = 3 on the oscillator: reversed on (sqrt 10, sqrt 60),
    preserved again beyond) cannot be certified: beyond h_max the check fails."""
    import scipy.sparse as sp

    w = np.linspace(0.1, 100.0, 2001)
    sp.save_npz(tmp_path / "K.npz", sp.diags(w ** 2).tocsr())
    path = tmp_path / "s.yaml"
    path.write_text("method: {name: gauss, stages: 3}\nh: 0.08\nsystem: {stiffness: K.npz}\n")
    code, out, _ = run("check", str(path))
    assert code == 1, out  # z = 8 is past sqrt 60 for the top mode: an island, not analysed
    path.write_text("method: {name: gauss, stages: 3}\nh: 0.03\nsystem: {stiffness: K.npz}\n")
    assert run("check", str(path))[0] == 0


def test_scene_with_modes_and_system_is_refused(run, tmp_path):
    path = tmp_path / "both.yaml"
    path.write_text("method: verlet\nh: 0.1\nmodes: [{beta: 1}]\n"
                    "system: {stiffness: [[4]]}\n")
    code, _, err = run("check", str(path))
    assert code == 2 and "$.system" in err and "not both" in err


def test_large_systems_list_the_most_limiting_modes(tmp_path, run):
    """advise/check on a 30-dof system list the ten modes with the smallest h limit (the
    first is the one that limits h) unless --every-mode; a coupled system counts its dof."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(30, 30))
    np.save(tmp_path / "K.npy", A @ A.T / 30 + np.eye(30))
    scene = tmp_path / "s.yaml"
    scene.write_text("method: verlet\nsystem:\n  stiffness: K.npy\n")
    for command in (["advise"], ["check", "--step", "0.1"]):
        code, out, _ = run(*command, str(scene))
        assert code == 0 and "the 10 most limiting of 30" in out
        listed = [line for line in out.splitlines() if "elliptic oscillator" in line]
        assert len(listed) == 10
        limits = [float(line.rsplit("h < ", 1)[1]) for line in listed]
        assert limits == sorted(limits)
        code, out, _ = run(*command, str(scene), "--every-mode")
        assert len([line for line in out.splitlines() if "elliptic oscillator" in line]) == 30
    np.save(tmp_path / "S.npy", np.block([[np.eye(3), 0.3 * np.ones((3, 3))],
                                          [0.3 * np.ones((3, 3)), np.eye(3)]]))
    scene.write_text("method: pefrl\nsystem:\n  hessian: S.npy\n")
    code, out, _ = run("check", str(scene), "--step", "0.01")
    assert code == 0 and "all 3 mode(s)" in out


def test_all_modes_analyses_the_islands_of_a_large_stiffness(tmp_path, run, run_json,
                                                             monkeypatch):
    """Above DENSE_LIMIT only the extreme modes are analysed (no islands, and the note says
    how to ask); `all_modes: true` analyses every mode: the same safe steps, islands
    included, as the frequencies given as modes. A bad value names the key."""
    from stepsafe.systems import loader as sysfile

    monkeypatch.setattr(sysfile, "DENSE_LIMIT", 40)
    betas = np.concatenate([np.linspace(0.2, 0.6, 59), [1.0]])
    np.save(tmp_path / "K.npy", np.diag(betas ** 2))
    scene = tmp_path / "s.yaml"
    scene.write_text("method: yoshida6\nsystem:\n  stiffness: K.npy\n")
    extremes = run_json("advise", str(scene))
    assert "extreme eigenvalues" in extremes["system"]["analysis"]
    assert any("all_modes: true" in note for note in extremes["system"]["notes"])
    scene.write_text("method: yoshida6\nsystem:\n  stiffness: K.npy\n  all_modes: true\n")
    every = run_json("advise", str(scene))
    modes = tmp_path / "m.yaml"
    modes.write_text("method: yoshida6\nmodes:\n"
                     + "".join(f"  - beta: {float(b)!r}\n" for b in betas))
    want = run_json("advise", str(modes))
    flat = [x for pair in every["safe_h"] for x in pair]
    assert flat == pytest.approx([x for pair in want["safe_h"] for x in pair], rel=1e-12)
    assert len(every["safe_h"]) > 1 and len(extremes["safe_h"]) == 1  # islands
    assert extremes["h_max"] == pytest.approx(every["h_max"], rel=1e-12)
    scene.write_text("method: yoshida6\nsystem:\n  stiffness: K.npy\n  all_modes: maybe\n")
    code, _, err = run("advise", str(scene))
    assert code == 2 and "$.system.all_modes" in err


@pytest.mark.parametrize("barrier", [False, True])
def test_large_dense_stiffness_uses_the_extreme_eigenvalues_only(tmp_path, run_json,
                                                                 monkeypatch, barrier):
    """Above DENSE_LIMIT a dense stiffness (with a lumped mass) is analysed by shift-invert
    Lanczos for its extreme eigenvalues: the same h_max as every eigenvalue gives."""
    from scipy.linalg import eigh

    from stepsafe.systems import loader as sysfile

    monkeypatch.setattr(sysfile, "DENSE_LIMIT", 40)
    rng = np.random.default_rng(6)
    A = rng.normal(size=(60, 60))
    K = A @ A.T / 60 + 0.5 * np.eye(60) - (1.5 * np.eye(60) if barrier else 0)
    m = rng.uniform(0.5, 2, 60)
    np.save(tmp_path / "K.npy", K)
    np.save(tmp_path / "M.npy", np.diag(m))
    scene = tmp_path / "s.yaml"
    scene.write_text("method: verlet\nsystem:\n  stiffness: K.npy\n  mass: M.npy\n")
    data = run_json("advise", str(scene))
    assert "extreme eigenvalues" in data["system"]["analysis"]
    w2 = eigh(K, np.diag(m), eigvals_only=True)
    beta_max = float(np.sqrt(w2.max()))
    assert data["h_max"] == pytest.approx(2 / beta_max, rel=1e-10) or barrier
    if barrier:  # the barrier's rate is there too, and h_max is the smaller limit
        rates = [item["beta"] for item in data["system"]["items"] if item["model"] != "oscillator"]
        assert max(rates) == pytest.approx(float(np.sqrt(-w2.min())), rel=1e-10)


def test_constant_powers_are_numbers_and_powers_of_q_are_capped(tmp_path):
    """2**65 is a number, not a power of a variable above 64 (H can be evaluated at every
    start); q**65 is refused as itself."""
    from stepsafe.exceptions import StepsafeError
    from stepsafe.systems.loader import analyse_system

    box = {"q": ["-1", "1"], "p": ["-1", "1"]}
    report = analyse_system({"hamiltonian": "2**65*p**2 + q**2", "box": box}, "h.yaml",
                            tmp_path, method("verlet"))
    (item,) = report.items
    assert item["beta"] == pytest.approx(2.0 ** 33.5, rel=1e-12)
    with pytest.raises(StepsafeError, match="go up to 64"):
        analyse_system({"hamiltonian": "q**65 + p**2", "box": box}, "h.yaml", tmp_path,
                       method("verlet"))


@pytest.mark.parametrize("n", [2, 2500])
def test_a_nearly_symmetric_stiffness_is_analysed_as_its_symmetric_part(tmp_path, run_json,
                                                                       n):
    """q^T K q / 2 sees (K + K^T) / 2 only: an asymmetry within the accepted 1e-12 gives
    the same h_max whichever triangle holds it, dense (n = 2) or on the large-system path
    (n = 2500), and never above the limit of the symmetric part (the largest eigenvalue
    1 + 5e-13 for n = 2, the chain's plus at most 5e-13 for n = 2500)."""
    import scipy.sparse as sp

    if n == 2:
        K = np.array([[1.0, 1e-12], [0.0, 1.0]])
        top = 1 + 5e-13  # eigenvalues of the symmetric part: 1 +- 5e-13
    else:
        K = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tolil()
        K[0, 1] += 1e-12  # only above the diagonal
        K = K.tocsr()
        # the chain's largest eigenvalue, plus at most 5e-13 (Weyl) for the symmetric part
        top = 2 - 2 * math.cos(n * math.pi / (n + 1)) + 5e-13
    got = []
    for name, matrix in (("upper", K), ("lower", K.T)):
        sp.save_npz(tmp_path / f"{name}.npz", sp.csr_matrix(matrix))
        path = tmp_path / f"{name}.yaml"
        path.write_text(f"method: verlet\nsystem: {{stiffness: {name}.npz}}\n")
        got.append(run_json("advise", str(path))["h_max"])
    assert got[0] == got[1]
    assert got[0] <= 2 / np.sqrt(top)


@pytest.mark.parametrize("barrier", [False, True])
def test_a_large_sparse_stiffness_has_a_barrier_only_if_it_has_one(tmp_path, run_json,
                                                                   barrier):
    """A 2500-dof chain, springs over 12 decades and masses over 6: its lowest
    eigenvalues cluster near 0 and the eigensolver does not resolve them within its
    budget. A sparse LDL^T (all pivots positive) proves there is no barrier; with one
    spring negative enough to make K indefinite, the barrier is kept (its rate the
    eigensolver's or, conservatively, the Gershgorin bound's)."""
    import scipy.sparse as sp
    from scipy.io import mmwrite
    from scipy.linalg import eigvalsh_tridiagonal

    n = 2500
    rng = np.random.default_rng(1)
    k = 10.0 ** rng.uniform(-6, 6, n + 1)  # springs, both ends fixed
    m = 10.0 ** rng.uniform(-3, 3, n)
    if barrier:
        k[n // 2] = -2 * max(k[n // 2 - 1], k[n // 2 + 1])  # a negative curvature
    K = sp.diags([-k[1:n], k[:n] + k[1:], -k[1:n]], [-1, 0, 1], format="csr")
    # the lowest w^2 of K v = w^2 M v, from the tridiagonal M^-1/2 K M^-1/2
    lowest = float(eigvalsh_tridiagonal((k[:n] + k[1:]) / m, -k[1:n] / np.sqrt(m[1:] * m[:-1]),
                                        select="i", select_range=(0, 0))[0])
    mmwrite(tmp_path / "K.mtx", K, symmetry="symmetric", precision=17)
    mmwrite(tmp_path / "M.mtx", sp.diags(m, format="csr"), symmetry="symmetric", precision=17)
    path = tmp_path / "scene.yaml"
    path.write_text("method: verlet\nsystem: {stiffness: K.mtx, mass: M.mtx}\n")
    items = run_json("advise", str(path))["system"]["items"]
    barriers = [i for i in items if i["type"] == "hyperbolic"]
    if barrier:
        assert lowest < 0 and barriers and barriers[0]["beta"] >= np.sqrt(-lowest) * (1 - 1e-9)
    else:
        assert lowest > 0 and not barriers, items
