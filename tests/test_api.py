"""The public Python API: the same answers as the command line, frozen, silent, typed errors."""

from __future__ import annotations

import dataclasses
import doctest
import importlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import stepsafe
from stepsafe.exceptions import StepsafeError

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
@pytest.mark.parametrize("module, least", [("inputs", 3), ("linear", 8), ("hmc", 2), ("md", 2),
                                           ("measure", 2)])
def test_docstring_examples_run(module, least):
    loaded = importlib.import_module(f"stepsafe.api.{module}")
    failures, tried = doctest.testmod(loaded, raise_on_error=False, verbose=False)
    assert tried >= least and failures == 0


def test_every_public_name_is_its_modules():
    for name in stepsafe.__all__:
        value = getattr(stepsafe, name)
        if name not in ("StepsafeError", "MethodError", "__version__"):
            module = importlib.import_module(value.__module__)
            assert module.__name__.startswith("stepsafe.api.") and getattr(module, name) is value
    assert set(stepsafe.__all__) <= set(dir(stepsafe))


def test_import_stepsafe_is_light():
    code = ("import sys, stepsafe; print(sorted({'numpy', 'scipy', 'yaml', 'rich', 'mpmath'}"
            " & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("args, call", [
    (["show", "pefrl", "--json"], lambda: stepsafe.method("pefrl").to_dict()),
    (["region", "lobatto3ab", "-s", "3", "--json"],
     lambda: stepsafe.region(stepsafe.method("lobatto3ab", stages=3)).to_dict()),
    (["region", "verlet", "--model", "saddle", "--zmax", "5", "--json"],
     lambda: stepsafe.region("verlet", "saddle", zmax=5).to_dict()),
    (["advise", "--method", "yoshida4", "--beta", "3.2", "--inverted-beta", "1.1", "--json"],
     lambda: stepsafe.advise("yoshida4", [3.2], inverted_beta=[1.1]).to_dict()),
    (["advise", "--method", "verlet", "--beta", "2", "--tol-phase", "1e-3", "--json"],
     lambda: stepsafe.advise("verlet", 2.0, tol_phase=1e-3).to_dict()),
    (["advise", str(ROOT / "examples/double-well.yaml"), "--json"],
     lambda: stepsafe.advise(scene=ROOT / "examples/double-well.yaml").to_dict()),
    (["error", "yoshida4", "--z", "0.1", "--z", "1", "--json"],
     lambda: stepsafe.errors("yoshida4", [0.1, 1.0]).to_dict()),
    (["compare", "--beta", "3.2", "--inverted-beta", "1", "--tol-phase", "1e-6", "--json"],
     lambda: stepsafe.compare(None, [3.2], inverted_beta=[1.0], tol_phase=1e-6).to_dict()),
    (["compare", "--methods", "verlet,gauss:3", "--beta", "2", "--margin", "0.9", "--json"],
     lambda: stepsafe.compare(["verlet", stepsafe.method("gauss", stages=3)], [2.0],
                              margin=0.9).to_dict()),
])
def test_to_dict_is_the_command_json(run, args, call):
    code, out, _ = run(*args)
    assert code == 0
    assert json.loads(out) == json.loads(json.dumps(call()))


def _scenes(folder):
    """Scenes for check: safe, unsafe, an impulse method's, one in fs with h in ps, one
    with a key that is no scene key, one that does not exist."""
    files = {"safe": "method: verlet\nh: 0.1\nmodes: [{beta: 1, label: bond}]\n",
             "unsafe": "method: verlet\nh: 3\nmodes: [{beta: 1}]\n",
             "impulse": "method: respa-verlet\nh: 0.1\nmodes: [{fast: 10, slow: 1}]\n",
             "units": "method: verlet\ntime_unit: fs\nh: 0.0005 ps\n"
                      "modes: [{wavenumber: 3700}]\n",
             "bad": "method: verlet\nh: 0.1\nmodez: [{beta: 1}]\n"}
    paths = {}
    for name, text in files.items():
        paths[name] = folder / f"{name}.yaml"
        paths[name].write_text(text)
    paths["missing"] = folder / "missing.yaml"
    return {k: str(v) for k, v in paths.items()}


@pytest.mark.parametrize("names, code", [
    (["unsafe"], 1), (["safe"], 0), (["impulse"], 0), (["units"], 0), (["bad"], 2),
    (["safe", "unsafe"], 1), (["safe", "bad", "unsafe", "missing"], 2),
    (["impulse", "units", "safe"], 0), (["paper"], 1),
])
def test_check_to_dict_is_the_command_json(run, tmp_path, names, code):
    """The API's check of one scene and check_scenes of several give exactly the dict
    that `stepsafe check ... --json` prints (a file that cannot be checked as its error
    record, in its place), and the command exits with the worst code of its files."""
    paths = {**_scenes(tmp_path), "paper": str(ROOT / "examples/paper-section3.yaml")}
    files = [paths[n] for n in names]
    got, out, err = run("check", *files, "--json")
    data = json.loads(out)
    suite = stepsafe.check_scenes(files)
    assert got == code == suite.exit_code
    assert data == json.loads(json.dumps(suite.to_dict()))
    assert [c["scene"] for c in data["checks"]] == files
    assert data["safe"] is (code == 0)
    errors = [c for c in data["checks"] if "error" in c]
    assert len(err.strip().splitlines()) == len(errors)
    for entry in errors:
        assert entry["safe"] is None and entry["where"].startswith(entry["scene"])
    if len(files) == 1 and not errors and names != ["impulse"]:
        assert data == json.loads(json.dumps(stepsafe.check(scene=files[0]).to_dict()))


@pytest.mark.parametrize("args, call", [
    (["--method", "verlet", "--beta", "3", "--step", "0.5"],
     lambda: stepsafe.check("verlet", 0.5, [3.0])),
    (["--method", "pefrl", "--beta", "1", "--saddle-beta", "2", "--step", "1.2"],
     lambda: stepsafe.check("pefrl", 1.2, [1.0], saddle_beta=[2.0])),
    (["--method", "verlet", "--wavenumber", "3700", "--step", "0.5fs"],
     lambda: stepsafe.check("verlet", "0.5 fs", wavenumber=[3700])),
    (["--method", "verlet", "--beta", "1", "--step", "1.8", "--resonance-order", "3"],
     lambda: stepsafe.check("verlet", 1.8, [1.0], resonance_order=3)),
])
def test_check_of_the_command_line_is_its_json(run, args, call):
    """Without scene files, ``check(...).to_dict()`` is the command's --json as well."""
    report = call()
    code, out, _ = run("check", *args, "--json")
    assert code == (0 if report.safe else 1)
    assert json.loads(out) == json.loads(json.dumps(report.to_dict()))
    assert report.to_dict()["checks"] == [report.entry()]


def test_results_are_frozen_and_calls_are_silent(capsys):
    report = stepsafe.advise("verlet", [1.0, 4.0])
    assert report.h_max == pytest.approx(0.5, rel=1e-12)
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.h_max = 1.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        report.record["h_max"] = 1.0  # type: ignore[index]
    data = report.to_dict()
    data["h_max"] = 7.0  # a copy: the report is unchanged
    assert report.to_dict()["h_max"] == report.h_max
    table = stepsafe.errors("verlet", [0.5])
    with pytest.raises(ValueError):
        table.phase[0] = 0.0
    assert capsys.readouterr() == ("", "")


@pytest.mark.parametrize("call, where", [
    (lambda: stepsafe.method("no-such-method"), "unknown method"),
    (lambda: stepsafe.advise("verlet", [-1.0]), "beta must be"),
    (lambda: stepsafe.advise("verlet", [1 + 1j]), "must be real"),
    (lambda: stepsafe.check("verlet", 0.1), "no frequencies"),
    (lambda: stepsafe.check("verlet", None, [1.0]), "no step"),
    (lambda: stepsafe.region("verlet", "pendulum"), "unknown model"),
    (lambda: stepsafe.region("verlet", zmax=-1), "zmax"),
    (lambda: stepsafe.advise("verlet", [1.0], margin=2), "margin"),
    (lambda: stepsafe.errors("verlet", [0.0]), "positive"),
    (lambda: stepsafe.advise("verlet", system={"stiffness": np.eye(2) * 1j}), "real"),
])
def test_bad_input_raises_stepsafe_error(call, where):
    with pytest.raises(stepsafe.StepsafeError, match=where):
        call()


def test_arrays_in_system_as_in_a_scene_file(tmp_path):
    """A stiffness and mass given as numpy arrays answer as the same matrices in a scene."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 5))
    K = A @ A.T + 5 * np.eye(5)
    mass = np.diag(rng.uniform(0.5, 2.0, 5))
    scene = tmp_path / "s.yaml"
    scene.write_text(f"method: pefrl\nsystem: {{stiffness: {K.tolist()}, "
                     f"mass: {mass.tolist()}}}\n")
    from_file = stepsafe.advise(scene=scene)
    from_arrays = stepsafe.advise("pefrl", system={"stiffness": K, "mass": mass})
    assert from_arrays.h_max == from_file.h_max
    scale = np.diag(1 / np.sqrt(np.diag(mass)))
    beta_max = np.sqrt(np.linalg.eigvalsh(scale @ K @ scale).max())
    z_star = stepsafe.region("pefrl", "oscillator").first_boundary()
    assert from_arrays.h_max == pytest.approx(z_star / beta_max, rel=1e-9)


def test_labels_name_the_failing_modes(run, tmp_path):
    scene = tmp_path / "labelled.yaml"
    scene.write_text("method: verlet\nh: 0.3\nmodes:\n"
                     "  - {beta: 1, label: slow torsion}\n"
                     "  - {beta: 7, label: fast stretch}\n")
    report = stepsafe.check(scene=scene)
    (fail,) = report.failures
    assert fail["label"] == "fast stretch" and fail["beta"] == 7
    code, out, _ = run("check", str(scene))
    assert code == 1 and "fast stretch (oscillator) beta = 7" in out
    assert out.startswith(f"{scene}: UNSAFE")


def test_several_scenes_one_json_shape(run, tmp_path):
    safe, unsafe = tmp_path / "a.yaml", tmp_path / "b.yaml"
    safe.write_text("method: verlet\nh: 0.1\nmodes: [{beta: 1}]\n")
    unsafe.write_text("method: verlet\nh: 3\nmodes: [{beta: 1}]\n")
    for files, verdict in (([safe], True), ([safe, unsafe], False)):
        code, out, _ = run("check", *map(str, files), "--json")
        data = json.loads(out)
        assert code == (0 if verdict else 1) and data["safe"] is verdict
        assert [c["scene"] for c in data["checks"]] == list(map(str, files))
    code, out, _ = run("check", str(safe), str(unsafe))
    lines = out.splitlines()
    assert lines[0].startswith(f"{safe}: SAFE") and lines[1].startswith(f"{unsafe}: UNSAFE")


def test_unknown_keys_suggest_the_closest(run, tmp_path):
    scene = tmp_path / "typo.yaml"
    scene.write_text("method: verlet\nh: 0.1\nmodez: [{beta: 1}]\n")
    code, _, err = run("check", str(scene))
    assert code == 2 and "did you mean 'modes'?" in err and "typo.yaml" in err
    method = tmp_path / "m.yaml"
    method.write_text("kind: splitting\ndrfit: [0.5, 0.5]\nkick: [1, 0]\n")
    code, _, err = run("region", str(method))
    assert code == 2 and "did you mean 'drift'?" in err


@pytest.mark.parametrize("args", [
    ["compare", "--beta", "1", "--tol-phase", "1e-6"],
    ["error", "verlet", "--z", "0.1", "--z", "2.5"],
    ["error", "yoshida4", "--z", "1", "--model", "inverted"],
    ["methods"],
])
def test_tsv_holds_what_json_holds(run, args):
    """--tsv: a header of JSON keys, one line per row, floats that read back exactly,
    empty fields for null."""
    _, js, _ = run(*args, "--json")
    code, out, err = run(*args, "--tsv")
    assert code == 0, err
    data = json.loads(js)
    rows = data if isinstance(data, list) else data.get("rows") or data["methods"]
    header, *lines = out.rstrip("\n").split("\n")
    columns = header.split("\t")
    assert len(lines) == len(rows)
    for line, row in zip(lines, rows):
        for column, cell in zip(columns, line.split("\t"), strict=True):
            value = row[column]
            if value is None:
                assert cell == ""
            elif isinstance(value, bool):
                assert cell == str(value).lower()
            elif isinstance(value, float):
                assert float(cell) == value
            elif isinstance(value, list):
                assert cell == ", ".join(value)
            else:
                assert cell == str(value)


def test_json_and_tsv_together_is_a_usage_error(run):
    code, out, err = run("compare", "--beta", "1", "--json", "--tsv")
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1


def test_compare_help_offers_only_what_compare_accepts(run):
    """Every option listed by compare --help is accepted (no method or --verify); a scene
    only through --measure, whose --time, --initial and --budget need it."""
    _, text, _ = run("compare", "--help")
    for refused in ("--verify", "--method "):
        assert refused not in text
    assert "--measure SCENE.yaml" in text
    for option, value in (("--budget", "5"), ("--time", "3"), ("--initial", "0,1")):
        code, _, err = run("compare", "--beta", "1", option, value)
        assert code == 2 and "--measure" in err


def test_transfer_matrices_and_recipes_agree():
    """M(z) from transfer_matrices equals the product of the method's own operations
    applied to the oscillator (and the PRK stage equations solved directly)."""
    z = np.array([0.3, 1.1, 2.7])
    for name, stages in (("verlet", None), ("yoshida4", None), ("pefrl", None),
                         ("gauss", 2), ("lobatto3ab", 3)):
        m = stepsafe.method(name, stages=stages)
        got = stepsafe.transfer_matrices(m, z)
        assert not got.flags.writeable
        for k, zz in enumerate(z):
            M = np.eye(2)
            if m.operations is not None:
                for kind, c in m.operations:
                    step = [[1, c * zz], [0, 1]] if kind == "drift" else [[1, 0], [-c * zz, 1]]
                    M = np.array(step) @ M
            else:
                t = m.partitioned_tableau
                s = t.stages
                # Q = q + z A_q P, P = p - z A_p Q  (beta = 1, h = z), solved for (Q, P)
                lhs = np.block([[np.eye(s), -zz * t.A_q], [zz * t.A_p, np.eye(s)]])
                for col, (q, p) in enumerate(((1.0, 0.0), (0.0, 1.0))):
                    Q, P = np.split(np.linalg.solve(lhs, np.r_[np.full(s, q), np.full(s, p)]),
                                    2)
                    M[:, col] = (q + zz * t.b_q @ P, p - zz * t.b_p @ Q)
            np.testing.assert_allclose(got[k], M, rtol=1e-12, atol=1e-12)


def test_examples_use_only_the_public_api():
    """Programs in examples/ import stepsafe, never its internal modules."""
    import ast

    for path in (ROOT / "examples").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            assert not any(n.startswith("stepsafe.") for n in names), (path, names)


def test_an_explicit_system_is_never_dropped(tmp_path):
    """An explicit ``system`` with explicit frequencies is refused (one would be ignored);
    against a scene's ``modes:`` it wins, as arguments do: a stiffness of 1e6 at h = 0.05
    (z = 50) is checked unsafe although the scene's own mode is safe."""
    with pytest.raises(StepsafeError, match="not both"):
        stepsafe.check("verlet", 1.0, beta=[1.0], system={"stiffness": [[100.0]]})
    with pytest.raises(StepsafeError, match="not both"):
        stepsafe.hmc(["verlet"], sigma=[1.0], system={"covariance": [[1e-6]]})
    scene = tmp_path / "modes.yaml"
    scene.write_text("method: verlet\nmodes: [{beta: 1.0, model: oscillator}]\nh: 0.05\n")
    report = stepsafe.check(scene=scene, system={"stiffness": [[1e6]]})
    assert not report.safe  # beta = 1000, z = 50
    assert stepsafe.check(scene=scene).safe
    assert stepsafe.advise(scene=scene, system={"stiffness": [[1e6]]}).h_max <= 2e-3


@pytest.mark.parametrize("kwargs", [{"frequencies": np.ones((2, 2))},
                                    {"sigma": np.ones((2, 2))},
                                    {"frequencies": np.array(["1"], dtype=object)}])
def test_frequencies_are_one_dimensional_real_numbers(kwargs):
    """A 2-D array of frequencies is refused (not flattened), and so is a text in an
    object array where texts are not accepted."""
    with pytest.raises(StepsafeError):
        stepsafe.check("verlet", 0.1, **kwargs)


def test_a_problem_is_not_combined_with_other_inputs():
    """problem= already holds the method, frequencies and options: any of them beside it
    is refused, never ignored (yoshida4 checked as verlet's problem would say safe at
    z = 1.9)."""
    p = stepsafe.problem("verlet", [1.0])
    for args, kwargs in ((("yoshida4", 1.9), {}), ((), {"h": 1.9, "margin": 0.5}),
                         ((), {"h": 0.05, "system": {"stiffness": [[1e6]]}})):
        with pytest.raises(StepsafeError, match="problem= already holds"):
            stepsafe.check(*args, problem=p, **kwargs)
    with pytest.raises(StepsafeError, match="problem= already holds"):
        stepsafe.advise("yoshida4", problem=p)
    assert stepsafe.check(h=1.9, problem=p).safe
