"""Time ``stepsafe measure`` against a plain numpy implementation of the same run.

    python benchmarks/measure_speed.py [--repeat N]

Two runs, each as its own process (start-up included, what a user types):

* ``stepsafe measure examples/fpu-alpha.yaml --method verlet --h 0.01 --time 100``
  (10^4 steps of a 4-mass FPU-alpha chain);
* ``stepsafe measure examples/pendulum.yaml --method verlet --h 0.1 --time 10000``
  (10^5 steps of the pendulum);

each beside a plain script (numpy and scipy imported, the Hamiltonian's force written by
hand): Verlet from the same start with the energy at every step, plus scipy's DOP853
reference to the same time at the same tolerance (1e-13). The runs are interleaved
(plain, stepsafe, plain, ...) and the medians of ``--repeat`` wall times are printed with
their ratio, side by side.

Measured on this project's machine (x86_64, 2 cores shared with other jobs, Python 3.11.7,
numpy 2.4.6, scipy 1.17.1), medians of interleaved runs. Before: the scene's expression
evaluated by forward-mode dual numbers at every force, an equilibrium search of 256 Newton
starts (with walks) before every n-dof run, the reference's right-hand side through the
batch engine (one repeat); after: the compiled gradient, the start's centre from one
vectorised Newton pass, the reference on the compiled right-hand side (three repeats; two
runs under different loads, the range shown).

===================================  =============  ============
run                                  before: ratio  after: ratio
===================================  =============  ============
FPU-alpha, 4 masses, 10^4 steps      13.1           1.37 - 1.65
pendulum, 10^5 steps                 4.4            1.45 - 1.49
===================================  =============  ============
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PLAIN_FPU = """
import numpy as np
from scipy.integrate import solve_ivp
alpha, n, h, T = 0.25, 4, 0.01, 100.0
def force(q):
    d = np.diff(np.concatenate(([0.0], q, [0.0])))
    f = d + alpha * d * d
    return f[1:] - f[:-1]
def energy(q, p):
    d = np.diff(np.concatenate(([0.0], q, [0.0])))
    return 0.5 * p @ p + np.sum(d * d / 2 + alpha * d ** 3 / 3)
q = np.zeros(n); q[0] = 0.05; p = np.zeros(n)
x0 = np.concatenate([q, p])
e0 = energy(q, p); worst = 0.0
F = force(q)
for _ in range(int(round(T / h))):
    p = p + 0.5 * h * F
    q = q + h * p
    F = force(q)
    p = p + 0.5 * h * F
    worst = max(worst, abs(energy(q, p) - e0))
def rhs(t, y):
    return np.concatenate([y[n:], force(y[:n])])
ref = solve_ivp(rhs, (0, T), x0, method="DOP853", rtol=1e-13, atol=1e-13 * 0.05)
print(worst, np.abs(ref.y[:, -1] - np.concatenate([q, p])).max())
"""

PLAIN_PENDULUM = """
import numpy as np
from scipy.integrate import solve_ivp
h, T = 0.1, 10000.0
q, p = np.array([0.4]), np.array([0.0])
x0 = np.concatenate([q, p])
def force(q):
    return -np.sin(q)
def energy(q, p):
    return 0.5 * p[0] ** 2 - np.cos(q[0])
e0 = energy(q, p); worst = 0.0
F = force(q)
for _ in range(int(round(T / h))):
    p = p + 0.5 * h * F
    q = q + h * p
    F = force(q)
    p = p + 0.5 * h * F
    worst = max(worst, abs(energy(q, p) - e0))
def rhs(t, y):
    return np.array([y[1], -np.sin(y[0])])
ref = solve_ivp(rhs, (0, T), x0, method="DOP853", rtol=1e-13, atol=1e-13 * 0.4)
print(worst, np.abs(ref.y[:, -1] - np.concatenate([q, p])).max())
"""

CASES = [
    ("FPU-alpha, 4 masses, 10^4 steps",
     ["measure", "examples/fpu-alpha.yaml", "--method", "verlet", "--h", "0.01", "--time",
      "100"], PLAIN_FPU),
    ("pendulum, 10^5 steps",
     ["measure", "examples/pendulum.yaml", "--method", "verlet", "--h", "0.1", "--time",
      "10000"], PLAIN_PENDULUM),
]


def _wall(command: list[str]) -> float:
    start = time.perf_counter()
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    stepsafe = [str(Path(sys.executable).parent / "stepsafe")]
    rows = []
    for name, command, plain in CASES:
        ours, theirs = [], []
        for _ in range(args.repeat):
            theirs.append(_wall([sys.executable, "-c", plain]))
            ours.append(_wall(stepsafe + command))
        a, b = statistics.median(ours), statistics.median(theirs)
        rows.append((name, a, b))
    print(f"{'run':34s} {'stepsafe':>10s} {'plain':>10s} {'ratio':>7s}")
    for name, a, b in rows:
        print(f"{name:34s} {a:9.2f}s {b:9.2f}s {a / b:7.2f}")


if __name__ == "__main__":
    main()
