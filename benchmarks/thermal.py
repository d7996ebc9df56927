"""The cost of the thermal analysis (issue: "a 1-dof scene in a few seconds, a 100-dof scene
in under a minute"), printed, not asserted.

    python benchmarks/thermal.py [--threads N] [--repeat N] [--steps N] [--follow N]
                                 [--only LABEL] [--keep-freed]

Each case is run ``--repeat`` times (default 3): printed are the medians of the wall clock
and of the process's CPU time (on a machine shared with other work the CPU time is the
figure to compare; the load average before and after is printed), the stages of the last
``advise`` run (wall clock and CPU time), and a summary of the median CPU times:

1. a Morse bond ``U = (1 - e^-q)^2 / 2`` (1 dof) at kT = 0.003 (``examples/morse.yaml``)
   with velocity Verlet, a run of 1e4 steps: ``thermal_limit`` (what ``advise`` runs:
   exact 1-D draws, frequencies, the band scan, the confirmation on 2995 fresh
   trajectories, the drift) and ``thermal_check`` at h = 0.8 (2995 trajectories, every
   step);
2. an FPU-alpha chain of 100 unit masses (alpha = 0.25) at kT = 0.05, the same run:
   ``thermal_limit`` (Langevin sampling, 1024 Hessians of 100 x 100, the whole chain on a
   coarse grid, profiles along its three fastest modes, the confirmation and drift) and
   ``thermal_check`` at h = 0.7, a safe step (the costliest check: none of its 4 x 2995
   trajectories stops early);
3. (``--only command``) ``stepsafe advise`` and ``stepsafe check examples/morse.yaml`` as
   commands (start-up and the 0 K analysis of the scene included; the CPU time of the
   child process).

``--steps`` sets the run and ``--follow`` how far the trajectories follow it
(``follow_steps``; the commands refuse a longer run, the functions cap it).
``--keep-freed`` first makes glibc's allocator keep freed memory, as the command line
does (:mod:`stepsafe.cli.allocator`), so that the functions run as a command runs them.

Measured on this project's machine (x86_64, 2 cores shared with other work, numpy 2.4.6,
one BLAS thread), CPU time, main at 8098456 ("before") and this version ("after") run
side by side at a load average of 9-10 (CPU time under such a load runs above what an
idle machine measures). An earlier round had taken the 100-dof ``advise`` from 190 s to
153 s and ``check`` from 46 s to 41 s (at a load of 8-14; confirmations stopped at their
first failure, the commands' allocator setting). The answers are the same (h_max 1.19393
and 0.766525; the same steps rejected, each with one failure, seen by another step where
the blocks' order finds another failing trajectory first; the JSON of ``advise
examples/morse.yaml`` at kT 0.003 and 0.015 is identical):

==========================================  ==========  ==========  ========
case (10^4 steps, 2995 trajectories)        before      after       ratio
==========================================  ==========  ==========  ========
Morse, 1 dof, advise (median of 3)          3.61 s      3.38 s      0.94
Morse, 1 dof, check (median of 3)           0.77 s      0.45 s      0.58
stepsafe advise examples/morse.yaml         5.77 s      5.85 s      1.01
stepsafe check examples/morse.yaml          1.75 s      1.60 s      0.91
FPU-alpha, 100 dof, advise (1 run)          163.5 s     89.5 s      0.55
FPU-alpha, 100 dof, check at 0.7 (1 run)    40.0 s      39.0 s      0.97
the same, ``--keep-freed``, advise          -           73.4 s
the same, ``--keep-freed``, check           -           27.8 s
==========================================  ==========  ==========  ========

(``--keep-freed`` runs the functions as the command line runs them; the commands set
the allocator before too, so the Morse commands compare like with like.)

What changed: a run integrates its trajectories in blocks of 65536 state values (655
trajectories of 100 dof), each over all its steps, where a step of 2995 x 100 made 2.4 MB
temporaries that glibc's default thresholds map and page-fault afresh (a whole-chain run
of 10^4 steps with the energy at every step: about 42 s in one array, 26 s in blocks of
8192 values, 18-20 s in blocks of 65536). Blocks of 8192 values had been taken for
programs that leave the allocator alone; measured again with the blocks of 65536 there,
the 100-dof ``advise`` took 58 s against 69 s, so both now take the larger blocks. A
confirmation stopped at its first failure skips the blocks after it, and runs first the
trajectories that failed at the steps above (in the Morse bond at kT 0.015, 13 of the 18
trajectories lost at h = 0.943 were among the 14 lost 0.02% above), then the hottest. A bisection
point of a scan stops once its failures make it a band. The tabulated profiles take half
the time per force. The engine keeps per-row sums compacted and tests the whole batch
before testing rows.

Where the 100-dof ``advise`` goes, on an idle machine (load about 1, one thread), with
the exits along normal modes, splits and valleys and the mixing check of the draws:
sampling, 1024 Hessians, the exits and the starts 3.2 s; the coarse whole-chain scan (12
steps of 300 trajectories, then 6 sequential bisection rounds) 20 s; the three profiles
12 s; the confirmation 21 s, of which the final full run of 2995 trajectories is about
19 s (the ``check``, 27 s, is mostly one such run) and the three rejected steps near the
scan's edge (0.7927, 0.7919, 0.7902, each losing a trajectory late) the rest: 57 s in all
(55-57 s with ``--keep-freed``). The rejected steps had cost 12 s. A confirmation now runs
its hottest starts first, after those that failed above (the trajectories the start's
order found lost at those steps rank 9th, 339th and 384th of 2995 by energy), and a run
stopped at its failures starts on a quarter block, doubling: a rejection costs part of a
small first block (confirmation 31.7 -> 27 -> 21 s). Two threads integrating blocks at
once were measured and not kept: 55.9 s of wall clock for 85 s of CPU against 60.7 s for
61 s (memory-bound blocks and the interpreter lock).
What is left: the rejected steps (a rule that skips clear scan
points within 1% of a rejected step takes the chain to 0.7689 with one rejection, about
12 s less, but takes the Morse bond at kT 0.003 from 1.1939 down to 1.1728, the step just
below its edge that passes now being skipped); the per-step cost of the user's numpy
potential (its energy and force are 60% of a block's step); the scan's 3600 trajectories
over the full run. The commands on the
Morse scene take about 2 s more than the functions: start-up and the 0 K analysis (about
0.7 s) and the scene's compiled expression in place of a numpy potential.

The defaults of :func:`stepsafe.systems.thermal.thermal_limit` and
:func:`~stepsafe.systems.thermal.thermal_check` are used throughout. The machine and its
load average are printed with the results; numpy's BLAS runs with the thread count given
(default 1, as the tests do).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--steps", type=float, default=1e4)
    parser.add_argument("--follow", type=int, default=10_000,
                        help="the most steps the trajectories follow (follow_steps)")
    parser.add_argument("--only", default="", help="run only the cases whose label has this")
    parser.add_argument("--keep-freed", action="store_true",
                        help="make the allocator keep freed memory first, as the command "
                             "line does (stepsafe.cli.allocator)")
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)

    import numpy as np

    if args.keep_freed:
        from stepsafe.cli.allocator import keep_freed_memory

        print(f"allocator keeps freed memory: {keep_freed_memory()}")
    from stepsafe.methods.library import resolve
    from stepsafe.systems.thermal import from_callables, thermal_check, thermal_limit

    def morse():
        def energy(q):
            return 0.5 * (1 - np.exp(-q[:, 0])) ** 2

        def gradient(q):
            e = np.exp(-q)
            return (1 - e) * e

        def hessian(q):
            e = np.exp(-q)
            return (2 * e * e - e)[:, :, None]

        return from_callables(energy, gradient, [1.0], minimum=[0.0], hessian=hessian)

    def fpu(n, alpha=0.25):
        def bonds(q):
            z = np.zeros((q.shape[0], 1))
            return np.diff(np.hstack([z, q, z]), axis=1)

        def energy(q):
            d = bonds(q)
            return np.sum(d * d * (0.5 + d * (alpha / 3)), axis=1)

        def gradient(q):
            d = bonds(q)
            f = d * (1 + alpha * d)
            return f[:, :-1] - f[:, 1:]

        def hessian(q):
            k = 1 + 2 * alpha * bonds(q)
            out = np.zeros((q.shape[0], n, n))
            i = np.arange(n)
            out[:, i, i] = k[:, :-1] + k[:, 1:]
            out[:, i[:-1], i[1:]] = -k[:, 1:-1]
            out[:, i[1:], i[:-1]] = -k[:, 1:-1]
            return out

        return from_callables(energy, gradient, np.ones(n), minimum=np.zeros(n), hessian=hessian)

    import statistics

    verlet = resolve("verlet")[0]
    print(f"machine: {platform.machine()} {platform.processor() or ''} "
          f"cpus {os.cpu_count()}, load {os.getloadavg()[0]:.2f}, "
          f"numpy {np.__version__}, BLAS threads {args.threads}, run of {args.steps:g} steps")
    cases = (("Morse, 1 dof, kT = 0.003", morse(), 0.003, 0.8, "a few s"),
             ("FPU-alpha, 100 dof, kT = 0.05", fpu(100), 0.05, 0.7, "< 60 s"))
    summary = []
    for label, pot, kT, h_check, goal in cases:
        if args.only and args.only not in label:
            continue
        walls, cpus = [], []
        for _ in range(max(1, args.repeat)):
            marks: list[tuple[str, float, float]] = []

            def progress(stage: str, fraction: float, marks=marks) -> None:
                if not marks or marks[-1][0] != stage:
                    marks.append((stage, time.perf_counter(), time.process_time()))

            t0, c0 = time.perf_counter(), time.process_time()
            r = thermal_limit(verlet, pot, kT, steps=args.steps, band_steps=args.follow,
                              progress=progress)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        total = walls[-1]
        print(f"\n{label}: h_max = {r.h_max:.6g} ({r.limited_by}); 0 K {r.zero.h_zero:.6g}, "
              f"linear at temperature {r.h_linear:.6g}; trajectories of "
              f"{min(sc.steps for sc in r.scans)} steps")
        e = r.linear.ensemble
        print(f"  sampling: {e.how}, {e.size} frames, seed {e.seed}")
        c = r.confirmation
        if c is not None:
            print(f"  confirmation (seed {c.seed}): {c.trajectories} trajectories at h = "
                  f"{c.h:.6g}; rejected " + (", ".join(
                      f"h = {x:.6g} ({k} failed" + (f" by step {n[0]})" if n else ")")
                      for x, k, *n in c.rejected)
                      or "none"))
        starts = [(t0, c0)] + [(wall, cpu) for _, wall, cpu in marks] + [
            (t0 + total, c0 + cpus[-1])]
        names = ["sampling, frequencies, starts"] + [stage for stage, _, _ in marks]
        print("  stages of the last run (wall clock, CPU time):")
        for name, a, b in zip(names, starts[:-1], starts[1:]):
            print(f"    {name[:56]:56s} {b[0] - a[0]:8.2f} s {b[1] - a[1]:8.2f} s")
        print(f"  advise (thermal_limit), median of {len(walls)}: wall "
              f"{statistics.median(walls):8.2f} s, CPU {statistics.median(cpus):8.2f} s   "
              f"goal {goal}")
        summary.append((f"{label}, advise", statistics.median(cpus)))
        walls, cpus = [], []
        for _ in range(max(1, args.repeat)):
            t0, c0 = time.perf_counter(), time.process_time()
            k = thermal_check(verlet, pot, kT, h_check, steps=args.steps,
                              band_steps=args.follow)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        print(f"  check at h = {h_check}: {'SAFE' if k.safe else 'UNSAFE'}; " + "; ".join(
            f"{name}: {pr.failures} of {pr.trajectories} failed in {pr.steps} steps"
            for name, pr in k.probes))
        print(f"  check (thermal_check), median of {len(walls)}: wall "
              f"{statistics.median(walls):8.2f} s, CPU {statistics.median(cpus):8.2f} s   "
              f"goal {goal}")
        summary.append((f"{label}, check", statistics.median(cpus)))
    if not args.only or "command" in args.only:
        import resource
        import subprocess

        for command in ("advise", "check"):
            walls, cpus = [], []
            for _ in range(max(1, args.repeat)):
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "stepsafe", command,
                                str(ROOT / "examples" / "morse.yaml")], check=True,
                               capture_output=True)
                walls.append(time.perf_counter() - t0)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpus.append(after.ru_utime + after.ru_stime - before.ru_utime
                            - before.ru_stime)
            print(f"\nstepsafe {command} examples/morse.yaml (kT = 0.003, 10^4 steps; start-up "
                  f"and the 0 K analysis included), median of {len(walls)}: wall "
                  f"{statistics.median(walls):8.2f} s, CPU {statistics.median(cpus):8.2f} s")
            summary.append((f"stepsafe {command} examples/morse.yaml", statistics.median(cpus)))
    print("\nmedian CPU time per analysis:")
    for name, cpu in summary:
        print(f"  {name:48s} {cpu:8.2f} s")
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
