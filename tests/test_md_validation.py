"""stepsafe's verdicts on the committed MD scenes (examples/water-box.yaml: 129 flexible TIP3P
waters with PME; examples/villin.yaml: the villin headpiece, Amber14, vacuum) against
OpenMM's own integrators at 300 K, fixed seeds; the ordering of the 300 K column of the
validation table in docs/guides/openmm.md, on the water cluster; and the Lanczos path of a
box of about 1,200 atoms (no dense Hessian; memory far below one) against the isolated
molecule and, on a small box, against the dense Hessian."""

from __future__ import annotations

import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import yaml
from md_support import tip3p_isolated_frequencies, water_cluster

import stepsafe
from stepsafe.exceptions import StepsafeError

openmm = pytest.importorskip("openmm")

pytestmark = pytest.mark.openmm

ROOT = Path(__file__).resolve().parent.parent
#: Seeds of the trial runs (thermalisation and Langevin noise).
SEEDS = (1, 2)
#: The steps tried, as fractions of stepsafe's limit: one SAFE, one UNSAFE.
BELOW, ABOVE = 0.7, 1.05


def prepared(scene: Path, **overrides):
    """The engine stepsafe analyses for ``scene`` (same rule, masses and minimum)."""
    from stepsafe.systems.md import system as md

    tree = {**yaml.safe_load(scene.read_text())["system"], **overrides}

    def fail(key, message):
        return StepsafeError(message, key)

    chosen = md.settings(tree, fail)
    engine = md.load_engine(tree["openmm"], tree["positions"], scene.parent, fail)
    return md.prepare(engine, chosen, fail)[0]


@pytest.mark.slow
@pytest.mark.parametrize("name, integrator, rule", [
    ("water-box.yaml", "verlet", None),
    ("water-box.yaml", "langevin-middle", None),
    ("villin.yaml", "verlet", "h-bonds"),
], ids=["water-box-verlet", "water-box-langevin-middle", "villin-h-bonds-verlet"])
def test_safe_steps_run_in_openmm_and_unsafe_steps_fail(name, integrator, rule):
    """check says SAFE at 0.7 h_max and UNSAFE at 1.05 h_max; thermalised at 300 K (0.5 ps of
    LangevinMiddle, friction 10/ps), OpenMM's integrator of the same name runs the SAFE step
    1 ps in every seed without a blow-up (total energy within n_dof kT / 2 of its start,
    Verlet's drift below 0.01 kT/ps per degree of freedom, kinetic temperature within 50 K of
    300 K), and blows up at the UNSAFE step in every seed within 0.5 ps."""
    from stepsafe.systems.md import enginerun as er

    scene = ROOT / "examples" / name
    extra = {"constraints": rule} if rule else {}
    h_max = stepsafe.advise(integrator, scene=str(scene), **extra).h_max
    assert stepsafe.check(integrator, BELOW * h_max, scene=str(scene), **extra).safe
    assert not stepsafe.check(integrator, ABOVE * h_max, scene=str(scene), **extra).safe
    engine = prepared(scene, **extra)
    system, state = engine.system_xml(), engine.state_xml()
    common = dict(temperature=300.0, seeds=SEEDS, equilibration=0.5,
                  equilibration_step=min(1.0, 0.35 * h_max) / 1000.0)
    below = er.run_trials(system, state, er.TrialSpec(integrator, BELOW * h_max / 1000.0, 1.0,
                                                      **common))
    assert below.verdict() == "stable", [r.reason for r in below.runs]
    if integrator == "verlet":
        mean, _ = below.drift()
        assert abs(mean) < er.DRIFT_TOLERANCE
    assert all(abs(r.kinetic_temperature - 300.0) < 50.0 for r in below.runs)
    above = er.run_trials(system, state, er.TrialSpec(integrator, ABOVE * h_max / 1000.0, 0.5,
                                                      **common))
    assert all(r.blew_up for r in above.runs), [r.reason for r in above.runs]


#: The guide's validation table: OpenMM's steps, as fractions of the 0 K limit, and the
#: length of each run at 300 K, ps (the limit at 300 K is asked for a run of that length).
FRACTIONS, DURATION = (0.7, 0.8, 0.9, 0.95, 1.0, 1.05), 5.0


@pytest.mark.slow
def test_water_cluster_limit_at_300_K_lies_below_openmm_s_first_failure_and_runs_there():
    """The ordering every row of the guide's validation table keeps, on the 8-water cluster
    with Verlet: stepsafe's h_max at 300 K for a run of 5 ps (its own runs in OpenMM of
    5 ps: a bisection in seeds 1-3, a confirmation in 72 or more others) lies below the 0 K
    limit and below the first step of OpenMM's scan that fails, and OpenMM runs that h_max
    in six other seeds (11-16), 5 ps each, without a blow-up or a drift beyond the
    tolerance. The scan is the table's: per seed 1-3, 1 ps of
    LangevinMiddle at 300 K (friction 10/ps, step 0.35 h_max at most 1 fs), then 5 ps of
    VerletIntegrator at 0.7, 0.8, ... of the 0 K h_max, up to the first failure (some step
    must fail: at 1.05 every run blows up)."""
    from stepsafe.systems.md import enginerun as er

    scene = ROOT / "examples" / "water-cluster.yaml"
    h_zero = stepsafe.advise(scene=str(scene)).h_max
    warm = stepsafe.advise(scene=str(scene), temperature=300, length=f"{DURATION:g} ps")
    assert warm.record["thermal"]["limited_by"] == "OpenMM runs"
    assert warm.h_max < h_zero
    engine = prepared(scene)
    system, state = engine.system_xml(), engine.state_xml()

    def runs(h_fs, seeds):
        return er.run_trials(system, state, er.TrialSpec(
            "verlet", h_fs / 1000.0, DURATION, temperature=300.0, seeds=seeds,
            equilibration=1.0, equilibration_step=min(1.0, 0.35 * h_zero) / 1000.0,
            equilibration_friction=10.0))

    first_failure = None
    for fraction in FRACTIONS:
        if runs(fraction * h_zero, (1, 2, 3)).verdict() != "stable":
            first_failure = fraction * h_zero
            break
    assert first_failure is not None
    assert warm.h_max < first_failure
    there = runs(warm.h_max, (11, 12, 13, 14, 15, 16))
    assert there.verdict() == "stable", [r.reason for r in there.runs]


def water_box(folder: Path, edge: float, cutoff: float) -> Path:
    """A scene (Verlet, fs, minimised) on a box of flexible TIP3P water with PME."""
    from stepsafe.systems.md import openmm_engine as oe

    xml, pdb = oe.write_example_system("water", folder, box_edge=edge, cutoff=cutoff)
    scene = folder / f"box-{edge:g}.yaml"
    scene.write_text(yaml.safe_dump({"method": "verlet", "time_unit": "fs", "system": {
        "openmm": xml.name, "positions": pdb.name, "minimize": True}}))
    return scene


@pytest.mark.slow
def test_a_large_box_is_analysed_by_lanczos_without_a_dense_hessian(tmp_path, monkeypatch):
    """396 waters with PME (1188 atoms), analysed on the large-system path (the fastest mode
    alone; the threshold lowered to 1000 atoms for the test): no dense Hessian is formed (the
    function that forms one fails if called), the memory Python and numpy hold at the peak of
    the analysis (imports and OpenMM's start-up done before, on the 24-atom cluster) stays
    below 5% of one dense 3N x 3N matrix, and Verlet's limit is within 1% of the isolated molecule's
    antisymmetric O-H stretch, 2 / sqrt(k_r (1/m_H + (1 - cos theta0)/m_O)) (hydrogen bonds
    move the stretch by a fraction of a percent)."""
    from stepsafe.systems.md import system as md

    def dense(*args, **kwargs):
        raise AssertionError("a dense Hessian was formed")

    water_cluster(tmp_path)
    warm = tmp_path / "cluster.yaml"
    warm.write_text(yaml.safe_dump({"method": "verlet", "system": {
        "openmm": "system.xml", "positions": "structure.pdb"}}))
    stepsafe.advise(scene=str(warm))
    monkeypatch.setattr(md, "hessian", dense)
    monkeypatch.setattr(md, "ONE_MODE_ATOMS", 1000)
    scene = water_box(tmp_path, 2.32, 1.0)
    tracemalloc.start()
    try:
        report = stepsafe.advise(scene=str(scene))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    analysis = report.record["system"]["analysis"]
    assert "the one of largest |omega^2| of 3564 by Lanczos" in analysis
    assert "1188 moving atoms" in analysis
    dim = 3 * 1188
    assert peak < 0.05 * dim * dim * 8, peak
    stretch = tip3p_isolated_frequencies()["antisymmetric_stretch"]
    isolated = 2.0 / math.sqrt(stretch) * 1000.0
    assert abs(report.h_max / isolated - 1) < 0.01


@pytest.mark.slow
def test_lanczos_paths_agree_with_the_dense_hessian_on_a_small_box(tmp_path, monkeypatch):
    """41 waters with PME (123 atoms): the dense Hessian (every mode), Lanczos for the five
    fastest and Lanczos for the fastest alone to the large-system tolerance give the same
    largest omega^2 within the sum of their error bounds, so the same limit."""
    from stepsafe.systems.md import system as md

    scene = water_box(tmp_path, 1.1, 0.5)
    tree = yaml.safe_load(scene.read_text())["system"]

    def fail(key, message):
        return StepsafeError(message, key)

    chosen = md.settings(tree, fail)
    engine = md.prepare(md.load_engine(tree["openmm"], tree["positions"], tmp_path, fail),
                        chosen, fail)[0]
    assert engine.n_particles == 123
    dense = md.analyse(engine, chosen)
    assert dense.complete
    monkeypatch.setattr(md, "DENSE_ATOMS", 0)
    five = md.analyse(engine, chosen)
    monkeypatch.setattr(md, "ONE_MODE_ATOMS", 0)
    one = md.analyse(engine, chosen)
    assert not five.complete and not one.complete
    assert len(five.spectrum.eigenvalues) == 5 and len(one.spectrum.eigenvalues) == 1
    top = dense.spectrum.eigenvalues[0]
    allowed = md.eigenvalue_errors(dense)[0]
    for lanczos in (five, one):
        lam = lanczos.spectrum.eigenvalues[0]
        assert abs(lam - top) <= allowed + md.eigenvalue_errors(lanczos)[0]
    np.testing.assert_allclose(five.spectrum.eigenvalues, dense.spectrum.eigenvalues[:5],
                               atol=allowed + float(np.max(md.eigenvalue_errors(five))))


def test_progress_names_the_lanczos_iterations_and_counts_them(tmp_path, monkeypatch):
    """A progress callback with a ``stage`` attribute (the command line's bar) is told what
    each stage counts: the minimiser's iterations, the step control's trial steps, then the
    Lanczos iterations (one Hessian-vector product each, no total known), counted from 1
    up."""
    from stepsafe.systems import loader
    from stepsafe.systems.md import system as md

    monkeypatch.setattr(md, "DENSE_ATOMS", 0)
    water_cluster(tmp_path)
    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump({"method": "verlet", "time_unit": "fs", "system": {
        "openmm": "system.xml", "positions": "structure.pdb", "minimize": True}}))
    seen: list[tuple[str, int, int | None]] = []

    def progress(fraction):
        raise AssertionError("a stage was reported as a bare fraction")

    progress.stage = lambda label, done, total: seen.append((label, done, total))
    stepsafe.advise(scene=str(scene), progress=progress)
    labels = [label for label, _, _ in seen]
    lanczos = loader.MD_STAGES["products"]
    assert lanczos == "Lanczos iterations (Hessian-vector products)"
    order = [label for k, label in enumerate(labels) if k == 0 or labels[k - 1] != label]
    assert order == [loader.MD_STAGES[s] for s in ("minimize", "step control", "products")]
    counts = [done for label, done, total in seen if label == lanczos]
    assert counts == list(range(1, len(counts) + 1)) and len(counts) > 5
    assert all(total is None for label, _, total in seen if label == lanczos)


@pytest.mark.parametrize("kind, folder", [("water", "water-box"), ("villin", "villin")])
def test_committed_md_examples_are_what_write_example_system_builds(tmp_path, kind, folder):
    """examples/water-box/ and examples/villin/ are rebuilt from the files in the OpenMM wheel
    by write_example_system: the same System XML, the same PDB (but for OpenMM's dated
    REMARK line)."""
    from stepsafe.systems.md import openmm_engine as oe

    xml, pdb = oe.write_example_system(kind, tmp_path)
    shipped = ROOT / "examples" / folder
    assert xml.read_text() == (shipped / "system.xml").read_text()

    def atoms(text):
        return [line for line in text.splitlines() if not line.startswith("REMARK")]

    assert atoms(pdb.read_text()) == atoms((shipped / "structure.pdb").read_text())
