"""mpmath transfer matrices of the shipped methods (the package's ``--verify`` reference)."""

from __future__ import annotations

from stepsafe.reference.verify import mp_method
from stepsafe.reference.verify import mp_transfer as _mp_transfer


def mp_transfer(name: str, stages: int | None = None, dps: int = 50):
    """``Mfun(z, model)`` returning the mpmath 2x2 transfer matrix."""
    return _mp_transfer(mp_method(name, stages, None, dps))
