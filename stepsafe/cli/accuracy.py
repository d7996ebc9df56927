"""Commands on accuracy and cost: ``error``, ``compare`` and ``plot``.

Registered on the group of :mod:`stepsafe.cli.group` when :mod:`stepsafe.cli` is imported.
"""

from __future__ import annotations

import dataclasses

import click

from stepsafe.api import inputs, linear
from stepsafe.api.md import impulse_method
from stepsafe.cli.group import (
    FLOAT,
    INT,
    _input_error,
    command_line_modes,
    criterion_option,
    frequency_options,
    gradient_cost_option,
    main,
    method_options,
    one_format,
)
from stepsafe.cli.measure import measured_ranking, print_measured_ranking, work_precision_plot
from stepsafe.cli.plots import plot_format, pyplot, save_figure
from stepsafe.cli.report import print_compare, print_errors, print_json, print_tsv
from stepsafe.cli.respa import draw_chart

MODEL_ONE = click.Choice(("oscillator", "saddle", "inverted", "saddle-p"))
MAX_POINTS = 100_000  # error --n: a table, not a sweep (bounded time and memory)


@main.command("error")
@method_options
@click.option("--z", "zs", type=FLOAT, multiple=True, metavar="Z", help="z = beta*h; repeatable.")
@click.option("--zmin", type=FLOAT, default=None, help="Range start (with --zmax and --n).")
@click.option("--zmax", type=FLOAT, default=None, help="Range end.")
@click.option("--n", "count", type=INT, default=11, show_default=True,
              help=f"Range points (at most {MAX_POINTS}).")
@click.option("--model", type=MODEL_ONE, default="oscillator", show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--tsv", is_flag=True,
              help="Print the table as tab-separated values (z, phase_error, energy_error, "
                   "overflow; empty where not preserved).")
def error_cmd(method, stages, base, zs, zmin, zmax, count, model, as_json, tsv) -> None:
    """Error figures of METHOD at given z = beta*h.

    oscillator: phase error theta/z - 1 (theta the rotation per step) and the relative
    energy error bound kappa - 1 from the invariant ellipse of M; saddle/inverted: the
    growth-rate error log(mu)/z - 1. "not preserved" (null in JSON) where the step does
    not preserve the structure; "overflow" (null, with "overflow": true) where M(z) is too
    large for float64 to evaluate the errors (entries beyond 1e150).

    \b
    Examples:
      stepsafe error verlet --z 0.1 --z 1
      stepsafe error yoshida4 --zmin 1e-6 --zmax 1.5 --n 7 --json
    """
    import numpy as np

    one_format(as_json, tsv)
    z = list(zs)
    if zmin is not None or zmax is not None:
        if zmin is None or zmax is None or count < 2:
            raise _input_error("a range needs --zmin, --zmax and --n >= 2")
        if count > MAX_POINTS:
            raise _input_error(f"--n {count}: at most {MAX_POINTS} points")
        if not (0 < zmin < zmax) or not np.isfinite(zmax):
            raise _input_error(f"need 0 < zmin < zmax (finite), got {zmin}, {zmax}")
        z += list(np.geomspace(zmin, zmax, count) if zmax / zmin > 100
                  else np.linspace(zmin, zmax, count))
    if not z:
        raise _input_error("give --z Z (repeatable) or --zmin/--zmax/--n")
    for value in z:
        if not (np.isfinite(value) and value > 0):
            raise _input_error(f"z must be a positive finite number, got {value}")
    data = linear.errors(inputs.method(method, stages=stages, base=base), z, model).to_dict()
    if as_json:
        print_json(data)
    elif tsv:
        print_tsv(("z", "phase_error", "energy_error", "overflow"), data["rows"])
    else:
        print_errors(data)


@main.command("compare")
@click.option("--methods", "names", default=None, metavar="M1,M2,...",
              help="Comma-separated methods (family members as gauss:2) [default: a standard "
                   "set].")
@click.option("--all", "use_all", is_flag=True, help="Every built-in method (families s=2,3).")
@click.option("--tol-phase", type=FLOAT, default=None, metavar="T",
              help="Largest |phase error| (|growth-rate error| for saddles and barriers).")
@click.option("--tol-energy", type=FLOAT, default=None, metavar="T",
              help="Largest relative energy error (vibrations).")
@click.option("--solver", type=click.Choice(("best", "fixed-point", "newton", "nominal")),
              default="best", show_default=True,
              help="How implicit methods are costed: best, the cheaper of the two solvers "
                   "at the step each allows (the table says which); fixed-point, force "
                   "evaluations of fixed-point iteration of their stages (Gauss-Seidel "
                   "order) to 1e-14 at the step used, which also caps h below its "
                   "convergence limit; newton, simplified Newton's method, its force "
                   "evaluations plus --jacobian-cost per Jacobian; nominal, one per stage.")
@click.option("--jacobian-cost", type=FLOAT, default=1.0, show_default=True, metavar="R",
              help="Newton's method: one Jacobian (the Hessian at the step's start and the "
                   "factorisation of the stage system) in force evaluations. 1 suits a few "
                   "degrees of freedom; a dense Hessian of d dof costs about d gradients.")
@click.option("--measure", "measure_scene", default=None, metavar="SCENE.yaml",
              help="Also run each method on the scene's nonlinear system (steps chosen as "
                   "plot --work-precision does) and say how far the linear ranking is from "
                   "the measured one, at the trajectory error the phase tolerance gives "
                   "over --time.")
@click.option("--time", "duration", type=FLOAT, default=None, metavar="T",
              help="--measure: integrate up to T [default: 100 periods of the vibration "
                   "the start orbits].")
@click.option("--initial", default=None, metavar="Q,P",
              help="--measure: the initial condition (as for stepsafe measure).")
@click.option("--budget", type=FLOAT, default=None, metavar="SECONDS",
              help="--measure: the seconds all the runs may take [default: 45].")
@click.option("--tsv", is_flag=True, help="Print the table as tab-separated values.")
@criterion_option()
@gradient_cost_option
@frequency_options
def compare_cmd(names, use_all, tol_phase, tol_energy, solver, jacobian_cost, measure_scene,
                duration, initial, budget, tsv, criterion, as_json, gradient_cost,
                **options) -> None:
    """Rank methods by cost per unit of simulated time for your frequencies.

    For each method: the first boundary, the largest safe h, the h that meets the
    tolerance, evaluations per step and the cost evaluations/h at the usable step
    min(safe, accurate); ranked by cost (cheapest first). Implicit methods cost what the
    cheaper of two stage solvers costs at the step it allows: fixed-point iteration
    (Gauss-Seidel order), whose step stays below 0.9 of its convergence limit (bound by
    "solver"), or simplified Newton's method with its Jacobians counted. Steps are in the
    time unit of 1/beta.

    \b
    Examples:
      stepsafe compare --beta 3.2 --tol-phase 1e-6
      stepsafe compare --beta 1 --tol-energy 1e-4 --methods verlet,pefrl,yoshida4,bcss2
      stepsafe compare --beta 1 --tol-phase 1e-6 --tol-energy 1e-6 --methods pefrl,gauss:2
    """
    one_format(as_json, tsv)
    if use_all and names:
        raise _input_error("give --methods or --all, not both")
    arrays, _ = command_line_modes(options)
    methods = "all" if use_all else (None if names is None else names.split(","))
    margin = options["margin"]
    report = linear.compare(methods, modes=arrays, tol_phase=tol_phase, tol_energy=tol_energy,
                            margin=1.0 if margin is None else margin, zmax=options["zmax"],
                            time_unit=options["time_unit"], solver=solver,
                            criterion=criterion, gradient_cost=gradient_cost,
                            jacobian_cost=jacobian_cost)
    data = report.to_dict()
    if measure_scene is None and (duration is not None or initial is not None
                                  or budget is not None):
        raise _input_error("--time, --initial and --budget apply to --measure SCENE")
    if measure_scene is not None:
        if tol_phase is None:
            raise _input_error("--measure needs --tol-phase (the trajectory error it gives "
                               "over --time is the measured tolerance)")
        vibrations = arrays.get("oscillator")
        if vibrations is None or not len(vibrations):
            raise _input_error("--measure needs the vibrations compared (--beta, ...)")
        measured = measured_ranking(data, measure_scene, tol_phase, float(max(vibrations)),
                                    duration, initial, budget)
        data = dataclasses.replace(report, measured=measured).to_dict()
    if as_json:
        print_json(data)
    elif tsv:
        print_tsv(("rank", "method", "implicit", "first_boundary", "h_max", "h_tol", "h",
                   "bound_by", "evaluations", "solver", "solver_iterations", "jacobians",
                   "cost"), data["methods"])
    else:
        print_compare(data)
        if "measured" in data:
            print_measured_ranking(data["measured"])


@main.command("plot")
@method_options(required=False)
@click.option("--model", type=MODEL_ONE, default="oscillator", show_default=True)
@click.option("--zmax", type=FLOAT, default=None, metavar="Z", help="Plot z up to Z [default: 6].")
@click.option("--phase", "with_phase", is_flag=True, help="Add the phase error (log scale).")
@click.option("-o", "--output", default=None, metavar="FILE.png",
              help="Where to write: exactly this path; its extension picks the format (png, "
                   "pdf, svg, eps, ...; an unknown or missing extension is refused) "
                   "[default: METHOD-MODEL.png in the current folder].")
@click.option("--ratio", type=FLOAT, default=None, metavar="R",
              help="Impulse (r-RESPA) methods: draw the ray of this ratio omega/Omega.")
@click.option("--substeps", type=INT, default=None, metavar="K",
              help="Impulse methods: inner steps per outer drift [default: the file's].")
@click.option("--work-precision", "scene_file", default=None, metavar="SCENE.yaml",
              help="Instead: measured error against force evaluations per unit time on the "
                   "scene's system, one curve per method of --methods (see stepsafe "
                   "measure).")
@click.option("--methods", default=None, metavar="M1,M2,...",
              help="--work-precision: the methods (family members as gauss:2).")
@click.option("--h-range", default=None, metavar="LO,HI,N",
              help="--work-precision: N steps spaced evenly in log h from LO to HI "
                   "[default: chosen per method, from just inside its first boundary, "
                   "halving h until the error reaches the reference's floor or the budget "
                   "runs out].")
@click.option("--budget", type=FLOAT, default=None, metavar="SECONDS",
              help="--work-precision: the whole diagram's time, shared by the methods "
                   "[default: 45].")
@click.option("--cost", type=click.Choice(("evaluations", "seconds")), default="evaluations",
              show_default=True,
              help="--work-precision: the cost axis, force evaluations or wall-clock seconds "
                   "per unit time.")
@click.option("--time", "duration", type=FLOAT, default=None, metavar="T",
              help="--work-precision: integrate up to T [default: 100 periods].")
@click.option("--error", "which", type=click.Choice(("trajectory", "energy")),
              default="trajectory", show_default=True,
              help="--work-precision: the measured error drawn.")
@click.option("--initial", default=None, metavar="Q,P",
              help="--work-precision: the initial condition (as for stepsafe measure).")
def plot_cmd(method, stages, base, model, zmax, with_phase, output, ratio, substeps,
             scene_file, methods, h_range, budget, cost, duration, which, initial) -> None:
    """Draw tr M(z)/2 with the band [-1, 1] and the preserved intervals (needs matplotlib).

    The file is written at exactly the path given, in the format its extension names; no
    extension is ever added. Without -o it is METHOD-MODEL.png (e.g. verlet-oscillator.png).

    For an impulse (r-RESPA) METHOD the stability chart in the plane (Omega H, omega H) is
    drawn instead (METHOD-chart.png), with the ray of --ratio when given.

    With --work-precision SCENE (no METHOD) it draws the measured error of each method of
    --methods against its force evaluations (or --cost seconds) per unit time on the
    scene's own system, one point per step of --h-range, or steps chosen per method within
    --budget seconds (default file: work-precision.png).

    \b
    Examples:
      stepsafe plot lobatto3ab -s 3 -o lobatto3.png --phase
      stepsafe plot --work-precision examples/pendulum.yaml --methods verlet,pefrl,gauss:2 \\
          --h-range 0.05,1,8
      stepsafe plot --work-precision examples/pendulum.yaml --methods verlet,pefrl \\
          --budget 20
    """
    import math
    import warnings

    if scene_file is not None or methods is not None or h_range is not None \
            or initial is not None or budget is not None:
        if method is not None:
            raise _input_error("give METHOD or --work-precision SCENE --methods M1,M2, not both")
        if scene_file is None or methods is None:
            raise _input_error("--work-precision needs SCENE and --methods M1,M2,...")
        if h_range is not None and budget is not None:
            raise _input_error("give --h-range or --budget, not both")
        work_precision_plot(scene_file, methods, h_range, duration, which,
                            output or "work-precision.png", initial, budget, cost)
        return
    if method is None:
        raise _input_error("missing METHOD (or --work-precision SCENE); see 'stepsafe plot "
                           "--help'")

    # the arguments are checked before matplotlib is looked for
    zmax_given = zmax is not None
    zmax = 6.0 if zmax is None else zmax
    if not (math.isfinite(zmax) and zmax > 0):
        raise _input_error(f"zmax must be a positive finite number, got {zmax}")
    plt = pyplot()
    import numpy as np

    integrator = inputs.method(method, stages=stages, base=base)
    if integrator.kind == "impulse" or ratio is not None or substeps is not None:
        if integrator.kind != "impulse":
            raise _input_error(f"--ratio and --substeps apply to impulse methods; "
                               f"{integrator.name} is a {integrator.kind} method")
        if model != "oscillator" or with_phase or zmax_given:
            raise _input_error("--model, --zmax and --phase do not apply to the stability "
                               "chart of an impulse method")
        if ratio is not None and not (math.isfinite(ratio) and ratio >= 0):
            raise _input_error(f"--ratio must be a finite number >= 0, got {ratio}")
        draw_chart(impulse_method(integrator, None, substeps), ratio,
                   output or f"{integrator.name}-chart.png")
        return
    if output is None:
        safe_name = "".join(c if c.isalnum() or c in "-_." else "_" for c in integrator.name)
        output = f"{safe_name}-{model}.png"
    fmt = plot_format(output, plt)
    region = linear.region(integrator, model, zmax=zmax).regions[model]
    z = np.linspace(zmax / 4000, zmax, 4000)
    M = linear.transfer_matrices(integrator, z, model)
    with np.errstate(all="ignore"):  # overflow far out is drawn clipped, not warned about
        half = 0.5 * (M[:, 0, 0] + M[:, 1, 1])
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        # matplotlib's tick locator overflows on axes out to 1e308: cosmetic, not a result
        warnings.simplefilter("ignore")
        fig = _draw(plt, integrator, model, region, z, half, zmax, with_phase)
    save_figure(fig, output, fmt)
    click.echo(f"wrote {output}")


def _draw(plt, integrator, model, region, z, half, zmax, with_phase):
    import numpy as np

    rows = 2 if with_phase else 1
    fig, axes = plt.subplots(rows, 1, figsize=(8, 3.2 * rows), sharex=True, squeeze=False)
    ax = axes[0, 0]
    ax.axhspan(-1, 1, color="0.9", label="|tr M|/2 < 1")
    ax.plot(z, np.clip(half, -3, 3), lw=1.2, label="tr M / 2 (clipped to ±3)")
    for iv in region.intervals:
        ax.axvspan(iv.lo, iv.hi if iv.hi is not None else zmax, color="tab:green", alpha=0.15)
    for p in region.resonances:
        ax.axvline(p.z, color="tab:orange", ls="--", lw=0.8)
    for p in region.poles:
        ax.axvline(p.z, color="tab:red", ls=":", lw=0.8)
    ax.set_ylim(-3, 3)
    ax.set_title(f"{integrator.name}, {model}: preserved z = beta*h shaded green")
    ax.legend(loc="lower left", fontsize=8)
    if with_phase:
        e = linear.errors(integrator, z, model)
        axes[1, 0].semilogy(z, np.abs(e.phase), lw=1.2)
        axes[1, 0].set_ylabel("|phase error|" if model == "oscillator" else "|rate error|")
    axes[-1, 0].set_xlabel("z = beta h")
    fig.tight_layout()
    return fig






