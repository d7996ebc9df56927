"""The Morse figure of the guide "Safe at temperature": the fraction of thermal trajectories
of velocity Verlet that fail on a Morse bond, against z = omega_0 h, at two temperatures,
with what the analysis reports.

The bond is ``examples/morse.yaml``: H = p^2/2 + (1 - e^-q)^2/2 (well depth D = 1/2,
omega_0 = 1, so z = h), a run of 10^4 steps. For kT = 0.003 and 0.015 (kT/D = 0.006 and
0.03) it asks the public API

* ``stepsafe.check(scene, h=z, kT=kT, steps=10000)`` at every z of a grid: the ensemble
  the check runs at that very step (its trajectories, how many failed, in how many steps:
  a trajectory fails when it escapes or its energy grows past the bound of the linear
  map, see the guide);
* ``stepsafe.advise(scene, kT=kT, steps=10000)``: ``h_max`` at temperature, what limits it,
  the linear limit at temperature and the bands its scan found;
* ``stepsafe.region("verlet")``: the 0 K limit z* = 2 and the linear resonance points
  n:m (4:1 at sqrt 2, 3:1 at sqrt 3, ...),

writes them to ``morse-thermal.json`` and draws ``morse-thermal.png`` from that file alone
(needs matplotlib). Run from the repository's root (a few minutes):

    python docs/figures/morse_thermal.py

``--draw-only`` redraws the PNG from the JSON. ``tests/test_thermal_figure.py`` checks the
JSON: the analysis gives the same answer today, and an integration written in the test
sees the failure fractions it holds.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

import stepsafe

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
SCENE = ROOT / "examples" / "morse.yaml"
DATA = HERE / "morse-thermal.json"
PICTURE = HERE / "morse-thermal.png"
#: The well depth of the scene's bond.
D = 0.5
#: kT of the two panels (kT/D = 0.006, about an O-H bond at 300 K, and 0.03).
TEMPERATURES = (0.003, 0.015)
#: The run's length in steps.
STEPS = 10000
#: The uniform part of the grid of z, and offsets around each resonance point.
UNIFORM = np.round(np.arange(0.40, 1.99, 0.02), 10)
OFFSETS = (0.005, 0.01, 0.02)
#: The steps the issue measured: 2% below 3:1, 0.5% below 4:1, and z = 1.5.
MEASURED = (1.40784, 1.5, 1.70056)


def grid(resonances: list[float]) -> np.ndarray:
    """The z of the curve: the uniform grid, each resonance point and its neighbours at
    ``OFFSETS``, and the issue's steps, below the 0 K limit."""
    extra = [z * (1 + s * o) for z in resonances for o in (0.0, *OFFSETS) for s in (-1, 1)]
    z = np.unique(np.round(np.concatenate([UNIFORM, extra, MEASURED]), 6))
    return z[(z >= UNIFORM[0]) & (z < 2.0)]


def resonance_points() -> tuple[float, list[dict]]:
    """The 0 K limit and the linear resonance points of velocity Verlet."""
    osc = stepsafe.region("verlet", model="oscillator").to_dict()["models"]["oscillator"]
    return osc["first_boundary"], [{"name": r["resonance"], "z": r["z"]}
                                   for r in osc["nonlinear_resonances"]]


def ensemble_at(z: float, kT: float) -> dict:
    """The check's ensemble at step z (the whole system's probe)."""
    entry = stepsafe.check(scene=str(SCENE), h=float(z), kT=kT, steps=STEPS).to_dict()
    thermal = entry["checks"][0]["thermal"]
    probe = thermal["minima"][0]["probes"][0]
    return {"z": float(z), "failures": probe["failures"],
            "trajectories": probe["trajectories"], "steps": probe["steps"],
            "safe": thermal["safe"]}


def analysis(kT: float) -> dict:
    """What ``advise`` reports at kT: h_max, its limit, the linear limit, the bands."""
    t = stepsafe.advise(scene=str(SCENE), kT=kT, steps=STEPS).to_dict()["thermal"]
    m = t["minima"][0]
    bands = [{"name": b["name"], "peak": b["peak"],
              "lower": None if b["lower"] is None else b["lower"]["clear"],
              "upper": None if b["upper"] is None else b["upper"]["clear"]}
             for sc in m["scans"] for b in sc["bands"]]
    scan = m["scans"][0]
    return {"h_max": t["h_max"], "limited_by": t["limited_by"], "h_linear": m["h_linear"],
            "scanned": scan["h_range"], "scan_steps": scan["steps"],
            "scan_trajectories": scan["trajectories"], "bands": bands}


def compute() -> dict:
    z_star, points = resonance_points()
    zs = grid([p["z"] for p in points])
    panels = []
    for kT in TEMPERATURES:
        print(f"kT = {kT}: the analysis, then {zs.size} checks", file=sys.stderr)
        panel = {"kT": kT, "kT_over_D": kT / D, **analysis(kT), "curve": []}
        for i, z in enumerate(zs):
            panel["curve"].append(ensemble_at(z, kT))
            if (i + 1) % 20 == 0:
                print(f"  {i + 1} of {zs.size}", file=sys.stderr)
        panels.append(panel)
    return {"scene": "examples/morse.yaml", "method": "verlet", "omega_0": 1.0, "D": D,
            "run_steps": STEPS, "seed": 0, "z_star": z_star, "resonances": points,
            "measured": list(MEASURED), "panels": panels}


def dumps(data: dict) -> str:
    """The data as JSON, an object without nested ones (a point of a curve) on one line."""
    text = json.dumps(data, indent=1)
    flat = re.compile(r"\{\n\s*([^{}\[\]]*?)\n\s*\}")
    return flat.sub(lambda m: "{" + " ".join(x.strip() for x in m.group(1).splitlines())
                    + "}", text) + "\n"


def draw(data: dict, path: Path) -> None:
    """The figure, from the data alone: one panel per temperature, failure fraction (log
    scale; none failed: on the axis) against z, the failure threshold, the resonance points,
    the 0 K limit, the linear limit at temperature and the bands, and h_max."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 5e-4
    fig, axes = plt.subplots(len(data["panels"]), 1, figsize=(8.5, 7.2), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, panel in zip(axes, data["panels"]):
        z = np.array([c["z"] for c in panel["curve"]])
        f = np.array([c["failures"] / c["trajectories"] for c in panel["curve"]])
        steps = panel["curve"][0]["steps"]
        m = panel["curve"][0]["trajectories"]
        ax.axvspan(panel["h_linear"], data["z_star"], color="tab:red", alpha=0.08, lw=0,
                   label="above the linear limit at temperature")
        for i, b in enumerate(panel["bands"]):
            lo = panel["scanned"][0] if b["lower"] is None else b["lower"]
            hi = panel["scanned"][1] if b["upper"] is None else b["upper"]
            ax.axvspan(lo, hi, color="tab:orange", alpha=0.35, lw=0,
                       label="band the analysis reports" if i == 0 else None)
        for r in data["resonances"]:
            ax.axvline(r["z"], color="0.55", ls=":", lw=1)
            ax.text(r["z"] + 0.005, 1.9, r["name"], ha="left", va="center", fontsize=8,
                    color="0.35")
        ax.axvline(data["z_star"], color="k", lw=1.5, label="0 K linear limit z* = 2")
        ax.axvline(panel["h_linear"], color="tab:red", ls="--", lw=1.2,
                   label="linear limit at temperature")
        ax.axhline(1e-3, color="0.4", ls="-.", lw=0.8,
                   label="max_failure 0.001 (check: no failure of its 2995)")
        ax.semilogy(z, np.where(f > 0, f, np.nan), "o-", color="tab:blue", ms=3, lw=1,
                    label=f"failed, of {m} trajectories in {steps} steps (check at z)")
        none = f == 0
        ax.plot(z[none], np.full(none.sum(), floor), "|", color="tab:blue", ms=6,
                label="none failed")
        ax.plot([panel["h_max"]], [floor], "^", color="tab:green", ms=10, clip_on=False,
                label="h_max at temperature (advise)")
        ax.set_ylim(floor * 0.8, 3.0)
        ax.set_xlim(z[0] - 0.02, data["z_star"] + 0.05)
        ax.set_ylabel("failure fraction")
        ax.text(0.985, 0.05, f"kT/D = {panel['kT_over_D']:g} (kT = {panel['kT']:g}), a run "
                f"of {data['run_steps']} steps\nh_max at temperature {panel['h_max']:.3f} "
                f"({panel['limited_by']})\nlinear limit at temperature "
                f"{panel['h_linear']:.3f}", transform=ax.transAxes, ha="right", va="bottom",
                fontsize=8.5, bbox={"facecolor": "white", "edgecolor": "0.7"})
    axes[0].legend(loc="upper left", bbox_to_anchor=(0.0, 0.93), fontsize=7,
                   framealpha=0.95)
    axes[-1].set_xlabel(r"$z = \omega_0 h$  (Morse bond, velocity Verlet)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draw-only", action="store_true",
                        help="redraw the PNG from the JSON")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--png", type=Path, default=PICTURE)
    args = parser.parse_args()
    if args.draw_only:
        data = json.loads(args.data.read_text())
    else:
        data = compute()
        args.data.write_text(dumps(data))
    draw(data, args.png)


if __name__ == "__main__":
    main()
