"""The core commands of the ``stepsafe`` command line: methods, show, region, advise, check,
schema and validate.

Exit codes (stable, for CI scripts): 0 ok; 1 the check found an unsafe step; 2 bad input
(the tool could not answer: unknown method, malformed file, bad option); 3 internal error
(a bug: rerun with ``--debug`` for the traceback).

The group, its option types and shared options are in :mod:`.group`.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import click

from stepsafe.api import inputs, linear, reports
from stepsafe.cli.group import (
    DURATION,
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_OK,
    EXIT_UNSAFE,
    FLOAT,
    INT,
    MODEL_CHOICES,
    TIME_HELP,
    _error_line,
    _input_error,
    _problem,
    criterion_option,
    gradient_cost_option,
    impulse_of,
    main,
    method_options,
    scene_options,
)
from stepsafe.cli.output import decided
from stepsafe.cli.progressbar import progress_bar
from stepsafe.cli.report import (
    RESONANCE_CAVEAT,
    print_advice,
    print_check,
    print_json,
    print_method,
    print_methods,
    print_region,
    print_system,
    print_tsv,
)
from stepsafe.cli.thermal import (
    print_thermal_advice,
    print_thermal_check,
    thermal_keywords,
    thermal_options,
    zero_kelvin_view,
)
from stepsafe.core.regions import DEFAULT_ZMAX
from stepsafe.exceptions import StepsafeError
from stepsafe.files.yamlio import load_yaml
from stepsafe.lazy import lazy_module
from stepsafe.methods.fileformat import json_schema as method_schema
from stepsafe.methods.library import FAMILIES, builtin_names, resolve
from stepsafe.methods.residuals import residuals
from stepsafe.systems.scene import SCENE_KEYS
from stepsafe.systems.scene import json_schema as scene_schema

if TYPE_CHECKING:
    from stepsafe.api import md, schemas
    from stepsafe.cli import respa
else:
    md = lazy_module("stepsafe.api.md")  # impulse (multiple time stepping) methods only
    respa = lazy_module("stepsafe.cli.respa")
    schemas = lazy_module("stepsafe.api.schemas")  # the schema command only


@main.command("methods")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON list.")
@click.option("--tsv", is_flag=True, help="Print the table as tab-separated values.")
def methods_cmd(as_json: bool, tsv: bool) -> None:
    """List the built-in methods and families."""
    rows: list[dict[str, object]] = []
    for name in builtin_names():
        if name in FAMILIES:
            title, smallest = FAMILIES[name]
            order = "2s" if name == "gauss" else "2s-2"
            rows.append({"name": f"{name} -s N", "kind": "rk" if name == "gauss" else "prk",
                         "order": order, "stages": f"N>={smallest}",
                         "evaluations": "implicit", "force_gradients": 0, "symplectic": True,
                         "title": title, "aliases": []})
            continue
        method, entry = resolve(name)
        rows.append({"name": name, "kind": method.kind, "order": method.order,
                     "stages": method.stages, "evaluations": entry.evaluations,
                     # force-gradient terms per step, besides the forces
                     "force_gradients": method.gradient_evaluations,
                     "symplectic": residuals(method).symplectic, "title": entry.title,
                     "aliases": list(entry.aliases)})
    if as_json:
        print_json(rows)
    elif tsv:
        print_tsv(("name", "kind", "order", "stages", "evaluations", "force_gradients",
                   "symplectic", "title", "aliases"), rows)
    else:
        for row in rows:  # the table shows "forces + force gradients"
            if row["force_gradients"] and row["evaluations"] is not None:
                row["evaluations"] = f"{row['evaluations']} + {row['force_gradients']} FG"
        print_methods(rows)


@main.command("show")
@method_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def show_cmd(method: str, stages: int | None, base: str | None, as_json: bool) -> None:
    """Coefficients, order, stages and symplecticity residuals of METHOD."""
    data = inputs.method(method, stages=stages, base=base).to_dict()
    if as_json:
        print_json(data)
    else:
        coefficients = data.pop("coefficients")
        print_method(data, coefficients)


@main.command("region")
@method_options
@click.option("--model", type=click.Choice(MODEL_CHOICES), default="all", show_default=True,
              help="Test model to analyse.")
@click.option("--zmax", type=FLOAT, default=None, metavar="Z",
              help="Search z = beta*h up to Z  [default: 10].")
@click.option("--resonance-orders", default="3,4,5,6", show_default=True, metavar="N,N,...",
              help="Orders n of the nonlinear resonances n theta = 2 pi m listed for the "
                   "oscillator.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option("--verify", is_flag=True,
              help="Recompute every reported point with mpmath (40 digits); exit 3 if one is "
                   "off by more than 1e-10 relative.")
@click.option("--ratio", type=FLOAT, default=None, metavar="R",
              help="Impulse (r-RESPA) methods: the slow/fast frequency ratio omega/Omega; "
                   "steps are then Omega H (the fast frequency is 1).")
@click.option("--substeps", type=INT, default=None, metavar="K",
              help="Impulse methods: inner steps per outer drift [default: the file's].")
@criterion_option(None)
def region_cmd(method: str, stages: int | None, base: str | None, model: str,
               zmax: float | None, resonance_orders: str, as_json: bool, verify: bool,
               ratio: float | None, substeps: int | None, criterion: str) -> None:
    """Every z = beta*h interval where METHOD preserves the equilibrium's structure.

    Reports the first boundary z* (the end of the interval from 0: the largest safe
    beta*h), islands further out with their orientation, isolated resonances (e.g.
    M = -I) with the half-width float64 cannot resolve, and poles (the implicit stage
    equations are singular: no unique step). METHOD is a built-in name, a family with
    -s N, or a path to a method file. With --model all, a model the method cannot be
    applied to (a splitting whose drift and kick sums differ has no form for the saddle)
    is listed as not analysed, with the reason.

    An impulse (r-RESPA) METHOD is analysed at a frequency ratio --ratio omega/Omega:
    its unstable bands in Omega H (see stepsafe respa).
    """
    integrator = inputs.method(method, stages=stages, base=base)
    if integrator.kind == "impulse" or ratio is not None or substeps is not None:
        respa.impulse_region(integrator, ratio, substeps, zmax, criterion, as_json,
                       verify or model != "all")
        return

    orders = [item.strip() for item in resonance_orders.split(",")]
    if not all(item.isascii() and item.isdigit() and len(item) <= 3 for item in orders):
        raise _input_error(f"--resonance-orders {resonance_orders}: give integers such as "
                           "3,4,5,6")
    report = linear.region(integrator, model, zmax=DEFAULT_ZMAX if zmax is None else zmax,
                        verify=verify, resonance_orders=tuple(int(item) for item in orders),
                        criterion=criterion)
    data = report.to_dict()
    verdict = data.get("verify")
    _decide([verdict])
    if as_json:
        print_json(data)
    else:
        head = {k: data[k] for k in ("method", "title", "kind", "stages", "order", "symplectic",
                                     "criterion")}
        print_region(head, data["models"])
        if verdict:
            _print_verify(verdict)
    _exit_if_unverified(verdict)




















@main.command("advise")
@click.option("--tol-energy", type=FLOAT, default=None, metavar="T",
              help="Also require relative energy error <= T (vibrations).")
@click.option("--tol-phase", type=FLOAT, default=None, metavar="T",
              help="Also require |phase error| <= T (|growth-rate error| for saddles).")
@click.option("--every-mode", is_flag=True,
              help="List every mode or equilibrium of a system (default: the ten most "
                   "limiting when there are more).")
@click.option("--resonance-order", type=INT, default=None, metavar="N",
              help="Also keep every vibration below its first nonlinear resonance "
                   "n theta = 2 pi m of order n <= N (3 or more; Verlet: 4:1 at "
                   "beta*h = sqrt 2, 3:1 at sqrt 3). The points only: the band around "
                   "each widens with amplitude (--temperature also measures the bands); "
                   "resonances between modes are not analysed.")
@click.option("--solver", type=click.Choice(("fixed-point", "newton", "nominal")),
              default="fixed-point", show_default=True,
              help="With --tol-*: how implicit methods' evaluations per step are counted "
                   "(fixed-point iteration of the stages, which also caps h below its "
                   "convergence limit; simplified Newton; or one per stage).")
@gradient_cost_option
@criterion_option(None)
@thermal_options
@scene_options
def advise_cmd(tol_phase, tol_energy, every_mode, resonance_order, solver, criterion,
               scene_files, as_json, verify, gradient_cost, **options) -> None:
    """Safe step sizes h for your frequencies.

    Safe h keep every mode's structure: beta*h lies in the method's region for that mode's
    model. The answer is h_max, the end of the safe interval from 0, the frequency that
    limits it, and any islands of safe h beyond it (outside the primary interval).

    A scene file gives the method and either modes: (frequencies with their models) or
    system: (a stiffness/mass pair, a Gaussian's covariance or precision, a Hessian, or a
    1-dof Hamiltonian whose equilibria stepsafe finds and linearises); options on the
    command line override it. Steps are in --time-unit (else in the unit of 1/beta).

    \b
    Examples:
      stepsafe advise --method yoshida4 --beta 3.2 --inverted-beta 1.1
      stepsafe advise --method lobatto3ab -s 3 --beta 1 --json
      stepsafe advise --method verlet --wavenumber 3700 --time-unit fs --resonance-order 4
      stepsafe advise --method bcss2 --sigma 0.1 --sigma 2
      stepsafe advise scene.yaml --margin 0.8
      stepsafe advise examples/pendulum.yaml
    """
    warm = thermal_keywords(options)
    if len(scene_files) > 1:
        raise _input_error("advise takes at most one scene file")
    scene_file = scene_files[0] if scene_files else None
    impulse = impulse_of(scene_file, {**options, "verify": verify})
    if impulse is not None:
        _no_temperature(warm)
        if tol_phase is not None or tol_energy is not None:
            raise _input_error("--tol-phase/--tol-energy do not apply to impulse methods")
        data = respa.impulse_report(impulse, scene_file, options, step=None, criterion=criterion,
                              resonance_order=resonance_order, check=False)
        print_json(data) if as_json else respa.print_impulse_modes(data, check=False)
        return
    problem = _problem(scene_files[0] if scene_files else None, options, not as_json,
                       length=warm["length"])
    with progress_bar("analysis at temperature", not as_json) as progress:
        data = linear.advise(problem=problem, tol_phase=tol_phase, tol_energy=tol_energy,
                             resonance_order=resonance_order, criterion=criterion,
                             solver=solver, verify=verify, gradient_cost=gradient_cost,
                             progress=progress, **warm).to_dict()
    verdict = data.get("verify")
    _decide([verdict])
    if as_json:
        print_json(data)
    elif "thermal" in data:
        click.echo("At 0 K (the linearisation at each equilibrium):")
        print_advice(zero_kelvin_view(data))
    else:
        print_advice(data)
    if "system" in data and not as_json:
        print_system(data["system"], every_mode, data.get("time_unit"))
    if "thermal" in data and not as_json:
        print_thermal_advice(data)
    if resonance_order is not None and not as_json and "thermal" not in data:
        click.echo(RESONANCE_CAVEAT)
    if verdict and not as_json:
        _print_verify(verdict)
    _exit_if_unverified(verdict)


@main.command("check")
@click.option("--step", "--h", "h", type=DURATION, default=None, metavar="H",
              help=f"The step to check, {TIME_HELP} (--h is the same option; -h is an "
                   "error, not help).")
@click.option("--every-mode", is_flag=True,
              help="List every mode or equilibrium of a system (default: the ten most "
                   "limiting when there are more).")
@click.option("--resonance-order", type=INT, default=None, metavar="N",
              help="Also fail a vibration at or beyond its first nonlinear resonance "
                   "n theta = 2 pi m of order n <= N (3 or more). The points only: the "
                   "band around each widens with amplitude (--temperature also measures "
                   "the bands); resonances between modes are not analysed.")
@click.option("--solver", type=click.Choice(("fixed-point", "newton")), default="fixed-point",
              show_default=True,
              help="How an implicit method's stages are solved: with fixed-point iteration a "
                   "step at or beyond its convergence limit fails too (reason given); "
                   "Newton's method has no such limit.")
@click.option("--require-complete-search", is_flag=True,
              help="Fail (exit 1) when the equilibrium search of a system: hamiltonian cannot "
                   "vouch that it found every equilibrium: a walk from an equilibrium found "
                   "stopped short of an equilibrium, the box boundary or a singularity, an "
                   "equilibrium was not followed, or H could not be evaluated at a start "
                   "(the 'Search:' line says which). Without it such a search is reported, "
                   "not failed.")
@criterion_option(None)
@thermal_options
@scene_options
def check_cmd(h, every_mode, resonance_order, solver, criterion, scene_files, as_json,
              verify, require_complete_search, **options) -> None:
    """Fail (exit 1) when the step h loses some mode's structure; for CI.

    Exit 0: every mode is preserved at h (with the margin); 1: not, with the reason for
    each failing mode (model, z = beta*h, the boundary crossed, the largest safe h), or
    (with --require-complete-search) a Hamiltonian's equilibrium search that cannot vouch
    for completeness; 2: bad input or a usage error (one line on stderr). A step exactly on
    a resonance or a pole is unsafe. Every scene is analysed before anything is printed, so
    a reader that stops early (| head -1) does not change the exit code. With several
    scenes each is reported (one that cannot be checked as its error, in text and in
    --json) and the exit code is the worst: 2 if a scene could not be checked, else 1 if
    one is unsafe.

    \b
    Examples:
      stepsafe check --method verlet --step 0.1 --beta 12
      stepsafe check scene.yaml --json
    """
    warm = thermal_keywords(options)
    checks = []
    for scene_file in scene_files or (None,):
        try:
            checks.append(_check_one(scene_file, h, options, resonance_order, criterion,
                                     verify, solver, require_complete_search, not as_json,
                                     warm))
        except StepsafeError as exc:
            if not scene_files:
                raise  # the command line alone: its error is the answer
            checks.append(reports.CheckError(scene_file, exc.message, exc.where))
    suite = reports.SceneChecks(tuple(checks))
    data = suite.to_dict()
    verdicts = [entry["verify"] for entry in data["checks"] if "verify" in entry]
    failed = next((v for v in verdicts if not v["ok"]), None)
    errors = [c for c in checks if isinstance(c, reports.CheckError)]
    decided(EXIT_INTERNAL if failed else suite.exit_code,
            None if failed is None else _unverified_message(failed))
    for error in errors:
        _error_line(str(StepsafeError(error.message, error.where)))
    if as_json:
        print_json(data)
    else:
        for entry in data["checks"]:
            if "error" in entry:  # (said on stderr; beside other scenes, in its place too)
                if len(checks) > 1:
                    where = f"{entry['where']}: " if entry["where"] else ""
                    click.echo(f"{entry['scene']}: NOT CHECKED: {where}{entry['error']}")
            elif entry.get("kind") == "impulse":
                respa.print_impulse_modes(entry, check=True)
            else:
                print_check(entry)
                if entry.get("engine_runs") and entry["safe"]:
                    click.echo(f"Engine runs: {entry['engine_runs']['summary']}")
                if "system" in entry:
                    print_system(entry["system"], every_mode, entry.get("time_unit"))
                if "thermal" in entry:
                    print_thermal_check(entry)
                if "verify" in entry:
                    _print_verify(entry["verify"])
        if resonance_order is not None and any("error" not in entry for entry in
                                               data["checks"]) and not any(
                "thermal" in entry for entry in data["checks"]):
            click.echo(RESONANCE_CAVEAT)
    for verdict in verdicts:
        _exit_if_unverified(verdict)
    if suite.exit_code:
        sys.exit(suite.exit_code)


def _check_one(scene_file, h, options: dict, resonance_order, criterion: str, verify: bool,
               solver: str, require_complete_search: bool, show_progress: bool,
               warm: dict | None = None):
    """The check of one scene (or of the command line alone): an impulse method's
    :class:`~stepsafe.api.md_reports.ImpulseModesReport`, else a
    :class:`~stepsafe.api.reports.CheckReport`."""
    impulse = impulse_of(scene_file, {**options, "verify": verify})
    warm = warm or {}
    if impulse is not None:
        _no_temperature(warm)
        report = md.impulse_advice(impulse, scene=scene_file, substeps=options.get("substeps"),
                                step=h, time_unit=options["time_unit"], criterion=criterion,
                                resonance_order=resonance_order, use_scene_step=h is None)
        if report.step is None:
            raise StepsafeError("no step to check: give --step H or h: in the scene",
                                scene_file)
        return report
    problem = _problem(scene_file, options, show_progress, h, warm.get("length"))
    with progress_bar("check at temperature", show_progress) as progress:
        return linear.check(problem=problem, resonance_order=resonance_order,
                            criterion=criterion, verify=verify, solver=solver,
                            require_complete_search=require_complete_search,
                            progress=progress, **warm)


def _no_temperature(warm: dict) -> None:
    """Impulse methods have no analysis at temperature yet: refuse its options."""
    given = next((key for key, value in warm.items() if value is not None), None)
    if given is not None:
        option = {"length": "--length", "steps": "--steps", "kT": "--kT",
                  "max_drift": "--max-drift",
                  "max_failure": "--max-failure",
                  "follow_steps": "--follow-steps"}.get(given, "--temperature")
        raise _input_error(f"{option}: the analysis at temperature does not apply to "
                           "impulse (multiple time stepping) methods yet")



def _print_verify(verdict: dict) -> None:
    worst = verdict["largest_discrepancy"]
    worst_text = "not confirmed" if worst is None else f"{worst:.1e}"
    click.echo(f"verify: {verdict['points']} point(s) recomputed with mpmath at "
               f"{verdict['digits']} digits or more; largest relative discrepancy {worst_text} "
               f"({'ok' if verdict['ok'] else 'FAILED'}; allowed: {verdict['tolerance']:g} plus "
               "each point's stated uncertainty)")
    if verdict.get("conservative"):
        click.echo(f"  {verdict['conservative']} status point(s) claimed 'not preserved' next "
                   "to bands float64 cannot decide, where mpmath finds the structure "
                   "preserved: conservative, not a failure")
    for f in verdict["failed"]:
        click.echo(f"  {f['model']} {f['kind']} at {f['z']!r}: reference {f['reference']!r}",
                   err=True)


def _unverified_message(verdict: dict) -> str:
    return ("verification failed: a float answer is off by more than "
            f"{verdict['tolerance']:g} (rerun as stepsafe --debug COMMAND ... and report it)")


def _decide(verdicts, unsafe: bool = False) -> None:
    """Record the exit code before printing: a reader that closes the pipe early (``| head``)
    then gets this code, never a code made up by the write error."""
    failed = next((v for v in verdicts if v and not v["ok"]), None)
    if failed is not None:
        decided(EXIT_INTERNAL, _unverified_message(failed))
    else:
        decided(EXIT_UNSAFE if unsafe else EXIT_OK)


def _exit_if_unverified(verdict) -> None:
    if verdict and not verdict["ok"]:
        _error_line(_unverified_message(verdict))
        sys.exit(EXIT_INTERNAL)


@main.command("schema")
@click.argument("which", type=click.Choice(("method", "scene", "output")))
@click.argument("command", required=False, metavar="[COMMAND]")
def schema_cmd(which: str, command: str | None) -> None:
    """Print the JSON Schema of method files, of scene files, or (``output COMMAND``) of
    what ``stepsafe COMMAND --json`` prints."""
    if (which == "output") != (command is not None):
        raise _input_error("give a COMMAND after 'output' (stepsafe schema output hmc), and "
                           "only there")
    if command is not None:
        print_json(schemas.output_schema(command), record=False)
        return
    print_json(method_schema() if which == "method" else scene_schema(), record=False)


@main.command("validate")
@click.argument("files", nargs=-1, required=True, metavar="FILE...")
def validate_cmd(files: tuple[str, ...]) -> None:
    """Check method files against the format; warn on non-symplectic or inconsistent ones.

    Exit 0 when every file is valid (warnings allowed), 2 at the first invalid file.
    """
    lines, invalid = [], None
    for path in files:  # all files first: a reader that stops early keeps the exit code
        try:
            _not_a_scene(path)
            method, entry = resolve(path if _is_pathlike(path) else f"./{path}")
        except StepsafeError as exc:
            invalid = exc
            break
        res = residuals(method)
        lines.append(f"ok: {path}: {entry.name} ({method.kind}, order {method.order}, "
                     f"{method.stages} stages)")
        if not method.hamiltonian:
            lines.append(f"note: {path}: {method.analysis_note}")
        elif not res.symplectic_for_separable:
            lines.append(f"warning: {path}: not symplectic "
                         f"(residual {res.symplectic_separable:.3g}, beyond the "
                         f"{res.symplectic_tolerance:.3g} the written digits allow)")
        elif not res.symplectic:
            lines.append(f"warning: {path}: symplectic only for separable H "
                         f"(|b_q - b_p| = {res.weights_equal:.3g}, beyond the "
                         f"{res.weights_tolerance:.3g} the written digits allow)")
        if not res.consistent:
            lines.append(f"warning: {path}: not consistent (weight sums off by "
                         f"{res.consistency:.3g})")
        natural = method.forces_per_step
        if natural is not None and entry.evaluations not in (None, natural):
            lines.append(f"warning: {path}: evaluations: {entry.evaluations} stated, the "
                         f"coefficients make {natural} force evaluations per step (kicks, "
                         "first same as last merged)")
    if invalid is not None:
        decided(EXIT_INPUT, str(invalid))
    for line in lines:
        click.echo(line)
    if invalid is not None:
        raise invalid


def _not_a_scene(path: str) -> None:
    """A scene file given to validate (which checks method files) is named as such."""
    try:
        tree = load_yaml(path)
    except StepsafeError:
        return  # resolve reports it, naming the file
    if isinstance(tree, dict) and tree and "kind" not in tree and set(map(str, tree)) <= set(
            SCENE_KEYS):
        raise StepsafeError(f"this is a scene file (keys {', '.join(map(str, tree))}); "
                            f"validate checks method files: use 'stepsafe check {path}'", path)


def _is_pathlike(path: str) -> bool:
    return "/" in path or path.endswith((".yaml", ".yml"))
