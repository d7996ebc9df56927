"""The ``hmc`` command: acceptance, step and cost of HMC on a Gaussian target."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import click

from stepsafe.api.hmc import TargetError, TargetReport, design, hmc
from stepsafe.cli.group import (
    DURATION,
    FLOAT,
    INT,
    _input_error,
    command_line_modes,
    criterion_option,
    gradient_cost_option,
    main,
    one_format,
    target_options,
)
from stepsafe.cli.plots import plot_format, pyplot, save_figure
from stepsafe.cli.progressbar import progress_bar
from stepsafe.cli.report import _console, _lit, fmt, fmt_below, print_json, print_tsv
from stepsafe.exceptions import NotConverged, StepsafeError

#: Steps per method on the acceptance curve drawn by --plot.
PLOT_POINTS = 200


@main.command("hmc")
@click.argument("scene_file", required=False, metavar="[SCENE.yaml]")
@click.option("--methods", "names", default=None, metavar="M1,M2,...",
              help="Comma-separated methods [default: verlet, mclachlan2-min, bcss2, bcss3, "
                   "yoshida4, pefrl].")
@click.option("--all", "use_all", is_flag=True, help="Every built-in method (families s=2,3).")
@click.option("--steps", type=INT, default=None, metavar="L",
              help="Leapfrog-style steps per trajectory (fixed L).")
@click.option("--length", type=DURATION, default=None, metavar="T",
              help="Integration time per trajectory: L = max(1, floor(T/h)) as Stan's static "
                   "HMC (in the time unit, or with one: 5fs). Without --steps or --length "
                   "the acceptance is the bound over every L.")
@click.option("--jitter", type=FLOAT, default=0.0, show_default=True, metavar="J",
              help="Each step drawn uniformly from h(1-J, 1+J), L kept (Stan's "
                   "stepsize_jitter); the acceptance is averaged over it, and h at target "
                   "keeps h(1+J) within the stability (or structure) limit, so that no "
                   "jittered step is unstable.")
@click.option("--allow-unstable-jitter", is_flag=True,
              help="Search h at target up to the limit itself, as without jitter: the "
                   "longest jittered steps may then be unstable (their share is noted; "
                   "Stan reports such trajectories as divergent transitions); on a target "
                   "given by its potential, also past the onset of divergent proposals.")
@click.option("--target-accept", type=FLOAT, default=0.8, show_default=True, metavar="A",
              help="Acceptance rate to reach (Stan's adapt_delta default), for the "
                   "trajectory given (--steps or --length).")
@click.option("--target-for-every-length", is_flag=True,
              help="Reach --target-accept for every trajectory length (the bound over L), "
                   "not only for the --steps or --length given (Gaussian targets).")
@click.option("--step", "step", type=DURATION, default=None, metavar="H",
              help="Also predict the acceptance and cost at this step (in the time unit, or "
                   "with one: 0.5fs).")
@click.option("--draws", "draws_file", default=None, metavar="FILE",
              help="A target given by its potential: estimate on these draws from it (.npy "
                   "of shape (n, d) or (chains, n, d), or CSV with a header naming the "
                   "coordinates and optionally chain) instead of a warm-up run of "
                   "stepsafe's own.")
@click.option("--seed", type=INT, default=None, metavar="N",
              help="A target given by its potential: the seed of the warm-up draws and of "
                   "the estimate's momenta, stated in the output [default: 20240611]. "
                   "Refused for a Gaussian target, whose figures are exact and "
                   "deterministic (no random numbers are drawn).")
@click.option("--require-converged", is_flag=True,
              help="A target given by its potential: when the draws have not converged "
                   "(R-hat above 1.01 or an effective sample size below 400), the warm-up "
                   "diverged at its step and every refit, or the draws miss a mode found, "
                   "exit 1 before the estimates, naming why. Without it such draws "
                   "still give the report, marked unverified (no h at target is "
                   "recommended), and the exit code is 1 after it.")
@click.option("--plot", "plot_file", default=None, metavar="FILE.png",
              help="Draw the predicted acceptance against h for each method (needs "
                   "matplotlib).")
@click.option("--tsv", is_flag=True, help="Print the table as tab-separated values.")
@criterion_option("stability")
@gradient_cost_option
@target_options
def hmc_cmd(scene_file, names, use_all, steps, length, jitter, allow_unstable_jitter,
            target_accept, target_for_every_length, step, draws_file, seed, require_converged,
            plot_file, tsv, criterion, as_json, gradient_cost, **options) -> None:
    """HMC on a target: acceptance rate, step size and cost per method.

    The target: standard deviations (--sigma, unit mass), frequencies (--beta =
    1/sigma), a modes file, or a scene whose system: gives a covariance or precision
    (dense, or a Matrix Market file) and optionally a mass matrix. For each method:
    the stability limit of the fastest mode, the predicted acceptance (exact for a
    Gaussian target: 2 P(Delta < 0) of the energy error Delta, from the one-step matrix
    of every mode), the largest h whose acceptance reaches --target-accept, and the
    gradient evaluations per proposal, per accepted proposal and per accepted unit of
    simulated time. Methods are ranked by gradients per accepted proposal at the L run
    (--steps L, or --length T with L = floor(T/h)); without either, per accepted unit of
    simulated time (JSON: ranked_by). Steps are in the time unit of sigma.

    A scene whose system: gives a potential (U = -log pi, with q: names, optional
    parameters:, mass: and start:) is not Gaussian: the acceptance (with its standard
    error), the divergent share and the mean energy error are estimated on draws from
    the target (a seeded warm-up run, or --draws FILE) with each method's own
    trajectories, beside the Gaussian figures at the mode (laplace_*); it needs --steps
    or --length.

    \b
    Examples:
      stepsafe hmc --sigma 1 --sigma 0.1 --length 5
      stepsafe hmc --sigma 1 --sigma 0.1 --steps 20 --jitter 0.1 --methods verlet,bcss2
      stepsafe hmc target.yaml --all --json
      stepsafe hmc banana.yaml --steps 10 --methods verlet,bcss2
    """
    one_format(as_json, tsv)
    if use_all and names:
        raise _input_error("give --methods or --all, not both")
    arrays, labels = command_line_modes(options, scene_file, step, length)
    methods = "all" if use_all else (None if names is None else names.split(","))
    with progress_bar("hmc", not as_json) as progress, _naming_the_modes_file(options):
        try:
            report = hmc(methods, modes=arrays or None, labels=labels or None,
                         scene=scene_file, trajectory_steps=steps, length=length,
                         jitter=jitter, allow_unstable_jitter=allow_unstable_jitter,
                         target_accept=target_accept,
                         target_for_every_length=target_for_every_length,
                         step=step, criterion=criterion, time_unit=options["time_unit"],
                         zmax=options["zmax"], curve=0 if plot_file is None else PLOT_POINTS,
                         gradient_cost=gradient_cost, progress=progress, draws=draws_file,
                         seed=seed, require_converged=require_converged)
        except NotConverged as exc:
            line = NotConverged(exc.message.replace("require_converged; ", ""), exc.where)
            click.echo(f"stepsafe: {line}", err=True)
            raise SystemExit(1) from None
    data = report.to_dict()
    if isinstance(report, TargetReport):
        if as_json:
            print_json(data)
        elif tsv:
            print_tsv(("rank", "method", "evaluations", "stability_h", "h_target", "steps",
                       "acceptance", "acceptance_se", "divergent", "expected_error",
                       "gradients_per_accepted", "gradients_per_time", "laplace_acceptance",
                       "laplace_rank"), data["methods"])
        else:
            print_hmc_target(data, scene_file)
        if report.unverified is not None:
            click.echo(f"stepsafe: {report.unverified}: the estimates are unverified and h "
                       "at target is not a recommendation (draws that represent the target: "
                       "--draws FILE)", err=True)
            raise SystemExit(1)
        return
    if plot_file is not None:
        _plot(data, plot_file)
    if as_json:
        print_json(data)
    elif tsv:
        print_tsv(("rank", "method", "evaluations", "stability_h", "structure_h", "h_target",
                   "steps", "acceptance", "expected_error", "gradients_per_proposal",
                   "gradients_per_accepted", "gradients_per_time"), data["methods"])
    else:
        print_hmc(data)


def print_hmc(data: dict[str, Any]) -> None:
    from rich.table import Table

    console = _console()
    unit = data["time_unit"]
    u = f" {unit}" if unit else ""
    trajectory = (f"L = {data['steps']} steps" if data["steps"] else
                  f"T = {fmt(data['length'])}{u} (L = floor(T/h))" if data["length"] else
                  "any L (the bound over every trajectory length)")
    jitter = f", steps jittered by ±{data['jitter']:g}" if data["jitter"] else ""
    console.print(_lit(f"Gaussian target: {data['modes']} mode(s), beta from "
                       f"{fmt(data['beta_min'], 6)} to {fmt(data['beta_max'], 6)}; "
                       f"{trajectory}{jitter}; target acceptance {data['target_accept']:g}; "
                       f"criterion {data['criterion']}"))
    table = Table()
    for col in ("rank", "method", "grads/step", f"stability h{u}", f"h at target{u}", "L",
                "acceptance", "mean dH", "grads/accepted", f"grads/accepted time{u and ' unit'}"):
        table.add_column(col, overflow="fold")
    for r in data["methods"]:
        def cell(x, digits=6):
            return "-" if x is None else fmt(x, digits)

        def limit(x):  # step limits rounded towards 0: a step shown is one that keeps it
            return "-" if x is None else fmt_below(x, 6)

        stab = limit(r["stability_h"])
        if r["structure_h"] is not None and r["structure_h"] != r["stability_h"]:
            stab += f" (structure {limit(r['structure_h'])})"
        table.add_row("-" if r["rank"] is None else str(r["rank"]), r["method"],
                      "-" if r["evaluations"] is None else f"{r['evaluations']:g}", stab,
                      limit(r["h_target"]), "-" if r["steps"] is None else str(r["steps"]),
                      cell(r["acceptance"], 4), _error_cell(r["expected_error"]),
                      cell(r["gradients_per_accepted"], 5), cell(r["gradients_per_time"], 5))
    console.print(table)
    for r in data["methods"]:
        lines = [f"M = ±I within rounding at h = {fmt(h)}{u} (excluded)"
                 for h in r["resonance_h"]]
        lines += [f"L = {s['steps']} turns the mode beta = {fmt(s['beta'], 6)} by exactly "
                  f"{s['turns']} turn(s) at h = {fmt(s['h'], 6)}{u} "
                  f"({100 * s['from_target']:.2g}% from h at target): a fixed-L sampler "
                  "leaves that mode where it is; jitter by more" for s in r["stalls"]]
        lines += r["notes"]
        at = r["at_step"]
        if at:
            lines.append(f"at h = {fmt(at['h'])}{u}: acceptance {at['acceptance']:.4g}, "
                         f"mean dH = {_error_cell(at['expected_error'])}"
                         + (f", {fmt(at['gradients_per_accepted'], 5)} gradients per accepted "
                            "proposal" if at["gradients_per_accepted"] is not None else ""))
        for line in lines:
            console.print(_lit(f"{r['method']}: {line}"))
    console.print("h at target: the largest step whose acceptance reaches the target "
                  + ("for every trajectory length; the acceptance shown is for the trajectory "
                     "given. " if data["target_for_every_length"] else
                     "for the trajectory given at every step up to it. ")
                  + _ranking_line(data["ranked_by"], data["steps"], data["length"]))
    if data["jitter"]:
        console.print(_lit(
            f"Jitter: h at target keeps h(1 + {data['jitter']:g}) within the "
            f"{data['criterion']} limit, so that no jittered step is unstable"
            if not data["allow_unstable_jitter"] else
            f"Jitter: h at target may put h(1 + {data['jitter']:g}) past the "
            f"{data['criterion']} limit (--allow-unstable-jitter); the unstable share of the "
            "jittered steps is noted per method"))
    if any(r["resonance_h"] for r in data["methods"]):
        console.print(_lit(f"M = ±I within rounding: {data['rounding_gaps']} (as design "
                           "counts it)."))


def print_hmc_target(data: dict[str, Any], scene_file: str | None) -> None:
    """The text of ``stepsafe hmc`` for a target given by its potential."""
    from rich.table import Table

    console = _console()
    trajectory = (f"L = {data['steps']} steps" if data["steps"] else
                  f"T = {fmt(data['length'])} (L = floor(T/h))")
    jitter = f", steps jittered by ±{data['jitter']:g}" if data["jitter"] else ""
    console.print(_lit(f"Target U = -log pi{f' of {scene_file}' if scene_file else ''} "
                       f"(d = {data['dimension']}), not Gaussian: acceptance estimated on "
                       f"draws; {trajectory}{jitter}; target acceptance "
                       f"{data['target_accept']:g}; seed {data['seed']}"))
    d, f = data["draws"], data["frequencies"]
    if d["source"] == "warm-up":
        console.print(_lit(f"Draws: stepsafe's warm-up HMC, {d['chains']} chains x "
                           f"{d['per_chain']} (verlet, step {fmt(d['sampler_step'], 4)}, "
                           f"acceptance {d['sampler_acceptance']:.3g}, "
                           f"{d['sampler_divergent']} divergent)" + _diagnosed(d)))
    else:
        console.print(_lit(f"Draws: given, {d['chains']} chain(s) x {d['per_chain']}"
                           + _diagnosed(d)))
    q = f["omega_max_quantiles"]
    lap = data["laplace"]
    console.print(_lit(f"Stiffest frequency over {f['draws']} draws ({f['how']}): median "
                       f"{fmt(q['0.5'], 4)}, 90% {fmt(q['0.9'], 4)}, max {fmt(q['1.0'], 4)}"
                       + (f"; at the mode {fmt(lap['beta_max'], 4)}"
                          if lap and lap["beta_max"] is not None else "")
                       + (f"; {100 * f['inverted_share']:.3g}% of draws have negative "
                          "curvature" if f["inverted_share"] else "")))
    table = Table()
    for col in ("rank", "method", "stability h", "h at target", "L", "acceptance",
                "divergent", "mean dH", "grads/accepted", "Laplace acceptance",
                "Laplace rank"):
        table.add_column(col, overflow="fold")
    for r in data["methods"]:
        acc = ("-" if r["acceptance"] is None else
               f"{r['acceptance']:.3f} ± {r['acceptance_se']:.3f}")
        table.add_row("-" if r["rank"] is None else str(r["rank"]), r["method"],
                      "-" if r["stability_h"] is None else fmt_below(r["stability_h"], 4),
                      _target_cell(r["h_target"], r["capped_by"], data["verified"]),
                      "-" if r["steps"] is None else str(r["steps"]), acc,
                      _divergent_cell(r["divergent"], r.get("divergent_bound")),
                      _error_cell(r["expected_error"]),
                      "-" if r["gradients_per_accepted"] is None else
                      fmt(r["gradients_per_accepted"], 4),
                      "-" if r["laplace_acceptance"] is None else
                      f"{r['laplace_acceptance']:.3f}",
                      "-" if r["laplace_rank"] is None else str(r["laplace_rank"]))
    console.print(table)
    for r in data["methods"]:
        lines = list(r["notes"])
        on = r["divergence_onset"]
        if on is not None and on["h_divergent"] is not None and \
                r["capped_by"] != "divergence onset":  # its note states the scan's figures
            lines.append(
                f"first divergent proposals at h = {fmt(on['h_divergent'], 4)}" +
                ("" if on["h_clean"] is None else
                 f"; none of {on['proposals']} at h = {fmt(on['h_clean'], 4)} (a rate below "
                 f"{on['rate_bound_clean']:.2g} at 95%)"))
        at = r["at_step"]
        if at:
            lines.append(f"at h = {fmt(at['h'])}: acceptance {at['acceptance']:.3f} ± "
                         f"{at['acceptance_se']:.3f}, {100 * at['divergent']:.2g}% divergent"
                         + ("" if at["laplace_acceptance"] is None else
                            f" (Laplace {at['laplace_acceptance']:.3f})"))
        for line in lines:
            console.print(_lit(f"{r['method']}: {line}"))
    for note in data["notes"]:
        console.print(_lit(note))
    if not data["verified"]:
        console.print(_lit(f"UNVERIFIED: {data['unverified']}: the acceptance and its "
                           "standard error assume draws that represent the target, and h at "
                           "target is not a recommendation"))
    console.print(_lit("acceptance: E[min(1, exp(-dH))] over the draws with fresh momenta and each "
                  "method's own trajectories, ± its Monte Carlo standard error; divergent: "
                  "dH > 1000 (< x: none diverged, the rate's 95% upper bound). h at target "
                  "stays within the stiffest draw's stability limit"
                  + (" over 1 + J" if data["jitter"] and not data["allow_unstable_jitter"]
                     else "") + " and at or below the largest step scanned with no divergent "
                  "proposal (the limit that binds in brackets). "
                  + _ranking_line(data["ranked_by"], data["steps"],
                                                     data["length"])
                  + " Laplace: the Gaussian at the mode, ranked by the same criterion at its "
                  "own h at target" + ("; the ranks differ for "
                                       + ", ".join(r["method"] for r in data["ranking_differs"])
                                       if data["ranking_differs"] else
                                       "; the two rankings agree") + "."))


#: How the text table marks the limit that capped h at target (``capped_by``).
_CAPS = {"stability": "stability", "stability over 1 + J": "stability/(1+J)",
         "divergence onset": "divergences"}


def _target_cell(h: float | None, capped_by: str | None, verified: bool) -> str:
    """h at target with the limit that capped it and, for draws that fail the convergence
    diagnostics, "unverified"."""
    if h is None:
        return "-"
    tags = [t for t in (_CAPS.get(capped_by or ""), None if verified else "unverified") if t]
    return fmt_below(h, 4) + (f" ({', '.join(tags)})" if tags else "")


def _ranking_line(key: str, steps: int | None, length: float | None) -> str:
    """The sentence naming what the methods are ranked by (``ranked_by``)."""
    if key == "gradients_per_accepted":
        run = (f"L = {steps}" if steps else "L = floor(T/h) at each method's h at target"
               if length else "the L given")
        return (f"Ranked by {key}: gradient evaluations per accepted proposal at the L run "
                f"({run}).")
    return (f"Ranked by {key}: gradient evaluations per accepted unit of simulated time (no "
            "trajectory length given: --steps or --length ranks per accepted proposal).")


def _diagnosed(d: dict[str, Any]) -> str:
    """The draws' R-hat and effective sample size, when computed."""
    if d.get("rhat") is None or d.get("effective_size") is None:
        return ""
    verdict = "converged" if d["converged"] else "NOT converged"
    return (f"; R-hat {d['rhat']:.4f}, effective sample size {d['effective_size']:.4g} "
            f"({verdict})")


def _divergent_cell(share: float | None, bound: float | None) -> str:
    """The divergent share of the proposals; where none diverged, the 95% upper bound on
    the rate that measures (``< bound``), not a rate of 0."""
    if share is None:
        return "-"
    if share == 0 and bound is not None:
        return f"< {100 * bound:.2g}%"
    return f"{100 * share:.2g}%"


def _error_cell(x: float | None) -> str:
    """An expected energy error; None stands for an overflow (an unstable mode)."""
    return "overflow (unstable)" if x is None else f"{x:.3g}"


def _plot(data: dict[str, Any], output: str) -> None:
    plt = pyplot()
    fmt = plot_format(output, plt)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for row in data["methods"]:
        if row["curve"]:
            hs, rates, bounds = zip(*row["curve"])
            line, = ax.plot(hs, bounds, lw=1.6, label=row["method"])
            if data["steps"] or data["length"]:
                ax.plot(hs, rates, lw=0.6, alpha=0.6, color=line.get_color())
    ax.axhline(data["target_accept"], color="k", lw=0.8, ls="--")
    unit = f" ({data['time_unit']})" if data["time_unit"] else ""
    ax.set_xlabel(f"step h{unit}")
    ax.set_ylabel("predicted acceptance (bold: for every L)")
    ax.set_ylim(0, 1.02)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, output, fmt)


@main.command("design")
@click.argument("scene_file", required=False, metavar="[SCENE.yaml]")
@click.option("--step", "step", type=DURATION, required=True, metavar="H",
              help="The step the method will be used at (one step = STAGES gradients), in "
                   "the time unit or with one (0.5fs).")
@click.option("--stages", type=click.Choice(("2", "3")), default="2", show_default=True,
              help="2: one free coefficient b; 3: two (b, a).")
@click.option("--jitter", type=FLOAT, default=0.0, show_default=True, metavar="J",
              help="The step distribution: each step uniform in H(1-J)..H(1+J), as a "
                   "jittered sampler draws them; the objective is averaged over it.")
@click.option("--objective", type=click.Choice(("error-bound", "acceptance")),
              default="error-bound", show_default=True,
              help="error-bound: the expected energy error summed over the modes (each at "
                   "its bound over every L); acceptance: what hmc ranks by, gradients per "
                   "accepted proposal for --steps/--length (the reciprocal of the "
                   "predicted acceptance), compared with the AIA-style minimax member.")
@click.option("--steps", type=INT, default=None, metavar="L",
              help="Steps per trajectory the sampler runs (with --objective acceptance: "
                   "the L designed for; else the L of the comparison).")
@click.option("--length", type=DURATION, default=None, metavar="T",
              help="Integration time per trajectory instead of --steps: L = max(1, "
                   "floor(T/h)) (in the time unit, or with one: 5fs).")
@click.option("--name", default=None, metavar="NAME",
              help="Name in the method file [default: designed-2stage / designed-3stage].")
@click.option("-o", "--output", default=None, metavar="FILE.yaml",
              help="Write the method file here (else it is printed).")
@target_options
def design_cmd(scene_file, step, stages, jitter, objective, steps, length, name, output,
               as_json, **options) -> None:
    """Design a 2- or 3-stage HMC splitting for your Gaussian target and step.

    Chooses the free coefficient(s) of the palindromic 2- or 3-stage splitting family of
    Blanes, Casas & Sanz-Serna (2014) for the target at step H, every mode kept stable up
    to H(1+J), and writes a method file every command accepts (stepsafe hmc --methods
    FILE, region, advise, ...). The objective (--objective) is the expected energy error
    summed over the modes, or what hmc ranks by: gradient evaluations per accepted
    proposal for the trajectory given (--steps L or --length T; neither: each mode at its
    bound over L), averaged over the jitter; the latter is compared with the AIA-style
    minimax member (the smallest worst error bound up to the fastest mode's z). The
    figures compare it with verlet, bcss2, bcss3 and mclachlan2-min at the same gradient
    evaluations per unit of simulated time. The coefficients are shown to 8 digits
    (further ones change the objective by less than its rounding); the method file and
    --json carry every digit.

    \b
    Examples:
      stepsafe design --sigma 1 --sigma 0.1 --step 0.15 -o mine.yaml
      stepsafe design --sigma 1 --sigma 0.1 --step 0.15 --objective acceptance --steps 20
      stepsafe hmc --sigma 1 --sigma 0.1 --length 5 --methods mine.yaml,bcss2
    """
    arrays, labels = command_line_modes(options, scene_file, step, length)
    with _naming_the_modes_file(options):
        report = design(modes=arrays or None, labels=labels or None, scene=scene_file,
                        step=step, stages=int(stages), jitter=jitter, name=name,
                        time_unit=options["time_unit"], zmax=options["zmax"],
                        objective=objective, trajectory_steps=steps, length=length)
    data = report.to_dict()
    if output is not None:
        _write_new_text(output, report.method_file)
    if as_json:
        print_json(data)
        return
    print_design(data, output)


def _against_aia(data: dict[str, Any]) -> str:
    """The sentence comparing the designed member with the AIA-style minimax one on the
    objective (gradient evaluations per accepted proposal, or per accepted unit of time
    when no trajectory is given)."""
    rows = {r["method"]: r for r in data["comparison"]}
    ours, aia = rows[data["name"]], rows.get("aia-minimax")
    key = ("gradients_per_accepted" if ours.get("gradients_per_accepted") is not None
           else "gradients_per_time")
    what = ("gradients per accepted proposal" if key == "gradients_per_accepted" else
            "gradients per accepted unit of time")
    if aia is None:
        return (f"Objective: {what}; no AIA-style minimax member is stable up to the top of "
                "the step distribution.")
    params = ", ".join(f"{k} = {v:.6g}" for k, v in data["aia_params"].items())
    if ours[key] is None or aia[key] is None:
        return f"Objective: {what}; AIA-style minimax member: {params}."
    return (f"Objective, {what}: {data['name']} {ours[key]:.5g}, AIA-style minimax "
            f"({params}) {aia[key]:.5g}; AIA / designed = {aia[key] / ours[key]:.4g}.")


@contextmanager
def _naming_the_modes_file(options: dict) -> Iterator[None]:
    """A refusal of the target that names no file is about the --modes file when that
    file gave every frequency: it then names it."""
    only_file = options["modes_file"] and not any(
        options[key] for key in ("beta", "frequency", "wavenumber", "period", "sigma",
                                 "saddle_beta", "inverted_beta"))
    try:
        yield
    except TargetError as exc:
        if exc.where or not only_file:
            raise
        raise StepsafeError(exc.message, f"{options['modes_file']}::$.modes") from None


def _write_new_text(path: str, text: str) -> None:
    """Write ``text`` to ``path``; a failure is one line naming the path (exit 2)."""
    import os

    if os.path.isdir(path):
        raise _input_error(f"-o {path}: a directory, not a file")
    try:
        with open(path, "w", encoding="utf-8") as handle:
            handle.write(text)
    except OSError as exc:
        raise _input_error(f"-o {path}: cannot write ({exc.strerror})") from None


#: Significant digits of a designed coefficient in the text report. The objective (rho summed
#: over the modes) is flat at its minimiser b*: it grows like C (b - b*)^2 relative, C of
#: order 1e4 on the HMC guide's target, so its float64 rounding (a few 1e-16 relative) leaves
#: b* uncertain by about 1e-10 and machines whose kernels round differently print other
#: tenth digits; at 8 digits the figure's own objective is within 1e-12 of the minimum.
PARAM_DIGITS = 8


def print_design(data: dict[str, Any], output: str | None) -> None:
    from rich.table import Table

    console = _console()
    u = f" {data['time_unit']}" if data["time_unit"] else ""
    # to the digits the objective decides (PARAM_DIGITS); the method file and --json carry
    # every digit
    params = ", ".join(f"{k} = {fmt(v, PARAM_DIGITS)}" for k, v in data["params"].items())
    console.print(_lit(f"{data['name']}: {data['stages']}-stage palindromic splitting with "
                       f"{params}, designed for {data['modes']} mode(s) at h = "
                       f"{fmt(data['step'])}{u}"
                       + (" (frequencies binned for the search)" if data["binned"] else "")))
    table = Table(title="At the same gradient evaluations per unit of simulated time")
    trajectory = data.get("trajectory") or "every L"
    per_proposal = data["objective"] == "acceptance"
    columns = ["method", "grads/step", f"h{u}",
               "error bound (every L)" if trajectory == "every L" else
               f"mean dH ({trajectory})", f"acceptance ({trajectory})"]
    columns += ["L", "grads/accepted"] if per_proposal else []
    for col in columns + ["grads/accepted time unit"]:
        table.add_column(col, overflow="fold")
    for r in data["comparison"]:
        cells = [r["method"], str(r["evaluations"]), fmt(r["h"], 6),
                 _error_cell(r["error_bound"]), f"{r['acceptance']:.4f}"]
        if per_proposal:
            cells += ["-" if r["steps"] is None else str(r["steps"]),
                      "-" if r["gradients_per_accepted"] is None else
                      fmt(r["gradients_per_accepted"], 5)]
        table.add_row(*cells, "-" if r["gradients_per_time"] is None else
                      fmt(r["gradients_per_time"], 5))
    console.print(table)
    if per_proposal:
        console.print(_lit(_against_aia(data)))
    for r in data["comparison"]:
        for h in r["resonance_h"]:
            console.print(_lit(f"{r['method']}: M = ±I within rounding at h = {fmt(h)}{u} "
                               "for the fastest mode (excluded; stable past it)"))
    if any(r["resonance_h"] for r in data["comparison"]):
        console.print(_lit(f"M = ±I within rounding: {data['rounding_gaps']} (as hmc counts "
                           "it)."))
    if output:
        console.print(_lit(f"Method file written to {output}"))
    else:
        click.echo(data["method_file"], nl=False)
