"""--verify: every reported point recomputed with mpmath; a wrong float answer exits 3."""

from __future__ import annotations

import dataclasses
import json

import stepsafe.core.regions as regions_module
from stepsafe.core.regions import Point


def test_region_verify_json(run_json):
    data = run_json("region", "lobatto3ab", "-s", "4", "--verify")
    v = data["verify"]
    assert v["ok"] and v["digits"] == 40 and v["points"] >= 5
    assert v["largest_discrepancy"] < 1e-12


def test_advise_and_check_verify(run, run_json):
    data = run_json("advise", "--method", "pefrl", "--beta", "2", "--saddle-beta", "1",
                    "--verify")
    assert data["verify"]["ok"] and data["verify"]["points"] >= 2
    code, out, _ = run("check", "--method", "verlet", "--h", "0.3", "--beta", "12", "--verify")
    assert code == 1 and "verify:" in out and "ok" in out


def test_a_wrong_float_answer_fails_verification(run, monkeypatch):
    real = regions_module.find_region

    def shifted(method, model="oscillator", zmax=10.0, resolution=None):
        region = real(method, model, zmax, resolution)
        first = region.intervals[0]
        p = first.hi_point
        if p is None:
            return region
        bad = Point(p.z * (1 + 1e-6), p.kind, p.uncertainty, p.detail)
        return dataclasses.replace(region, intervals=(first._replace(hi=bad.z, hi_point=bad),)
                                   + region.intervals[1:])

    monkeypatch.setattr(regions_module, "find_region", shifted)
    code, out, err = run("region", "verlet", "--model", "oscillator", "--verify", "--json")
    assert code == 3
    assert json.loads(out)["verify"]["ok"] is False
    assert "verification failed" in err and "Traceback" not in err


def test_verify_at_tiny_z_and_on_a_processed_saddle(run, tmp_path):
    """--verify raises its precision where the deciding quantity is tiny (2 - tr M = z^2 =
    1e-42 at z = 1e-21 was 'reference None', exit 3), and takes a processed method on the
    saddle as its kernel, as the float analysis does (P commutes with K there): review 23."""
    code, out, err = run("region", "verlet", "--zmax", "1e-12", "--verify")
    assert code == 0, out + err
    path = tmp_path / "proc.yaml"
    path.write_text('name: proc1\nkind: processed\norder: 2\nsource: test\nkernel: verlet\n'
                    'processor: {drift: ["0.25"], kick: ["0"]}\n')
    code, out, err = run("check", "--method", str(path), "--saddle-beta", "1", "--step", "1",
                         "--verify")
    assert code == 0 and "SAFE" in out, out + err
