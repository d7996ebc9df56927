"""``python -m stepsafe``: the same as the ``stepsafe`` command."""

from stepsafe.cli import main

main(prog_name="stepsafe")
