"""``--criterion stability`` (the type only) against ``structure`` (type and orientation).

The stability interval of bcss3 (|tr M| <= 2 from 0) is pinned at 50 digits from its
drift/kick product; the M = -I point of bcss3 is, at 60 digits, a gap 1e-13 wide where
tr M < -2, so it stays excluded under either criterion.
"""

from __future__ import annotations

import json
import math

import mpmath as mp
import pytest

import stepsafe
from stepsafe.exceptions import StepsafeError


def _bcss3(z):
    b, a = mp.mpf("0.11888010966548"), mp.mpf("0.29619504261126")
    M = mp.eye(2)
    for kind, c in (("k", b), ("d", a), ("k", mp.mpf(1) / 2 - b), ("d", 1 - 2 * a),
                    ("k", mp.mpf(1) / 2 - b), ("d", a), ("k", b)):
        step = (mp.matrix([[1, c * z], [0, 1]]) if kind == "d" else
                mp.matrix([[1, 0], [-c * z, 1]]))
        M = step * M
    return M


def test_bcss3_stability_interval_at_50_digits():
    with mp.workdps(50):
        z_end = mp.findroot(lambda z: (lambda M: M[0, 0] + M[1, 1] - 2)(_bcss3(z)),
                            (4.6, 4.7), solver="anderson")
        z_b = mp.findroot(lambda z: _bcss3(z)[0, 1], (2.95, 3.0), solver="anderson")
        z_c = mp.findroot(lambda z: _bcss3(z)[1, 0], (2.95, 3.0), solver="anderson")
    assert abs(z_b - z_c) > 1e-14  # a real gap where tr M < -2, not a touch
    report = stepsafe.region("bcss3", "oscillator", criterion="stability")
    osc = report.regions["oscillator"]
    assert osc.criterion == "stability" and osc.reversed == ()
    (lo1, hi1), (lo2, hi2) = [(iv.lo, iv.hi) for iv in osc.intervals[:2]]
    res = osc.resonances[0]
    # the two intervals end and start at the edges of the resonance's band
    assert lo1 == 0.0 and (hi1, lo2) == (res.z - res.uncertainty, res.z + res.uncertainty)
    assert abs(hi2 - float(z_end)) < 1e-12 * float(z_end)
    assert abs(res.z - float(z_b)) <= res.uncertainty  # the gap lies within its uncertainty
    assert report.to_dict()["models"]["oscillator"]["structure_first_boundary"] == \
        pytest.approx(res.z, rel=1e-15)


def test_check_exit_codes_follow_the_criterion(run):
    code, out, _ = run("check", "--method", "bcss3", "--beta", "1", "--step", "3.5",
                       "--criterion", "stability")
    assert code == 0 and "SAFE" in out and "unsafe under it" in out
    code, out, _ = run("check", "--method", "bcss3", "--beta", "1", "--step", "3.5")
    assert code == 1 and "safe under it" in out
    # on the resonance itself: unsafe under both (a gap 1e-13 wide at 60 digits)
    code, _, _ = run("check", "--method", "bcss3", "--beta", "1", "--step",
                     "2.9763246405798", "--criterion", "stability")
    assert code == 1


def test_lobatto_island_of_reversed_orientation_joins_under_stability(run_json):
    data = run_json("region", "lobatto3ab", "-s", "3", "--model", "oscillator",
                    "--criterion", "stability")
    osc = data["models"]["oscillator"]
    assert data["criterion"] == "stability" and osc["criterion"] == "stability"
    assert osc["intervals"][1] == pytest.approx([math.sqrt(12), math.sqrt(24)], rel=1e-13)
    assert osc["islands"][0]["orientation"] == "any"
    adv = run_json("advise", "--method", "lobatto3ab", "-s", "3", "--beta", "1",
                   "--criterion", "stability")
    assert adv["criterion"] == "stability"
    assert adv["safe_h"][1] == pytest.approx([math.sqrt(12), math.sqrt(24)], rel=1e-12)
    other = adv["other_criterion"]
    assert other["criterion"] == "structure" and len(other["safe_h"]) == 1


def test_identical_answers_are_not_repeated():
    report = stepsafe.advise("verlet", [1.0], criterion="stability")
    assert "other_criterion" not in report.record and report.record["criterion"] == "stability"


def test_hyperbolic_models_keep_the_type_only():
    """Gauss s=2 on the barrier: the structure region ends at its pole; under stability the
    type (tr M > 2) is what counts, so the stability set contains the structure set."""
    for name in ("gauss", "lobatto3ab"):
        for model in ("saddle", "inverted"):
            full = stepsafe.region(stepsafe.method(name, stages=3), model).regions[model]
            typ = stepsafe.region(stepsafe.method(name, stages=3), model,
                                  criterion="stability").regions[model]
            for iv in full.intervals:
                assert any(t.lo <= iv.lo and (t.hi is None or (iv.hi is not None
                                                               and iv.hi <= t.hi))
                           for t in typ.intervals)


@pytest.mark.parametrize("bad", ["Stability", "", 3, 1.0, b"structure"])
def test_bad_criterion_is_refused(bad):
    with pytest.raises(StepsafeError, match="criterion must be one of"):
        stepsafe.advise("verlet", [1.0], criterion=bad)


def test_no_criterion_is_the_methods_own():
    """``criterion=None`` (the default) is ``structure`` for a Hamiltonian method and
    ``stability`` for a Langevin splitting, the only one that applies to it."""
    assert stepsafe.advise("verlet", [1.0]).record["criterion"] == "structure"
    assert stepsafe.advise("verlet", [1.0], criterion=None).h_max == \
        stepsafe.advise("verlet", [1.0], criterion="structure").h_max
    assert stepsafe.advise("baoab", [1.0]).record["criterion"] == "stability"
    assert stepsafe.check("obabo", 0.5, [1.0]).record["criterion"] == "stability"
    assert stepsafe.region("aboba").to_dict()["criterion"] == "stability"


def test_bad_criterion_on_the_command_line(run):
    code, _, err = run("advise", "--method", "verlet", "--beta", "1", "--criterion", "type")
    assert code == 2 and "--criterion" in err


def test_coupled_systems_refuse_the_stability_criterion(tmp_path, run):
    scene = tmp_path / "coupled.yaml"
    scene.write_text("method: verlet\nsystem:\n  hessian: [[2, 0.5, 0, 0.3], [0.5, 1, 0.2, 0],"
                     " [0, 0.2, 1, 0], [0.3, 0, 0, 1]]\n")
    code, _, err = run("advise", str(scene), "--criterion", "stability")
    assert code == 2 and "couple" in err
    code, out, _ = run("advise", str(scene), "--json")
    assert code == 0 and json.loads(out)["criterion"] == "structure"


@pytest.mark.parametrize("scale", [1e-300, 1e-150, 1e150, 1e300])
def test_stability_verdicts_are_scale_free(scale):
    """The same z = beta h gives the same stability verdict at every scale, including the
    island past bcss3's M = -I point and steps past the stability limit (beta h to 1e12)."""
    for z in (1.0, 2.9763, 3.5, 4.7, 1e3, 1e12):
        if not math.isfinite(z / scale):
            continue
        ref = stepsafe.check("bcss3", z, [1.0], criterion="stability").safe
        got = stepsafe.check("bcss3", z / scale, [scale], criterion="stability").safe
        assert got == ref, (scale, z)
    assert stepsafe.check("bcss3", 3.5, [1.0], criterion="stability").safe
    assert not stepsafe.check("bcss3", 4.7, [1.0], criterion="stability").safe
