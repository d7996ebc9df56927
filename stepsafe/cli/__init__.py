"""The ``stepsafe`` command line: the click group, the option types and options its commands
share (:mod:`.group`), the core commands (:mod:`.commands`), the commands of each user group
(:mod:`.accuracy`, :mod:`.measure`, :mod:`.respa`, :mod:`.sampling`), each registering on
the group, and their text, JSON and figures (:mod:`.report`, :mod:`.output`,
:mod:`.plots`). The group loads a command's module when the command is looked up
(:data:`.group.COMMANDS`)."""

from stepsafe.cli.group import main

__all__ = ["main"]
