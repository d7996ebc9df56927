"""--verify: every reported point recomputed with mpmath; a wrong float answer exits 3."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe.api.linear as linear_api
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

    monkeypatch.setattr(linear_api, "find_region", shifted)
    code, out, err = run("region", "verlet", "--model", "oscillator", "--verify", "--json")
    assert code == 3
    assert json.loads(out)["verify"]["ok"] is False
    assert "verification failed" in err and "Traceback" not in err


def test_verify_at_tiny_z_and_on_a_processed_saddle(run, tmp_path):
    """--verify raises its precision where the deciding quantity is tiny (2 - tr M = z^2 =
    1e-42 at z = 1e-21: the reference decides it, exit 0), and takes a processed method on
    the saddle as its kernel, as the float analysis does (P commutes with K there)."""
    code, out, err = run("region", "verlet", "--zmax", "1e-12", "--verify")
    assert code == 0, out + err
    path = tmp_path / "proc.yaml"
    path.write_text('name: proc1\nkind: processed\norder: 2\nsource: test\nkernel: verlet\n'
                    'processor: {drift: ["0.25"], kick: ["0"]}\n')
    code, out, err = run("check", "--method", str(path), "--saddle-beta", "1", "--step", "1",
                         "--verify")
    assert code == 0 and "SAFE" in out, out + err


@settings(max_examples=200, deadline=None)
@given(spans=st.lists(st.tuples(st.floats(0, 10), st.floats(0, 3)), max_size=30),
       probes=st.lists(st.floats(-1, 14), min_size=1, max_size=20), closed=st.booleans())
def test_a_span_lookup_answers_as_a_scan_of_every_span(spans, probes, closed):
    """The sorted lookup that cuts a region into stretches (overlapping spans, shared
    ends, probes on an end) agrees with testing each span in turn."""
    from stepsafe.reference.verify import _covering

    spans = [(a, a + w) for a, w in spans] + [(a, a) for a, _ in spans[:2]]
    covered = _covering(spans, closed)
    probes += [x for span in spans for x in span]
    for x in probes:
        scan = any((a <= x <= b) if closed else (a < x < b) for a, b in spans)
        assert covered(x) == scan, (x, spans)


@pytest.mark.slow
def test_the_largest_families_verify(run_json):
    """--verify on Gauss and Lobatto IIIA-IIIB with 40 stages (zmax 4 pi): every point and
    stretch recomputed at 40 digits agrees."""
    for family in ("gauss", "lobatto3ab"):
        data = run_json("region", family, "-s", "40", "--zmax", repr(4 * math.pi),
                        "--verify")
        assert data["verify"]["ok"] and data["verify"]["points"] >= 18, data["verify"]
