"""Sweep ``--verify`` over the families and the library (the verify table of docs/validation.md).

For Gauss and Lobatto IIIA-IIIB with s = 2..40 and every built-in method, at zmax = 4 pi
and 40, find the regions of the three main models and recompute every reported point and
the status between points at 40 digits (:func:`stepsafe.reference.verify.verify_regions`, what
``region --verify`` runs). Prints one line per run and a summary; ``--json FILE`` also
writes the rows.

    python benchmarks/verify_sweep.py                 # everything (tens of minutes)
    python benchmarks/verify_sweep.py --max-stages 12 # a quicker subset
    python benchmarks/verify_sweep.py --shard 1/2     # every other case (one per core)
"""

from __future__ import annotations

import argparse
import json
import math
import time

from stepsafe.core.models import MAIN_MODELS
from stepsafe.core.regions import find_region
from stepsafe.core.transfer import has_form
from stepsafe.methods.library import FAMILIES, builtin_names, resolve
from stepsafe.reference.verify import verify_regions

ZMAXES = (4 * math.pi, 40.0)


def run(name: str, stages: int | None, zmax: float) -> dict:
    start = time.perf_counter()
    method, entry = resolve(name, stages)
    # a force-gradient method has no form for the saddle model (it mixes q and p)
    regions = {model: find_region(method, model, zmax) for model in MAIN_MODELS
               if has_form(method, model)}
    found = time.perf_counter() - start
    checks = verify_regions(name, stages, None, regions)
    failed = [c for c in checks if not c.ok]
    worst = max((c.discrepancy for c in checks if c.point.kind != "status"), default=0.0)
    return {"method": entry.name, "zmax": zmax, "points": len(checks), "ok": not failed,
            "worst": worst, "failed": [f"{c.model} {c.point.kind} {c.point.z!r}"
                                       for c in failed],
            "undecided": sum(len(r.undecided) for r in regions.values()),
            "seconds_region": round(found, 2),
            "seconds_verify": round(time.perf_counter() - start - found, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-stages", type=int, default=40)
    parser.add_argument("--json", dest="json_path", default=None)
    parser.add_argument("--shard", default="1/1", metavar="I/N",
                        help="run only cases I, I+N, I+2N, ... (1-based), to split over cores")
    args = parser.parse_args()
    index, count = (int(x) for x in args.shard.split("/"))
    cases = [(f, s) for f in FAMILIES for s in range(2, args.max_stages + 1)]
    cases += [(n, None) for n in builtin_names(single_force=True) if n not in FAMILIES]
    rows = []
    for name, stages in cases[index - 1::count]:
        for zmax in ZMAXES:
            row = run(name, stages, zmax)
            rows.append(row)
            verdict = "ok" if row["ok"] else f"FAILED {row['failed']}"
            print(f"{row['method']:28s} zmax {zmax:7.4f}  {row['points']:4d} checks  "
                  f"worst {row['worst']:.1e}  {verdict}  undecided {row['undecided']}  "
                  f"{row['seconds_region']:.1f}+{row['seconds_verify']:.1f} s", flush=True)
    bad = [r for r in rows if not r["ok"]]
    print(f"\n{len(rows)} runs, {sum(r['points'] for r in rows)} checks, {len(bad)} failed, "
          f"worst point discrepancy {max(r['worst'] for r in rows):.1e}, "
          f"{sum(r['undecided'] for r in rows)} undecided bands")
    if args.json_path:
        with open(args.json_path, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
