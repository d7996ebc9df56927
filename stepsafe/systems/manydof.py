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
``eval``) in the named variables and parameters. Derivatives are exact: H is evaluated on
second-order jets (value, gradient, Hessian in all 2n variables), forward-mode automatic
differentiation, never finite differences.

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
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from stepsafe.exceptions import StepsafeError
from stepsafe.files.expressions import ExpressionError, parse
from stepsafe.systems.compiler import Compiled, from_tree, trace
from stepsafe.systems.intervals import Certified, certified_equilibria, certified_gaps
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

_F = {"sin": (np.sin, np.cos, lambda x: -np.sin(x)),
      "cos": (np.cos, lambda x: -np.sin(x), lambda x: -np.cos(x)),
      "exp": (np.exp, np.exp, np.exp),
      "log": (np.log, lambda x: 1 / x, lambda x: -1 / x ** 2),
      "sqrt": (np.sqrt, lambda x: 0.5 / np.sqrt(x), lambda x: -0.25 / x ** 1.5),
      "cosh": (np.cosh, np.sinh, np.cosh),
      "sinh": (np.sinh, np.cosh, np.sinh),
      "tanh": (np.tanh, lambda x: 1 - np.tanh(x) ** 2,
               lambda x: -2 * np.tanh(x) * (1 - np.tanh(x) ** 2))}


class NotReal(TypeError):
    """A Hamiltonian function combined q or p with something that is not a real number."""


class Jet:
    """A value with its gradient (N,) and Hessian (N, N): second-order forward AD."""

    __slots__ = ("v", "g", "h")

    def __init__(self, v: float, g: np.ndarray, h: np.ndarray) -> None:
        self.v, self.g, self.h = v, g, h

    def lift(self, o: Any) -> Jet:
        """A number as a constant jet (Python callables mix numbers with jets)."""
        if isinstance(o, Jet):
            return o
        if isinstance(o, (int, float)) and not isinstance(o, bool):
            return Jet(float(o), np.zeros_like(self.g), np.zeros_like(self.h))
        raise NotReal(f"cannot combine a jet with {type(o).__name__}")

    def __add__(self, o: Any) -> Jet:
        o = self.lift(o)
        return Jet(self.v + o.v, self.g + o.g, self.h + o.h)

    def __sub__(self, o: Any) -> Jet:
        o = self.lift(o)
        return Jet(self.v - o.v, self.g - o.g, self.h - o.h)

    def __radd__(self, o: Any) -> Jet:
        return self.lift(o) + self

    def __rsub__(self, o: Any) -> Jet:
        return self.lift(o) - self

    def __rmul__(self, o: Any) -> Jet:
        return self.lift(o) * self

    def __rtruediv__(self, o: Any) -> Jet:
        return self.lift(o) / self

    def __pow__(self, o: Any) -> Jet:
        constant = not isinstance(o, Jet) or (not o.g.any() and not o.h.any())
        return self.power(self.lift(o), constant)

    def __neg__(self) -> Jet:
        return Jet(-self.v, -self.g, -self.h)

    def __mul__(self, o: Any) -> Jet:
        o = self.lift(o)
        cross = np.outer(self.g, o.g)
        return Jet(self.v * o.v, self.v * o.g + o.v * self.g,
                   self.v * o.h + o.v * self.h + cross + cross.T)

    def chain(self, f0: float, f1: float, f2: float) -> Jet:
        if f2 == 0.0:
            return Jet(f0, f1 * self.g, f1 * self.h)
        return Jet(f0, f1 * self.g, f1 * self.h + f2 * np.outer(self.g, self.g))

    def __truediv__(self, o: Any) -> Jet:
        o = self.lift(o)
        if o.v == 0:
            raise ZeroDivisionError("division by zero")
        return self * o.chain(1 / o.v, -1 / o.v ** 2, 2 / o.v ** 3)

    def power(self, o: Jet, constant: bool) -> Jet:
        if constant:
            n, x = o.v, self.v
            if x <= 0 and n != int(n):
                raise ValueError("power of a non-positive base")
            if x == 0 and n == int(n) and n >= 0:
                k = int(n)
                return self.chain(0.0 if k else 1.0, 1.0 if k == 1 else 0.0,
                                  2.0 if k == 2 else 0.0)
            return self.chain(x ** n, n * x ** (n - 1), n * (n - 1) * x ** (n - 2))
        if self.v <= 0:
            raise ValueError("power of a non-positive base")
        log = self.chain(math.log(self.v), 1 / self.v, -1 / self.v ** 2)
        e = math.exp((o * log).v)
        return (o * log).chain(e, e, e)

    def call(self, name: str) -> Jet:
        if name in ("log", "sqrt") and self.v <= 0:
            raise ValueError(f"{name} of a non-positive number")
        f0, f1, f2 = _F[name]
        x = self.v
        return self.chain(float(f0(x)), float(f1(x)), float(f2(x)))


class Dual:
    """Values of shape (m,) with their gradients (N, m): first-order forward AD over m
    points at once (the integration engine's force evaluations)."""

    __slots__ = ("v", "d")

    def __init__(self, v: Any, d: Any) -> None:
        self.v, self.d = v, d

    def lift(self, o: Any) -> Dual:
        if isinstance(o, Dual):
            return o
        if isinstance(o, (int, float)) and not isinstance(o, bool):
            return Dual(np.full_like(self.v, float(o)), np.zeros_like(self.d))
        raise NotReal(f"cannot combine a dual number with {type(o).__name__}")

    def __add__(self, o: Any) -> Dual:
        o = self.lift(o)
        return Dual(self.v + o.v, self.d + o.d)

    def __sub__(self, o: Any) -> Dual:
        o = self.lift(o)
        return Dual(self.v - o.v, self.d - o.d)

    def __radd__(self, o: Any) -> Dual:
        return self.lift(o) + self

    def __rsub__(self, o: Any) -> Dual:
        return self.lift(o) - self

    def __rmul__(self, o: Any) -> Dual:
        return self.lift(o) * self

    def __rtruediv__(self, o: Any) -> Dual:
        return self.lift(o) / self

    def __pow__(self, o: Any) -> Dual:
        return self.power(self.lift(o), not isinstance(o, Dual) or not np.any(o.d))

    def __neg__(self) -> Dual:
        return Dual(-self.v, -self.d)

    def __mul__(self, o: Any) -> Dual:
        o = self.lift(o)
        return Dual(self.v * o.v, self.v * o.d + o.v * self.d)

    def __truediv__(self, o: Any) -> Dual:
        o = self.lift(o)
        r = 1.0 / o.v
        return Dual(self.v * r, (self.d * o.v - self.v * o.d) * r * r)

    def power(self, o: Dual, constant: bool) -> Dual:
        if constant:
            n = o.v
            return Dual(self.v ** n, n * self.v ** (n - 1) * self.d)
        value = self.v ** o.v
        return Dual(value, value * (o.d * np.log(self.v) + o.v * self.d / self.v))

    def call(self, name: str) -> Dual:
        f0, f1, _ = _F[name]
        return Dual(f0(self.v), f1(self.v) * self.d)


def _constant(node: ast.AST, variables: set[str]) -> bool:
    return not any(isinstance(n, ast.Name) and n.id in variables for n in ast.walk(node))


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
    def compiled_or_none(self) -> Compiled | None:
        """H's expression graph with its derivatives (None: a Python function that
        cannot be traced on symbolic variables)."""
        try:
            if self.function is not None:
                node = trace(self.function, self.q, self.p)
            else:
                node = from_tree(self.tree, self.text.strip(), self.names, self.parameters)
        except Exception:  # the user's function on symbolic variables: any failure
            return None
        return Compiled(node, self.names)

    @cached_property
    def _program(self) -> Callable[[dict[str, Any], Callable[[float], Any]], Any]:
        """H as nested closures of (env, make): parsed once (constants read, exponents
        classified), then evaluated on jets or duals without walking the tree."""
        if self.function is not None:
            return self._call

        variables = set(self.names)

        def build(node: ast.AST):
            if isinstance(node, ast.Constant):
                value = float(node.value)  # Python reads a decimal literal as float() does
                return lambda env, make: make(value)
            if isinstance(node, ast.Name):
                name = node.id
                return lambda env, make: env[name]
            if isinstance(node, ast.UnaryOp):
                inner = build(node.operand)
                if isinstance(node.op, ast.USub):
                    return lambda env, make: -inner(env, make)
                return inner
            if isinstance(node, ast.Call):
                arg, fname = build(node.args[0]), node.func.id
                return lambda env, make: arg(env, make).call(fname)
            assert isinstance(node, ast.BinOp)
            left, right = build(node.left), build(node.right)
            if isinstance(node.op, ast.Add):
                return lambda env, make: left(env, make) + right(env, make)
            if isinstance(node.op, ast.Sub):
                return lambda env, make: left(env, make) - right(env, make)
            if isinstance(node.op, ast.Mult):
                return lambda env, make: left(env, make) * right(env, make)
            if isinstance(node.op, ast.Div):
                return lambda env, make: left(env, make) / right(env, make)
            constant = _constant(node.right, variables)

            def power(env, make):
                b = right(env, make)
                if constant and isinstance(b, Jet) and abs(b.v) > 64:
                    raise ValueError("exponent above 64")
                return left(env, make).power(b, constant)

            return power

        return build(self.tree)

    def _call(self, env: dict[str, Any], make: Callable[[float], Any]) -> Any:
        """The user's function on jets or duals; numbers it returns are lifted."""
        q = [env[name] for name in self.q]
        p = [env[name] for name in self.p]
        try:
            out = self.function(q, p, OPS)
        except (ZeroDivisionError, ValueError, OverflowError, FloatingPointError):
            raise
        except NotReal as exc:  # e.g. q[0] * 1j: H is not real anywhere, a bad input
            raise StepsafeError(f"the Hamiltonian function is not real: {exc} (H must be "
                                "real: combine q, p, real numbers and ops)", self._key) from None
        except Exception as exc:  # the user's code: report, do not crash
            raise ValueError(f"the Hamiltonian function raised {type(exc).__name__}: "
                             f"{exc}") from None
        if isinstance(out, (Jet, Dual)):
            return out
        if isinstance(out, (bool, np.bool_)) or not isinstance(out, (int, float, np.integer,
                                                                      np.floating)):
            # a complex, a text or a container is no energy at any point: a bad input
            raise StepsafeError(f"the Hamiltonian function returned {type(out).__name__} "
                                f"{repr(out)[:40]}, not a real number (H must be "
                                "real: combine q, p, real numbers and ops)", self._key)
        return make(float(out))

    @property
    def _key(self) -> str | None:
        return f"{self.where}::$.system.hamiltonian" if self.where else None

    def jet(self, x: np.ndarray) -> Jet:
        """Value, gradient and Hessian at x (the 2n variables, q then p)."""
        N = len(self.names)
        zero_g, zero_h = np.zeros(N), np.zeros((N, N))
        env: dict[str, Any] = {name: Jet(float(x[i]), np.eye(N)[i], zero_h)
                               for i, name in enumerate(self.names)}
        env.update({k: Jet(float(v), zero_g, zero_h) for k, v in self.parameters.items()})
        env["pi"] = Jet(math.pi, zero_g, zero_h)
        try:
            with np.errstate(over="raise", divide="raise", invalid="raise", under="ignore"):
                out = self._program(env, lambda c: Jet(c, zero_g, zero_h))
        except (ZeroDivisionError, ValueError, OverflowError, FloatingPointError) as exc:
            raise ExpressionError(str(exc) or type(exc).__name__) from None
        if not (math.isfinite(out.v) and np.all(np.isfinite(out.g))
                and np.all(np.isfinite(out.h))):
            raise ExpressionError("H or its derivatives are not finite here")
        return out

    def dual(self, X: np.ndarray) -> Dual:
        """Values and gradients at the rows of X (shape (m, 2n))."""
        m, N = X.shape
        env: dict[str, Any] = {name: Dual(X[:, i], np.eye(N)[i][:, None] * np.ones(m))
                               for i, name in enumerate(self.names)}
        zero = np.zeros((N, m))
        env.update({k: Dual(np.full(m, float(v)), zero) for k, v in self.parameters.items()})
        env["pi"] = Dual(np.full(m, math.pi), zero)
        with np.errstate(all="ignore"):
            if self.function is None:
                return self._program(env, lambda c: Dual(np.full(m, c), zero))
            try:
                return self._program(env, lambda c: Dual(np.full(m, c), zero))
            except (ZeroDivisionError, ValueError, OverflowError, FloatingPointError) as exc:
                # the user's function failed on a point of the run: said, never a traceback
                raise StepsafeError(str(exc) or type(exc).__name__, self._key) from None

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


class _Ops:
    """The elementary functions for Hamiltonians given as Python functions: each works on
    stepsafe's jets and dual numbers and on plain numbers."""

    pi = math.pi

    def __getattr__(self, name: str) -> Callable[[Any], Any]:
        if name not in _F:
            raise AttributeError(f"ops has no function {name!r}; it has "
                                 f"{', '.join(sorted(_F))}")

        def apply(x: Any) -> Any:
            if isinstance(x, (Jet, Dual)):
                return x.call(name)
            return float(_F[name][0](float(x)))

        return apply


OPS = _Ops()


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
            d = H.dual(centre + half * U)
            G = np.asarray(d.d, dtype=float).T * half
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
    from stepsafe.systems.linear import hamiltonian_matrix, normalised

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
    """The equations of motion for :mod:`stepsafe.core.integrator`."""
    from stepsafe.core.integrator import System

    n = len(H.q)

    def grads(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        d = H.dual(np.hstack([q, p]))
        return np.asarray(d.d).T  # (m, 2n)

    def hessian(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        X = np.hstack([q, p])
        S = np.stack([H.jet(row).h for row in X])
        return S[:, :n, :n], S[:, :n, n:], S[:, n:, n:]

    def field(q: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = grads(q, p)
        return g[:, n:], -g[:, :n]

    return System(dH_dq=lambda q, p: grads(q, p)[:, :n], dH_dp=lambda q, p: grads(q, p)[:, n:],
                  energy=lambda q, p: np.asarray(H.dual(np.hstack([q, p])).v, dtype=float),
                  separable=H.separable, dimension=n, vector_field=field, hessian=hessian)
