"""OpenMM systems in scenes and in stepsafe.advise/check: the limit against closed forms for one
TIP3P molecule, the constraints: and hydrogen_mass: rules against OpenMM's own createSystem,
the verdicts at the command line (exit 0 / 1 / 2), and, in the slow set, the verdicts against
OpenMM's own Verlet and LangevinMiddle integrators (fixed seeds)."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import yaml
from md_support import one_water, tip3p_isolated_frequencies, water_cluster

import stepsafe
from stepsafe.exceptions import StepsafeError

openmm = pytest.importorskip("openmm")
app = pytest.importorskip("openmm.app")
unit = pytest.importorskip("openmm.unit")

pytestmark = pytest.mark.openmm

#: rad^2/ps^2 -> the Verlet limit 2/omega in fs
def verlet_fs(omega_squared):
    return 2.0 / math.sqrt(omega_squared) * 1000.0


def scene(folder, name="scene.yaml", **system):
    """A scene for Verlet in fs on ``folder``'s system.xml and structure.pdb."""
    tree = {"method": "verlet", "time_unit": "fs",
            "system": {"openmm": "system.xml", "positions": "structure.pdb", **system}}
    path = folder / name
    path.write_text(yaml.safe_dump(tree))
    return str(path)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Eight flexible TIP3P waters in vacuum (24 atoms), no constraints."""
    folder = tmp_path_factory.mktemp("cluster")
    water_cluster(folder)
    return folder


# --- the limit against closed forms -------------------------------------------------------

def test_limit_of_a_flexible_water_is_its_antisymmetric_stretch():
    system, x = one_water()
    report = stepsafe.advise("verlet", openmm_system=system, positions=x, time_unit="fs")
    want = verlet_fs(tip3p_isolated_frequencies()["antisymmetric_stretch"])
    assert report.h_max == pytest.approx(want, rel=1e-6)
    assert report.h_max_limited_by == "boundary"


def test_limit_of_a_water_with_rigid_bonds_is_its_bend():
    """h-bond constraints carried by the System (createSystem(constraints=HBonds)) leave the
    bend, whose frequency with rigid bonds is the closed form."""
    system, x = one_water(constraints=app.HBonds)
    assert system.getNumConstraints() == 2
    report = stepsafe.advise("verlet", openmm_system=system, positions=x * unit.nanometer,
                             time_unit="fs")
    want = verlet_fs(tip3p_isolated_frequencies()["rigid_bend"])
    assert report.h_max == pytest.approx(want, rel=1e-6)


def test_scene_limit_of_a_water_cluster_is_near_the_isolated_stretch(cluster, run):
    """Hydrogen bonds move the fastest O-H stretch of a minimised cluster by well under 1%;
    check says SAFE just below h_max and UNSAFE just above (exit 0 and 1)."""
    path = scene(cluster, minimize=True)
    code, out, err = run("advise", path, "--json")
    assert code == 0, err
    data = json.loads(out)
    isolated = verlet_fs(tip3p_isolated_frequencies()["antisymmetric_stretch"])
    assert data["h_max"] == pytest.approx(isolated, rel=0.01)
    fastest = data["system"]["items"][0]
    assert {name.split(":")[1][0] for name, _ in fastest["atoms"]} <= {"H", "O"}
    assert 3650 < fastest["wavenumber"] < 3850
    assert any("minimised" in note for note in data["system"]["notes"])
    assert run("check", path, "--step", repr(0.99 * data["h_max"]))[0] == 0
    code, out, _ = run("check", path, "--step", repr(1.01 * data["h_max"]))
    assert code == 1
    assert "UNSAFE" in out


@pytest.mark.parametrize("system", [{}, {"constraints": "h-bonds"}])
def test_lanczos_path_agrees_with_the_dense_spectrum(cluster, monkeypatch, system):
    """Above DENSE_ATOMS moving atoms the fastest modes come from Lanczos: the same h_max
    as the dense Hessian within their error bounds, the rest bounded, islands not analysed
    (a step beyond h_max fails with that reason)."""
    from stepsafe.systems.md import system as md

    path = scene(cluster, f"lanczos-{len(system)}.yaml", **system)
    dense = stepsafe.advise(scene=path)
    monkeypatch.setattr(md, "DENSE_ATOMS", 10)
    sparse = stepsafe.advise(scene=path)
    assert "Lanczos" in sparse.record["system"]["analysis"]
    a, b = dense.record["system"]["items"][0], sparse.record["system"]["items"][0]
    assert abs(a["omega_squared"] - b["omega_squared"]) <= (a["omega_squared_error"]
                                                            + b["omega_squared_error"])
    # each h_max is 2 / sqrt of its top eigenvalue taken at the top of its error
    allowed = 0.5 * (a["omega_squared_error"] / a["omega_squared"]
                     + b["omega_squared_error"] / b["omega_squared"]) + 1e-12
    assert abs(sparse.h_max / dense.h_max - 1) <= allowed
    assert sum(item["type"] == "bound" for item in sparse.record["system"]["items"]) == 2
    assert "islands not analysed" in sparse.record["system"]["analysis"]
    assert sparse.safe_h == ((0.0, sparse.h_max),)
    assert not stepsafe.check("verlet", 3 * sparse.h_max, scene=path).safe


def test_md_json_output_fits_the_command_schemas(cluster, run):
    """advise and check --json of an OpenMM scene (modes with their atoms) validate against
    ``stepsafe schema output``."""
    jsonschema = pytest.importorskip("jsonschema")
    from stepsafe.api.schemas import output_schema

    path = scene(cluster, "schema.yaml", constraints="h-bonds")
    for command, args in (("advise", ()), ("check", ("--step", "1"))):
        code, out, err = run(command, path, *args, "--json")
        assert code == 0, err
        data = json.loads(out)
        jsonschema.validate(data, output_schema(command))
        items = (data if command == "advise" else data["checks"][0])["system"]["items"]
        assert items[0]["atoms"] and items[0]["omega_squared"] > 0


def test_langevin_middle_has_verlet_s_limit_on_an_openmm_system(cluster, run):
    """LangevinMiddle's mean map is stable for every friction exactly where Verlet is: the
    same h_max; it is analysed on vibrations only, so the rigid-body modes near 0 count as
    vibrations, and a configuration with a barrier (the unminimised grid) is refused."""
    path = scene(cluster, "langevin.yaml", minimize=True)
    verlet = stepsafe.advise("verlet", scene=path)
    langevin = stepsafe.advise("langevin-middle", scene=path)
    assert langevin.h_max == verlet.h_max
    assert any("analysed on vibrations only" in note
               for note in langevin.record["system"]["notes"])
    grid = scene(cluster, "grid.yaml")
    assert any(item["model"] == "inverted" and item["type"] == "hyperbolic"
               for item in stepsafe.advise("verlet", scene=grid).record["system"]["items"])
    code, _, err = run("advise", grid, "--method", "langevin-middle")
    assert code == 2 and "$.system.openmm:" in err and "minimize: true" in err


# --- the rules against OpenMM's createSystem ----------------------------------------------

@pytest.mark.parametrize("rule, option", [("h-bonds", "HBonds"), ("all-bonds", "AllBonds"),
                                          ("h-angles", "HAngles")])
@pytest.mark.parametrize("hydrogen_mass", [None, 3.0])
def test_constraint_rule_and_hmr_equal_openmm_create_system(cluster, tmp_path, rule, option,
                                                             hydrogen_mass):
    """constraints: and hydrogen_mass: on a flexible system give the limit of the System that
    createSystem builds with the same constraints and hydrogenMass (both at the structure's
    positions put on the constraints)."""
    ours = stepsafe.advise(scene=scene(cluster, f"{rule}-{hydrogen_mass}.yaml",
                                       constraints=rule,
                                       **({} if hydrogen_mass is None
                                          else {"hydrogen_mass": f"{hydrogen_mass:g} amu"})))
    extra = {} if hydrogen_mass is None else {"hydrogenMass": hydrogen_mass * unit.amu}
    water_cluster(tmp_path, constraints=getattr(app, option), **extra)
    theirs = stepsafe.advise(scene=scene(tmp_path))
    # h = 2/omega: a relative error e/lambda of the eigenvalue moves h by half of it; the
    # two Systems differ in the bond and angle terms createSystem drops for constrained
    # pairs, which change nothing on the constraints beyond rounding
    (a,), (b,) = (r.record["system"]["items"][:1] for r in (ours, theirs))
    allowed = 0.5 * (a["omega_squared_error"] / a["omega_squared"]
                     + b["omega_squared_error"] / b["omega_squared"])
    assert abs(ours.h_max / theirs.h_max - 1) <= allowed
    notes = " ".join(ours.record["system"]["notes"])
    assert f"the rule {rule}" in notes
    assert ("hydrogen mass 3 amu on 16 hydrogens" in notes) == (hydrogen_mass is not None)


def test_hmr_with_h_bond_constraints_lengthens_the_limit_of_water(cluster):
    """With rigid O-H bonds the bend limits; 3 amu hydrogens slow it (the advice for a longer
    step comes from the modes, not a rule of thumb)."""
    plain = stepsafe.advise(scene=scene(cluster, "a.yaml", constraints="h-bonds"))
    heavy = stepsafe.advise(scene=scene(cluster, "b.yaml", constraints="h-bonds"),
                            hydrogen_mass=3)
    assert heavy.h_max > 1.3 * plain.h_max
    assert stepsafe.check("verlet", "4 fs", scene=scene(cluster, "c.yaml"),
                          constraints="h-bonds").safe
    assert stepsafe.check("verlet", "6 fs", scene=scene(cluster, "d.yaml"),
                          constraints="h-bonds", hydrogen_mass=3).safe
    assert not stepsafe.check("verlet", "6 fs", scene=scene(cluster, "e.yaml"),
                              constraints="h-bonds").safe


# --- the OpenMM guide (docs/guides/openmm.md) ----------------------------------------------

ROOT = __import__("pathlib").Path(__file__).resolve().parent.parent
GUIDE = (ROOT / "docs" / "guides" / "openmm.md").read_text()


def readme_rows(system):
    """The engine-validation table's rows for ``system``: (constraints and H mass, h_max).
    The table is the guide's one headed ``| system (minimised, vacuum) | constraints, H mass``
    (other tables name the same systems)."""
    header = "| system (minimised, vacuum) | constraints, H mass |"
    table = next(block for block in GUIDE.split("\n\n") if block.startswith(header))
    rows = []
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0].startswith(system):
            rows.append((cells[1], cells[2]))
    return rows


def test_the_guide_table_limits_of_the_water_cluster_are_what_advise_gives(cluster):
    """The h_max column of the cluster's rows is what advise gives, to one unit of the last
    digit shown (the minimiser's end point moves the third digit by less than that)."""
    rows = readme_rows("8 flexible TIP3P waters")
    assert len(rows) == 3
    for rule, h_max in rows:
        parts = [p.strip() for p in rule.split(",")]
        system = {} if parts[0] == "none" else {"constraints": parts[0]}
        if len(parts) > 1:
            system["hydrogen_mass"] = parts[1]
        report = stepsafe.advise(scene=scene(cluster, "readme.yaml", minimize=True, **system))
        assert h_max.endswith(" fs") and abs(report.h_max - float(h_max[:-3])) <= 0.01


def test_the_guide_python_example_gives_the_limit_it_states(monkeypatch):
    block = GUIDE.split("in Python:\n\n```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    exec(block, scope)
    assert f"{scope['h_max']:.2f}" == block.rsplit("# ", 1)[1].split()[0]


# --- bad input ----------------------------------------------------------------------------

@pytest.mark.parametrize("system, key, message", [
    ({"constraints": "rigid"}, "constraints", "must be one of none, h-bonds"),
    ({"hydrogen_mass": -1}, "hydrogen_mass", "between 0 and 100"),
    ({"hydrogen_mass": "3 kg"}, "hydrogen_mass", "a mass in amu"),
    ({"minimize": "maybe"}, "minimize", "true or false"),
    ({"temperature": 300}, "temperature", "unknown key"),
    ({"positions": None}, "positions", "missing"),
    ({"positions": "nowhere.pdb"}, "positions", "not found"),
    ({"openmm": "structure.pdb"}, "openmm", "not an OpenMM XML file"),
    ({"hydrogen_mass": 14}, "hydrogen_mass", "leaves atom"),
    ({"runs": {"seeds": [1]}}, "runs.temperature", "missing"),
    ({"runs": {"temperature": "300 C"}}, "runs.temperature", "must be a number in (0, 10000] K"),
    ({"runs": {"temperature": 300, "seeds": [1, 1]}}, "runs.seeds", "distinct whole numbers"),
    ({"runs": {"temperature": 300, "seeds": "1"}}, "runs.seeds", "distinct whole numbers"),
    ({"runs": {"temperature": 300, "duration": 0}}, "runs.duration", "(0, 1000] ps"),
    ({"runs": {"temperature": 300, "steps": 10}}, "runs.steps", "unknown key"),
    ({"runs": [300]}, "runs", "must be a mapping"),
])
def test_bad_md_scenes_name_the_key_and_exit_2(cluster, run, system, key, message):
    tree = {"openmm": "system.xml", "positions": "structure.pdb", **system}
    tree = {k: v for k, v in tree.items() if v is not None}
    path = cluster / f"bad-{key}.yaml"
    path.write_text(yaml.safe_dump({"method": "verlet", "time_unit": "fs", "system": tree}))
    code, out, err = run("advise", str(path))
    assert code == 2
    assert f"{path}::$.system.{key}:" in err
    assert message in err.lower() or message in err
    assert len(err.strip().splitlines()) == 1


def test_a_rule_without_a_structure_file_is_refused(cluster, tmp_path):
    """A State has no bonds or elements: a constraint rule or HMR cannot be applied."""
    from stepsafe.systems.md import openmm_engine as oe

    engine = oe.load(cluster / "system.xml", cluster / "structure.pdb")
    (tmp_path / "state.xml").write_text(engine.state_xml())
    (tmp_path / "system.xml").write_text(engine.system_xml())
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({"method": "verlet", "system": {
        "openmm": "system.xml", "positions": "state.xml", "constraints": "h-bonds"}}))
    with pytest.raises(StepsafeError, match="PDB or PDBx"):
        stepsafe.advise(scene=str(path))
    stepsafe.advise(scene=str(path), constraints="none")  # the System's own: none


def test_md_keywords_need_an_openmm_system():
    with pytest.raises(StepsafeError, match="only for an OpenMM system"):
        stepsafe.advise("verlet", [1.0], hydrogen_mass=3)
    with pytest.raises(StepsafeError, match="positions= goes with openmm_system="):
        stepsafe.advise("verlet", [1.0], positions=np.zeros((3, 3)))
    system, x = one_water()
    with pytest.raises(StepsafeError, match="needs positions="):
        stepsafe.advise("verlet", openmm_system=system)
    with pytest.raises(StepsafeError, match=r"shape \(3, 3\)"):
        stepsafe.advise("verlet", openmm_system=system, positions=x[:2])


def test_missing_openmm_is_exit_2_naming_the_extra(cluster, run, monkeypatch):
    path = scene(cluster, "missing.yaml")
    for name in ("openmm", "openmm.app", "openmm.unit"):
        monkeypatch.setitem(sys.modules, name, None)
    code, _, err = run("check", path, "--step", "1")
    assert code == 2
    assert "$.system.openmm:" in err and "pip install 'stepsafe[openmm]'" in err


# --- verdicts against OpenMM's own integrators (fixed seeds) ------------------------------

#: Seeds of every trial run (thermalisation and Langevin noise).
SEEDS = (1, 2, 3)


def engine_of(folder, xml="system.xml", pdb="structure.pdb", **system):
    """The engine a scene of ``folder`` analyses (same rule, masses and minimisation)."""
    from stepsafe.systems.md import system as md

    def fail(key, message):
        return StepsafeError(message, key)

    chosen = md.settings({"openmm": xml, "positions": pdb, **system}, fail)
    engine = md.load_engine(xml, pdb, folder, fail)
    return md.prepare(engine, chosen, fail)[0]


def trials(engine, integrator, step_fs, temperature, **spec):
    from stepsafe.systems.md import enginerun as er

    return er.run_trials(engine.system_xml(), engine.state_xml(), er.TrialSpec(
        integrator, step_fs / 1000.0, spec.pop("duration", 1.0), temperature=temperature,
        seeds=SEEDS, equilibration=0.5, **spec))


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["verlet", "langevin-middle"])
@pytest.mark.parametrize("system", [{}, {"constraints": "h-bonds"},
                                    {"constraints": "h-bonds", "hydrogen_mass": 3}],
                         ids=["flexible", "h-bonds", "h-bonds-hmr3"])
def test_openmm_blows_up_just_above_the_limit_and_runs_below(cluster, integrator, system):
    """The water cluster at its minimum. At 1 K (the linearisation holds): check says SAFE
    at 0.99 h_max and every seed of OpenMM's integrator runs 1 ps with its total energy
    within 100 n_dof kT of its start (a linearly stable Verlet's energy fluctuates by up to
    1/(1 - (omega h/2)^2) = 50 times the fast modes' kT there), UNSAFE at 1.01 h_max and every
    seed blows up (an unstable mode grows by a factor 1.15 per step and more). At 300 K:
    1.1 h_max blows up in every seed, and 0.5 h_max runs 2 ps without blow-up, Verlet
    drifting less than 0.01 kT/ps per degree of freedom. (Between the two the 0 K verdict
    says nothing about 300 K: test_runs_at_300_k_turn_a_linearly_safe_step_unsafe.
    LangevinMiddle has Verlet's limit omega h < 2 on the harmonic oscillator: its O step
    only scales the velocities.)"""
    from stepsafe.systems.md import enginerun as er

    path = scene(cluster, f"trial-{len(system)}.yaml", minimize=True, **system)
    method = integrator  # the library's verlet and langevin-middle: OpenMM's integrators
    h_max = stepsafe.advise(method, scene=path).h_max
    assert stepsafe.check(method, 0.99 * h_max, scene=path).safe
    assert not stepsafe.check(method, 1.01 * h_max, scene=path).safe
    engine = engine_of(cluster, minimize=True, **system)
    below = trials(engine, integrator, 0.99 * h_max, 1.0, energy_bound=100.0)
    assert not below.blew_up, [r.reason for r in below.runs]
    above = trials(engine, integrator, 1.01 * h_max, 1.0, energy_bound=100.0)
    assert all(r.blew_up for r in above.runs)
    safe = trials(engine, integrator, 0.5 * h_max, 300.0, duration=2.0)
    assert not safe.blew_up
    if integrator == "verlet":
        drift, _ = safe.drift()
        assert abs(drift) < er.DRIFT_TOLERANCE
    unsafe = trials(engine, integrator, 1.1 * h_max, 300.0)
    assert all(r.blew_up for r in unsafe.runs)


@pytest.mark.slow
def test_villin_at_4_fs_with_h_bonds_and_hmr(tmp_path):
    """The villin headpiece (582 atoms, Amber14, vacuum), minimised, h-bond constraints and
    3 amu hydrogens: the analysis (Lanczos) puts the limit near 5.6 fs (aromatic ring
    stretches; no hydrogen among the fastest modes), so 4 fs is SAFE, and OpenMM's Verlet
    runs 4 fs at 300 K for 2 ps in every seed, drifting less than 0.01 kT/ps per degree of
    freedom; at 1 K OpenMM blows up at 1.01 h_max in every seed."""
    from stepsafe.systems.md import enginerun as er
    from stepsafe.systems.md import openmm_engine as oe

    xml, pdb = oe.write_example_system("villin", tmp_path)
    settings = {"constraints": "h-bonds", "hydrogen_mass": 3, "minimize": True}
    tree = {"method": "verlet", "time_unit": "fs", "h": 4,
            "system": {"openmm": xml.name, "positions": pdb.name, **settings}}
    path = tmp_path / "villin.yaml"
    path.write_text(yaml.safe_dump(tree))
    report = stepsafe.check(scene=str(path))
    assert report.safe
    items = report.record["system"]["items"]
    assert not any(name.split(":")[1].startswith("H") for item in items[:5]
                   for name, _ in item["atoms"])
    h_max = report.h_max
    ((rule, shown),) = readme_rows("villin headpiece")
    assert rule == "h-bonds, 3 amu" and abs(h_max - float(shown.split()[0])) <= 0.01
    engine = engine_of(tmp_path, xml.name, pdb.name, **settings)
    run = trials(engine, "verlet", 4.0, 300.0, duration=2.0, equilibration_step=0.001)
    assert not run.blew_up
    assert abs(run.drift()[0]) < er.DRIFT_TOLERANCE
    above = trials(engine, "verlet", 1.01 * h_max, 1.0, energy_bound=100.0,
                   equilibration_step=0.001)
    assert all(r.blew_up for r in above.runs)


@pytest.mark.slow
def test_runs_at_300_k_turn_a_linearly_safe_step_unsafe(cluster, run):
    """runs: at 300 K: 0.5 h_max passes the linear check and OpenMM's runs (3 seeds,
    stated); at 0.95 h_max every mode keeps its structure at the minimum, yet the runs
    blow up (every seed, within 300 steps), so check says UNSAFE (exit 1) and says why. A
    method OpenMM cannot run is refused (exit 2)."""
    path = scene(cluster, "runs.yaml", minimize=True,
                 runs={"temperature": "300 K", "seeds": [1, 2, 3], "duration": "2 ps"})
    h_max = stepsafe.advise(scene=path).h_max
    good = stepsafe.check("verlet", 0.5 * h_max, scene=path)
    assert good.safe and good.record["engine_runs"]["verdict"] == "stable"
    assert good.record["engine_runs"]["seeds"] == [1, 2, 3]
    code, out, _ = run("check", path, "--step", repr(0.95 * h_max), "--json")
    assert code == 1
    jsonschema = pytest.importorskip("jsonschema")
    from stepsafe.api.schemas import output_schema

    data = json.loads(out)
    jsonschema.validate(data, output_schema("check"))
    assert data["checks"][0]["engine_runs"]["verdict"] == "blew up"
    code, out, _ = run("check", path, "--step", repr(0.95 * h_max))
    assert code == 1
    assert "every mode keeps its structure, but verlet in OpenMM at 300 K" in out
    assert "blew up" in out
    code, _, err = run("check", path, "--method", "pefrl", "--step", "0.5")
    assert code == 2 and "OpenMM runs verlet, langevin-middle only" in err
