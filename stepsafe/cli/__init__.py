"""The ``stepsafe`` command line: click commands (:mod:`.main`, :mod:`.accuracy`) and their
text and JSON output (:mod:`.report`, :mod:`.output`). Imports only click at start-up."""

from stepsafe.cli.main import main

__all__ = ["main"]
