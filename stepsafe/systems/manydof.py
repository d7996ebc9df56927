"""Nonlinear systems of n degrees of freedom: named coordinates and momenta, equilibria in a
box, their exact linearisation and type.

::

    system:
      hamiltonian: "(px**2 + py**2)/2 + (x**2 + y**2)/2 + x**2*y - y**3/3"
      q: [x, y]
      p: [px, py]
      box: {x: [-1.2, 1.2], y: [-1.2, 1.2], px: [-1, 1], py: [-1, 1]}
      energy_below: 0.2          # optional: only equilibria the motion can reach

H is the restricted expression language of :mod:`stepsafe.files.expressions` (never
``eval``) in the named variables and parameters. Derivatives are exact: the gradient and
Hessian in all 2n variables are differentiated symbolically on the expression graph
(:mod:`stepsafe.systems.compiler`), never by finite differences.

Equilibria (``grad H = 0``) are found by Newton's method from a Halton set of starts in
the box (box coordinates, each variable scaled to [-1, 1]; plain Newton steps, then
steps damped so that ``|grad H|`` decreases; where both fail, a descent to the minimum
whose basin the start lies in), merged when they coincide, and each verified: the linear
change of H along every variable is negligible next to its local change
(:func:`_verified`). From every equilibrium found, walks along its eigendirections reach
the ones it is connected to (down from a saddle into the well behind it, up from a
minimum over the ridge), and each one found is followed in turn
(:mod:`stepsafe.systems.walks`, which also says whether the search vouches for
completeness). An equilibrium off every walk whose basin no start reaches (a narrow well
away from those found) can still be missed; ``starts:`` raises their number. The type
comes from the eigenvalues ``mu`` of ``J S`` (S the Hessian, classified in units where
it is of order 1: :func:`stepsafe.systems.linear.normalised`): pairs ``+-i omega`` are
elliptic, ``+-lambda`` hyperbolic, quadruplets ``+-a +-ib`` loxodromic, an eigenvalue
within rounding of 0 degenerate (no linear model): ``elliptic`` (a centre: all
elliptic), ``hyperbolic`` (all hyperbolic), ``mixed`` (``index`` k hyperbolic pairs among
elliptic ones, as transition states have), ``loxodromic`` or ``degenerate`` (a zero mode;
when no family of equilibria continues along it, its other modes are still analysed; a
family, a line or ring of equilibria from a symmetry, is flagged: its members across the
box are not all reached).
"""

from __future__ import annotations

import ast
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.files.expressions import ExpressionError, parse
from stepsafe.systems.compiler import Compiled, NotReal, from_tree, trace
from stepsafe.systems.dynamics import compiled_system
from stepsafe.systems.intervals import Certified, certified_equilibria, certified_gaps
from stepsafe.systems.linear import hamiltonian_matrix, normalised
from stepsafe.systems.walks import Walks, descend, explore

FUNCTIONS = ("sin", "cos", "exp", "log", "sqrt", "cosh", "sinh", "tanh")
#: Degrees of freedom at most (2n variables, a 2n x 2n Hessian per Newton step).
MAX_DOF = 20
#: Newton starts at most (``starts:``; about a millisecond each in 4 variables), and by
#: default per variable.
MAX_STARTS = 1 << 16
STARTS_PER_VARIABLE = 32
NEWTON_ITERATIONS = 40
#: The linear change of H an equilibrium may show, relative to its local change (see
#: :func:`_verified`).
RESIDUAL = 1e-7

class Jet(NamedTuple):
    """H at a point with its gradient ``g`` (N,) and Hessian ``h`` (N, N)."""

    v: float
    g: np.ndarray
    h: np.ndarray


@dataclass(frozen=True, eq=False)
class ManyDofHamiltonian:
    """``H(q, p)`` in the named coordinates and momenta (``q`` and ``p`` lists of names)."""

    text: str
    q: tuple[str, ...]
    p: tuple[str, ...]
    parameters: dict[str, float]
    tree: Any = field(repr=False)
    #: a Python function ``H(q, p, ops)`` instead of an expression (see :func:`parse_many`)
    function: Callable[..., Any] | None = field(default=None, repr=False)
    #: where the function was given (``"system"`` from the API), for its errors
    where: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return self.q + self.p


    @cached_property
    def compiled(self) -> Compiled:
        """H's expression graph with its derivatives (:mod:`stepsafe.systems.compiler`);
        a Python function is traced once on symbolic variables. A function that is not
        real (returns or combines the variables with a complex, a text, ...) is a
        StepsafeError naming the key; one that fails otherwise, an ExpressionError."""
        if self.function is None:
            return Compiled(from_tree(self.tree, self.text.strip(), self.names,
                                      self.parameters), self.names)
        try:
            node = trace(self.function, self.q, self.p)
        except NotReal as exc:  # e.g. q[0] * 1j: H is not real anywhere, a bad input
            raise StepsafeError(f"the Hamiltonian function is not real: {exc} (H must be "
                                "real: combine q, p, real numbers and ops)", self._key) from None
        except ExpressionError:
            raise
        except Exception as exc:  # the user's code: report, do not crash
            raise ExpressionError(f"the Hamiltonian function raised {type(exc).__name__}: "
                                  f"{exc}") from None
        return Compiled(node, self.names)

    @cached_property
    def compiled_or_none(self) -> Compiled | None:
        """:attr:`compiled`, or None where the function cannot be traced."""
        try:
            return self.compiled
        except (ExpressionError, StepsafeError):
            return None

    @property
    def _key(self) -> str | None:
        return f"{self.where}::$.system.hamiltonian" if self.where else None

    def jet(self, x: np.ndarray) -> Jet:
        """Value, gradient and Hessian at x (the 2n variables, q then p); an
        ExpressionError where they are not finite."""
        x = np.asarray(x, dtype=float)
        v, g = self.compiled.energy_gradient(x)
        h = self.compiled.hessian(x)
        if not (np.isfinite(v) and np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
            raise ExpressionError("H or its derivatives are not finite here")
        return Jet(float(v), g, h)

    @property
    def separable(self) -> bool:
        """Whether every term of H is in the coordinates alone or the momenta alone (for a
        function: whether H_qp is exactly 0 at sixteen pseudo-random points of [-1, 1]^2n,
        which forward AD gives exactly when no term mixes them)."""
        if self.function is not None:
            n = len(self.q)
            points = np.random.default_rng(0).uniform(-1, 1, (16, 2 * n))
            try:
                return all(not self.jet(x).h[:n, n:].any() for x in points)
            except ExpressionError:
                return False
        terms = [self.tree]
        out = []
        while terms:
            node = terms.pop()
            if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub)):
                terms += [node.left, node.right]
            elif isinstance(node, ast.UnaryOp):
                terms.append(node.operand)
            else:
                out.append(node)
        for node in out:
            names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
            if names & set(self.q) and names & set(self.p):
                return False
        return True




def parse_many(text: Any, q: Any, p: Any, parameters: dict[str, float],
               where: str) -> ManyDofHamiltonian:
    """Validate the variable lists and the expression (errors name the key); ``text`` may
    be a Python function ``H(q, p, ops)`` (from the API): ``q`` and ``p`` are lists of
    stepsafe's AD numbers supporting + - * / ** with each other and with numbers, ``ops``
    gives sin, cos, exp, log, sqrt, cosh, sinh, tanh and pi for them."""
    def fail(key: str, message: str) -> StepsafeError:
        return StepsafeError(message, f"{where}::$.system.{key}")

    if callable(text):
        qs, ps = _names(q, p, parameters, fail)
        return ManyDofHamiltonian(getattr(text, "__name__", "H"), qs, ps, dict(parameters),
                                  None, text, where)
    if not isinstance(text, str):
        raise fail("hamiltonian", "must be an expression in the named variables")
    qs, ps = _names(q, p, parameters, fail)
    names = qs + ps
    try:
        expr = parse(text, FUNCTIONS)
    except ExpressionError as exc:
        raise fail("hamiltonian", f"{exc} in {text[:60]!r}") from None
    unknown = expr.names - set(names) - set(parameters) - {"pi"}
    if unknown:
        raise fail("hamiltonian", f"unknown name {sorted(unknown)[0]!r} (use the names of q, "
                                  "p, the parameters and pi)")
    return ManyDofHamiltonian(text, qs, ps, dict(parameters), expr.tree)


def _names(q: Any, p: Any, parameters: dict[str, float], fail
           ) -> tuple[tuple[str, ...], tuple[str, ...]]:
    lists = {}
    for key, names in (("q", q), ("p", p)):
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise fail(key, "must be a non-empty list of names")
        for name in names:
            if not name.isidentifier() or name in FUNCTIONS or name == "pi" \
                    or name.startswith("_"):
                raise fail(key, f"{name!r} is not an allowed variable name")
        lists[key] = tuple(names)
    if len(lists["q"]) != len(lists["p"]):
        raise fail("p", f"{len(lists['p'])} momenta for {len(lists['q'])} coordinates")
    if len(lists["q"]) > MAX_DOF:
        raise fail("q", f"{len(lists['q'])} degrees of freedom; at most {MAX_DOF}")
    names = lists["q"] + lists["p"]
    if len(set(names)) != len(names):
        raise fail("p", "a name appears twice among q and p")
    clash = set(names) & set(parameters)
    if clash:
        raise fail("parameters", f"{sorted(clash)[0]!r} is also a variable")
    return lists["q"], lists["p"]


@dataclass(frozen=True, eq=False)
class ManyDofEquilibrium:
    x: np.ndarray  # q then p
    energy: float
    hessian: np.ndarray
    kind: str  # elliptic | hyperbolic | mixed | loxodromic | degenerate
    index: int  # hyperbolic pairs
    frequencies: tuple[float, ...]  # elliptic pairs' omega
    rates: tuple[float, ...]  # hyperbolic pairs' lambda
    family: bool = False  # a zero mode along which the equilibria continue (a line, a ring)


def halton(count: int, dim: int) -> np.ndarray:
    """The first ``count`` points of the Halton sequence in [-1, 1]^dim."""
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71, 73,
              79, 83, 89, 97, 101, 103, 107, 109, 113, 127, 131, 137, 139, 149, 151, 157,
              163, 167, 173][:dim]
    out = np.empty((count, dim))
    for j, base in enumerate(primes):
        for i in range(count):
            f, r, k = 1.0, 0.0, i + 1
            while k:
                f /= base
                r += f * (k % base)
                k //= base
            out[i, j] = r
    return 2 * out - 1


@dataclass(frozen=True)
class ManyDofSearch:
    equilibria: tuple[ManyDofEquilibrium, ...]
    starts: int
    failed: int  # starts that did not converge in the box
    reason: str | None = None  # why H could not be evaluated, when that stopped starts
    stopped: int | None = None  # starts tried before the time budget ran out (None: all)
    walks: Walks = Walks()  # the walks from the equilibria the starts found
    unevaluable: int = 0  # starts where H or its derivatives could not be evaluated
    undescended: int = 0  # starts where Newton failed not followed down (the time budget)
    certified: Certified | None = None  # the interval branch and bound
    unconfirmed: int = 0  # equilibria it proved that Newton's method did not verify
    found_by_bound: int = 0  # equilibria the starts and walks missed and the bound found

    def explain(self) -> str:
        text = (f"{self.starts} Newton starts, {self.failed} did not converge to a point of "
                "the box")
        return text + (f"; H could not be evaluated: {self.reason}" if self.reason else "")

    def gaps(self) -> list[str]:
        """Why the search cannot vouch for completeness (empty when it can: the interval
        branch and bound proved every equilibrium of the box found)."""
        return certified_gaps(self.certified, self.unconfirmed)

    def walk_gaps(self) -> list[str]:
        """What the starts and walks left out (a heuristic's account, not a proof)."""
        out = self.walks.gaps()
        if self.undescended:
            out.append(f"{self.undescended} start(s) where Newton's method failed were not "
                       "followed down (the time budget ran out)")
        if self.unevaluable:
            out.append(f"H could not be evaluated at {self.unevaluable} start(s): where it "
                       "is undefined the box is not searched")
        return out


def find_many(H: ManyDofHamiltonian, lo: np.ndarray, hi: np.ndarray,
              starts: int | None = None, deadline: float | None = None) -> ManyDofSearch:
    """Every equilibrium Newton's method reaches from a Halton set of starts in the box
    (from each start plain Newton steps first, they jump into narrow basins, then damped
    ones if those fail), and every one the walks of :mod:`stepsafe.systems.walks` reach
    from those."""
    N = lo.size
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    count = min(MAX_STARTS, starts or STARTS_PER_VARIABLE * N)
    points = halton(count, N)
    found: list[np.ndarray] = []
    stuck: list[np.ndarray] = []  # starts from which Newton's method did not converge
    failed = unevaluable = 0
    reasons: list[str] = []
    for k, u in enumerate(points):
        if deadline is not None and time.monotonic() > deadline:
            return ManyDofSearch((), count, failed, None, k)
        x = None
        for damped in (False, True):
            try:
                x = _newton(H, u, centre, half, damped)
            except ExpressionError as exc:
                reasons.append(str(exc))
                x = None
                if not damped:
                    unevaluable += 1
                    break
            if x is not None:
                break
        if x is None:
            failed += 1
            stuck.append(u)
            continue
        if not any(np.all(np.abs(x - y) <= 1e-7 * half) for y in found):
            found.append(x)
    local, slopes, settle = _walkers(H, centre, half)
    descended, undescended = descend(stuck, local, slopes, settle, deadline)
    for _, x in descended:
        if not any(np.all(np.abs(x - y) <= 1e-7 * half) for y in found):
            found.append(x)
    new, walks = explore([(x - centre) / half for x in found], local, slopes, settle,
                         deadline)
    for _, x in new:
        if not any(np.all(np.abs(x - y) <= 1e-7 * half) for y in found):
            found.append(x)
    before = len(found)
    certified, unconfirmed = _certify(H, lo, hi, found, centre, half, deadline)
    classified = []
    for x in found:
        e = _classify(H, x)
        if e.kind == "degenerate" and _is_family(H, e, centre, half):
            e = dataclasses.replace(e, family=True)
        classified.append(e)
    equilibria = tuple(sorted(classified, key=lambda e: (e.energy, tuple(e.x))))
    reason = reasons[0] if reasons and len(reasons) >= failed > 0 and not found else None
    return ManyDofSearch(equilibria, count, failed, reason, walks=walks,
                         unevaluable=unevaluable, undescended=undescended,
                         certified=certified, unconfirmed=unconfirmed,
                         found_by_bound=len(found) - before)


def _certify(H: ManyDofHamiltonian, lo: np.ndarray, hi: np.ndarray, found: list[np.ndarray],
             centre: np.ndarray, half: np.ndarray, deadline: float | None
             ) -> tuple[Certified | None, int]:
    """The interval branch and bound on grad H in the box; each equilibrium it proves
    that the starts and walks missed is verified by Newton's method from there and added
    to ``found``. Returns the bound's result (None: H has no expression graph) and the
    count of proved equilibria Newton's method did not verify."""
    compiled = H.compiled_or_none
    if compiled is None:
        return None, 0
    result = certified_equilibria(compiled, lo, hi, deadline=deadline)
    unconfirmed = 0
    for root in result.roots:
        if any(np.all(np.abs(root - y) <= 1e-7 * half) for y in found):
            continue
        x = None
        for damped in (False, True):
            try:
                x = _newton(H, (root - centre) / half, centre, half, damped)
            except ExpressionError:
                x = None
            if x is not None:
                break
        if x is None:
            unconfirmed += 1
        elif not any(np.all(np.abs(x - y) <= 1e-7 * half) for y in found):
            found.append(x)
    return result, unconfirmed


def centres(H: ManyDofHamiltonian, lo: np.ndarray, hi: np.ndarray,
            starts: int | None = None) -> list[ManyDofEquilibrium]:
    """The elliptic equilibria Newton's method reaches from a Halton set of starts in the
    box, all starts advanced at once on the compiled gradient and Hessian (pseudo-inverse
    steps, so a singular Hessian does not stop the batch), each end point verified
    (:func:`_verified`) and classified; sorted by energy. A start to run near, found fast:
    no completeness is claimed (the search of :func:`find_many` is for the analysis)."""
    N = lo.size
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    count = min(MAX_STARTS, starts or STARTS_PER_VARIABLE * N)
    X = centre + half * halton(count, N)
    compiled = H.compiled
    with np.errstate(all="ignore"):
        for _ in range(NEWTON_ITERATIONS):
            g = compiled.gradient(X)
            S = compiled.hessian(X)
            ok = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(S), axis=(1, 2))
            if not ok.any():
                break
            X = X[ok]
            step = np.einsum("bij,bj->bi", np.linalg.pinv(S[ok], rcond=1e-13), g[ok])
            X = X - step
            inside = np.all(np.abs(X - centre) <= 1.5 * half, axis=1)
            X = X[inside]
            if np.all(np.abs(step[inside]) <= 1e-14 * half):
                break
    found: list[np.ndarray] = []
    for x in X:
        if np.all(np.abs(x - centre) <= half * (1 + 1e-9)) and \
                not any(np.all(np.abs(x - y) <= 1e-7 * half) for y in found):
            x = np.where(np.abs(x) <= 1e-12 * half, 0.0, x)
            if _verified(H, x, half):
                found.append(x)
    out = [e for e in (_classify(H, x) for x in found) if e.kind == "elliptic"]
    return sorted(out, key=lambda e: (e.energy, tuple(e.x)))


def _walkers(H: ManyDofHamiltonian, centre: np.ndarray, half: np.ndarray):
    """``local``, ``slopes`` and ``settle`` of :func:`stepsafe.systems.walks.explore` for H
    in box coordinates ``x = centre + half u``."""
    scale = np.outer(half, half)

    def local(u: np.ndarray):
        try:
            j = H.jet(centre + half * u)
        except ExpressionError:
            return None
        return j.g * half, j.h * scale

    def slopes(U: np.ndarray) -> np.ndarray:
        try:
            G = H.compiled.gradient(centre + half * U) * half
        except (ExpressionError, ValueError, ZeroDivisionError, OverflowError,
                FloatingPointError, TypeError):
            return np.full(U.shape, np.nan)
        return np.where(np.isfinite(G), G, np.nan)

    def settle(u: np.ndarray):
        for damped in (False, True):
            try:
                x = _newton(H, u, centre, half, damped)
            except ExpressionError:
                return None
            if x is not None:
                return (x - centre) / half, x
        return None

    return local, slopes, settle


def _newton(H: ManyDofHamiltonian, u: np.ndarray, centre: np.ndarray, half: np.ndarray,
            damped: bool) -> np.ndarray | None:
    """Newton's method on grad H in box coordinates (``damped``: steps halved until
    ``|grad H|`` decreases); the verified point (:func:`_verified`) or None. An
    ExpressionError at the start propagates (it says why H cannot be evaluated)."""
    def state(u):
        j = H.jet(centre + half * u)
        return j.g * half, j.h * np.outer(half, half)

    g, A = state(u)
    converged = False
    for _ in range(NEWTON_ITERATIONS):
        diag = np.sqrt(np.abs(np.diag(A)))  # equilibrate: any units, any anisotropy
        diag = np.where(diag > 0, diag, max(float(np.sqrt(np.abs(A).max())), 1e-300))
        try:
            step = np.linalg.lstsq(A / np.outer(diag, diag), g / diag, rcond=1e-13)[0] / diag
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(step)):
            return None
        norm = float(np.abs(g).max())
        t = 1.0
        for _ in range(16 if damped else 1):
            trial = u - t * step
            if np.abs(trial).max() <= 1.5:
                try:
                    g2, A2 = state(trial)
                    if not damped or float(np.abs(g2).max()) < norm \
                            or t * np.abs(step).max() < 1e-12:
                        break
                except ExpressionError:
                    pass
            t /= 2
        else:
            return None
        if np.abs(trial).max() > 1.5:
            return None
        u, g, A = trial, g2, A2
        if t * np.abs(step).max() <= 1e-14:
            converged = True
            break
    if not converged or np.abs(u).max() > 1 + 1e-9:
        return None
    x = centre + half * u
    # a coordinate within the location's rounding of 0 is 0 (the origin, not 1e-34)
    x = np.where(np.abs(x) <= 1e-12 * half, 0.0, x)
    return x if _verified(H, x, half) else None


def _is_family(H: ManyDofHamiltonian, e: ManyDofEquilibrium, centre: np.ndarray,
               half: np.ndarray) -> bool:
    """Whether the equilibria continue along the zero mode: Newton's method from a point
    a little way along the Hessian's null direction (box units) ends at another
    equilibrium there, not back at this one."""
    w, V = np.linalg.eigh(e.hessian * np.outer(half, half))
    v = V[:, int(np.argmin(np.abs(w)))]
    u0 = (e.x - centre) / half
    for sign in (1.0, -1.0):
        u = u0 + sign * 1e-3 * v
        if np.abs(u).max() > 1:
            continue
        try:
            x = _newton(H, u, centre, half, damped=True)
        except ExpressionError:
            continue
        # back at this point (an isolated degenerate zero, where Newton creeps back) or
        # still about as far as the step went (the family)
        if x is not None and float(np.abs((x - e.x) / half).max()) \
                > 0.25 * 1e-3 * float(np.abs(v).max()):
            return True
    return False


def _verified(H: ManyDofHamiltonian, x: np.ndarray, half: np.ndarray) -> bool:
    """Whether grad H vanishes at x on the scale of H there: along each variable the
    linear change ``|dH/dx_i| d_i`` over ``d_i = 1e-3 w_i`` is at most ``RESIDUAL`` times
    the change of H over that distance in the direction where H changes most (so a point
    where Newton stalled on a least-squares step, with a gradient left in a flat
    direction, is refused whatever the size of H over the box)."""
    try:
        g = H.jet(x).g
        h0 = H.jet(x).v
        d = 1e-3 * half
        changes = []
        for i in range(x.size):
            e = np.zeros(x.size)
            e[i] = d[i]
            changes += [abs(H.jet(x + e).v - h0), abs(H.jet(x - e).v - h0)]
    except ExpressionError:
        return False
    top = max(changes)
    for i in range(x.size):
        # along each variable: the linear part of H's change next to the whole change
        # there, or (a flat direction) next to the largest change in any direction
        local = max(changes[2 * i], changes[2 * i + 1]) or top
        if abs(g[i] * d[i]) > RESIDUAL * local / 1e-3:
            return False
    return True


def _classify(H: ManyDofHamiltonian, x: np.ndarray) -> ManyDofEquilibrium:
    """The type from the eigenvalues of J S; an eigenvalue within the rounding of the
    eigensolver (a few 1e3 (2n) eps |mu|_max, as stepsafe.systems.linear counts it) of a
    zero real or imaginary part has that part zero, one within it of 0 is a zero mode."""
    jet = H.jet(x)
    S = 0.5 * (jet.h + jet.h.T)
    # in the units where S is of order 1 (exact powers of two; the rates scale back)
    scaled, exponent = normalised(S)
    mu = np.linalg.eigvals(hamiltonian_matrix(scaled))
    tol = 1e3 * S.shape[0] * float(np.finfo(float).eps) * max(float(np.abs(mu).max()),
                                                              1e-300)
    upper = mu[(mu.imag > tol) | ((np.abs(mu.imag) <= tol) & (mu.real > tol))]
    zero = int((np.abs(mu) <= tol).sum())
    # a zero mode makes S singular; its eigenvalues (symmetric, well conditioned) tell it
    # even where J S has a Jordan block at 0, whose eigenvalues rounding moves by sqrt(eps)
    s_eig = np.abs(np.linalg.eigvalsh(scaled))
    if s_eig.min() <= 1e3 * S.shape[0] * float(np.finfo(float).eps) * s_eig.max():
        zero = max(zero, 2)
    freqs = tuple(sorted(float(np.ldexp(m.imag, exponent)) for m in upper
                         if abs(m.real) <= tol))
    rates = tuple(sorted(float(np.ldexp(m.real, exponent)) for m in upper
                         if abs(m.imag) <= tol))
    lox = sum(1 for m in upper if abs(m.real) > tol and abs(m.imag) > tol)
    if zero:
        kind = "degenerate"
    elif lox:
        kind = "loxodromic"
    elif not rates:
        kind = "elliptic"
    elif not freqs:
        kind = "hyperbolic"
    else:
        kind = "mixed"
    return ManyDofEquilibrium(x, float(jet.v), S, kind, len(rates), freqs, rates)


def system_of(H: ManyDofHamiltonian):
    """The equations of motion for :mod:`stepsafe.core.integrator` (the compiled
    gradient; see :func:`stepsafe.systems.dynamics.compiled_system`)."""
    return compiled_system(H.compiled, len(H.q), H.separable, H._key)
