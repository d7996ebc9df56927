"""Figures of the ``plot`` commands: matplotlib (imported when a figure is drawn) on the
Agg backend, the format named by the output's extension, and a write of exactly that
path."""

from __future__ import annotations

from stepsafe.cli.group import _input_error


def pyplot():
    """matplotlib.pyplot on the Agg backend, or a one-line error when it is missing."""
    import logging

    try:
        logging.getLogger("matplotlib").setLevel(logging.ERROR)  # font cache, eps alpha notes
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise _input_error("plotting needs matplotlib: pip install matplotlib (from a clone "
                           "of stepsafe: pip install '.[plot]')") from None
    return plt


def plot_format(output: str, plt) -> str:
    """The format named by the extension of ``output``; refuses anything that would not
    write exactly that path."""
    import os

    formats = sorted(set(plt.figure().canvas.get_supported_filetypes()) - {"pgf"})
    plt.close("all")
    listed = ", ".join(formats)
    if output == "-":
        raise _input_error("-o -: plot writes a file, not standard output (give a path such "
                           "as plot.png)")
    if os.path.isdir(output) or output.endswith(("/", os.sep)):
        raise _input_error(f"-o {output}: a directory, not a file (give a path such as "
                           f"plot.png; formats: {listed})")
    ext = os.path.splitext(os.path.basename(output))[1][1:].lower()
    if not ext:
        raise _input_error(f"-o {output}: no extension to choose the format from (one of: "
                           f"{listed})")
    if ext not in formats:
        raise _input_error(f"-o {output}: unknown format .{ext} (one of: {listed})")
    return ext


def save_figure(fig, output: str, fmt: str) -> None:
    """Write exactly ``output`` (the format is given, so matplotlib never adds an extension);
    a file left half-written by a failure is removed unless it was there before."""
    import os
    import warnings

    existed = os.path.lexists(output)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fig.savefig(output, dpi=120, format=fmt)
    except OSError as exc:
        if not existed and os.path.isfile(output):
            os.remove(output)
        raise _input_error(f"cannot write {output}: {exc.strerror or exc}") from None
