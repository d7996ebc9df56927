"""Interval arithmetic on expression graphs, and the certified equilibrium search built on it.

An interval ``[lo, hi]`` encloses every value an expression takes for the variables in a
box, where the expression is defined: each operation's float result is rounded outward
(``nextafter`` away from the enclosed set after the round-to-nearest operation, and the
elementary functions, accurate to a few ulps, widened by :data:`REL` of their value first),
so the enclosure holds whatever the rounding. Where part of the box is outside a function's
domain (``log`` of ``[-1, 2]``, ``1 / [0, 1]``), the enclosure is of the values on the part
where it is defined, and the box is marked *partial*; where none of it is, the result is
*empty*. All arrays carry a leading axis of boxes: one pass evaluates every box of a
generation.

The search (:func:`certified_equilibria`) is a branch and bound on ``grad H = 0`` in a box:

* a box where some component of the interval gradient excludes 0 (or is empty: H is
  defined nowhere in it) holds no equilibrium and is dropped;
* a box ``X`` is settled by the Krawczyk test on ``X'``, ``X`` widened by a tenth of its
  width on each side: with ``m`` the midpoint, ``Y`` the inverse of the midpoint of the
  interval Hessian ``J(X')`` and ``K = m - Y grad H(m) + (I - Y J(X')) (X' - m)`` (all in
  interval arithmetic), ``K`` inside the interior of ``X'`` proves a unique equilibrium in
  ``X'`` (located by the iteration ``x -> x - Y grad H(x)``, a contraction there); ``K``
  disjoint from ``X'`` proves none. The test needs H defined on all of ``X'``;
* every other box is halved across its widest side (relative to the search box).

The search is *complete* when every box is dropped or settled within :data:`MAX_BOXES`
box evaluations: then every equilibrium in the box is among the roots it returns. It is
not complete where an equilibrium is degenerate (a singular Hessian: no Krawczyk test
succeeds near it), where H is singular (the interval gradient near ``1/r`` at 0 is
unbounded) or where the budget runs out first; it then says how many boxes were left
and where the first one is.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from stepsafe.systems.compiler import Compiled, Node, _postorder, constant_value

EPS = float(np.finfo(float).eps)
#: Relative widening of an elementary function's value (they are accurate to an ulp or two).
REL = 4 * EPS
#: Box evaluations at most (each evaluates the interval gradient; a box that survives it,
#: the interval Hessian as well).
MAX_BOXES = 60_000
#: The Krawczyk test runs on the box widened by this fraction of its width on each side.
INFLATE = 0.1
#: Boxes kept at once at most (the rest wait for the next generation).
MAX_LIVE = 4096
_TINY = 5e-324


class Interval:
    """Enclosures over a batch: ``lo``, ``hi`` arrays, ``partial`` (the function is
    undefined on part of the box) and ``empty`` (undefined on all of it)."""

    __slots__ = ("lo", "hi", "partial", "empty")

    def __init__(self, lo, hi, partial=False, empty=False) -> None:
        self.lo, self.hi, self.partial, self.empty = lo, hi, partial, empty


def _out(lo, hi, rel: float = 0.0):
    """Round an enclosure outward (``rel``: widen by that fraction of each bound first);
    a NaN bound (``inf - inf``, ``0 * inf``) becomes unbounded."""
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    if rel:
        lo = lo - rel * np.abs(lo)
        hi = hi + rel * np.abs(hi)
    lo = np.where(np.isnan(lo), -np.inf, np.nextafter(lo, -np.inf))
    hi = np.where(np.isnan(hi), np.inf, np.nextafter(hi, np.inf))
    return lo, hi


def _exact(node: Node) -> bool:
    if node.text == "pi":
        return False
    try:
        return Fraction(node.text) == Fraction(node.value)
    except (ValueError, ZeroDivisionError):
        return False


def _mul(a: Interval, b: Interval) -> tuple[np.ndarray, np.ndarray]:
    p = np.stack(np.broadcast_arrays(a.lo * b.lo, a.lo * b.hi, a.hi * b.lo, a.hi * b.hi))
    p = np.where(np.isnan(p), 0.0, p)  # 0 * inf: the product at that corner is 0
    return _out(p.min(axis=0), p.max(axis=0))


def _recip(b: Interval) -> Interval:
    """1 / b over where b is not 0."""
    lo, hi = np.broadcast_arrays(np.asarray(b.lo, float), np.asarray(b.hi, float))
    straddles = (lo < 0) & (hi > 0)
    zero = (lo == 0) & (hi == 0)
    rlo = np.where(hi == 0, -np.inf, 1.0 / np.where(hi == 0, 1.0, hi))
    rhi = np.where(lo == 0, np.inf, 1.0 / np.where(lo == 0, 1.0, lo))
    rlo, rhi = _out(rlo, rhi)
    rlo = np.where(straddles, -np.inf, rlo)
    rhi = np.where(straddles, np.inf, rhi)
    partial = b.partial | (lo <= 0) & (hi >= 0)
    return Interval(rlo, rhi, partial, b.empty | zero)


def _integer_power(a: Interval, n: int) -> Interval:
    if n < 0:
        return _recip(_integer_power(a, -n))
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, float), np.asarray(a.hi, float))
    pl, ph = lo ** n, hi ** n
    if n % 2:
        rlo, rhi = pl, ph
    else:
        rlo = np.where(lo >= 0, pl, np.where(hi <= 0, ph, 0.0))
        rhi = np.where(lo >= 0, ph, np.where(hi <= 0, pl, np.maximum(pl, ph)))
    rlo, rhi = _out(rlo, rhi, REL)
    if not n % 2:
        rlo = np.maximum(rlo, 0.0)
    return Interval(rlo, rhi, a.partial, a.empty)


def _nonnegative(a: Interval, strict: bool = False) -> Interval:
    """a restricted to [0, inf) (``strict``: (0, inf)), the domain of sqrt, log, x^c."""
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, float), np.asarray(a.hi, float))
    outside = (hi < 0) | (strict & (hi <= 0))
    cut = (lo < 0) | (strict & (lo <= 0))
    return Interval(np.maximum(lo, 0.0), hi, a.partial | cut, a.empty | outside)


def _monotone(f, a: Interval) -> Interval:
    lo, hi = _out(f(a.lo), f(a.hi), REL)
    return Interval(lo, hi, a.partial, a.empty)


def _periodic(a: Interval, peak: float) -> Interval:
    """sin (``peak = pi/2``) or cos (``peak = 0``) of a, by where its maxima and minima
    ``peak + k pi`` fall."""
    lo, hi = np.broadcast_arrays(np.asarray(a.lo, float), np.asarray(a.hi, float))
    f = np.sin if peak else np.cos
    with np.errstate(all="ignore"):
        fl, fh = f(lo), f(hi)
        k = np.ceil((lo - peak) / (2 * np.pi))
        top = peak + 2 * np.pi * k <= hi + 1e-9 * (1 + np.abs(hi))
        kb = np.ceil((lo - peak - np.pi) / (2 * np.pi))
        bottom = peak + np.pi + 2 * np.pi * kb <= hi + 1e-9 * (1 + np.abs(hi))
    rhi = np.where(top, 1.0, np.maximum(fl, fh))
    rlo = np.where(bottom, -1.0, np.minimum(fl, fh))
    slack = 4 * EPS * (1 + np.maximum(np.abs(lo), np.abs(hi)))
    wide = ~np.isfinite(lo) | ~np.isfinite(hi) | (hi - lo >= 2 * np.pi) \
        | (np.maximum(np.abs(lo), np.abs(hi)) > 1e8)
    rlo = np.where(wide, -1.0, np.maximum(rlo - slack, -1.0))
    rhi = np.where(wide, 1.0, np.minimum(rhi + slack, 1.0))
    return Interval(rlo, rhi, a.partial, a.empty)


def _call(name: str, a: Interval) -> Interval:
    with np.errstate(all="ignore"):
        if name == "sin":
            return _periodic(a, np.pi / 2)
        if name == "cos":
            return _periodic(a, 0.0)
        if name in ("exp", "sinh", "tanh", "cbrt"):
            return _monotone(getattr(np, name), a)
        if name == "sqrt":
            return _monotone(np.sqrt, _nonnegative(a))
        if name == "log":
            return _monotone(np.log, _nonnegative(a, strict=True))
        # cosh: even, its minimum 1 at 0
        lo, hi = np.asarray(a.lo, float), np.asarray(a.hi, float)
        cl, ch = np.cosh(lo), np.cosh(hi)
        rlo = np.where((lo <= 0) & (hi >= 0), 1.0, np.minimum(cl, ch))
        rlo, rhi = _out(rlo, np.maximum(cl, ch), REL)
        return Interval(np.maximum(rlo, 1.0), rhi, a.partial, a.empty)


def _power(a: Interval, b: Interval, b_node: Node) -> Interval:
    if not b_node.variables:
        # a constant exponent that is an integer as float64 computes it (4/2 as well as
        # 2): numpy's power is then defined for a negative base too
        c = constant_value(b_node)
        if math.isfinite(c) and c == int(c) and abs(c) <= 64:
            return _integer_power(a, int(c))
    # a^b = exp(b log a) on a > 0 (and a = 0 for b > 0), as for a real exponent
    base = _nonnegative(a)
    with np.errstate(all="ignore"):
        corners = np.stack(np.broadcast_arrays(base.lo ** b.lo, base.lo ** b.hi,
                                               base.hi ** b.lo, base.hi ** b.hi))
    corners = np.where(np.isnan(corners), np.inf, corners)
    # (a^b is monotone in a for each b and in b for each a >= 0: its extremes over the
    # box are at the corners)
    lo, hi = _out(np.nanmin(corners, axis=0), np.nanmax(corners, axis=0), REL)
    return Interval(np.maximum(lo, 0.0), hi, base.partial | b.partial,
                    base.empty | b.empty)


def evaluate(outputs: Sequence[Node], names: Sequence[str], lo: np.ndarray,
             hi: np.ndarray) -> list[Interval]:
    """Enclosures of the outputs over the boxes ``[lo, hi]`` (shape ``(B, N)``, columns
    in the order of ``names``)."""
    index = {n: i for i, n in enumerate(names)}
    B = lo.shape[0]
    values: dict[int, Interval] = {}
    false = np.zeros(B, dtype=bool)
    with np.errstate(all="ignore"):
        for node in _postorder(list(outputs)):
            op = node.op
            if op == "const":
                v = np.asarray(node.value, dtype=float)
                clo, chi = (v, v) if _exact(node) else _out(v, v)
                out = Interval(clo, chi, false, false)
            elif op == "var":
                i = index[node.value]
                out = Interval(lo[:, i], hi[:, i], false, false)
            else:
                a = values[id(node.args[0])]
                if op == "neg":
                    out = Interval(-a.hi, -a.lo, a.partial, a.empty)
                elif op == "call":
                    out = _call(node.value, a)
                else:
                    b = values[id(node.args[1])]
                    partial, empty = a.partial | b.partial, a.empty | b.empty
                    if op == "add":
                        lo_, hi_ = _out(a.lo + b.lo, a.hi + b.hi)
                    elif op == "sub":
                        lo_, hi_ = _out(a.lo - b.hi, a.hi - b.lo)
                    elif op == "mul":
                        lo_, hi_ = _mul(a, b)
                    elif op == "div":
                        r = _recip(b)
                        lo_, hi_ = _mul(a, r)
                        partial, empty = partial | r.partial, empty | r.empty
                    if op in ("add", "sub", "mul", "div"):
                        out = Interval(lo_, hi_, partial, empty)
                    else:
                        out = _power(a, b, node.args[1])
            values[id(node)] = out
    result = []
    for o in outputs:
        w = values[id(o)]
        result.append(Interval(np.broadcast_to(w.lo, (B,)), np.broadcast_to(w.hi, (B,)),
                               np.broadcast_to(w.partial, (B,)),
                               np.broadcast_to(w.empty, (B,))))
    return result


@dataclass(frozen=True)
class Certified:
    """What the certified search proved.

    ``roots``: one point near each equilibrium proved unique in its box (in the box's
    coordinates, rows of shape ``(N,)``); ``complete``: every box was dropped or settled,
    so there are no others; ``boxes``: box evaluations spent; ``undecided``: boxes left
    when it stopped, ``where`` the centre of one of them."""

    roots: tuple[np.ndarray, ...]
    complete: bool
    boxes: int
    undecided: int = 0
    where: tuple[float, ...] | None = None
    reason: str = ""


def certified_equilibria(compiled: Compiled, lo: np.ndarray, hi: np.ndarray,
                         max_boxes: int = MAX_BOXES, deadline: float | None = None
                         ) -> Certified:
    """Every zero of grad H in the box ``[lo, hi]``, proved (see the module docstring)."""
    names = compiled.names
    N = len(names)
    grad = compiled.gradient_nodes
    hess = [compiled.hessian_nodes[i][j] for i in range(N) for j in range(N)]
    scale = np.asarray(hi, float) - np.asarray(lo, float)
    live = [(np.asarray(lo, float)[None, :], np.asarray(hi, float)[None, :])]
    queue_lo, queue_hi = live[0]
    roots: list[np.ndarray] = []
    spent = 0
    while queue_lo.shape[0]:
        late = deadline is not None and time.monotonic() > deadline
        if spent >= max_boxes or late:
            centre = 0.5 * (queue_lo[0] + queue_hi[0])
            return Certified(tuple(roots), False, spent, int(queue_lo.shape[0]),
                             tuple(float(c) for c in centre),
                             "the time budget ran out" if late else
                             f"the box budget ({max_boxes}) ran out")
        take = min(MAX_LIVE, queue_lo.shape[0], max_boxes - spent)
        blo, bhi = queue_lo[:take], queue_hi[:take]
        rest_lo, rest_hi = queue_lo[take:], queue_hi[take:]
        spent += take
        g = evaluate(grad, names, blo, bhi)
        excluded = np.zeros(take, dtype=bool)
        for gi in g:
            excluded |= gi.empty | (gi.lo > 0) | (gi.hi < 0)
        blo, bhi = blo[~excluded], bhi[~excluded]
        if blo.shape[0]:
            settled, found = _krawczyk(compiled, grad, hess, blo, bhi)
            for x in found:
                if np.all(x >= lo - 1e-9 * scale) and np.all(x <= hi + 1e-9 * scale) and \
                        not any(np.all(np.abs(x - r) <= 1e-9 * scale) for r in roots):
                    roots.append(x)
            blo, bhi = blo[~settled], bhi[~settled]
        if blo.shape[0]:
            # halve each box across its widest side relative to the search box
            k = np.argmax((bhi - blo) / scale, axis=1)
            rows = np.arange(blo.shape[0])
            mid = 0.5 * blo[rows, k] + 0.5 * bhi[rows, k]
            left_hi, right_lo = bhi.copy(), blo.copy()
            left_hi[rows, k] = mid
            right_lo[rows, k] = mid
            if np.any((mid <= blo[rows, k]) | (mid >= bhi[rows, k])):
                i = int(np.argmax((mid <= blo[rows, k]) | (mid >= bhi[rows, k])))
                centre = 0.5 * (blo[i] + bhi[i])
                return Certified(tuple(roots), False, spent, int(blo.shape[0]),
                                 tuple(float(c) for c in centre),
                                 "boxes shrank to the float64 resolution")
            blo = np.concatenate([blo, right_lo])
            bhi = np.concatenate([left_hi, bhi])
        queue_lo = np.concatenate([rest_lo, blo])
        queue_hi = np.concatenate([rest_hi, bhi])
    return Certified(tuple(roots), True, spent)


def _krawczyk(compiled: Compiled, grad, hess, lo: np.ndarray, hi: np.ndarray
              ) -> tuple[np.ndarray, list[np.ndarray]]:
    """The Krawczyk test on each box widened by :data:`INFLATE`: which boxes it settles
    (a unique zero, or none, in the widened box) and the zeros it proves."""
    B, N = lo.shape
    width = hi - lo
    xlo = lo - INFLATE * width
    xhi = hi + INFLATE * width
    m = 0.5 * xlo + 0.5 * xhi
    J = evaluate(hess, compiled.names, xlo, xhi)
    Jlo = np.stack([j.lo for j in J], axis=1).reshape(B, N, N)
    Jhi = np.stack([j.hi for j in J], axis=1).reshape(B, N, N)
    defined = ~np.any(np.stack([j.partial | j.empty for j in J], axis=1), axis=1)
    G = evaluate(grad, compiled.names, m, m)
    glo = np.stack([g.lo for g in G], axis=1)
    ghi = np.stack([g.hi for g in G], axis=1)
    defined &= ~np.any(np.stack([g.partial | g.empty for g in G], axis=1), axis=1)
    with np.errstate(all="ignore"):
        Jc = 0.5 * Jlo + 0.5 * Jhi
        Jr = np.nextafter(np.maximum(Jhi - Jc, Jc - Jlo), np.inf)
        ok = defined & np.all(np.isfinite(Jlo) & np.isfinite(Jhi), axis=(1, 2)) \
            & np.all(np.isfinite(glo) & np.isfinite(ghi), axis=1)
        Y = np.zeros_like(Jc)
        det_ok = ok & np.all(np.isfinite(Jc), axis=(1, 2))
        if det_ok.any():
            try:
                Y[det_ok] = np.linalg.inv(Jc[det_ok])
            except np.linalg.LinAlgError:
                Y[det_ok] = np.array([_inverse(a) for a in Jc[det_ok]])
        ok &= np.all(np.isfinite(Y), axis=(1, 2))
        Y = np.where(ok[:, None, None], Y, 0.0)
        gamma = 2 * (N + 3) * EPS
        tiny = 4 * N * _TINY
        aY = np.abs(Y)
        gc = 0.5 * glo + 0.5 * ghi
        gr = np.nextafter(np.maximum(ghi - gc, gc - glo), np.inf)
        c1 = np.einsum("bij,bj->bi", Y, gc)
        r1 = np.einsum("bij,bj->bi", aY, gr) \
            + gamma * np.einsum("bij,bj->bi", aY, np.abs(gc)) + tiny
        C = np.eye(N) - np.einsum("bij,bjk->bik", Y, Jc)
        R = np.einsum("bij,bjk->bik", aY, Jr) \
            + gamma * (np.einsum("bij,bjk->bik", aY, np.abs(Jc)) + np.eye(N)) + tiny
        w = np.nextafter(np.maximum(xhi - m, m - xlo), np.inf)
        centre = m - c1
        rad = r1 + (1 + gamma) * np.einsum("bij,bj->bi", np.abs(C) + R, w) \
            + gamma * np.abs(centre) + tiny
        rad = rad * (1 + gamma)
        Klo, Khi = np.nextafter(centre - rad, -np.inf), np.nextafter(centre + rad, np.inf)
        finite = np.all(np.isfinite(Klo) & np.isfinite(Khi), axis=1)
        ok &= finite
        unique = ok & np.all((Klo > xlo) & (Khi < xhi), axis=1)
        none = ok & np.any((Khi < xlo) | (Klo > xhi), axis=1)
    found = []
    for b in np.nonzero(unique)[0]:
        x = m[b].copy()
        for _ in range(100):
            gx = compiled.gradient(x)
            if not np.all(np.isfinite(gx)):
                break
            step = Y[b] @ gx
            x = np.clip(x - step, xlo[b], xhi[b])
            if np.all(np.abs(step) <= 4 * EPS * (np.abs(x) + width[b])):
                break
        found.append(x)
    return unique | none, found


def _inverse(A: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return np.full_like(A, np.nan)


def certified_gaps(certified: Certified | None, unconfirmed: int) -> list[str]:
    """Why a search is not proved complete (empty when it is)."""
    if certified is None:
        return ["H is a Python function the expression compiler could not trace: no "
                "interval bound proves that every equilibrium was found"]
    out = []
    if not certified.complete:
        where = ", ".join(f"{v:.6g}" for v in certified.where or ())
        out.append(f"the interval branch and bound left {certified.undecided} box(es) "
                   f"undecided after {certified.boxes} ({certified.reason}; one at ({where}))"
                   ": an equilibrium there is not excluded (a degenerate equilibrium or a "
                   "singularity of H leaves boxes undecided)")
    if unconfirmed:
        out.append(f"{unconfirmed} equilibri{'um' if unconfirmed == 1 else 'a'} proved by the "
                   "interval bound not verified by Newton's method")
    return out
