"""n-dof Hamiltonian expressions: equilibria, their type and frequencies against closed
forms (Henon-Heiles, an FPU-alpha chain, the Lagrange points), the step limits they set,
measurement on them, and bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import stepsafe
from stepsafe.exceptions import StepsafeError

ROOT = Path(__file__).resolve().parent.parent
HH = ROOT / "examples/henon-heiles.yaml"


def _items(scene, **extra):
    report = stepsafe.advise(scene=str(scene), **extra)
    return report, report.record["system"]["items"]


def test_henon_heiles_closed_forms():
    report, items = _items(HH)
    assert len(items) == 4
    origin = items[0]
    assert origin["type"] == "elliptic" and origin["x"] == [0.0] * 4
    assert origin["frequencies"] == pytest.approx([1.0, 1.0], rel=1e-12)
    saddles = sorted(tuple(i["x"][:2]) for i in items[1:])
    expected = sorted([(0.0, 1.0), (-math.sqrt(3) / 2, -0.5), (math.sqrt(3) / 2, -0.5)])
    assert np.allclose(saddles, expected, rtol=0, atol=1e-12)
    for item in items[1:]:
        assert item["type"] == "mixed" and item["index"] == 1
        assert item["energy"] == pytest.approx(1 / 6, rel=1e-13)
        assert item["frequencies"] == pytest.approx([math.sqrt(3)], rel=1e-12)
        assert item["rates"] == pytest.approx([1.0], rel=1e-12)
    # the saddles' sqrt(3) limits Verlet: h < 2 / sqrt 3, unless they cannot be reached
    assert report.h_max == pytest.approx(2 / math.sqrt(3), rel=1e-12)
    limits = [item["h_limit"] for item in items]
    assert limits == pytest.approx([2.0] + [2 / math.sqrt(3)] * 3, rel=1e-12)
    assert report.record["system"]["limiting_item"] in (1, 2, 3)  # a saddle


def test_energy_below_drops_unreachable_equilibria(tmp_path):
    scene = tmp_path / "hh.yaml"
    scene.write_text(HH.read_text().replace("  box:", "  energy_below: 0.1\n  box:"))
    report, items = _items(scene)
    assert len(items) == 1 and report.h_max == pytest.approx(2.0, rel=1e-12)
    notes = [n for n in report.record["system"]["notes"] if "not below" in n]
    assert len(notes) == 3 and all("not below 0.1" in n for n in notes)


def test_fpu_chain_frequencies():
    report, items = _items(ROOT / "examples/fpu-alpha.yaml")
    assert len(items) == 1 and items[0]["type"] == "elliptic"
    expected = [2 * math.sin(k * math.pi / 10) for k in range(1, 5)]
    assert items[0]["frequencies"] == pytest.approx(expected, rel=1e-12)
    assert report.h_max == pytest.approx(2 / expected[-1], rel=1e-12)


@pytest.mark.parametrize("mu", [0.01, 0.1])
def test_lagrange_points(mu, tmp_path):
    """L4/L5 at (1/2 - mu, +-sqrt(3)/2), momenta (-y, x); their eigenvalues solve
    lambda^4 + lambda^2 + (27/4) mu (1 - mu) = 0: two frequencies below Routh's mass ratio
    0.0385, a loxodromic quadruplet above. L1-L3 have one hyperbolic pair."""
    scene = tmp_path / "l.yaml"
    scene.write_text((ROOT / "examples/lagrange-points.yaml").read_text()
                     .replace("mu: 0.01", f"mu: {mu}"))
    _, items = _items(scene, stages=2)
    triangular = [i for i in items if abs(i["x"][1]) > 0.5]
    collinear = [i for i in items if abs(i["x"][1]) < 1e-12]
    assert len(triangular) == 2 and len(collinear) == 3
    for item in triangular:
        x, y, px, py = item["x"]
        assert (x, abs(y)) == pytest.approx((0.5 - mu, math.sqrt(3) / 2), abs=1e-11)
        assert (px, py) == pytest.approx((-y, x), abs=1e-11)
        d = 1 - 27 * mu * (1 - mu)
        if d > 0:
            w2 = sorted([(1 - math.sqrt(d)) / 2, (1 + math.sqrt(d)) / 2])
            assert item["type"] == "elliptic"
            assert item["frequencies"] == pytest.approx([math.sqrt(w) for w in w2],
                                                        rel=1e-10)
        else:
            assert item["type"] == "loxodromic"
    assert all(i["type"] == "mixed" and i["index"] == 1 for i in collinear)


@pytest.mark.parametrize("change, key", [
    (("q: [x, y]", "q: [x]"), "system.p"),
    (("p: [px, py]", "p: [px, x]"), "system.p"),
    (("p: [px, py]", "p: px"), "system.p"),
    (("- y**3/3", "- z**3/3"), "system.hamiltonian"),
    (("- y**3/3", "- y**3/"), "system.hamiltonian"),
    (("py: [-1, 1]}", "py: [-1, 1], pz: [0, 1]}"), "system.box"),
    ((", py: [-1, 1]}", "}"), "system.box"),
    (("px: [-1, 1]", "px: [1, -1]"), "system.box.px"),
    (("px: [-1, 1]", "px: [-1, .inf]"), "system.box.px[1]"),
    (("px: [-1, 1]", "px: [-1e308, 1e308]"), "system.box.px"),
    (("  box:", "  starts: 0\n  box:"), "system.starts"),
    (("  box:", "  energy_below: -1\n  box:"), "system.energy_below"),
    (("  box:", "  parameters: {x: 1}\n  box:"), "system.parameters"),
])
def test_bad_input_names_the_key(run, tmp_path, change, key):
    scene = tmp_path / "bad.yaml"
    text = HH.read_text()
    assert change[0] in text
    scene.write_text(text.replace(change[0], change[1]))
    code, out, err = run("advise", str(scene))
    assert code == 2 and err.count("\n") == 1 and out == "", err
    assert f"bad.yaml::$.{key}" in err, err


@pytest.mark.parametrize("hamiltonian, h_max", [
    # an isolated degenerate minimum (x^4): its other mode is still analysed
    ("(p1**2 + p2**2)/2 + q1**4 + 50*q2**2", 2 / math.sqrt(100)),
    # frequencies 1e6 and 1e-6: the slow one is no zero mode
    ("(p1**2 + p2**2)/2 + 1e12*q1**2/2 + 1e-12*q2**2/2", 2e-6),
])
def test_zero_and_slow_modes_do_not_hide_the_others(hamiltonian, h_max, tmp_path):
    """An isolated equilibrium with a zero mode still has its other modes analysed, and a
    slow mode is not taken for a zero one."""
    scene = tmp_path / "s.yaml"
    scene.write_text(f"method: verlet\nsystem:\n  hamiltonian: \"{hamiltonian}\"\n"
                     "  q: [q1, q2]\n  p: [p1, p2]\n  box: {q1: [-0.5, 0.5], q2: [-0.5, 0.5], "
                     "p1: [-0.5, 0.5], p2: [-0.5, 0.5]}\n")
    report = stepsafe.advise(scene=str(scene))
    assert report.h_max == pytest.approx(h_max, rel=1e-9)
    assert not stepsafe.check(h=1.01 * h_max, scene=str(scene)).safe


@pytest.mark.parametrize("hamiltonian", [
    # a ring of 4 masses: every translate is an equilibrium
    "(p1**2 + p2**2 + p3**2 + p4**2)/2 + ((q2 - q1)**2 + (q3 - q2)**2 + (q4 - q3)**2"
    " + (q1 - q4)**2)/2",
    # a line of equilibria q1 = q2 whose frequency grows along it: members
    # Newton does not reach would set the limit
    "(p1**2 + p2**2)/2 + (q1 - q2)**2*(1 + q1**2)",
])
def test_families_of_equilibria_are_refused(run, tmp_path, hamiltonian):
    n = 4 if "p4" in hamiltonian else 2
    qs, ps = [f"q{i}" for i in range(1, n + 1)], [f"p{i}" for i in range(1, n + 1)]
    box = ", ".join(f"{v}: [-3, 3]" for v in qs + ps)
    scene = tmp_path / "fam.yaml"
    scene.write_text(f"method: verlet\nsystem:\n  hamiltonian: \"{hamiltonian}\"\n"
                     f"  q: [{', '.join(qs)}]\n  p: [{', '.join(ps)}]\n  box: {{{box}}}\n")
    code, out, err = run("check", str(scene), "--step", "0.01")
    assert code == 2 and "family" in err and "fam.yaml::$.system.hamiltonian" in err, err


def test_points_where_newton_stalls_are_no_equilibria(tmp_path):
    """A box 1e150 wide in one variable: one equilibrium, not the starts Newton left."""
    scene = tmp_path / "wide.yaml"
    scene.write_text("method: verlet\nsystem:\n  hamiltonian: \"(px**2 + py**2)/2 + x**2/2 "
                     "+ y**2/2\"\n  q: [x, y]\n  p: [px, py]\n  box: {x: [-1e150, 1e150], "
                     "y: [-1, 1], px: [-1, 1], py: [-1, 1]}\n")
    _, items = _items(scene)
    assert len(items) == 1 and items[0]["x"] == [0.0] * 4


def test_too_many_degrees_of_freedom(run, tmp_path):
    n = 21
    qs, ps = [f"q{i}" for i in range(n)], [f"p{i}" for i in range(n)]
    H = " + ".join(f"{p}**2/2 + {q}**2/2" for q, p in zip(qs, ps))
    box = ", ".join(f"{v}: [-1, 1]" for v in qs + ps)
    scene = tmp_path / "big.yaml"
    scene.write_text(f"method: verlet\nsystem:\n  hamiltonian: \"{H}\"\n  q: [{', '.join(qs)}]"
                     f"\n  p: [{', '.join(ps)}]\n  box: {{{box}}}\n")
    code, _, err = run("advise", str(scene))
    assert code == 2 and "big.yaml::$.system.q" in err


def test_measure_on_henon_heiles(run):
    """Near the centre the measured energy spread follows the linear model; the engine's
    order on the 2-dof system is 2 for Verlet and 4 for Yoshida against DOP853."""
    from scipy.integrate import solve_ivp

    from stepsafe.core.integrator import Engine
    from stepsafe.files.yamlio import load_yaml
    from stepsafe.systems.loader import read_many
    from stepsafe.systems.manydof import system_of

    code, out, err = run("measure", str(HH), "--h", "0.1", "--time", "50", "--json")
    assert code == 0, err
    row = json.loads(out)["rows"][0]
    assert row["status"] == "ok" and abs(row["energy_ratio"] - 1) < 0.03
    H, _, _ = read_many(load_yaml(HH)["system"], "hh")
    system = system_of(H)
    x0 = np.array([0.3, 0.1, 0.0, 0.2])
    T = 3.0

    def rhs(_, y):
        x, yy, px, py = y
        return [px, py, -(x + 2 * x * yy), -(yy + x * x - yy * yy)]

    ref = solve_ivp(rhs, (0, T), x0, method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    for name, order in (("verlet", 2), ("yoshida4", 4)):
        errs = []
        for n in (30, 60):
            engine = Engine(stepsafe.method(name).tableau, system)
            q, p = x0[None, :2].copy(), x0[None, 2:].copy()
            for _ in range(n):
                q, p = engine.step(q, p, T / n)
            errs.append(float(np.linalg.norm(np.concatenate([q[0], p[0]]) - ref)))
        assert abs(math.log2(errs[0] / errs[1]) - order) < 0.3, (name, errs)
    with pytest.raises(StepsafeError, match="1-dof"):
        stepsafe.measure("verlet", [0.1], scene=str(HH), energy=0.1)


def test_double_pendulum_closed_forms():
    """Hanging: omega^2 = 2 -+ sqrt 2; one arm up: omega^4 = 2 (a frequency and a rate
    2^(1/4)); both up: rates sqrt(2 -+ sqrt 2); energies -3, -1, 1, 3."""
    _, items = _items(ROOT / "examples/double-pendulum.yaml")
    by_energy: dict[float, list] = {}
    for item in items:
        by_energy.setdefault(round(item["energy"], 9), []).append(item)
    assert sorted(by_energy) == [-3.0, -1.0, 1.0, 3.0]
    (hanging,) = by_energy[-3.0]
    assert hanging["type"] == "elliptic" and hanging["frequencies"] == pytest.approx(
        [math.sqrt(2 - math.sqrt(2)), math.sqrt(2 + math.sqrt(2))], rel=1e-12)
    for item in by_energy[-1.0] + by_energy[1.0]:
        assert item["type"] == "mixed" and item["index"] == 1
        assert item["frequencies"] == pytest.approx([2 ** 0.25], rel=1e-12)
        assert item["rates"] == pytest.approx([2 ** 0.25], rel=1e-12)
    for item in by_energy[3.0]:
        assert item["type"] == "hyperbolic" and item["rates"] == pytest.approx(
            [math.sqrt(2 - math.sqrt(2)), math.sqrt(2 + math.sqrt(2))], rel=1e-12)


BOX = {"x": [-1.2, 1.2], "y": [-1.2, 1.2], "px": [-1, 1], "py": [-1, 1]}


def test_a_python_function_as_the_hamiltonian():
    """H given in code (the API): the same equilibria and limits as the expression; ops
    gives the elementary functions; mixed terms are detected; errors become
    StepsafeError."""
    def henon_heiles(q, p, ops):
        x, y = q
        px, py = p
        return (px ** 2 + py ** 2) / 2 + (x ** 2 + y ** 2) / 2 + x ** 2 * y - y ** 3 / 3

    system = {"hamiltonian": henon_heiles, "q": ["x", "y"], "p": ["px", "py"], "box": BOX}
    report = stepsafe.advise("verlet", system=system)
    _, items = _items(HH)
    assert report.h_max == stepsafe.advise(scene=str(HH)).h_max
    mine = report.record["system"]["items"]
    assert [i["type"] for i in mine] == [i["type"] for i in items]
    assert np.allclose([i["x"] for i in mine], [i["x"] for i in items], atol=1e-12)

    def coupled(q, p, ops):
        return (p[0] ** 2 + p[1] ** 2) / 2 - ops.cos(q[0]) - 2 * ops.cos(q[1]) + \
            0.01 * q[0] * p[1]

    mixed = {"hamiltonian": coupled, "q": ["x", "y"], "p": ["px", "py"], "box": BOX}
    from stepsafe.systems.loader import read_many

    assert not read_many(mixed, "api")[0].separable
    assert read_many(system, "api")[0].separable
    assert stepsafe.measure(stepsafe.method("gauss", stages=2), [0.1], system=mixed,
                            time=1.0).rows[0].status == "ok"

    def broken(q, p, ops):
        return ops.nosuch(q[0]) + p[0] ** 2

    with pytest.raises(StepsafeError):
        stepsafe.advise("verlet", system={**system, "hamiltonian": broken})


def test_indexed_chains(tmp_path):
    """q[i] with sums over i: an FPU chain of N = 8 gives 2 sin(k pi / 18)."""
    text = (ROOT / "examples/fpu-alpha.yaml").read_text().replace(
        "{N: 4}", "{N: 8}").replace("  box:", "  starts: 24\n  box:")
    scene = tmp_path / "fpu8.yaml"
    scene.write_text(text)
    report, items = _items(scene)
    expected = [2 * math.sin(k * math.pi / 18) for k in range(1, 9)]
    assert items[0]["frequencies"] == pytest.approx(expected, rel=1e-12)
    assert items[0]["names"][:2] == ["q_1", "q_2"]
    assert report.h_max == pytest.approx(2 / expected[-1], rel=1e-12)


@pytest.mark.parametrize("change, key", [
    (('"q[0]": 0, ', ""), "system.hamiltonian"),  # q[0] neither a variable nor fixed
    (('"q[0]": 0', '"q[1]": 0'), "system.fixed.q[1]"),
    (('q: "q[1..N]"', 'q: "q[N..1]"'), "system.q"),
    (('q: "q[1..N]"', 'q: "q(1..N)"'), "system.q"),
    (("{N: 4}", "{N: -1}"), "system.sizes.N"),
    (("sum(i, 1, N, p[i]**2/2)", "sum(i, 1, N, sum(i, 1, 2, p[i]**2/2))"),
     "system.hamiltonian"),
    (("sum(i, 1, N, p[i]**2/2)", "sum(i, 1, N, p[i/2]**2/2)"), "system.hamiltonian"),
    (("sum(i, 1, N, p[i]**2/2)", "sum(i, 1, N, x[i]**2/2)"), "system.hamiltonian"),
    (("box: {q: [-0.5, 0.5], p: [-0.5, 0.5]}", "box: {q: [-0.5, 0.5]}"), "system.box"),
    (("{N: 4}", "{N: 40}"), "system.q"),
])
def test_bad_indexed_input(run, tmp_path, change, key):
    text = (ROOT / "examples/fpu-alpha.yaml").read_text()
    assert change[0] in text
    scene = tmp_path / "bad.yaml"
    scene.write_text(text.replace(change[0], change[1]))
    code, out, err = run("advise", str(scene))
    assert code == 2 and err.count("\n") == 1 and out == "", err
    assert f"bad.yaml::$.{key}" in err, err


def test_the_search_honours_the_time_budget(run):
    code, _, err = run("advise", str(ROOT / "examples/lagrange-points.yaml"), "-s", "2",
                       "--budget", "1e-6")
    assert code == 2 and "time budget" in err and "lagrange-points.yaml::$.system" in err


@pytest.mark.parametrize("a", [1e-100, 1e100])
def test_n_dof_limits_at_extreme_scales(a, tmp_path):
    """H = (px^2 + py^2)/2 + (a x)^2/2 + (2 a y)^2/2: Verlet's limit 2 / (2a) at any scale."""
    scene = tmp_path / "s.yaml"
    scene.write_text("method: verlet\nsystem:\n  hamiltonian: \"(px**2 + py**2)/2 + (a*x)**2/2"
                     " + (2*a*y)**2/2\"\n  q: [x, y]\n  p: [px, py]\n  parameters: {a: "
                     f"{a!r}}}\n  box: {{x: [-1, 1], y: [-1, 1], px: [-1, 1], py: [-1, 1]}}\n")
    report = stepsafe.advise(scene=str(scene))
    assert report.h_max == pytest.approx(1 / a, rel=1e-12)
    assert not stepsafe.check(h=1.0001 / a, scene=str(scene)).safe
