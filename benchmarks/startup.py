"""Start-up of the command line against ``python -c "import numpy"``, side by side.

    python benchmarks/startup.py [--repeat N]

Each command runs in a fresh interpreter; the commands take turns (round r runs every
command once, in an order shifted by r), so a change in the machine's load reaches them all
alike, and the figure is the median over the rounds. Printed: the median wall time of each
command and its ratio to ``import numpy`` measured in the same rounds, with the machine's
load average before and after. Goal: ``stepsafe check`` on a built-in method within 2x
``import numpy`` (check runs in CI on every commit).

Bytecode is cached, as for an installed package (pip compiles it): a sandbox that sets
PYTHONDONTWRITEBYTECODE would otherwise time the compilation of stepsafe's sources. Exit code
0 (a benchmark reports, it does not fail).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: (label, arguments after the interpreter, ratio goal or "")
COMMANDS = (
    ("python -c 'import numpy'", ["-c", "import numpy"], ""),
    ("python -c 'import stepsafe'", ["-c", "import stepsafe"], ""),
    ("stepsafe check --method verlet --step 0.5 --beta 1",
     ["-m", "stepsafe", "check", "--method", "verlet", "--step", "0.5", "--beta", "1"],
     "<= 2x"),
    ("stepsafe check examples/scene.yaml", ["-m", "stepsafe", "check", "examples/scene.yaml"],
     "<= 2x"),
    ("stepsafe advise --method yoshida4 --beta 3.2",
     ["-m", "stepsafe", "advise", "--method", "yoshida4", "--beta", "3.2"], "<= 3x"),
)


def environment() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(ROOT)
    return env


def medians(commands=COMMANDS, repeat: int = 15) -> list[float]:
    """The median wall time (s) of each command over ``repeat`` interleaved rounds (after
    one untimed round that fills the bytecode and file caches)."""
    env = environment()
    argv = [[sys.executable, *args] for _, args, _ in commands]
    for args in argv:
        subprocess.run(args, capture_output=True, cwd=ROOT, env=env, check=False)
    times: list[list[float]] = [[] for _ in argv]
    for r in range(repeat):
        order = [(i + r) % len(argv) for i in range(len(argv))]
        for i in order:
            start = time.perf_counter()
            subprocess.run(argv[i], capture_output=True, cwd=ROOT, env=env, check=False)
            times[i].append(time.perf_counter() - start)
    return [statistics.median(t) for t in times]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15, help="interleaved rounds")
    repeat = parser.parse_args().repeat
    before = os.getloadavg()[0]
    figures = medians(repeat=repeat)
    after = os.getloadavg()[0]
    base = figures[0]
    print(f"start-up, median of {repeat} interleaved rounds, {os.cpu_count()} cores, "
          f"load average {before:.2f} before, {after:.2f} after")
    print(f"  {'command':58s} {'median':>9s} {'ratio':>8s}  goal")
    for (label, _, goal), t in zip(COMMANDS, figures):
        print(f"  {label:58s} {t * 1e3:7.0f} ms {t / base:7.2f}x  {goal}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
