"""Indexed variables for chains: ``q[i]`` with sizes and sums over i, expanded into named
variables before the analysis of :mod:`stepsafe.systems.manydof`.

::

    system:
      hamiltonian: "sum(i, 1, N, p[i]**2/2) + sum(i, 0, N, (q[i+1] - q[i])**2/2)"
      q: "q[1..N]"                 # the coordinates q[1] ... q[N]
      p: "p[1..N]"
      sizes: {N: 4}
      fixed: {"q[0]": 0, "q[N+1]": 0}      # entries outside the range held at a value
      box: {q: [-1, 1], p: [-1, 1]}        # one interval for every entry of an array

``sum(i, lo, hi, body)`` adds ``body`` for the integers ``i = lo .. hi`` (an empty range
adds nothing); indices and bounds are integer expressions (``+ - *``, numbers, the sizes
and the summation indices). The expansion builds the expression's syntax tree directly
(balanced sums, so long chains stay shallow); the text is checked first against the same
whitelist as every expression (numbers, ``+ - * / **``, the elementary functions, names),
plus the subscripts and ``sum``. Entry ``q[k]`` becomes the variable ``q_k``.
"""

from __future__ import annotations

import ast
import re
from typing import Any

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.manydof import FUNCTIONS

#: Length of the text before expansion, and nodes after it, at most.
MAX_TEXT = 20_000
MAX_NODES = 200_000
_SPEC = re.compile(r"^\s*([A-Za-z][A-Za-z0-9]*)\s*\[(.+)\.\.(.+)\]\s*$")
_ALLOWED = (ast.Expression, ast.BinOp, ast.UnaryOp, ast.Constant, ast.Name, ast.Load,
            ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd, ast.Call,
            ast.Subscript)


class _Fail(Exception):
    def __init__(self, key: str, message: str) -> None:
        super().__init__(message)
        self.key = key


def _integer(node: ast.AST, env: dict[str, int]) -> int:
    """An index or bound: integers, sizes and summation indices with + - *."""
    if isinstance(node, ast.Constant) and type(node.value) is int:
        return node.value
    if isinstance(node, ast.Name) and node.id in env:
        return env[node.id]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        return -_integer(node.operand, env)
    if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub, ast.Mult)):
        a, b = _integer(node.left, env), _integer(node.right, env)
        value = a + b if isinstance(node.op, ast.Add) else a - b if isinstance(
            node.op, ast.Sub) else a * b
        if abs(value) > 10 ** 6:
            raise _Fail("hamiltonian", "an index beyond 10^6")
        return value
    raise _Fail("hamiltonian", f"{ast.unparse(node)[:40]!r} is not an integer expression of "
                               "the sizes and summation indices")


def parse_spec(spec: object, sizes: dict[str, int], key: str) -> tuple[str, int, int]:
    """``"q[1..N]"`` -> ``("q", 1, N)``."""
    match = _SPEC.match(spec) if isinstance(spec, str) else None
    if match is None:
        raise _Fail(key, "must be a list of names or an indexed range such as q[1..N]")
    name = match.group(1)
    try:
        lo, hi = (_integer(ast.parse(match.group(k).strip(), mode="eval").body, sizes)
                  for k in (2, 3))
    except SyntaxError:
        raise _Fail(key, f"{spec!r}: the range must be integer expressions") from None
    if hi < lo:
        raise _Fail(key, f"{spec!r} is empty")
    return name, lo, hi


def expand(text: str, arrays: dict[str, tuple[int, int]], sizes: dict[str, int],
           fixed: dict[str, float], functions: tuple[str, ...]) -> ast.expr:
    """The expression with every sum expanded and every entry named (see the module
    docstring); raises :class:`_Fail` naming the key at fault."""
    if not isinstance(text, str) or len(text) > MAX_TEXT:
        raise _Fail("hamiltonian", f"must be an expression of at most {MAX_TEXT} characters")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        raise _Fail("hamiltonian", f"not an arithmetic expression: {text[:40]!r}") from None
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED):
            raise _Fail("hamiltonian", f"{type(node).__name__} is not allowed")
        if isinstance(node, ast.Constant) and type(node.value) not in (int, float):
            raise _Fail("hamiltonian", f"{node.value!r} is not a number")
        if isinstance(node, ast.Call):
            ok = isinstance(node.func, ast.Name) and (
                (node.func.id in functions and len(node.args) == 1)
                or (node.func.id == "sum" and len(node.args) == 4))
            if not ok or node.keywords:
                raise _Fail("hamiltonian", "only sum(i, lo, hi, body) and "
                                           f"{', '.join(functions)} (one argument) may be called")
        if isinstance(node, ast.Subscript) and not (
                isinstance(node.value, ast.Name) and node.value.id in arrays):
            raise _Fail("hamiltonian", f"only {', '.join(arrays)} may be indexed")
    count = [0]

    def grow(node: ast.expr) -> ast.expr:
        count[0] += 1
        if count[0] > MAX_NODES:
            raise _Fail("hamiltonian", f"the expansion has more than {MAX_NODES} parts")
        return node

    # the walk above admits only the node types, constants, callees and subscripted
    # names narrowed below
    def build(node: ast.expr, env: dict[str, int]) -> ast.expr:
        if isinstance(node, ast.Constant):
            assert isinstance(node.value, (int, float))
            return grow(ast.Constant(float(node.value)))
        if isinstance(node, ast.Name):
            if node.id in env:
                return grow(ast.Constant(float(env[node.id])))
            return grow(ast.Name(node.id, ast.Load()))
        if isinstance(node, ast.Subscript):
            assert isinstance(node.value, ast.Name)
            name = node.value.id
            k = _integer(node.slice, env)
            label = f"{name}[{k}]"
            if label in fixed:
                return grow(ast.Constant(float(fixed[label])))
            lo, hi = arrays[name]
            if not lo <= k <= hi:
                raise _Fail("hamiltonian", f"{label} is outside {name}[{lo}..{hi}] and not "
                                           "fixed (give it under fixed:)")
            return grow(ast.Name(f"{name}_{k}", ast.Load()))
        if isinstance(node, ast.UnaryOp):
            return grow(ast.UnaryOp(node.op, build(node.operand, env)))
        if isinstance(node, ast.BinOp):
            return grow(ast.BinOp(build(node.left, env), node.op, build(node.right, env)))
        assert isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
        if node.func.id != "sum":
            return grow(ast.Call(ast.Name(node.func.id, ast.Load()),
                                 [build(node.args[0], env)], []))
        index, lo_node, hi_node, body = node.args
        if not isinstance(index, ast.Name) or index.id in env:
            raise _Fail("hamiltonian", "sum(i, lo, hi, body) needs a new index name i")
        a, b = _integer(lo_node, env), _integer(hi_node, env)
        terms = [build(body, {**env, index.id: k}) for k in range(a, b + 1)]
        return _balanced(terms) if terms else grow(ast.Constant(0.0))

    return build(tree.body, dict(sizes))


def _balanced(terms: list[ast.expr]) -> ast.expr:
    """``t1 + t2 + ...`` as a balanced tree (depth log n)."""
    while len(terms) > 1:
        terms = [ast.BinOp(terms[i], ast.Add(), terms[i + 1]) if i + 1 < len(terms)
                 else terms[i] for i in range(0, len(terms), 2)]
    return terms[0]


def read_indexed(tree: dict[str, Any], where: str, number) -> tuple[Any, list, list, dict]:
    """``(expanded tree, q names, p names, box)`` of an indexed ``system:`` (``number``
    reads a YAML number naming its key)."""
    def fail(key: str, message: str) -> StepsafeError:
        return StepsafeError(message, f"{where}::$.system.{key}")

    strings = [key for key in ("q", "p") if isinstance(tree.get(key), str)]
    if len(strings) == 1:
        raise fail(strings[0], "must be a list of names like the other, or q and p both "
                               "indexed ranges such as q[1..N] and p[1..N]")
    sizes_tree = tree.get("sizes", {})
    if not isinstance(sizes_tree, dict):
        raise fail("sizes", "must map names to whole numbers")
    sizes = {}
    for name, value in sizes_tree.items():
        v = number(value, f"sizes.{name}")
        if v != int(v) or not 0 <= v <= 10 ** 6 or not str(name).isidentifier():
            raise fail(f"sizes.{name}", "must be a whole number from 0 to 10^6")
        sizes[str(name)] = int(v)
    try:
        arrays = {}
        names = {}
        for key in ("q", "p"):
            arr, lo, hi = parse_spec(tree.get(key), sizes, key)
            if arr in arrays:
                raise _Fail(key, f"q and p are both {arr}")
            arrays[arr] = (lo, hi)
            names[key] = [f"{arr}_{k}" for k in range(lo, hi + 1)]
        fixed_tree = tree.get("fixed", {})
        if not isinstance(fixed_tree, dict):
            raise _Fail("fixed", "must map entries such as q[0] to numbers")
        fixed = {}
        for label, value in fixed_tree.items():
            match = re.match(r"^\s*([A-Za-z][A-Za-z0-9]*)\s*\[(.+)\]\s*$", str(label))
            if match is None or match.group(1) not in arrays:
                raise _Fail(f"fixed.{label}", "must name an entry of q or p, such as q[0]")
            k = _integer(ast.parse(match.group(2), mode="eval").body, sizes)
            lo, hi = arrays[match.group(1)]
            if lo <= k <= hi:
                raise _Fail(f"fixed.{label}", "is one of the variables; fixed entries lie "
                                              "outside the range")
            fixed[f"{match.group(1)}[{k}]"] = number(value, f"fixed.{label}")
        expanded = expand(tree["hamiltonian"], arrays, sizes, fixed, FUNCTIONS)
    except _Fail as exc:
        raise fail(exc.key, str(exc)) from None
    except SyntaxError:
        raise fail("fixed", "an index must be an integer expression") from None
    box_tree = tree.get("box")
    if not isinstance(box_tree, dict):
        raise fail("box", "must give [lo, hi] for each array (q, p) or each entry")
    box = {}
    for key, arr in (("q", tree["q"]), ("p", tree["p"])):
        name = parse_spec(arr, sizes, key)[0]
        for var in names[key]:
            index = var.split("_")[-1]
            entry = box_tree.get(f"{name}[{index}]", box_tree.get(name))
            if entry is None:
                raise fail("box", f"no interval for {name}[{index}] (give {name}: [lo, hi])")
            box[var] = entry
    return expanded, names["q"], names["p"], box
