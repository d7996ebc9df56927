"""The equilibrium search of Hamiltonian systems against truths computed here: centres in
any units (1e-300 to 1e300, in q and p together or apart), and narrow wells behind ridges
and saddles, which the walks between the equilibria found must reach.

Every truth is independent of stepsafe: the equilibria of the wells by bracketing and
refining V'(q) = 0 in mpmath (50 digits) on a grid finer than the well, their frequencies
from the analytic second derivative there, and Verlet's verdict from the trace of its
one-step matrix built in mpmath at that linearisation."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from support import method

import stepsafe
from stepsafe.systems.linear import hessian_modes

DIGITS = 50


def verlet_trace(a, b, h) -> mp.mpf:
    """tr M of Verlet (half kick, drift, half kick) on H = a q^2 + b p^2, in mpmath."""
    with mp.workdps(DIGITS):
        a, b, h = mp.mpf(a), mp.mpf(b), mp.mpf(h)
        kick = mp.matrix([[1, 0], [-a * h, 1]])  # p -= (h/2) dH/dq = (h/2) 2 a q
        drift = mp.matrix([[1, 2 * b * h], [0, 1]])  # q += h dH/dp = h 2 b p
        M = kick * drift * kick
        return M[0, 0] + M[1, 1]


def centre_scene(tmp_path, a: str, b: str, h: float) -> str:
    path = tmp_path / "centre.yaml"
    path.write_text(f'method: verlet\nh: {h!r}\nsystem:\n  hamiltonian: "{a}*q**2 + {b}*p**2"\n'
                    "  box: {q: [-1, 1], p: [-1, 1]}\n  starts: 9\n")
    return str(path)


# ------------------------------------------------------------------ centres in any units


def test_a_centre_scaled_by_1e_minus_300_in_q_and_p_is_a_centre(run, tmp_path):
    """H = 1e-300 (q^2 + p^2): beta = 2e-300, Verlet needs h < 1e300; tr M = -14 at
    h = 2e300 (the discriminant H_qp^2 - H_qq H_pp = -4e-600 is below float64's range)."""
    assert verlet_trace("1e-300", "1e-300", "2e300") == -14
    scene = centre_scene(tmp_path, "1e-300", "1e-300", 2e300).replace("  starts: 9\n", "")
    code, out, _ = run("check", scene, "--json")
    (data,) = json.loads(out)["checks"]
    (item,) = data["system"]["items"]
    assert code == 1 and not data["safe"]
    assert item["type"] == "elliptic" and item["model"] == "oscillator"
    assert item["beta"] == pytest.approx(2e-300, rel=1e-15) and item["D"] is None
    assert data["h_max"] == pytest.approx(1e300, rel=1e-10) and data["h_max"] <= 1e300
    code, _, _ = run("check", centre_scene(tmp_path, "1e-300", "1e-300", 0.99e300))
    assert code == 0


def test_an_n_dof_centre_scaled_by_1e_minus_300_is_analysed(tmp_path):
    """1e-300 ((px^2 + py^2)/2 + (x^2 + y^2)/2): frequencies 1e-300, Verlet's limit 2e300."""
    scene = tmp_path / "s.yaml"
    scene.write_text('method: verlet\nsystem:\n  hamiltonian: "1e-300*((px**2 + py**2)/2 + '
                     '(x**2 + y**2)/2)"\n  q: [x, y]\n  p: [px, py]\n  box: {x: [-1, 1], '
                     "y: [-1, 1], px: [-1, 1], py: [-1, 1]}\n")
    report = stepsafe.advise(scene=str(scene))
    (item,) = report.record["system"]["items"]
    assert item["type"] == "elliptic"
    assert item["frequencies"] == pytest.approx([1e-300, 1e-300], rel=1e-15)
    assert report.h_max == pytest.approx(2e300, rel=1e-10) and report.h_max <= 2e300
    assert stepsafe.check(h=1.9e300, scene=str(scene)).safe
    assert not stepsafe.check(h=2.1e300, scene=str(scene)).safe


scales = st.integers(-300, 300)
where = st.sampled_from(["q and p", "q", "p"])


@settings(max_examples=25, deadline=None)
@given(k=scales, part=where, a=st.sampled_from(["0.5", "1", "3.25"]),
       b=st.sampled_from(["0.5", "2", "7"]), f=st.floats(0.3, 1.7))
def test_1_dof_centres_in_any_units(k, part, a, b, f):
    """H = A q^2 + B p^2 with A, B scaled by 10^k (together, or one alone): Verlet is safe
    exactly where |tr M| < 2, tr M computed in mpmath at the true linearisation."""
    A = f"{a}e{k}" if part in ("q and p", "q") else a
    B = f"{b}e{k}" if part in ("q and p", "p") else b
    with mp.workdps(DIGITS):
        beta = 2 * mp.sqrt(mp.mpf(A) * mp.mpf(B))
        h = float(f * 2 / beta)
        assume(math.isfinite(h) and h > 0 and abs(f - 1) > 1e-6)
        trace = verlet_trace(A, B, h)
    report = stepsafe.check("verlet", h, system={
        "hamiltonian": f"{A}*q**2 + {B}*p**2", "box": {"q": [-1, 1], "p": [-1, 1]},
        "starts": 9})
    (item,) = report.record["system"]["items"]
    assert item["model"] == "oscillator" and item["type"] == "elliptic"
    assert item["beta"] == pytest.approx(float(beta), rel=1e-14)
    assert report.safe == bool(abs(trace) < 2)


@settings(max_examples=25, deadline=None)
@given(kq=scales, kp=scales, c=st.sampled_from(["0", "0.5", "-0.9"]),
       f=st.floats(0.3, 1.7))
def test_n_dof_centres_in_any_units(kq, kp, c, f):
    """H = 10^kp (px^2 + py^2)/2 + 10^kq (x^2 + c x y + 2 y^2)/2: the frequencies are
    sqrt(10^(kq + kp) mu) for the eigenvalues mu of [[1, c/2], [c/2, 2]], in any units."""
    assume(abs(kq + kp) <= 560)  # frequencies within float64's range (10^+-280)
    with mp.workdps(DIGITS):
        c_ = mp.mpf(c)
        mu = [(3 - s * mp.sqrt(1 + c_ * c_)) / 2 for s in (1, -1)]
        omega = [mp.sqrt(mp.mpf(10) ** (kq + kp) * m) for m in mu]
        h = float(f * 2 / omega[1])
        assume(math.isfinite(h) and h > 0 and abs(f - 1) > 1e-6)
        # Verlet on each mode: H = omega^2 Q^2 / 2 + P^2 / 2 in its normal coordinates
        safe = all(abs(verlet_trace(w * w / 2, mp.mpf(1) / 2, h)) < 2 for w in omega)
    text = (f"1e{kp}*(px**2 + py**2)/2 + 1e{kq}*(x**2 + {c}*x*y + 2*y**2)/2")
    box = {name: [-1, 1] for name in ("x", "y", "px", "py")}
    report = stepsafe.check("verlet", h, system={"hamiltonian": text, "q": ["x", "y"],
                                                 "p": ["px", "py"], "box": box,
                                                 "starts": 8})
    (item,) = report.record["system"]["items"]
    assert item["type"] == "elliptic"
    assert item["frequencies"] == pytest.approx([float(w) for w in omega], rel=1e-12)
    assert report.safe == safe


@settings(max_examples=60, deadline=None)
@given(kq=scales, kp=scales, entries=st.lists(st.floats(-2, 2), min_size=3, max_size=3),
       rk=st.booleans())
def test_linearisations_in_any_units(kq, kp, entries, rk):
    """hessian_modes of S = [[10^kq a, c], [c, 10^kp b]] (separable for Verlet, or the RK
    path with a mixed term c): the rate is |mu| for the eigenvalues mu of J S, computed in
    mpmath from the float entries, to the uncertainty the mode states (an undecided one
    bounds it from above)."""
    assume(abs(kq + kp) <= 560)
    a, b, c = entries
    assume(abs(a) > 1e-3 and b > 1e-3)
    mixed = c * 10.0 ** ((kq + kp) / 2) if rk else 0.0
    S = [[a * 10.0 ** kq, mixed], [mixed, b * 10.0 ** kp]]
    d = hessian_modes(np.array(S), method("gauss", 2) if rk else method("verlet"))
    assume(d is not None)
    with mp.workdps(DIGITS):
        # J S = [[S_pq, S_pp], [-S_qq, -S_qp]]: mu^2 = S_qp^2 - S_qq S_pp, exactly
        qq, qp, pp = (mp.mpf(x) for x in (S[0][0], S[0][1], S[1][1]))
        rate = mp.sqrt(abs(qp * qp - qq * pp))
    modes = [m for m in d.modes if m.model != "free"]
    assume(modes and rate > 0)
    top = max(modes, key=lambda m: m.beta)
    if top.decided:  # within its stated uncertainty (and a few roundings of this test's)
        assert abs(top.beta - float(rate)) <= (top.rel_error + 1e-14) * float(rate)
    else:  # a rate within rounding of 0: analysed at the largest rate rounding allows
        assert top.beta >= float(rate)


# ------------------------------------------------------------------ wells behind a ridge


BACKGROUNDS = {"harmonic": ("q**2/2", lambda q: q, lambda q: 1),
               "double-well": ("(q**2 - 1)**2/4", lambda q: q ** 3 - q,
                               lambda q: 3 * q ** 2 - 1)}


def well_equilibria(background: str, depth, centre, width, lo, hi):
    """Every zero of V'(q) in [lo, hi] for V = background - depth exp(-(q - c)^2 / w),
    with V''(q) there: sign changes of V' on a grid (a 200th of the well's width apart
    within ten widths of it, 1/2000 of the interval elsewhere; numpy), each refined by
    bisection in mpmath to 50 digits."""
    _, d1, d2 = BACKGROUNDS[background]
    sigma = math.sqrt(width / 2)
    grid = np.union1d(centre + sigma * np.linspace(-10, 10, 4001), np.linspace(lo, hi, 4001))
    grid = grid[(grid >= lo) & (grid <= hi)]
    sign = np.sign(d1(grid) + 2 * depth * (grid - centre) / width
                   * np.exp(-(grid - centre) ** 2 / width))
    with mp.workdps(DIGITS):
        A, c, w = mp.mpf(depth), mp.mpf(centre), mp.mpf(width)

        def dV(q):
            return d1(q) + 2 * A * (q - c) / w * mp.exp(-(q - c) ** 2 / w)

        def d2V(q):
            e = mp.exp(-(q - c) ** 2 / w)
            return d2(q) + 2 * A / w * e * (1 - 2 * (q - c) ** 2 / w)

        roots = [mp.findroot(dV, (mp.mpf(x0), mp.mpf(x1)), solver="bisect")
                 for x0, x1, s0, s1 in zip(grid, grid[1:], sign, sign[1:]) if s0 * s1 < 0]
        roots += [mp.mpf(x) for x, s in zip(grid, sign) if s == 0]
        return [(r, d2V(r)) for r in sorted(roots)]


@st.composite
def wells(draw):
    background = draw(st.sampled_from(sorted(BACKGROUNDS)))
    width = 10 ** draw(st.floats(-4, -1))
    depth = draw(st.floats(0.05, 3.0))
    centre = draw(st.floats(-1.6, 1.6))
    return background, float(f"{width:.3g}"), float(f"{depth:.3g}"), float(f"{centre:.4g}")


def _well_text(background: str, depth: float, centre: float, width: float, p: str = "p"
               ) -> str:
    return (f"{p}**2/2 + {BACKGROUNDS[background][0]} - {depth!r}*exp(-(q - ({centre!r}))**2"
            f"/{width!r})")


@settings(max_examples=15, deadline=None)
@given(well=wells(), f=st.floats(0.3, 1.7))
def test_1_dof_wells_are_found_and_safe_verdicts_hold(well, f):
    """A narrow Gaussian well (width 1e-4 to 1e-1, on the flank of a harmonic or
    double-well potential): the walks between the equilibria sweep the q axis, so a search
    that vouches for completeness has found every equilibrium, and a SAFE verdict holds at
    the true linearisation of each (tr M of Verlet in mpmath)."""
    _check_1_dof_well(well, f)


@pytest.mark.slow
@settings(max_examples=150, deadline=None)
@given(well=wells(), f=st.floats(0.3, 1.7))
def test_1_dof_wells_are_found_and_safe_verdicts_hold_over_many_wells(well, f):
    _check_1_dof_well(well, f)


def _check_1_dof_well(well, f) -> None:
    background, width, depth, centre = well
    truth = well_equilibria(background, depth, centre, width, -2, 2)
    # well-posed draws only: simple zeros, apart from each other and from the box edge
    assume(all(abs(k) > 1e-6 for _, k in truth))
    assume(all(abs(r1 - r0) > 1e-4 for (r0, _), (r1, _) in zip(truth, truth[1:])))
    assume(all(abs(abs(r) - 2) > 1e-3 for r, _ in truth))
    top = max(mp.sqrt(k) for _, k in truth if k > 0)
    h = float(f * 2 / top)
    assume(abs(f - 1) > 1e-6)
    report = stepsafe.check("verlet", h, require_complete_search=True, system={
        "hamiltonian": _well_text(background, depth, centre, width),
        "box": {"q": [-2, 2], "p": [-1, 1]}, "starts": 25})
    record = report.record["system"]
    if record["search"]["complete"]:
        found = sorted(item["q"] for item in record["items"])
        assert found == pytest.approx([float(r) for r, _ in truth], abs=1e-7), \
            (found, truth, record["search"])
    if report.safe:
        for _, k in truth:
            if k > 0:  # a centre: Verlet keeps it iff |tr M| < 2
                assert abs(verlet_trace(k / 2, 0.5, h)) < 2


@pytest.mark.slow
def test_the_well_behind_the_saddle_is_found(tmp_path, run):
    """H = (px^2 + py^2)/2 + (x^2 + y^2)/2 - exp(-((x - 0.7)^2 + (y - 0.3)^2)/1e-3) in the
    box +-1 from 2000 starts: Newton's method reaches the saddle on the ridge; the walk
    down from it finds the minimum behind it, beta = 44.73 (by mpmath Newton here), which
    Verlet at h = 0.05 does not keep (tr M < -2)."""
    with mp.workdps(DIGITS):
        def grad(x, y):
            e = mp.exp(-((x - mp.mpf("0.7")) ** 2 + (y - mp.mpf("0.3")) ** 2) / mp.mpf("1e-3"))
            return [x + 2000 * (x - mp.mpf("0.7")) * e, y + 2000 * (y - mp.mpf("0.3")) * e]

        x, y = mp.findroot(grad, (mp.mpf("0.7"), mp.mpf("0.3")))
        e = mp.exp(-((x - mp.mpf("0.7")) ** 2 + (y - mp.mpf("0.3")) ** 2) / mp.mpf("1e-3"))
        dx, dy = x - mp.mpf("0.7"), y - mp.mpf("0.3")
        V = mp.matrix([[1 + 2000 * e * (1 - 2000 * dx * dx), -2000 * 2000 * e * dx * dy],
                       [-2000 * 2000 * e * dx * dy, 1 + 2000 * e * (1 - 2000 * dy * dy)]])
        omega = max(mp.sqrt(v) for v in mp.eigsy(V)[0])
        assert verlet_trace(omega ** 2 / 2, 0.5, "0.05") < -2
    assert float(x) == pytest.approx(0.69965, abs=1e-5) and float(omega) == pytest.approx(
        44.73, abs=0.01)
    scene = tmp_path / "well.yaml"
    scene.write_text('method: verlet\nh: 0.05\nsystem:\n  hamiltonian: "(px**2 + py**2)/2 + '
                     '(x**2 + y**2)/2 - exp(-((x - 0.7)**2 + (y - 0.3)**2)/1e-3)"\n  q: [x, y]\n'
                     "  p: [px, py]\n  starts: 2000\n  box: {x: [-1, 1], y: [-1, 1], px: [-1, 1], "
                     "py: [-1, 1]}\n")
    code, out, _ = run("check", str(scene), "--json")
    (data,) = json.loads(out)["checks"]
    assert code == 1 and not data["safe"]
    well = [i for i in data["system"]["items"] if abs(i["x"][0] - float(x)) < 1e-6]
    assert len(well) == 1 and max(well[0]["frequencies"]) == pytest.approx(float(omega),
                                                                          rel=1e-9)
    assert data["system"]["search"]["found_by_walks"] >= 1


@st.composite
def wells_2_dof(draw):
    background, width, depth, centre = draw(wells())
    stiffness = draw(st.floats(1.5, 4.0))  # y is stiffer: the eigendirections are the axes
    return background, width, depth, centre, float(f"{stiffness:.3g}")


@settings(max_examples=8, deadline=None)
@given(well=wells_2_dof(), f=st.floats(0.3, 1.7))
def test_2_dof_wells_on_a_walk_are_found(well, f):
    """The 1-dof wells in x beside a stiffer y (H = (px^2 + py^2)/2 + background(x) +
    k y^2/2 - depth exp(-((x - c)^2 + y^2)/w)): every equilibrium lies on the x axis
    (dV/dy = y (k + 2 depth/w e) vanishes only at y = 0), where the walks from the
    background's equilibria go; a complete search finds them all and SAFE holds at each
    (Verlet's tr M in mpmath for both modes: V_yy = k + 2 depth e / w)."""
    _check_2_dof_well(well, f)


@pytest.mark.slow
@settings(max_examples=80, deadline=None)
@given(well=wells_2_dof(), f=st.floats(0.3, 1.7))
def test_2_dof_wells_on_a_walk_are_found_over_many_wells(well, f):
    _check_2_dof_well(well, f)


def _check_2_dof_well(well, f) -> None:
    background, width, depth, centre, k = well
    truth = well_equilibria(background, depth, centre, width, -2, 2)
    assume(all(abs(v) > 1e-6 for _, v in truth))
    assume(all(abs(r1 - r0) > 1e-4 for (r0, _), (r1, _) in zip(truth, truth[1:])))
    assume(all(abs(abs(r) - 2) > 1e-3 for r, _ in truth))
    with mp.workdps(DIGITS):
        modes = []
        for r, vxx in truth:
            e = mp.exp(-(r - mp.mpf(centre)) ** 2 / mp.mpf(width))
            modes += [vxx, k + 2 * mp.mpf(depth) * e / mp.mpf(width)]
        top = max(mp.sqrt(v) for v in modes if v > 0)
    h = float(f * 2 / top)
    assume(abs(f - 1) > 1e-6)
    text = (f"(px**2 + py**2)/2 + {BACKGROUNDS[background][0].replace('q', 'x')} + "
            f"{k!r}*y**2/2 - {depth!r}*exp(-((x - ({centre!r}))**2 + y**2)/{width!r})")
    box = {"x": [-2, 2], "y": [-1, 1], "px": [-1, 1], "py": [-1, 1]}
    report = stepsafe.check("verlet", h, require_complete_search=True, system={
        "hamiltonian": text, "q": ["x", "y"], "p": ["px", "py"], "box": box, "starts": 16})
    record = report.record["system"]
    if record["search"]["complete"]:
        found = sorted(item["x"][0] for item in record["items"])
        assert found == pytest.approx([float(r) for r, _ in truth], abs=1e-7), \
            (found, truth, record["search"])
    if report.safe:
        for v in modes:
            if v > 0:
                assert abs(verlet_trace(v / 2, 0.5, h)) < 2


# ------------------------------------------------------------------ what the search says


@pytest.mark.slow
def test_an_incomplete_search_is_said_and_can_fail_check(run, tmp_path):
    """log(q) is undefined for q <= 0: the starts there cannot be evaluated, so the search
    cannot vouch for completeness. check says so, exits 0 by default and 1 with
    --require-complete-search; a complete search passes with it."""
    scene = tmp_path / "log.yaml"
    scene.write_text('method: verlet\nh: 0.5\nsystem:\n  hamiltonian: "log(q) + 1/q + p**2"\n'
                     "  box: {q: [-1, 1], p: [-1, 1]}\n")
    code, out, _ = run("check", str(scene))
    assert code == 0 and "Search:" in out and "INCOMPLETE" in out
    code, out, _ = run("check", str(scene), "--require-complete-search")
    assert code == 1 and "cannot vouch" in out
    code, out, _ = run("check", str(scene), "--require-complete-search", "--json")
    data = json.loads(out)
    (check,) = data["checks"]
    assert code == 1 and not data["safe"] and not check["system"]["search"]["complete"]
    assert check["system"]["search"]["gaps"] and "cannot vouch" in check["search_failure"]
    report = stepsafe.check(scene=str(scene), require_complete_search=True)
    assert not report.safe and report.record["search_failure"]
    assert stepsafe.check(scene=str(scene)).safe
    pendulum = Path(__file__).resolve().parent.parent / "examples" / "pendulum.yaml"
    code, out, _ = run("check", str(pendulum), "--require-complete-search", "--json")
    (check,) = json.loads(out)["checks"]
    assert code == 0 and check["system"]["search"]["complete"]
    assert check["system"]["search"]["walks_to_equilibrium"] >= 2


def test_require_complete_search_is_a_flag():
    with pytest.raises(stepsafe.StepsafeError, match="require_complete_search"):
        stepsafe.check("verlet", 0.1, [1.0], require_complete_search="yes")
