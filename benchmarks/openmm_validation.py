"""stepsafe's limits on real MD systems against OpenMM's own integrators: the table of
docs/guides/openmm.md (engine validation), printed, not asserted.

    python benchmarks/openmm_validation.py [--only 0 1 2 3] [--integrators verlet ...]
        [--stages warm scan check] [--seeds 1 2 3] [--duration 5] [--length "5 ps"]
        [--check-seeds 1001 ... 1030] [--json FILE] [--reuse FILE ...]
    python benchmarks/openmm_validation.py --table --reuse FILE ...

Systems (the scenes committed in examples/, built by
``stepsafe.systems.md.openmm_engine.write_example_system`` from files in the OpenMM wheel):

* ``examples/water-box.yaml``: 129 flexible TIP3P waters, PME (387 atoms);
* ``examples/villin.yaml``: the villin headpiece, Amber14, vacuum (582 atoms), without
  constraints, with ``--constraints h-bonds``, and with h-bonds and ``--hydrogen-mass 3``.

For each system: ``stepsafe.advise`` (minimised, as the scene says) gives the 0 K limit h_max of
``verlet`` and of ``langevin-middle`` and the safe intervals below it (a band of unsafe steps
below h_max would show as a gap). Then OpenMM runs its ``VerletIntegrator`` and
``LangevinMiddleIntegrator`` (friction 1/ps, 300 K) at fractions of h_max, ascending, on the
System OpenMM's own ``createSystem`` makes with those constraints and hydrogen masses, from
the minimum stepsafe analysed (:mod:`stepsafe.systems.md.enginerun`): per seed, 1 ps of
LangevinMiddle thermalisation at 300 K (friction 10/ps, step 1 fs or 0.35 h_max if smaller),
then ``--duration`` ps of the integrator under test, CPU platform, one thread, energies every
10 steps. A run *blew up* at a non-finite energy, an OpenMM error, or (Verlet) a total energy
moved by more than n_dof kT / 2, (LangevinMiddle) a kinetic energy past its mean n_dof kT / 2
by that much; Verlet *drifts* when the mean slope of its total energy over the seeds exceeds
0.01 kT per ps per degree of freedom. The scan of a system and integrator stops at the first
step where every seed blew up.

Stages (``--stages``; the 0 K limit is always computed, in seconds):

* ``warm``: stepsafe's own limit at 300 K for a run of ``--length``, ``stepsafe.advise(...,
  temperature=300, length=...)`` (OpenMM's snapshots, the linear limit at temperature, a
  bisection of runs of the same integrator in OpenMM in seeds 1-3, and a confirmation in 72
  or more fresh seeds, each run as long as ``--length``: the failure probability of one run
  below 0.05 at 95% confidence; docs/guides/openmm.md, "At temperature"), minutes per row;
* ``scan``: OpenMM's runs at the fractions :data:`FRACTIONS` of the 0 K limit, as above;
* ``check``: OpenMM's runs at stepsafe's step at 300 K in the scan's protocol (``--duration``
  ps), in ``--check-seeds`` (choose none of stepsafe's own seeds: its confirmations use 4 up
  to 373), needing ``warm`` in this run or in a ``--reuse`` file; with many seeds
  (``--check-seeds $(seq 1001 1030)``) a failure rate, and with ``--check-steps`` at other
  steps (fs) instead.

Each row also says whether stepsafe's step at 300 K is *consistent* with OpenMM: below the
scan's first failing step and run in every seed of the check; anything else is printed as a
``FALSE SAFE``. ``--json`` writes the rows; ``--reuse`` reads earlier files (a later file's
stage replaces an earlier one's), so rows and stages can run apart and ``--table`` prints the
whole table from their files. The machine, the versions, the seeds, and each stage's wall time
with the load average are printed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: (label, scene in examples/, write_example_system kind, constraint rule, hydrogen mass)
SYSTEMS = (
    ("water box, 129 flexible TIP3P, PME (387 atoms)", "water-box.yaml", "water", "none", None),
    ("villin, Amber14, vacuum (582 atoms)", "villin.yaml", "villin", "none", None),
    ("villin, Amber14, vacuum (582 atoms)", "villin.yaml", "villin", "h-bonds", None),
    ("villin, Amber14, vacuum (582 atoms)", "villin.yaml", "villin", "h-bonds", 3.0),
)
INTEGRATORS = ("verlet", "langevin-middle")
#: The steps tried, as fractions of stepsafe's 0 K limit.
FRACTIONS = (0.7, 0.8, 0.9, 0.95, 1.0, 1.05)


def prepared_engine(scene: Path, rule: str, hydrogen_mass: float | None):
    """The engine stepsafe analyses for the scene with these overrides (masses, constraints,
    minimum)."""
    import yaml

    from stepsafe.exceptions import StepsafeError
    from stepsafe.systems.md import system as md

    tree = dict(yaml.safe_load(scene.read_text())["system"])
    tree["constraints"] = rule
    if hydrogen_mass is not None:
        tree["hydrogen_mass"] = hydrogen_mass

    def fail(key, message):
        return StepsafeError(message, key)

    chosen = md.settings(tree, fail)
    engine = md.load_engine(tree["openmm"], tree["positions"], scene.parent, fail)
    return md.prepare(engine, chosen, fail)[0]


def bands(safe_h: list, h_max: float) -> str:
    """The unsafe intervals below h_max that advise reports (gaps between safe intervals)."""
    gaps = [(a[1], b[0]) for a, b in zip(safe_h, safe_h[1:]) if a[1] is not None
            and b[0] < h_max]
    return "none" if not gaps else ", ".join(f"{lo:.3g}-{hi:.3g} fs" for lo, hi in gaps)


def trial(system_xml: str, state: str, integrator: str, step: float, h_max: float,
          seeds: tuple[int, ...], duration: float) -> dict:
    """OpenMM's runs at ``step`` (fs) in the scan's protocol (module docstring), as a record
    (``fraction`` of the 0 K ``h_max``)."""
    from stepsafe.systems.md import enginerun as er

    t1 = time.time()
    record = er.run_trials(system_xml, state, er.TrialSpec(
        integrator, step / 1000.0, duration, temperature=300.0, friction=1.0, seeds=seeds,
        equilibration=1.0, equilibration_step=min(1.0, 0.35 * h_max) / 1000.0,
        equilibration_friction=10.0, sample_every=10))
    drift, se = record.drift()
    return {"fraction": step / h_max, "step_fs": step, "seeds": list(seeds),
            "duration_ps": duration, "verdict": record.verdict(),
            "blowup_steps": [r.blowup_step for r in record.runs],
            "blew_up": [r.blew_up for r in record.runs],
            "reasons": [r.reason for r in record.runs], "drift": drift, "drift_se": se,
            "kinetic_temperature": [r.kinetic_temperature for r in record.runs],
            "seconds": time.time() - t1, "load": os.getloadavg()[0]}


def shown(run: dict) -> str:
    """One line: the step, the verdict, each seed's blow-up step, the drift and T_kin."""
    steps = ", ".join("-" if s is None else str(s) for s in run["blowup_steps"])
    temps = ", ".join("-" if t is None or math.isnan(t) else f"{t:.0f}"
                      for t in run["kinetic_temperature"])
    return (f"{run['step_fs']:.3f} fs ({run['fraction']:.2f} h_max): {run['verdict']}; blow-up "
            f"step per seed {steps}; drift {run['drift']:+.1e} ± {run['drift_se']:.1e} "
            f"kT/ps/dof; T_kin {temps} K ({run['seconds']:.0f} s, load {run['load']:.1f})")


def measured(run: dict, integrator: str) -> str:
    """Verlet's drift with its standard error, or LangevinMiddle's kinetic temperatures."""
    if integrator == "verlet":
        return f"{run['drift']:+.1e} ± {run['drift_se']:.1e} kT/ps/dof"
    temps = [t for t in run["kinetic_temperature"] if t is not None and math.isfinite(t)]
    return ", ".join(f"{t:.0f}" for t in temps) + " K" if len(temps) < 4 else \
        f"{min(temps):.0f}-{max(temps):.0f} K"


def seed_list(seeds: list) -> str:
    """``1-3`` for consecutive seeds, else ``1, 5, 9``."""
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def consistency(row: dict) -> str | None:
    """Whether stepsafe's step at 300 K is one OpenMM runs: ``None`` without that step,
    else ``"consistent"`` (it lies below the scan's first failing step, OpenMM ran it in
    every seed of every check, or the seeds that blew up do not show a failure probability
    per run above the one stepsafe bounds: their 95% Clopper-Pearson lower bound is below
    it) or what contradicts it, starting ``FALSE SAFE``."""
    warm = row.get("warm")
    if warm is None:
        return None
    h = warm["h_max_fs"]
    failed = [r for r in row.get("runs", []) if r["verdict"] != "stable"]
    problems = []
    if failed and h >= failed[0]["step_fs"]:
        problems.append(f"at or above the scan's first failing step {failed[0]['step_fs']:.3f} "
                        "fs")
    limit = failure_limit(warm)
    within = []
    for check in row.get("checks", []):
        k, n = sum(check["blew_up"]), len(check["seeds"])
        lower, upper = rate_interval(k, n)
        what = (f"OpenMM at that step, seeds {seed_list(check['seeds'])}: {check['verdict']} "
                f"({k} of {n} blew up; failure probability per run {lower:.2g} to "
                f"{upper:.2g}, one-sided 95% bounds)")
        if check["verdict"] == "drifts" or (k and lower > limit):
            problems.append(what)
        elif k:
            within.append(what)
    if problems:
        return "FALSE SAFE: " + "; ".join(problems)
    if within:
        return (f"consistent with a failure probability per run below {limit:g}: "
                + "; ".join(within))
    return "consistent" if row.get("checks") else "consistent with the scan (no check run)"


def failure_limit(warm: dict) -> float:
    """The failure probability per run stepsafe's 300 K limit bounds (its record's
    ``max_failure``)."""
    minima = warm.get("thermal", {}).get("minima") or [{}]
    return float(minima[0].get("engine_runs", {}).get("max_failure", 0.0))


def rate_interval(k: int, n: int) -> tuple[float, float]:
    """The failure probability per run k failures in n show: from the one-sided 95%
    Clopper-Pearson lower bound to the upper one."""
    from scipy.stats import beta

    lower = 0.0 if k == 0 else float(beta.ppf(0.05, k, n - k + 1))
    upper = 1.0 if k == n else float(beta.ppf(0.95, k + 1, n - k))
    return lower, upper


def checked(check: dict, integrator: str) -> str:
    """A check's cell: how many seeds ran, those that blew up and when, the drift or
    T_kin of the others."""
    seeds, steps = check["seeds"], check["blowup_steps"]
    blew = [(s, b) for s, b, up in zip(seeds, steps, check["blew_up"]) if up]
    head = f"seeds {seed_list(seeds)}, {check['duration_ps']:g} ps: "
    lower, upper = rate_interval(len(blew), len(seeds))
    if not blew:
        return head + f"{len(seeds)} of {len(seeds)} ran, " + measured(check, integrator) + \
            f"; failure probability per run < {upper:.2g} (95%)"
    plural = "s" if len(blew) > 1 else ""
    return head + (f"{len(blew)} of {len(seeds)} blew up (seed{plural} "
                   f"{', '.join(str(s) for s, _ in blew)} at step{plural} "
                   f"{', '.join(str(b) for _, b in blew)}); failure probability per run "
                   f"{lower:.2g} to {upper:.2g}, one-sided 95% bounds")


def table(rows: list, temperature: float, length: str) -> str:
    """The guide's table, one line per row (system and integrator) of ``rows``."""
    head = ("| system | integrator | constraints, H mass | stepsafe h_max (0 K) | unsafe bands "
            f"below it | stepsafe h_max at {temperature:g} K (a run of {length}) | OpenMM "
            f"at 300 K: largest step run | drift there (Verlet) or T_kin (LangevinMiddle) | "
            "first step that failed: blow-up step per seed | OpenMM at stepsafe's 300 K step |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for row in rows:
        ok = [r for r in row["runs"] if r["verdict"] == "stable"]
        bad = [r for r in row["runs"] if r["verdict"] != "stable"]
        if not row["runs"]:
            ran = there = failed = "not run"
        else:
            ran, there = "none", ""
            if ok:
                ran = f"{ok[-1]['step_fs']:.2f} fs ({ok[-1]['fraction']:.2f} h_max)"
                there = measured(ok[-1], row["integrator"])
            if not bad:
                failed = f"none up to {row['runs'][-1]['fraction']:.2f} h_max"
            else:
                first = bad[0]
                what = first["verdict"] if first["verdict"] != "drifts" else \
                    f"drifts {first['drift']:+.1e} kT/ps/dof"
                steps = ", ".join("-" if s is None else str(s) for s in first["blowup_steps"])
                failed = f"{first['step_fs']:.2f} fs ({first['fraction']:.2f} h_max): {what}" + \
                    (f"; {steps}" if first["verdict"] == "blew up" else "")
        warm = row.get("warm")
        hot = "not computed" if warm is None else \
            f"{warm['h_max_fs']:.3f} fs ({warm['h_max_fs'] / row['h_max_fs']:.2f} h_max)"
        at = "; ".join(checked(c, row["integrator"]) for c in row.get("checks", [])) or \
            ("-" if warm is None else "not run")
        name = "Verlet" if row["integrator"] == "verlet" else "LangevinMiddle"
        lines.append(f"| {row['system']} | {name} | {row['constraints']} | "
                     f"{row['h_max_fs']:.3f} fs | {row['bands']} | {hot} | {ran} | {there} | "
                     f"{failed} | {at} |")
    return "\n".join(lines)


def merged(files: list[Path]) -> list[dict]:
    """The rows of earlier runs' ``--json`` files, in the order of SYSTEMS and INTEGRATORS;
    a later file's 300 K limit or scan replaces an earlier one's, and its check one in the
    same seeds; checks at another step than the row's 300 K limit are left out."""
    rows: dict[tuple[int, str], dict] = {}
    for path in files:
        for row in json.loads(path.read_text()):
            if "index" not in row:  # files written before rows carried their index
                row["index"] = next(k for k, (label, _, _, rule, mass) in enumerate(SYSTEMS)
                                    if label == row["system"] and row["constraints"] ==
                                    rule + (f", H {mass:g} amu" if mass else ""))
            key = (row["index"], row["integrator"])
            if row.get("check") is not None:  # files written before rows had checks
                row["checks"] = [row["check"]]
            old = rows.setdefault(key, {**row, "runs": [], "checks": [], "warm": None})
            if row.get("warm") is not None:
                old["warm"] = row["warm"]
            if row.get("runs"):
                old["runs"] = row["runs"]
            for check in row.get("checks") or []:
                old["checks"] = [c for c in old["checks"] if c["seeds"] != check["seeds"]] + \
                    [check]
    for row in rows.values():  # a check at another step than the row's 300 K limit is dropped
        warm = row.get("warm")
        row["checks"] = [c for c in row["checks"] if warm is not None and
                         abs(c["step_fs"] - warm["h_max_fs"]) <= 1e-9 * warm["h_max_fs"]]
    return [rows[key] for key in sorted(rows, key=lambda k: (k[0], INTEGRATORS.index(k[1])))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3],
                        help="seeds of the scan")
    parser.add_argument("--duration", type=float, default=5.0, help="ps per run")
    parser.add_argument("--only", type=int, nargs="*", help="rows of SYSTEMS to run (0-3)")
    parser.add_argument("--integrators", nargs="+", default=list(INTEGRATORS),
                        choices=INTEGRATORS)
    parser.add_argument("--stages", nargs="+", default=["warm", "scan", "check"],
                        choices=["warm", "scan", "check"],
                        help="what to run besides the 0 K limit: stepsafe's limit at 300 K, "
                        "the scan of fractions of the 0 K limit, OpenMM at the 300 K limit")
    parser.add_argument("--length", default="5 ps", help="the run's length at 300 K")
    parser.add_argument("--check-seeds", type=int, nargs="+", default=list(range(1001, 1031)),
                        help="seeds of OpenMM's runs at stepsafe's step at 300 K (none of "
                        "stepsafe's own, 1-373)")
    parser.add_argument("--check-steps", type=float, nargs="+",
                        help="with the check stage: run OpenMM at these steps (fs) instead "
                        "of stepsafe's step at 300 K (a failure rate below it)")
    parser.add_argument("--reuse", type=Path, nargs="*", default=[],
                        help="earlier --json files: their 300 K limits serve the check stage "
                        "and their rows fill the table")
    parser.add_argument("--table", action="store_true",
                        help="run nothing: print the table of the --reuse files")
    parser.add_argument("--json", type=Path, help="also write every row to this file")
    args = parser.parse_args()
    temperature = 300.0
    earlier = merged(args.reuse)
    if args.table:
        print(table(earlier, temperature, args.length))
        for row in earlier:
            print(f"{row['system']}; {row['constraints']}; {row['integrator']}: "
                  f"{consistency(row)}")
        return
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    import numpy
    import openmm

    import stepsafe
    from stepsafe.systems.md import openmm_engine as oe

    seeds = tuple(args.seeds)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores (shared), load average "
          f"{os.getloadavg()[0]:.1f}; Python {platform.python_version()}, numpy "
          f"{numpy.__version__}, OpenMM {openmm.__version__} (CPU platform, 1 thread); seeds "
          f"{', '.join(map(str, seeds))}; {args.duration:g} ps per run at 300 K", flush=True)
    started = time.time()
    rows: list[dict] = []
    tmp = Path(tempfile.mkdtemp(prefix="stepsafe-validation-"))
    for index, (label, name, kind, rule, mass) in enumerate(SYSTEMS):
        if args.only and index not in args.only:
            continue
        scene = ROOT / "examples" / name
        extra = {} if rule == "none" else {"constraints": rule}
        if mass is not None:
            extra["hydrogen_mass"] = mass
        engine = prepared_engine(scene, rule, mass)
        state = engine.state_xml()
        xml, _ = oe.write_example_system(kind, tmp, constraints=rule, hydrogen_mass=mass)
        system_xml = xml.read_text()
        cons = rule + (f", H {mass:g} amu" if mass else "")
        for integrator in args.integrators:
            t0 = time.time()
            report = stepsafe.advise(integrator, scene=str(scene), **extra)
            h_max = float(report.h_max)
            band = bands(report.record["safe_h"], h_max)
            print(f"\n{label}; {cons}; {integrator}: stepsafe h_max {h_max:.4f} fs "
                  f"({time.time() - t0:.0f} s)", flush=True)
            row = {"index": index, "system": label, "constraints": cons,
                   "integrator": integrator, "h_max_fs": h_max, "bands": band, "warm": None,
                   "runs": [], "checks": []}
            before = next((r for r in earlier if (r["index"], r["integrator"]) ==
                           (index, integrator)), None)
            if "warm" in args.stages:
                t2, load = time.time(), os.getloadavg()[0]
                hot = stepsafe.advise(integrator, scene=str(scene), **extra,
                                      temperature=temperature, length=args.length)
                thermal = hot.record["thermal"]
                row["warm"] = {"h_max_fs": float(hot.h_max),
                               "limited_by": thermal.get("limited_by"),
                               "length": args.length, "seconds": time.time() - t2,
                               "load": [load, os.getloadavg()[0]], "thermal": thermal}
                print(f"  at {temperature:g} K ({args.length}): stepsafe h_max "
                      f"{row['warm']['h_max_fs']:.4f} fs, limited by "
                      f"{row['warm']['limited_by']} ({row['warm']['seconds']:.0f} s, load "
                      f"{load:.1f} to {os.getloadavg()[0]:.1f})", flush=True)
            elif before is not None:
                row["warm"] = before.get("warm")
            for fraction in FRACTIONS if "scan" in args.stages else ():
                run = trial(system_xml, state, integrator, fraction * h_max, h_max, seeds,
                            args.duration)
                row["runs"].append(run)
                print("  " + shown(run), flush=True)
                if all(run["blew_up"]):
                    break
            if "check" in args.stages and args.check_steps:
                row["checks_at"] = []
                for step in args.check_steps:
                    run = trial(system_xml, state, integrator, step, h_max,
                                tuple(args.check_seeds), args.duration)
                    row["checks_at"].append(run)
                    print(f"  seeds {seed_list(args.check_seeds)}: " + shown(run) +
                          f"; {sum(run['blew_up'])} blew up", flush=True)
            elif "check" in args.stages and row["warm"] is not None:
                run = trial(system_xml, state, integrator, row["warm"]["h_max_fs"], h_max,
                            tuple(args.check_seeds), args.duration)
                row["checks"].append(run)
                print("  at stepsafe's 300 K step, seeds "
                      f"{seed_list(args.check_seeds)}: " + shown(run) +
                      f"; {sum(run['blew_up'])} blew up", flush=True)
            rows.append(row)
            if args.json:
                args.json.write_text(json.dumps(rows, indent=1, default=str))
    print(f"\n(all runs: {time.time() - started:.0f} s)\n")
    print(table(merged(args.reuse + [args.json]) if args.json else rows, temperature,
                args.length))
    for row in rows:
        print(f"{row['system']}; {row['constraints']}; {row['integrator']}: "
              f"{consistency(row)}")


if __name__ == "__main__":
    main()
