"""Processed methods psi = P^-1 K P: region from the kernel, error from the full map.

* On the oscillator the one-step matrix is similar to the kernel's (det P = 1): the region
  the finder reports is the kernel's, and the full map's trace equals the kernel's at 50
  digits; the stated threshold is that of the full map's tr M = 2, found at 50 digits.
* The published coefficients (Blanes, Casas & Ros 2000, orders (7,6,4)) are checked by
  what they promise on real nonlinear integrations at 50 digits: order 4 on the pendulum
  (the kernel alone: 2), order 7 on a weakly perturbed problem H = p^2/2 - eps cos q.
* The measurement engine runs P once, the kernel per step and P^-1 at the output: order 4
  measured, smaller errors than the kernel alone, processor evaluations counted once.
* HMC: the energy error of L steps is that of (P^-1 M_K P)^L at 50 digits, and the
  predicted acceptance matches a numpy HMC run of x -> P^-1 K^L P x on a Gaussian.
"""

from __future__ import annotations

import json

import mpmath as mp
import numpy as np
import pytest
from integrate import integrate, mp_method

import stepsafe
from stepsafe import hmc, measure
from stepsafe.core import hmc as H
from stepsafe.core.accuracy import errors, kernel_errors
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import transfer_matrix
from stepsafe.exceptions import StepsafeError
from stepsafe.files.yamlio import load_yaml
from stepsafe.methods.fileformat import json_schema
from stepsafe.methods.library import builtin_dir, resolve
from stepsafe.reference.verify import mp_transfer

NAME = "blanes-casas-ros764"
PENDULUM = {"hamiltonian": "p**2/2 - cos(q)", "box": {"q": [-4, 4], "p": [-2, 2]}}


def _trace(M):
    return M[0, 0] + M[1, 1]


def test_the_region_is_the_kernels_and_the_full_map_has_its_trace():
    method, _ = resolve(NAME)
    full, kernel = find_region(method, "oscillator", 10.0), find_region(method.kernel, "oscillator",
                                                                       10.0)
    assert [(iv.lo, iv.hi) for iv in full.intervals] == \
        [(iv.lo, iv.hi) for iv in kernel.intervals]
    z = np.linspace(0.05, 6.0, 40)
    M_full, M_kernel = transfer_matrix(method, z), transfer_matrix(method.kernel, z)
    # equal up to the rounding of the products (the full map's entries grow to 1e8 where
    # the kernel's are 1e3: the similarity transform is ill-conditioned far out)
    rounding = 64 * np.finfo(float).eps * np.abs(M_full).sum(axis=(1, 2))
    assert np.all(np.abs(np.trace(M_full, axis1=1, axis2=2)
                         - np.trace(M_kernel, axis1=1, axis2=2)) <= rounding)
    assert not np.allclose(M_full, M_kernel, atol=1e-3)  # a different map all the same
    with mp.workdps(50):
        m = mp_method(NAME, None, None, 50)
        F, K = mp_transfer(m), mp_transfer(m.data["kernel"])
        for zz in ("0.3", "1.1", "2.5", "4.75"):
            a = F(mp.mpf(zz), "oscillator")
            b = K(mp.mpf(zz), "oscillator")
            size = 1 + sum(abs(a[i, j]) for i in range(2) for j in range(2))
            assert abs(_trace(a) - _trace(b)) < mp.mpf(10) ** -45 * size
            assert abs(mp.det(a) - 1) < mp.mpf(10) ** -45 * size ** 2


@pytest.mark.parametrize("model", ["saddle", "saddle-p", "inverted"])
def test_hyperbolic_models_keep_the_kernels_boundaries(model):
    """Diagonal models: drifts and kicks are diagonal, P commutes with K. The barrier
    (inverted) is analysed on the full map (its orientation compares eigenvectors), with
    the kernel's trace boundaries all the same."""
    method, _ = resolve(NAME)
    full, kernel = find_region(method, model, 10.0), find_region(method.kernel, model, 10.0)
    assert len(full.intervals) == len(kernel.intervals) >= 1
    for a, b in zip(full.intervals, kernel.intervals):
        assert a.lo == pytest.approx(b.lo, abs=1e-12) and a.hi == pytest.approx(b.hi, rel=1e-12)


def test_stated_threshold_is_the_full_maps_at_50_digits():
    stated = load_yaml(builtin_dir() / f"{NAME}.yaml")["thresholds"]
    with mp.workdps(50):
        F = mp_transfer(mp_method(NAME, None, None, 50))
        root = mp.findroot(lambda z: _trace(F(z, "oscillator")) - 2, mp.mpf(stated["structure"]))
        slope = mp.diff(lambda z: _trace(F(z, "oscillator")), root)
        assert abs(root - mp.mpf(stated["structure"])) < mp.mpf("5e-9")
        assert slope > 1  # a crossing: |tr M| > 2 beyond it
        # inside: |tr M| < 2 on a fine grid up to the root
        assert all(abs(_trace(F(z, "oscillator"))) < 2 for z in mp.linspace(0.01, root - 1e-6,
                                                                              200))
    region = find_region(resolve(NAME)[0], "oscillator", 10.0)
    assert abs(region.first_boundary - float(root)) < 1e-9


@pytest.fixture(scope="module")
def pendulum_reference():
    with mp.workdps(45):
        sol = mp.odefun(lambda t, y: [y[1], -mp.sin(y[0])], 0, [mp.mpf(1), mp.mpf("0.5")])
        return sol(1)


def _error(m, n, T, reference, force):
    q, p = integrate(m, 1, "0.5", T, n, force)
    return mp.sqrt((q - reference[0]) ** 2 + (p - reference[1]) ** 2)


def test_order_4_processed_and_2_for_the_kernel_alone(pendulum_reference):
    with mp.workdps(40):
        m = mp_method(NAME, None, None, 40)
        force = lambda q: -mp.sin(q)  # noqa: E731
        for method, order in ((m, 4), (m.data["kernel"], 2)):
            e = [_error(method, n, 1, pendulum_reference, force) for n in (32, 64)]
            assert abs(float(mp.log(e[0] / e[1], 2)) - order) < 0.1, (order, e)
        # the processed error is far below the kernel's at the same step
        assert _error(m, 32, 1, pendulum_reference, force) < \
            1e-3 * _error(m.data["kernel"], 32, 1, pendulum_reference, force)


def test_orders_7_6_4_on_a_near_integrable_problem():
    """H = p^2/2 - eps cos q with eps = 1e-4: the error eps h^7 dominates, so the observed
    order is 7 (drift = the integrable part A, kick = the perturbation eps B)."""
    eps = mp.mpf("1e-4")
    with mp.workdps(36):
        ref = mp.odefun(lambda t, y: [y[1], -eps * mp.sin(y[0])], 0,
                        [mp.mpf(1), mp.mpf("0.5")])(2)
    with mp.workdps(32):
        m = mp_method(NAME, None, None, 32)
        e = [_error(m, n, 2, ref, lambda q: -eps * mp.sin(q)) for n in (2, 4)]
        assert 6.8 < float(mp.log(e[0] / e[1], 2)) < 7.5


def test_processor_changes_the_energy_error_not_the_phase():
    method, _ = resolve(NAME)
    z = np.array([0.05, 0.3, 1.0])
    processed, kernel = errors(method, z), kernel_errors(method, z)
    assert np.array_equal(processed.phase, kernel.phase)
    assert np.all(processed.energy < 0.2 * kernel.energy)
    # order 4 and 2 in z of the energy error bounds
    assert 3.8 < np.log(processed.energy[1] / processed.energy[0]) / np.log(6) < 4.2
    assert 1.8 < np.log(kernel.energy[1] / kernel.energy[0]) / np.log(6) < 2.2
    assert kernel_errors(resolve("verlet")[0], z) is None


def test_energy_error_bound_is_the_full_maps_at_50_digits():
    """kappa - 1 of P^-1 K P from the file's decimals at 50 digits, from z = 1e-3 up (below,
    the decimals' own rounding, ~1e-17, is the larger part): the float figure is the series
    of the ideal method, never a reference of its rounded coefficients."""
    method, _ = resolve(NAME)
    zs = [1e-3, 1e-2, 0.1, 0.5, 1.0]
    got = errors(method, np.array(zs)).energy
    with mp.workdps(50):
        F = mp_transfer(mp_method(NAME, None, None, 50))
        for z, value in zip(zs, got):
            M = F(mp.mpf(z), "oscillator")
            a, b, c, d = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
            spread = mp.sqrt((b + c) ** 2 + (a - d) ** 2)
            truth = spread / ((b - c - spread) / 2)
            assert abs(value / truth - 1) < 1e-4, (z, value, truth)


def test_the_engine_runs_P_once_the_kernel_per_step_and_P_inverse_at_the_output(tmp_path):
    kernel = tmp_path / "kernel.yaml"
    k = resolve(NAME)[0].kernel
    kernel.write_text(
        "name: kernel764\nkind: splitting\norder: 2\nevaluations: 3\nsource: test\n"
        f"drift: {json.dumps([repr(float(x)) for x in k.drift])}\n"
        f"kick: {json.dumps([repr(float(x)) for x in k.kick])}\n")
    hs = [0.2, 0.1]
    T = 10.0
    rows = measure(NAME, hs, system=PENDULUM, initial=[1.0, 0.5], time=T).rows
    alone = measure(str(kernel), hs, system=PENDULUM, initial=[1.0, 0.5], time=T).rows
    assert all(r.status == "ok" for r in rows + alone)
    order = np.log2(rows[0].trajectory_error / rows[1].trajectory_error)
    assert 3.7 < order < 4.5
    assert all(r.trajectory_error < 0.05 * a.trajectory_error for r, a in zip(rows, alone))
    # 3 per kernel step, plus 6 for P and 6 for the final P^-1 (energy samples not counted)
    for r, h in zip(rows, hs):
        assert r.evaluations_per_time == pytest.approx((3 * round(T / h) + 12) / T)


def test_energy_error_of_L_steps_is_that_of_the_processed_trajectory_at_50_digits():
    method, _ = resolve(NAME)
    with mp.workdps(50):
        F = mp_transfer(mp_method(NAME, None, None, 50))
        for z in (0.2, 1.0, 1.9):
            M = F(mp.mpf(z), "oscillator")
            for L in (1, 3, 20):
                P = M ** L
                ref = (sum(P[i, j] ** 2 for i in range(2) for j in range(2)) - 2) / 2
                got = H.energy_errors(method, [z], L)[0]
                assert abs(got - float(ref)) <= 1e-8 * float(abs(ref)) + 1e-14, (z, L)


def _hmc_run(integrator, precision, h, L, chains, iterations, rng):
    """Measured acceptance of x -> P^-1 K^L P x on N(0, diag(precision)^-1)."""
    pre = integrator.processor
    post = tuple((kind, -c) for kind, c in reversed(pre))
    kernel = integrator.operations

    def run(ops, q, p):
        for kind, c in ops:
            if kind == "drift":
                q = q + c * h * p
            else:
                p = p - c * h * q * precision
        return q, p

    def energy(q, p):
        return 0.5 * (q * q * precision).sum(axis=1) + 0.5 * (p * p).sum(axis=1)

    q = rng.standard_normal((chains, precision.size)) / np.sqrt(precision)
    accepted = []
    for _ in range(iterations):
        p = rng.standard_normal((chains, precision.size))
        qn, pn = run(pre, q, p)
        for _ in range(L):
            qn, pn = run(kernel, qn, pn)
        qn, pn = run(post, qn, pn)
        prob = np.minimum(1.0, np.exp(np.minimum(energy(q, p) - energy(qn, pn), 0.0)))
        q = np.where((rng.random(chains) < prob)[:, None], qn, q)
        accepted.append(prob)
    per_chain = np.mean(accepted, axis=0)
    return per_chain.mean(), per_chain.std(ddof=1) / np.sqrt(chains)


def test_measured_hmc_acceptance_matches_the_prediction():
    sigmas = np.linspace(0.5, 1.0, 40)
    h, L = 1.05, 6
    row = hmc([NAME], sigma=list(sigmas), trajectory_steps=L, step=h).rows[0]
    predicted = row.at_step["acceptance"]
    measured, se = _hmc_run(stepsafe.method(NAME), 1.0 / sigmas ** 2, h, L, 64, 120,
                            np.random.default_rng(7))
    assert 0.05 < predicted < 0.99
    assert abs(measured - predicted) < 4 * se, (measured, predicted, se)
    # the processor's two passes are paid once per proposal; the proposal is not reversible
    assert row.at_step["gradients_per_proposal"] == L * 3 + 2 * 6
    assert not row.symmetric


def test_show_compare_and_the_file_report_the_processor(run_json):
    shown = run_json("show", NAME, "--json")
    assert shown["processor_evaluations"] == {"start": 6, "per_output": 6}
    assert shown["coefficients"]["processor"]["kick"][-1] == -0.5
    compared = run_json("compare", "--beta", "1", "--tol-energy", "1e-6", "--methods",
                        f"verlet,{NAME}", "--json")
    rows = {r["method"]: r for r in compared["methods"]}
    assert rows[NAME]["processor_evaluations"] == {"start": 6, "per_output": 6}
    assert rows[NAME]["evaluations"] == 3 and "processor_evaluations" not in rows["verlet"]
    table = run_json("error", NAME, "--z", "0.3", "--json")["rows"][0]
    assert table["kernel_energy_error"] > 10 * table["energy_error"]


BASE = ("name: p\nkind: processed\norder: 2\nevaluations: 1\nsource: test\n")


@pytest.mark.parametrize("body, key, message", [
    ("kernel: verlet\nprocessor: {drift: [0.1], kick: [x]}\n", "processor.kick[0]",
     "unknown name"),
    ("kernel: verlet\nprocessor: {drift: [0.1]}\n", "processor.kick", "missing"),
    ("kernel: verlet\nprocessor: {drift: [0.1, 1, 2], kick: [1]}\n", "processor.drift",
     "as many as kick"),
    ("kernel: {drift: [1], kick: [1], speed: 2}\nprocessor: {drift: [0.1], kick: [0]}\n",
     "kernel.speed", "unknown key"),
    ("kernel: no-such-method\nprocessor: {drift: [0.1], kick: [0]}\n", "kernel",
     "unknown method"),
    ("kernel: gauss\nprocessor: {drift: [0.1], kick: [0]}\n", "kernel", "family"),
    ("kernel: verlet\nprocessor: {drift: [0.1], kick: [0]}\nweights: [1]\n", "weights",
     "does not apply"),
    ("processor: {drift: [0.1], kick: [0]}\n", "kernel", "missing"),
])
def test_bad_processed_files_name_file_and_key(tmp_path, body, key, message):
    path = tmp_path / "p.yaml"
    path.write_text(BASE + body)
    with pytest.raises(StepsafeError) as err:
        resolve(str(path))
    assert err.value.where == f"{path}::$.{key}", err.value.where
    assert message in err.value.message.lower()


def test_a_kernel_that_is_not_a_splitting_is_refused(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(BASE + "kernel: rk4\nprocessor: {drift: [0.1], kick: [0]}\n")
    with pytest.raises(StepsafeError, match="kernel of a processed method must be a splitting"):
        resolve(str(path))


def test_inline_kernel_and_processor_reference(tmp_path):
    """An inline symmetric kernel equals the referenced one; the processor may name a
    splitting file."""
    path = tmp_path / "p.yaml"
    path.write_text(BASE + "kernel: {symmetric: true, drift: [0, 1], kick: ['1/2']}"
                    "\nprocessor: symplectic-euler\n")
    method, _ = resolve(str(path))
    assert method.kernel_splitting.operations == resolve("verlet")[0].operations
    assert method.processor_operations == resolve("symplectic-euler")[0].operations


def test_schema_describes_kernel_and_processor():
    schema = json_schema()
    assert "processed" in schema["properties"]["kind"]["enum"]
    assert {"kernel", "processor"} <= set(schema["properties"])
    branch = next(b for b in schema["allOf"]
                  if b["if"]["properties"]["kind"]["const"] == "processed")
    assert set(branch["then"]["required"]) >= {"kernel", "processor"}


def test_the_processed_proposal_is_not_reversible_and_the_report_says_so():
    """With the momentum flip S, S o (P^-1 K^L P) is an involution only if S P S = P: on the
    pendulum (50 digits) bcr764's proposal misses it by 6e-5, far above rounding, while the
    kernel alone and P* K^L P (P* = S P^-1 S, the processor's adjoint) keep it to rounding;
    `hmc` notes it."""
    integrator = stepsafe.method(NAME)
    pre = integrator.processor
    post = tuple((kind, -c) for kind, c in reversed(pre))  # P^-1
    adjoint = tuple(reversed(pre))  # S P^-1 S: P's operations in reverse order
    kernel = integrator.operations
    h, L = mp.mpf("0.4"), 7

    def run(ops, q, p):
        for kind, c in ops:
            if kind == "drift":
                q = q + mp.mpf(c) * h * p
            else:
                p = p - mp.mpf(c) * h * mp.sin(q)
        return q, p

    def proposal(first, last, q, p):
        q, p = run(first, q, p)
        for _ in range(L):
            q, p = run(kernel, q, p)
        return run(last, q, p)

    def flip_twice(first, last):
        q, p = proposal(first, last, mp.mpf("0.7"), mp.mpf("1.3"))
        q, p = proposal(first, last, q, -p)
        return abs(q - mp.mpf("0.7")) + abs(-p - mp.mpf("1.3"))

    with mp.workdps(50):
        assert flip_twice((), ()) < mp.mpf(10) ** -45
        assert flip_twice(pre, adjoint) < mp.mpf(10) ** -45
        assert flip_twice(pre, post) > 1e-6
    row = hmc([NAME], sigma=[1.0] * 4, trajectory_steps=L, step=0.4).rows[0]
    assert any(note.startswith("not reversible") for note in row.notes)


def test_a_kernel_that_is_not_a_splitting_is_refused_naming_the_key(tmp_path, run):
    path = tmp_path / "p.yaml"
    path.write_text("name: px\ntitle: x\nkind: processed\norder: 2\nsource: test\n"
                    "kernel: rk4\nprocessor: {drift: [0.1, -0.1], kick: [0.2, -0.2]}\n")
    code, _, err = run("region", str(path))
    assert code == 2 and "::$.kernel" in err


def test_an_hmc_chain_with_the_processed_method_drifts_from_the_target():
    """Measured: with P^-1 K^L P as the proposal, the first transition from
    the target accepts as predicted, but the chain is not reversible and leaves the
    target (the whitened variance of q grows); a verlet chain on the same target, moving
    as much, stays on it. hmc says so and does not rank the processed method."""
    sigmas = np.array([1.0, 0.3, 0.01])
    L, chains, transitions = 20, 4000, 150
    report = hmc([NAME, "verlet"], sigma=list(sigmas), trajectory_steps=L, step=0.0204357)
    rows = {r.method: r for r in report.rows}
    assert rows[NAME].rank is None and rows["verlet"].rank == 1

    def chain(name, h):
        m = resolve(name)[0]
        proposal = [np.linalg.matrix_power(transfer_matrix(m, h / s)[0], L) for s in sigmas]
        rng = np.random.default_rng(5)
        x = rng.standard_normal((chains, 3, 2))  # whitened (q / sigma, p), from the target
        first = None
        for k in range(transitions):
            x[:, :, 1] = rng.standard_normal((chains, 3))
            new = np.stack([x[:, i] @ proposal[i].T for i in range(3)], axis=1)
            dH = 0.5 * ((new ** 2).sum(axis=(1, 2)) - (x ** 2).sum(axis=(1, 2)))
            accept = rng.random(chains) < np.exp(-np.maximum(dH, 0.0))
            x[accept] = new[accept]
            if k == 0:
                first = np.minimum(1.0, np.exp(-dH))
        return first, (x[:, :, 0] ** 2).mean()

    first, variance = chain(NAME, 0.0204357)
    predicted = rows[NAME].at_step["acceptance"]
    assert abs(first.mean() - predicted) < 4 * first.std() / np.sqrt(chains)
    se = np.sqrt(2.0 / (3 * chains))  # of a mean of 3 chains x 4000 chi^2_1 / 1 draws
    assert variance > 1 + 10 * se, variance
    first, variance = chain("verlet", 0.015)  # (z = 1.5 on the fastest mode)
    assert first.mean() > 0.3 and abs(variance - 1) < 4 * se, (first.mean(), variance)
