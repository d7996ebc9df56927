"""stepsafe's limits on real MD systems against OpenMM's own integrators: the table of
docs/guides/openmm.md (engine validation), printed, not asserted.

    python benchmarks/openmm_validation.py [--seeds 1 2 3] [--duration 5] [--json FILE]

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

The machine, the versions and the seeds are printed with the table.
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--duration", type=float, default=5.0, help="ps per run")
    parser.add_argument("--only", type=int, nargs="*", help="rows of SYSTEMS to run (0-3)")
    parser.add_argument("--integrators", nargs="+", default=list(INTEGRATORS),
                        choices=INTEGRATORS)
    parser.add_argument("--temperature", type=float,
                        help="also stepsafe's h_max at this temperature (K), with --length")
    parser.add_argument("--length", default="5 ps", help="the run's length at temperature")
    parser.add_argument("--no-scan", action="store_true",
                        help="stepsafe's limits only, no OpenMM scan")
    parser.add_argument("--json", type=Path, help="also write every run to this file")
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    import numpy
    import openmm

    import stepsafe
    from stepsafe.systems.md import enginerun as er
    from stepsafe.systems.md import openmm_engine as oe

    seeds = tuple(args.seeds)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores (shared), load average "
          f"{os.getloadavg()[0]:.1f}; Python {platform.python_version()}, numpy "
          f"{numpy.__version__}, OpenMM {openmm.__version__} (CPU platform, 1 thread); seeds "
          f"{', '.join(map(str, seeds))}; {args.duration:g} ps per run at 300 K", flush=True)
    started = time.time()
    rows, log = [], []
    tmp = Path(tempfile.mkdtemp(prefix="stepsafe-validation-"))
    for index, (label, name, kind, rule, mass) in enumerate(SYSTEMS):
        if args.only and index not in args.only:
            continue
        scene = ROOT / "examples" / name
        extra = {} if rule == "none" else {"constraints": rule}
        if mass is not None:
            extra["hydrogen_mass"] = mass
        t0 = time.time()
        engine = prepared_engine(scene, rule, mass)
        state = engine.state_xml()
        xml, _ = oe.write_example_system(kind, tmp, constraints=rule, hydrogen_mass=mass)
        system_xml = xml.read_text()
        cons = rule + (f", H {mass:g} amu" if mass else "")
        for integrator in args.integrators:
            report = stepsafe.advise(integrator, scene=str(scene), **extra)
            h_max = float(report.h_max)
            band = bands(report.record["safe_h"], h_max)
            print(f"\n{label}; {cons}; {integrator}: stepsafe h_max {h_max:.4f} fs "
                  f"({time.time() - t0:.0f} s)", flush=True)
            warm = None
            if args.temperature is not None:
                t2 = time.time()
                hot = stepsafe.advise(integrator, scene=str(scene), **extra,
                                      temperature=args.temperature, length=args.length)
                warm = {"h_max_fs": float(hot.h_max),
                        "limited_by": hot.record.get("h_max_limited_by"),
                        "seconds": time.time() - t2}
                print(f"  at {args.temperature:g} K ({args.length}): stepsafe h_max "
                      f"{warm['h_max_fs']:.4f} fs, limited by {warm['limited_by']} "
                      f"({warm['seconds']:.0f} s)", flush=True)
            runs = []
            for fraction in () if args.no_scan else FRACTIONS:
                step = fraction * h_max
                t1 = time.time()
                record = er.run_trials(system_xml, state, er.TrialSpec(
                    integrator, step / 1000.0, args.duration, temperature=300.0, friction=1.0,
                    seeds=seeds, equilibration=1.0,
                    equilibration_step=min(1.0, 0.35 * h_max) / 1000.0,
                    equilibration_friction=10.0, sample_every=10))
                drift, se = record.drift()
                run = {"fraction": fraction, "step_fs": step, "verdict": record.verdict(),
                       "blowup_steps": [r.blowup_step for r in record.runs],
                       "reasons": [r.reason for r in record.runs],
                       "drift": drift, "drift_se": se,
                       "kinetic_temperature": [r.kinetic_temperature for r in record.runs],
                       "seconds": time.time() - t1}
                runs.append(run)
                shown = ", ".join("-" if s is None else str(s) for s in run["blowup_steps"])
                temps = ", ".join("-" if math.isnan(t) else f"{t:.0f}"
                                  for t in run["kinetic_temperature"])
                print(f"  {step:.3f} fs ({fraction:.2f} h_max): {run['verdict']}; blow-up "
                      f"step per seed {shown}; drift {drift:+.1e} ± {se:.1e} kT/ps/dof; "
                      f"T_kin {temps} K ({run['seconds']:.0f} s)", flush=True)
                if all(r.blew_up for r in record.runs):
                    break
            rows.append({"system": label, "constraints": cons, "integrator": integrator,
                         "h_max_fs": h_max, "bands": band, "warm": warm, "runs": runs})
            if args.json:
                args.json.write_text(json.dumps(log + rows[-1:], indent=1, default=str))
            log.append(rows[-1])
    print(f"\n(all runs: {time.time() - started:.0f} s)\n")
    hot = "" if args.temperature is None else f" stepsafe h_max at {args.temperature:g} K |"
    print("| system | integrator | constraints, H mass | stepsafe h_max (0 K) |" + hot +
          " unsafe bands below it | OpenMM at 300 K: largest step run | drift there (Verlet) "
          "or T_kin (LangevinMiddle) | first step that failed: blow-up step per seed |")
    print("|---|---|---|---|---|---|---|---|" + ("" if not hot else "---|"))
    for row in rows:
        ok = [r for r in row["runs"] if r["verdict"] == "stable"]
        bad = [r for r in row["runs"] if r["verdict"] != "stable"]
        good = ok[-1] if ok else None
        first = bad[0] if bad else None
        if good is None:
            ran, measured = "none", ""
        else:
            ran = f"{good['step_fs']:.2f} fs ({good['fraction']:.2f} h_max)"
            if row["integrator"] == "verlet":
                measured = f"{good['drift']:+.1e} ± {good['drift_se']:.1e} kT/ps/dof"
            else:
                measured = ", ".join(f"{t:.0f}" for t in good["kinetic_temperature"]) + " K"
        if not row["runs"]:
            ran = measured = failed = "not run"
        elif first is None:
            failed = "none up to " + f"{row['runs'][-1]['fraction']:.2f} h_max"
        else:
            steps = ", ".join("-" if s is None else str(s) for s in first["blowup_steps"])
            what = first["verdict"] if first["verdict"] != "drifts" else \
                f"drifts {first['drift']:+.1e} kT/ps/dof"
            failed = f"{first['step_fs']:.2f} fs ({first['fraction']:.2f} h_max): {what}" + \
                (f"; {steps}" if first["verdict"] == "blew up" else "")
        name = "Verlet" if row["integrator"] == "verlet" else "LangevinMiddle"
        warm = "" if row["warm"] is None else f" {row['warm']['h_max_fs']:.3f} fs |"
        print(f"| {row['system']} | {name} | {row['constraints']} | {row['h_max_fs']:.3f} fs |"
              f"{warm} {row['bands']} | {ran} | {measured} | {failed} |")
    if args.json:
        args.json.write_text(json.dumps(log, indent=1, default=str))


if __name__ == "__main__":
    main()
