"""Targets of HMC given as a potential: a scene's ``system: {potential:}`` and draws files.

::

    system:
      potential: "x**2/2 + (y - c*x**2)**2/2"     # U(q) = -log pi(q), up to a constant
      q: [x, y]                                    # the coordinates, in this order
      parameters: {c: 0.3}                         # optional named numbers
      mass: [1, 1]                                 # optional: a number, d masses or d x d
      start: [0.3, 0.2]                            # optional: where the mode search starts

``U`` is the restricted expression language of :mod:`stepsafe.files.expressions` (never
``eval``) with the functions of :mod:`stepsafe.systems.manydof` (sin, cos, exp, log, sqrt,
cosh, sinh, tanh). Its gradient and Hessian are exact: U is compiled with its symbolic
derivatives (:mod:`stepsafe.systems.compiler`) and evaluated over every draw at once, never
by finite differences. The kinetic energy is
``p^T M^-1 p / 2`` with the mass M (unit masses by default), as HMC runs it.

A draws file (``--draws FILE``) holds positions from the target: ``.npy`` of shape (n, d)
(one chain, in the order drawn) or (chains, n, d); or CSV text whose header row names the
columns: every coordinate of ``q:`` (any order) and optionally ``chain`` (rows with the
same value form one chain, in file order); without a header, exactly d numeric columns.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.core.hmc_target.draws import Draws, given_draws
from stepsafe.core.hmc_target.potential import Target, mass_matrix
from stepsafe.exceptions import StepsafeError, unknown_key
from stepsafe.files.expressions import ExpressionError, parse
from stepsafe.files.yamlio import read_bytes
from stepsafe.systems.compiler import Compiled, from_tree
from stepsafe.systems.manydof import FUNCTIONS
from stepsafe.systems.scene import number, parse_real

#: The keys of a ``system:`` that gives a potential.
POTENTIAL_KEYS = ("potential", "q", "parameters", "mass", "start")
#: Coordinates at most (the dual numbers carry d derivatives through every operation).
MAX_COORDINATES = 200
#: Largest draws file read.
MAX_DRAWS_BYTES = 256 << 20


@dataclass(frozen=True, eq=False)
class ExpressionPotential:
    """``U(q)`` from an expression in the named coordinates, batched over leading axes,
    with its exact gradient and Hessian (module docstring)."""

    text: str
    names: tuple[str, ...]
    program: Any  # a stepsafe.systems.compiler.Compiled of U in q

    @property
    def dimension(self) -> int:
        return len(self.names)

    def energy(self, q: np.ndarray) -> np.ndarray:
        """U at the rows of q (shape (..., d) -> (...))."""
        return np.asarray(self.program.energy(np.asarray(q, dtype=float)), dtype=float)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """grad U at the rows of q (shape (..., d) -> (..., d))."""
        return self.program.gradient(np.asarray(q, dtype=float))

    def hessian(self, q: np.ndarray) -> np.ndarray:
        """The Hessian of U at the rows of q (shape (..., d) -> (..., d, d))."""
        return self.program.hessian(np.asarray(q, dtype=float))


@dataclass(frozen=True)
class PotentialTarget:
    """A target read from ``system: {potential:}``: the potential with its mass, where the
    mode search starts (None: the origin), the coordinates' names and where it was read."""

    target: Target
    start: np.ndarray | None
    names: tuple[str, ...]
    where: str


def _fail(where: str, key: str, message: str) -> StepsafeError:
    return StepsafeError(message, f"{where}::$.system.{key}" if where else f"system.{key}")


def is_potential(tree: Any) -> bool:
    """Whether a ``system:`` mapping gives a potential (an HMC target, not a Hamiltonian)."""
    return isinstance(tree, dict) and "potential" in tree


def potential_target(tree: Any, where: str = "") -> PotentialTarget:
    """The target of a ``system:`` mapping with ``potential:`` (module docstring); every
    error names the file and key.

    Parameters
    ----------
    tree
        The mapping (from YAML, or the API's ``system=``).
    where
        The scene file ("" from the API).

    Returns
    -------
    PotentialTarget
    """
    if not is_potential(tree):
        raise _fail(where, "", "must be a mapping with potential:")
    for key in tree:
        if key not in POTENTIAL_KEYS:
            raise _fail(where, str(key), unknown_key(key, POTENTIAL_KEYS) +
                        " (beside potential:)")
    names = tree.get("q")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise _fail(where, "q", "must be a non-empty list of coordinate names")
    if len(names) > MAX_COORDINATES:
        raise _fail(where, "q", f"{len(names)} coordinates; at most {MAX_COORDINATES}")
    for name in names:
        if not name.isidentifier() or name in FUNCTIONS or name == "pi" or \
                name.startswith("_") or not name.isascii():
            raise _fail(where, "q", f"{name[:40]!r} is not an allowed coordinate name")
    if len(set(names)) != len(names):
        raise _fail(where, "q", "a name appears twice")
    params_tree = tree.get("parameters", {})
    if not isinstance(params_tree, dict):
        raise _fail(where, "parameters", "must be a mapping of names to numbers")
    params = {}
    for k, v in params_tree.items():
        if not isinstance(k, str) or not k.isidentifier() or k in FUNCTIONS or k == "pi":
            raise _fail(where, "parameters", f"{str(k)[:40]!r} is not an allowed name")
        if k in names:
            raise _fail(where, "parameters", f"{k!r} is also a coordinate")
        params[k] = number(v, where, f"system.parameters.{k}")
    text = tree["potential"]
    if not isinstance(text, str):
        raise _fail(where, "potential", "must be an expression in the coordinates of q: "
                                        "(U = -log pi)")
    try:
        expr = parse(text, FUNCTIONS)
    except ExpressionError as exc:
        raise _fail(where, "potential", f"{exc} in {text[:60]!r}") from None
    unknown = expr.names - set(names) - set(params) - {"pi"}
    if unknown:
        raise _fail(where, "potential", f"unknown name {sorted(unknown)[0]!r} (use the names "
                                        "of q:, the parameters and pi)")
    try:
        program = Compiled(from_tree(expr.tree, text.strip(), tuple(names), params),
                           tuple(names))
    except ExpressionError as exc:
        raise _fail(where, "potential", f"{exc} in {text[:60]!r}") from None
    potential = ExpressionPotential(text, tuple(names), program)
    d = len(names)
    mass = tree.get("mass")
    target = Target(potential, mass_matrix(_numbers(mass, where, "mass"), d,
                                           _key(where, "mass")))
    start = None
    if "start" in tree:
        start = np.asarray(_numbers(tree["start"], where, "start"), dtype=float)
        if start.shape != (d,):
            raise _fail(where, "start", f"must list {d} numbers, one per coordinate of q:")
    if start is not None or d:
        probe = np.zeros((1, d)) if start is None else start[None, :]
        with np.errstate(all="ignore"):
            try:
                value = potential.energy(probe)
            except StepsafeError:
                raise
            except (ArithmeticError, ValueError, TypeError) as exc:
                raise _fail(where, "potential", f"cannot be evaluated: {exc}") from None
        if start is not None and not np.isfinite(value).all():
            raise _fail(where, "start", "U is not finite there: start inside the target's "
                                        "support")
    return PotentialTarget(target, start, tuple(names), where)


def _key(where: str, key: str) -> str:
    return f"{where}::$.system.{key}" if where else f"system.{key}"


def _numbers(value: Any, where: str, key: str) -> Any:
    """A number, a list of numbers or a list of lists of numbers from YAML (texts read as
    plain decimals) or the API, as nested lists of floats; None stays None."""
    if value is None:
        return None
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "iuf":
            raise _fail(where, key, f"must hold real numbers, got dtype {value.dtype}")
        return value.astype(float)

    def one(x: Any, path: str) -> Any:
        if isinstance(x, list):
            return [one(y, f"{path}[{i}]") for i, y in enumerate(x)]
        if isinstance(x, bool):
            raise _fail(where, path, f"is not a number: {x!r}")
        if isinstance(x, (int, float, np.integer, np.floating)):
            return float(x)
        if isinstance(x, str):
            got = parse_real(x)
            if got is not None:
                return got
        raise _fail(where, path, f"is not a number: {str(x)[:40]!r}")

    return one(value, key)


def read_draws(path: str | Path, names: tuple[str, ...]) -> Draws:
    """Draws from a file (module docstring) for a target with coordinates ``names``.

    Parameters
    ----------
    path
        A ``.npy`` file, or CSV text.
    names
        The target's coordinate names, in order (their number is d).

    Returns
    -------
    Draws
        Marked ``given``; errors name the file.
    """
    where = str(path)
    d = len(names)
    data = read_bytes(path, MAX_DRAWS_BYTES)
    if where.endswith(".npy"):
        import io

        try:
            arr = np.load(io.BytesIO(data), allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise StepsafeError(f"not a numpy .npy array: {str(exc)[:80]}", where) from None
        if arr.dtype.kind not in "iuf":
            raise StepsafeError(f"must hold real numbers, got dtype {arr.dtype}", where)
        return given_draws(arr, d, where)
    if b"\x00" in data:
        raise StepsafeError("binary file: draws are a .npy array or CSV text", where)
    try:
        text = data.decode("utf-8-sig")  # a leading byte-order mark, as spreadsheets write
    except UnicodeDecodeError as exc:
        raise StepsafeError(f"not UTF-8 text (byte {exc.start})", where) from None
    rows = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    numbered = [(k + 1, line) for k, line in enumerate(rows) if line]
    if not numbered:
        raise StepsafeError("no draws in the file", where)
    first = [c.strip() for c in numbered[0][1].split(",")]
    header = None
    if any(_float_or_none(c) is None for c in first):
        header = first
        numbered = numbered[1:]
    columns = list(range(d))
    chain_col = None
    if header is not None:
        missing = [n for n in names if n not in header]
        if missing:
            raise StepsafeError(f"the header names no column {missing[0]!r} (it needs every "
                                f"coordinate of q: {', '.join(names)}; and optionally chain)",
                                where)
        extra = [c for c in header if c not in names and c != "chain"]
        if extra:
            raise StepsafeError(f"column {extra[0][:40]!r} is neither a coordinate of q: nor "
                                "chain", where)
        if len(set(header)) != len(header):
            raise StepsafeError("a column is named twice in the header", where)
        columns = [header.index(n) for n in names]
        chain_col = header.index("chain") if "chain" in header else None
    width = len(header) if header is not None else d
    values = np.empty((len(numbered), width))
    for i, (line_no, line) in enumerate(numbered):
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != width:
            raise StepsafeError(f"line {line_no}: {len(cells)} columns, expected {width}"
                                + ("" if header is not None else
                                   f" (one per coordinate: {', '.join(names)})"), where)
        for j, cell in enumerate(cells):
            x = _float_or_none(cell)
            if x is None:
                raise StepsafeError(f"line {line_no}: {cell[:40]!r} is not a number", where)
            values[i, j] = x
    q = values[:, columns]
    if chain_col is None:
        return given_draws(q, d, where)
    labels = values[:, chain_col]
    chains = [q[labels == c] for c in dict.fromkeys(labels.tolist())]
    n = min(len(c) for c in chains)
    if any(len(c) != n for c in chains):
        raise StepsafeError(f"chains have different lengths ({n} to "
                            f"{max(len(c) for c in chains)} draws): give each chain as many",
                            where)
    return given_draws(np.stack(chains), d, where)


def _float_or_none(cell: str) -> float | None:
    return parse_real(cell)
