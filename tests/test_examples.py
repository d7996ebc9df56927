"""Every file in examples/ runs as shipped: each is taken from the directory listing, so a new
example is covered (or fails here until a command is named for its kind)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = sorted(p.name for p in (ROOT / "examples").iterdir() if not p.name.startswith("."))

#: The columns of a modes file (``--modes FILE``): commands that take frequencies read it.
MODES_COLUMNS = {"beta", "frequency", "wavenumber", "period", "sigma", "model", "label"}


def _kind(name: str) -> str:
    path = ROOT / "examples" / name
    if path.is_dir():
        return "data"
    if path.suffix in (".yaml", ".yml"):
        tree = yaml.safe_load(path.read_text())
        if isinstance(tree, dict) and isinstance(tree.get("system"), dict) and \
                "potential" in tree["system"]:
            return "target"
        return "workflow" if isinstance(tree, dict) and "jobs" in tree else "scene"
    if path.suffix == ".py":
        return "program"
    if path.suffix == ".csv":
        with path.open() as handle:
            header = next(csv.reader(line for line in handle if not line.startswith("#")))
        return "modes" if set(header) <= MODES_COLUMNS else "table"
    return "unknown"


def test_every_example_has_a_kind():
    """A file of a kind no test below runs fails here: name the command that takes it."""
    assert EXAMPLES and all(_kind(name) != "unknown" for name in EXAMPLES), \
        [name for name in EXAMPLES if _kind(name) == "unknown"]


def _openmm_atoms(name: str) -> int:
    """Particles of the OpenMM System a scene names (0 for another scene)."""
    import xml.etree.ElementTree as ET

    system = yaml.safe_load((ROOT / "examples" / name).read_text()).get("system")
    if not (isinstance(system, dict) and "openmm" in system):
        return 0
    particles = ET.parse(ROOT / "examples" / system["openmm"]).getroot().find("Particles")
    return 0 if particles is None else len(particles)


#: Scenes of OpenMM systems above this many atoms (minimised, then Lanczos: seconds each)
#: run in the slow set.
SLOW_OPENMM_ATOMS = 200

#: Examples whose run as shipped takes seconds and is in the slow set, each with the test
#: of the default run that runs the same file.
SLOW_EXAMPLES = {
    "lagrange-points.yaml": "test_manydof.py::test_lagrange_points analyses it (mu = 0.01)",
    "tradeoff.py": "test_accuracy.py::test_tradeoff_example_measures_what_it_predicts runs "
                   "it on two methods",
}


def _at_temperature(name: str) -> bool:
    """Whether a scene states a temperature (its analysis runs thermal ensembles: seconds)."""
    tree = yaml.safe_load((ROOT / "examples" / name).read_text())
    return isinstance(tree, dict) and ("temperature" in tree or "kT" in tree)


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.slow)
    if _openmm_atoms(n) > SLOW_OPENMM_ATOMS or _at_temperature(n) or n in SLOW_EXAMPLES else n
    for n in EXAMPLES if _kind(n) == "scene"])
def test_scene_runs_with_advise_and_check(run, name):
    """advise answers (exit 0); check answers a scene with h: (0 or 1, as advise's safe
    steps say), and one without h: at half of advise's h_max (0)."""
    path = str(ROOT / "examples" / name)
    scene = yaml.safe_load((ROOT / "examples" / name).read_text())
    if isinstance(scene.get("system"), dict) and "openmm" in scene["system"]:
        pytest.importorskip("openmm", reason="an OpenMM system: pip install 'stepsafe[openmm]'")
    code, out, err = run("advise", path, "--json")
    assert code == 0, err
    advice = json.loads(out)
    if "h" in scene:
        code, out, err = run("check", path, "--json")
        assert code in (0, 1), err
        data = json.loads(out)
        assert code == (0 if data["safe"] else 1)
        (entry,) = data["checks"]
        step = entry.get("h", entry.get("step"))
        in_safe = any(lo < step and (hi is None or step < hi) for lo, hi in advice["safe_h"])
        if "solver_failure" not in entry:
            assert data["safe"] is in_safe, (step, advice["safe_h"])
    elif advice["h_max"]:
        code, out, err = run("check", path, "--step", repr(advice["h_max"] / 2))
        assert code == 0, (out, err)


@pytest.mark.parametrize("name", [n for n in EXAMPLES if _kind(n) == "data"])
def test_a_data_folder_belongs_to_a_scene(name):
    """A folder holds the files of a scene's system (an MD engine's System and structure):
    some scene names every file in it."""
    named = set()
    for scene in EXAMPLES:
        if _kind(scene) == "scene":
            system = yaml.safe_load((ROOT / "examples" / scene).read_text()).get("system")
            if isinstance(system, dict):
                named |= {v for v in system.values() if isinstance(v, str)}
    files = {f"{name}/{p.name}" for p in (ROOT / "examples" / name).iterdir()}
    assert files and files <= named, files - named


@pytest.mark.parametrize("name", [n for n in EXAMPLES if _kind(n) == "target"])
def test_target_scene_runs_with_hmc(run, name):
    """A scene giving a potential is an HMC target: hmc estimates each method's acceptance
    on draws (a standard error, a divergent share, the Laplace figure beside it)."""
    code, out, err = run("hmc", str(ROOT / "examples" / name), "--steps", "10",
                         "--methods", "verlet,bcss2", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert [r["rank"] for r in data["methods"]] == [1, 2]
    for row in data["methods"]:
        assert 0 < row["acceptance"] < 1 and row["acceptance_se"] > 0
        assert row["laplace_acceptance"] is not None and row["divergent"] is not None


@pytest.mark.parametrize("name", [n for n in EXAMPLES if _kind(n) == "modes"])
def test_modes_file_runs_with_the_commands_that_take_one(run, name):
    path = str(ROOT / "examples" / name)
    for args in (("advise", "--method", "verlet", "--modes", path),
                 ("hmc", "--modes", path, "--methods", "verlet,bcss2", "--length", "5")):
        code, _, err = run(*args)
        assert code == 0, (args, err)


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.slow) if n in SLOW_EXAMPLES else n
    for n in EXAMPLES if _kind(n) == "program"])
def test_program_runs_as_shipped(name, tmp_path):
    """The program runs with its own defaults (in tmp_path, where it writes its output)
    and exits 0; a table shipped beside it has the columns it writes."""
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    shipped = ROOT / "examples" / f"{Path(name).stem}.csv"
    out = tmp_path / shipped.name
    if shipped.exists():
        with out.open() as mine, shipped.open() as theirs:
            written, given = list(csv.DictReader(mine)), list(csv.DictReader(theirs))
        assert written and list(written[0]) == list(given[0])
        assert {r["method"] for r in written} <= {r["method"] for r in given}
        for row in written:  # each measured figure is a finite number
            assert all(math.isfinite(float(v)) for k, v in row.items() if k != "method")


@pytest.mark.parametrize("name", [n for n in EXAMPLES if _kind(n) == "table"])
def test_a_table_is_written_by_an_example_program(name):
    """A CSV that is no modes file is the output of the program of the same name (checked
    against that program's run in :func:`test_program_runs_as_shipped`)."""
    assert (ROOT / "examples" / f"{Path(name).stem}.py").exists()


@pytest.mark.parametrize("name", [n for n in EXAMPLES if _kind(n) == "workflow"])
def test_workflow_calls_stepsafe_check(name):
    """A CI workflow runs `stepsafe check` (tests/test_ci_recipes.py runs the job itself)."""
    job = yaml.safe_load((ROOT / "examples" / name).read_text())
    runs = [step.get("run", "") for j in job["jobs"].values() for step in j["steps"]]
    assert any("stepsafe check" in r for r in runs)


def test_each_slow_example_is_run_in_the_default_run_elsewhere():
    """An example left to the slow set names a default-run test that runs the same file."""
    for name, where in SLOW_EXAMPLES.items():
        assert name in EXAMPLES
        path, test = where.split(" ")[0].split("::")
        text = (ROOT / "tests" / path).read_text()
        body = text[text.index(f"def {test}("):]
        assert Path(name).stem in body.split("\ndef ")[0], (name, where)
