"""stepsafe measure: the engine against closed forms, the mpmath reference integrator of
tests/integrate.py and the solver model; the measured figures against an independent run."""

from __future__ import annotations

import json
import math

import mpmath as mp
import numpy as np
import pytest

from stepsafe import measure, method
from stepsafe.core.integrator import Engine
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.dynamics import hamiltonian_system, linear_system
from stepsafe.systems.nonlinear import parse_hamiltonian

PENDULUM = {"hamiltonian": "p**2/2 - cos(q)", "box": {"q": [-4, 4], "p": [-1, 1]}}


def _pendulum():
    return hamiltonian_system(parse_hamiltonian("p**2/2 - cos(q)"))


def _run(name, system, q, p, h, n, stages=None):
    engine = Engine(method(name, stages=stages).tableau, system)
    for _ in range(n):
        q, p = engine.step(q, p, h)
    return q, p, engine


@pytest.mark.parametrize("name, stages, order", [
    ("verlet", None, 2), ("yoshida4", None, 4), ("pefrl", None, 4), ("rk4", None, 4),
    ("gauss", 2, 4), ("lobatto3ab", 3, 4), ("midpoint", None, 2)])
def test_order_on_the_pendulum(name, stages, order):
    from scipy.integrate import solve_ivp

    T, q0 = 2.0, 1.0
    ref = solve_ivp(lambda t, y: [y[1], -math.sin(y[0])], (0, T), [q0, 0.0],
                    method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    errs = []
    for n in (20, 40):
        q, p, _ = _run(name, _pendulum(), np.array([[q0]]), np.array([[0.0]]), T / n, n,
                       stages)
        errs.append(math.hypot(q[0, 0] - ref[0], p[0, 0] - ref[1]))
    assert abs(math.log2(errs[0] / errs[1]) - order) < 0.3, errs


def test_vectorised_over_initial_conditions_and_against_mpmath():
    """Three starts at once give each start's own run; Verlet matches the 40-digit
    integrator of tests/integrate.py to rounding."""
    from integrate import integrate, mp_method

    starts = np.array([[0.3], [1.0], [2.5]])
    q, p, engine = _run("verlet", _pendulum(), starts, np.zeros((3, 1)), 0.1, 200)
    with mp.workdps(40):
        m = mp_method("verlet")
        for k in range(3):
            qr, pr = integrate(m, starts[k, 0], 0, 20, 200, lambda x: -mp.sin(x))
            assert q[k, 0] == pytest.approx(float(qr), abs=1e-12)
            assert p[k, 0] == pytest.approx(float(pr), abs=1e-12)
    assert engine.force_evaluations == 201  # first same as last: one per step, plus the first


def test_linear_systems_follow_the_transfer_matrices():
    """On x' = J S x the engine's n steps are M(h)^n x0 (the coupled module's one-step
    matrix, built independently of the engine)."""
    from stepsafe.systems.coupled import one_step_matrix

    rng = np.random.default_rng(2)
    n = 3
    B = rng.normal(size=(n, n))
    K = B @ B.T + np.eye(n)
    S = np.block([[K, np.zeros((n, n))], [np.zeros((n, n)), np.eye(n)]])
    system = linear_system(S)
    x0 = rng.normal(size=2 * n)
    for name, stages in (("yoshida4", None), ("gauss", 2), ("lobatto3ab", 3)):
        M = one_step_matrix(method(name, stages=stages).tableau, S, 0.05)
        q, p, _ = _run(name, system, x0[None, :n], x0[None, n:], 0.05, 30, stages)
        expected = np.linalg.matrix_power(M, 30) @ x0
        assert np.allclose(np.concatenate([q[0], p[0]]), expected, rtol=0, atol=1e-11)


@pytest.mark.parametrize("name, stages", [("gauss", 2), ("gauss", 3), ("lobatto3ab", 3)])
@pytest.mark.parametrize("z", [0.3, 1.0, 2.0])
def test_iterations_are_those_of_the_solver_model(name, stages, z):
    """On the oscillator (beta = 1) from the unit states, the engine's fixed-point
    iterations and force evaluations per step are the solver model's counts."""
    from stepsafe.core.solver import fixed_point_cost

    tableau = method(name, stages=stages).tableau
    cost = fixed_point_cost(tableau, z)
    S = np.eye(2)
    counts = []
    for x0 in ((1.0, 0.0), (0.0, 1.0)):
        engine = Engine(tableau, linear_system(S))
        engine.step(np.array([[x0[0]]]), np.array([[x0[1]]]), z)
        counts.append((engine.iterations, engine.force_evaluations))
    assert max(c[0] for c in counts) == cost.iterations
    worst = max(counts)
    assert worst[1] == cost.evaluations + (1 if name == "lobatto3ab" else 0)


@pytest.mark.parametrize("name, stages, order", [("verlet", None, 2), ("yoshida4", None, 4),
                                                  ("lobatto3ab", 3, 4), ("gauss", 2, 4)])
def test_order_on_a_non_separable_h(name, stages, order):
    """H = (1 + q^2) p^2 / 2 + q^2 / 2 mixes q and p: splittings run as their (implicit) PRK
    form of symplectic Euler factors and keep their order, as the PRKs do (a stage with
    Q_i = q still sees its own P_i)."""
    from scipy.integrate import solve_ivp

    system = hamiltonian_system(parse_hamiltonian("(1 + q**2)*p**2/2 + q**2/2"))
    assert not system.separable
    T, x0 = 2.0, (0.8, 0.3)
    ref = solve_ivp(lambda t, y: [(1 + y[0] ** 2) * y[1], -(y[0] * y[1] ** 2 + y[0])],
                    (0, T), x0, method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    errs = []
    for n in (20, 40):
        q, p, _ = _run(name, system, np.array([[x0[0]]]), np.array([[x0[1]]]), T / n, n,
                       stages)
        errs.append(math.hypot(q[0, 0] - ref[0], p[0, 0] - ref[1]))
    assert abs(math.log2(errs[0] / errs[1]) - order) < 0.3, errs
    with pytest.raises(ValueError, match="sums differ"):
        Engine(_unequal(), system)


def _unequal():
    from stepsafe.methods.tableaux import Splitting

    return Splitting([0.5, 0.5], [0.7], name="unequal")


def test_the_linear_bound_is_measured_on_the_oscillator():
    """Harmonic oscillator: the energy's spread over a long run, (max - min) / min, reaches
    the linear bound kappa - 1 (irrational rotation) from any start (kick-drift-kick
    Verlet conserves p^2 + (1 - h^2/4) q^2: kappa = 1 / (1 - h^2/4)). The trajectory error
    is the phase drift, as predicted."""
    h = 0.3
    system = {"stiffness": np.eye(1)}  # H = p^2/2 + q^2/2, the exact flow as reference
    other = measure("verlet", [h], system=system, initial=[1.0, 0.0], time=500.0)
    assert other.rows[0].energy_error == pytest.approx(1 / (1 - h * h / 4) - 1, rel=1e-6)
    report = measure("verlet", [h], system=system, initial=[0.0, 1.0], time=1000.0)
    row = report.rows[0]
    assert row.energy_ratio == pytest.approx(1.0, abs=2e-4)
    assert row.predicted_trajectory_error == 2.0  # more than half a turn out of phase
    short = measure("verlet", [h], system=system, initial=[0.0, 1.0], time=100.0).rows[0]
    theta = math.acos(1 - h * h / 2)
    drift = (theta / h - 1) * short.time
    assert short.predicted_trajectory_error == pytest.approx(2 * abs(math.sin(drift / 2)),
                                                             rel=1e-9)
    assert short.trajectory_ratio == pytest.approx(1.0, abs=5e-3)
    assert abs(row.energy_drift) < 1e-6  # bounded oscillation, no drift
    assert row.evaluations_per_time == pytest.approx((row.steps + 1) / row.time)


def test_small_amplitude_pendulum_approaches_the_linear_prediction():
    """The measured energy spread tends to the linear bound as the amplitude shrinks."""
    ratios = []
    for amplitude in (0.4, 0.1):
        report = measure("verlet", [0.2], system=PENDULUM, initial=[0.0, amplitude],
                         time=200.0)
        ratios.append(report.rows[0].energy_ratio)
    assert abs(ratios[1] - 1) < abs(ratios[0] - 1) and abs(ratios[1] - 1) < 0.01


def test_measured_figures_agree_with_an_independent_run():
    """The trajectory error measure reports is the distance between an independent
    40-digit Verlet run and a scipy reference (to 1e-6 relative)."""
    from integrate import integrate, mp_method
    from scipy.integrate import solve_ivp

    h, T = 0.25, 30.0
    report = measure("verlet", [h], system=PENDULUM, initial=[1.0, 0.0], time=T)
    n = report.rows[0].steps
    with mp.workdps(40):
        qr, pr = integrate(mp_method("verlet"), 1.0, 0, n * h, n, lambda x: -mp.sin(x))
    ref = solve_ivp(lambda t, y: [y[1], -math.sin(y[0])], (0, n * h), [1.0, 0.0],
                    method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    independent = math.hypot(float(qr) - ref[0], float(pr) - ref[1]) / math.hypot(*ref)
    assert report.rows[0].trajectory_error == pytest.approx(independent, rel=1e-6)


def test_an_unstable_step_and_a_failing_solver_are_reported():
    oscillator = {"hamiltonian": "p**2/2 + q**2/2", "box": {"q": [-1, 1], "p": [-1, 1]}}
    report = measure("verlet", [2.1], system=oscillator, initial=[0.1, 0.0], time=200.0)
    assert report.rows[0].status == "unstable" and report.rows[0].energy_error is None
    # the pendulum past z* = 2 stays finite (its force is bounded): measured, no prediction
    row = measure("verlet", [2.1], system=PENDULUM, initial=[0.4, 0.0], time=200.0).rows[0]
    assert row.status == "beyond z*" and row.energy_error > 1
    assert row.predicted_energy_error is None
    report = measure(method("gauss", stages=2), [3.6], system=PENDULUM, initial=[0.1, 0.0],
                     time=20.0)
    assert report.rows[0].status == "solver failed"


def test_linear_scene_from_a_stiffness(tmp_path):
    scene = tmp_path / "chain.yaml"
    scene.write_text("method: verlet\nsystem:\n  stiffness: [[2, -1, 0], [-1, 2, -1], "
                     "[0, -1, 2]]\n")
    report = measure("verlet", [0.1, 0.5], scene=str(scene), time=50.0)
    assert report.beta == pytest.approx(math.sqrt(2 + math.sqrt(2)), rel=1e-12)
    assert all(r.status == "ok" for r in report.rows)
    assert report.rows[1].energy_error > report.rows[0].energy_error


def test_cli(run, tmp_path):
    code, out, err = run("measure", "examples/pendulum.yaml", "--h", "0.1", "--h", "2.1",
                         "--time", "50")
    assert code == 0, err
    assert "beyond z*" in out and "energy err" in out
    code, out, err = run("measure", "examples/pendulum.yaml", "--method", "gauss", "-s", "2",
                         "--h-range", "0.1,1,3", "--time", "20", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert [r["h"] for r in data["rows"]] == pytest.approx([0.1, 10 ** -0.5, 1.0])
    assert all(r["iterations_per_step"] > 1 for r in data["rows"])
    code, out, _ = run("measure", "examples/pendulum.yaml", "--h", "0.5", "--time", "20",
                       "--tsv")
    assert code == 0 and out.splitlines()[0].startswith("h\tsteps")


@pytest.mark.parametrize("args", [
    ("--h", "-1"), ("--h-range", "1,0.1,3"), ("--h-range", "0.1,1,1000"),
    ("--h-range", "a,b,c"), ("--h", "0.1", "--initial", "1,2,3"),
    ("--h", "0.1", "--initial", "1,2", "--energy", "1"),
    ("--h", "0.1", "--energy", "-5"), ("--h", "1e-9", "--time", "100"),
    ("--h", "0.1", "--method", "respa-verlet"), ("--h", "0.1", "--time", "0"),
    ("--h", "0.1", "--json", "--tsv"),
])
def test_bad_input(run, args):
    code, out, err = run("measure", "examples/pendulum.yaml", *args)
    assert code == 2 and err.count("\n") == 1 and out == "", (args, err)


def test_scenes_without_a_system_are_refused(run, tmp_path):
    scene = tmp_path / "modes.yaml"
    scene.write_text("method: verlet\nmodes:\n  - {beta: 1}\n")
    code, _, err = run("measure", str(scene), "--h", "0.1")
    assert code == 2 and "modes.yaml" in err


def test_work_precision_plot(run, tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "wp.png"
    code, out, err = run("plot", "--work-precision", "examples/pendulum.yaml", "--methods",
                         "verlet,gauss:2", "--h-range", "0.2,1,3", "--time", "20", "-o",
                         str(png))
    assert code == 0 and png.read_bytes()[:4] == b"\x89PNG", err
    for args in (("plot",), ("plot", "verlet", "--work-precision", "examples/pendulum.yaml"),
                 ("plot", "--work-precision", "examples/pendulum.yaml", "--methods", "verlet",
                  "--budget", "-1"),
                 ("plot", "--work-precision", "examples/pendulum.yaml"),
                 ("plot", "--work-precision", "examples/pendulum.yaml", "--methods", ",",
                  "--h-range", "0.1,1,2")):
        code, _, err = run(*args)
        assert code == 2 and err.count("\n") == 1, (args, err)


def test_refinement_finds_the_measured_step():
    """On the oscillator the measured energy spread is the linear bound, so the refined h
    is the predicted one; on the pendulum the refined h meets the tolerance and twice it
    (or the next run up) does not."""
    from stepsafe import refine

    oscillator = {"stiffness": np.eye(1)}
    r = refine("verlet", "energy", 1e-3, system=oscillator, initial=[0.0, 1.0], time=200.0)
    assert r.limited_by == "tolerance" and r.h == pytest.approx(r.predicted, rel=3e-3)
    r = refine("pefrl", "trajectory", 1e-4, system=PENDULUM, initial=[0.0, 1.0], time=15.0)
    assert r.error <= 1e-4 and r.limited_by == "tolerance"
    above = [row for row in r.runs.rows if row.h > r.h]
    assert above and all(row.trajectory_error > 1e-4 for row in above
                         if row.h >= r.h * (1 + 1e-3))
    loose = refine("verlet", "energy", 1e3, system=PENDULUM, initial=[0.0, 0.5], time=10.0)
    assert loose.limited_by == "safety" and loose.h == pytest.approx(2.0, rel=1e-6)


def test_refinement_on_the_command_line(run):
    code, out, err = run("measure", "examples/pendulum.yaml", "--tol-energy", "1e-3",
                         "--time", "8", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["quantity"] == "energy" and data["h"] and data["runs"]["rows"]
    code, out, _ = run("measure", "examples/pendulum.yaml", "--tol-energy", "1e-3",
                       "--time", "8")
    assert "Measured: h = " in out and "predicted h = " in out
    for extra in (("--tol-energy", "1e-3", "--tol-trajectory", "1e-3"),
                  ("--tol-energy", "1e-3", "--h", "0.1"), ("--tol-energy", "-1")):
        code, _, err = run("measure", "examples/pendulum.yaml", *extra)
        assert code == 2 and err.count("\n") == 1, (extra, err)


@pytest.mark.parametrize("name, stages", [("gauss", 2), ("gauss", 3), ("lobatto3ab", 3),
                                          ("midpoint", None)])
@pytest.mark.parametrize("z", [0.3, 3.0, 10.0])
def test_newton_counts_are_those_of_the_solver_model(name, stages, z):
    """Simplified Newton on the oscillator: 2 passes at every z (also beyond fixed-point
    iteration's limit), the model's force evaluations, one Jacobian per step, and the same
    step as the exact one-step matrix."""
    from stepsafe.core.solver import NEWTON_ITERATIONS, newton_cost
    from stepsafe.core.transfer import transfer_matrix

    tableau = method(name, stages=stages).tableau
    engine = Engine(tableau, linear_system(np.eye(2)), solver="newton")
    q, p = engine.step(np.array([[1.0]]), np.array([[0.0]]), z)
    cost = newton_cost(tableau, z)
    assert engine.iterations == NEWTON_ITERATIONS == cost.iterations
    first_step = 1 if name == "lobatto3ab" else 0  # its fixed stage is reused afterwards
    assert engine.force_evaluations == cost.evaluations + first_step
    assert engine.jacobians == 1
    M = transfer_matrix(tableau, [z], "oscillator")[0]
    assert np.allclose([q[0, 0], p[0, 0]], M[:, 0], rtol=0, atol=1e-12)


def test_newton_on_the_pendulum_and_in_compare(run):
    from scipy.integrate import solve_ivp

    T = 2.0
    ref = solve_ivp(lambda t, y: [y[1], -math.sin(y[0])], (0, T), [1.0, 0.0],
                    method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]
    errs = []
    for n in (20, 40):
        engine = Engine(method("gauss", stages=2).tableau, _pendulum(), solver="newton")
        q, p = np.array([[1.0]]), np.array([[0.0]])
        for _ in range(n):
            q, p = engine.step(q, p, T / n)
        errs.append(math.hypot(q[0, 0] - ref[0], p[0, 0] - ref[1]))
    assert abs(math.log2(errs[0] / errs[1]) - 4) < 0.3
    code, out, err = run("compare", "--beta", "1", "--tol-phase", "1e-6", "--methods",
                         "pefrl,gauss:2", "--solver", "newton", "--json")
    assert code == 0, err
    rows = {r["method"]: r for r in json.loads(out)["methods"]}
    assert rows["gauss-s2"]["evaluations"] == 6  # 2 stages x (2 passes + the update)
    code, out, _ = run("measure", "examples/pendulum.yaml", "--method", "gauss", "-s", "2",
                       "--h", "3", "--time", "30", "--solver", "newton", "--json")
    assert json.loads(out)["rows"][0]["status"] == "ok"


def test_advise_counts_the_solver_asked_for(run):
    counts = {}
    for solver in ("fixed-point", "newton", "nominal"):
        code, out, err = run("advise", "--method", "gauss", "-s", "2", "--beta", "1",
                             "--tol-phase", "1e-6", "--solver", solver, "--json")
        assert code == 0, err
        counts[solver] = json.loads(out)["evaluations"]
    assert counts == {"fixed-point": 14, "newton": 6, "nominal": 2}


def test_check_names_the_solver_limit(run):
    """Midpoint keeps every oscillator's structure, but fixed-point iteration of its stage
    converges only for beta h < 2: check fails there and says why, unless Newton."""
    code, out, _ = run("check", "--method", "midpoint", "--beta", "1", "--step", "3")
    assert code == 1 and "fixed-point iteration" in out and "h < 2" in out
    assert run("check", "--method", "midpoint", "--beta", "1", "--step", "1.99")[0] == 0
    assert run("check", "--method", "midpoint", "--beta", "1", "--step", "3", "--solver",
               "newton")[0] == 0
    import stepsafe

    report = stepsafe.check("midpoint", 3.0, [1.0])
    assert not report.safe and "fixed-point" in report.record["solver_failure"]
    assert stepsafe.check("midpoint", 3.0, [1.0], solver="newton").safe


def test_budgets(run):
    code, out, err = run("measure", "examples/pendulum.yaml", "--h", "0.1", "--time", "50",
                         "--budget", "1e-9", "--json")
    assert code == 2 and "budget" in err  # not even the reference run fits
    code, _, err = run("measure", "examples/pendulum.yaml", "--h", "1e6")
    assert code == 2 and "longer than the run" in err
    code, _, err = run("measure", "examples/pendulum.yaml", "--h", "0.1", "--time", "50",
                       "--max-steps", "100")
    assert code == 2 and "100" in err
    report = measure("verlet", [1e-4], system={"stiffness": np.eye(1)}, time=1000.0,
                     budget=0.3, max_steps=10_000_000)
    assert report.rows[0].status == "budget" and report.rows[0].energy_error is None


@pytest.mark.parametrize("system", [
    "{stiffness: [[4]]}",
    '{hamiltonian: "p**2/2 + 4*q**2/2", box: {q: [-1, 1], p: [-1, 1]}}',
    '{hamiltonian: "(px**2 + py**2)/2 + 2*x**2 + y**2/2 + 0.1*x*py", q: [x, y], '
    "p: [px, py], box: {x: [-1, 1], y: [-1, 1], px: [-1, 1], py: [-1, 1]}}",
])
def test_system_scenes_apply_the_solver_limit(run, tmp_path, system):
    """Midpoint at omega = 2: fixed-point iteration converges only for h < 1 (about 1 for
    the coupled one), whatever the form of the scene."""
    scene = tmp_path / "s.yaml"
    scene.write_text(f"method: midpoint\nsystem: {system}\n")
    code, out, _ = run("check", str(scene), "--step", "1.5")
    assert code == 1 and "fixed-point iteration" in out
    assert run("check", str(scene), "--step", "1.5", "--solver", "newton")[0] == 0
    assert run("check", str(scene), "--step", "0.9")[0] == 0
    code, out, _ = run("advise", str(scene), "--json")
    assert 0.9 < json.loads(out)["fixed_point_limit"] < 1.1


def test_trajectory_error_in_the_energy_norm():
    """omega = 2 (not 1): the measured trajectory error equals the predicted phase chord
    (the energy norm makes the orbit a circle), and no ratio once half a turn is lost."""
    row = measure(method("gauss", stages=2), [0.466731], system={"stiffness": 4 * np.eye(1)},
                  time=100.0, initial=[1.0, 0.0], solver="newton").rows[0]
    assert row.trajectory_ratio == pytest.approx(1.0, abs=1e-3)
    wrapped = measure(method("gauss", stages=2), [1.5], system={"stiffness": 4 * np.eye(1)},
                      time=100.0, initial=[1.0, 0.0], solver="newton").rows[0]
    assert wrapped.predicted_trajectory_error == 2.0 and wrapped.trajectory_ratio is None


def test_kepler_without_an_equilibrium(run, tmp_path):
    """The planar Kepler problem has no equilibrium: measured from --initial, the energy
    spread over |H(0)|, no prediction; the work-precision plot takes --initial too."""
    scene = tmp_path / "kepler.yaml"
    scene.write_text("method: verlet\nsystem:\n  hamiltonian: \"(px**2 + py**2)/2 - "
                     "1/sqrt(x**2 + y**2)\"\n  q: [x, y]\n  p: [px, py]\n  box: {x: [0.5, 1.5], "
                     "y: [-0.5, 0.5], px: [-0.5, 0.5], py: [0.5, 1.5]}\n")
    report = measure("yoshida4", [0.05, 0.1], scene=str(scene), time=20.0,
                     initial=[1.0, 0.0, 0.0, 1.2])
    assert report.beta is None and all(r.predicted_energy_error is None for r in report.rows)
    small, large = report.rows
    assert 0 < small.energy_error < large.energy_error
    assert large.energy_error / small.energy_error == pytest.approx(16, rel=0.25)
    pytest.importorskip("matplotlib")
    png = tmp_path / "k.png"
    code, _, err = run("plot", "--work-precision", str(scene), "--methods", "verlet",
                       "--h-range", "0.05,0.1,2", "--time", "10", "--initial", "1,0,0,1.2",
                       "-o", str(png))
    assert code == 0 and png.exists(), err


def _builtin_splittings():
    from stepsafe.methods.library import builtin_names, resolve

    out = []
    for name in builtin_names():
        try:
            m, entry = resolve(name)
        except StepsafeError:
            continue  # a family (needs a stage count)
        if m.hamiltonian and (m.forces_per_step is not None or entry.evaluations is not None):
            out.append(name)
    return out


@pytest.mark.parametrize("name", _builtin_splittings())
def test_every_stated_evaluation_count_is_what_the_engine_makes_per_step(name):
    """A method file's ``evaluations:`` (what compare, hmc and the cost model use) equals
    the forces the engine evaluates per step, measured as the difference between 40 and 20
    steps on the pendulum (a processor's one-off forces cancel); and equals what
    ``stepsafe validate`` derives from the coefficients."""
    from stepsafe.methods.library import resolve

    m, entry = resolve(name)
    counts = []
    for n in (20, 40):
        engine = Engine(m, _pendulum())
        q, p = engine.start(np.array([[0.5]]), np.array([[0.0]]), 0.1)
        for _ in range(n):
            q, p = engine.step(q, p, 0.1)
        counts.append(engine.force_evaluations)
    if not m.kind == "rk":  # (an RK's implicit solve counts iterations, not stages)
        assert (counts[1] - counts[0]) / 20 == entry.evaluations
    natural = m.forces_per_step
    assert natural is None or natural == entry.evaluations


def _verlet_energies(h, q, p, n):
    """The energy ``(q^2 + p^2) / 2`` after each of n kick-drift-kick steps (and at the
    start) on the oscillator ``H = (q^2 + p^2) / 2``: a plain float loop, independent of
    the engine."""
    out = np.empty(n + 1)
    out[0] = 0.5 * (q * q + p * p)
    for k in range(1, n + 1):
        p -= 0.5 * h * q
        q += h * p
        p -= 0.5 * h * q
        out[k] = 0.5 * (q * q + p * p)
    return out


def test_energy_spread_is_the_extreme_over_every_step_when_the_orbit_repeats():
    """At h = 1 Verlet turns the oscillator's state by exactly pi/3 per step (cos theta =
    1 - h^2/2 = 1/2): the orbit repeats every 6 steps, with energies 1/8, 13/128, 13/128
    from (0.5, 0) (exact in rationals), so the spread over every step is exactly
    (1/8 - 13/128) / (13/128) = 3/13; any fixed subset of the 6 phases misses it (every
    third step sees 1/8 alone)."""
    from fractions import Fraction

    q, p, energies = Fraction(1, 2), Fraction(0), []
    for _ in range(6):
        energies.append((q * q + p * p) / 2)
        p -= q / 2
        q += p
        p -= q / 2
    assert (q, p) == (Fraction(1, 2), 0)  # period 6
    exact = (max(energies) - min(energies)) / min(energies)
    assert exact == Fraction(3, 13)
    row = measure("verlet", [1.0], system={"hessian": np.eye(2)}, initial=[0.5, 0.0],
                  time=60000.0).rows[0]
    assert row.steps == 60000 and row.status == "ok"
    assert row.energy_error == pytest.approx(float(exact), rel=1e-12)


def test_energy_spread_and_drift_are_those_of_every_step_near_a_resonant_stride():
    """z = 1.414224669 (theta within 1e-5 of pi/2): every other step sees nearly one
    energy, so a sample of every other step misses the spread (kappa - 1 = 1.000 here);
    the spread and the least-squares drift through every one of the 40001 steps are those
    of an independent float loop and numpy's fit of every step."""
    h, T = 1.414224669, 56570.0
    row = measure("verlet", [h], system={"hessian": np.eye(2)}, initial=[0.5, 0.0],
                  time=T).rows[0]
    n = row.steps
    assert n == math.ceil(T / h * (1 - 1e-12)) and row.status == "ok"
    e = _verlet_energies(h, 0.5, 0.0, n)
    assert row.energy_error == pytest.approx((e.max() - e.min()) / e.min(), rel=1e-9)
    assert row.energy_error == pytest.approx(1 / (1 - h * h / 4) - 1, rel=1e-3)
    slope = np.polyfit(h * np.arange(n + 1), (e - e[0]) / e[0], 1)[0]
    assert row.energy_drift == pytest.approx(slope, rel=1e-6, abs=1e-15)


def test_drift_is_the_fit_through_every_step_when_a_stride_would_beat():
    """theta = (pi + eps) / 3 with eps = pi / 40000: three steps turn the state by pi + eps,
    so the state every third step drifts through a quarter turn over the 60000 steps and
    its energies fall steadily from the largest to the smallest: a fit through them shows
    a drift of about -spread / T where the energy only oscillates. The drift reported is
    numpy's least-squares slope through every step of an independent float loop."""
    n = 60000
    theta = (math.pi + math.pi / 2 / (n / 3)) / 3
    h = math.sqrt(2 - 2 * math.cos(theta))  # Verlet: cos theta = 1 - h^2 / 2
    row = measure("verlet", [h], system={"hessian": np.eye(2)}, initial=[0.5, 0.0],
                  time=n * h).rows[0]
    assert row.steps == n and row.status == "ok"
    e = _verlet_energies(h, 0.5, 0.0, n)
    err = (e - e[0]) / e[0]
    slope = np.polyfit(h * np.arange(n + 1), err, 1)[0]
    strided = np.polyfit(h * np.arange(0, n + 1, 3), err[::3], 1)[0]
    assert abs(strided) > 1e3 * abs(slope)  # the beat a stride of 3 would fit
    assert row.energy_drift == pytest.approx(slope, rel=1e-6, abs=1e-15)
    assert row.energy_error == pytest.approx((e.max() - e.min()) / e.min(), rel=1e-9)
