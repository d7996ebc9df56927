"""The ``stepsafe`` command line: the click group, the option types and options its commands
share (:mod:`.group`), the core commands (:mod:`.main`), the commands of each user group
(:mod:`.accuracy`, :mod:`.measure`, :mod:`.respa`, :mod:`.sampling`), each registering on
the group, and their text, JSON and figures (:mod:`.report`, :mod:`.output`,
:mod:`.plots`). Importing it registers every command."""

from stepsafe.cli import accuracy, measure, respa, sampling
from stepsafe.cli.main import main

__all__ = ["accuracy", "main", "measure", "respa", "sampling"]
