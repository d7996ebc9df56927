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
from hypothesis import given, settings
from hypothesis import strategies as st
from md_support import TIP3P, one_water, single_water_hessian

from stepsafe.systems.md import enginerun as er
from stepsafe.systems.md import thermal as th

ROOT = Path(__file__).resolve().parents[1]


# --- the scan, on engines whose runs fail above a known step -------------------------------

def _record(spec, fails):
    """The TrialRecord of ``spec`` whose seed s blows up when ``fails(s)``, stopping at the
    first blow-up when the spec says so."""
    runs = []
    for s in spec.seeds:
        bad = bool(fails(s))
        runs.append(er.SeedRun(s, bad, 10 if bad else None, "", spec.steps, 0.0, 0.0, 0.0,
                               300.0))
        if bad and spec.stop_at_blowup:
            break
    return er.TrialRecord(spec, 30, tuple(runs))


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
        return _record(spec, lambda s: spec.step >= self.edge(s))


RUNS = th.Runs("verlet", 300.0)
#: The seeds of the scan's first confirmation.
FIRST = th.confirm_seeds(RUNS.seeds, th.confirmations(th.MAX_FAILURE, th.CONFIDENCE, 0))


@pytest.mark.parametrize("edge", [0.5, 0.71, 0.8, 0.95, 0.9985, 1.2])
def test_scan_finds_the_largest_passing_step_within_its_resolution(edge):
    """Every seed fails from ``edge`` on (h_linear = 1): the scan's step passes and lies
    within RESOLUTION of the edge below it (or at TOP when the edge is above it), every
    step it calls failing failed, and the step was confirmed by the first confirmation's
    fresh seeds (72 for a failure probability below 0.05 at 95% over the confirmations)."""
    engine = Threshold(lambda s: edge)
    found = th.scan(engine, RUNS, 1.0, 1e-3)
    if edge > th.TOP:
        assert found.h_clear == th.TOP and found.h_fail is None
    else:
        below = found.h_clear / (1 - th.BACKOFF)  # the bisection's passing step
        assert below < edge <= found.h_fail
        assert found.h_fail / below - 1 <= th.RESOLUTION * (1 + 1e-12)
        assert (below, RUNS.seeds) in engine.steps
    assert engine.steps[-1] == (found.h_clear, FIRST)
    assert len(FIRST) == 72 and not set(FIRST) & set(RUNS.seeds)
    assert tuple(r.seed for r in found.confirmed.runs) == FIRST
    assert not found.confirmed.blew_up


def test_scan_lowers_a_step_the_confirmation_seeds_fail_and_confirms_on_fresh_seeds():
    """The bisection seeds fail from 0.9 on, the others from 0.85: the first confirmation
    (BACKOFF below the bisection's step, above 0.85) stops at its first seed, the step is
    lowered by 2 BACKOFF below 0.85 and passes in the second confirmation's seeds (86, none
    of the first's)."""
    engine = Threshold(lambda s: 0.9 if s in RUNS.seeds else 0.85)
    found = th.scan(engine, RUNS, 1.0, 1e-3)
    assert 0.85 <= found.h_fail < 0.9 * (1 - th.BACKOFF)
    assert found.h_clear == found.h_fail * (1 - 2 * th.BACKOFF) < 0.85
    first, second = [t for t in found.trials if t.stage.startswith("confirmation")]
    assert [r.seed for r in first.record.runs] == [FIRST[0]] and not first.passed
    assert first.planned == FIRST
    seeds = [r.seed for r in found.confirmed.runs]
    assert len(seeds) == 86 and seeds[0] == FIRST[-1] + 1 and second.passed
    assert not found.confirmed.blew_up


def test_scan_gives_no_step_when_every_run_fails():
    found = th.scan(Threshold(lambda s: 0.0), RUNS, 1.0, 1e-3)
    assert found.h_clear == 0.0 and found.confirmed is None


def test_the_record_of_the_runs_states_their_seeds_counts_and_failure_limit():
    """The JSON record of a scan (run of 20 ps, runs of 10 ps): the failure limit per run and
    its confidence, the runs a check and each confirmation need, the seeds of each step
    (the confirmation's fresh, all planned run), its Clopper-Pearson bound 1 - 0.025^(1/72),
    and that the runs do not follow the whole run."""
    import json

    from stepsafe.api import thermal as api_thermal

    found = th.scan(Threshold(lambda s: 0.8), RUNS, 1.0, 1e-3)
    rec = json.loads(json.dumps(api_thermal._runs_record(RUNS, list(found.trials), 1.0, 1.0,
                                                         20.0)))
    assert rec["max_failure"] == 0.05 and rec["failure_per"] == "run"
    assert rec["confidence"] == 0.95 and rec["check_runs"] == 59
    assert rec["confirmation_runs"] == [72, 86, 99, 113]
    assert rec["seeds"] == [1, 2, 3] and rec["duration"] == 10.0
    assert rec["max_duration"] == 10.0 and rec["run_length"] == 20.0 and not rec["followed"]
    bisection = [t for t in rec["trials"] if not t["stage"].startswith("confirmation")]
    assert all(t["seeds"] == [1, 2, 3] or t["failures"] == 1 for t in bisection)
    last = rec["trials"][-1]
    assert last["stage"] == "confirmation 1" and last["seeds"] == list(FIRST)
    assert last["planned_seeds"] == 72 and last["failures"] == 0
    assert last["confidence"] == 0.975
    assert last["upper"] == pytest.approx(1 - 0.025 ** (1 / 72), rel=1e-9) and \
        last["upper"] < 0.05


#: Runs of 5 ps.
RUNS_5PS = th.Runs("verlet", 300.0, duration=5.0)


def checked(monkeypatch, engine, h, run_length, runs=RUNS_5PS):
    """thermal_check of step h on ``engine`` with the linear limit at temperature 1 (its
    snapshots and frequencies replaced: only the runs are under test)."""
    from types import SimpleNamespace

    linear = SimpleNamespace(h_linear=1.0, ensemble=SimpleNamespace(h=1e-3))
    monkeypatch.setattr(th, "_at_temperature",
                        lambda analysis, r, z, length, progress: (engine, 1.0, 2.0, 2.49,
                                                                  linear))
    return th.thermal_check(None, runs, 2.0, h, run_length)


def test_check_runs_the_clopper_pearson_count_at_its_step(monkeypatch):
    """Runs fail from 0.8 (h_linear 1): at 0.5 every one of the 59 fresh seeds after the
    bisection's runs (bound 1 - 0.05^(1/59) < 0.05) and the check is SAFE; at 0.85 it stops
    at its first seed, UNSAFE; at 0.79 the runs pass but the step lies above the limit the
    scan gives (BACKOFF below its bisection), UNSAFE."""
    engine = Threshold(lambda s: 0.8)
    c = checked(monkeypatch, engine, 0.5, 5.0)
    assert c.safe and c.trial.planned == th.confirm_seeds((1, 2, 3), 59)
    assert len(c.trial.record.runs) == 59 and c.trial.upper == pytest.approx(
        1 - 0.05 ** (1 / 59), rel=1e-9) and c.trial.upper < 0.05
    bad = checked(monkeypatch, engine, 0.85, 5.0)
    assert not bad.safe and len(bad.trial.record.runs) == 1 and bad.trial.upper is None
    assert "1 of 59 seeds" in bad.reasons[0]
    near = checked(monkeypatch, engine, 0.79, 5.0)
    assert not near.safe and near.h_max < 0.79 and near.reasons == (
        "at or above the largest step the runs in the engine pass (the limit at temperature "
        "advise gives)",)


def test_limit_where_no_run_fails_is_the_confirmed_step_and_check_agrees_on_both_sides(
        monkeypatch):
    """No run fails below 1.2 (h_linear 1): advise's h_max is the step its confirmation ran,
    TOP h_linear, limited by the linear limit at temperature; check is SAFE just below it
    and UNSAFE at it and between it and the linear limit."""
    from types import SimpleNamespace

    engine = Threshold(lambda s: 1.2)
    linear = SimpleNamespace(h_linear=1.0, ensemble=SimpleNamespace(h=1e-3),
                             omega=SimpleNamespace(estimate=1.9))
    monkeypatch.setattr(th, "_at_temperature",
                        lambda analysis, r, z, length, progress: (engine, 1.0, 2.0, 2.49,
                                                                  linear))
    limit = th.thermal_limit(None, RUNS_5PS, 2.0, 5.0)
    assert limit.h_max == limit.scan.h_clear == th.TOP
    assert limit.limited_by == "linear at temperature"
    assert tuple(r.seed for r in limit.scan.confirmed.runs) == FIRST
    assert checked(monkeypatch, engine, 0.9999 * limit.h_max, 5.0).safe
    for h in (limit.h_max, 0.5 * (limit.h_max + 1.0)):
        c = checked(monkeypatch, engine, h, 5.0)
        assert not c.safe and c.h_max == limit.h_max


def test_check_of_a_run_longer_than_the_runs_is_not_safe(monkeypatch):
    """Runs of 5 ps that all pass do not make a 20 ps run SAFE: the reason names both
    lengths."""
    c = checked(monkeypatch, Threshold(lambda s: 0.8), 0.5, 20.0)
    assert not c.safe and c.trial.passed
    assert c.reasons[0].startswith("the run's 20 ps are longer than the runs in the engine "
                                   "(5 ps")


@settings(deadline=None, max_examples=20)
@given(st.floats(0.06, 0.5))
def test_check_passes_a_step_whose_runs_fail_more_often_than_the_limit_rarely(q):
    """A step whose runs fail with probability q > 0.05: the check passes it only when all
    59 of its runs pass, probability (1 - q)^59 < 0.05 (0.026 at q = 0.06); over 200 seeded
    draws the fraction of SAFE verdicts stays within that and a binomial margin."""
    with pytest.MonkeyPatch.context() as mp:
        safe = sum(checked(mp, Curve(lambda h: q, d), 0.5, 5.0).safe for d in range(200))
    p = (1 - q) ** 59
    assert p < 0.05 and safe <= 200 * p + 4 * math.sqrt(200 * p) + 1


@settings(deadline=None, max_examples=12)
@given(st.floats(1e-4, 0.5), st.floats(0.5, 0.999))
def test_confirmation_runs_are_the_fewest_whose_zero_failures_bound_the_probability(p, c):
    """m = confirmations(p, c): zero failures in m runs put the one-sided Clopper-Pearson
    bound (1 - (1 - c)^(1/m), from scipy's beta quantile) below p, in m - 1 runs not; the
    scan's k-th confirmation at level 1 - (1 - c) / 2^(k+1)."""
    from scipy.stats import beta

    for attempt, level in [(None, c)] + [(k, 1 - (1 - c) / 2 ** (k + 1)) for k in range(4)]:
        m = th.confirmations(p, c, attempt)
        assert beta.ppf(level, 1, m) < p
        assert m == 1 or beta.ppf(level, 1, m - 1) >= p * (1 - 1e-12)


def test_default_failure_limit_needs_59_runs_at_the_step_and_72_in_a_first_confirmation():
    """1 - 0.05^(1/59) = 0.0495 < 0.05 <= 1 - 0.05^(1/58) = 0.0503; 0.025^(1/72) and
    0.025^(1/71) likewise around 0.95."""
    assert th.MAX_FAILURE == 0.05 and th.CONFIDENCE == 0.95
    assert th.confirmations(0.05) == 59
    assert 1 - 0.05 ** (1 / 59) < 0.05 <= 1 - 0.05 ** (1 / 58)
    assert th.confirmations(0.05, attempt=0) == 72
    assert 1 - 0.025 ** (1 / 72) < 0.05 <= 1 - 0.025 ** (1 / 71)


class Curve:
    """An engine whose run of seed s at step h fails when ``u_s < q(h)``, ``u_s`` uniform in
    [0, 1) drawn from (draw, s): the failure probability of a run at h is exactly q(h), and a
    seed that fails at h fails at every larger step (as a real run's chance does)."""

    def __init__(self, q, draw):
        self.q = q
        self.u = np.random.default_rng(draw).random(1000)

    def trial_worker(self):
        return nullcontext()

    def trials(self, spec, progress=None, worker=None):
        q = self.q(spec.step)
        return _record(spec, lambda s: self.u[s] < q)


def false_safe_rate(q, draws, runs=RUNS):
    """The fraction of ``draws`` scans whose step has a failure probability above the limit
    (a false SAFE), and the steps given."""
    bad, steps = 0, []
    for d in range(draws):
        found = th.scan(Curve(q, d), runs, 1.0, 1e-3)
        steps.append(found.h_clear)
        bad += found.h_clear > 0 and q(found.h_clear) > runs.max_failure
    return bad / draws, steps


@pytest.mark.slow
def test_a_failure_rate_just_above_the_limit_everywhere_is_passed_rarely():
    """Every step's runs fail with probability 0.055, just above the 0.05 limit: the scan
    tries every confirmation; each passes with probability (0.945)^m, m = 72, 86, 99, 113,
    together at most 3.0% (59 runs in each would give 13%). Over 4000 seeded draws the
    false SAFE rate stays below 5% (its expectation <= 3.0%, standard deviation 0.27%)."""
    expected = sum(0.945 ** th.confirmations(0.05, attempt=k) for k in range(th.LOWERINGS))
    assert expected < 0.031
    rate, _ = false_safe_rate(lambda h: 0.055, 4000)
    assert rate < 0.05


@pytest.mark.slow
@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.floats(0.2, 0.99), st.floats(1e-3, 0.2), st.floats(1e-6, 0.3))
def test_over_failure_curves_the_scan_gives_a_step_above_the_limit_at_most_5_percent(
        mid, width, floor):
    """Failure curves q(h) = floor + (1 - floor) / (1 + exp(-(h - mid) / width)) (a rate
    that rises with the step from a floor): over 300 seeded draws, the steps whose failure
    probability exceeds 0.05 are given at most 5% of the time (binomial: with a true rate of
    5% or less, 30 or more of 300 has probability below 2e-4), and when the floor is below
    the limit near the first failures a step is found."""
    def q(h):
        z = min(max((h - mid) / width, -700.0), 700.0)
        return floor + (1 - floor) / (1 + math.exp(-z))

    rate, steps = false_safe_rate(q, 300)
    assert rate < 30 / 300
    if floor < 1e-3 and width < 0.02:
        assert sum(h > 0 for h in steps) > 250


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

#: Seeds of the runs written here: none of the analysis' (1-373).
OWN_SEEDS = tuple(range(1001, 1011))


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
    confirmed = runs["confirmed_seeds"]
    assert len(confirmed) in runs["confirmation_runs"] and min(confirmed) > max(runs["seeds"])
    assert runs["max_failure"] == th.MAX_FAILURE and runs["duration"] == 10.0
    unsafe = 0.95 * h0
    assert stepsafe.check(scene=scene, h=unsafe).safe
    hot = stepsafe.check(scene=scene, h=unsafe, temperature=300, length="10 ps")
    assert not hot.safe
    safe = 0.999 * warm.h_max
    assert stepsafe.check(scene=scene, h=safe, temperature=300, length="10 ps").safe
    above = stepsafe.check(scene=scene, h=1.01 * warm.h_max, temperature=300, length="10 ps")
    # (UNSAFE because a run at the step itself fails, or, when all 59 pass, because the
    # step lies above the limit advise gives)
    reasons = above.record["thermal"]["reasons"]
    assert not above.safe and len(reasons) == 1, reasons
    assert reasons[0].startswith("the runs in the engine at h: verlet, ") or reasons[0] == (
        "at or above the largest step the runs in the engine pass (the limit at temperature "
        "advise gives)")
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
    1 ps: the check at 2.7 fs exits 1, its JSON fits the schema and states the seeds run at
    the step (fresh ones after the two, 29 planned for ``--max-failure 0.1``: 1 - 0.05^(1/29)
    < 0.1), their length against the run's, the failure limit per run and the drift
    tolerance ``--max-drift`` sets."""
    pytest.importorskip("openmm")
    jsonschema = pytest.importorskip("jsonschema")
    import json

    from stepsafe.api.schemas import output_schema

    scene = cluster_scene(tmp_path, temperature="300 K", length="10 ps", h=2.7,
                          system={"runs": {"temperature": "300 K", "seeds": [11, 12],
                                           "duration": "1 ps"}})
    code, out, err = run("check", scene, "--json", "--max-drift", "0.5", "--max-failure",
                         "0.1")
    assert code == 1, err
    data = json.loads(out)
    jsonschema.validate(data, output_schema("check"))
    entry = data["checks"][0]
    assert "engine_runs" not in entry  # (the 0 K check runs nothing at temperature)
    runs = entry["thermal"]["minima"][0]["engine_runs"]
    assert runs["seeds"] == [11, 12] and runs["check_runs"] == 29
    assert runs["max_failure"] == 0.1 and runs["failure_per"] == "run"
    assert runs["confidence"] == 0.95
    at_step = runs["trials"][0]
    assert at_step["planned_seeds"] == 29 and at_step["stage"] == "at the step"
    assert at_step["seeds"] == list(range(13, 13 + len(at_step["seeds"])))
    assert at_step["verdict"] != "stable" or at_step["upper"] < 0.1
    assert runs["duration"] == 1.0 and runs["run_length"] == 10.0 and not runs["followed"]
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


@given(st.lists(st.integers(1, 400), unique=True))
def test_printed_seed_lists_name_every_seed_run_in_order(seeds):
    """The text output's seed lists (``4-75`` for consecutive runs) expand to the seeds."""
    from stepsafe.cli.thermal import _seeds

    out = []
    for part in _seeds(seeds).split(", ") if seeds else []:
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    assert out == seeds
