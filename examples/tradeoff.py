"""Measure speed against accuracy with real integrations, next to stepsafe's predictions.

For each method and a range of steps h (frequency beta = 1, so z = h) this integrates

* the harmonic oscillator H = (p^2 + q^2)/2 — the measured energy error (max over the run of
  E_max/E_min - 1) and phase error (from the mean period) must match the prediction;
* a pendulum near its stable equilibrium, H = p^2/2 - cos q, amplitude 0.1 — the same
  figures, now nonlinear (the prediction is for the linearisation);
* a pendulum near its top (a saddle of rate 1): the measured escape rate against the
  predicted growth-rate error log(mu)/z - 1;

and records the wall time per unit of simulated time. Writes a CSV (and a PNG when
matplotlib is installed). Run from the repository root:

    python examples/tradeoff.py --out tradeoff.csv --png tradeoff.png

Implicit methods (gauss, lobatto3ab) solve their stages by fixed-point iteration to
rounding; their wall time includes those iterations, and their evaluations per step (the
PNG's cost axis) are the force calls counted on the oscillator run.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time

import numpy as np

import stepsafe

MAIN = ["verlet", "yoshida4", "suzuki4", "pefrl", "blanes-moan6", "kahan-li8", "gauss:2",
        "lobatto3ab:3"]


def stepper(method: stepsafe.Integrator):
    """A one-step function (q, p, h, force) -> (q, p) running the method's own recipe."""
    ops = method.operations
    if ops is not None:

        def step(q, p, h, force):
            for kind, c in ops:
                if kind == "drift":
                    q = q + c * h * p
                else:
                    p = p + c * h * force(q)
            return q, p

        return step
    prk = method.partitioned_tableau
    if prk is None:
        raise SystemExit(f"{method.name}: a composition of implicit steps is not run here")
    A_q, b_q, A_p, b_p, s = prk.A_q, prk.b_q, prk.A_p, prk.b_p, prk.stages

    def step(q, p, h, force):
        Q, P = np.full(s, q), np.full(s, p)
        for _ in range(100):
            F = force(Q)
            Q_new, P_new = q + h * A_q @ P, p + h * A_p @ F
            done = max(np.abs(Q_new - Q).max(), np.abs(P_new - P).max()) <= 1e-16 * (
                1 + abs(q) + abs(p))
            Q, P = Q_new, P_new
            if done:
                break
        return q + h * b_q @ P, p + h * b_p @ force(Q)

    return step


def run(step, q, p, h, T, force, energy):
    """The orbit, its energies, wall time per unit time and force evaluations per step
    (each stage value a force is computed at counts one)."""
    n = max(1, int(round(T / h)))
    qs, es = np.empty(n + 1), np.empty(n + 1)
    qs[0], es[0] = q, energy(q, p)
    calls = [0]

    def counted(x):
        calls[0] += np.size(x)
        return force(x)

    start = time.perf_counter()
    for i in range(n):
        q, p = step(q, p, h, counted)
        qs[i + 1], es[i + 1] = q, energy(q, p)
    wall = time.perf_counter() - start
    return qs, es, wall / (n * h), calls[0] / n


def recurrence_phase(qs, h):
    """Rotation per step measured from a linear orbit: q_{k+1} + q_{k-1} = 2 cos(theta) q_k
    holds exactly for every linear one-step method; fit cos(theta) by least squares and
    return theta/h - 1 through cos(theta) - cos(h) = -2 sin((theta+h)/2) sin((theta-h)/2)."""
    num = np.dot(qs[2:] + qs[:-2] - 2 * np.cos(h) * qs[1:-1], qs[1:-1])
    delta = num / (2 * np.dot(qs[1:-1], qs[1:-1]))  # cos(theta) - cos(h)
    theta = math.acos(min(1.0, max(-1.0, math.cos(h) + delta)))
    return 2 * math.asin(-delta / (2 * math.sin(0.5 * (theta + h)))) / h


def mean_period(qs, h):
    """Mean period from the upward zero crossings, located on the cubic through the four
    samples around each crossing (Newton), so interpolation adds only O(h^4)."""
    idx = np.flatnonzero((qs[1:-2] < 0) & (qs[2:-1] >= 0)) + 1
    if idx.size < 2:
        return math.nan
    times = []
    for i in idx:
        y = qs[i - 1:i + 3]  # samples at u = -1, 0, 1, 2 (u in steps from i)
        coef = np.polyfit([-1.0, 0.0, 1.0, 2.0], y, 3)
        u = -y[1] / (y[2] - y[1])
        for _ in range(20):
            u -= np.polyval(coef, u) / np.polyval(np.polyder(coef), u)
        times.append((i + u) * h)
    return (times[-1] - times[0]) / (len(times) - 1)


def pendulum_period(amplitude):
    """Exact pendulum period 4 K(sin(a/2)) (arithmetic-geometric mean)."""
    k = math.sin(amplitude / 2)
    a, b = 1.0, math.sqrt(1 - k * k)
    for _ in range(40):
        a, b = (a + b) / 2, math.sqrt(a * b)
    return 2 * math.pi / a


def measure(name, stages, h, T):
    method = stepsafe.method(name, stages=stages)
    step = stepper(method)
    pred = stepsafe.errors(method, [h])
    rate_pred = stepsafe.errors(method, [h], "inverted").phase[0]
    rows = {}
    # harmonic oscillator (start on q: the energy extremes are sampled as the orbit turns)
    qs, es, wall, calls = run(step, 1.0, 0.0, h, T, lambda q: -q,
                              lambda q, p: 0.5 * (q * q + p * p))
    rows["osc"] = (es.max() / es.min() - 1, recurrence_phase(qs, h), wall)
    # pendulum near the bottom, amplitude 0.1
    amp = 0.1
    qs, es, wall_p, _ = run(step, amp, 0.0, h, T, lambda q: -np.sin(q),
                         lambda q, p: 0.5 * p * p - np.cos(q))
    e0 = 1 - math.cos(amp)  # energy above the bottom
    rows["pend"] = (np.abs(es - es[0]).max() / e0, pendulum_period(amp) / mean_period(qs, h) - 1,
                    wall_p)
    # pendulum near the top in x = q - pi (x'' = sin x ~ x): start on the unstable manifold
    # at 1e-12 (full relative precision), fit log x while x < 1e-6 (nonlinearity ~ 1e-13)
    x, v, t, ts, logs = 1e-12, 1e-12, 0.0, [], []
    while x < 1e-6 and t < 40.0:
        ts.append(t)
        logs.append(math.log(x))
        x, v = step(x, v, h, np.sin)
        t += h
    half = len(ts) // 2
    rate = (np.polyfit(ts[half:], logs[half:], 1)[0] - 1) if len(ts) - half > 3 else math.nan
    # explicit methods: their evaluations per step (the last kick's force is the next
    # step's first); implicit ones: the force calls their fixed-point solve made
    evaluations = method.evaluations if method.operations is not None else calls
    return method.name, evaluations, pred, rate_pred, rows, rate


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default=",".join(MAIN))
    parser.add_argument("--steps", default="0.05,0.1,0.2,0.4,0.8")
    parser.add_argument("--T", type=float, default=200.0, help="simulated time per run")
    parser.add_argument("--out", default="tradeoff.csv")
    parser.add_argument("--png", default=None)
    args = parser.parse_args(argv)
    fields = ["method", "h", "evaluations", "pred_phase", "osc_phase", "pred_energy",
              "osc_energy", "pend_phase", "pend_energy", "pred_rate", "top_rate",
              "wall_per_time_s"]
    records = []
    for item in args.methods.split(","):
        name, _, s = item.partition(":")
        for h in map(float, args.steps.split(",")):
            label, evals, pred, rate_pred, rows, rate = measure(name, int(s) if s else None,
                                                                h, args.T)
            if not np.isfinite(pred.phase[0]):
                continue  # beyond the first boundary
            records.append({
                "method": label, "h": h, "evaluations": evals,
                "pred_phase": pred.phase[0], "osc_phase": rows["osc"][1],
                "pred_energy": pred.energy[0], "osc_energy": rows["osc"][0],
                "pend_phase": rows["pend"][1], "pend_energy": rows["pend"][0],
                "pred_rate": rate_pred, "top_rate": rate, "wall_per_time_s": rows["osc"][2],
            })
            print(f"{label:16s} h={h:<5g} phase pred {pred.phase[0]: .3e} meas "
                  f"{rows['osc'][1]: .3e} | energy pred {pred.energy[0]:.3e} meas "
                  f"{rows['osc'][0]:.3e} | pendulum phase {rows['pend'][1]: .3e} | "
                  f"rate pred {rate_pred: .2e} meas {rate: .2e} | "
                  f"{rows['osc'][2] * 1e6:.0f} us per unit time")
    with open(args.out, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows(records)
    print(f"wrote {args.out}")
    if args.png:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            print("no PNG: matplotlib is not installed (pip install 'stepsafe[plot]')",
                  file=sys.stderr)
            return 0
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for label in dict.fromkeys(r["method"] for r in records):
            rs = [r for r in records if r["method"] == label]
            cost = [r["evaluations"] / r["h"] for r in rs]
            ax.loglog(cost, [abs(r["osc_phase"]) for r in rs], "o-", label=label)
        ax.set_xlabel("force evaluations per unit time (beta = 1)")
        ax.set_ylabel("|phase error| measured on the oscillator")
        ax.legend(fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        fig.savefig(args.png, dpi=110)
        print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
