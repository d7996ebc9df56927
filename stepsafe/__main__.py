"""``python -m stepsafe`` and the ``stepsafe`` command: the command line in a process of its
own (:func:`main`).

Start-up runs without the cyclic garbage collector. Loading numpy, PyYAML, click, the
package and the command's module makes some 10^5 objects that live as long as the process
(functions, classes, their dictionaries); the collector's passes over them, one every 700
new objects, cost about a tenth of ``stepsafe check``'s start-up and free nothing. Once the
command's module is loaded those objects are frozen (``gc.freeze``: later passes skip them)
and the collector runs again for the command itself. A program that imports stepsafe, or
runs its click group in-process (click's ``CliRunner``), keeps its own collector settings.
"""

from __future__ import annotations

import gc
import sys
from typing import TYPE_CHECKING

from stepsafe.lazy import lazy_module, loaded

if TYPE_CHECKING:
    from stepsafe.cli import group
else:  # loaded once the collector is off
    group = lazy_module("stepsafe.cli.group")


def main() -> None:
    """Run the command line on ``sys.argv`` and exit with its code (the ``stepsafe``
    script's entry point)."""
    gc.disable()
    name = next((arg for arg in sys.argv[1:] if not arg.startswith("-")), None)
    if name in group.COMMANDS:
        try:
            loaded(group.COMMANDS[name])  # the command's module
        except Exception:  # noqa: BLE001 - the group loads it again and reports the error
            pass
    gc.freeze()
    gc.enable()
    group.main(prog_name="stepsafe")


if __name__ == "__main__":
    main()
