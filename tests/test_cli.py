"""The CLI through click's runner: JSON shape, human output, errors and exit codes."""

from __future__ import annotations

import math

import pytest


def test_region_json_shape(run_json):
    data = run_json("region", "lobatto3ab", "-s", "3")
    assert data["method"] == "lobatto3ab-s3" and data["kind"] == "prk"
    assert data["stages"] == 3 and data["symplectic"] is True
    osc = data["models"]["oscillator"]
    assert abs(osc["first_boundary"] - math.sqrt(8)) < 1e-12
    assert osc["intervals"] == [[0.0, osc["first_boundary"]]]
    assert osc["islands"][0]["orientation"] == "reversed"
    assert set(data["models"]) == {"oscillator", "saddle", "inverted"}
    assert data["models"]["saddle"]["intervals"] == [[0.0, None]]
    assert data["models"]["saddle"]["first_boundary"] is None
    inv = data["models"]["inverted"]
    assert inv["poles"] == [inv["first_boundary"]] and inv["first_boundary_kind"] == "pole"


def test_region_base_swap_is_the_papers_midpoint_composition(run_json):
    data = run_json("region", "yoshida4", "--base", "midpoint", "--model", "saddle")
    saddle = data["models"]["saddle"]
    assert saddle["first_boundary_kind"] == "resonance"  # M = +I: R(z) returns to 1
    assert 1.13 < saddle["first_boundary"] < 1.14


def test_region_human_output(run):
    code, out, _ = run("region", "gauss", "-s", "2", "--model", "oscillator")
    assert code == 0
    assert "3.46410161514" in out and "M = -I" in out and "reversed" in out


def test_non_symplectic_reports_classical_interval(run_json):
    data = run_json("region", "rk4", "--model", "oscillator")
    osc = data["models"]["oscillator"]
    assert data["symplectic"] is False and osc["intervals"] == []
    assert abs(osc["classical_intervals"][0][1] - 2 * math.sqrt(2)) < 1e-12


def test_methods_lists_the_required_names(run_json):
    rows = run_json("methods")
    names = {r["name"] for r in rows}
    for required in ("symplectic-euler", "verlet", "midpoint", "gauss -s N", "lobatto3ab -s N",
                     "yoshida4", "triple-jump6", "suzuki4", "rk4"):
        assert required in names
    rk4 = next(r for r in rows if r["name"] == "rk4")
    assert rk4["symplectic"] is False


def test_show_reports_residuals(run_json):
    data = run_json("show", "gauss", "-s", "3")
    assert data["symplectic"] and data["residuals"]["symplecticity"] < 1e-15
    assert data["order"] == 6 and len(data["coefficients"]["A"]) == 3
    rk4 = run_json("show", "rk4")
    assert rk4["symplectic"] is False and rk4["residuals"]["symplecticity"] > 0.01


@pytest.mark.parametrize("args, message", [
    (["region", "verlte"], "did you mean verlet"),
    (["region", "gauss"], "give the stage count"),
    (["region", "gauss", "-s", "0"], "-s must be between 1"),
    (["region", "lobatto3ab", "-s", "1"], "-s must be between 2"),
    (["region", "gauss", "-s", "100000"], "-s must be between"),
    (["region", "verlet", "-s", "3"], "applies only to the families"),
    (["region", "verlet", "--zmax", "nan"], "zmax must be a positive finite number"),
    (["region", "verlet", "--zmax", "0"], "zmax must be a positive finite number"),
    (["region", "verlet", "--zmax", "-2"], "zmax must be a positive finite number"),
    (["region", "verlet", "--zmax", "inf"], "zmax must be a positive finite number"),
    (["region", "verlet", "--base", "midpoint"], "applies to compositions"),
    (["region", "missing/file.yaml"], "no such file"),
    (["show", "nothing-like-this"], "unknown method"),
])
def test_bad_input_is_one_line_exit_2(run, args, message):
    code, out, err = run(*args)
    assert code == 2
    assert message in err and "Traceback" not in err + out
    assert len(err.strip().splitlines()) == 1


def test_bad_option_type_exit_2(run):
    code, _, err = run("region", "gauss", "-s", "three")
    assert code == 2 and "Traceback" not in err


def test_base_can_be_a_family_member(run_json, run):
    data = run_json("region", "yoshida4", "--base", "gauss:2", "--model", "saddle", "--verify")
    assert data["stages"] == 6 and data["verify"]["ok"]
    code, _, err = run("region", "yoshida4", "--base", "lobatto3ab")
    assert code == 2 and "lobatto3ab:N" in err
