"""Time ``hmc`` on 10^5 Gaussian modes with the six default methods, and HMC on a target.

    python benchmarks/hmc.py [--before PATH] [--repeat N] [--timeout S] [--json FILE]

Each case runs in its own process (``python -c``, one BLAS thread) and reports its wall
time and CPU time (user + system of the child: on a shared machine the CPU time is the
steadier figure), the median of ``--repeat`` runs. With ``--before PATH`` (a checkout of
another commit, e.g. ``git worktree add /tmp/before <commit>``) every case also runs
against that source tree, the two interleaved run by run, side by side; a run past
``--timeout`` seconds is stopped and reported as such.

Cases: ``hmc(None, sigma=S)`` with 10^5 standard deviations S log-uniform on [0.1, 1]
(seed 0) and L unknown (the bound over L), L = 20, jitter 0.1, and L = 20 with jitter 0.1;
and :func:`stepsafe.core.hmc_target.advice.hmc_on_target` on the banana
``x^2/2 + (y - 0.3 x^2)^2/2`` with verlet and bcss2 at L = 10 (the mode search, warm-up
draws, the frequency spread, the step searches, the Laplace figures and the divergence
scan), and on a Gaussian of 100 standard deviations log-uniform on [0.1, 1] (seed 0) given
as numpy callables, with verlet at L = 10.

Measured on this project's machine (x86_64, 2 cores shared with other jobs, load average
10-13, Python 3.11.7, numpy 2.4), one run each; CPU time is the figure to compare (wall
time is mostly waiting for a core). Before: main at f56d497 (the Gaussian hmc as it was);
after: this branch (the step search narrowed by regula falsi over a grid walked upwards,
M(z) of a splitting without the jet, jitter panels in proportion to J, the search for a
given L started at the bound's step and, with jitter on more than 2048 distinct
frequencies, the bound standing for it).

========================================  =====================  ===================  =====
case                                      before: wall, CPU      after: wall, CPU     ratio
========================================  =====================  ===================  =====
10^5 modes, L unknown                     71.6 s, 13.0 s         10.0 s, 2.0 s        6.6x
10^5 modes, L = 20                        36.4 s, 12.3 s         38.3 s, 3.6 s        3.4x
10^5 modes, jitter 0.1                    > 500 s (stopped)      111.6 s, 12.6 s      > 6x
10^5 modes, L = 20, jitter 0.1            > 500 s (stopped)      331.1 s, 35.2 s      -
banana c = 0.3, verlet + bcss2, L = 10    -                      7.9 s, 0.8 s         -
========================================  =====================  ===================  =====

With a given L and jitter, most of the time is one jittered acceptance of the L given per
method at its step at target (about 30 s of CPU on 10^5 distinct frequencies: the average
follows every mode's turns of L theta across the jitter), not the search.

Second round (``--before`` main at 00ddcb8, ``--only "L = 20" --repeat 3``, medians of
interleaved runs, load average 11-15): the per-mode errors evaluated in pieces of 2^14
elements instead of 2^18 (cache-sized temporaries; the larger pieces spent much of their
time in page faults of fresh arrays), the Chebyshev factor's elliptic and hyperbolic
branches each on its own entries, and the lumped modes' mean and variance from their
errors (``a + b = E``, ``a^2 + b^2 = E^2 + E``) rather than from their weights. Figures
within 5e-14 relative of main's on six targets (3 to 10^5 modes, L, T, jitter).

========================================  =====================  ===================  =====
case                                      before: wall, CPU      after: wall, CPU     ratio
========================================  =====================  ===================  =====
10^5 modes, L = 20                        54.0 s, 5.5 s          24.9 s, 3.1 s        1.7x
10^5 modes, L = 20, jitter 0.1            290.9 s, 35.0 s        154.9 s, 26.6 s      1.3x
========================================  =====================  ===================  =====

Where the jittered case's CPU goes now (cProfile): the one-step matrices and their offsets
of 10^5 modes at each of about 3400 quadrature nodes (two thirds), the Gil-Pelaez
integral of the 2048 largest errors per node (a fifth). The node count is set by the turns
of L theta of the fastest modes and the kinks of the acceptance at L theta = k pi; the
jitter costs about 8x because each node evaluates every mode.

Third round (``--before`` main at 334c072, ``--only "10^5" --repeat 3``, medians of
interleaved runs, load average 7-12): beyond 2048 distinct frequencies the sums over modes
are taken by a Gauss rule of the spectrum (8 points per bin, a few hundred points for
these 10^5 modes), checked against every mode's ``sum E`` and ``sum E^2`` at the jitter's
two ends, so each jitter node evaluates the rule's points, not every mode, and the
characteristic function of all modes is integrated without lumping. On this spectrum the
jittered acceptances agree with every mode evaluated (the Gil-Pelaez integral of all 10^5
modes at each node) within 1e-10, where main's lumped figures were 0.9e-6 to 1.7e-6 off.
Without jitter the rule saves nothing (one node per step, evaluated in full for the
check) and costs its construction: about 10% more CPU, for the same accuracy gain.

========================================  =====================  ===================  =====
case                                      before: wall, CPU      after: wall, CPU     ratio
========================================  =====================  ===================  =====
10^5 modes, L unknown                     24.4 s, 2.0 s          26.7 s, 2.2 s        0.9x
10^5 modes, L = 20                        8.4 s, 3.2 s           9.1 s, 3.7 s         0.9x
10^5 modes, jitter 0.1                    24.3 s, 9.4 s          10.3 s, 3.7 s        2.5x
10^5 modes, L = 20, jitter 0.1            85.7 s, 28.7 s         11.5 s, 4.3 s        6.6x
========================================  =====================  ===================  =====

What is left in the jittered case's 4.3 s (cProfile): the rule at each step the search
evaluates (about 25 per method: the exact one-step matrices of every mode at the jitter's
two ends for its check, and its bins), about half; the jitter rules (edges, turns of
L theta) and the Gil-Pelaez integrals at the nodes, most of the rest.

Fourth round (``--before`` main at 8098456, ``--only "L = 10" --repeat 3``, medians of
interleaved runs, load average 8): HMC on a target searches for other modes (1024 starts
around the Laplace approximation, 50 batched descent steps, the lowest distinct end points
polished) and compares the draws with what it finds. Measured alone in one process (one
BLAS thread, mean of 5): 0.012 s of CPU on the banana, 0.06 s on the 100-dimensional
Gaussian, each finding no other mode; the whole runs' CPU moves within their noise.

========================================  =====================  ===================  =====
case                                      before: wall, CPU      after: wall, CPU     ratio
========================================  =====================  ===================  =====
banana c = 0.3, verlet + bcss2, L = 10    3.3 s, 1.3 s           3.5 s, 1.4 s         0.9x
Gaussian d = 100 (callable), verlet       16.8 s, 6.9 s          28.7 s, 7.0 s        1.0x
========================================  =====================  ===================  =====
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

SETUP = ("import inspect\n"
         "import numpy as np\n"
         "from stepsafe import hmc\n"
         "L = ('trajectory_steps' if 'trajectory_steps' in inspect.signature(hmc).parameters\n"
         "     else 'steps')\n"
         "sigma = np.exp(np.random.default_rng(0).uniform(np.log(0.1), 0.0, 10**5))\n")
BANANA = (
    "import numpy as np\n"
    "from stepsafe import method\n"
    "from stepsafe.core.hmc import Trajectory\n"
    "from stepsafe.core.hmc_target.advice import hmc_on_target\n"
    "from stepsafe.core.hmc_target.potential import CallablePotential, target\n"
    "def energy(q):\n"
    "    x, y = q[..., 0], q[..., 1]\n"
    "    return 0.5 * x * x + 0.5 * (y - 0.3 * x * x) ** 2\n"
    "def gradient(q):\n"
    "    x, y = q[..., 0], q[..., 1]\n"
    "    r = y - 0.3 * x * x\n"
    "    return np.stack([x - 0.6 * x * r, r], axis=-1)\n"
    "hmc_on_target(target(CallablePotential(energy, gradient, 2)),\n"
    "              [method('verlet').tableau, method('bcss2').tableau], Trajectory(steps=10))\n")
GAUSSIAN_100 = (
    "import numpy as np\n"
    "from stepsafe import method\n"
    "from stepsafe.core.hmc import Trajectory\n"
    "from stepsafe.core.hmc_target.advice import hmc_on_target\n"
    "from stepsafe.core.hmc_target.potential import CallablePotential, target\n"
    "s = np.exp(np.random.default_rng(0).uniform(np.log(0.1), 0.0, 100))\n"
    "hmc_on_target(target(CallablePotential(lambda q: 0.5 * ((q / s) ** 2).sum(-1),\n"
    "                                       lambda q: q / s ** 2, 100)),\n"
    "              [method('verlet').tableau], Trajectory(steps=10))\n")
CASES = {
    "10^5 modes, L unknown": SETUP + "hmc(None, sigma=sigma)\n",
    "10^5 modes, L = 20": SETUP + "hmc(None, sigma=sigma, **{L: 20})\n",
    "10^5 modes, jitter 0.1": SETUP + "hmc(None, sigma=sigma, jitter=0.1)\n",
    "10^5 modes, L = 20, jitter 0.1": SETUP + "hmc(None, sigma=sigma, jitter=0.1, **{L: 20})\n",
    "banana c = 0.3, verlet + bcss2, L = 10": BANANA,
    "Gaussian d = 100 (callable), verlet, L = 10": GAUSSIAN_100,
}


def timed(code: str, tree: str | None, timeout: float) -> tuple[float, float, str]:
    """(wall seconds, child CPU seconds, ok|stopped|failed) of ``python -c CODE`` with ``tree``
    first on the import path (None: this checkout)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               MKL_NUM_THREADS="1")
    root = tree or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              env=env, cwd=root, timeout=timeout)
        status = "ok" if done.returncode == 0 else "failed"
        if status == "failed":
            print(done.stderr[-2000:], file=sys.stderr)
    except subprocess.TimeoutExpired:
        status = "stopped"
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, status


Run = tuple[float, float, str]


def _cell(runs: list[Run], timeout: float) -> str:
    if not runs:
        return "-"
    if any(status == "failed" for _, _, status in runs):
        return "failed (stderr above)"
    if any(status == "stopped" for _, _, status in runs):
        return (f"> {timeout:.0f} s (stopped; "
                f"{statistics.median(c for _, c, _ in runs):.0f} s CPU)")
    return (f"{statistics.median(w for w, _, _ in runs):.1f} s, "
            f"{statistics.median(c for _, c, _ in runs):.1f} s")


def _ratio(before: list[Run], after: list[Run]) -> str:
    """Before over after, of the median CPU time ('>' when the before run was stopped)."""
    if not before or not after or any(status != "ok" for _, _, status in after) or \
            any(status == "failed" for _, _, status in before):
        return "-"
    cpu_after = statistics.median(c for _, c, _ in after)
    cpu_before = statistics.median(c for _, c, _ in before)
    sign = "" if all(status == "ok" for _, _, status in before) else "> "
    return f"{sign}{cpu_before / cpu_after:.1f}x" if cpu_after > 0 else "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default=None, help="another source tree to compare")
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=600.0)
    parser.add_argument("--only", default=None, help="run the cases whose name has this")
    parser.add_argument("--json", dest="json_path", default=None)
    args = parser.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}, Python {platform.python_version()}")
    print(f"{'case':<40}  {'before: wall, CPU':<22}  {'after: wall, CPU':<22}  "
          "CPU before / after")
    rows = []
    for label, code in CASES.items():
        if args.only and args.only not in label:
            continue
        before, after = [], []
        for _ in range(args.repeat):  # interleaved: before, after, before, after, ...
            if args.before is not None:
                before.append(timed(code, args.before, args.timeout))
            after.append(timed(code, None, args.timeout))
        row = {"case": label, "before": _cell(before, args.timeout),
               "after": _cell(after, args.timeout), "ratio": _ratio(before, after)}
        rows.append(row)
        print(f"{label:<40}  {row['before']:<22}  {row['after']:<22}  {row['ratio']}",
              flush=True)
    if args.json_path:
        with open(args.json_path, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
