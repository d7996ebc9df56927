"""advise and check: agreement with region, islands, margins, exit codes, extremes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from support import method

from stepsafe.core.advice import Modes, advise, check_step
from stepsafe.core.models import MODELS
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import has_form
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.library import builtin_names

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = [n for n in builtin_names(single_force=True) if n not in ("gauss", "lobatto3ab", "rk4")]
BETA_SETS = [(1.0,), (3.2, 0.7, 0.01), (2.0, 2.0, 1e-3)]


@pytest.mark.parametrize("name", LIBRARY)
def test_advise_agrees_with_region(name):
    m = method(name)
    for model in MODELS:
        if not has_form(m, model):  # force-gradient methods: no saddle form
            with pytest.raises(StepsafeError, match="force-gradient"):
                advise(m, Modes.from_arrays({model: np.array([1.0])}))
            continue
        region = find_region(m, model)
        for betas in BETA_SETS:
            adv = advise(m, Modes.from_arrays({model: np.array(betas)}))
            z_star = region.first_boundary
            if z_star is None:
                assert adv.h_max == pytest.approx(region.zmax / max(betas), rel=1e-9)
                continue
            # h_max stays below z*/beta by the boundary's float64 uncertainty
            unc = region.first_boundary_point.uncertainty + 1e-12 * z_star
            assert z_star / max(betas) - unc / max(betas) <= adv.h_max <= z_star / max(betas)
            assert adv.limiting.model == model and adv.limiting.beta_max == max(betas)
            h_in, h_out = 0.99 * adv.h_max, 1.01 * adv.h_max
            assert check_step(m, Modes.from_arrays({model: np.array(betas)}), h_in).safe
            out = check_step(m, Modes.from_arrays({model: np.array(betas)}), h_out)
            status = [s for iv in region.intervals for s in [iv.contains(max(betas) * h_out)]]
            assert out.safe == any(status)


def test_island_is_safe_but_flagged():
    m = method("lobatto3ab", 4)
    region = find_region(m, "oscillator")
    island = next(iv for iv, same in region.islands if same)
    h = 0.5 * (island.lo + island.hi)  # beta = 1
    result = check_step(m, Modes.from_pairs([(1.0, "oscillator")]), h)
    assert result.safe and not result.in_primary
    adv = advise(m, Modes.from_pairs([(1.0, "oscillator")]))
    assert any(lo > 0 and lo <= h <= hi for lo, hi in adv.safe_h if hi is not None)


def test_reversed_island_is_unsafe():
    m = method("lobatto3ab", 3)
    result = check_step(m, Modes.from_pairs([(1.0, "oscillator")]), 4.0)  # in (sqrt12, sqrt24)
    assert not result.safe and "first boundary" in result.failures[0].reason


def test_islands_are_intersected_across_modes():
    m = method("lobatto3ab", 4)
    one = advise(m, Modes.from_pairs([(1.0, "oscillator")]))
    two = advise(m, Modes.from_pairs([(1.0, "oscillator"), (1.1, "oscillator")]))
    assert len(one.safe_h) == 2
    # the second frequency's island (7.746/1.1, 8.620/1.1) = (7.04, 7.84) overlaps the
    # first's (7.746, 8.620) in (7.746, 7.837)
    lo, hi = two.safe_h[1]
    assert lo == pytest.approx(7.745966692414834, rel=1e-9)
    assert hi == pytest.approx(8.62038217498546 / 1.1, rel=1e-9)


def test_margin_scales_h_max():
    m = method("verlet")
    adv = advise(m, Modes.from_pairs([(4.0, "oscillator")]), margin=0.8)
    assert adv.h_max == pytest.approx(0.8 * 2.0 / 4.0, rel=1e-12)
    assert check_step(m, Modes.from_pairs([(4.0, "oscillator")]), 0.41, margin=0.8).safe is False
    assert check_step(m, Modes.from_pairs([(4.0, "oscillator")]), 0.39, margin=0.8).safe


def test_paper_section3_symplectic_euler_saddle():
    m = method("symplectic-euler")
    modes = Modes.from_pairs([(2.0, "saddle")])  # alpha = 2
    assert advise(m, modes).h_max == pytest.approx(0.5, rel=1e-12)
    assert check_step(m, modes, 0.49).safe
    bad = check_step(m, modes, 0.5)  # alpha h = 1: the pole
    assert not bad.safe and "pole" in bad.failures[0].reason


def test_resonance_and_pole_steps_are_unsafe():
    g2 = method("gauss", 2)
    on = check_step(g2, Modes.from_pairs([(1.0, "oscillator")]), 2 * math.sqrt(3))
    assert not on.safe and "resonance" in on.failures[0].reason
    mid = check_step(method("midpoint"), Modes.from_pairs([(1.0, "saddle")]), 2.0)
    assert not mid.safe and "pole" in mid.failures[0].reason


def test_beta_spanning_twelve_decades_and_zero():
    m = method("pefrl")
    betas = np.array([0.0, 1e-6, 1.0, 1e6])
    adv = advise(m, Modes.from_arrays({"oscillator": betas}))
    z_star = find_region(m, "oscillator").first_boundary
    assert adv.h_max == pytest.approx(z_star / 1e6, rel=1e-12)
    free = advise(m, Modes.from_arrays({"oscillator": np.array([0.0])}))
    assert free.safe_h == ((0.0, None),) and free.h_max is None
    wide = np.array([1e-12, 1e12])
    assert advise(m, Modes.from_arrays({"oscillator": wide})).h_max == pytest.approx(
        z_star / 1e12, rel=1e-12)


def test_a_million_frequencies():
    betas = np.exp(np.random.default_rng(1).uniform(np.log(1e-3), np.log(1e3), 10**6))
    adv = advise(method("verlet"), Modes.from_arrays({"oscillator": betas}))
    assert adv.h_max == pytest.approx(2.0 / betas.max(), rel=1e-12)


def test_non_symplectic_method_has_no_safe_step():
    adv = advise(method("rk4"), Modes.from_pairs([(1.0, "oscillator")]))
    assert adv.h_max == 0.0 and adv.safe_h == ()


# ---------------------------------------------------------------- CLI and exit codes


def test_exit_codes(run):
    assert run("check", "--method", "verlet", "--h", "0.1", "--beta", "12")[0] == 0
    code, out, _ = run("check", "--method", "verlet", "--h", "0.2", "--beta", "12")
    assert code == 1 and "UNSAFE" in out and "z = beta*h = 2.4" in out
    assert run("check", "--method", "verlet", "--h", "0.1")[0] == 2


def test_advise_json(run_json):
    data = run_json("advise", "--method", "yoshida4", "--beta", "3.2", "--inverted-beta", "1.1",
                    "--saddle-beta", "0.4")
    assert data["method"] == "yoshida4"
    assert data["h_max"] == pytest.approx(1.573401947434541 / 3.2, rel=1e-12)
    assert data["safe_h"][0][0] == 0.0 and data["limiting"] == data["models"]["oscillator"]
    assert data["limiting"]["beta"] == 3.2
    assert set(data["models"]) == {"oscillator", "inverted", "saddle"}
    assert all("first_boundary" in v for v in data["models"].values())


def test_check_json_failure_reasons(run):
    code, out, _ = run("check", str(ROOT / "examples/paper-section3.yaml"),
                       "--json")
    data = json.loads(out)
    assert code == 1 and data["safe"] is False
    (entry,) = data["checks"]
    assert entry["safe"] is False and entry["scene"].endswith("paper-section3.yaml")
    (fail,) = entry["failures"]
    assert fail["model"] == "saddle" and fail["z"] == pytest.approx(1.2)
    assert fail["largest_safe_h"] == pytest.approx(0.5)


def test_scene_file_and_overrides(run, tmp_path):
    scene = ROOT / "examples" / "scene.yaml"
    assert run("check", str(scene))[0] == 0
    assert run("check", str(scene), "--h", "0.5")[0] == 1
    assert run("check", str(scene), "--method", "verlet")[0] == 0
    code, out, _ = run("advise", str(scene), "--json")
    assert code == 0 and json.loads(out)["margin"] == 0.9


def test_modes_files_yaml_and_csv(run_json, tmp_path):
    csv = tmp_path / "modes.csv"
    csv.write_text("beta,model\n3.2,oscillator\n1.1,inverted\n0,oscillator\n")
    data = run_json("advise", "--method", "verlet", "--modes", str(csv))
    assert data["models"]["oscillator"]["count"] == 2
    assert data["h_max"] == pytest.approx(2 / 3.2, rel=1e-12)
    yml = tmp_path / "modes.yaml"
    yml.write_text("- {beta: 4, model: oscillator}\n- {beta: 1, model: saddle}\n")
    data = run_json("advise", "--method", "verlet", "--modes", str(yml))
    assert data["h_max"] == pytest.approx(0.5, rel=1e-12)


def test_a_million_frequencies_from_csv(run_json, tmp_path):
    betas = np.random.default_rng(2).uniform(0.1, 10.0, 10**6)
    path = tmp_path / "many.csv"
    path.write_text("beta\n" + "\n".join(f"{b:.17g}" for b in betas) + "\n")
    data = run_json("advise", "--method", "pefrl", "--modes", str(path))
    assert data["models"]["oscillator"]["count"] == 10**6
    # the largest frequency alone sets the limit (every other z is below pefrl's z*)
    alone = run_json("advise", "--method", "pefrl", "--beta", repr(float(betas.max())))
    assert data["h_max"] == alone["h_max"]


@pytest.mark.parametrize("args, message", [
    (["advise", "--method", "verlet", "--beta", "nan"], "beta must be a finite"),
    (["advise", "--method", "verlet", "--beta", "inf"], "beta must be a finite"),
    (["advise", "--method", "verlet", "--beta", "-1"], "beta must be a finite"),
    (["advise", "--method", "verlet", "--beta", "1", "--margin", "0"], "margin must be in"),
    (["advise", "--method", "verlet", "--beta", "1", "--margin", "1.01"], "margin must be in"),
    (["advise", "--method", "verlet", "--beta", "1", "--margin", "nan"], "margin must be in"),
    (["advise", "--method", "verlet"], "no frequencies"),
    (["advise", "--beta", "1"], "no method"),
    (["check", "--method", "verlet", "--beta", "1", "--h", "-0.1"], "h must be a positive"),
    (["check", "--method", "verlet", "--beta", "1", "--h", "inf"], "h must be a positive"),
    (["check", "--method", "verlet", "--beta", "1", "--h", "0"], "h must be a positive"),
    (["advise", "--method", "verlet", "--modes", "missing.csv"], "no such file"),
])
def test_bad_advice_input_exit_2(run, args, message):
    code, out, err = run(*args)
    assert code == 2 and message in err and "Traceback" not in err + out


def test_bad_scene_files(run, tmp_path):
    cases = {
        "method: verlet\nh: 0.1\nmodes: [{beta: 1, model: wobble}]\n": "$.modes[0].model",
        "method: verlet\nh: fast\nmodes: [{beta: 1}]\n": "$.h: must be a number",
        "method: verlet\nmodes: [{beta: x}]\n": "$.modes[0].beta",
        "method: verlet\nh: 0.1\nsystem: {hessian: [[1]]}\n":
            "$.system.hessian: hessian must be 2n x 2n",
        "method: verlet\nh: 0.1\nmodes: []\n": "$.modes: must be a non-empty list",
        "colour: red\n": "$.colour: unknown key",
    }
    for text, message in cases.items():
        path = tmp_path / "scene.yaml"
        path.write_text(text)
        code, _, err = run("check", str(path))
        assert code == 2 and message in err, (text, err)


def test_one_ulp_around_a_boundary_is_consistent_with_region():
    """One ulp above z*: region and check agree it is lost. One ulp below: within the
    boundary's stated float64 uncertainty, which the interval leaves out; check refuses to
    certify it and says so (never a 'safe' that the uncertainty cannot back). Just inside
    the interval's end both say preserved."""
    m = method("pefrl")
    region = find_region(m, "oscillator")
    z_star, unc = region.first_boundary, region.first_boundary_point.uncertainty
    end = region.intervals[0].hi
    assert unc > 0 and end == z_star - unc
    modes = Modes.from_pairs([(1.0, "oscillator")])
    above = check_step(m, modes, np.nextafter(z_star, np.inf))
    assert not above.safe and not region.intervals[0].contains(np.nextafter(z_star, np.inf))
    below = check_step(m, modes, np.nextafter(z_star, 0))
    assert not region.intervals[0].contains(np.nextafter(z_star, 0))
    assert not below.safe and "uncertainty" in below.failures[0].reason
    assert region.intervals[0].contains(z_star - 2 * unc)
    assert check_step(m, modes, z_star - 2 * unc).safe


def test_steps_far_beyond_float64_range_of_m(run):
    """z = beta*h = 1e200. Verlet on a barrier: tr M = 2 + z^2 and M_qp = z (1 + z^2/4) > 0
    for every z, so every step keeps the structure, although M itself overflows float64
    there (the polynomial's root bound shows nothing changes beyond z ~ 3). kahan-li8 on
    the saddle: M overflows long before; that range is not analysed, so not safe."""
    code, out, _ = run("check", "--method", "verlet", "--inverted-beta", "1e100", "--h", "1e100")
    assert code == 0 and "SAFE" in out
    code, out, _ = run("check", "--method", "kahan-li8", "--saddle-beta", "1e100", "--h", "1e100")
    assert code == 1 and "UNSAFE" in out


@pytest.mark.parametrize("seed", range(4))
def test_dropping_modes_that_cannot_reach_the_horizon_changes_nothing(seed, monkeypatch):
    """advise drops, before sorting, modes whose every gap starts above the horizon; the
    answer (islands included) equals the one from every mode."""
    from stepsafe.core import advice as A

    rng = np.random.default_rng(seed)
    if seed < 2:  # many modes over six decades
        betas = {"oscillator": np.exp(rng.uniform(-4, 2, 300)), "saddle": rng.uniform(0, 3, 40)}
    else:  # two fast modes close enough to share an island, many slow ones
        betas = {"oscillator": np.concatenate([[1.0, 1.005], np.exp(rng.uniform(-9, -4, 298))])}
    betas["oscillator"][-3:] = 0.0
    errors = {"oscillator": rng.uniform(0, 1e-4, 300)}
    modes = A.Modes.from_arrays(betas, errors)
    name = ("yoshida4", "blanes-moan6", "pefrl", "kahan-li8")[seed]
    margin = 0.95 if seed < 2 else 1.0  # (a margin closes the islands)
    fast = A.advise(method(name), modes, margin=margin, zmax=30.0)
    assert seed < 2 or len(fast.safe_h) > 1  # islands are part of what is compared
    monkeypatch.setattr(A, "_above", lambda b, e, floor: (
        b[b > 0], np.zeros(int((b > 0).sum())) if e is None else e[b > 0]))
    slow = A.advise(method(name), modes, margin=margin, zmax=30.0)
    assert fast.safe_h == slow.safe_h and fast.h_max == slow.h_max
    assert fast.horizon == slow.horizon
