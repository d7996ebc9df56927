"""Standard output that may fail: a reader that went away, a full disk.

A closed pipe (``stepsafe check ... | head -1``) is not an error of the tool: the command's
answer was decided before it printed, so the process exits with that answer's code (0 or 1
for ``check``, 0 otherwise) and prints nothing more, the way the Python documentation
recommends (stdout is pointed at ``os.devnull`` so the final flush cannot fail again).
Output that cannot be written for another reason (``> /dev/full``: no space left on
device) is reported in one line and exits 2: nothing is wrong with the tool, but the
answer did not reach the caller, so the caller must not read success.

Commands call :func:`decided` with their exit code before printing their results.
"""

from __future__ import annotations

import errno
import os
import sys
from collections.abc import Callable

EXIT_CANNOT_WRITE = 2
_WRITE_ERRNOS = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}
_state: dict = {"code": 0, "message": None}


def reset() -> None:
    """Start of a command: nothing decided yet (a closed stdout then means exit 0)."""
    _state.update(code=0, message=None)
    if sys.stdout is None:  # started with stdout closed (>&-): as if the reader had gone
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - lives as long as the process
    if sys.stderr is None:  # started with stderr closed (2>&-): messages go nowhere, the
        sys.stderr = open(os.devnull, "w")  # noqa: SIM115 - exit code still tells


def decided(code: int, message: str | None = None) -> None:
    """The command will exit with ``code`` (and print ``message`` on stderr, if given),
    whatever happens to its output from now on."""
    _state.update(code=code, message=message)


def is_output_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a failure to write the output (closed pipe, full disk)."""
    return isinstance(exc, OSError) and exc.errno in ({errno.EPIPE} | _WRITE_ERRNOS)


def flush() -> None:
    if sys.stdout is not None:
        sys.stdout.flush()


def failed(exc: OSError, report: Callable[[str], None]) -> int:
    """Handle an output error; returns the exit code."""
    _silence_stdout()
    if exc.errno == errno.EPIPE:
        if _state["message"]:
            report(_state["message"])
        return _state["code"]
    report(f"cannot write output: {exc.strerror or exc}")
    return EXIT_CANNOT_WRITE


def _silence_stdout() -> None:
    """Point file descriptor 1 at /dev/null: what is still buffered goes nowhere, quietly."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return  # not a real file (a test runner's buffer): nothing will fail at exit
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)
