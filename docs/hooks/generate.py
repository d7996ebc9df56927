"""MkDocs hook: the pages' generated parts come from the code at build time, never by hand.

A line ``<!-- generated: stepsafe ARGS -->`` in a page becomes the output of the command
``stepsafe ARGS`` (a ``json`` block for ``schema``, a ``text`` block otherwise), a line
``<!-- generated: python -m stepsafe.cli.methods_table -->`` the method-library table, and a line
``<!-- generated: cli reference -->`` the ``--help`` of ``stepsafe`` and of every command,
rendered by click at a fixed width of 100 columns, and a line
``<!-- generated: api reference -->`` the mkdocstrings blocks of every public name of
``stepsafe`` (``stepsafe.__all__``), grouped by the module that defines it. A command that
fails stops the build.
"""

from __future__ import annotations

import re
import shlex

import click
from click.testing import CliRunner

MARKER = re.compile(r"^<!-- generated: (.+?) -->$", re.M)
#: click renders help to this width, whatever the terminal building the site
WIDTH = 100


def _command_output(args: list[str]) -> str:
    from stepsafe.cli import main

    result = CliRunner().invoke(main, args, env={"COLUMNS": str(WIDTH), "NO_COLOR": "1"})
    if result.exit_code != 0:
        raise RuntimeError(f"stepsafe {shlex.join(args)} exited {result.exit_code}: "
                           f"{result.output}")
    return result.stdout


def _help(command: click.Command, path: str) -> str:
    with click.Context(command, info_name=path, terminal_width=WIDTH,
                       max_content_width=WIDTH) as ctx:
        return command.get_help(ctx)


def cli_reference() -> str:
    """The help of ``stepsafe`` and of each of its commands, one section per command."""
    from stepsafe.cli import main

    parts = ["## stepsafe\n", "```text\n" + _help(main, "stepsafe") + "\n```\n"]
    with click.Context(main, info_name="stepsafe") as ctx:
        names = main.list_commands(ctx)
        for name in names:
            command = main.get_command(ctx, name)
            assert command is not None, name
            parts += [f"## stepsafe {name}\n",
                      "```text\n" + _help(command, f"stepsafe {name}") + "\n```\n"]
    return "\n".join(parts)


def api_reference() -> str:
    """One mkdocstrings block per module of the public API, listing only its public names
    (those ``stepsafe`` exports), in the order ``stepsafe.__all__`` gives them."""
    import stepsafe

    modules: dict[str, list[str]] = {}
    for name in stepsafe.__all__:
        if not name.startswith("__"):
            modules.setdefault(getattr(stepsafe, name).__module__, []).append(name)
    order = sorted(modules, key=lambda m: (m.endswith("reports"),
                                           m == "stepsafe.exceptions"))
    return "\n".join(f"::: {module}\n    options:\n      members:\n"
                     + "".join(f"        - {name}\n" for name in modules[module])
                     for module in order)


def render(what: str) -> str:
    """The Markdown a marker ``<!-- generated: WHAT -->`` stands for."""
    if what == "cli reference":
        return cli_reference()
    if what == "api reference":
        return api_reference()
    if what == "python -m stepsafe.cli.methods_table":
        from stepsafe.cli.methods_table import markdown

        return markdown()
    args = shlex.split(what)
    if args[0] != "stepsafe":
        raise ValueError(f"unknown generated part: {what!r}")
    language = "json" if args[1] == "schema" else "text"
    return f"```{language}\n{_command_output(args[1:])}```\n"


def on_page_markdown(markdown: str, **kwargs) -> str:
    return MARKER.sub(lambda m: render(m.group(1)), markdown)
