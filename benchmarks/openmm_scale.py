"""An MD system's analysis at scale: boxes of flexible TIP3P water with PME, from about 2,600
to about 10,000 atoms, analysed end to end by ``stepsafe.advise`` as the command line does
(read the System, minimise on OpenMM's CPU platform, choose the finite-difference step,
Lanczos on Hessian-vector products from OpenMM's Reference-platform forces), each size in its
own process so that its peak memory is its own. Printed, not asserted.

    python benchmarks/openmm_scale.py [--edges 3.0 3.7 4.64] [--cutoff 1.0]

Per size: the atoms, the wall-clock time of the analysis and its CPU time (the machine is
shared: the CPU time is what the analysis itself used), the wall-clock time of each stage
(minimisation, step control, Lanczos; from the progress callback the command line's bar
uses), the Hessian-vector products, Verlet's limit, and memory: the process's peak resident
set (``ru_maxrss``, which includes Python, numpy, scipy and OpenMM themselves, about 90 MB)
and its growth during the analysis, and the peak of the memory Python and numpy allocated
during the analysis (``tracemalloc``), beside what a dense 3N x 3N Hessian would need; a
straight line through memory against atoms, fitted by least squares, with its largest
deviation. Before the timed analysis the process analyses the 24-atom water cluster of
examples/, so that imports and OpenMM's start-up are outside what is traced. The systems are
built by ``write_example_system("water", box_edge=...)`` from files in the OpenMM wheel (not
committed: the 4.64 nm box's System is several MB). OpenMM's CPU platform runs on one thread.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def child(edge: float, cutoff: float) -> dict:
    """Analyse one box (in this process) and return its figures."""
    import tracemalloc

    import yaml

    import stepsafe
    from stepsafe.systems.loader import MD_STAGES
    from stepsafe.systems.md import openmm_engine as oe

    folder = Path(tempfile.mkdtemp(prefix="stepsafe-scale-"))
    xml, pdb = oe.write_example_system("water", folder, box_edge=edge, cutoff=cutoff)
    scene = folder / "scene.yaml"
    scene.write_text(yaml.safe_dump({"method": "verlet", "time_unit": "fs", "system": {
        "openmm": xml.name, "positions": pdb.name, "minimize": True}}))
    atoms = oe.read_system(xml).getNumParticles()
    stages: dict[str, list[float]] = {}
    counts: dict[str, int] = {}
    start = time.perf_counter()
    last = [start]

    def progress(fraction: float) -> None:
        return None

    def stage(label: str, done: int, total: int | None) -> None:
        now = time.perf_counter()
        stages.setdefault(label, [now, now])[1] = now
        counts[label] = done
        if label == MD_STAGES["products"] and now - last[0] > 30:
            last[0] = now
            print(f"  [{atoms} atoms] {label}: {done} after {now - start:.0f} s",
                  file=sys.stderr, flush=True)

    progress.stage = stage  # type: ignore[attr-defined]
    # import everything the analysis uses (and start OpenMM) on the 24-atom cluster first, so
    # that the memory traced below is the analysis's own
    stepsafe.advise("verlet", scene=str(ROOT / "examples" / "water-cluster.yaml"))
    usage = resource.getrusage(resource.RUSAGE_SELF)
    baseline, cpu0 = usage.ru_maxrss * 1024, usage.ru_utime + usage.ru_stime
    start = time.perf_counter()
    tracemalloc.start()
    report = stepsafe.advise("verlet", scene=str(scene), progress=progress)
    _, traced = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    total = time.perf_counter() - start
    usage = resource.getrusage(resource.RUSAGE_SELF)
    rss = usage.ru_maxrss * 1024  # Linux: kB
    cpu = usage.ru_utime + usage.ru_stime - cpu0
    record = report.record
    marks = sorted((t0, label) for label, (t0, _) in stages.items())
    durations = {}
    for k, (t0, label) in enumerate(marks):
        t1 = marks[k + 1][0] if k + 1 < len(marks) else start + total
        durations[label] = t1 - t0
    return {"edge": edge, "cutoff": cutoff, "atoms": atoms, "h_max_fs": report.h_max,
            "seconds": total, "cpu_seconds": cpu, "stages": durations, "counts": counts,
            "setup": (marks[0][0] - start) if marks else total,
            "peak_rss": rss, "baseline_rss": baseline, "traced_peak": traced,
            "dense_bytes": (3 * atoms) ** 2 * 8, "analysis": record["system"]["analysis"],
            "notes": record["system"]["notes"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edges", type=float, nargs="+", default=[3.0, 3.7, 4.64])
    parser.add_argument("--cutoff", type=float, default=1.0)
    parser.add_argument("--child", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the figures to this file")
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    from stepsafe.systems.loader import MD_STAGES

    if args.child is not None:
        print(json.dumps(child(args.child, args.cutoff)))
        return
    import numpy
    import openmm
    import scipy

    print(f"machine: {platform.machine()} {platform.processor() or ''}, "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; Python "
          f"{platform.python_version()}, numpy {numpy.__version__}, scipy {scipy.__version__}, "
          f"OpenMM {openmm.__version__}")
    rows = []
    for edge in args.edges:
        proc = subprocess.run([sys.executable, __file__, "--child", str(edge), "--cutoff",
                               str(args.cutoff)], capture_output=True, text=True)
        if proc.returncode:
            sys.exit(f"edge {edge}: {proc.stderr[-2000:]}")
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"edge {edge} nm: {r['atoms']} atoms, {r['seconds']:.0f} s", file=sys.stderr)
    print()
    print("| atoms | total (CPU) | minimise | step control | Lanczos (products) | h_max (fs) | "
          "peak RSS (growth) | traced peak (per atom) | dense 3N x 3N |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        st, n = r["stages"], r["counts"]
        lanczos, step, mini = (MD_STAGES[k] for k in ("products", "step control", "minimize"))
        print(f"| {r['atoms']} | {r['seconds']:.0f} s ({r['cpu_seconds']:.0f} s) | "
              f"{st.get(mini, 0):.0f} s | {st.get(step, 0):.0f} s | "
              f"{st.get(lanczos, 0):.0f} s ({n.get(lanczos, 0)}) | {r['h_max_fs']:.4f} | "
              f"{r['peak_rss'] / 2**20:.0f} MB ({(r['peak_rss'] - r['baseline_rss']) / 2**20:.0f}"
              f" MB) | {r['traced_peak'] / 2**20:.1f} MB "
              f"({r['traced_peak'] / r['atoms'] / 1024:.2f} kB) | "
              f"{r['dense_bytes'] / 2**30:.2f} GB |")
    if len(rows) > 1:
        import numpy as np

        n = np.array([r["atoms"] for r in rows], dtype=float)
        for key, name in (("traced_peak", "traced peak"), ("peak_rss", "peak RSS")):
            y = np.array([r[key] for r in rows], dtype=float)
            slope, icpt = np.polyfit(n, y, 1)
            worst = float(np.max(np.abs(y - (slope * n + icpt)) / y))
            print(f"\n{name}: {icpt / 2**20:.1f} MB + {slope / 1024:.2f} kB per atom "
                  f"(least squares over {len(n)} sizes; largest deviation {100 * worst:.1f}%)")
    for r in rows:
        print(f"\n{r['atoms']} atoms: {r['analysis']}")
        for note in r["notes"]:
            print(f"  note: {note}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
