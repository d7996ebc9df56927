"""Walks from the equilibria found to the ones they connect to: the second half of the
equilibrium search, after Newton's method from a set of starts.

H is seen in box coordinates ``u`` (each variable mapped to ``[-1, 1]``) with its gradient
``g`` and Hessian ``A`` there. From an equilibrium, for every eigenvector ``v`` of ``A``
(eigenvalue ``lambda``) two walks leave, along ``+v`` and ``-v``:

* ``lambda < 0`` (H falls along v): walks *down*, the descent from a saddle along its
  unstable direction into the basin on each side (where a well behind a ridge lies);
* ``lambda > 0``: walks *up*, eigenvector following from a minimum along each of its
  directions over the ridge to the saddle there;
* ``lambda`` within rounding of 0 (a degenerate equilibrium's zero mode): none; that
  direction is not followed (and the search says so).

A walk tracks one mode. At each step it takes the eigenvector of ``A`` nearest in angle to
the one it followed (``v``, eigenvalue ``lambda``, slope ``s = g . v``) and

* moves along it by the trust radius ``R``, up (or down) hill, while ``lambda`` has the
  wrong sign for a maximum (minimum) along it; else takes the Newton step ``-s / lambda``
  to that maximum (minimum);
* takes the Newton step ``-g_i / lambda_i`` along every other eigenvector, each cut to
  ``R``: towards where H is stationary along it.

So it ends at an equilibrium where H has a maximum (a walk up) or a minimum (down) along
the tracked mode. ``R`` (box units) starts at :data:`FIRST_STEP`, is quartered where the
gradient at the new point differs from ``g + A d`` by more than half of the largest of
``|A d|`` and the two gradients (and a Newton step retaken; a step along v is kept, the
samples along it having shown it went the walk's way), doubled up to
:data:`LARGEST_STEP` where it agrees to a tenth. A step is also
cut where, at points :data:`RESOLUTION` apart along it, the slope along the tracked
direction turns (it crossed a ridge or valley of that direction, such as a well narrower
than the step): the walk then resumes from the first point past the turn. A walk ends

* at an equilibrium: with every mode in its Newton regime and the step below
  :data:`CONVERGED`, the point the module's Newton's method polishes and verifies
  (``settle``), or a known one within :data:`SAME` of it;
* at the box boundary: a step reaches it without a turn;
* at a singularity: its steps shrink to :data:`SMALLEST_STEP` (each step's gradient far
  from A's prediction) where the gradient has grown :data:`SINGULAR` times over its value where
  the walk took its largest steps: H falls (or rises) without bound there, as into the
  ``1/r`` well of a point mass;
* stopped: after :data:`MAX_STEPS` steps, where H cannot be evaluated ahead (``R`` shrunk
  to :data:`SMALLEST_STEP` otherwise), or at a point that is not confirmed as an
  equilibrium.

Every equilibrium a walk finds is followed in turn (up to :data:`MAX_EQUILIBRIA`). The search
*vouches for completeness* (:attr:`Walks.complete`) when every walk from every equilibrium
found ended at an equilibrium found, at the boundary or at a singularity, and no direction
was left out. That
is a statement about the walks, not a proof: an equilibrium whose basin no Newton start
reaches and that lies on no walk (a well narrower than the starts' spacing, away from every
equilibrium found and every path between them), or a feature along a walk narrower than
:data:`RESOLUTION`, is not seen.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: The first step of a walk and the largest (box units, per coordinate).
FIRST_STEP = 1 / 16
LARGEST_STEP = 0.25
#: The slope along the tracked direction is sampled along each step at points this far
#: apart (box units): the walks' resolution.
RESOLUTION = 1e-3
#: Steps of one walk at most.
MAX_STEPS = 200
#: Equilibria followed at most (each sends two walks along each of its directions).
MAX_EQUILIBRIA = 64
#: A walk has converged when its Newton step is below this (box units).
CONVERGED = 1e-9
#: The trust radius may shrink to this (box units, a few roundings of a coordinate): a
#: stiff term (1e30 q^4 beside q^2) needs steps of 1e-15 at first.
SMALLEST_STEP = 1e-15
#: End points closer than this (box units, every coordinate) are one equilibrium.
SAME = 1e-6
#: A walk whose steps shrink to nothing where the gradient has grown by this factor over
#: its value where the walk took its largest steps ran into a singularity of H (a 1/r well).
SINGULAR = 1e6
#: An eigenvalue of A below this fraction of the largest is a zero mode.
ZERO_MODE = 1e-10

Local = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray] | None"]
Slopes = Callable[[np.ndarray], np.ndarray]
Settle = Callable[[np.ndarray], "tuple[np.ndarray, Any] | None"]


@dataclass(frozen=True)
class Walks:
    """What following the equilibria did (see the module docstring)."""

    followed: int = 0  #: walks followed
    to_equilibrium: int = 0  #: ended at an equilibrium (found before, or new)
    to_boundary: int = 0  #: left the box
    to_singularity: int = 0  #: ran into a point where the gradient grows without bound
    stopped: int = 0  #: ended neither way (see ``why``)
    new: int = 0  #: equilibria first found by a walk
    unfollowed: int = 0  #: equilibria not followed (the limit or the time budget)
    zero_modes: int = 0  #: directions not followed: zero modes of degenerate equilibria
    why: tuple[str, ...] = field(default=())  #: distinct reasons walks stopped

    @property
    def complete(self) -> bool:
        """Every walk ended at an equilibrium found or the boundary, and every direction
        of every equilibrium found was followed."""
        return not (self.stopped or self.unfollowed or self.zero_modes)

    def gaps(self) -> list[str]:
        """Why the walks cannot vouch for completeness (empty when they can)."""
        out = []
        if self.stopped:
            out.append(f"{self.stopped} walk(s) stopped before reaching an equilibrium or the "
                       f"box boundary ({'; '.join(self.why)})")
        if self.unfollowed:
            out.append(f"{self.unfollowed} equilibri{'um' if self.unfollowed == 1 else 'a'} "
                       f"not followed (at most {MAX_EQUILIBRIA} are, within the time "
                       "budget)")
        if self.zero_modes:
            out.append(f"{self.zero_modes} zero mode(s) of degenerate equilibria not "
                       "followed (no direction up or down)")
        return out

    def summary(self) -> str:
        singular = (f", {self.to_singularity} into a singularity of H"
                    if self.to_singularity else "")
        return (f"{self.followed} walks along the equilibria's eigendirections "
                f"({self.to_equilibrium} to an equilibrium, {self.to_boundary} to the box "
                f"boundary{singular}, {self.stopped} stopped; {self.new} new "
                f"equilibri{'um' if self.new == 1 else 'a'} found by them)")


def explore(points: list[np.ndarray], local: Local, slopes: Slopes, settle: Settle,
            deadline: float | None = None, hessians: list[np.ndarray] | None = None
            ) -> tuple[list[tuple[np.ndarray, Any]], Walks]:
    """Follow every equilibrium in ``points`` (box coordinates) and those the walks find.

    ``local(u)``: the gradient and Hessian of H at u in box coordinates, None where H
    cannot be evaluated. ``slopes(U)``: the gradients at the rows of U (NaN rows where H
    cannot be evaluated). ``settle(u)``: the verified equilibrium near the end point u of
    a walk, as ``(its box coordinates, the caller's record of it)``, or None.
    ``hessians``: the Hessians (box coordinates) at ``points`` where ``local`` cannot give
    them (at a removable singularity such as ``sin(q)/q`` at 0, whose limit the caller
    has).

    Returns the new equilibria (as ``settle`` gave them) and the record of the walks.
    """
    known = [np.asarray(u, dtype=float) for u in points]
    queue = list(range(len(known)))
    new: list[tuple[np.ndarray, Any]] = []
    counts = {"followed": 0, "to_equilibrium": 0, "to_boundary": 0, "to_singularity": 0,
              "stopped": 0, "zero_modes": 0}
    why: list[str] = []
    explored = 0
    while queue:
        if explored >= MAX_EQUILIBRIA or (deadline is not None and time.monotonic() > deadline):
            break
        index = queue.pop(0)
        explored += 1
        state = local(known[index])
        if state is None and hessians is not None and index < len(hessians):
            state = (np.zeros(known[index].size), hessians[index])
        if state is None:
            counts["stopped"] += 1
            why.append("H cannot be evaluated at an equilibrium")
            continue
        directions, zero = _directions(state[1])
        counts["zero_modes"] += zero
        for v, sense in directions:
            for sign in (1.0, -1.0):
                counts["followed"] += 1
                end, reason = _walk(known[index], state, sign * v, sense, local, slopes)
                if end is None and reason in ("boundary", "singularity"):
                    counts["to_" + reason] += 1
                    continue
                if end is None:
                    counts["stopped"] += 1
                    why.append(reason)
                    continue
                match = _known(end, known)
                if match is None:
                    settled = settle(end)
                    if settled is None:
                        counts["stopped"] += 1
                        why.append("an end point was not confirmed as an equilibrium")
                        continue
                    match = _known(settled[0], known)
                    if match is None:
                        known.append(np.asarray(settled[0], dtype=float))
                        new.append(settled)
                        queue.append(len(known) - 1)
                counts["to_equilibrium"] += 1
    reasons = tuple(dict.fromkeys(why))
    return new, Walks(**counts, new=len(new), unfollowed=len(queue), why=reasons)


def _directions(A: np.ndarray) -> tuple[list[tuple[np.ndarray, int]], int]:
    """The directions walks leave an equilibrium along: the eigenvectors ``v`` of A, each
    with ``sense`` 1 (up: H rises along it) or -1, and the number of zero modes. An
    eigenvalue is a zero mode when below :data:`ZERO_MODE` of ``v^T D v`` (``D = |diag A|``,
    its zeros replaced by A's largest entry): relative to the curvature of the coordinates
    v is made of, so that a stiffness ratio (``1e-6 p^2 + 1e6 q^2``) is not taken for one."""
    A = 0.5 * (A + A.T)
    top = float(np.abs(A).max(initial=0.0))
    if top == 0:
        return [], A.shape[0]
    lam, V = np.linalg.eigh(A)
    D = np.abs(np.diagonal(A))
    D = np.where(D > 0, D, top)
    out, zero = [], 0
    for i in range(lam.size):
        if abs(lam[i]) <= ZERO_MODE * float(V[:, i] ** 2 @ D):
            zero += 1
            continue
        out.append((V[:, i], 1 if lam[i] > 0 else -1))
    return out, zero


def descend(starts: list[np.ndarray], local: Local, slopes: Slopes, settle: Settle,
            deadline: float | None = None) -> tuple[list[tuple[np.ndarray, Any]], int]:
    """The minima the descents from ``starts`` (box coordinates) reach: from each, a walk
    down along every mode (Newton's step where H is convex along it, downhill by the trust
    radius where not), verified by ``settle``. Gradient descent reaches a minimum from
    anywhere in its basin, which is far wider than Newton's method's around a narrow well
    (whose inflections send Newton's steps away). Also returns the number of starts left
    when ``deadline`` (a ``time.monotonic()`` value) passed."""
    known: list[np.ndarray] = []
    out: list[tuple[np.ndarray, Any]] = []
    for k, u in enumerate(starts):
        if deadline is not None and time.monotonic() > deadline:
            return out, len(starts) - k
        state = local(np.asarray(u, dtype=float))
        if state is None:
            continue
        end, _ = _walk(np.asarray(u, dtype=float), state, None, -1, local, slopes)
        if end is None or _known(end, known) is not None:
            continue
        settled = settle(end)
        if settled is not None and _known(settled[0], known) is None:
            known.append(np.asarray(settled[0], dtype=float))
            out.append(settled)
    return out, 0


def _known(u: np.ndarray, known: list[np.ndarray]) -> int | None:
    for k, v in enumerate(known):
        if float(np.abs(u - v).max()) <= SAME:
            return k
    return None


def _walk(u0: np.ndarray, state: tuple[np.ndarray, np.ndarray], v0: np.ndarray | None,
          sense: int, local: Local, slopes: Slopes) -> tuple[np.ndarray | None, str]:
    """One walk from u0 (``state``: gradient and Hessian there) along v0, up (``sense`` 1)
    or down (-1), or (``v0`` None) down along every mode (a descent to a minimum): its end
    point (near an equilibrium) or None with why it ended ("boundary", "singularity", or
    the reason it stopped)."""
    u = np.array(u0, dtype=float)
    g, A = state
    v = None if v0 is None else np.array(v0, dtype=float)
    R = FIRST_STEP
    smooth = (0.0, float("inf"))  # (R, |g|) where the walk took its largest steps
    for count in range(MAX_STEPS):
        lam, V = np.linalg.eigh(0.5 * (A + A.T))
        s = V.T @ g  # slopes along the eigenvectors
        with np.errstate(all="ignore"):  # (a step over a zero eigenvalue is cut to R)
            if v is None:  # descent: Newton where H is convex along a mode, downhill else
                newton = -s / np.abs(lam)
                regime = bool(np.all(lam > 0))
            else:
                k = int(np.argmax(np.abs(V.T @ v)))
                v = V[:, k] * (1.0 if V[:, k] @ v >= 0 else -1.0)
                newton = -s / lam
                # a maximum (up) or minimum (down) along v ahead: Newton's step to it
                regime = bool(sense * lam[k] < 0)
        newton = np.where(np.isnan(newton), 0.0, newton)
        if v is not None and not regime:
            # along v, up or down hill (at the equilibrium itself, with no slope yet, the
            # way v points); a full step R
            ahead = sense * np.sign(s[k]) if count and s[k] != 0 else \
                float(np.sign(V[:, k] @ v))
            newton[k] = ahead * 2 * LARGEST_STEP
        if regime and float(np.abs(V @ newton).max()) <= CONVERGED:
            return u, ""
        while True:
            if R <= SMALLEST_STEP:
                if _size(g) >= SINGULAR * smooth[1]:
                    return None, "singularity"
                return None, "H cannot be evaluated ahead"
            d = _to_face(u, V @ np.clip(newton, -R, R))
            if float(np.abs(d).max()) == 0.0:
                return None, "boundary"
            along = d / float(np.linalg.norm(d)) if v is None else v
            cut = _turn(u, d, along, sense, slopes)
            if cut is not None:
                d = d * cut
            trial = u + d
            new = local(trial)
            if new is None:
                R = 0.25 * float(np.abs(d).max())
                continue
            g2, A2 = new
            err = _size(g2 - (g + A @ d))
            # against the size of the gradient and of its predicted change (at an
            # inflection A d is 0 while the slope is not)
            ref = max(_size(A @ d), _size(g), _size(g2), 1e-300)
            if cut is not None:
                R = min(R, float(np.abs(d).max()))  # a feature of about that size ahead
            elif err > 0.5 * ref:
                R = 0.25 * float(np.abs(d).max())
                if regime:  # Newton's model was wrong: retake the step (else the step
                    continue  # went the walk's way along v, the samples say: keep it)
            elif err < 0.1 * ref:
                R = min(2.0 * R, LARGEST_STEP)
            break
        u, g, A = trial, g2, A2
        if R >= smooth[0]:
            smooth = (R, _size(g))
        if cut is None and float(np.abs(u).max()) >= 1.0 - 1e-12:
            return None, "boundary"
    return None, f"the step limit ({MAX_STEPS}) was reached"


def _size(x: np.ndarray) -> float:
    """The largest entry's modulus (no squares: H of 1e300 does not overflow it)."""
    return float(np.abs(x).max(initial=0.0))


def _to_face(u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``t d`` with ``t`` in (0, 1] the largest that keeps ``u + t d`` in the box."""
    t = 1.0
    for ui, di in zip(u, d):
        if di > 0 and ui + di > 1.0:
            t = min(t, (1.0 - ui) / di)
        elif di < 0 and ui + di < -1.0:
            t = min(t, (-1.0 - ui) / di)
    return d * max(t, 0.0)


def _turn(u: np.ndarray, d: np.ndarray, v: np.ndarray, sense: int, slopes: Slopes
          ) -> float | None:
    """The fraction of the step d to the first sample point (:data:`RESOLUTION` apart)
    where the slope along v goes against the walk (down for an upward walk, ``sense`` 1),
    or where H cannot be evaluated (the point before it); None when it never does."""
    count = int(np.ceil(float(np.abs(d).max()) / RESOLUTION))
    if count <= 1:  # within the resolution: no check
        return None
    moving = 1.0 if d @ v >= 0 else -1.0
    t = np.arange(1, count + 1) / count
    G = slopes(u[None, :] + t[:, None] * d[None, :])
    along = sense * moving * (G @ v)  # > 0 while the walk goes its way along v
    bad = ~np.isfinite(along)
    if bad.any():
        first = int(np.argmax(bad))
        return t[first - 1] if first > 0 else 0.5 * t[0]
    # turned: against the walk by more than a thousandth of the gradient (a slope that
    # only hovers about 0, at a maximum along v the step's other modes converge to, is not
    # a turn)
    turned = along < -1e-3 * float(np.abs(G).max())
    if not turned.any():
        return None
    first = int(np.argmax(turned))
    return float(t[first])
