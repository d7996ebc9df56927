"""The ``stepsafe`` command line: the click group and its core commands (:mod:`.main`),
the commands of each user group (:mod:`.accuracy`, :mod:`.measure`, :mod:`.respa`,
:mod:`.sampling`, each registering on the group of :mod:`.main`, which imports none of
them), and their text and JSON output (:mod:`.report`, :mod:`.output`). Imports only
click at start-up."""

from stepsafe.cli import accuracy, measure, respa, sampling
from stepsafe.cli.main import main

__all__ = ["accuracy", "main", "measure", "respa", "sampling"]
