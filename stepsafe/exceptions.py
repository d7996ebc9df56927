"""Typed errors. Every error a user can cause is a :class:`StepsafeError` (exit code 2)."""

from __future__ import annotations


class StepsafeError(Exception):
    """Bad input: the tool cannot answer. Rendered as one line, exit code 2.

    ``where`` names the file and the key path (``file::$.kick[2]``) when there is one.
    """

    def __init__(self, message: str, where: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.where = where

    def __str__(self) -> str:
        return f"{self.where}: {self.message}" if self.where else self.message


class MethodError(StepsafeError):
    """A method definition is malformed (wrong shape, non-finite coefficient, ...)."""


class NotConverged(StepsafeError):
    """Draws from a target fail a convergence diagnostic and convergence was required
    (``require_converged``): the estimates on them would not be verified. The command line
    exits 1 with it (the input is well formed; the answer is not established)."""


def positive_finite(value, name: str) -> float:
    """``value`` (a real number: not a bool, not a text) as a float > 0 and finite, else a
    :class:`StepsafeError` naming ``name``."""
    import math

    if isinstance(value, str):
        raise StepsafeError(f"{name} must be a number, got the text {value[:40]!r} (give the "
                            "number itself)")
    if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(
            value, "__float__"):
        raise StepsafeError(f"{name} must be a number, got {type(value).__name__}")
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError(f"{name} must be a finite number, got {str(value)[:40]}") from None
    if not math.isfinite(x) or x <= 0:
        raise StepsafeError(f"{name} must be a positive finite number, got {x}")
    return x


def finite_real(value, name: str) -> float:
    """``value``, a real number (not a bool, not text), as a finite float, else a
    :class:`StepsafeError` naming ``name``."""
    import math
    from numbers import Real

    if isinstance(value, bool) or not isinstance(value, Real):
        raise StepsafeError(f"{name} must be a number, got {type(value).__name__}")
    try:
        x = float(value)
    except OverflowError:
        raise StepsafeError(f"{name} must be a finite number, got {str(value)[:40]}") from None
    if not math.isfinite(x):
        raise StepsafeError(f"{name} must be a finite number, got {x}")
    return x


def unknown_key(key: object, valid: tuple[str, ...] | list[str]) -> str:
    """``unknown key`` with the closest valid key, if one is close, and the valid keys."""
    import difflib

    text = str(key)
    close = [k for k in valid if k.lower() == text.lower()] or \
        difflib.get_close_matches(text, list(valid), n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown key{hint} (valid keys: {', '.join(valid)})"
