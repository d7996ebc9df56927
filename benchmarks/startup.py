"""Start-up of the command line against ``python -c "import numpy"``, side by side.

    python benchmarks/startup.py [--repeat N]

Each command runs in a fresh interpreter; the commands take turns (round r runs every
command once, in an order shifted by r), so a change in the machine's load reaches them all
alike, and the figure is the median over the rounds. Printed: the median CPU time (user +
system of the child) and the median wall time of each command, each with its ratio to
``import numpy`` measured in the same rounds, and the machine's load average before and
after. On a shared machine the CPU times are the steadier figures. Goal: ``stepsafe check``
within 2x ``import numpy`` (check runs in CI on every commit).

Bytecode is cached, as for an installed package (pip compiles it): a sandbox that sets
PYTHONDONTWRITEBYTECODE would otherwise time the compilation of stepsafe's sources. Exit code
0 (a benchmark reports, it does not fail).

Measured (2 cores, numpy 2.4.6, 15 rounds, CPU time; main at 8098456 against this version
in the same rounds, load average 7.6-8.6 from other work):

    command                                           before    now
    check --method verlet --step 0.5 --beta 1          1.78x   1.38x
    check examples/scene.yaml                          2.04x   1.52x
    advise --method yoshida4 --beta 3.2                2.17x   1.71x

``import numpy, yaml, click`` alone took 1.22x. What changed: ``python -m stepsafe`` and the
``stepsafe`` script start without the cyclic garbage collector and freeze what start-up made
(:mod:`stepsafe.__main__`), each model's region is analysed once for both criteria
(:func:`stepsafe.core.regions.shared_regions`), YAML files are read by libyaml's scanner
(:mod:`stepsafe.files.yamlio`), and a plain check loads no module of tolerances, resonance
orders, stage solvers, Langevin splittings or JSON output. On an idle machine the ratios
come out higher (``import numpy`` is then relatively faster): main measured 1.99x, 2.30x
and 2.33x at a load of 0.15.
"""

from __future__ import annotations

import argparse
import os
import resource
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


def medians(commands=COMMANDS, repeat: int = 15) -> tuple[list[float], list[float]]:
    """The median wall time and the median CPU time (s, user + system of the child) of each
    command over ``repeat`` interleaved rounds (after one untimed round that fills the
    bytecode and file caches)."""
    env = environment()
    argv = [[sys.executable, *args] for _, args, _ in commands]
    for args in argv:
        subprocess.run(args, capture_output=True, cwd=ROOT, env=env, check=False)
    wall: list[list[float]] = [[] for _ in argv]
    cpu: list[list[float]] = [[] for _ in argv]
    for r in range(repeat):
        order = [(i + r) % len(argv) for i in range(len(argv))]
        for i in order:
            used = _children_cpu()
            start = time.perf_counter()
            subprocess.run(argv[i], capture_output=True, cwd=ROOT, env=env, check=False)
            wall[i].append(time.perf_counter() - start)
            cpu[i].append(_children_cpu() - used)
    return [statistics.median(t) for t in wall], [statistics.median(t) for t in cpu]


def _children_cpu() -> float:
    """User + system CPU time (s) of the children waited for so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15, help="interleaved rounds")
    repeat = parser.parse_args().repeat
    before = os.getloadavg()[0]
    wall, cpu = medians(repeat=repeat)
    after = os.getloadavg()[0]
    print(f"start-up, median of {repeat} interleaved rounds, {os.cpu_count()} cores, "
          f"load average {before:.2f} before, {after:.2f} after")
    print(f"  {'command':54s} {'CPU':>7s} {'ratio':>6s} {'wall':>7s} {'ratio':>6s}  goal")
    for (label, _, goal), c, w in zip(COMMANDS, cpu, wall):
        print(f"  {label:54s} {c * 1e3:4.0f} ms {c / cpu[0]:5.2f}x {w * 1e3:4.0f} ms "
              f"{w / wall[0]:5.2f}x  {goal}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
