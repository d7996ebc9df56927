"""The version of stepsafe, in one place: the package root, the command line's ``--version``
and the packaging read it."""

__version__ = "0.1.0"
