"""Trial runs of the engine's own integrators: the check of a step-size verdict against the
engine.

Protocol (per seed, in an engine process of its own, :class:`TrialWorker`, because OpenMM's
Reference platform can crash the process when a run blows up; a crash counts as a blow-up and
the process is started again for the next seed):

1. Thermalisation: velocities drawn at temperature T (``setVelocitiesToTemperature`` with the
   seed), then ``equilibration`` ps of ``LangevinMiddleIntegrator(T, equilibration_friction,
   equilibration_step)`` (random stream from the seed; a strong friction brings the potential
   energy of a minimised structure to temperature within a ps).
2. Production from that state: ``integrator = "verlet"`` runs ``VerletIntegrator(step)``
   (NVE: leapfrog with SHAKE-type position constraints), ``"langevin-middle"`` runs
   ``LangevinMiddleIntegrator(T, friction, step)``; ``duration`` ps, sampled every
   ``sample_every`` steps: potential energy U and kinetic energy (for Verlet OpenMM reports the
   on-step estimate from the two half-step velocities, for LangevinMiddle that of the half-step
   velocities).
3. Blow-up: a non-finite energy, an OpenMM exception (the CPU platform refuses NaN
   coordinates), a crash of the process, or, for Verlet, a change of the total energy since
   the first sample by more than ``energy_bound`` n_dof kT (default 1/2: the system's whole
   equilibrium kinetic energy); for LangevinMiddle, whose total energy wanders with the heat
   the thermostat exchanges (and its potential energy with the structure: a small cluster
   restructures), the kinetic energy exceeding its mean n_dof kT / 2 by that much (an
   unstable mode heats the system; for 72 degrees of freedom that is 6 standard deviations
   of the kinetic energy at equilibrium). The step of the first such sample is recorded.
4. Drift (Verlet): the least-squares slope of E = U + K against time, in kJ/mol/ps, per degree
   of freedom (n_dof = 3 x moving particles - constraints - 3 with a centre-of-mass motion
   remover, which also edits velocities every step and should be left out of NVE checks).
   Across seeds: the mean and its standard error (standard deviation over seeds / sqrt(seeds)).
   A run *drifts* when the mean exceeds ``tolerance`` kT per ps per degree of freedom
   (:data:`DRIFT_TOLERANCE`: a total energy rising by 1% of kT per dof per ps heats the system by
   about 1% per ps).

The seeds are stated in the record; runs are reproducible on the CPU platform with one thread.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.systems.md.engine import MOLAR_GAS_CONSTANT

INTEGRATORS = ("verlet", "langevin-middle")
#: kT per ps per degree of freedom beyond which a run counts as drifting.
DRIFT_TOLERANCE = 0.01


@dataclass(frozen=True)
class TrialSpec:
    """What to run (units: ps, K, 1/ps).

    Attributes
    ----------
    integrator : {"verlet", "langevin-middle"}
    step : float
        The step under test, ps.
    duration : float
        Production length, ps.
    temperature : float
        K.
    friction : float
        Langevin friction gamma of the run for ``langevin-middle``, 1/ps.
    seeds : tuple of int
        One run per seed.
    equilibration : float
        Thermalisation length, ps.
    equilibration_step : float
        Its step, ps (choose it well inside the stable range).
    equilibration_friction : float
        Its friction, 1/ps.
    sample_every : int
        Steps between energy samples.
    energy_bound : float
        Blow-up when the total energy moves by more than this many n_dof kT (Verlet), or the
        kinetic energy exceeds n_dof kT / 2 by that much (LangevinMiddle).
    platform : {"CPU", "Reference"}
    threads : int
        CPU threads per run.
    constraint_tolerance : float or None
        Integrator constraint tolerance (OpenMM's default 1e-5 when None).
    timeout : float
        Seconds a seed's process may take before it is stopped (an error, not a verdict).
    stop_at_blowup : bool
        Run no further seed after one blows up (the record holds the seeds run).
    """

    integrator: str
    step: float
    duration: float
    temperature: float = 300.0
    friction: float = 1.0
    seeds: tuple[int, ...] = (1, 2, 3)
    equilibration: float = 1.0
    equilibration_step: float = 0.0005
    equilibration_friction: float = 10.0
    sample_every: int = 10
    energy_bound: float = 0.5
    platform: str = "CPU"
    threads: int = 1
    constraint_tolerance: float | None = None
    timeout: float = 1800.0
    stop_at_blowup: bool = False

    def __post_init__(self) -> None:
        if self.integrator not in INTEGRATORS:
            raise StepsafeError(f"unknown integrator {self.integrator!r}; choose one of "
                                f"{', '.join(INTEGRATORS)}")
        for name in ("step", "duration", "temperature", "friction", "equilibration",
                     "equilibration_step", "equilibration_friction", "energy_bound", "timeout"):
            positive_finite(getattr(self, name), name)
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise StepsafeError("seeds must be distinct, at least one")
        if int(self.sample_every) < 1:
            raise StepsafeError("sample_every must be at least 1")

    @property
    def steps(self) -> int:
        """Production steps (a multiple of ``sample_every``)."""
        n = max(1, round(self.duration / self.step / self.sample_every))
        return n * self.sample_every


@dataclass(frozen=True)
class SamplingSpec:
    """Configurations at temperature from the engine's own Langevin dynamics (units: ps, K,
    1/ps): per seed, velocities drawn at ``temperature``, ``thermalisation`` steps of
    ``LangevinMiddle`` (friction ``friction``, step ``step``), then ``frames`` frames
    ``spacing`` steps apart. Chains of different seeds are independent.

    Attributes
    ----------
    temperature : float
    step : float
    friction : float
    thermalisation : int
        Steps before the first frame.
    spacing : int
        Steps between frames.
    frames : int
        Frames per seed.
    seeds : tuple of int
    """

    temperature: float
    step: float
    friction: float
    thermalisation: int
    spacing: int
    frames: int
    seeds: tuple[int, ...]

    def __post_init__(self) -> None:
        for name in ("temperature", "step", "friction"):
            positive_finite(getattr(self, name), name)
        if min(self.thermalisation, self.spacing, self.frames) < 1:
            raise StepsafeError("thermalisation, spacing and frames must be at least 1")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise StepsafeError("seeds must be distinct, at least one")


@dataclass(frozen=True)
class SeedRun:
    """One seed's run.

    Attributes
    ----------
    seed : int
    blew_up : bool
    blowup_step : int or None
        Production step at the end of the sampling window (``sample_every`` steps) in which
        the blow-up showed.
    reason : str
        What showed it.
    steps : int
        Production steps completed.
    drift : float
        Least-squares slope of U + K in kJ/mol/ps (Verlet only: nan for a blow-up, for fewer
        than 3 samples and for LangevinMiddle, whose energy is exchanged with the bath).
    drift_error : float
        The slope's standard error from the fit (residuals taken as independent: a lower
        bound for correlated fluctuations).
    energy_rms : float
        RMS of U + K about the fitted line, kJ/mol.
    kinetic_temperature : float
        2 <K> / (n_dof R), K (nan for a blow-up).
    """

    seed: int
    blew_up: bool
    blowup_step: int | None
    reason: str
    steps: int
    drift: float
    drift_error: float
    energy_rms: float
    kinetic_temperature: float


@dataclass(frozen=True)
class TrialRecord:
    """All seeds of one trial.

    Attributes
    ----------
    spec : TrialSpec
    n_dof : int
    runs : tuple of SeedRun
    """

    spec: TrialSpec
    n_dof: int
    runs: tuple[SeedRun, ...] = field(default_factory=tuple)

    @property
    def blew_up(self) -> bool:
        return any(r.blew_up for r in self.runs)

    @property
    def first_blowup_step(self) -> int | None:
        steps = [r.blowup_step for r in self.runs if r.blowup_step is not None]
        return min(steps) if steps else None

    @property
    def kT(self) -> float:
        """kT in kJ/mol."""
        return MOLAR_GAS_CONSTANT * self.spec.temperature

    def drift(self) -> tuple[float, float]:
        """Mean drift over the seeds that did not blow up and its standard error, in kT per ps
        per degree of freedom (nan when no seed finished; error nan with one seed)."""
        d = np.array([r.drift for r in self.runs if not r.blew_up and math.isfinite(r.drift)])
        if len(d) == 0:
            return float("nan"), float("nan")
        d = d / (self.n_dof * self.kT)
        se = float(np.std(d, ddof=1) / math.sqrt(len(d))) if len(d) > 1 else float("nan")
        return float(np.mean(d)), se

    def verdict(self, tolerance: float = DRIFT_TOLERANCE) -> str:
        """``"blew up"``, ``"drifts"`` (Verlet: mean drift above ``tolerance`` kT/ps/dof) or
        ``"stable"``."""
        if self.blew_up:
            return "blew up"
        mean, _ = self.drift()
        if self.spec.integrator == "verlet" and math.isfinite(mean) and abs(mean) > tolerance:
            return "drifts"
        return "stable"


def _fit(times: list[float], energy: list[float]) -> tuple[float, float, float]:
    t = np.asarray(times, dtype=float)
    e = np.asarray(energy, dtype=float)
    if len(t) < 3:
        return float("nan"), float("nan"), float("nan")
    a = np.vstack([t - t.mean(), np.ones_like(t)]).T
    coef, *_ = np.linalg.lstsq(a, e, rcond=None)
    res = e - a @ coef
    s2 = float(res @ res) / (len(t) - 2)
    se = math.sqrt(s2 / float(((t - t.mean()) ** 2).sum()))
    return float(coef[0]), se, math.sqrt(float(res @ res) / len(t))


def _seed_run(out: dict, n_dof: int, integrator: str) -> SeedRun:
    e = [u + k for u, k in zip(out["potential"], out["kinetic"])]
    conserved = integrator == "verlet" and not out["blew_up"]
    drift, err, rms = _fit(out["times"], e) if conserved else (float("nan"),) * 3
    kin = float(np.mean(out["kinetic"])) if out["kinetic"] and not out["blew_up"] \
        else float("nan")
    return SeedRun(int(out["seed"]), bool(out["blew_up"]), out["blowup_step"],
                   str(out["reason"]), int(out.get("steps_done", 0)), drift, err, rms,
                   2.0 * kin / (n_dof * MOLAR_GAS_CONSTANT) if n_dof > 0 else float("nan"))


def degrees_of_freedom(system_xml: str) -> int:
    """n_dof of a serialized OpenMM System: 3 per particle of positive mass, minus one per
    constraint, minus 3 with a ``CMMotionRemover`` (read from the XML, without OpenMM)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(system_xml)
    except ET.ParseError as exc:
        raise StepsafeError(f"the System XML does not parse: {exc}") from None
    masses = [float(p.get("mass", "0")) for p in root.iter("Particle")]
    constraints = sum(1 for _ in root.iter("Constraint"))
    cm = any(f.get("type") == "CMMotionRemover" for f in root.iter("Force"))
    return 3 * sum(1 for m in masses if m > 0) - constraints - (3 if cm else 0)


class TrialWorker:
    """One engine process that runs trial seeds one after the other (JSON lines on its
    standard input and output: a job per line, a result per line), started again when a run
    crashes it; one process serves every seed and step of a scan, so the engine's start-up
    is paid once. Use as a context manager (the process ends on exit)."""

    def __init__(self, timeout: float = 1800.0, command: list[str] | None = None) -> None:
        self.timeout = timeout
        #: The process to start (the engine's worker by default).
        self.command = command or [sys.executable, "-m", "stepsafe.systems.md.openmm_engine",
                                   "--serve"]
        self._process: subprocess.Popen[str] | None = None
        # (a file, not a pipe: a pipe nobody reads stops a process that writes much to it)
        self._stderr: Any = None

    def __enter__(self) -> TrialWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """End the process (if running)."""
        proc, self._process = self._process, None
        if proc is not None and proc.poll() is None:
            try:
                assert proc.stdin is not None
                proc.stdin.close()
                proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                proc.kill()
                proc.wait()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def _start(self) -> subprocess.Popen[str]:
        if self._process is None or self._process.poll() is not None:
            if self._stderr is not None:
                self._stderr.close()
            self._stderr = tempfile.TemporaryFile(mode="w+")
            self._process = subprocess.Popen(
                self.command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                stderr=self._stderr, text=True, bufsize=1)
        return self._process

    def _ended(self, proc: subprocess.Popen[str], job: dict) -> dict:
        """The process ended during ``job``: a crash (a signal) is the job's result, a
        timeout or an exit a :class:`StepsafeError` or a bug."""
        code = proc.wait()
        self._process = None
        if code == -9:
            raise StepsafeError(f"the trial run of seed {job['seed']} took longer than "
                                f"{self.timeout:g} s")
        if code < 0:
            return {"crashed": -code}
        err = ""
        if self._stderr is not None:
            self._stderr.seek(0)
            err = self._stderr.read()
        raise RuntimeError(f"trial run failed (exit {code}): {err.strip()[-400:]}")

    def run(self, job: dict) -> dict:
        """The result of one seed's job; ``{"crashed": signal}`` when the run killed the
        process (which is started again for the next job)."""
        proc = self._start()
        assert proc.stdin is not None and proc.stdout is not None
        try:
            proc.stdin.write(json.dumps(job) + "\n")
            proc.stdin.flush()
        except OSError:  # the process had ended
            return self._ended(proc, job)
        timer = threading.Timer(self.timeout, proc.kill)
        timer.start()
        try:
            line = proc.stdout.readline()
        finally:
            timer.cancel()
        if not line:
            return self._ended(proc, job)
        return json.loads(line)


def run_trials(system_xml: str, state_xml: str, spec: TrialSpec, *,
               progress: Callable[[str, int, int | None], None] | None = None,
               worker: TrialWorker | None = None) -> TrialRecord:
    """Run ``spec`` on a serialized OpenMM System and State (positions), the seeds one after
    the other in an engine process (:class:`TrialWorker`; a run that crashes the process
    counts as blown up and the process is started again).

    Parameters
    ----------
    system_xml : str
        ``XmlSerializer.serialize(system)``
        (:meth:`~stepsafe.systems.md.openmm_engine.OpenMMEngine.system_xml`).
    state_xml : str
        A serialized State with positions (and box)
        (:meth:`~stepsafe.systems.md.openmm_engine.OpenMMEngine.state_xml`).
    spec : TrialSpec
    progress : callable, optional
        ``progress("trials", seeds_done, seeds)``.
    worker : TrialWorker, optional
        The engine process to use (one for this call when omitted).

    Returns
    -------
    TrialRecord
    """
    if worker is None:
        with TrialWorker(spec.timeout) as own:
            return run_trials(system_xml, state_xml, spec, progress=progress, worker=own)
    runs = []
    n_dof = degrees_of_freedom(system_xml)
    with tempfile.TemporaryDirectory(prefix="stepsafe-trial-") as tmp:
        sys_path, pos_path = Path(tmp) / "system.xml", Path(tmp) / "state.xml"
        sys_path.write_text(system_xml)
        pos_path.write_text(state_xml)
        base = {k: v for k, v in asdict(spec).items()
                if k not in ("seeds", "timeout", "stop_at_blowup")}
        base.update(system=str(sys_path), positions=str(pos_path), steps=spec.steps,
                    equilibration_steps=max(1, round(spec.equilibration / spec.equilibration_step)))
        for done, seed in enumerate(spec.seeds):
            out = worker.run({**base, "seed": int(seed)})
            if "crashed" in out:
                runs.append(SeedRun(int(seed), True, None,
                                    f"engine process crashed (signal {out['crashed']})", 0,
                                    *(float("nan"),) * 4))
                if spec.stop_at_blowup:
                    break
                continue
            if "error" in out:
                raise StepsafeError(out["error"])
            if not out["equilibrated"]:
                raise StepsafeError(f"seed {seed}: {out['reason']} at the equilibration step "
                                    f"{spec.equilibration_step:g} ps; choose a smaller one")
            if int(out["n_dof"]) != n_dof:
                raise RuntimeError(f"degrees of freedom: {out['n_dof']} from OpenMM, {n_dof} "
                                   f"from the XML")
            runs.append(_seed_run(out, n_dof, spec.integrator))
            if progress is not None:
                progress("trials", done + 1, len(spec.seeds))
            if spec.stop_at_blowup and runs[-1].blew_up:
                break
    return TrialRecord(spec, n_dof, tuple(runs))
