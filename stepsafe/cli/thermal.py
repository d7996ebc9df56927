"""The command line's options and report of the analysis at temperature (advise and check
with ``--temperature`` or ``--kT``; see :mod:`stepsafe.api.thermal`)."""

from __future__ import annotations

from typing import Any

import click

from stepsafe.cli.group import DURATION, FLOAT, INT
from stepsafe.cli.report import fmt_above, fmt_below
from stepsafe.text import printable

#: Significant digits shown: the measured figures are statistical (their spread is stated).
DIGITS = 6


def _g(x: float | None) -> str:
    return "none" if x is None else f"{x:.{DIGITS}g}"


def _below(x: float) -> str:
    return fmt_below(x, DIGITS)


def thermal_options(func):
    """--temperature, --kT, --length, --steps, --max-drift, --max-failure and
    --follow-steps."""
    opts = [
        click.option("--follow-steps", "follow_steps", type=INT, default=None, metavar="N",
                     help="With a temperature: the most steps the thermal trajectories "
                          "follow (default 10000). A run of more steps is refused, not "
                          "judged by its first steps: raise N to follow it all (the cost "
                          "grows in proportion), or state a shorter run."),
        click.option("--max-failure", "max_failure", type=FLOAT, default=None, metavar="P",
                     help="With a temperature: the largest acceptable probability that a "
                          "run fails, from 1e-5 to 0.1. A scene's Hamiltonian: per thermal "
                          "trajectory, default 0.001; check needs none of ln(20)/P "
                          "trajectories at the step to fail (P = 0.001: 2995), advise "
                          "confirms its answer so on a fresh ensemble. An OpenMM system: per "
                          "run of the system in OpenMM (the run's length, at most 10 ps), "
                          "default 0.05; check needs none of ln(20)/P runs at the step to "
                          "fail (P = 0.05: 59), advise confirms its answer on 72 or more "
                          "fresh runs."),
        click.option("--max-drift", "max_drift", type=FLOAT, default=None, metavar="D",
                     help="With a temperature: the largest acceptable energy drift, energy "
                          "per time unit (advise lowers h until the measured drift meets "
                          "it; check fails a step whose drift does not)."),
        click.option("--steps", "run_steps", type=INT, default=None, metavar="N",
                     help="With a temperature: the run's number of steps (or --length)."),
        click.option("--length", "run_length", type=DURATION, default=None, metavar="TIME",
                     help="With a temperature: the run's simulated time, in the time unit "
                          "or with a unit (10ps): how far into the thermal tails it reaches."),
        click.option("--kT", "kT", type=FLOAT, default=None, metavar="E",
                     help="Analyse at the thermal energy E, in the system's energy unit "
                          "(a system: Hamiltonian; its minima are sampled, their resonance "
                          "bands and drift measured; an OpenMM system, kJ/mol: sampled and "
                          "run in OpenMM). 0: the 0 K answer."),
        click.option("--temperature", type=str, default=None, metavar="T",
                     help="As --kT, at T kelvin (300 or 300K), for a scene with "
                          "energy_unit: or an OpenMM system."),
    ]
    for opt in opts:
        func = opt(func)
    return func


def thermal_keywords(options: dict[str, Any]) -> dict[str, Any]:
    """The API's keywords of the options (removed from ``options``)."""
    return {"temperature": options.pop("temperature"), "kT": options.pop("kT"),
            "length": options.pop("run_length"), "steps": options.pop("run_steps"),
            "max_drift": options.pop("max_drift"), "max_failure": options.pop("max_failure"),
            "follow_steps": options.pop("follow_steps")}


def zero_kelvin_view(data: dict[str, Any]) -> dict[str, Any]:
    """The advice with its 0 K answer in place (for the 0 K report)."""
    zero = data.get("zero_kelvin")
    return data if zero is None else {**data, **zero}


def _condition(t: dict[str, Any], unit: str) -> str:
    energy = f" {t['energy_unit']}" if t.get("energy_unit") else ""
    kT = f"kT = {_g(t['kT'])}{energy}"
    if t.get("temperature") is not None:
        kT = f"T = {_g(t['temperature'])} K ({kT})"
    run = t["run"]
    length = (f"{_g(run['length'])}{unit}" if run["length"] is not None
              else f"{run['steps']:.0f} steps")
    return f"{kT}, a run of {length}"


def _from(t: dict[str, Any], u: str) -> str:
    """``0 < h``, or ``h_min <= h`` when smaller steps make runs longer than followed."""
    low = t.get("h_min")
    return "0 < h" if low is None else f"{fmt_above(low, DIGITS)}{u} <= h"


def print_thermal_advice(data: dict[str, Any]) -> None:
    """The answer at temperature under the 0 K report."""
    t = data["thermal"]
    u = f" {data['time_unit']}" if data.get("time_unit") else ""
    click.echo(f"At {_condition(t, u)}:")
    if t["harmonic"]:
        click.echo(f"  {t['notes'][0]}.")
        return
    h0 = t["h_max_0K"]
    zero = "none" if h0 is None else f"h < {_below(h0)}{u}"
    runs = t["minima"][0].get("engine_runs") if t["minima"] else None
    safe = click.style("Safe", fg="green")
    if runs is not None and not runs.get("followed", True):
        safe += f" for a run of at most {_g(runs['duration'])} ps (runs this long were followed)"
    if not t["h_max"] > 0:
        click.echo(click.style("No step confirmed safe", fg="red") + " at this temperature: "
                   + _no_step(t, u) + f" (at 0 K: {zero})")
    elif t["limited_by"] == "0 K":
        click.echo(safe + f": {_from(t, u)} < {_below(t['h_max'])}{u}, "
                   "the 0 K limit (no band or thermal frequency below it)")
    else:
        where = ("" if t["minima"] and "engine_runs" in t["minima"][0]
                 else f" at the minimum {printable(t['at'])}")
        click.echo(safe + f": {_from(t, u)} < {_below(t['h_max'])}{u}, "
                   f"limited by the {t['limited_by']}{where} (at 0 K: {zero})")
    if t.get("h_min") is not None and t["h_max"] > 0:
        click.echo(f"  (below h = {fmt_above(t['h_min'], DIGITS)}{u} the run has more than the "
                   f"{t['follow_steps']} steps followed: give --follow-steps to follow it)")
    for m in t["minima"]:
        _print_minimum(m, u, data.get("margin", 1.0))
    for note in t.get("notes", ()):
        click.echo(f"  note: {printable(note)}")
    if t["minima"] and "engine_runs" in t["minima"][0]:
        click.echo(f"  Reproducible: seeds stated; {_ENGINE_REPRODUCIBLE}.")
        return
    click.echo(f"  Reproducible: every draw seeded ({t['seed']}); the failure criterion: "
               + (t["minima"][0]["scans"][0]["failure"] if t["minima"] and
                  t["minima"][0]["scans"] else "none") + ".")


def _no_step(t: dict[str, Any], u: str) -> str:
    """Why no step is safe at temperature: the lowest step tried and what failed there."""
    for m in t["minima"]:
        if m["h_max"] is not None and m["h_max"] > 0:
            continue
        at = ("" if "engine_runs" in m else f" at the minimum {printable(m['at'])}")
        c = m.get("confirmation")
        if c is not None and c.get("rejected"):
            low = min(r["h"] for r in c["rejected"])
            return (f"a fresh ensemble lost trajectories at every step tried{at}, down to "
                    f"h = {_g(low)}{u}")
        first = [sc["h_range"][0] for sc in m["scans"]
                 if sc["bands"] and sc["bands"][0]["lower"] is None]
        if first:
            return (f"the thermal trajectories fail from the scan's first step h = "
                    f"{_g(min(first))}{u}{at} on; smaller steps were not scanned")
        return f"{m['limited_by']}{at}"
    return t["limited_by"]


#: How an engine's runs are reproduced.
_ENGINE_REPRODUCIBLE = ("the engine's runs are on its CPU platform with one thread, the same "
                        "on one machine")


def _seeds(seeds: list[int]) -> str:
    """``1, 2, 3`` for up to three seeds; runs of consecutive ones as ``4-75``."""
    parts: list[str] = []
    start = prev = None
    for k in seeds:
        if prev is not None and k == prev + 1:
            prev = k
            continue
        if start is not None:
            parts.append(_span(start, prev))
        start = prev = k
    if start is not None:
        parts.append(_span(start, prev))
    return ", ".join(parts)


def _span(a: Any, b: Any) -> str:
    if a == b:
        return str(a)
    return f"{a}, {b}" if b == a + 1 else (f"{a}, {a + 1}, {b}" if b == a + 2 else f"{a}-{b}")


def _print_engine_runs(r: dict[str, Any], u: str, indent: str) -> None:
    """The runs of the user's integrator in the engine: what they are, each step run, and
    the drift where they passed."""
    click.echo(f"{indent}runs of {r['integrator']} in {r['engine']} at {_g(r['temperature'])} "
               f"K: {_g(r['duration'])} ps each after {_g(r['thermalisation'])} ps of "
               f"thermalisation; a step fails when a seed blows up (non-finite energy, or "
               + (f"the total energy moves by more than {_g(r['energy_bound'])} n_dof kT) "
                  f"or the mean drift exceeds {_g(r['drift_tolerance'])} kT/ps per degree "
                  "of freedom" if r["integrator"] == "verlet" else
                  f"the kinetic energy exceeds its mean by more than "
                  f"{_g(r['energy_bound'])} n_dof kT)"))
    if "max_failure" in r:
        click.echo(f"{indent}a step passes when no run fails in {r['check_runs']} fresh seeds "
                   f"(check) or {', '.join(map(str, r['confirmation_runs']))} "
                   f"(advise's confirmations, stopping at the first failure): the failure "
                   f"probability of one run of {_g(r['duration'])} ps below "
                   f"{_g(r['max_failure'])} at {r['confidence']:.0%} confidence"
                   + ("" if r["followed"] else
                      f" (the run's {_g(r['run_length'])} ps are not followed to their end)"))
    for t in r["trials"]:
        blown = [x for x in t["runs"] if x["blew_up"]]
        how = "; ".join(f"seed {x['seed']} by step {x['step']}" if x["step"] is not None
                        else f"seed {x['seed']}: {x['reason']}" for x in blown)
        drift = "" if t["drift"] is None else (", drift" + (" of the others" if blown else "")
                                                + f" {t['drift']:.2g}") + (
            "" if t["drift_error"] is None else f" +- {t['drift_error']:.1g}")
        ran = len(t["seeds"])
        planned = t.get("planned_seeds", ran)
        of = f"; {ran} of {planned} run, stopped at the first failure" if ran < planned else ""
        bound = "" if t.get("upper") is None else (
            f"; failure probability of a run < {t['upper']:.2g} at "
            f"{t['confidence']:.1%} confidence")
        click.echo(f"{indent}  h = {_g(t['h'])}{u} ({t['stage']}; seeds "
                   f"{_seeds(t['seeds'])}{of}): {t['verdict']}" + (f" ({how})" if how else "")
                   + drift + bound)
    if r.get("h_clear") is not None:
        fail = "" if r["h_fail"] is None else f", fail at {_g(r['h_fail'])}{u}"
        drift = "" if r["drift"] is None else (
            f"; drift there {r['drift']:.2g}" + ("" if r["drift_error"] is None else
                                                 f" +- {r['drift_error']:.1g}")
            + " kT/ps per degree of freedom")
        click.echo(f"{indent}passed up to h = {_g(r['h_clear'])}{u} in every seed "
                   f"({_seeds(r['confirmed_seeds'])}){fail}{drift}")


def _print_minimum(m: dict[str, Any], u: str, margin: float) -> None:
    what = printable(m["at"]) if "engine_runs" in m else f"minimum at {printable(m['at'])}"
    limit = (f"h < {_below(m['h_max'])}{u}" if m["h_max"] is not None and m["h_max"] > 0
             else "no step confirmed")
    click.echo(f"  {what}: {limit} ({m['limited_by']})")
    f = m["frequencies"]
    if f is not None:
        click.echo(f"    largest frequency over {f['frames']} thermal frames "
                   f"({f['sampling']['how']}): median {_g(f['median'])}, maximum "
                   f"{_g(f['maximum'])}; a run of {f['run_frames']:.3g} frames reaches "
                   f"{_g(f['run_quantile'])} ({_g(f['upper'])} at {f['confidence']:.0%} "
                   f"confidence; {f['extrapolation']})")
        click.echo(f"    linear limit at temperature h < {_below(m['h_linear'])}{u} "
                   f"(0 K: {_below(m['h_zero'])}{u})")
    for sc in m["scans"]:
        for b in sc["bands"]:
            lo = b["lower"]
            edge = ("below the scan" if lo is None else
                    f"from h = {_g(lo['clear'])}{u}" + (
                        f" +- {_g(lo['uncertainty'])}" if lo["uncertainty"] is not None
                        else " (edge uncertainty not measured)"))
            what = ("band" if b["peak"] > sc["threshold"] else
                    "steps with failures observed")
            click.echo(f"    {what} {b['name']} {edge}, peak failure fraction "
                       f"{b['peak']:.2g} ({sc['target']}: {sc['trajectories']} trajectories "
                       f"x {sc['steps']} steps, scanned h in [{_g(sc['h_range'][0])}, "
                       f"{_g(sc['h_range'][1])}]{u})")
        if not sc["bands"]:
            click.echo(f"    no band in h = [{_g(sc['h_range'][0])}, {_g(sc['h_range'][1])}]"
                       f"{u} ({sc['target']}: {sc['trajectories']} trajectories x "
                       f"{sc['steps']} steps)")
    c = m.get("confirmation")
    if c is not None and c["h"] > 0:
        click.echo(f"    confirmed at h = {_g(c['h'])}{u} on a fresh ensemble (seed "
                   f"{c['seed']}): {c['failures']} of {c['trajectories']} trajectories "
                   f"failed in {c['steps']} steps, failure probability below "
                   f"{c['upper']:.2g} at {c['confidence']:.0%} confidence (max_failure "
                   f"{c['max_failure']:g})")
    elif c is not None:
        click.echo(f"    no step confirmed on a fresh ensemble (seed {c['seed']}, "
                   f"{c['trajectories']} trajectories)")
    _print_drift(m.get("drift"), u, "    ")
    if "engine_runs" in m:
        _print_engine_runs(m["engine_runs"], u, "    ")
    for note in m["notes"]:
        click.echo(f"    note: {printable(note)}")


def _print_drift(d: dict[str, Any] | None, u: str, indent: str) -> None:
    if d is None:
        return
    per = f"/{u.strip()}" if u else " per time unit"
    if d["failed"]:
        rate = "not bounded (trajectories failed; the survivors' slope is no drift)"
    elif d["rate"] is None or d["error"] is None:
        rate = "not finite in float64"
    else:
        rate = f"{d['rate']:.3g} +- {d['error']:.2g} energy{per}"
    fluct = "" if d["fluctuation"] is None else f"fluctuation {d['fluctuation']:.3g}; "
    click.echo(f"{indent}drift at h = {_g(d['h'])}{u}: {rate} ({fluct}{d['failed']} of "
               f"{d['trajectories']} trajectories failed in {d['steps']} steps)")


def print_thermal_check(entry: dict[str, Any]) -> None:
    """The check at temperature under the 0 K verdict."""
    t = entry["thermal"]
    u = f" {entry['time_unit']}" if entry.get("time_unit") else ""
    verdict = (click.style("SAFE", fg="green") if t["safe"]
               else click.style("UNSAFE", fg="red"))
    click.echo(f"At {_condition(t, u)}: {verdict}")
    if t["harmonic"]:
        click.echo(f"  {t['notes'][0]}.")
        return
    for reason in t["reasons"]:
        click.echo(f"  {printable(reason)}")
    for m in t["minima"]:
        f = m["frequencies"]
        lim = "" if m["h_linear"] is None else \
            f"; linear limit at temperature h < {_below(m['h_linear'])}{u}"
        what = printable(m["at"]) if "engine_runs" in m else f"minimum at {printable(m['at'])}"
        click.echo(f"  {what}: 0 K limit h < "
                   f"{_below(m['h_zero'])}{u}{lim}")
        if f is not None:
            click.echo(f"    (a run of {f['run_frames']:.3g} frames reaches frequency "
                       f"{_g(f['run_quantile'])}, {_g(f['upper'])} at "
                       f"{f['confidence']:.0%} confidence; {f['extrapolation']})")
        for p in m["probes"]:
            click.echo(f"    {p['target']} at h: {p['failures']} of {p['trajectories']} "
                       f"trajectories failed in {p['steps']} steps ({p['verdict']}; failure "
                       f"probability {p['lower']:.2g} to {p['upper']:.2g} at "
                       f"{t['confidence']:.0%} confidence, max_failure "
                       f"{p['max_failure']:g})")
        _print_drift(m.get("drift"), u, "    ")
        if "engine_runs" in m:
            _print_engine_runs(m["engine_runs"], u, "    ")
    for note in t.get("notes", ()):
        click.echo(f"  note: {printable(note)}")
    if t["minima"] and "engine_runs" in t["minima"][0]:
        click.echo(f"  Reproducible: seeds stated; {_ENGINE_REPRODUCIBLE}.")
        return
    click.echo(f"  Reproducible: every draw seeded ({t['seed']}).")
