"""The ``stepsafe`` click group and what its commands share: the option types (ASCII
numbers, times with units), the option groups, the exit codes and the one-line error
contract. Every command module (:mod:`.commands`, :mod:`.accuracy`, :mod:`.measure`,
:mod:`.respa`, :mod:`.sampling`) registers its commands on :data:`main`.

The group loads a command's module when the command is looked up (:data:`COMMANDS`, click's
lazily loading group): ``stepsafe check`` loads :mod:`.commands` and what it imports, not the
HMC, measurement or multiple-time-stepping commands. ``--help``, shell completion and the
generated command-line reference look every command up, and so load them all.
"""

from __future__ import annotations

import sys
from typing import Any

import click

from stepsafe._version import __version__
from stepsafe.api import inputs
from stepsafe.cli import output
from stepsafe.cli.allocator import keep_freed_memory
from stepsafe.cli.output import is_output_error
from stepsafe.cli.progressbar import progress_bar
from stepsafe.exceptions import StepsafeError
from stepsafe.lazy import lazy_module, loaded
from stepsafe.methods.library import builtin_names
from stepsafe.systems.scene import load_modes, load_scene, time_unit_in_force
from stepsafe.text import printable
from stepsafe.units import TIME_UNITS, parse_quantity, quantity

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


#: Each command and the module that defines it (and registers it on :data:`main` when
#: loaded): a command loads its own module only (tests/test_imports.py checks the table
#: against the commands the modules define).
COMMANDS = {name: module for module, names in (
    (lazy_module("stepsafe.cli.commands"),
     ("methods", "show", "region", "advise", "check", "schema", "validate")),
    (lazy_module("stepsafe.cli.accuracy"), ("error", "compare", "plot")),
    (lazy_module("stepsafe.cli.measure"), ("measure",)),
    (lazy_module("stepsafe.cli.respa"), ("respa",)),
    (lazy_module("stepsafe.cli.sampling"), ("hmc", "design")),
) for name in names}


class _Group(click.Group):
    """Owns every exit path: one-line errors with the documented exit codes.

    Usage errors (unknown option or command, bad choice, missing argument, a bare
    ``stepsafe``) are one line on stderr and exit 2, never click's multi-line Usage block.
    ``-h`` is not a help alias (``--help`` is): on ``check`` it would read as the step.
    A command's module is loaded when the command is looked up (:data:`COMMANDS`).
    """

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(self.commands) | set(COMMANDS))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in self.commands and cmd_name in COMMANDS:
            loaded(COMMANDS[cmd_name])  # its module registers its commands on the group
        return self.commands.get(cmd_name)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True,
             **extra):
        if not standalone_mode:  # for embedding: click's behaviour, exceptions propagate
            return super().main(args, prog_name or PROG, complete_var, False, **extra)
        # shell completion (_STEPSAFE_COMPLETE=bash_source stepsafe): click answers and exits
        self._main_shell_completion(extra, prog_name or PROG, complete_var)
        args = sys.argv[1:] if args is None else list(args)
        keep_freed_memory()
        sys.exit(self._run(args, extra))

    def _run(self, args: list[str], extra: dict) -> int:
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
    try:
        click.echo(prefix + printable(" ".join(message.split())), err=True)
    except (OSError, ValueError, AttributeError):  # stderr closed or full: the code tells
        pass


def _usage_message(exc: click.UsageError, group: click.Group, args: list[str]) -> str:
    ctx = exc.ctx
    command = ctx.command if ctx is not None else None
    names = sorted(set(group.commands) | set(COMMANDS))
    if command is None:  # some parser errors carry no context: name the command given
        name = next((a for a in args if a in names), None)
        if name in COMMANDS:
            loaded(COMMANDS[name])
        command = group.commands.get(name, group) if name else group
    where = PROG if command is group else f"{PROG} {command.name}"
    takes_step = any(p.name == "h" for p in command.params)
    if isinstance(exc, click.NoSuchOption) and exc.option_name in ("-h", "-H", "--H"):
        message = (f"{exc.option_name} is not an option: write the step as --step H; "
                   "for help use --help") if takes_step else \
            f"{exc.option_name} is not an option: for help use --help"
    elif isinstance(exc, click.exceptions.NoArgsIsHelpError) or (
            command is group and exc.message == "Missing command."):
        message = f"missing command (one of: {', '.join(names)})"
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

    if "/" in incomplete or incomplete.endswith((".yaml", ".yml")):
        return [CompletionItem(incomplete, type="file")]
    return [CompletionItem(name) for name in builtin_names() if name.startswith(incomplete)]


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
    unit names the time unit where nothing else does and the frequencies need one: see
    :func:`stepsafe.api.inputs.problem_for_run`)."""
    def build(unit):
        given = dict(options)  # (the time unit found is this scene's alone)
        if unit is not None:
            given["time_unit"] = unit
        modes, labels = command_line_modes(given, scene_file, h)
        with progress_bar("coupled analysis", show_progress) as progress:
            return inputs.problem(given["method_name"], modes=modes, labels=labels,
                               scene=scene_file, stages=given["stages"], base=given["base"],
                               margin=given["margin"], zmax=given["zmax"],
                               time_unit=given["time_unit"], h=h, progress=progress,
                               budget=given["budget"], constraints=given["constraints"],
                               hydrogen_mass=given["hydrogen_mass"],
                               minimize=given["minimize"])

    if length is not None and options["time_unit"] is None and time_unit_in_force(
            None, scene_file, h, list(options["period"])) is None:
        return inputs.problem_for_run(build, length)
    return build(None)


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

    options["time_unit"] = time_unit_in_force(options["time_unit"], scene_file, *times,
                                              list(options["period"]))
    loaded = None
    if options["modes_file"]:
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
    try:
        return convert(value)
    except StepsafeError as exc:
        raise StepsafeError(f"--{option} {value}: {exc.message}") from None


def one_format(as_json: bool, tsv: bool) -> None:
    """--json and --tsv each choose the whole output: giving both is a usage error."""
    if as_json and tsv:
        raise _input_error("give --json or --tsv, not both")


def _input_error(message: str):
    return StepsafeError(message)


#: advise/check options that an impulse method cannot take (its frequencies come in
#: fast/slow pairs from a scene file).
_SINGLE_FORCE_OPTIONS = ("beta", "frequency", "wavenumber", "period", "sigma", "saddle_beta",
                         "inverted_beta", "modes_file", "margin", "zmax", "budget", "verify")


def impulse_of(scene_file: str | None, options: dict) -> Any:
    """The impulse method advise/check were asked about (by --method or the scene's
    method:), or None for any other method. --substeps is refused for other methods."""
    name = options["method_name"]
    if name is None and scene_file is not None:
        ref = load_scene(scene_file, options["time_unit"]).method
        name = None if ref is None or ref.stages or ref.base else ref.name
    integrator = None
    if name is not None and options["stages"] is None and options["base"] is None:
        try:
            integrator = inputs.method(name)
        except StepsafeError:
            integrator = None  # the analysis of any other method reports it in context
    if integrator is None or integrator.kind != "impulse":
        if options.get("substeps") is not None:
            raise _input_error("--substeps applies to impulse (multiple time stepping) "
                               "methods only")
        return None
    given = [key for key in _SINGLE_FORCE_OPTIONS if options.get(key) not in (None, (), False)]
    if given:
        raise _input_error(f"--{given[0].replace('_', '-')} does not apply to the impulse "
                           f"method {integrator.name}: its modes come as fast: and slow: "
                           "frequencies in a scene file (or use stepsafe respa for one pair)")
    if scene_file is None:
        raise _input_error(f"{integrator.name} is an impulse method: give a scene file whose "
                           "modes give fast: and slow: frequencies (or use stepsafe respa)")
    return integrator
