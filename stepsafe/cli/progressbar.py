"""A progress bar on stderr for analyses that take more than a second (command line only).

The numeric core reports progress through a callback ``progress(fraction)``; this module
turns it into a rich bar when stderr is a terminal. A stage that names what it counts, and
may not know its total (Lanczos iterations, for one), reports through the callback's
``stage(label, done, total)`` attribute instead: the bar then shows that label in place of
its own, and the count (``done of total``, or ``done`` alone under a pulsing bar). Nothing
is drawn before :data:`DELAY` seconds (most analyses finish first), and the bar is removed
when done, so stdout (the report or the JSON) is never mixed with it.
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

    def bar() -> bool:
        if "bar" not in state:
            if time.monotonic() - start < DELAY:
                return False
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            shown = Progress(TextColumn("{task.description}"), BarColumn(),
                             TextColumn("{task.fields[count]}"), TimeElapsedColumn(),
                             console=Console(stderr=True), transient=True)
            shown.start()
            state["bar"], state["task"] = shown, shown.add_task(label, total=1.0, count="")
        return True

    def report(fraction: float) -> None:
        if bar():
            state["bar"].update(state["task"], description=label, total=1.0,
                                completed=min(max(fraction, 0.0), 1.0),
                                count=f"{100 * min(max(fraction, 0.0), 1.0):>3.0f}%")

    def stage(name: str, done: int, total: int | None) -> None:
        if bar():
            count = f"{done} of {total}" if total else f"{done}"
            state["bar"].update(state["task"], description=name, total=total,
                                completed=done if total else 0, count=count)

    report.stage = stage  # type: ignore[attr-defined]
    try:
        yield report
    finally:
        if "bar" in state:
            state["bar"].stop()
