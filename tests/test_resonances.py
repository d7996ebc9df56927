"""Nonlinear resonances n theta = 2 pi m: closed forms, 50-digit values, a real integration."""

from __future__ import annotations

import json
import math

import mpmath
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.core.regions import find_region
from stepsafe.core.resonances import fractions, nonlinear_resonances
from stepsafe.methods.library import FAMILIES, builtin_names, resolve
from stepsafe.reference.verify import mp_method, mp_transfer

LIBRARY = [(n, None) for n in builtin_names(single_force=True) if n not in FAMILIES]
FAMILY = [(f, s) for f in FAMILIES for s in (2, 3, 4, 5)]


def _found(name, stages, orders=(3, 4, 5, 6)):
    method, _ = resolve(name, stages)
    region = find_region(method, "oscillator", 10.0)
    return region, nonlinear_resonances(method, region, orders)


def test_fractions_are_the_reduced_ones_below_a_half():
    assert fractions((3, 4, 5, 6)) == [(3, 1), (4, 1), (5, 1), (5, 2), (6, 1)]
    assert fractions((12,)) == [(12, 1), (12, 5)]


def test_verlet_closed_forms():
    """Verlet: tr M = 2 - z^2, so n theta = 2 pi m at z = 2 sin(pi m / n): 4:1 at sqrt 2,
    3:1 at sqrt 3 (Schlick et al. 1998), 6:1 at 1, 5:1 and 5:2 at 2 sin(pi/5), 2 sin(2 pi/5)."""
    _, found = _found("verlet", None)
    expected = {f"{n}:{m}": 2 * math.sin(math.pi * m / n) for n, m in fractions((3, 4, 5, 6))}
    assert {r.name for r in found} == set(expected)
    for r in found:
        assert abs(r.z - expected[r.name]) <= r.uncertainty + 2e-16 * r.z, r
        assert r.uncertainty < 1e-12


@pytest.mark.parametrize("name, stages", LIBRARY + FAMILY)
def test_resonances_at_50_digits(name, stages):
    """Each resonance is within its stated uncertainty of the root of
    tr M = 2 cos(2 pi m / n) at 50 digits (M from the stage equations solved in mpmath),
    and none below z* is missed: an mpmath scan finds no other crossing of any level."""
    region, found = _found(name, stages)
    if region.first_interval is None or not region.symplectic:
        assert found == ()
        return
    Mfun = mp_transfer(mp_method(name, stages, None, 50))
    z_end = region.first_boundary or region.zmax
    with mpmath.workdps(50):
        def trace(x):
            M = Mfun(mpmath.mpf(x), "oscillator")
            return M[0, 0] + M[1, 1]

        for r in found:
            level = 2 * mpmath.cos(2 * mpmath.pi * r.m / r.n)
            width = max(4 * r.uncertainty, 1e-9 * r.z)
            lo, hi = mpmath.mpf(r.z) - width, mpmath.mpf(r.z) + width
            assert (trace(lo) - level) * (trace(hi) - level) < 0, r
            root = mpmath.findroot(lambda x, c=level: trace(x) - c, (lo, hi), solver="anderson")
            assert abs(r.z - root) <= r.uncertainty + 4e-16 * r.z, (r, root)
        grid = [z_end * (k + 0.5) / 240 for k in range(240)]
        values = [trace(x) for x in grid]
        for n, m in fractions((3, 4, 5, 6)):
            level = 2 * mpmath.cos(2 * mpmath.pi * m / n)
            crossings = [(a, b) for a, b, fa, fb in zip(grid, grid[1:], values, values[1:])
                         if (fa - level) * (fb - level) < 0]
            for a, b in crossings:
                assert any(r.n == n and r.m == m and a <= r.z <= b for r in found), (n, m, a)


def _force(x):
    """The cubic anharmonic force -V'(q) of V = q^2/2 + q^3, and its derivative."""
    return -(x + 3.0 * x * x), -(1.0 + 6.0 * x)


def _stepper(method: stepsafe.Integrator):
    """One step of the method on q'' = force(q): drifts and kicks for a splitting; for an
    RK method the stage equations Q = q + h A_q P, P = p + h A_p f(Q) solved by Newton's
    method with the exact Jacobian (fixed-point iteration diverges at these z)."""
    ops = method.operations
    if ops is not None:
        def step(q, p, h):
            for kind, c in ops:
                if kind == "drift":
                    q = q + c * h * p
                else:
                    p = p + c * h * _force(q)[0]
            return q, p
        return step
    t = method.partitioned_tableau
    s, eye = t.stages, np.eye(t.stages)

    def step(q, p, h):
        Q, P = np.full(s, q), np.full(s, p)
        for _ in range(50):
            f, df = _force(Q)
            residual = np.concatenate([Q - q - h * t.A_q @ P, P - p - h * t.A_p @ f])
            jacobian = np.block([[eye, -h * t.A_q], [-h * t.A_p * df[None, :], eye]])
            delta = np.linalg.solve(jacobian, residual)
            Q, P = Q - delta[:s], P - delta[s:]
            if np.abs(delta).max() <= 1e-15 * (1.0 + np.abs(Q).max() + np.abs(P).max()):
                break
        return q + h * t.b_q @ P, p + h * t.b_p @ _force(Q)[0]
    return step


def _escape_step(step, h, amplitude=0.005, steps=20_000):
    """Steps until the cubic anharmonic oscillator started at rest at ``amplitude`` leaves
    |q| < 1 (None: it stays bounded)."""
    q, p = amplitude, 0.0
    for k in range(steps):
        q, p = step(q, p, h)
        if not abs(q) < 1.0:
            return k
    return None


@pytest.mark.parametrize("name, stages", [("verlet", None), ("gauss", 1)])
def test_the_3_1_resonance_is_measured_where_predicted(name, stages):
    """A real integration: with a cubic force V = q^2/2 + q^3 (beta = 1) Verlet and the
    implicit midpoint rule are linearly stable at their 3:1 resonance (z = sqrt 3 and
    2 sqrt 3), yet a small oscillation (amplitude 0.005) escapes there within a thousand
    steps; 3% below it, it stays bounded for 20,000 steps. (More accurate methods, whose
    step map is closer to the flow, were not destabilised at theirs: how strong a resonance
    is depends on the method; where it is, is what stepsafe predicts.)"""
    method = stepsafe.method(name, stages=stages)
    z3 = next(r["z"] for r in stepsafe.region(method, "oscillator").to_dict()["models"][
        "oscillator"]["nonlinear_resonances"] if r["resonance"] == "3:1")
    assert z3 == pytest.approx(math.sqrt(3) if name == "verlet" else 2 * math.sqrt(3),
                               rel=1e-14)
    step = _stepper(method)
    assert _escape_step(step, z3, steps=5_000) is not None
    assert _escape_step(step, 0.97 * z3) is None


def test_advise_and_check_keep_below_the_resonance(run):
    code, out, err = run("advise", "--method", "verlet", "--beta", "2", "--resonance-order",
                         "4", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["h_max"] < math.sqrt(2) / 2 and data["h_max"] == pytest.approx(
        math.sqrt(2) / 2, rel=1e-12)
    assert data["limiting"]["resonance"] == "4:1"
    assert [r["resonance"] for r in data["nonlinear_resonances"]] == ["6:1", "5:1"]
    h = data["h_max"]  # the open end of the safe interval: just below it is safe
    assert run("check", "--method", "verlet", "--beta", "2", "--step", repr(h * (1 - 1e-12)),
               "--resonance-order", "4")[0] == 0
    assert run("check", "--method", "verlet", "--beta", "2", "--step", repr(h),
               "--resonance-order", "4")[0] == 1
    code, out, _ = run("check", "--method", "verlet", "--beta", "2", "--step",
                       repr(math.sqrt(2) / 2), "--resonance-order", "4")
    assert code == 1 and "4:1 nonlinear resonance" in out
    # without the option the same step is safe (the linear limit is z = 2)
    assert run("check", "--method", "verlet", "--beta", "2", "--step",
               repr(math.sqrt(2) / 2))[0] == 0


@pytest.mark.parametrize("order", ["2", "0", "51", "x"])
def test_bad_orders_are_usage_errors(run, order):
    code, out, err = run("advise", "--method", "verlet", "--beta", "1", "--resonance-order",
                         order)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1


def test_verify_checks_the_resonance_cap(run):
    code, out, err = run("advise", "--method", "pefrl", "--beta", "1", "--resonance-order",
                         "3", "--verify", "--json")
    assert code == 0, err
    verdict = json.loads(out)["verify"]
    assert verdict["ok"] and verdict["points"] >= 2


@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
@given(name=st.sampled_from(["verlet", "pefrl", "bcss2", "yoshida4", "blanes-moan6"]),
       exponent=st.integers(-150, 150), offset=st.floats(-1e-6, 1e-6),
       order=st.integers(3, 6))
def test_resonance_order_verdicts_at_every_scale(name, exponent, offset, order):
    """check --resonance-order at beta from 1e-150 to 1e150: a SAFE step lies below the
    first resonance of order <= N at 50 digits; steps clearly above it are UNSAFE. Where
    no resonance of order <= N lies below the first boundary (yoshida4), the order
    changes no verdict there."""
    beta = 10.0 ** exponent
    region, found = _found(name, None, tuple(range(3, order + 1)))
    if not found:
        h = region.first_boundary * (1 + offset) / beta
        assert stepsafe.check(name, h, [beta], resonance_order=order).safe == \
            stepsafe.check(name, h, [beta]).safe
        return
    first = found[0]
    Mfun = mp_transfer(mp_method(name, None, None, 50))
    with mpmath.workdps(50):
        level = 2 * mpmath.cos(2 * mpmath.pi * first.m / first.n)
        lo = mpmath.mpf(first.z) * (1 - mpmath.mpf(1e-9))
        hi = mpmath.mpf(first.z) * (1 + mpmath.mpf(1e-9))

        def g(x):
            M = Mfun(x, "oscillator")
            return M[0, 0] + M[1, 1] - level

        exact = mpmath.findroot(g, (lo, hi), solver="anderson")
    h = first.z * (1 + offset) / beta
    report = stepsafe.check(name, h, [beta], resonance_order=order)
    with mpmath.workdps(50):
        z = mpmath.mpf(h) * mpmath.mpf(beta)
        if report.safe:
            assert z < exact, (name, beta, offset)
        if z > exact * (1 + mpmath.mpf(1e-12)):
            assert not report.safe


def _fpu_stiffness(n: int = 4) -> list[list[float]]:
    """The FPU chain's linear stiffness (unit masses, fixed walls): frequencies
    2 sin(k pi / (2 (n + 1)))."""
    return (2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)).tolist()


# (order 4 also searches the equilibria of examples/fpu-alpha.yaml: about 3.4 s)
@pytest.mark.parametrize("order, resonant", [
    pytest.param(4, math.sqrt(2), marks=pytest.mark.slow), (3, math.sqrt(3))])
def test_resonance_order_applies_to_system_scenes(run, tmp_path, order, resonant):
    """A system: scene (a Hamiltonian with its equilibria, or a stiffness with or without
    all_modes) keeps below the fastest mode's n:1 resonance, z = 2 sin(pi/n) for Verlet,
    as the same frequencies given as modes do; the step just above it fails."""
    top = 2 * math.sin(4 * math.pi / 10)  # the FPU chain's fastest mode
    limit = resonant / top
    stiffness = tmp_path / "fpu-k.json"
    stiffness.write_text(json.dumps({"method": "verlet",
                                     "system": {"stiffness": _fpu_stiffness()}}))
    dense = tmp_path / "fpu-all.json"
    dense.write_text(json.dumps({"method": "verlet", "system": {
        "stiffness": _fpu_stiffness(), "all_modes": True}}))
    # (the Hamiltonian scene, whose equilibria are searched on every run, at order 4 only)
    scenes = [str(stiffness), str(dense)] + (["examples/fpu-alpha.yaml"] if order == 4 else [])
    for scene in scenes:
        if scene != "examples/fpu-alpha.yaml":
            data = json.loads(run("advise", scene, "--resonance-order", str(order),
                                  "--json")[1])
            assert data["h_max"] == pytest.approx(limit, rel=1e-9) and data["h_max"] <= limit
        code, out, _ = run("check", scene, "--step", repr(limit * (1 + 1e-6)),
                           "--resonance-order", str(order))
        assert code == 1 and f"{order}:1 nonlinear resonance" in out
        assert run("check", scene, "--step", repr(limit * (1 - 1e-6)),
                   "--resonance-order", str(order))[0] == 0


def test_resonance_order_is_refused_for_a_coupled_system(run, tmp_path):
    """A system whose modes do not decouple has no per-mode rotation angle: the option is
    refused (exit 2) rather than ignored."""
    scene = tmp_path / "gyro.json"
    scene.write_text(json.dumps({"method": "verlet", "system": {
        "hessian": [[2, 0, 0, -0.5], [0, 2, 0.5, 0], [0, 0.5, 1, 0], [-0.5, 0, 0, 1]]}}))
    code, _, err = run("check", str(scene), "--step", "0.1", "--resonance-order", "4")
    assert code == 2 and "--resonance-order is not available" in err
    assert run("advise", str(scene), "--resonance-order", "4")[0] == 2


@pytest.mark.parametrize("name", ["verlet", "pefrl", "bcss2"])
@pytest.mark.parametrize("order", [3, 4, 5, 6])
def test_a_resonance_that_limits_the_step_is_named(run, name, order):
    """With --resonance-order N the end of the safe interval is the first resonance n:m of
    order n <= N (placed here at 50 digits from the mpmath transfer matrix), and
    h_max_limited_by names it as ``resonance n:m`` in the API, in --json and in text,
    for advise and check alike; the step just below h_max is safe, the 50-digit
    resonance step is not."""
    beta = 3.0
    _, found = _found(name, None, tuple(range(3, order + 1)))
    first = min(found, key=lambda r: r.z)
    Mfun = mp_transfer(mp_method(name, None, None, 50))
    with mpmath.workdps(50):
        level = 2 * mpmath.cos(2 * mpmath.pi * first.m / first.n)

        def g(x):
            M = Mfun(x, "oscillator")
            return M[0, 0] + M[1, 1] - level

        z = mpmath.findroot(g, (mpmath.mpf(first.z) * (1 - mpmath.mpf(1e-9)),
                                mpmath.mpf(first.z) * (1 + mpmath.mpf(1e-9))),
                            solver="anderson")
        if name == "verlet":  # tr M = 2 - z^2: n theta = 2 pi m at z = 2 sin(pi m / n)
            assert abs(z - 2 * mpmath.sin(mpmath.pi * first.m / first.n)) < mpmath.mpf(10) ** -40
        h_exact = z / beta
    expected = f"resonance {first.n}:{first.m}"
    advice = stepsafe.advise(name, [beta], resonance_order=order)
    assert advice.h_max_limited_by == expected
    assert advice.record["h_max_limited_by"] == expected
    assert mpmath.mpf(advice.h_max) <= h_exact
    assert float(h_exact) == pytest.approx(advice.h_max, rel=1e-12)
    below = math.nextafter(advice.h_max, 0)
    report = stepsafe.check(name, below, [beta], resonance_order=order)
    assert report.safe and report.record["h_max_limited_by"] == expected
    above = float(h_exact * (1 + mpmath.mpf(1e-12)))
    assert not stepsafe.check(name, above, [beta], resonance_order=order).safe
    code, out, _ = run("check", "--method", name, "--beta", repr(beta), "--step", repr(below),
                       "--resonance-order", str(order), "--json")
    assert code == 0 and json.loads(out)["checks"][0]["h_max_limited_by"] == expected
    code, out, _ = run("check", "--method", name, "--beta", repr(beta), "--step", repr(above),
                       "--resonance-order", str(order))
    assert code == 1 and f"(limited by the {first.n}:{first.m} nonlinear resonance)" in " ".join(
        out.split())
    code, out, _ = run("advise", "--method", name, "--beta", repr(beta), "--resonance-order",
                       str(order))
    assert code == 0 and f"(its {first.n}:{first.m} nonlinear resonance)" in " ".join(
        out.split())


def test_a_linear_boundary_is_not_called_a_resonance():
    """Without --resonance-order the limit stays ``boundary``: Verlet's z = 2 at beta = 1."""
    assert stepsafe.advise("verlet", [1.0]).h_max_limited_by == "boundary"
    assert stepsafe.check("verlet", 1.0, [1.0]).record["h_max_limited_by"] == "boundary"
