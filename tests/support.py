"""Small helpers shared by the tests (the tests folder is on sys.path)."""

from __future__ import annotations

from stepsafe.methods.library import resolve


def method(name: str, stages: int | None = None, base: str | None = None):
    """A method object by CLI name."""
    return resolve(name, stages, base)[0]
