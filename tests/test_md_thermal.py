"""OpenMM systems at temperature (stepsafe.systems.md.thermal): the scan of the runs against
engines whose failures are known exactly, the instantaneous frequencies at OpenMM's thermal
snapshots against the analytic Hessian of a TIP3P molecule, and, in the slow set, the verdicts
at 300 K on the water cluster against runs of OpenMM's VerletIntegrator written here (other
seeds than the analysis')."""

from __future__ import annotations

import math
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import pytest
from md_support import TIP3P, one_water, single_water_hessian

from stepsafe.systems.md import enginerun as er
from stepsafe.systems.md import thermal as th

ROOT = Path(__file__).resolve().parents[1]


# --- the scan, on engines whose runs fail above a known step -------------------------------

class Threshold:
    """An engine whose run of seed s at step h blows up when ``h >= edge(s)``; it counts the
    trials run."""

    def __init__(self, edge):
        self.edge = edge
        self.steps = []

    def trial_worker(self):
        return nullcontext()

    def trials(self, spec, progress=None, worker=None):
        self.steps.append((spec.step, spec.seeds))
        runs = tuple(er.SeedRun(s, spec.step >= self.edge(s), 10 if spec.step >= self.edge(s)
                                else None, "", spec.steps, 0.0, 0.0, 0.0, 300.0)
                     for s in spec.seeds)
        return er.TrialRecord(spec, 30, runs)


RUNS = th.Runs("verlet", 300.0)


@pytest.mark.parametrize("edge", [0.5, 0.71, 0.8, 0.95, 0.9985, 1.2])
def test_scan_finds_the_largest_passing_step_within_its_resolution(edge):
    """Every seed fails from ``edge`` on (h_linear = 1): the scan's step passes and lies
    within RESOLUTION of the edge below it (or at TOP when the edge is above it), every
    step it calls failing failed, and the step was confirmed by other seeds."""
    engine = Threshold(lambda s: edge)
    found = th.scan(engine, RUNS, 1.0, 1e-3)
    every = RUNS.seeds + th.confirm_seeds(RUNS.seeds)
    if edge > th.TOP:
        assert found.h_clear == th.TOP and found.h_fail is None
    else:
        below = found.h_clear / (1 - th.BACKOFF)  # the bisection's passing step
        assert below < edge <= found.h_fail
        assert found.h_fail / below - 1 <= th.RESOLUTION * (1 + 1e-12)
        assert (below, RUNS.seeds) in engine.steps
    assert engine.steps[-1] == (found.h_clear, every)
    assert tuple(r.seed for r in found.confirmed.runs) == every
    assert not found.confirmed.blew_up


def test_scan_lowers_a_step_the_confirmation_seeds_fail():
    """The bisection seeds fail from 0.9 on, the confirmation's from 0.85: the step given is
    below 0.85, at most BACKOFF below, and passed in every seed."""
    engine = Threshold(lambda s: 0.9 if s in RUNS.seeds else 0.85)
    found = th.scan(engine, RUNS, 1.0, 1e-3)
    assert 0.85 * (1 - th.BACKOFF) <= found.h_clear < 0.85
    assert not found.confirmed.blew_up and len(found.confirmed.runs) == 6


def test_scan_gives_no_step_when_every_run_fails():
    found = th.scan(Threshold(lambda s: 0.0), RUNS, 1.0, 1e-3)
    assert found.h_clear == 0.0 and found.confirmed is None


# --- frequencies at OpenMM's thermal snapshots ----------------------------------------------

openmm_only = pytest.mark.openmm


def one_water_engine():
    """One TIP3P molecule at its equilibrium geometry behind the engine interface."""
    pytest.importorskip("openmm")
    from stepsafe.systems.md import openmm_engine as oe

    return oe.OpenMMEngine(*one_water())


@openmm_only
def test_snapshot_frequencies_are_the_analytic_hessian_s_largest():
    """One TIP3P molecule at 300 K: OpenMM's LangevinMiddle moves its bonds by thermal
    amounts (the frames differ), and at every frame the largest eigenvalue found by Lanczos
    on differences of OpenMM's forces is the analytic Hessian's within its stated error."""
    engine = one_water_engine()
    spec = er.SamplingSpec(300.0, 0.0005, 10.0, 200, 20, 4, (7, 8))
    frequencies, ensemble = th.snapshot_frequencies(engine, spec)
    x = ensemble.q.reshape(-1, 3, 3)
    assert x.shape[0] == 8 and list(ensemble.chain) == [0] * 4 + [1] * 4
    bonds = np.linalg.norm(x[:, 1] - x[:, 0], axis=1)
    assert np.ptp(bonds) > 1e-4  # thermal O-H amplitude ~ sqrt(kT/k) = 2.3e-3 nm
    s = 1 / np.repeat(np.sqrt([TIP3P["mO"], TIP3P["mH"], TIP3P["mH"]]), 3)
    for k, frame in enumerate(x):
        want = np.linalg.eigvalsh(s[:, None] * single_water_hessian(frame) * s[None, :])[-1]
        assert abs(frequencies.lambda_max[k] - want) <= frequencies.error[k], k
        assert frequencies.error[k] < 1e-5 * want


@openmm_only
def test_linear_limit_at_temperature_is_below_the_0_K_one():
    """At 300 K the largest frequency a 10 ps run of one water meets is above the
    minimum's (its bonds stretch and compress), so z*/omega_q < z*/omega_0."""
    engine = one_water_engine()
    s = 1 / np.repeat(np.sqrt([TIP3P["mO"], TIP3P["mH"], TIP3P["mH"]]), 3)
    lam0 = np.linalg.eigvalsh(s[:, None] * single_water_hessian(engine.positions)
                              * s[None, :])[-1]
    omega0 = math.sqrt(lam0)
    at = th.linear_at_temperature(engine, 300.0, 2.0, omega0, 10.0)
    assert at.h_linear < 2.0 / omega0
    assert at.omega.maximum > omega0 and at.h_linear == pytest.approx(2.0 / at.omega.upper)
    assert at.omega.frames == th.FRAMES * len(th.SAMPLING_SEEDS)


# --- the water cluster at 300 K against OpenMM's own Verlet ---------------------------------

#: Seeds of the runs written here: none of the analysis' (1-6).
OWN_SEEDS = tuple(range(101, 111))


def own_runs(engine, h_ps, seeds=OWN_SEEDS, duration=2.0, temperature=300.0,
                    langevin=False):
    """OpenMM's VerletIntegrator at h from thermal states made here: per seed, velocities
    at T and 1 ps of LangevinMiddle (0.5 fs, 10/ps), then ``duration`` ps of NVE sampled
    every 10 steps; a seed blows up at a non-finite energy, an OpenMM error or the total
    energy moving by n_dof kT / 2. Returns (blew_up per seed, mean drift in kT/ps per degree
    of freedom over the seeds that finished). With ``langevin``: LangevinMiddleIntegrator
    (friction 1/ps) in place of Verlet, blowing up when the kinetic energy exceeds
    n_dof kT (its mean plus n_dof kT / 2); no drift."""
    import openmm

    kT = er.MOLAR_GAS_CONSTANT * temperature
    n_dof = 3 * engine.n_particles - engine.system.getNumConstraints()
    platform = openmm.Platform.getPlatformByName("CPU")
    blew, drifts = [], []
    for seed in seeds:
        eq = openmm.LangevinMiddleIntegrator(temperature, 10.0, 0.0005)
        eq.setRandomNumberSeed(seed)
        ctx = openmm.Context(engine.system, eq, platform, {"Threads": "1"})
        ctx.setPositions(engine.positions)
        ctx.setVelocitiesToTemperature(temperature, seed)
        eq.step(2000)
        state = ctx.getState(getPositions=True, getVelocities=True)
        nve = openmm.VerletIntegrator(h_ps)
        if langevin:
            nve = openmm.LangevinMiddleIntegrator(temperature, 1.0, h_ps)
            nve.setRandomNumberSeed(seed + 1000)
        run = openmm.Context(engine.system, nve, platform, {"Threads": "1"})
        run.setState(state)
        times, energy, failed = [], [], False
        for k in range(int(round(duration / h_ps / 10))):
            try:
                nve.step(10)
                st = run.getState(getEnergy=True)
                kinetic = st.getKineticEnergy()._value
                e = st.getPotentialEnergy()._value + kinetic
            except Exception:
                failed = True
                break
            if not math.isfinite(e) or (langevin and kinetic > n_dof * kT) or (
                    not langevin and energy and abs(e - energy[0]) > 0.5 * n_dof * kT):
                failed = True
                break
            times.append((k + 1) * 10 * h_ps)
            energy.append(e)
        blew.append(failed)
        if not failed and not langevin:
            drifts.append(np.polyfit(times, energy, 1)[0] / (n_dof * kT))
    return blew, float(np.mean(drifts)) if drifts else math.nan


@pytest.fixture(scope="module")
def cluster_at_300K():
    pytest.importorskip("openmm")
    import stepsafe

    scene = str(ROOT / "examples" / "water-cluster.yaml")
    warm = stepsafe.advise(scene=scene, temperature=300, length="10 ps")
    return scene, warm


@openmm_only
@pytest.mark.slow
def test_water_cluster_limit_at_300_K_is_below_0_K_and_openmm_agrees(cluster_at_300K):
    """The 8-water cluster at 300 K, a run of 10 ps: the limit at temperature lies below the
    0 K one, set by OpenMM's runs. A step below the 0 K limit that the analysis calls UNSAFE
    at 300 K (0.95 of the 0 K limit, SAFE at 0 K) blows up or drifts beyond the tolerance in
    runs written here with other seeds; the step it gives as safe at 300 K (just below its
    h_max) runs 2 ps in 10 other seeds without blow-up, drifting less than the tolerance;
    check agrees with advise on both sides of its h_max."""
    import stepsafe
    from stepsafe.systems.md import openmm_engine as oe

    scene, warm = cluster_at_300K
    t = warm.record["thermal"]
    h0 = t["h_max_0K"]
    assert warm.h_max < h0 and t["limited_by"] == "OpenMM runs"
    runs = t["minima"][0]["engine_runs"]
    assert runs["h_clear"] == pytest.approx(warm.h_max) and runs["h_fail"] > warm.h_max
    assert set(runs["confirmed_seeds"]) == {1, 2, 3, 4, 5, 6}
    unsafe = 0.95 * h0
    assert stepsafe.check(scene=scene, h=unsafe).safe
    hot = stepsafe.check(scene=scene, h=unsafe, temperature=300, length="10 ps")
    assert not hot.safe
    safe = 0.999 * warm.h_max
    assert stepsafe.check(scene=scene, h=safe, temperature=300, length="10 ps").safe
    above = stepsafe.check(scene=scene, h=1.01 * warm.h_max, temperature=300, length="10 ps")
    assert not above.safe and above.record["thermal"]["reasons"] == [
        "at or above the largest step the runs in the engine pass (the limit at temperature "
        "advise gives)"]
    engine = oe.load(ROOT / "examples" / "water-cluster" / "system.xml",
                     ROOT / "examples" / "water-cluster" / "structure.pdb", platform="CPU",
                     threads=1)
    engine.minimize(1.0)
    blew, drift = own_runs(engine, unsafe / 1000.0)
    assert any(blew) or abs(drift) > er.DRIFT_TOLERANCE, (blew, drift)
    blew, drift = own_runs(engine, safe / 1000.0)
    assert not any(blew) and abs(drift) < er.DRIFT_TOLERANCE, (blew, drift)


def cluster_scene(folder, **keys):
    """The water cluster's scene, its files linked into ``folder``, with ``keys`` added."""
    import yaml

    (folder / "water-cluster").symlink_to(ROOT / "examples" / "water-cluster")
    tree = yaml.safe_load((ROOT / "examples" / "water-cluster.yaml").read_text())
    system = keys.pop("system", {})
    tree["system"].update(system)
    tree.update(keys)
    path = folder / "scene.yaml"
    path.write_text(yaml.safe_dump(tree))
    return str(path)


@openmm_only
def test_runs_at_another_temperature_than_asked_are_refused_naming_the_key(tmp_path, run):
    pytest.importorskip("openmm")
    scene = cluster_scene(tmp_path, system={"runs": {"temperature": "310 K"}})
    code, out, err = run("check", scene, "--temperature", "300K", "--length", "10ps")
    assert code == 2 and "SAFE" not in out
    assert "$.system.runs.temperature" in err and "310 K" in err


@openmm_only
@pytest.mark.slow
def test_scene_temperature_and_runs_give_the_check_and_its_json(tmp_path, run):
    """``temperature:``, ``length:`` and ``h:`` in the scene, ``runs:`` with two seeds of
    1 ps: the check at 2.7 fs exits 1, its JSON fits the schema and states the seeds run
    (the two and two others), their length and the drift tolerance ``--max-drift`` sets."""
    pytest.importorskip("openmm")
    jsonschema = pytest.importorskip("jsonschema")
    import json

    from stepsafe.api.schemas import output_schema

    scene = cluster_scene(tmp_path, temperature="300 K", length="10 ps", h=2.7,
                          system={"runs": {"temperature": "300 K", "seeds": [11, 12],
                                           "duration": "1 ps"}})
    code, out, err = run("check", scene, "--json", "--max-drift", "0.5")
    assert code == 1, err
    data = json.loads(out)
    jsonschema.validate(data, output_schema("check"))
    entry = data["checks"][0]
    assert "engine_runs" not in entry  # (the 0 K check runs nothing at temperature)
    runs = entry["thermal"]["minima"][0]["engine_runs"]
    assert runs["seeds"] == [11, 12] and runs["confirm_seeds"] == [13, 14]
    assert runs["duration"] == 1.0 and runs["trials"][0]["seeds"] == [11, 12, 13, 14]
    assert entry["thermal"]["temperature"] == 300.0 and entry["thermal"]["energy_unit"] == \
        "kJ/mol"
    # --max-drift: kJ/mol per fs for the 24 atoms, as kT per ps per degree of freedom
    kT = er.MOLAR_GAS_CONSTANT * 300.0
    assert runs["drift_tolerance"] == pytest.approx(0.5 * 1000.0 / (72 * kT), rel=1e-12)


@openmm_only
@pytest.mark.slow
def test_water_cluster_with_langevin_middle_at_300_K_against_openmm():
    """LangevinMiddle (friction 1/ps) on the cluster at 300 K: its limit at temperature
    lies below the 0 K one (Verlet's); at 0.9 of the 0 K limit, SAFE at 0 K, the analysis
    says UNSAFE and LangevinMiddle runs written here (other seeds) blow up; just below the
    h_max it gives they run 2 ps in 10 seeds."""
    import stepsafe
    from stepsafe.systems.md import openmm_engine as oe

    scene = str(ROOT / "examples" / "water-cluster.yaml")
    warm = stepsafe.advise("langevin-middle", scene=scene, temperature=300, length="10 ps")
    h0 = warm.record["thermal"]["h_max_0K"]
    assert warm.h_max < h0 and warm.record["thermal"]["limited_by"] == "OpenMM runs"
    unsafe = 0.9 * h0
    assert stepsafe.check("langevin-middle", unsafe, scene=scene).safe
    assert not stepsafe.check("langevin-middle", unsafe, scene=scene, temperature=300,
                              length="10 ps").safe
    engine = oe.load(ROOT / "examples" / "water-cluster" / "system.xml",
                     ROOT / "examples" / "water-cluster" / "structure.pdb", platform="CPU",
                     threads=1)
    engine.minimize(1.0)
    blew, _ = own_runs(engine, unsafe / 1000.0, langevin=True)
    assert any(blew), blew
    blew, _ = own_runs(engine, 0.999 * warm.h_max / 1000.0, langevin=True)
    assert not any(blew), blew
