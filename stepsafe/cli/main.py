"""The ``stepsafe`` command line.

Exit codes (stable, for CI scripts): 0 ok; 1 the check found an unsafe step; 2 bad input
(the tool could not answer: unknown method, malformed file, bad option); 3 internal error
(a bug: rerun with ``--debug`` for the traceback).

Only click is imported at start-up; each command imports what it uses.
"""

from __future__ import annotations

import sys

import click

from stepsafe import __version__
from stepsafe.units import TIME_UNITS

EXIT_OK, EXIT_UNSAFE, EXIT_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
EXIT_INTERRUPTED = 130
MODEL_CHOICES = ("oscillator", "saddle", "inverted", "saddle-p", "all")
TIME_UNIT_NAMES = tuple(TIME_UNITS)
PROG = "stepsafe"


class _Number(click.ParamType):
    """An int or float option written in ASCII: click's own types accept other scripts'
    digits (``-s ٣`` read as 3) and ``1_0`` (read as 10)."""

    def __init__(self, kind: type) -> None:
        self.kind = kind
        self.name = "integer" if kind is int else "float"

    def convert(self, value, param, ctx):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return self.kind(value)  # a default given in the code
        text = str(value).strip()
        try:
            if not text.isascii() or "_" in text:
                raise ValueError(text)
            return self.kind(text)
        except ValueError:
            shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
            self.fail(f"{shown} is not a valid {self.name} (ASCII digits 0-9)", param, ctx)


class _Beta(_Number):
    """--beta: a plain number (rad per time unit); a value with a unit is pointed to the
    option that takes it."""

    def __init__(self) -> None:
        super().__init__(float)

    def convert(self, value, param, ctx):
        from stepsafe.exceptions import StepsafeError
        from stepsafe.units import parse_quantity

        try:
            _, unit = parse_quantity(str(value))
        except StepsafeError:
            unit = None
        if unit is not None:
            form = ("--wavenumber" if unit == "cm-1" else "--period" if unit in TIME_UNIT_NAMES
                    else "--frequency")
            self.fail(f"{value!r}: --beta is a plain number in rad per time unit; for a "
                      f"value in {unit} use {form} with --time-unit (e.g. --wavenumber 3700 "
                      "--time-unit fs)", param, ctx)
        return super().convert(value, param, ctx)


class _Duration(_Number):
    """A time (a step, a run or trajectory time): a plain number in the time unit, or a
    number with a time unit (``0.5fs``, ``'0.5 fs'``, ``2e-15s``), kept as text for the API
    to convert exactly to the time unit in force (:func:`stepsafe.units.duration`)."""

    def __init__(self) -> None:
        super().__init__(float)
        self.name = "time"

    def convert(self, value, param, ctx):
        from stepsafe.exceptions import StepsafeError
        from stepsafe.units import parse_quantity

        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        try:
            _, unit = parse_quantity(str(value))
        except StepsafeError:
            unit = None
        if unit is None:
            return super().convert(value, param, ctx)
        if unit not in TIME_UNIT_NAMES:
            self.fail(f"{value!r} is not a time: {unit} is not a time unit (give a number in "
                      f"the time unit, or one with {', '.join(TIME_UNIT_NAMES)})", param, ctx)
        return str(value).strip()


INT, FLOAT, BETA, DURATION = _Number(int), _Number(float), _Beta(), _Duration()
#: What the help of an option that takes a time says about its unit.
TIME_HELP = ("in --time-unit (else the time unit of 1/beta), or with a unit, converted: "
             "0.5fs, '0.5 fs', 2e-15s")


class _Group(click.Group):
    """Owns every exit path: one-line errors with the documented exit codes.

    Usage errors (unknown option or command, bad choice, missing argument, a bare
    ``stepsafe``) are one line on stderr and exit 2, never click's multi-line Usage block.
    ``-h`` is not a help alias (``--help`` is): on ``check`` it would read as the step.
    """

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True,
             **extra):
        if not standalone_mode:  # for embedding: click's behaviour, exceptions propagate
            return super().main(args, prog_name or PROG, complete_var, False, **extra)
        # shell completion (_STEPSAFE_COMPLETE=bash_source stepsafe): click answers and exits
        self._main_shell_completion(extra, prog_name or PROG, complete_var)
        args = sys.argv[1:] if args is None else list(args)
        sys.exit(self._run(args, extra))

    def _run(self, args: list[str], extra: dict) -> int:
        from stepsafe.cli import output

        output.reset()
        try:
            try:
                with self.make_context(PROG, args, **extra) as ctx:
                    self.invoke(ctx)
                code = EXIT_OK
            except click.exceptions.Exit as exc:
                code = exc.exit_code
            except SystemExit as exc:
                code = _system_exit_code(exc)
            output.flush()
        except click.UsageError as exc:
            _error_line(_usage_message(exc, self, args))
            return EXIT_INPUT
        except click.ClickException as exc:  # e.g. a file click could not open: bad input
            _error_line(exc.format_message())
            return EXIT_INPUT
        except (click.exceptions.Abort, KeyboardInterrupt, EOFError):
            _error_line("interrupted")
            return EXIT_INTERRUPTED
        except OSError as exc:
            if not output.is_output_error(exc):
                raise
            return output.failed(exc, _error_line)
        return code

    def invoke(self, ctx: click.Context):
        import warnings

        from stepsafe.exceptions import StepsafeError

        debug = "--debug" in sys.argv[1:] or bool(ctx.params.get("debug"))
        try:
            with warnings.catch_warnings():
                # overflow far out is handled (a limit, or an error naming it), never printed:
                # a warning line would break --json and the one-line error contract
                if not debug:
                    warnings.simplefilter("ignore", RuntimeWarning)
                return super().invoke(ctx)
        except StepsafeError as exc:
            if debug:
                raise
            _error_line(str(exc))
            ctx.exit(EXIT_INPUT)
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise
        except Exception as exc:  # noqa: BLE001 - the documented internal-error path
            from stepsafe.cli.output import is_output_error

            if debug or is_output_error(exc):  # a closed pipe or a full disk: see _run
                raise
            message = str(exc).splitlines()[0] if str(exc) else ""
            _error_line(f"internal error: {type(exc).__name__}: {message} "
                        "(rerun as stepsafe --debug COMMAND ... for the traceback)",
                        prefix="stepsafe: ")
            ctx.exit(EXIT_INTERNAL)


def _system_exit_code(exc: SystemExit) -> int:
    if exc.code is None:
        return EXIT_OK
    if isinstance(exc.code, int):
        return exc.code
    _error_line(str(exc.code))
    return EXIT_INTERNAL


def _error_line(message: str, prefix: str = "stepsafe: error: ") -> None:
    """One line on stderr, control characters made visible (the message may quote a file)."""
    from stepsafe.text import printable

    try:
        click.echo(prefix + printable(" ".join(message.split())), err=True)
    except (OSError, ValueError, AttributeError):  # stderr closed or full: the code tells
        pass


def _usage_message(exc: click.UsageError, group: click.Group, args: list[str]) -> str:
    ctx = exc.ctx
    command = ctx.command if ctx is not None else None
    if command is None:  # some parser errors carry no context: name the command given
        name = next((a for a in args if a in group.commands), None)
        command = group.commands[name] if name else group
    where = PROG if command is group else f"{PROG} {command.name}"
    takes_step = any(p.name == "h" for p in command.params)
    if isinstance(exc, click.NoSuchOption) and exc.option_name in ("-h", "-H", "--H"):
        message = (f"{exc.option_name} is not an option: write the step as --step H; "
                   "for help use --help") if takes_step else \
            f"{exc.option_name} is not an option: for help use --help"
    elif isinstance(exc, click.exceptions.NoArgsIsHelpError) or (
            command is group and exc.message == "Missing command."):
        message = f"missing command (one of: {', '.join(sorted(group.commands))})"
    else:
        message = exc.format_message().rstrip(".")
    return f"{message} (see '{where} --help')"


@click.group(cls=_Group, context_settings={"help_option_names": ["--help"]})
@click.version_option(__version__, prog_name="stepsafe")
@click.option("--debug", is_flag=True, help="Show tracebacks instead of one-line errors.")
def main(debug: bool) -> None:
    """Step sizes that keep the type of an equilibrium under a symplectic integrator.

    For a method and a linear test model, z = beta*h decides whether the discrete map keeps
    a centre a centre (model 'oscillator': q'=p, p'=-beta^2 q), a saddle a saddle ('saddle':
    H = beta p q) or a barrier top unstable in the right direction ('inverted': q'=p,
    p'=+beta^2 q).

    \b
    Examples:
      stepsafe methods
      stepsafe region verlet
      stepsafe region lobatto3ab -s 3 --model oscillator --zmax 6
      stepsafe region yoshida4 --base midpoint --model saddle --json

    Exit codes: 0 ok, 1 unsafe (check), 2 bad input, a usage error or output that cannot
    be written (one line on stderr), 3 internal error. Help is --help only (-h is an
    error, never help); 'stepsafe' without a command is a usage error.
    """


def criterion_option(default: str | None = "structure"):
    """``--criterion``: what a safe step must keep (see stepsafe.core.regions.CRITERIA);
    ``default`` None: the method's own (structure, or stability for a Langevin splitting)."""
    return click.option(
        "--criterion", type=click.Choice(("structure", "stability")), default=default,
        show_default=default is not None,
        help="structure: the flow's type and orientation are kept (a centre stays a centre "
             "turning the same way); stability: the type only, |tr M| <= 2 for vibrations "
             "(the stability interval of the HMC literature; bcss3 reaches 4.66 instead of "
             "2.98). Where the other criterion gives other safe steps, both are printed."
             + ("" if default is not None else
                "  [default: structure; stability for a Langevin splitting, the only one "
                "that applies to it]"))


def gradient_cost_option(func):
    """``--gradient-cost``: force evaluations one force-gradient term costs."""
    return click.option(
        "--gradient-cost", type=FLOAT, default=1.0, show_default=True, metavar="R",
        help="Force-gradient methods: the cost of one force-gradient term (a Hessian-vector "
             "product) in force evaluations; a step costs its forces plus R per term. 1: "
             "reverse-mode AD forms V''(q) v at about the cost of one more gradient "
             "(Hessian-free methods count their displaced force as a force).")(func)


def method_options(func=None, *, required: bool = True):
    """METHOD argument with -s/--stages and --base (``required=False``: METHOD may be
    omitted, for commands with another mode)."""
    if func is None:
        return lambda f: method_options(f, required=required)
    func = click.option("--base", metavar="NAME",
                        help="Swap the base method of a composition (e.g. midpoint, or "
                             "gauss:2 for a family member).")(func)
    func = click.option("-s", "--stages", type=INT, metavar="N",
                        help="Stage count for the families gauss (N>=1) and "
                             "lobatto3ab (N>=2).")(func)
    return click.argument("method", metavar="METHOD" if required else "[METHOD]",
                          required=required, shell_complete=_complete_method)(func)


def method_options_optional(func):
    """--method METHOD (default: the scene's) with -s/--stages and --base."""
    func = click.option("--base", metavar="NAME",
                        help="Swap the base method of a composition.")(func)
    func = click.option("-s", "--stages", type=INT, metavar="N",
                        help="Stage count for the families gauss and lobatto3ab.")(func)
    return click.option("--method", "method", default=None, metavar="METHOD",
                        shell_complete=_complete_method,
                        help="Built-in name, family (with -s) or method file [default: the "
                             "scene's method:].")(func)


def _complete_method(ctx, param, incomplete: str) -> list:
    """Shell completion of METHOD: built-in names and aliases, then method files."""
    from click.shell_completion import CompletionItem

    from stepsafe.methods.library import builtin_names

    if "/" in incomplete or incomplete.endswith((".yaml", ".yml")):
        return [CompletionItem(incomplete, type="file")]
    return [CompletionItem(name) for name in builtin_names() if name.startswith(incomplete)]


@main.command("methods")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON list.")
@click.option("--tsv", is_flag=True, help="Print the table as tab-separated values.")
def methods_cmd(as_json: bool, tsv: bool) -> None:
    """List the built-in methods and families."""
    from stepsafe.cli.report import print_json, print_methods, print_tsv
    from stepsafe.methods.library import FAMILIES, builtin_names, resolve
    from stepsafe.methods.residuals import residuals

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
    from stepsafe.api import inputs
    from stepsafe.cli.report import print_json, print_method

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
    from stepsafe.api import inputs, linear
    from stepsafe.cli.report import print_json, print_region
    from stepsafe.core.regions import DEFAULT_ZMAX

    integrator = inputs.method(method, stages=stages, base=base)
    if integrator.kind == "impulse" or ratio is not None or substeps is not None:
        from stepsafe.cli.respa import impulse_region

        impulse_region(integrator, ratio, substeps, zmax, criterion, as_json,
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


def frequency_options(func):
    """Frequencies, margin, zmax and --json: the options of every command that analyses
    frequencies (advise, check, compare)."""
    func = click.option("--margin", type=FLOAT, default=None, metavar="F",
                        help="0 < F <= 1: allow every frequency to be up to 1/F times larger "
                             "(scales h_max by F) [default: 1].")(func)
    return target_options(func)


def target_options(func):
    """The frequencies (in every form), zmax, the time unit and --json, without a margin
    (hmc and design predict for the frequencies as given)."""
    opts = [
        click.option("--json", "as_json", is_flag=True, help="Print one JSON object."),
        click.option("--zmax", type=FLOAT, default=None, metavar="Z",
                     help="Analyse z = beta*h up to Z (islands beyond are not reported) "
                          "[default: 10]."),
        click.option("--modes", "modes_file", type=str, default=None, metavar="FILE",
                     help="Frequencies from a YAML list of {beta:, model:[, label:]} (or a "
                          "scene file's modes:, in its time_unit:) or a CSV file with "
                          "columns beta[,model][,label]."),
        click.option("--inverted-beta", type=FLOAT, multiple=True, metavar="R",
                     help="Rate of a barrier top (q'=p, p'=+R^2 q); repeatable."),
        click.option("--saddle-beta", type=FLOAT, multiple=True, metavar="R",
                     help="Rate of a saddle (H = R p q); repeatable."),
        click.option("--time-unit", type=click.Choice(TIME_UNIT_NAMES), default=None,
                     help="The unit of h (in and out); frequencies become rad per unit "
                          "[default: the time unit of 1/beta]."),
        click.option("--period", multiple=True, metavar="T",
                     help="Period of a vibration: T in the time unit, or with a unit "
                          "('9fs', which also names the time unit when none is given); "
                          "repeatable."),
        click.option("--wavenumber", multiple=True, metavar="K",
                     help="Wavenumber of a vibration in cm-1 (needs --time-unit); "
                          "repeatable."),
        click.option("--frequency", multiple=True, metavar="F",
                     help="Frequency of a vibration: cycles per time unit, or with a unit "
                          "('100THz', '3ps-1'); repeatable."),
        click.option("--sigma", multiple=True, metavar="S",
                     help="Standard deviation of a Gaussian target (HMC, unit mass): "
                          "beta = 1/S; repeatable."),
        click.option("--beta", type=BETA, multiple=True, metavar="B",
                     help="Angular frequency of a vibration (q'=p, p'=-B^2 q), rad per "
                          "time unit; repeatable."),
    ]
    for opt in opts:
        func = opt(func)
    return func


def _thermal_options(func):
    """--temperature, --kT, --length, --steps (:mod:`stepsafe.cli.thermal`)."""
    from stepsafe.cli.thermal import thermal_options

    return thermal_options(func)


def scene_options(func):
    """Options shared by advise and check; they override the scene file's values."""
    opts = [
        click.option("--verify", is_flag=True,
                     help="Recompute every boundary used with mpmath (40 digits) and report "
                          "the largest discrepancy; exit 3 if one exceeds 1e-10."),
        click.option("--budget", type=FLOAT, default=None, metavar="SECONDS",
                     help="Stop a coupled system analysis after SECONDS: steps above the h "
                          "reached are then not analysed (reported as the horizon). A bar "
                          "on stderr shows its progress when it takes over a second."),
        frequency_options,
        click.option("--minimize/--no-minimize", default=None,
                     help="OpenMM systems: minimise the energy before the analysis "
                          "[default: the scene's minimize:, else no]."),
        click.option("--hydrogen-mass", type=FLOAT, default=None, metavar="AMU",
                     help="OpenMM systems: hydrogen mass repartitioning to AMU (the mass "
                          "comes from the bonded heavy atom, OpenMM's hydrogenMass rule)."),
        click.option("--constraints", type=click.Choice(("none", "h-bonds", "all-bonds",
                                                         "h-angles")), default=None,
                     help="OpenMM systems: add the distance constraints of this rule to the "
                          "System's own (OpenMM's createSystem rules; needs a PDB)."),
        click.option("--substeps", type=INT, default=None, metavar="K",
                     help="Impulse (r-RESPA) methods: inner steps per outer drift "
                          "[default: the scene's, else the method file's]."),
        click.option("--base", metavar="NAME", help="Swap the base method of a composition "
                                                    "(a family member as gauss:2)."),
        click.option("-s", "--stages", type=INT, metavar="N", help="Stage count of a family."),
        click.option("--method", "method_name", metavar="METHOD",
                     shell_complete=_complete_method,
                     help="Built-in name, family (with -s) or method file."),
        click.argument("scene_files", nargs=-1, metavar="[SCENE.yaml]..."),
    ]
    for opt in opts:
        func = opt(func)
    return func


def _problem(scene_file, options: dict, show_progress: bool = False, h=None, length=None):
    """The scene file merged with the command-line options (the options win); ``h`` the
    step to check (a number, or a text with a time unit); ``length`` a run's time (its
    unit names the time unit where nothing else does)."""
    from stepsafe.api import inputs
    from stepsafe.cli.progressbar import progress_bar

    options = dict(options)  # (the time unit found is this scene's alone)
    modes, labels = command_line_modes(options, scene_file, h, length)
    with progress_bar("coupled analysis", show_progress) as progress:
        return inputs.problem(options["method_name"], modes=modes, labels=labels,
                           scene=scene_file, stages=options["stages"], base=options["base"],
                           margin=options["margin"], zmax=options["zmax"],
                           time_unit=options["time_unit"], h=h, progress=progress,
                           budget=options["budget"], constraints=options["constraints"],
                           hydrogen_mass=options["hydrogen_mass"],
                           minimize=options["minimize"])


def command_line_modes(options: dict, scene_file: str | None = None, *times
                       ) -> tuple[dict, dict[str, tuple[str | None, ...]]]:
    """Every frequency given on the command line, per model, as beta in rad per time
    unit: --beta, --frequency, --wavenumber, --period (vibrations), --saddle-beta,
    --inverted-beta and the --modes file together, in that order (none is dropped); and
    the labels of the file's modes at their places in that order. ({}, {}) if none.

    The time unit (set in ``options["time_unit"]``) is --time-unit, else the scene's, else
    the one that the command line's times (``times``: the step; the periods) name, else the
    --modes file's."""
    import numpy as np

    from stepsafe.systems.scene import time_unit_in_force
    from stepsafe.units import quantity

    options["time_unit"] = time_unit_in_force(options["time_unit"], scene_file, *times,
                                              list(options["period"]))
    loaded = None
    if options["modes_file"]:
        from stepsafe.systems.scene import load_modes

        # in --time-unit, else in the file's time_unit:, which then is the command's
        loaded = load_modes(options["modes_file"], options["time_unit"])
        options["time_unit"] = options["time_unit"] or loaded.time_unit
    unit = options["time_unit"]
    vibrations = list(options["beta"])
    for form in ("frequency", "wavenumber", "period", "sigma"):
        vibrations += [_option_value(lambda v, f=form: quantity(v, f, unit), form, v)
                       for v in options[form]]
    parts: dict[str, list] = {"oscillator": vibrations, "saddle": list(options["saddle_beta"]),
                              "inverted": list(options["inverted_beta"])}
    labels: dict[str, tuple[str | None, ...]] = {}
    if loaded is not None:
        for model, values in loaded.betas.items():
            if model in loaded.labels:
                labels[model] = (None,) * len(parts.get(model, ())) + loaded.labels[model]
            parts.setdefault(model, []).extend(np.atleast_1d(values).tolist())
    arrays = {model: np.asarray(vs, dtype=float) for model, vs in parts.items() if len(vs)}
    return arrays, labels


def _option_value(convert, option: str, value: str) -> float:
    """``convert(value)``, an error naming the option otherwise."""
    from stepsafe.exceptions import StepsafeError

    try:
        return convert(value)
    except StepsafeError as exc:
        raise StepsafeError(f"--{option} {value}: {exc.message}") from None


def one_format(as_json: bool, tsv: bool) -> None:
    """--json and --tsv each choose the whole output: giving both is a usage error."""
    if as_json and tsv:
        raise _input_error("give --json or --tsv, not both")


def _input_error(message: str):
    from stepsafe.exceptions import StepsafeError

    return StepsafeError(message)


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
                   "each widens with amplitude (--temperature measures the bands instead); "
                   "resonances between modes are not analysed.")
@click.option("--solver", type=click.Choice(("fixed-point", "newton", "nominal")),
              default="fixed-point", show_default=True,
              help="With --tol-*: how implicit methods' evaluations per step are counted "
                   "(fixed-point iteration of the stages, which also caps h below its "
                   "convergence limit; simplified Newton; or one per stage).")
@gradient_cost_option
@criterion_option(None)
@_thermal_options
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
    from stepsafe.api import linear
    from stepsafe.cli.progressbar import progress_bar
    from stepsafe.cli.report import print_advice, print_json
    from stepsafe.cli.respa import impulse_of, impulse_report, print_impulse_modes
    from stepsafe.cli.thermal import (
        print_thermal_advice,
        thermal_keywords,
        zero_kelvin_view,
    )

    warm = thermal_keywords(options)
    if len(scene_files) > 1:
        raise _input_error("advise takes at most one scene file")
    scene_file = scene_files[0] if scene_files else None
    impulse = impulse_of(scene_file, {**options, "verify": verify})
    if impulse is not None:
        _no_temperature(warm)
        if tol_phase is not None or tol_energy is not None:
            raise _input_error("--tol-phase/--tol-energy do not apply to impulse methods")
        data = impulse_report(impulse, scene_file, options, step=None, criterion=criterion,
                              resonance_order=resonance_order, check=False)
        print_json(data) if as_json else print_impulse_modes(data, check=False)
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
        from stepsafe.cli.report import print_system

        print_system(data["system"], every_mode, data.get("time_unit"))
    if "thermal" in data and not as_json:
        print_thermal_advice(data)
    if resonance_order is not None and not as_json and "thermal" not in data:
        from stepsafe.cli.report import RESONANCE_CAVEAT

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
                   "band around each widens with amplitude (--temperature measures the "
                   "bands instead); resonances between modes are not analysed.")
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
@_thermal_options
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
    from stepsafe.api import reports
    from stepsafe.cli.report import print_check, print_json, print_system
    from stepsafe.cli.respa import print_impulse_modes
    from stepsafe.cli.thermal import print_thermal_check, thermal_keywords
    from stepsafe.exceptions import StepsafeError

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
    from stepsafe.cli.output import decided

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
                print_impulse_modes(entry, check=True)
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
        if resonance_order is not None and not any(
                "thermal" in entry for entry in data["checks"]):
            from stepsafe.cli.report import RESONANCE_CAVEAT

            click.echo(RESONANCE_CAVEAT)
    for verdict in verdicts:
        _exit_if_unverified(verdict)
    if suite.exit_code:
        sys.exit(suite.exit_code)


def _check_one(scene_file, h, options: dict, resonance_order, criterion: str, verify: bool,
               solver: str, require_complete_search: bool, show_progress: bool,
               warm: dict | None = None):
    """The check of one scene (or of the command line alone): an impulse method's
    :class:`~stepsafe.api.reports.ImpulseModesReport`, else a
    :class:`~stepsafe.api.reports.CheckReport`."""
    from stepsafe.api import linear
    from stepsafe.cli.respa import impulse_of

    impulse = impulse_of(scene_file, {**options, "verify": verify})
    warm = warm or {}
    if impulse is not None:
        from stepsafe.api.md import impulse_advice

        _no_temperature(warm)
        report = impulse_advice(impulse, scene=scene_file, substeps=options.get("substeps"),
                                step=h, time_unit=options["time_unit"], criterion=criterion,
                                resonance_order=resonance_order, use_scene_step=h is None)
        if report.step is None:
            from stepsafe.exceptions import StepsafeError

            raise StepsafeError("no step to check: give --step H or h: in the scene",
                                scene_file)
        return report
    from stepsafe.cli.progressbar import progress_bar

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
                  "max_drift": "--max-drift"}.get(given, "--temperature")
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
    from stepsafe.cli.output import decided

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
    from stepsafe.api.schemas import output_schema
    from stepsafe.cli.report import print_json

    if (which == "output") != (command is not None):
        raise _input_error("give a COMMAND after 'output' (stepsafe schema output hmc), and "
                           "only there")
    if command is not None:
        print_json(output_schema(command), record=False)
        return
    if which == "method":
        from stepsafe.methods.fileformat import json_schema
    else:
        from stepsafe.systems.scene import json_schema
    print_json(json_schema(), record=False)


@main.command("validate")
@click.argument("files", nargs=-1, required=True, metavar="FILE...")
def validate_cmd(files: tuple[str, ...]) -> None:
    """Check method files against the format; warn on non-symplectic or inconsistent ones.

    Exit 0 when every file is valid (warnings allowed), 2 at the first invalid file.
    """
    from stepsafe.cli.output import decided
    from stepsafe.exceptions import StepsafeError
    from stepsafe.methods.library import resolve
    from stepsafe.methods.residuals import residuals

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
    from stepsafe.exceptions import StepsafeError
    from stepsafe.files.yamlio import load_yaml
    from stepsafe.systems.scene import SCENE_KEYS

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
