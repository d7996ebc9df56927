"""The ``measure`` command: the method run on the scene's own system, beside the linear
prediction."""

from __future__ import annotations

import math
from typing import Any

import click

from stepsafe.api import inputs
from stepsafe.api.measure import DEFAULT_SEED, cost_at, measure, refine, work_precision
from stepsafe.cli.group import (
    DURATION,
    FLOAT,
    INT,
    TIME_HELP,
    TIME_UNIT_NAMES,
    _input_error,
    main,
    method_options_optional,
    one_format,
)
from stepsafe.cli.plots import plot_format, pyplot, save_figure
from stepsafe.cli.progressbar import progress_bar
from stepsafe.cli.report import print_json, print_tsv
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.scene import load_scene, parse_real, time_unit_in_force

#: Step sizes of --h-range at most.
MAX_RANGE = 200
#: Methods in one work-precision diagram at most.
MAX_METHODS = 20


def _numbers(text: str, option: str) -> list[float]:
    """Comma-separated plain numbers (``1e-3,0.1,8``)."""
    values = [parse_real(item) for item in text.split(",")]
    if any(v is None for v in values):
        raise _input_error(f"--{option} {text}: give plain numbers separated by commas")
    return [float(v) for v in values if v is not None]


def _range(text: str) -> list[float]:
    """``LO,HI,N``: N steps spaced evenly in log h from LO to HI."""
    import numpy as np

    values = _numbers(text, "h-range")
    if len(values) != 3 or not values[2] == int(values[2]) or not 1 <= values[2] <= MAX_RANGE:
        raise _input_error(f"--h-range {text}: give LO,HI,N with N from 1 to {MAX_RANGE}")
    lo, hi, n = values[0], values[1], int(values[2])
    if not (0 < lo <= hi < float("inf")):
        raise _input_error(f"--h-range {text}: need 0 < LO <= HI")
    return [float(h) for h in np.geomspace(lo, hi, n)]


@main.command("measure")
@click.argument("scene_file", metavar="SCENE.yaml")
@method_options_optional
@click.option("--h", "steps", type=DURATION, multiple=True, metavar="H",
              help=f"A step size to run (repeatable), {TIME_HELP}.")
@click.option("--h-range", default=None, metavar="LO,HI,N",
              help="N step sizes spaced evenly in log h from LO to HI.")
@click.option("--time", "duration", type=DURATION, default=None, metavar="T",
              help="Integrate up to T, in the time unit or with one (60fs) [default: 100 "
                   "periods of the vibration the start orbits].")
@click.option("--initial", default=None, metavar="Q,P",
              help="Initial condition: q then p (1-dof: two numbers; linear systems: 2n) "
                   "[default: 1-dof, a tenth of the box from the elliptic equilibrium; "
                   "linear, q from a fixed pseudo-random draw (seed 0), p = 0].")
@click.option("--energy", type=FLOAT, default=None, metavar="E",
              help="1-dof: start at the elliptic equilibrium with the momentum that gives "
                   "this energy H.")
@click.option("--time-unit", type=click.Choice(TIME_UNIT_NAMES), default=None,
              help="The unit of h and T (stated in the output).")
@click.option("--tol-energy", type=FLOAT, default=None, metavar="T",
              help="Instead of given steps: find the largest h whose measured energy spread "
                   "is at most T (bisection on runs, from the linear prediction).")
@click.option("--tol-trajectory", type=FLOAT, default=None, metavar="T",
              help="Instead of given steps: the largest h whose measured trajectory error at "
                   "the time T is at most this.")
@click.option("--solver", type=click.Choice(("fixed-point", "newton")), default="fixed-point",
              show_default=True,
              help="How implicit methods solve their stages: fixed-point iteration, or "
                   "simplified Newton (the Jacobian from the Hessian at each step's start).")
@click.option("--max-steps", type=INT, default=None, metavar="N",
              help="Refuse runs of more than N steps [default: 2000000].")
@click.option("--budget", type=FLOAT, default=None, metavar="SECONDS",
              help="Stop after SECONDS: the run under way reports 'budget', the rest "
                   "'not run'.")
@click.option("--ensemble", type=INT, default=None, metavar="N",
              help="Run N trajectories at once (splitting methods), drawn around the "
                   "elliptic equilibrium on the energy shell --energy E or at --kT E, and "
                   "report the distribution of their largest energy errors.")
@click.option("--kT", "kT", type=FLOAT, default=None, metavar="E",
              help="With --ensemble: draw the trajectories from the Boltzmann distribution "
                   "of the equilibrium's quadratic model at this temperature (energy units).")
@click.option("--seed", type=INT, default=None, metavar="S",
              help="With --ensemble: the seed of the draw [default: 0; printed].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--tsv", is_flag=True, help="Print the rows as tab-separated values.")
def measure_cmd(scene_file, method, stages, base, steps, h_range, duration, initial, energy,
                time_unit, tol_energy, tol_trajectory, solver, max_steps, budget, ensemble,
                kT, seed, as_json, tsv) -> None:
    """Run the method on the scene's own system and measure what each h buys and costs.

    The scene's system: (a Hamiltonian expression in q and p, or with named variables for
    n degrees of freedom, or a linear system) is integrated at each step h for a time T.
    Measured: the spread of the energy over every step of the run (relative to the energy
    above the equilibrium the start orbits), the energy drift per unit time (the
    least-squares slope through every step, relative in the same way), the trajectory
    error at T against a reference (the exact flow for linear
    systems, an adaptive 8th-order run at tolerance 1e-13 for expressions: errors below
    about 1e-13 are that run's own) in the energy norm of that equilibrium, force
    evaluations per unit time as counted (implicit methods with their solver's
    iterations) and whether the run stayed bounded. Beside them: the linear model's
    prediction for the vibration the start orbits and the ratio measured / predicted, the
    nonlinear calibration of `advise --tol-...`.

    With --ensemble N it runs N trajectories at once instead, drawn
    with --seed around the elliptic equilibrium: on the energy shell --energy E (every
    phase; H = E in the equilibrium's quadratic model) or at the temperature --kT E, and
    prints the median, 90% and 99% quantiles and maximum over the trajectories of each
    one's largest energy error |H_k - H_0| / |H_0 - H_e| over every step.

    With --tol-energy or --tol-trajectory it refines instead: the largest h (within the
    safe steps) whose measured error meets the tolerance, by bisection on runs started
    from the h the linear model predicts (what advise --tol-* would give), both printed.

    \b
    Examples:
      stepsafe measure examples/pendulum.yaml --h 0.1 --h 0.5
      stepsafe measure examples/pendulum.yaml --method pefrl --tol-trajectory 1e-4 --time 60
      stepsafe measure examples/pendulum.yaml --method yoshida4 --h-range 0.05,1,6 --energy 0
      stepsafe measure examples/pendulum.yaml --h 0.5 --time 50 --ensemble 1000 --kT 0.2
    """
    one_format(as_json, tsv)
    hs = list(steps) + (_range(h_range) if h_range else [])
    time_unit = time_unit_in_force(time_unit, scene_file, hs, duration)
    loaded = load_scene(scene_file, time_unit)
    if method is None:
        if loaded.method is None:
            raise _input_error("no method: give --method METHOD or method: in the scene")
        try:
            integrator = inputs.method(loaded.method.name,
                                    stages=stages or loaded.method.stages,
                                    base=base or loaded.method.base)
        except StepsafeError as exc:
            raise StepsafeError(exc.message, exc.where or f"{scene_file}::$.method") from None
    else:
        integrator = inputs.method(method, stages=stages, base=base)
    start = None if initial is None else _numbers(initial, "initial")
    if ensemble is None and (kT is not None or seed is not None):
        raise _input_error("--kT and --seed draw an ensemble: give --ensemble N")
    if ensemble is not None:
        if tol_energy is not None or tol_trajectory is not None or tsv or \
                initial is not None or budget is not None or solver != "fixed-point":
            raise _input_error("--ensemble draws its own starts: give no --initial, "
                               "--tol-*, --tsv, --budget or --solver")
        if energy is not None and kT is not None:
            raise _input_error("--ensemble: give --energy E (a shell) or --kT E (a "
                               "temperature), not both")
        if not 1 <= ensemble:
            raise _input_error(f"--ensemble {ensemble}: give a number of trajectories >= 1")
        with progress_bar("measuring", not as_json) as progress:
            result = measure(integrator, hs or ([loaded.h] if loaded.h else []),
                             scene=scene_file, time=duration, energy=energy,
                             time_unit=loaded.time_unit, progress=progress,
                             ensemble=ensemble, kT=kT,
                             seed=DEFAULT_SEED if seed is None else seed,
                             **({} if max_steps is None else {"max_steps": max_steps}))
        if as_json:
            print_json(result.to_dict())
        else:
            print_ensemble(result.to_dict())
        return
    if tol_energy is not None or tol_trajectory is not None:
        if tol_energy is not None and tol_trajectory is not None:
            raise _input_error("give --tol-energy or --tol-trajectory, not both")
        if hs or tsv or max_steps is not None or budget is not None:
            raise _input_error("--tol-* finds the step itself: give no --h, --h-range, --tsv, "
                               "--max-steps or --budget")
        quantity, tol = (("energy", tol_energy) if tol_energy is not None
                         else ("trajectory", tol_trajectory))
        with progress_bar("refining", not as_json) as progress:
            result = refine(integrator, quantity, tol, scene=scene_file, time=duration,
                            initial=start, energy=energy, time_unit=loaded.time_unit,
                            solver=solver, progress=progress)
        if as_json:
            print_json(result.to_dict())
        else:
            print_measure(result.runs.to_dict())
            print_refinement(result.to_dict())
        return
    with progress_bar("measuring", not (as_json or tsv)) as progress:
        report = measure(integrator, hs or ([loaded.h] if loaded.h else []), scene=scene_file,
                         time=duration, initial=start, energy=energy,
                         time_unit=loaded.time_unit, solver=solver, budget=budget,
                         progress=progress, **({} if max_steps is None
                                               else {"max_steps": max_steps}))
    data = report.to_dict()
    if as_json:
        print_json(data)
    elif tsv:
        print_tsv(tuple(data["rows"][0]), data["rows"])
    else:
        print_measure(data)


def print_measure(data: dict[str, Any]) -> None:
    """The text form of :meth:`stepsafe.api.measure_reports.MeasureReport.to_dict`."""
    unit = data["time_unit"] or "time unit"

    def g(x: float | None, digits: int = 3) -> str:
        return "-" if x is None else f"{x:.{digits}g}"

    beta = data["beta"]
    click.echo(f"{data['method']} on {data['system']}, from (q, p) = "
               f"({', '.join(f'{x:.6g}' for x in data['initial'])}), energy "
               f"{data['energy']:.6g}")
    click.echo("Prediction: the linear model of the vibration the start orbits"
               + (f" (beta = {beta:.6g} rad/{unit})" if beta else " (none: no vibration)")
               + f"; reference: {data['reference']}.")
    floors = [r["reference_error"] for r in data["rows"] if r.get("reference_error") is not None]
    if floors:
        click.echo(f"The reference's own error at T (relative, as the trajectory errors): "
                   f"{min(floors):.2g}" + (f" to {max(floors):.2g}" if max(floors) > min(floors)
                                           else "")
                   + "; a trajectory error below it prints as < that floor.")

    def trajectory(r: dict[str, Any]) -> str:
        if r.get("below_reference"):
            return f"<{r['reference_error']:.2g}"
        return g(r["trajectory_error"])

    click.echo(f"{'h':>10} {'steps':>8} {'evals/' + unit:>12}  {'energy err':>10} "
               f"{'predicted':>9} {'ratio':>6}  {'drift/' + unit:>10}  {'traj err':>9} "
               f"{'predicted':>9} {'ratio':>6}  status")
    for r in data["rows"]:
        click.echo(f"{r['h']:>10.4g} {r['steps']:>8} {g(r['evaluations_per_time'], 4):>12}  "
                   f"{g(r['energy_error']):>10} {g(r['predicted_energy_error']):>9} "
                   f"{g(r['energy_ratio'], 2):>6}  {g(r['energy_drift'], 2):>10}  "
                   f"{trajectory(r):>9} {g(r['predicted_trajectory_error']):>9} "
                   f"{g(r['trajectory_ratio'], 2):>6}  {r['status']}"
                   + (f" ({r['iterations_per_step']:.3g} solver iterations per step"
                      + (f", {r['jacobians_per_time']:.4g} Hessians per {unit}"
                         if r.get("jacobians_per_time") else "") + ")"
                      if r["iterations_per_step"] else "")
                   + (f" ({r['gradients_per_time']:.4g} force gradients per {unit})"
                      if r.get("gradients_per_time") else ""))
    fitted = [r for r in data["rows"] if r.get("energy_behaviour")]
    if fitted:
        click.echo("Against time (least-squares line through every step; a drift when it "
                   "explains half the variance or more, else a bounded oscillation):")
    for r in fitted:
        parts = [f"energy {r['energy_behaviour']} (R2 {r['energy_r2']:.2f})"]
        for inv in r.get("invariants", ()):
            parts.append(f"{inv['name']} spread {g(inv['spread'])}, drift "
                         f"{g(inv['drift'], 2)}/{unit}, {inv['behaviour']} "
                         f"(R2 {inv['r2']:.2f})" if inv['r2'] is not None else "")
        click.echo(f"{r['h']:>10.4g}  " + "; ".join(parts))


def print_ensemble(data: dict[str, Any]) -> None:
    """The text form of :meth:`stepsafe.api.measure_reports.EnsembleReport.to_dict`."""
    def g(x: float | None) -> str:
        return "inf" if x is None else f"{x:.3g}"

    centre = ", ".join(f"{x:.6g}" for x in data["centre"])
    draw = (f"on the energy shell H = {data['energy']:.6g} of its quadratic model (every "
            f"phase)" if data["draw"] == "shell" else
            f"from the Boltzmann distribution of its quadratic model at kT = {data['kT']:.6g}")
    click.echo(f"{data['method']} on {data['system']}: {data['ensemble']} trajectories drawn "
               f"around the equilibrium ({centre}) (H = {data['centre_energy']:.6g}) {draw}; "
               f"seed {data['seed']}.")
    click.echo("Each trajectory's largest energy error |H_k - H_0| / |H_0 - H_e| over every "
               "step, across the trajectories:")
    click.echo(f"{'h':>10} {'steps':>8}  {'median':>9} {'90%':>9} {'99%':>9} {'max':>9}  "
               "unstable")
    for r in data["rows"]:
        click.echo(f"{r['h']:>10.4g} {r['steps']:>8}  {g(r['median']):>9} {g(r['q90']):>9} "
                   f"{g(r['q99']):>9} {g(r['max']):>9}  {r['unstable']}")


#: Seconds of a work-precision diagram with steps chosen per method, by default.
WORK_PRECISION_BUDGET = 45.0


def work_precision_plot(scene_file: str, methods: str, h_range: str | None,
                        duration: float | None, which: str, output: str,
                        initial: str | None = None, budget: float | None = None,
                        cost: str = "evaluations") -> None:
    """Measure every method at every step of the range (or at steps chosen per method
    within the budget: :func:`stepsafe.api.measure.work_precision`); draw error against
    cost."""
    hs = None if h_range is None else _range(h_range)
    names = [item.strip() for item in methods.split(",") if item.strip()]
    if not names or len(names) > MAX_METHODS:
        raise _input_error(f"--methods {methods}: give 1 to {MAX_METHODS} names separated by "
                           "commas")
    integrators = [inputs.named_method(name) for name in names]
    start = None if initial is None else _numbers(initial, "initial")
    plt = pyplot()
    fmt = plot_format(output, plt)
    reports = []
    with progress_bar("measuring") as progress:
        if hs is None:
            reports = list(work_precision(
                integrators, scene=scene_file, time=duration, initial=start,
                budget=WORK_PRECISION_BUDGET if budget is None else budget,
                error=which, progress=progress))
        else:
            for k, integrator in enumerate(integrators):
                def part(f: float, k=k) -> None:
                    if progress:
                        progress((k + f) / len(integrators))

                reports.append(measure(integrator, hs, scene=scene_file, time=duration,
                                       initial=start, progress=part))
    key = "trajectory_error" if which == "trajectory" else "energy_error"
    axis = "evaluations_per_time" if cost == "evaluations" else "seconds_per_time"
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for report in reports:
        points = [(getattr(r, axis), getattr(r, key)) for r in report.rows
                  if getattr(r, key) and getattr(r, axis)]
        if points:
            x, y = zip(*points)
            ax.loglog(x, y, marker="o", ms=3, lw=1, label=report.method)
    floors = [r.reference_error for report in reports for r in report.rows
              if r.reference_error is not None]
    if floors and which == "trajectory":
        ax.axhline(max(floors), color="0.5", lw=0.8, ls="--", label="reference's floor")
    ax.set_xlabel("force evaluations per unit time (measured)" if cost == "evaluations"
                  else "wall-clock seconds per unit time (measured)")
    ax.set_ylabel("trajectory error at T (relative)" if which == "trajectory"
                  else "energy spread (max - min) / min")
    ax.set_title(f"work-precision on {reports[0].system}")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, output, fmt)
    click.echo(f"wrote {output}")
    for report in reports:
        usable = [r for r in report.rows if getattr(r, key) is not None]
        click.echo(f"  {report.method}: {len(usable)} points"
                   + (f", h from {min(r.h for r in usable):.4g} to {max(r.h for r in usable):.4g}"
                      if usable else ""))


def print_refinement(data: dict[str, Any]) -> None:
    """The text form of :meth:`stepsafe.api.measure_reports.Refinement.to_dict`."""
    unit = data["runs"]["time_unit"]
    u = f" {unit}" if unit else ""
    what = "energy spread" if data["quantity"] == "energy" else "trajectory error"
    vibration = data["h_safe"] is not None
    predicted = "none" if data["predicted_h"] is None else f"{data['predicted_h']:.6g}{u}"
    model = (f"the linear model predicted h = {predicted}" if vibration else
             "no linear prediction: the start orbits no vibration, the search began at "
             "T / 1000")
    if data["h"] is None:
        if data["limited_by"] == "reference":
            floor = min(r["reference_error"] for r in data["runs"]["rows"]
                        if r.get("below_reference"))
            click.echo(f"The {what} tolerance {data['tol']:g} is below the reference's own "
                       f"error ({floor:.2g}): no run can show it met ({model}).")
            return
        click.echo(f"No step meets {what} <= {data['tol']:g} in the runs made ({model}).")
        return
    tail = {"tolerance": "", "unreachable": "", "reference": "", "time": ", up to the run time",
            "safety": "" if not vibration else
            f", up to the safe limit {data['h_safe']:.6g}{u}"}[data["limited_by"]]
    ratio = "" if data["predicted_h"] is None else \
        f" ({data['h'] / data['predicted_h']:.3g} times the prediction)"
    at = (f"below the reference's floor {data['error']:.3g}" if data.get("below_reference")
          else f"at {data['error']:.3g}")
    click.echo(f"Measured: h = {data['h']:.6g}{u} keeps the {what} {at} <= "
               f"{data['tol']:g}{tail}; {model}{ratio}; "
               f"{len(data['runs']['rows'])} runs.")


def measured_ranking(data: dict[str, Any], scene_file: str, tol_phase: float, beta: float,
                     duration: float | None, initial: str | None, budget: float | None
                     ) -> dict[str, Any]:
    """Each compared method's measured cost on the scene's system at the trajectory error
    ``2 sin(tol_phase beta T / 2)`` (the phase drift the linear model allows over T, beta
    the largest vibration compared), from its :func:`stepsafe.api.measure.work_precision`
    curve, beside the cost ``compare`` predicts; ratios to the linear ranking's first."""
    start = None if initial is None else _numbers(initial, "initial")
    rows = [r for r in data["methods"] if r["cost"] is not None]
    if not rows:
        raise _input_error("--measure: no compared method has a predicted cost")
    names = [r["method"] for r in rows]
    integrators = [inputs.named_method(name) for name in names]
    with progress_bar("measuring") as progress:
        reports = work_precision(integrators, scene=scene_file, time=duration,
                                 initial=start, progress=progress,
                                 budget=WORK_PRECISION_BUDGET if budget is None else budget)
    T = next((row.time for report in reports for row in report.rows), None)
    if T is None:
        raise _input_error("--measure: no run finished within the budget")
    tol = 2 * math.sin(min(tol_phase * beta * T, math.pi) / 2)
    measured = {name: cost_at(report, tol) for name, report in zip(names, reports)}
    first = names[0]
    base, base_measured = float(rows[0]["cost"]), measured[first]
    out = []
    for r in rows:
        m = measured[r["method"]]
        out.append({"method": r["method"], "predicted_cost": r["cost"], "measured_cost": m,
                    "predicted_ratio": float(r["cost"]) / base,
                    "measured_ratio": (None if m is None or base_measured is None
                                       else m / base_measured)})
    order = sorted((o for o in out if o["measured_cost"] is not None),
                   key=lambda o: o["measured_cost"])
    return {"scene": scene_file, "time": T, "tolerance": tol, "first": first,
            "methods": out, "measured_order": [o["method"] for o in order]}


def print_measured_ranking(data: dict[str, Any]) -> None:
    """The text form of :func:`measured_ranking`."""
    click.echo(f"Measured on {data['scene']} (trajectory error <= {data['tolerance']:.3g} at "
               f"T = {data['time']:.6g}; costs interpolated between runs), each relative "
               f"to {data['first']}, the linear ranking's first:")
    for o in data["methods"]:
        measured = "not reached" if o["measured_cost"] is None else \
            f"{o['measured_cost']:.4g}"
        ratio = "-" if o["measured_ratio"] is None else f"{o['measured_ratio']:.3g}"
        click.echo(f"  {o['method']}: cost predicted {o['predicted_cost']:.4g}, measured "
                   f"{measured}; {o['method']}/{data['first']} predicted "
                   f"{o['predicted_ratio']:.3g}, measured {ratio}")
    click.echo("Measured order: " + (", ".join(data["measured_order"]) or "none reached"))
