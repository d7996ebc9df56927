"""The ``stepsafe`` command line.

Exit codes (stable, for CI scripts): 0 ok; 1 the check found an unsafe step; 2 bad input
(the tool could not answer: unknown method, malformed file, bad option); 3 internal error
(a bug: rerun with ``--debug`` for the traceback).

Only click is imported at start-up; each command imports what it uses.
"""

from __future__ import annotations

import sys

import click

from . import __version__

EXIT_OK, EXIT_UNSAFE, EXIT_INPUT, EXIT_INTERNAL = 0, 1, 2, 3
MODEL_CHOICES = ("oscillator", "saddle", "inverted", "all")


class _Group(click.Group):
    """Turns errors into one-line messages with the documented exit codes."""

    def invoke(self, ctx: click.Context):
        from .errors import StepsafeError

        debug = "--debug" in sys.argv[1:] or bool(ctx.params.get("debug"))
        try:
            return super().invoke(ctx)
        except StepsafeError as exc:
            if debug:
                raise
            click.echo(f"stepsafe: error: {exc}", err=True)
            ctx.exit(EXIT_INPUT)
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise
        except Exception as exc:  # noqa: BLE001 - the documented internal-error path
            if debug:
                raise
            message = str(exc).splitlines()[0] if str(exc) else ""
            click.echo(f"stepsafe: internal error: {type(exc).__name__}: {message} "
                       "(rerun with --debug for the traceback)", err=True)
            ctx.exit(EXIT_INTERNAL)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
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

    Exit codes: 0 ok, 1 unsafe (check), 2 bad input, 3 internal error.
    """


def method_options(func):
    """METHOD argument with -s/--stages and --base."""
    func = click.option("--base", metavar="NAME",
                        help="Swap the base method of a composition (e.g. midpoint).")(func)
    func = click.option("-s", "--stages", type=int, metavar="N",
                        help="Stage count for the families gauss (N>=1) and "
                             "lobatto3ab (N>=2).")(func)
    return click.argument("method", metavar="METHOD")(func)


def _resolve(method: str, stages: int | None, base: str | None):
    from .library import resolve

    return resolve(method, stages, base)


@main.command("methods")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON list.")
def methods_cmd(as_json: bool) -> None:
    """List the built-in methods and families."""
    from .checks import residuals
    from .library import FAMILIES, builtin_names, resolve
    from .report import print_json, print_methods

    rows = []
    for name in builtin_names():
        if name in FAMILIES:
            title, smallest = FAMILIES[name]
            order = "2s" if name == "gauss" else "2s-2"
            rows.append({"name": f"{name} -s N", "kind": "rk" if name == "gauss" else "prk",
                         "order": order, "stages": f"N>={smallest}",
                         "evaluations": "implicit", "symplectic": True, "title": title})
            continue
        method, entry = resolve(name)
        rows.append({"name": name, "kind": method.kind, "order": method.order,
                     "stages": method.stages, "evaluations": entry.evaluations,
                     "symplectic": residuals(method).symplectic, "title": entry.title})
    if as_json:
        print_json(rows)
    else:
        print_methods(rows)


@main.command("show")
@method_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def show_cmd(method: str, stages: int | None, base: str | None, as_json: bool) -> None:
    """Coefficients, order, stages and symplecticity residuals of METHOD."""
    from .report import method_data, print_json, print_method

    m, entry = _resolve(method, stages, base)
    data = method_data(m, entry)
    coefficients = _coefficients(m)
    if as_json:
        print_json({**data, "coefficients": coefficients})
    else:
        print_method(data, coefficients)


def _coefficients(method) -> dict:
    from .methods import Composition, PartitionedRK, RungeKutta, Splitting

    if isinstance(method, RungeKutta):
        return {"A": method.A.tolist(), "b": method.b.tolist(), "c": method.c.tolist()}
    if isinstance(method, PartitionedRK):
        return {k: getattr(method, k).tolist() for k in ("A_q", "b_q", "A_p", "b_p")}
    if isinstance(method, Splitting):
        return {"drift": method.drift.tolist(), "kick": method.kick.tolist()}
    assert isinstance(method, Composition)
    return {"base": method.base.name, "weights": method.weights.tolist()}


@main.command("region")
@method_options
@click.option("--model", type=click.Choice(MODEL_CHOICES), default="all", show_default=True,
              help="Test model to analyse.")
@click.option("--zmax", type=float, default=None, metavar="Z",
              help="Search z = beta*h up to Z  [default: 10].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def region_cmd(method: str, stages: int | None, base: str | None, model: str,
               zmax: float | None, as_json: bool) -> None:
    """Every z = beta*h interval where METHOD preserves the equilibrium's structure.

    Reports the first boundary z* (the end of the interval from 0: the largest safe
    beta*h), islands further out with their orientation, isolated resonances (e.g.
    M = -I) with the half-width float64 cannot resolve, and poles (the implicit stage
    equations are singular: no unique step). METHOD is a built-in name, a family with
    -s N, or a path to a method file.
    """
    from .models import MODELS
    from .regions import DEFAULT_ZMAX, find_region
    from .report import method_data, print_json, print_region, region_data

    m, entry = _resolve(method, stages, base)
    models = MODELS if model == "all" else (model,)
    zmax = DEFAULT_ZMAX if zmax is None else zmax
    results = {name: region_data(find_region(m, name, zmax)) for name in models}
    head = method_data(m, entry)
    if as_json:
        print_json({"method": head["method"], "title": head["title"], "kind": head["kind"],
                    "stages": head["stages"], "order": head["order"],
                    "symplectic": head["symplectic"], "models": results})
    else:
        print_region(head, results)


@main.command("validate")
@click.argument("files", nargs=-1, required=True, metavar="FILE...")
def validate_cmd(files: tuple[str, ...]) -> None:
    """Check method files against the format; warn on non-symplectic or inconsistent ones.

    Exit 0 when every file is valid (warnings allowed), 2 at the first invalid file.
    """
    from .checks import residuals
    from .library import resolve

    for path in files:
        method, entry = resolve(path if _is_pathlike(path) else f"./{path}")
        res = residuals(method)
        click.echo(f"ok: {path}: {entry.name} ({method.kind}, order {method.order}, "
                   f"{method.stages} stages)")
        if not res.symplectic_for_separable:
            click.echo(f"warning: {path}: not symplectic (residual {res.symplectic_separable:.3g})")
        elif not res.symplectic:
            click.echo(f"warning: {path}: symplectic only for separable H "
                       f"(|b_q - b_p| = {res.weights_equal:.3g})")
        if not res.consistent:
            click.echo(f"warning: {path}: not consistent (weight sums off by "
                       f"{res.consistency:.3g})")


def _is_pathlike(path: str) -> bool:
    return "/" in path or path.endswith((".yaml", ".yml"))


if __name__ == "__main__":  # pragma: no cover
    main()
