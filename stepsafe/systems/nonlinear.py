"""Nonlinear 1-dof systems (paper Sec. 3): equilibria of H(q, p), their type, and the
linear model each one gives.

``H`` is a restricted expression in ``q``, ``p`` and named parameters (numbers, + - * / **,
sin, cos, exp, log, sqrt, cosh, sinh, tanh, pi; checked by :mod:`stepsafe.files.expressions`,
never ``eval``). Derivatives are exact: the gradient and Hessian are differentiated
symbolically on the expression graph (:mod:`stepsafe.systems.compiler`), not by finite
differences, and evaluated in float64 or, to verify, in mpmath.

Equilibria solve ``grad H = 0`` inside a box, whatever the units:

1. Newton's method in float64 from a grid of starts (:data:`GRID` squared, or ``starts:``),
   in box coordinates (the box mapped to ``[-1, 1]^2``) and with the Hessian scaled by its
   diagonal, so coefficients from 1e-300 to 1e300 and anisotropic energies (``1e-6 p^2 +
   1e6 q^2``) converge alike; starts where H or its derivatives cannot be evaluated
   (overflow, a domain error) are counted. From a start where Newton's method does not
   converge (it cycles between the inflections of a narrow well) a descent follows H down
   to the minimum whose basin it lies in (:func:`stepsafe.systems.walks.descend`).
2. From every equilibrium found, walks along its eigendirections, down from a saddle and
   up from a minimum, reach the equilibria it is connected to (a well behind a ridge);
   each one found is followed in turn (:func:`stepsafe.systems.walks.explore`, which also
   says whether the search vouches for completeness).
3. Each cluster of end points is re-solved by Newton's method in mpmath
   (:data:`VERIFY_DPS` digits, to steps of :data:`VERIFY_STEP`) and kept only if it
   converges: that is the verification. The last steps give the location's uncertainty
   ``dx``.
4. The Hessian there (in mpmath, so that cancellations such as ``sin(q)/q`` near 0 do
   not matter; at a removable singularity it is the limit from both sides) decides the
   type by ``D = H_qp^2 - H_qq H_pp`` (the paper's ``f_q g_p - f_p g_q``): ``D < 0``
   elliptic, ``D > 0`` hyperbolic, decided and turned into ``beta`` at that precision, so
   in any units (``1e-300 (q^2 + p^2)`` has ``D = -4e-600``, below float64's range, and
   ``beta = 2e-300``). ``D`` is *degenerate* (no linear model) when its sign
   is not decided: ``|D|`` is within what moving the point by ``dx`` changes it, plus
   rounding relative to its terms ``max(H_qp^2, |H_qq H_pp|)``, or when Newton's method
   approached it only linearly (more than six steps below 1e-8): a zero of the gradient
   where the Hessian is singular (``q^4`` at 0), whose Hessian at the computed point is
   an artefact of the location error.

The exact linearisation ``x' = L x``, ``L = [[H_pq, H_pp], [-H_qq, -H_qp]]``, maps to a
test model when a partition-preserving scaling ``q -> a q, p -> b p`` brings it there
(which every partitioned method commutes with):

* ``H_qp = 0``: ``oscillator`` with ``beta = sqrt(H_qq H_pp)`` if H_qq and H_pp have one
  sign, else ``inverted`` with ``beta = sqrt(-H_qq H_pp)``;
* ``H_qq = H_pp = 0``: ``saddle`` (q expands) if ``H_qp > 0`` or ``saddle-p`` if ``H_qp < 0``,
  ``beta = |H_qp|``;
* otherwise the linearisation is analysed as a 2x2 Hessian (:mod:`stepsafe.systems.linear`:
  decoupled for RK methods, coupled for partitioned ones).
"""

from __future__ import annotations

import ast
import functools
import math
from typing import Any, NamedTuple

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.files.expressions import Expression, ExpressionError, parse
from stepsafe.systems.compiler import Compiled, from_tree
from stepsafe.systems.intervals import Certified, certified_equilibria, certified_gaps
from stepsafe.systems.walks import Walks, descend, explore

FUNCTIONS = ("sin", "cos", "exp", "log", "sqrt", "cosh", "sinh", "tanh")
MAX_PARAMETERS = 100
VERIFY_DPS = 120
#: mpmath Newton stops when its step falls below this (box units); the cancellations near
#: a removable singularity at that distance (~1/x^3) leave ~30 of the working digits.
VERIFY_STEP = 1e-30
#: Newton steps allowed in the verification (a stiff zero, 1e308 q^4 + q^2, creeps by 2/3
#: per step for ~900 steps before it converges quadratically)
VERIFY_ITERATIONS = 2000
GRID = 13


class Jet2(NamedTuple):
    """H at (q, p) with its gradient ``g = (H_q, H_p)`` and Hessian
    ``H = (H_qq, H_qp, H_pp)``, in float64 or mpmath numbers."""

    v: Any
    g: tuple[Any, Any]
    H: tuple[Any, Any, Any]


class Hamiltonian(NamedTuple):
    expression: Expression
    parameters: dict[str, float]

    @property
    def compiled(self) -> Compiled:
        """H's expression graph in (q, p) with its derivatives."""
        return _compiled(self.expression.text, self.expression.tree,
                         tuple(sorted(self.parameters.items())))

    def jet(self, q, p, lib=math) -> Jet2:
        """Value, gradient and Hessian at (q, p) in float64 (``lib=math``) or mpmath (at
        its current precision), from the compiled graph; an ExpressionError where they
        are not finite reals."""
        compiled = self.compiled
        if lib is math:
            x = np.array([float(q), float(p)])
            v, g = compiled.energy_gradient(x)
            h = compiled.hessian(x)
            if not (np.isfinite(v) and np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
                raise ExpressionError("H or its derivatives overflow float64")
            return Jet2(float(v), (float(g[0]), float(g[1])),
                        (float(h[0, 0]), float(h[0, 1]), float(h[1, 1])))
        mv, mg, mh = compiled.mp_jet([lib.mpf(q), lib.mpf(p)])
        return Jet2(mv, (mg[0], mg[1]), (mh[0][0], mh[0][1], mh[1][1]))


def parse_hamiltonian(text: str, parameters: dict[str, float] | None = None) -> Hamiltonian:
    """A whitelisted H(q, p); unknown names are an error."""
    parameters = dict(parameters or {})
    if len(parameters) > MAX_PARAMETERS:
        raise ExpressionError(f"more than {MAX_PARAMETERS} parameters")
    for name in parameters:
        if name in ("q", "p", "pi") or name in FUNCTIONS or not name.isidentifier():
            raise ExpressionError(f"parameter name {name!r} is not allowed")
    expr = parse(text, FUNCTIONS)
    unknown = expr.names - {"q", "p", "pi"} - set(parameters)
    if unknown:
        raise ExpressionError(f"unknown name {sorted(unknown)[0]!r} (use q, p, pi and the "
                              "parameters)")
    for node in ast.walk(expr.tree):  # (said here, not as 'cannot be evaluated' everywhere)
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow) and \
                isinstance(node.right, ast.Constant) and \
                any(isinstance(n, ast.Name) and n.id in ("q", "p")
                    for n in ast.walk(node.left)):
            exponent = float(ast.get_source_segment(expr.text.strip(), node.right) or 0)
            if abs(exponent) > 64:
                raise ExpressionError(f"{ast.get_source_segment(expr.text.strip(), node)}: "
                                      "powers of an expression in q or p go up to 64")
    return Hamiltonian(expr, parameters)


@functools.lru_cache(maxsize=64)
def _compiled(text: str, tree: ast.AST, parameters: tuple) -> Compiled:
    return Compiled(from_tree(tree, text, ("q", "p"), dict(parameters)), ("q", "p"))


class Equilibrium(NamedTuple):
    q: float
    p: float
    D: float | None  # None: |D| beyond float64's range (see _classify)
    kind: str  # "elliptic", "hyperbolic", "degenerate"
    hessian: np.ndarray  # [[H_qq, H_qp], [H_pq, H_pp]]
    beta: float | None
    model: str | None  # a test model, "coupled" (needs the 2x2 Hessian analysis) or None


class Search(NamedTuple):
    """What the search found: verified equilibria, and why the other starts failed."""

    equilibria: list[Equilibrium]
    starts: int
    unevaluable: int  # starts (or iterates) where H or its derivatives could not be evaluated
    outside: int  # Newton left the box or did not converge
    unverified: int  # float64 end points that high precision did not confirm
    flat: int = 0  # starts where gradient and Hessian vanish: no isolated equilibrium
    walks: Walks = Walks()  # the walks from the equilibria the starts found
    certified: Certified | None = None  # the interval branch and bound
    unconfirmed: int = 0  # equilibria it proved that high precision did not verify
    found_by_bound: int = 0  # equilibria the starts and walks missed and the bound found

    def gaps(self) -> list[str]:
        """Why the search cannot vouch for completeness (empty when it can: the interval
        branch and bound proved every equilibrium of the box found)."""
        return certified_gaps(self.certified, self.unconfirmed)

    def walk_gaps(self) -> list[str]:
        """What the starts and walks left out (a heuristic's account, not a proof)."""
        out = self.walks.gaps()
        if self.unevaluable:
            out.append(f"H could not be evaluated at {self.unevaluable} start(s): where it "
                       "is undefined the box is not searched")
        return out

    def explain(self) -> str:
        """Why nothing was found, in one phrase."""
        parts = [f"{self.starts} Newton starts"]
        if self.flat:
            parts.append(f"{self.flat} where H is flat (zero gradient and Hessian, e.g. a "
                         "constant): no isolated equilibrium to analyse")
        if self.unevaluable:
            parts.append(f"{self.unevaluable} where H or its derivatives cannot be evaluated "
                         "(overflow or outside its domain)")
        if self.outside:
            parts.append(f"{self.outside} that left the box or did not converge")
        if self.unverified:
            parts.append(f"{self.unverified} end points not confirmed at high precision")
        return "; ".join(parts)


def find_equilibria(H: Hamiltonian, box_q: tuple[float, float], box_p: tuple[float, float],
                    grid: int = GRID) -> Search:
    """All zeros of grad H in the box (see the module docstring)."""
    (q0, q1), (p0, p1) = box_q, box_p
    if not (q0 < q1 and p0 < p1) or not all(map(math.isfinite, (q0, q1, p0, p1))):
        raise StepsafeError("the box needs finite q: [lo, hi] and p: [lo, hi] with lo < hi")
    centre = np.array([0.5 * q0 + 0.5 * q1, 0.5 * p0 + 0.5 * p1])
    half = np.array([0.5 * q1 - 0.5 * q0, 0.5 * p1 - 0.5 * p0])
    if not np.all(np.isfinite(half)) or np.any(half <= 0):
        raise StepsafeError("the box is too wide or too narrow for float64")
    ends: list[np.ndarray] = []
    failed: list[np.ndarray] = []  # starts from which Newton's method did not converge
    unevaluable = outside = flat = 0
    axis = np.linspace(-1.0, 1.0, grid)
    for uq in axis:
        for up in axis:
            start = np.array([uq, up])
            status, u = _newton_float(H, start, centre, half)
            if status in ("stalled", "outside"):
                failed.append(start)
            if status == "unevaluable":
                unevaluable += 1
            elif status == "flat":
                flat += 1
            elif status == "outside":
                outside += 1
            elif not any(np.abs(u - v).max() <= 1e-6 for v in ends):
                ends.append(u)
    found: list[Equilibrium] = []
    unverified = 0
    for u in ends:
        e = _verify(H, u, centre, half)
        if e is None:
            unverified += 1
        elif not any(abs(e.q - f.q) <= 1e-9 * half[0] and abs(e.p - f.p) <= 1e-9 * half[1]
                     for f in found):
            found.append(e)
    def at(e: Equilibrium) -> np.ndarray:
        return (np.array([e.q, e.p]) - centre) / half

    local, slopes, settle = _walkers(H, centre, half, at)
    descended, _ = descend(failed, local, slopes, settle)
    for _, e in descended:
        if not any(abs(e.q - f.q) <= 1e-9 * half[0] and abs(e.p - f.p) <= 1e-9 * half[1]
                   for f in found):
            found.append(e)
    more, walks = explore([at(e) for e in found], local, slopes, settle,
                          hessians=[e.hessian * np.outer(half, half) for e in found])
    for _, e in more:
        if not any(abs(e.q - f.q) <= 1e-9 * half[0] and abs(e.p - f.p) <= 1e-9 * half[1]
                   for f in found):
            found.append(e)
    before = len(found)
    certified = certified_equilibria(H.compiled, np.array([q0, p0]), np.array([q1, p1]))
    unconfirmed = 0
    for root in certified.roots:
        if any(abs(root[0] - f.q) <= 1e-7 * half[0] and abs(root[1] - f.p) <= 1e-7 * half[1]
               for f in found):
            continue
        settled = settle((root - centre) / half)
        if settled is None:
            unconfirmed += 1
            continue
        e = settled[1]
        if not any(abs(e.q - f.q) <= 1e-9 * half[0] and abs(e.p - f.p) <= 1e-9 * half[1]
                   for f in found):
            found.append(e)
    found.sort(key=lambda e: (e.q, e.p))
    return Search(found, grid * grid, unevaluable, outside, unverified, flat, walks,
                  certified, unconfirmed, len(found) - before)


def _walkers(H: Hamiltonian, centre: np.ndarray, half: np.ndarray, at):
    """``local``, ``slopes`` and ``settle`` of :func:`stepsafe.systems.walks.explore` in
    box coordinates; ``settle`` verifies an end point as the starts' end points are."""
    def local(u: np.ndarray):
        try:
            g, A = _scaled(H, u, centre, half)
        except ExpressionError:
            return None
        return (g, A) if np.all(np.isfinite(A)) and np.all(np.isfinite(g)) else None

    def slopes(U: np.ndarray) -> np.ndarray:
        """The gradients at many points at once (the compiled gradient)."""
        G = H.compiled.gradient(centre + half * U) * half
        return np.where(np.isfinite(G), G, np.nan)

    def settle(u: np.ndarray):
        status, u = _newton_float(H, u, centre, half)
        e = _verify(H, u, centre, half) if status in ("ok", "stalled") else None
        return None if e is None else (at(e), e)

    return local, slopes, settle


def _scaled(H: Hamiltonian, u: np.ndarray, centre: np.ndarray, half: np.ndarray):
    """Gradient and Hessian of H in box coordinates ``x = centre + half * u``."""
    j = H.jet(*(centre + half * u))
    g = np.array(j.g) * half
    hqq, hqp, hpp = j.H
    A = np.array([[hqq, hqp], [hqp, hpp]]) * np.outer(half, half)
    return g, A


def _newton_float(H: Hamiltonian, u: np.ndarray, centre, half, iterations: int = 80):
    """Newton's method in box coordinates with the Hessian scaled by its diagonal; returns
    ("ok", u) converged, ("stalled", u) still creeping after ``iterations`` steps inside the
    box (a stiff zero does for hundreds of steps: high precision decides), ("outside", u)
    (it left the box, or cycles without creeping towards a point), ("unevaluable", u) or
    ("flat", u) (zero gradient and Hessian: no isolated equilibrium)."""
    steps: list[float] = []
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            try:
                g, A = _scaled(H, u, centre, half)
            except ExpressionError:
                return "unevaluable", u
            if not (np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
                return "unevaluable", u
            if not A.any():
                return ("flat" if not g.any() else "outside"), u
            d = np.sqrt(np.abs(np.diag(A)))
            d = np.where(d > 0, d, np.sqrt(np.abs(A).max()))
            try:
                step = np.linalg.lstsq(A / np.outer(d, d), g / d, rcond=1e-13)[0] / d
            except np.linalg.LinAlgError:
                return "outside", u
            u = u - step
            if not np.all(np.isfinite(u)) or np.abs(u).max() > 4.0:
                return "outside", u
            steps.append(float(np.abs(step).max()))
            if steps[-1] <= 1e-14:
                return ("ok", u) if np.abs(u).max() <= 1.0 + 1e-9 else ("outside", u)
    # still creeping towards a zero (steps shrinking, or down to rounding), or cycling
    # among points (not)
    creeping = steps[-1] <= 1e-8 or steps[-1] < 0.9 * steps[-10]
    return ("stalled", u) if np.abs(u).max() <= 1.0 + 1e-9 and creeping else ("outside", u)


def _verify(H: Hamiltonian, u: np.ndarray, centre, half) -> Equilibrium | None:
    """Newton's method in mpmath from a float64 end point; the equilibrium with its
    classification, or None when high precision does not converge to one in the box."""
    import mpmath as mp

    with mp.workdps(VERIFY_DPS):
        c = [mp.mpf(float(x)) for x in centre]
        w = [mp.mpf(float(x)) for x in half]
        x = [c[0] + w[0] * mp.mpf(float(u[0])), c[1] + w[1] * mp.mpf(float(u[1]))]
        steps: list[Any] = []
        for _ in range(VERIFY_ITERATIONS):
            jet = _mp_jet(H, x, w)
            if jet is None:
                return None
            (gq, gp), (hqq, hqp, hpp) = jet.g, jet.H
            det = hqq * hpp - hqp * hqp
            if det == 0:
                break
            dq, dp = (hpp * gq - hqp * gp) / det, (hqq * gp - hqp * gq) / det
            x = [x[0] - dq, x[1] - dp]
            size = max(abs(dq) / w[0], abs(dp) / w[1])
            steps.append(size)
            if size <= VERIFY_STEP:
                break
        if not steps or steps[-1] > (mp.mpf(10) ** -12 if det == 0 else VERIFY_STEP):
            return None  # did not converge: not an equilibrium we can vouch for
        uq, up = (x[0] - c[0]) / w[0], (x[1] - c[1]) / w[1]
        if max(abs(uq), abs(up)) > 1 + mp.mpf(10) ** -9:
            return None
        # Newton converges quadratically to a zero where the Hessian is regular and only
        # linearly where it is singular (q^4 at 0: each step 2/3 of the last). A stiff
        # regular zero (q^2 + 1e30 q^4) also creeps at first, far from it, so only the
        # end counts: the last steps did not collapse
        tail = steps[-4:]
        linear = len(tail) == 4 and all(b > mp.mpf("1e-3") * a for a, b in zip(tail, tail[1:]))
        # location uncertainty (box units): a few times the last steps (linear convergence
        # at a degenerate zero leaves an error comparable to the last step; after a
        # quadratic one the error is far below the last step)
        # (at least VERIFY_STEP, even where the gradient vanishes exactly: at 1e-76 of
        # sin(q)/q, cancellation makes both the gradient and the Hessian noise; a stiff
        # term, 1e308 q^4, then makes the Hessian over that distance, a bound, 4.8e249)
        dx = (4 * max(steps[-3:]) if linear else 4 * steps[-1]) + VERIFY_STEP
        shifted = [_mp_jet(H, [x[0] + sq * dx * w[0], x[1] + sp * dx * w[1]], w)
                   for sq, sp in ((1, 1), (-1, -1), (1, -1), (-1, 1))]
        if any(s is None for s in shifted):
            return None
        # the Hessian at the point: the mean over the four corners dx away (O(dx^2) off; the
        # point itself may sit where cancellations swamp the digits, e.g. sin(q)/q at 1e-70);
        # an entry within what the location uncertainty moves it is zero (e.g. H_pp = 2 a q
        # at q = 0 of alpha q p (p - 1)), so the point maps to its exact test model
        mean = [mp.fsum(s.H[i] for s in shifted) / 4 for i in range(3)]
        entries = [h if abs(h) > 2 * max(abs(s.H[i] - h) for s in shifted) else mp.mpf(0)
                   for i, h in enumerate(mean)]
        hqq, hqp, hpp = entries
        D = hqp * hqp - hqq * hpp
        spread = max(abs((s.H[1] ** 2 - s.H[0] * s.H[2]) - D) for s in shifted)
        terms = max(hqp * hqp, abs(hqq * hpp))
        undecided = abs(D) <= 2 * spread + mp.mpf(10) ** (-(VERIFY_DPS // 2)) * terms
        # a coordinate within the location's uncertainty of 0 is 0 (the equilibrium at the
        # origin, not at 1e-87)
        q, p = (mp.mpf(0) if abs(xi) <= dx * wi else xi for xi, wi in zip(x, w))
        return _classify(float(q), float(p), hqq, hqp, hpp, D,
                         undecided or linear or terms == 0)


def _mp_jet(H: Hamiltonian, x, w):
    """The mpmath jet at x; at a removable singularity (H not defined at the point but on
    both sides, with the same Hessian) the mean of the two sides a little way off."""
    import mpmath as mp

    try:
        return H.jet(x[0], x[1], lib=mp)
    except ExpressionError:
        pass
    eps = mp.mpf(VERIFY_STEP)
    sides = []
    for s in (1, -1):
        try:
            sides.append(H.jet(x[0] + s * eps * w[0], x[1] + s * eps * w[1], lib=mp))
        except ExpressionError:
            return None
    a, b = sides
    scale = max(max(abs(h) for h in a.H), mp.mpf(10) ** -300)
    if max(abs(ha - hb) for ha, hb in zip(a.H, b.H)) > mp.mpf(10) ** (-(VERIFY_DPS // 8)) * scale:
        return None  # a genuine singularity, not a removable one
    return Jet2((a.v + b.v) / 2, ((a.g[0] + b.g[0]) / 2, (a.g[1] + b.g[1]) / 2),
                ((a.H[0] + b.H[0]) / 2, (a.H[1] + b.H[1]) / 2, (a.H[2] + b.H[2]) / 2))


def _classify(q: float, p: float, hqq: Any, hqp: Any, hpp: Any, D: Any,
              degenerate: bool) -> Equilibrium:
    """The type and linear model from the Hessian entries and ``D = H_qp^2 - H_qq H_pp`` at
    high precision (mpmath numbers, whose exponent range is unbounded): the signs and
    ``beta`` are decided there and only the results are rounded to float64, so a centre
    ``1e-300 (q^2 + p^2)`` (``D = -4e-600``, below float64's range) is a centre of ``beta =
    2e-300``. ``D`` is reported as None when it is beyond float64's range."""
    import mpmath as mp

    hessian = np.array([[float(hqq), float(hqp)], [float(hqp), float(hpp)]])
    if any((float(h) == 0) != (h == 0) or not math.isfinite(float(h)) for h in (hqq, hqp, hpp)):
        raise ExpressionError(f"the Hessian of H at (q, p) = ({q:.6g}, {p:.6g}) has an entry "
                              "beyond the float64 range; rescale the units of H")
    rounded = float(D)
    # None: |D| beyond float64's range (its sign is used, not its float)
    shown = None if (rounded == 0 and D != 0) or not math.isfinite(rounded) else rounded
    if degenerate:
        return Equilibrium(q, p, 0.0, "degenerate", hessian, None, None)
    kind = "elliptic" if D < 0 else "hyperbolic"
    if hqp == 0:
        model = "oscillator" if mp.sign(hqq) == mp.sign(hpp) else "inverted"
        return Equilibrium(q, p, shown, kind, hessian, _rate(mp.sqrt(abs(hqq * hpp))), model)
    if hqq == 0 and hpp == 0:
        return Equilibrium(q, p, shown, kind, hessian, _rate(abs(hqp)),
                           "saddle" if hqp > 0 else "saddle-p")
    return Equilibrium(q, p, shown, kind, hessian, _rate(mp.sqrt(abs(D))), "coupled")


def _rate(beta: Any) -> float:
    """An mpmath rate as a float; beyond float64's range it cannot be analysed."""
    value = float(beta)
    if value == 0 or not math.isfinite(value):
        raise ExpressionError(f"the equilibrium's rate {_mp_text(beta)} is beyond the float64 "
                              "range; rescale the units of H")
    return value


def _mp_text(x: Any) -> str:
    """An mpmath number in a few digits, whatever its exponent."""
    import mpmath as mp

    return mp.nstr(x, 6)
