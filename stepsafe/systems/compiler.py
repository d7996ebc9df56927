"""One compiler for the Hamiltonian expression language: H, its gradient and its Hessian
from one expression graph, evaluated by vectorised numpy code, by mpmath, or in interval
arithmetic (:mod:`stepsafe.systems.intervals`).

An expression (a whitelisted :mod:`ast` tree from :mod:`stepsafe.files.expressions`, or a
Python function ``H(q, p, ops)`` traced once on symbolic variables) becomes a graph of
:class:`Node` objects: constants, variables, ``+ - * / **``, unary minus and the functions
``sin cos exp log sqrt cbrt cosh sinh tanh``. Equal subexpressions are one node (hash
consing), so a derivative that reuses ``exp(u)`` or ``a / b`` shares it.

Derivatives are symbolic, on the graph (:func:`derivative`): the sum, product and quotient
rules, ``d(a^c) = c a^(c-1) da`` for an exponent ``c`` free of the variables and
``d(a^b) = a^b (db log a + b da / a)`` otherwise, and the chain rule for the functions.
Simplification is exact only (``0 + x = x``, ``1 * x = x``, ``0 * x = 0``, ``x^1 = x``,
integer constants folded while exact), so the derivative of ``q^2`` is ``2 q`` and its
second derivative the constant 2, exact at ``q = 0`` as well. The gradient is the first
derivatives, the Hessian the derivatives of those: one differentiation path; n = 1 is the
case of two variables ``q, p``.

Backends:

* :meth:`Compiled.function`: numpy source generated from the graph (one local per shared
  node; only names the compiler makes, never text from the input) and compiled once; its
  arguments are the variables as float arrays of any common shape (a leading batch axis of
  states), its results the requested outputs broadcast to that shape. Where an operation
  leaves the real numbers (``log`` of a negative number, ``0 ** -1``), the value is not
  finite: callers test ``isfinite``.
* :meth:`Compiled.mp_values`: the graph evaluated in mpmath at the caller's precision, each
  decimal literal read exactly from its text; a domain error raises
  :class:`~stepsafe.files.expressions.ExpressionError`.
"""

from __future__ import annotations

import ast
import math
import weakref
from collections.abc import Callable, Sequence
from fractions import Fraction
from functools import cached_property
from typing import Any

import numpy as np

from stepsafe.files.expressions import ExpressionError

FUNCTIONS = ("sin", "cos", "exp", "log", "sqrt", "cbrt", "cosh", "sinh", "tanh")
#: A power of an expression in the variables takes exponents up to this in size.
MAX_EXPONENT = 64


class Node:
    """One node of an expression graph (immutable and interned: build with the module's
    constructors or with operators, never directly)."""

    __slots__ = ("op", "args", "value", "text", "variables", "__weakref__")

    op: str  # const, var, neg, add, sub, mul, div, pow, call
    args: tuple[Node, ...]
    value: Any  # const: float; var: the name; call: the function's name
    text: str  # const: the decimal text (exact in mpmath), or "pi"
    variables: frozenset[str]

    def __repr__(self) -> str:
        return f"Node({to_text(self)})"

    # operators, so that a Python function H(q, p, ops) traces into a graph
    def __add__(self, o: Any) -> Node:
        return add(self, lift(o))

    def __radd__(self, o: Any) -> Node:
        return add(lift(o), self)

    def __sub__(self, o: Any) -> Node:
        return sub(self, lift(o))

    def __rsub__(self, o: Any) -> Node:
        return sub(lift(o), self)

    def __mul__(self, o: Any) -> Node:
        return mul(self, lift(o))

    def __rmul__(self, o: Any) -> Node:
        return mul(lift(o), self)

    def __truediv__(self, o: Any) -> Node:
        return div(self, lift(o))

    def __rtruediv__(self, o: Any) -> Node:
        return div(lift(o), self)

    def __pow__(self, o: Any) -> Node:
        return power(self, lift(o))

    def __rpow__(self, o: Any) -> Node:
        return power(lift(o), self)

    def __neg__(self) -> Node:
        return neg(self)

    def __pos__(self) -> Node:
        return self


_INTERN: weakref.WeakValueDictionary[tuple, Node] = weakref.WeakValueDictionary()


def _make(op: str, args: tuple[Node, ...] = (), value: Any = None, text: str = "") -> Node:
    key = (op, tuple(id(a) for a in args), value if op != "const" else text)
    node = _INTERN.get(key)
    if node is not None:
        return node
    node = object.__new__(Node)
    node.op, node.args, node.value, node.text = op, args, value, text
    node.variables = frozenset({value}) if op == "var" else frozenset().union(
        *(a.variables for a in args))
    _INTERN[key] = node
    return node


class NotReal(TypeError):
    """A Hamiltonian function combined a variable with something that is not a real number."""


def const(value: float | str) -> Node:
    """A constant: a float, or a decimal text (kept for mpmath, which reads it exactly)."""
    if isinstance(value, str):
        text = value
        number = math.pi if text == "pi" else float(text)
    else:
        number = float(value)
        text = repr(number)
    if not math.isfinite(number):
        raise ExpressionError("a constant is not a finite number")
    return _make("const", (), number, text)


def var(name: str) -> Node:
    return _make("var", (), name)


def lift(o: Any) -> Node:
    """A node, or a real number as a constant."""
    if isinstance(o, Node):
        return o
    if isinstance(o, (bool, np.bool_)) or not isinstance(o, (int, float, np.integer,
                                                             np.floating)):
        raise NotReal(f"cannot combine a variable with {type(o).__name__}")
    return const(float(o))


ZERO, ONE = const(0.0), const(1.0)


def _is(node: Node, number: float) -> bool:
    return node.op == "const" and node.value == number and node.text != "pi"


def _integer(node: Node) -> int | None:
    """The value of a constant that is an exact integer of moderate size."""
    if node.op == "const" and node.text != "pi" and node.value == int(node.value) \
            and abs(node.value) < 2.0 ** 50 and Fraction(node.text) == int(node.value):
        return int(node.value)
    return None


def _fold(a: Node, b: Node, f: Callable[[int, int], int]) -> Node | None:
    ia, ib = _integer(a), _integer(b)
    if ia is None or ib is None:
        return None
    v = f(ia, ib)
    return const(str(v)) if abs(v) < 2 ** 50 else None


def neg(a: Node) -> Node:
    if a.op == "neg":
        return a.args[0]
    if a.op == "const" and a.text != "pi":
        return const(a.text[1:] if a.text.startswith("-") else "-" + a.text)
    return _make("neg", (a,))


def add(a: Node, b: Node) -> Node:
    if _is(a, 0):
        return b
    if _is(b, 0):
        return a
    if b.op == "neg":
        return sub(a, b.args[0])
    return _fold(a, b, lambda x, y: x + y) or _make("add", (a, b))


def sub(a: Node, b: Node) -> Node:
    if _is(b, 0):
        return a
    if _is(a, 0):
        return neg(b)
    if a is b:
        return ZERO
    if b.op == "neg":
        return add(a, b.args[0])
    return _fold(a, b, lambda x, y: x - y) or _make("sub", (a, b))


def mul(a: Node, b: Node) -> Node:
    if _is(a, 0) or _is(b, 0):
        return ZERO
    if _is(a, 1):
        return b
    if _is(b, 1):
        return a
    if _is(a, -1):
        return neg(b)
    if _is(b, -1):
        return neg(a)
    if a.op == "neg" and b.op == "neg":
        return mul(a.args[0], b.args[0])
    if a.op == "neg":
        return neg(mul(a.args[0], b))
    if b.op == "neg":
        return neg(mul(a, b.args[0]))
    return _fold(a, b, lambda x, y: x * y) or _make("mul", (a, b))


def div(a: Node, b: Node) -> Node:
    if _is(b, 1):
        return a
    if _is(a, 0) and not _is(b, 0):
        return ZERO
    if a.op == "neg":
        return neg(div(a.args[0], b))
    return _make("div", (a, b))


def power(a: Node, b: Node) -> Node:
    if _is(b, 1):
        return a
    if _is(b, 0):
        return ONE
    if b.op == "const" and a.variables and abs(b.value) > MAX_EXPONENT:
        raise ExpressionError(f"powers of an expression in the variables go up to "
                              f"{MAX_EXPONENT}")
    ia, ib = _integer(a), _integer(b)
    if ia is not None and ib is not None and 0 <= ib <= 64 and abs(ia) ** ib < 2 ** 50:
        return const(str(ia ** ib))
    return _make("pow", (a, b))


def call(name: str, a: Node) -> Node:
    if name not in FUNCTIONS:
        raise ExpressionError(f"unknown function {name!r}")
    return _make("call", (a,), name)


# ------------------------------------------------------------------ building graphs


def from_tree(tree: ast.AST, source: str, variables: Sequence[str],
              parameters: dict[str, float] | None = None) -> Node:
    """The graph of a whitelisted expression tree (``source`` its text, for the literals);
    parameters become constants, ``pi`` the constant pi."""
    parameters = parameters or {}
    names = set(variables)

    def build(node: ast.AST) -> Node:
        if isinstance(node, ast.Constant):
            text = ast.get_source_segment(source, node)
            value = float(node.value)  # type: ignore[arg-type]  # (whitelisted: int or float)
            try:
                exact = text is not None and float(text) == value
            except ValueError:
                exact = False
            return const(text if exact and text else value)
        if isinstance(node, ast.Name):
            if node.id in names:
                return var(node.id)
            if node.id in parameters:
                return const(float(parameters[node.id]))
            if node.id == "pi":
                return const("pi")
            raise ExpressionError(f"unknown name {node.id!r}")
        if isinstance(node, ast.UnaryOp):
            inner = build(node.operand)
            return neg(inner) if isinstance(node.op, ast.USub) else inner
        if isinstance(node, ast.Call):
            assert isinstance(node.func, ast.Name)
            return call(node.func.id, build(node.args[0]))
        if isinstance(node, ast.Expression):
            return build(node.body)
        assert isinstance(node, ast.BinOp), type(node)
        a, b = build(node.left), build(node.right)
        op = node.op
        if isinstance(op, ast.Add):
            return add(a, b)
        if isinstance(op, ast.Sub):
            return sub(a, b)
        if isinstance(op, ast.Mult):
            return mul(a, b)
        if isinstance(op, ast.Div):
            return div(a, b)
        return power(a, b)

    return build(tree)


class _Ops:
    """``ops`` of a Hamiltonian function: the elementary functions (on graph nodes while
    tracing, on plain numbers otherwise) and ``pi``."""

    pi = math.pi

    def __getattr__(self, name: str) -> Callable[[Any], Any]:
        if name not in FUNCTIONS:
            raise AttributeError(f"ops has no function {name!r}; it has "
                                 f"{', '.join(sorted(FUNCTIONS))}")

        def apply(x: Any) -> Any:
            if isinstance(x, Node):
                return call(name, x)
            return float(getattr(np, name)(float(x)))

        return apply


OPS = _Ops()


def trace(function: Callable[..., Any], q: Sequence[str], p: Sequence[str]) -> Node:
    """The graph of a Python function ``H(q, p, ops)`` (lists of variables), called once
    on symbolic variables: it may use + - * / ** and ``ops``' functions, not comparisons
    of the variables (which have no value while it is traced)."""
    out = function([var(n) for n in q], [var(n) for n in p], OPS)
    return lift(out)


# ------------------------------------------------------------------ differentiation


def derivative(node: Node, name: str, memo: dict[int, Node] | None = None) -> Node:
    """d node / d name, as a graph (see the module docstring for the rules)."""
    memo = {} if memo is None else memo
    order = _postorder([node])
    for n in order:
        if id(n) in memo:
            continue
        if name not in n.variables:
            memo[id(n)] = ZERO
            continue
        d = [memo[id(a)] for a in n.args]
        op = n.op
        if op == "var":
            out = ONE
        elif op == "neg":
            out = neg(d[0])
        elif op == "add":
            out = add(d[0], d[1])
        elif op == "sub":
            out = sub(d[0], d[1])
        elif op == "mul":
            a, b = n.args
            out = add(mul(d[0], b), mul(a, d[1]))
        elif op == "div":
            a, b = n.args
            out = div(sub(d[0], mul(n, d[1])), b)
        elif op == "pow":
            a, b = n.args
            if name not in b.variables:
                out = mul(mul(b, power(a, sub(b, ONE))), d[0])
            else:
                out = mul(n, add(mul(d[1], call("log", a)), div(mul(b, d[0]), a)))
        else:
            a = n.args[0]
            f = n.value
            if f == "sin":
                inner = call("cos", a)
            elif f == "cos":
                inner = neg(call("sin", a))
            elif f == "exp":
                inner = n
            elif f == "log":
                inner = div(ONE, a)
            elif f == "sqrt":
                inner = div(const("0.5"), n)
            elif f == "cbrt":
                inner = div(ONE, mul(const("3"), mul(n, n)))
            elif f == "cosh":
                inner = call("sinh", a)
            elif f == "sinh":
                inner = call("cosh", a)
            else:  # tanh
                inner = sub(ONE, mul(n, n))
            out = mul(inner, d[0])
        memo[id(n)] = out
    return memo[id(node)]


def _postorder(roots: Sequence[Node]) -> list[Node]:
    """Every node reachable from ``roots``, each once, arguments before their users."""
    seen: set[int] = set()
    out: list[Node] = []
    for root in roots:
        stack: list[tuple[Node, bool]] = [(root, False)]
        while stack:
            node, ready = stack.pop()
            if ready:
                out.append(node)
                continue
            if id(node) in seen:
                continue
            seen.add(id(node))
            stack.append((node, True))
            stack.extend((a, False) for a in reversed(node.args) if id(a) not in seen)
    return out


def to_text(node: Node) -> str:
    """The expression as text (fully parenthesised; for messages and tests)."""
    if node.op == "const":
        return node.text
    if node.op == "var":
        return str(node.value)
    if node.op == "neg":
        return f"(-{to_text(node.args[0])})"
    if node.op == "call":
        return f"{node.value}({to_text(node.args[0])})"
    sym = {"add": "+", "sub": "-", "mul": "*", "div": "/", "pow": "**"}[node.op]
    return f"({to_text(node.args[0])} {sym} {to_text(node.args[1])})"


# ------------------------------------------------------------------ backends

_SYMBOL = {"add": "+", "sub": "-", "mul": "*", "div": "/", "pow": "**"}
_NUMPY = {"sin": np.sin, "cos": np.cos, "exp": np.exp, "log": np.log, "sqrt": np.sqrt,
          "cbrt": np.cbrt, "cosh": np.cosh, "sinh": np.sinh, "tanh": np.tanh}


def numpy_function(outputs: Sequence[Node], names: Sequence[str]
                   ) -> Callable[..., tuple[Any, ...]]:
    """A Python function of the variables (arrays or numbers, in the order of ``names``)
    returning the outputs' values, from numpy source generated for the graph: subgraphs
    free of the variables are evaluated once here, every shared node is computed once per
    call. The generated text holds only names made here (``x0``, ``t3``, ``c1``, numpy's
    functions), never text from the expression."""
    index = {n: i for i, n in enumerate(names)}
    namespace: dict[str, Any] = dict(_NUMPY)
    lines = [f"def compiled({', '.join(f'x{i}' for i in range(len(names)))}):"]
    local: dict[int, str] = {}
    with np.errstate(all="ignore"):
        for node in _postorder(list(outputs)):
            if not node.variables:
                value = _float_value(node, local, namespace)
                name = f"c{len(namespace)}"
                namespace[name] = value
                local[id(node)] = name
                continue
            if node.op == "var":
                local[id(node)] = f"x{index[node.value]}"
                continue
            a = [local[id(x)] for x in node.args]
            expr = (f"-{a[0]}" if node.op == "neg" else
                    f"{node.value}({a[0]})" if node.op == "call" else
                    f"{a[0]} {_SYMBOL[node.op]} {a[1]}")
            name = f"t{len(local)}"
            lines.append(f"    {name} = {expr}")
            local[id(node)] = name
    lines.append(f"    return ({', '.join(local[id(o)] for o in outputs)},)")
    code = compile("\n".join(lines), "<stepsafe compiled expression>", "exec")
    exec(code, namespace)  # the source is made above from the compiler's own names
    return namespace["compiled"]


def _float_value(node: Node, local: dict[int, str], namespace: dict[str, Any]) -> float:
    """A variable-free node in float64 (its arguments already in ``namespace``)."""
    if node.op == "const":
        return node.value
    a = [namespace[local[id(x)]] for x in node.args]
    x = np.float64(a[0])
    op = node.op
    if op == "neg":
        return float(-x)
    if op == "call":
        return float(_NUMPY[node.value](x))
    y = np.float64(a[1])
    return float({"add": x + y, "sub": x - y, "mul": x * y,
                  "div": x / y if y != 0 else np.float64(np.nan), "pow": x ** y}[op])


def constant_value(node: Node) -> float:
    """A variable-free node in float64, as the numpy backend computes it."""
    local: dict[int, str] = {}
    namespace: dict[str, Any] = {}
    with np.errstate(all="ignore"):
        for n in _postorder([node]):
            name = f"c{len(namespace)}"
            namespace[name] = _float_value(n, local, namespace)
            local[id(n)] = name
    return float(namespace[local[id(node)]])


def mp_evaluate(outputs: Sequence[Node], values: dict[str, Any]) -> list[Any]:
    """The outputs in mpmath at the current precision (``values`` the variables as mpf);
    a value that is not a finite real raises ExpressionError."""
    import mpmath as mp

    out: dict[int, Any] = {}
    try:
        for node in _postorder(list(outputs)):
            op = node.op
            if op == "const":
                v = mp.pi if node.text == "pi" else mp.mpf(node.text)
            elif op == "var":
                v = values[node.value]
            else:
                a = [out[id(x)] for x in node.args]
                if op == "neg":
                    v = -a[0]
                elif op == "add":
                    v = a[0] + a[1]
                elif op == "sub":
                    v = a[0] - a[1]
                elif op == "mul":
                    v = a[0] * a[1]
                elif op == "div":
                    if a[1] == 0:
                        raise ExpressionError("division by zero")
                    v = a[0] / a[1]
                elif op == "pow":
                    if a[0] == 0 and a[1] < 0:
                        raise ExpressionError("division by zero")
                    if a[0] < 0 and a[1] != int(a[1]):
                        raise ExpressionError("power of a negative number")
                    v = a[0] ** a[1]
                else:
                    f = node.value
                    if f in ("log", "sqrt") and (a[0] < 0 or (f == "log" and a[0] == 0)):
                        raise ExpressionError(f"{f} of a non-positive number")
                    v = getattr(mp, f)(a[0])
                if not isinstance(v, mp.mpf) or not mp.isfinite(v):
                    raise ExpressionError("the value is not a finite real number")
            out[id(node)] = v
    except (ZeroDivisionError, OverflowError, ValueError) as exc:
        raise ExpressionError(str(exc) or type(exc).__name__) from None
    return [out[id(o)] for o in outputs]


class Compiled:
    """A Hamiltonian's graph with its gradient and Hessian (built when first asked for)
    and their compiled numpy functions.

    Parameters
    ----------
    H : Node
        The Hamiltonian.
    names : sequence of str
        The variables, coordinates then momenta (the columns of a state array).
    """

    def __init__(self, H: Node, names: Sequence[str]) -> None:
        self.H = H
        self.names = tuple(names)

    @cached_property
    def gradient_nodes(self) -> tuple[Node, ...]:
        """dH/dx_i for each variable."""
        return tuple(derivative(self.H, n) for n in self.names)

    @cached_property
    def hessian_nodes(self) -> tuple[tuple[Node, ...], ...]:
        """d^2 H / dx_i dx_j (symmetric: the upper triangle built, the lower shared)."""
        N = len(self.names)
        rows: list[list[Node]] = [[ZERO] * N for _ in range(N)]
        memos: list[dict[int, Node]] = [{} for _ in range(N)]  # one per variable
        for i in range(N):
            for j in range(i, N):
                rows[i][j] = rows[j][i] = derivative(self.gradient_nodes[i], self.names[j],
                                                     memos[j])
        return tuple(tuple(r) for r in rows)

    @cached_property
    def _energy_gradient(self) -> Callable[..., tuple[Any, ...]]:
        return numpy_function([self.H, *self.gradient_nodes], self.names)

    @cached_property
    def _gradient(self) -> Callable[..., tuple[Any, ...]]:
        return numpy_function(self.gradient_nodes, self.names)

    @cached_property
    def _energy(self) -> Callable[..., tuple[Any, ...]]:
        return numpy_function([self.H], self.names)

    @cached_property
    def _hessian(self) -> Callable[..., tuple[Any, ...]]:
        N = len(self.names)
        return numpy_function([self.hessian_nodes[i][j] for i in range(N)
                               for j in range(i, N)], self.names)

    def function(self, outputs: Sequence[Node]) -> Callable[..., tuple[Any, ...]]:
        """A compiled numpy function of the variables for other outputs of the graph."""
        return numpy_function(outputs, self.names)

    @staticmethod
    def _columns(X: np.ndarray) -> list[np.ndarray]:
        X = np.asarray(X, dtype=float)
        return [X[..., i] for i in range(X.shape[-1])]

    def energy(self, X: np.ndarray) -> np.ndarray:
        """H at the states ``X`` (shape ``(..., N)``): shape ``(...)``."""
        X = np.asarray(X, dtype=float)
        with np.errstate(all="ignore"):
            (v,) = self._energy(*self._columns(X))
        return np.broadcast_to(v, X.shape[:-1]).astype(float)

    def gradient(self, X: np.ndarray) -> np.ndarray:
        """grad H at the states ``X`` (shape ``(..., N)``): shape ``(..., N)``."""
        X = np.asarray(X, dtype=float)
        with np.errstate(all="ignore"):
            g = self._gradient(*self._columns(X))
        return _stack(g, X.shape[:-1])

    def energy_gradient(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """H and grad H at the states ``X`` together (their shared nodes computed once)."""
        X = np.asarray(X, dtype=float)
        with np.errstate(all="ignore"):
            out = self._energy_gradient(*self._columns(X))
        return (np.broadcast_to(out[0], X.shape[:-1]).astype(float),
                _stack(out[1:], X.shape[:-1]))

    def hessian(self, X: np.ndarray) -> np.ndarray:
        """The Hessian at the states ``X`` (shape ``(..., N)``): shape ``(..., N, N)``."""
        X = np.asarray(X, dtype=float)
        N = len(self.names)
        with np.errstate(all="ignore"):
            upper = self._hessian(*self._columns(X))
        out = np.empty(X.shape[:-1] + (N, N))
        k = 0
        for i in range(N):
            for j in range(i, N):
                out[..., i, j] = out[..., j, i] = upper[k]
                k += 1
        return out

    def mp_jet(self, x: Sequence[Any]) -> tuple[Any, list[Any], list[list[Any]]]:
        """H, its gradient and Hessian at the point ``x`` (mpf values) in mpmath at the
        current precision; raises ExpressionError where they are not finite reals."""
        N = len(self.names)
        flat = [self.hessian_nodes[i][j] for i in range(N) for j in range(N)]
        values = mp_evaluate([self.H, *self.gradient_nodes, *flat], dict(zip(self.names, x)))
        return values[0], values[1:N + 1], [values[N + 1 + i * N: N + 1 + (i + 1) * N]
                                             for i in range(N)]


def _stack(values: Sequence[Any], shape: tuple[int, ...]) -> np.ndarray:
    out = np.empty(shape + (len(values),))
    for i, v in enumerate(values):
        out[..., i] = v
    return out
