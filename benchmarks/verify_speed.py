"""Time ``--verify`` on the largest families and the library's slowest barrier.

    python benchmarks/verify_speed.py [--repeat N] [--json FILE]

Runs each command as its own process (what a user types) and reports its wall time and
its CPU time (user + system of the child: on a shared machine the CPU time is the steadier
figure), the median of ``--repeat`` runs:

* ``region gauss -s 40 --zmax 4pi --verify``
* ``region lobatto3ab -s 40 --zmax 4pi --verify``
* ``region blanes-casas-ros764 --model inverted --zmax 40 --verify``

and, for the record, the same ``region`` commands without ``--verify``. Every run must
end with exit 0 (the verification passed); a benchmark reports, it does not fail otherwise.

Measured on this project's machine (x86_64, 2 cores, Python 3.11.7, mpmath with its
pure-Python backend), one run each, while other jobs kept the load average at 8-9: wall
times are about four times the CPU times. Before: commit 6391180; after: the Legendre
nodes by Newton's method, the tableaux cached, the stage solves on a Hessenberg form and
the stretches found by bisection.

==========================================  =================  =================
command (``region ...``)                    before: wall, CPU  after: wall, CPU
==========================================  =================  =================
gauss -s 40 --zmax 4pi                      39.8 s, 7.1 s      9.3 s, 2.0 s
gauss -s 40 --zmax 4pi --verify             117.4 s, 16.6 s    20.4 s, 3.2 s
lobatto3ab -s 40 --zmax 4pi                 67.7 s, 10.7 s     10.4 s, 2.1 s
lobatto3ab -s 40 --zmax 4pi --verify        116.6 s, 24.2 s    15.3 s, 3.9 s
blanes-casas-ros764 (inverted, zmax 40)     6.7 s, 3.5 s       8.2 s, 2.6 s
... --verify                                741.8 s, 209.1 s   36.0 s, 8.6 s
==========================================  =================  =================
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

FOUR_PI = repr(4 * math.pi)
COMMANDS = {
    "gauss -s 40, zmax 4pi": ["region", "gauss", "-s", "40", "--zmax", FOUR_PI],
    "lobatto3ab -s 40, zmax 4pi": ["region", "lobatto3ab", "-s", "40", "--zmax", FOUR_PI],
    "blanes-casas-ros764, inverted, zmax 40": ["region", "blanes-casas-ros764", "--model",
                                               "inverted", "--zmax", "40"],
}


def timed(args: list[str]) -> tuple[float, float, int]:
    """(wall seconds, child CPU seconds, exit code) of ``python -m stepsafe ARGS``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "stepsafe", *args], capture_output=True,
                          text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if done.returncode != 0:
        print(done.stdout[-2000:], done.stderr[-2000:], file=sys.stderr)
    return wall, cpu, done.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--json", dest="json_path", default=None)
    args = parser.parse_args()
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}, Python {platform.python_version()}")
    rows = []
    for label, command in COMMANDS.items():
        for verify in (False, True):
            runs = [timed(command + (["--verify"] if verify else []))
                    for _ in range(args.repeat)]
            wall = statistics.median(r[0] for r in runs)
            cpu = statistics.median(r[1] for r in runs)
            codes = sorted({r[2] for r in runs})
            rows.append({"command": label, "verify": verify, "wall": round(wall, 2),
                         "cpu": round(cpu, 2), "exit": codes})
            print(f"  {label:40s} {'--verify' if verify else '':9s} wall {wall:7.1f} s  "
                  f"cpu {cpu:7.1f} s  exit {codes}", flush=True)
    if args.json_path:
        with open(args.json_path, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
