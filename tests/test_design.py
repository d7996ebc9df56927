"""``stepsafe design``: the objective against the published BCSS coefficient, the method file
it writes against every command, and the designed integrator against the fixed ones on its
own target by sampling."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from test_hmc import _run_hmc

import stepsafe
from stepsafe import design, hmc
from stepsafe.core.design import design as core_design
from stepsafe.core.design import family_member, rho_values
from stepsafe.exceptions import StepsafeError


def _rho_mp(b, z):
    """rho(z) of the 2-stage member b at 40 digits, straight from the kick/drift product."""
    with mp.workdps(40):
        b, z = mp.mpf(b), mp.mpf(z)
        M = mp.eye(2)
        for kind, c in (("k", b), ("d", mp.mpf(1) / 2), ("k", 1 - 2 * b),
                        ("d", mp.mpf(1) / 2), ("k", b)):
            S = mp.matrix([[1, c * z], [0, 1]]) if kind == "d" else \
                mp.matrix([[1, 0], [-c * z, 1]])
            M = S * M
        half = (M[0, 0] + M[1, 1]) / 2
        e1 = ((M[0, 0] - M[1, 1]) ** 2 + (M[0, 1] + M[1, 0]) ** 2) / 2
        return e1 / (1 - half ** 2)


def test_rho_of_the_family_at_40_digits():
    for b in (0.19, 0.21178, 0.25):
        for z in (0.3, 1.1, 2.0, 2.5):
            got = rho_values(2, np.array([[b]]), np.array([z]))[0, 0]
            assert got == pytest.approx(float(_rho_mp(b, z)), rel=1e-9)


def test_the_bcss_coefficient_minimises_its_own_criterion():
    """Blanes, Casas & Sanz-Serna (2014) choose b minimising max rho over 0 < h <= 2 and
    print b = 0.21178: the family's rho reproduces it (minimiser 0.2117809815...)."""
    z = np.linspace(1e-3, 2.0, 4000)
    bs = np.linspace(0.2110, 0.2125, 1501)
    worst = rho_values(2, bs[:, None], z).max(axis=1)
    assert bs[int(np.argmin(worst))] == pytest.approx(0.21178, abs=2e-6)
    # the other value in circulation (methods/bcss2.yaml) is a different member
    other = rho_values(2, np.array([[(3 - np.sqrt(3)) / 6], [0.21178]]), z).max(axis=1)
    assert other[0] == pytest.approx(5.17e-4, rel=1e-2)
    assert other[1] == pytest.approx(3.99e-4, rel=1e-2)
    assert float(_rho_mp(0.21178, 2.0)) == pytest.approx(other[1], rel=1e-9)


def test_design_minimises_the_expected_error_of_one_mode():
    """One mode, 2 stages: the expected error rho(z) at z = 1.5 is minimised over b, which
    a scan of b confirms; the 3-stage family can make it vanish."""
    found = core_design(2, np.array([1.5]), np.array([1.0]), 1.0)
    bs = np.linspace(0.15, 0.3, 30001)
    scan = rho_values(2, bs[:, None], np.array([1.5]))[:, 0]
    assert found.error_bound <= scan.min() * (1 + 1e-9) + 1e-300
    assert abs(found.params[0] - bs[int(np.argmin(scan))]) < 1e-4
    three = core_design(3, np.array([1.5]), np.array([1.0]), 1.0)
    assert three.error_bound < 1e-12


def test_the_method_file_is_accepted_by_every_command(run, tmp_path):
    out = tmp_path / "mine.yaml"
    code, text, err = run("design", "--sigma", "1", "--sigma", "0.1", "--step", "0.15",
                          "--stages", "3", "-o", str(out), "--json")
    assert code == 0, err
    data = json.loads(text)
    assert out.read_text() == data["method_file"]
    integrator = stepsafe.method_from_file(out)
    assert integrator.evaluations == 3 and integrator.order == 2
    b, a = data["params"]["b"], data["params"]["a"]
    direct = family_member(3, (b, a))
    z = np.linspace(0.1, 3.0, 7)
    assert np.allclose(stepsafe.transfer_matrices(integrator, z),
                       stepsafe.transfer_matrices(stepsafe.Integrator(
                           "x", "splitting", "", 2, 4, 3, "", True, direct, None), z),
                       rtol=1e-14, atol=1e-15)
    for args in (("region", str(out)), ("advise", "--method", str(out), "--beta", "3"),
                 ("hmc", "--methods", f"{out},verlet", "--sigma", "1")):
        code, _, err = run(*args)
        assert code == 0, (args, err)
    code, _, _ = run("check", "--method", str(out), "--beta", "1", "--step", "0.5")
    assert code == 0


@pytest.mark.parametrize("stages, rivals", [
    # verlet at h/2 is the 2-stage member b = 1/4, at h/3 the 3-stage member (1/6, 1/3)
    (2, ("verlet", "bcss2")),
    (3, ("verlet", "bcss3")),
])
def test_designed_beats_its_family_on_its_own_target(stages, rivals):
    """Predicted and measured: at the same gradient evaluations per unit time (each method
    at h * evaluations / stages) the designed member has the smallest error bound of its
    family, and HMC chains with it accept at least as often."""
    sigmas = np.linspace(0.1, 1.0, 40)
    # past z ~ 2.98 only members through M = -I are stable: the fastest mode stays below
    h = 0.2 if stages == 2 else 0.23
    report = design(sigma=list(sigmas), step=h, stages=stages, jitter=0.25)
    # the objective recomputed on its own: rho averaged over the jitter interval (400
    # points), for the family members the rivals are (verlet at h/2 is b = 1/4, at h/3
    # (b, a) = (1/6, 1/3))
    members = {"verlet": (0.25,) if stages == 2 else (1 / 6, 1 / 3), "bcss2": (0.21178,),
               "bcss3": (0.11888010966548, 0.29619504261126)}
    x = np.linspace(0.75 * h, 1.25 * h, 400)[:, None] / sigmas[None, :]

    def objective(params):
        return rho_values(stages, np.array([params]), x.ravel()).reshape(x.shape).mean(
            axis=0).sum()

    ours = objective(tuple(report.params.values()))
    for ref in rivals:
        assert ours < objective(members[ref])
    rng = np.random.default_rng(2)
    designed = stepsafe.Integrator("designed", "splitting", "", 2, stages + 1, stages, "",
                                       True, family_member(stages, tuple(
                                           report.params.values())), None)
    runs = []
    for integrator, step in [(designed, h)] + [
            (stepsafe.method(r), h * stepsafe.method(r).evaluations / stages) for r in rivals]:
        # trajectories of the same length in time; jitter averages over L theta
        runs.append(_run_hmc(integrator, 1.0 / sigmas ** 2, step, None, 64, 60, rng,
                             jitter=0.25, length=3.0))
    (m0, s0), *others = runs
    for name, (m, s) in zip(rivals, others):
        assert m0 > m - 3 * np.hypot(s0, s), (name, m0, m)


@pytest.mark.parametrize("kwargs, match", [
    ({"stages": 4}, "stages"),
    ({"stages": True}, "stages"),
    ({"step": 0.0}, "step"),
    ({"step": 50.0}, "no 2-stage member"),
    ({"name": "bad name"}, "name"),
    ({"name": "my_method"}, "name"),
    ({"name": "v1.2"}, "name"),
    ({"step": 3.5, "stages": 3, "jitter": 0.2}, "no 3-stage member"),
])
def test_bad_design_arguments(kwargs, match):
    args = {"step": 0.2, **kwargs}
    with pytest.raises(StepsafeError, match=match):
        design(sigma=[1.0, 0.1], **args)


def test_design_cli_errors(run, tmp_path):
    code, _, err = run("design", "--sigma", "1", "--step", "0.1", "-o", str(tmp_path))
    assert code == 2 and "directory" in err
    code, _, err = run("design", "--sigma", "1")
    assert code == 2 and "--step" in err
    code, _, err = run("design", "--sigma", "1", "--step", "0.1", "--stages", "4")
    assert code == 2


def test_designed_members_are_certified_stable_over_the_jitter():
    """Each design is confirmed by the region finder: |tr M| < 2 for every step up to
    h (1 + jitter) of every mode (a sampled check stepped over gaps 1e-3 wide)."""
    from stepsafe.core.regions import find_region, under_criterion

    for stages, h, jitter in ((3, 2.9, 0.0), (3, 2.6, 0.1), (2, 2.4, 0.05)):
        report = design(sigma=[1.0, 2.0], step=h, stages=stages, jitter=jitter)
        member = family_member(stages, tuple(report.params.values()))
        region = under_criterion(find_region(member, "oscillator", 5.0), "stability")
        first = region.first_interval
        assert first.hi is None or first.hi > h * (1 + jitter)


def test_the_comparison_averages_over_the_jitter():
    report = design(sigma=[1.0], step=2.3, jitter=0.2)
    rows = {r["method"]: r for r in report.comparison}
    assert rows["bcss2"]["error_bound"] is None  # unstable beyond z = 2.634 < 2.76
    assert rows["designed-2stage"]["acceptance"] > rows["bcss2"]["acceptance"]


# --- design's refusals against the family's exact stable set ------------------------------

def _tr_half_mp(stages, params, z):
    """tr M / 2 and M at 50 digits, straight from the kick/drift product (no formula)."""
    with mp.workdps(50):
        z = mp.mpf(z)
        if stages == 2:
            b = mp.mpf(params[0])
            ops = (("k", b), ("d", mp.mpf(1) / 2), ("k", 1 - 2 * b), ("d", mp.mpf(1) / 2),
                   ("k", b))
        else:
            b, a = (mp.mpf(p) for p in params)
            ops = (("k", b), ("d", a), ("k", mp.mpf(1) / 2 - b), ("d", 1 - 2 * a),
                   ("k", mp.mpf(1) / 2 - b), ("d", a), ("k", b))
        M = mp.eye(2)
        for kind, c in ops:
            M = (mp.matrix([[1, c * z], [0, 1]]) if kind == "d" else
                 mp.matrix([[1, 0], [-c * z, 1]])) * M
        return (M[0, 0] + M[1, 1]) / 2, M


def _bounded_at(stages, params, z):
    """|tr M| < 2, or M = +-I exactly (the stability criterion), at 50 digits (the
    comparisons too: abs() outside the context would round 1 - 5e-17 to 1)."""
    half, M = _tr_half_mp(stages, params, z)
    with mp.workdps(50):
        if abs(half) < 1:
            return True
        return abs(half) == 1 and M[0, 1] == 0 and M[1, 0] == 0


def test_the_quarter_member_is_bounded_up_to_4_and_only_it_beyond_2_sqrt_2():
    """b = 1/4 (two half-step leapfrogs): tr M/2 = -0.96875 at z = 3, M = -I exactly at
    z = 2 sqrt 2 (50 digits), unstable at 4; every other b is unstable at 2 sqrt 2; its rho
    (closed form through the resonance) against 40 digits."""
    from stepsafe.core.design import stable_b

    with mp.workdps(50):
        assert _tr_half_mp(2, (0.25,), 3)[0] == mp.mpf("-0.96875")
        half, M = _tr_half_mp(2, (0.25,), mp.sqrt(8))
        assert abs(half + 1) < mp.mpf(10) ** -45 and mp.norm(M + mp.eye(2)) < mp.mpf(10) ** -45
        assert not _bounded_at(2, (0.25,), 4)
        for b in (0.25 - 1e-9, 0.25 + 1e-9, 0.2, 0.3):
            assert _tr_half_mp(2, (b,), mp.sqrt(8))[0] < -1
    for z in (1.0, 2.8, 2.83, 3.5, 3.99):
        assert rho_values(2, np.array([[0.25]]), np.array([z]))[0, 0] == pytest.approx(
            float(_rho_mp(0.25, z)), rel=1e-9)
    assert stable_b(3.0) == (0.25, 0.25) and stable_b(4.0) is None
    # the interval's ends are the roots in b of tr M = -2 at Z: just inside stable, outside not
    for Z in (2.2, 2.5, 2.8):
        lo, hi = stable_b(Z)
        for b, inside in ((lo, True), (hi, True), (lo - 1e-9, False), (hi + 1e-9, False)):
            assert _bounded_at(2, (b,), Z) is inside


def _refusal_is_true(stages, top):  # stages == 2
    """No member of the family is bounded for every z up to top: a grid of members plus
    the exact roots (b = 2/Z^2, 1/2 - 2/Z^2, 1/4), each shown unbounded at 50 digits at
    z = top or 2 sqrt 2 (where the stable set closes: module docstring)."""
    members = [(b,) for b in np.linspace(1e-3, 0.5 - 1e-3, 400)]
    members += [(2 / top ** 2,), (0.5 - 2 / top ** 2,), (0.25,)]
    zs = (top, mp.sqrt(8))
    return all(not all(_bounded_at(stages, m, z) for z in zs if z <= top) for m in members)


def _design_is_stable(stages, params, zs, jitter):
    """Every mode bounded over its whole jitter interval at 50 digits."""
    return all(_bounded_at(stages, params, z * (1 + jitter * u))
               for z in zs for u in np.linspace(-1.0, 1.0, 21))


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@pytest.mark.slow
@settings(max_examples=25, deadline=None)
@given(scale=st.floats(-3.0, 3.0), spread=st.floats(1.0, 20.0),
       top=st.floats(2.4, 4.4), jitter=st.sampled_from((0.0, 0.1, 0.3, 0.6)))
def test_two_stage_design_refuses_only_when_no_member_is_stable(scale, spread, top, jitter):
    sigma = [10.0 ** scale, 10.0 ** scale * spread]
    step = top * 10.0 ** scale / (1.0 + jitter)
    zs = [step / s for s in sigma]
    try:
        report = design(sigma=sigma, step=step, jitter=jitter)
    except StepsafeError as exc:
        assert "no 2-stage member" in str(exc)
        assert top >= 4.0 * (1 - 1e-12) and _refusal_is_true(2, top)
        return
    assert top < 4.0 * (1 + 1e-12)
    assert _design_is_stable(2, tuple(report.params.values()), zs, jitter)


@pytest.mark.parametrize("step, jitter", [(3.0, 0.0), (2.0, 0.6), (3.99, 0.0)])
def test_a_jitter_top_between_two_root_two_and_four_gets_the_quarter_member(step, jitter,
                                                                             run):
    """Where the top of the jitter interval, z = h (1 + J), lies in [2 sqrt 2, 4), b = 1/4
    is the only stable 2-stage member, and it is the design."""
    code, text, err = run("design", "--sigma", "1", "--step", str(step), "--jitter",
                          str(jitter), "--json")
    assert code == 0, err
    assert json.loads(text)["params"] == {"b": 0.25}
    code, _, err = run("design", "--sigma", "1", "--step", "4")
    assert code == 2 and "end at h = 4" in err


BCSS3 = (0.11888010966548, 0.29619504261126)
THIRDS = (1 / 6, 1 / 3)  # three third-step leapfrogs


def _touch(params, near):
    """The least ``tr M / 2 + 1`` at 50 digits near z = ``near`` (golden-section search
    on [near - 0.05, near + 0.05], where ``tr M / 2`` has one minimum): negative by the
    depth of the gap the member's float coefficients leave at its M = -I point."""
    with mp.workdps(50):
        lo, hi = mp.mpf(near) - mp.mpf("0.05"), mp.mpf(near) + mp.mpf("0.05")
        ratio = (mp.sqrt(5) - 1) / 2
        for _ in range(200):
            a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
            if _tr_half_mp(3, params, a)[0] < _tr_half_mp(3, params, b)[0]:
                hi = b
            else:
                lo = a
        return _tr_half_mp(3, params, (lo + hi) / 2)[0] + 1


@pytest.mark.parametrize("top, jitter", [(2.9, 0.0), (2.7, 0.1), (3.2, 0.0), (4.2, 0.1),
                                         (5.9, 0.0), (6.0, 0.0)])
def test_three_stage_design_against_the_end_of_its_stable_range(top, jitter):
    """Below z = 3 the design is bounded over its jitter interval at 50 digits. From 3 to 6
    only members whose tr M touches -2 (M = -I) are stable, and the design is one of the
    two known ones, bcss3 (to 4.66) or three third-step leapfrogs (1/6, 1/3) (to 6): at 50
    digits their float coefficients leave a gap at the touch, 3.2e-27 deep for bcss3 and
    1e-33 for (1/6, 1/3) (their exact M = -I is not representable), within the rounding
    that the rule hmc and design share passes over; elsewhere on the jitter interval they
    are bounded. From 6 = 2s on the design is refused."""
    step = top / (1.0 + jitter)
    if top >= 6.0:
        with pytest.raises(StepsafeError, match="no 3-stage member.*end at h = 6"):
            design(sigma=[1.0], step=step, stages=3, jitter=jitter)
        return
    params = tuple(design(sigma=[1.0], step=step, stages=3, jitter=jitter).params.values())
    if top < 3.0:
        assert _design_is_stable(3, params, [step], jitter)
        return
    assert params in (BCSS3, THIRDS)
    near = 2.9763246405798 if params == BCSS3 else 3.0
    assert -mp.mpf("1e-25") < _touch(params, near) < 0
    if params == THIRDS:
        assert not _bounded_at(3, params, 3)  # the gap at z = 3 itself
    assert all(_bounded_at(3, params, step * (1 + jitter * u))
               for u in np.linspace(-1.0, 1.0, 21) if abs(step * (1 + jitter * u) - near) > 1e-6)


@pytest.mark.slow
@settings(max_examples=6, deadline=None)
@given(exponent=st.floats(-200.0, 200.0), spread=st.floats(1.0, 10.0),
       count=st.integers(1, 4), top=st.floats(2.5, 4.6),
       jitter=st.sampled_from((0.0, 0.1, 0.25)))
def test_design_and_hmc_apply_one_rule_to_rounding_gaps(exponent, spread, count, top, jitter):
    """Where hmc finds bcss3 stable for every jittered step (its M = -I point at z = 2.976,
    a rounding gap, excluded but not an end), design --stages 3 designs a member (bcss3
    is one); a design it makes, hmc finds stable for every jittered step; a refusal comes
    only where hmc finds bcss3 unstable too."""
    sigmas = list(10.0 ** exponent * np.geomspace(1.0, spread, count))
    step = top * min(sigmas) / (1.0 + jitter)
    bcss3 = hmc(["bcss3"], sigma=sigmas).rows[0]
    try:
        report = design(sigma=sigmas, step=step, stages=3, jitter=jitter)
    except StepsafeError as exc:
        assert "no 3-stage member" in str(exc)
        assert bcss3.stability_h < step * (1.0 + jitter)
        return
    params = tuple(report.params.values())
    designed = stepsafe.Integrator("designed", "splitting", "", 2, 4, 3, "", True,
                                       family_member(3, params), None)
    row = hmc([designed], sigma=sigmas).rows[0]
    assert row.stability_h >= step * (1.0 + jitter) * (1 - 1e-12)
    resonances = report.comparison[0]["resonance_h"]
    assert list(resonances) == [h for h in row.resonance_h
                                if h <= step * (1.0 + jitter) * (1 + 1e-12)]


@pytest.mark.slow
def test_the_rule_for_rounding_gaps_is_stated_by_both_commands(run):
    """The HMC guide's target at bcss3's step at target there (0.354016, z = 3.54, past its
    M = -I point at 2.976, where hmc ranks it first): design --stages 3 designs, and both
    commands state the rule in text and JSON."""
    target = str(Path(__file__).parents[1] / "examples" / "gaussian-1000.csv")
    code, out, err = run("design", "--modes", target, "--step", "0.354016", "--stages", "3",
                         "--jitter", "0.1", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert "continue past it" in data["rounding_gaps"]
    assert data["comparison"][0]["resonance_h"] == pytest.approx([0.2976324640579853])
    code, out, err = run("design", "--sigma", "0.1", "--sigma", "1", "--step", "0.354016",
                         "--stages", "3", "--jitter", "0.1")
    assert code == 0 and "M = ±I within rounding" in out and "as hmc counts it" in out
    code, out, err = run("hmc", "--sigma", "0.1", "--sigma", "1", "--methods", "bcss3",
                         "--json")
    assert "continue past it" in json.loads(out)["rounding_gaps"]
    code, out, err = run("hmc", "--sigma", "0.1", "--sigma", "1", "--methods", "bcss3")
    assert "M = ±I within rounding" in out and "as design counts it" in out


@pytest.mark.parametrize("relative", [0.0, 1e-16, 2e-16, 3e-13, 2e-10, 6e-10])
def test_steps_just_below_two_root_two_get_a_stable_design(run, relative):
    """Just below z = 2 sqrt 2 the stable interval of b is narrower than the rounding of
    its ends, or its members too close to M = -I for float64's error bound: b = 1/4
    (stable on all of (0, 4)) is designed instead of a refusal."""
    import mpmath as mp

    step = 2 * math.sqrt(2) * (1 - relative)
    code, out, err = run("design", "--sigma", "1", "--step", repr(step))
    assert code == 0, err
    b = float(out.split("b = ")[1].split(",")[0])
    with mp.workdps(50):
        z, bb = mp.mpf(step), mp.mpf(b)
        half_trace = 1 - z ** 2 / 2 + bb * (1 - 2 * bb) * z ** 4 / 4
        assert abs(half_trace) <= 1


def test_a_step_at_the_familys_limit_within_an_ulp_is_refused():
    """sigma = 10^1.5, h = 4 sigma: z = h / sigma rounds to 4, where b = 1/4 is not stable,
    although 1/sigma rounded down makes z = 4 - 4e-16."""
    sigma = 10.0 ** 1.5
    with pytest.raises(StepsafeError, match="no 2-stage member"):
        design(sigma=[sigma, sigma], step=4.0 * sigma)


@pytest.mark.parametrize("slow", [1.0, 1e6, 1e150])
def test_a_mode_far_slower_than_the_rest_does_not_change_the_design(slow):
    """A mode at z = 1.5e-12, where tr M / 2 rounds to 1, adds ~z^4 to the objective: its
    rho must be computed without that rounding (as inf, every member would score inf)."""
    fast = 1e-12 * slow
    alone = design(sigma=[fast], step=1.5 * fast).params["b"]
    both = design(sigma=[slow, fast], step=1.5 * fast).params["b"]
    assert abs(both - alone) < 1e-9 and abs(alone - 0.25) > 0.01


def test_a_mode_resolved_beyond_float_range_does_not_change_the_design():
    """A slow mode with z = beta h = 1e-200 has rho = O(z^4) = 0 in float64 (its z^2
    underflows, which must not make a member 'not elliptic'): the design is the fast
    mode's alone."""
    import stepsafe

    alone = stepsafe.design(sigma=[1e-200], step=1e-200)
    both = stepsafe.design(sigma=[1e-200, 1.0], step=1e-200)
    assert both.params == pytest.approx(alone.params, rel=1e-12)
    assert both.params["b"] != 0.25
