"""mpmath transfer matrices of the shipped methods, built from their files' coefficients.

Coefficients are evaluated by the mpmath backend of the expression evaluator (decimal
literals read exactly), family tableaux come from :mod:`mpref` (computed at high precision
from their definitions), and M(z) is then computed by :mod:`mpref` alone (stage equations
solved with mpmath): nothing of stepsafe's float64 path is involved.
"""

from __future__ import annotations

from functools import cache

import mpmath as mp
import mpref
from integrate import mp_method


@cache
def _cached(name: str, stages: int | None, dps: int):
    with mp.workdps(dps):
        return mp_method(name, stages)


def mp_transfer(name: str, stages: int | None = None, dps: int = 50):
    """``Mfun(z, model)`` returning the mpmath 2x2 transfer matrix."""
    m = _cached(name, stages, dps)

    def build(mm):
        if mm.kind == "composition":
            inner = build(mm.data["base"])
            weights = mm.data["weights"]
            return lambda z, model: mpref.transfer_matrix_composition(
                lambda x: inner(x, model), weights, z)
        if mm.kind == "splitting":
            d, k = mm.data["drift"], mm.data["kick"]
            return lambda z, model: mpref.transfer_matrix_splitting(d, k, z, model)
        A_q, b_q, A_p, b_p = (mm.data[key] for key in ("A_q", "b_q", "A_p", "b_p"))
        return lambda z, model: mpref.transfer_matrix_prk(A_q, b_q, A_p, b_p, z, model)

    return build(m)
