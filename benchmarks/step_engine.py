"""Time the float one-step maps (the 2x2 transfer jet and the 2n x 2n step) of two trees.

    python benchmarks/step_engine.py BASELINE [--repeat N] [--json FILE]

BASELINE is a directory holding another version of the ``stepsafe`` package (for instance
``git archive REV stepsafe methods | tar -x -C DIR``); the current tree is the one this script
sits in. Each repeat runs one child process per tree, alternating (interleaved, so a
change in the machine's load hits both), and each child times every case below as the
median of its own inner runs (CPU time of the process). Printed: the median over repeats
per case and tree, and the ratio current / baseline (above 1: slower).

Cases (the region finder's hot path is :func:`stepsafe.core.transfer.transfer_jet` with
derivatives to second order and the rounding bound, on a grid of z):

* ``pefrl`` (a splitting) on the oscillator and on the saddle, 4000 z;
* ``gauss -s 4`` (an implicit RK method) on the oscillator, 4000 z;
* ``baoab`` (several blocks: drift/kick, friction, drift/kick) on the oscillator, 4000 z;
* ``transfer_matrix`` of ``pefrl`` alone (no derivatives, no bound), 4000 z;
* the 2n x 2n step (``M - I`` with its rounding bound, as the coupled scan asks for it:
  the system built once) of ``pefrl`` and of ``gauss -s 2`` on a 6-dof S, one h at a time.

Measured on this project's machine (x86_64, 2 cores shared, load average 11-15, Python
3.11.7, one BLAS thread), ``--repeat 7``, baseline the two maps written separately (commit
15cfba2), current the one step engine (:mod:`stepsafe.core.engine`); CPU ms per call:

===========================  ========  =======  =====
case                         baseline  current  ratio
===========================  ========  =======  =====
jet pefrl oscillator         1.31      1.45     1.10
jet pefrl saddle             0.38      0.38     1.01
jet gauss-4 oscillator       16.83     16.79    1.00
jet baoab oscillator         5.96      5.97     1.00
matrix pefrl oscillator      0.12      0.13     1.01
2n pefrl (40 h)              6.95      7.79     1.12
2n gauss-2 (40 h)            4.01      2.08     0.52
===========================  ========  =======  =====

The first row varied between 1.00 and 1.16 over runs; timed in one process, the two
versions of ``transfer_jet`` alternating 40 times, it was 1.01 (1.240 ms against 1.251 ms).
The 2n x 2n Runge–Kutta step is faster because its stage operator is built once per system
instead of at every h; the 2n x 2n splitting pays the engine's per-call bookkeeping
(~20 microseconds) on one h at a time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent

CHILD = r"""
import json, statistics, time
import numpy as np
from stepsafe.core.transfer import transfer_jet, transfer_matrix
from stepsafe.methods.library import resolve
from stepsafe.systems.coupled import _Steps

z = np.linspace(1e-3, 6.0, 4000)
pefrl = resolve("pefrl")[0]
gauss4 = resolve("gauss", 4)[0]
gauss2 = resolve("gauss", 2)[0]
baoab = resolve("baoab")[0]
rng = np.random.default_rng(1)
n = 6
A = rng.normal(size=(n, n))
S = np.zeros((2 * n, 2 * n))
S[:n, :n] = A @ A.T + n * np.eye(n)
S[n:, n:] = np.eye(n)
hs = np.linspace(0.01, 0.3, 40)
steps_pefrl, steps_gauss2 = _Steps(pefrl, S), _Steps(gauss2, S)
cases = {
    "jet pefrl oscillator": lambda: transfer_jet(pefrl, z, "oscillator", order=2),
    "jet pefrl saddle": lambda: transfer_jet(pefrl, z, "saddle", order=2),
    "jet gauss-4 oscillator": lambda: transfer_jet(gauss4, z, "oscillator", order=2),
    "jet baoab oscillator": lambda: transfer_jet(baoab, z, "oscillator", order=2),
    "matrix pefrl oscillator": lambda: transfer_matrix(pefrl, z, "oscillator"),
    "2n pefrl (40 h)": lambda: [steps_pefrl.deviation(h) for h in hs],
    "2n gauss-2 (40 h)": lambda: [steps_gauss2.deviation(h) for h in hs],
}
out = {}
for name, run in cases.items():
    run()
    times = []
    for _ in range(25):
        t = time.process_time()
        run()
        times.append(time.process_time() - t)
    out[name] = statistics.median(times)
print(json.dumps(out))
"""


def _child(tree: Path) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True,
                          text=True, cwd=tree)
    if done.returncode:
        raise SystemExit(f"{tree}: {done.stderr.strip().splitlines()[-1]}")
    return json.loads(done.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("baseline", type=Path)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    trees = {"baseline": args.baseline.resolve(), "current": HERE}
    runs: dict[str, list[dict[str, float]]] = {k: [] for k in trees}
    for _ in range(args.repeat):
        for key, tree in trees.items():
            runs[key].append(_child(tree))
    cases = list(runs["current"][0])
    table = {}
    print(f"{'case':28s} {'baseline ms':>12s} {'current ms':>11s} {'ratio':>6s}")
    for case in cases:
        base = statistics.median(r[case] for r in runs["baseline"])
        cur = statistics.median(r[case] for r in runs["current"])
        table[case] = {"baseline_s": base, "current_s": cur, "ratio": cur / base}
        print(f"{case:28s} {1e3 * base:12.2f} {1e3 * cur:11.2f} {cur / base:6.2f}")
    if args.json:
        args.json.write_text(json.dumps(table, indent=2) + "\n")


if __name__ == "__main__":
    main()
