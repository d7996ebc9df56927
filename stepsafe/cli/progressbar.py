"""A progress bar on stderr for analyses that take more than a second (command line only).

The numeric core reports progress through a callback ``progress(fraction)``; this module
turns it into a rich bar when stderr is a terminal. Nothing is drawn before
:data:`DELAY` seconds (most analyses finish first), and the bar is removed when done, so
stdout (the report or the JSON) is never mixed with it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

#: seconds before the bar appears
DELAY = 1.0


@contextmanager
def progress_bar(label: str, enabled: bool = True) -> Iterator[Callable[[float], None] | None]:
    """Yields a ``progress(fraction)`` callback drawing a bar on stderr, or None when
    disabled or stderr is not a terminal."""
    if not enabled or not sys.stderr.isatty():
        yield None
        return
    start = time.monotonic()
    state: dict = {}

    def report(fraction: float) -> None:
        if "bar" not in state:
            if time.monotonic() - start < DELAY:
                return
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            bar = Progress(TextColumn(label), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                           TimeElapsedColumn(), console=Console(stderr=True), transient=True)
            bar.start()
            state["bar"], state["task"] = bar, bar.add_task(label, total=1.0)
        state["bar"].update(state["task"], completed=min(max(fraction, 0.0), 1.0))

    try:
        yield report
    finally:
        if "bar" in state:
            state["bar"].stop()
