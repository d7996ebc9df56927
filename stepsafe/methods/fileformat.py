"""The method file format: its schema, validation and the construction of method objects.

A method file is a YAML mapping (read by :mod:`stepsafe.files.yamlio`, all scalars strings)::

    name: pefrl                      # CLI name
    title: "Position-extended Forest-Ruth-like"
    kind: splitting                  # rk | prk | splitting | composition | impulse | processed
                                     # | langevin
    order: 4
    evaluations: 4                   # force evaluations per step, first-same-as-last merged
    source: "Omelyan, Mryglod, Folk, Comput. Phys. Commun. 146 (2002) 188, eq. (20)"
    aliases: [omelyan4]              # optional
    constants: {xi: "0.1786178958448091", lam: "-0.2123418310626054"}   # optional, in order
    symmetric: true                  # optional: only the first half (with the middle) given
    drift: [xi, "1/2 - xi"]
    kick: ["(1 - 2*lam)/2", lam]

Coefficient fields by kind: ``rk``: ``A``, ``b``, optional ``c``; ``prk``: ``A_q``, ``b_q``,
``A_p``, ``b_p``; ``splitting``: ``drift``, ``kick``; ``composition``: ``base`` (a method
name, or ``{name:, stages:}``) and either ``weights`` or ``recipe`` (``triple-jump`` |
``suzuki``); ``impulse`` (multiple time stepping): ``outer`` and ``inner`` (splitting
methods, each a name or a path) and ``substeps``; ``processed`` (``psi = P^-1 o K o P``):
``kernel`` (a method name or path, ``{name:, stages:}``, or inline ``{drift:, kick:,
symmetric:}``; a splitting or a composition of one) and ``processor`` (inline ``{drift:,
kick:}``: P applies ``drift(c_1 h), kick(d_1 h), drift(c_2 h), ...``, sums free; or the name
of a splitting method file); ``order`` is then the processed method's order and
``evaluations`` the kernel's per step (P and P^-1 are counted apart); ``langevin``:
``letters`` (a word in A = drift, B = kick, O = the exact Ornstein–Uhlenbeck step, each
letter's substep h over its count: ``BAOAB``, ``OBABO``), ``friction`` (gamma, per time unit,
default 1) and ``kT`` (thermal energy, default 1). Coefficients are
numbers or expressions (:mod:`stepsafe.files.expressions`). With ``symmetric: true`` the
listed operation sequence (``drift a_1, kick b_1, drift a_2, ...``, or the weights) is the
first half including the middle operation; the rest is its mirror image.

:data:`FIELDS` is the single description of the format: :func:`validate_tree` enforces it
and :func:`json_schema` renders it as a JSON Schema for editors (``stepsafe schema method``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

from stepsafe.exceptions import MethodError, StepsafeError, unknown_key
from stepsafe.files.expressions import (
    EPS,
    FLOAT,
    Backend,
    ExpressionError,
    evaluate,
    evaluate_with_bound,
    mpmath_backend,
    parse,
)
from stepsafe.lazy import lazy_module
from stepsafe.methods import tableaux as m
from stepsafe.methods.families import RECIPES
from stepsafe.methods.residuals import written_residuals
from stepsafe.methods.tableaux import MAX_SUBSTEPS
from stepsafe.text import ascii_whole

if TYPE_CHECKING:
    from stepsafe.methods import langevin
else:  # Langevin splittings only
    langevin = lazy_module("stepsafe.methods.langevin")

KINDS = ("rk", "prk", "splitting", "composition", "impulse", "processed", "langevin")
MAX_STAGES = 200
MAX_WEIGHTS = 200
#: RK and PRK tableaux: each sample of M(z) solves a 2s x 2s stage system, so the cost grows
#: like s^3 (Gauss s = 40: about a second per region; s = 64: tens of seconds).
MAX_TABLEAU_STAGES = 40


class Field(NamedTuple):
    type: str  # "text", "int", "bool", "coef", "vector", "matrix", "names", "ref", "map", "enum"
    description: str
    kinds: tuple[str, ...] = KINDS
    required: bool = False
    choices: tuple[str, ...] = ()


FIELDS: dict[str, Field] = {
    "name": Field("text", "CLI name of the method (lower case, digits, '-')", required=True),
    "title": Field("text", "human-readable title"),
    "kind": Field("enum", "method kind", required=True, choices=KINDS),
    "order": Field("int", "classical order of accuracy", required=True),
    "evaluations": Field("int", "force evaluations per step as run in practice "
                                "(first-same-as-last merged; per stage for implicit methods)"),
    "source": Field("text", "paper and table the coefficients come from", required=True),
    "aliases": Field("names", "other names the method is known by"),
    "constants": Field("map", "named coefficients, usable in later expressions"),
    "symmetric": Field("bool", "only the first half (with the middle) is listed",
                       kinds=("splitting", "composition")),
    "A": Field("matrix", "RK coefficient matrix", kinds=("rk",), required=True),
    "b": Field("vector", "RK weights", kinds=("rk",), required=True),
    "c": Field("vector", "RK nodes (default: row sums of A)", kinds=("rk",)),
    "A_q": Field("matrix", "PRK matrix for the q equation", kinds=("prk",), required=True),
    "b_q": Field("vector", "PRK weights for q", kinds=("prk",), required=True),
    "A_p": Field("matrix", "PRK matrix for the p equation", kinds=("prk",), required=True),
    "b_p": Field("vector", "PRK weights for p", kinds=("prk",), required=True),
    "drift": Field("vector", "drift coefficients a_i (q += a_i h T'(p))", kinds=("splitting",),
                   required=True),
    "kick": Field("vector", "kick coefficients b_i (p -= b_i h V'(q))", kinds=("splitting",),
                  required=True),
    "gradient": Field("vector", "force-gradient coefficients c_i, one per kick, zeros allowed: "
                                "kick i is p += b_i h F + c_i h^3 grad(|F|^2_{M^-1}) with "
                                "F = -V'(q), i.e. Chin's exp(b_i h (V + (c_i/b_i) h^2 "
                                "[V,[T,V]])) with classical Lie operators",
                      kinds=("splitting",)),
    "gradient_form": Field("enum", "how integrations evaluate a force-gradient kick: hessian "
                                   "(a Hessian-vector product) or displaced-force (the force at "
                                   "q - (2 c_i h^2 / b_i) M^-1 V'(q), Hessian-free; identical on "
                                   "quadratic V) [default: hessian]",
                           kinds=("splitting",), choices=("hessian", "displaced-force")),
    "base": Field("ref", "base method: a name or {name:, stages:}", kinds=("composition",),
                  required=True),
    "weights": Field("vector", "substep fractions g_i (sum 1, negative allowed)",
                     kinds=("composition",)),
    "recipe": Field("enum", "build the weights from the base's order instead",
                    kinds=("composition",), choices=("triple-jump", "suzuki")),
    "outer": Field("ref", "splitting over the slow force at the outer step H: a name or path",
                   kinds=("impulse",), required=True),
    "inner": Field("ref", "splitting over the fast force, run substeps times per outer drift",
                   kinds=("impulse",), required=True),
    "substeps": Field("int", "inner steps per outer drift (commands may override it)",
                      kinds=("impulse",), required=True),
    "kernel": Field("kernel", "kernel K of psi = P^-1 K P: a method name or path, "
                              "{name:, stages:}, or inline {drift:, kick:, symmetric:}",
                    kinds=("processed",), required=True),
    "processor": Field("processor", "processor P, run once before the first step (P^-1 at "
                                    "each output): inline {drift:, kick:} (drift first, sums "
                                    "free) or a splitting method's name",
                       kinds=("processed",), required=True),
    "letters": Field("text", "Langevin splitting as a word in A (drift q += t M^-1 p), B "
                             "(kick p -= t V'(q)) and O (p <- c p + sqrt((1 - c^2) kT) "
                             "M^1/2 xi, c = exp(-gamma t)), each letter's substep h over its "
                             "count, e.g. BAOAB", kinds=("langevin",), required=True),
    "friction": Field("coef", "friction gamma, per time unit [default 1]",
                      kinds=("langevin",)),
    "kT": Field("coef", "thermal energy kT in the system's energy unit [default 1]",
                kinds=("langevin",)),
    "published_stability": Field("map", "a stability threshold stated by a source "
                                        "({value:, source:})"),
    "thresholds": Field("map", "harmonic-oscillator thresholds of these coefficients as "
                               "decimals, checked against the computed region by the tests: "
                               "{structure: first boundary z*, stability: classical limit "
                               "|tr M| <= 2}"),
    "notes": Field("text", "free text"),
}


@dataclass
class MethodData:
    """A validated method file, with coefficients evaluated in one backend."""

    name: str
    kind: str
    title: str
    order: int
    evaluations: int | None
    source: str
    aliases: tuple[str, ...]
    coefficients: dict[str, Any]  # A, b, c / A_q, ... / drift, kick / weights (backend values)
    base: Any = None  # str or {"name":, "stages":} for compositions
    recipe: str | None = None
    published_stability: dict[str, Any] | None = None
    thresholds: dict[str, str] | None = None  # decimal text as written (its digits count)
    where: str = ""
    extras: dict[str, Any] = field(default_factory=dict)


def _fail(where: str, path: str, message: str) -> StepsafeError:
    return StepsafeError(message, f"{where}::$.{path}" if path else where)


def _text(value: Any, where: str, key: str) -> str:
    if not isinstance(value, str):
        raise _fail(where, key, "must be a text value")
    return value


def _int(value: Any, where: str, key: str, lo: int = 0, hi: int = 10_000) -> int:
    number = ascii_whole(value, max_digits=30)
    if number is None:
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        raise _fail(where, key, f"must be a whole number written with the digits 0-9, got "
                                f"{shown}")
    if not lo <= number <= hi:
        raise _fail(where, key, f"must be between {lo} and {hi}, got {number}")
    return number


def _bool(value: Any, where: str, key: str) -> bool:
    if isinstance(value, str) and value.lower() in ("true", "false"):
        return value.lower() == "true"
    raise _fail(where, key, f"must be true or false, got {value!r}")


#: A float coefficient whose rounding bound exceeds this many ulps is re-evaluated at
#: EXACT_DPS digits and rounded once.
EXACT_ULPS = 16
EXACT_DPS = 50


class _Scope:
    """Constants defined so far, in float (the guard) and in the requested backend.

    Float values are the decimal text's value rounded once: an expression whose float
    evaluation may be off by more than :data:`EXACT_ULPS` ulps (cancellation) is evaluated
    at :data:`EXACT_DPS` digits instead, so the float path analyses the method the file
    defines."""

    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        self.floats: dict[str, float] = {}
        self.errors: dict[str, float] = {}
        self.values: dict[str, Any] = {}
        self.texts: dict[str, Any] = {}
        #: how far each constant's exact value may lie from the value its author meant
        #: (:func:`~stepsafe.files.expressions.written_rounding` of its literals)
        self.allowances: dict[str, float] = {}
        self._exact: dict[str, Any] | None = None

    def _precise(self, expr) -> Any:
        """The exact value of ``expr``'s text at :data:`EXACT_DPS` digits (an mpf; imports
        mpmath)."""
        import mpmath

        with mpmath.workdps(EXACT_DPS):
            if self._exact is None:
                self._exact = {}
            backend = mpmath_backend()
            for name, known in self.texts.items():
                if name not in self._exact:
                    self._exact[name] = evaluate(known, self._exact, backend)
            return evaluate(expr, self._exact, backend)

    def _float(self, expr, text: str) -> float:
        guard = evaluate(expr, self.floats, FLOAT)
        value, bound = evaluate_with_bound(expr, self.floats, self.errors)
        if not bound > EXACT_ULPS * EPS * abs(guard):
            return guard
        return FLOAT.check(float(self._precise(expr)))

    def written(self, text: str) -> tuple[Any, float]:
        """An already validated coefficient as written: its exact value at
        :data:`EXACT_DPS` digits, and how far that may lie from the value meant."""
        expr = parse(text)
        allowance = evaluate_with_bound(expr, self.floats, self.allowances, written=True)[1]
        return self._precise(expr), allowance

    def value(self, text: Any, where: str, path: str) -> Any:
        if not isinstance(text, str):
            raise _fail(where, path, "must be a number or an expression string")
        try:
            expr = parse(text)
            as_float = self._float(expr, text)
            if self.backend is FLOAT:
                return as_float
            return evaluate(expr, self.values, self.backend)
        except ExpressionError as exc:
            raise _fail(where, path, f"{exc} in {text[:60]!r}") from None

    def define(self, name: str, text: Any, where: str, path: str) -> None:
        self.values[name] = self.value(text, where, path)
        self.floats[name] = self.values[name] if self.backend is FLOAT else \
            self._float(parse(text), text)
        self.errors[name] = EPS / 2 * abs(self.floats[name])
        self.allowances[name] = evaluate_with_bound(parse(text), self.floats, self.allowances,
                                                    written=True)[1]
        self.texts[name] = parse(text)


def _vector(value: Any, where: str, key: str, scope: _Scope, limit: int) -> list:
    if not isinstance(value, list) or not value:
        raise _fail(where, key, "must be a non-empty list of coefficients")
    if len(value) > limit:
        raise _fail(where, key, f"has {len(value)} entries, more than the {limit} allowed")
    return [scope.value(v, where, f"{key}[{i}]") for i, v in enumerate(value)]


def _matrix(value: Any, where: str, key: str, scope: _Scope) -> list[list]:
    if not isinstance(value, list) or not value:
        raise _fail(where, key, "must be a non-empty list of rows")
    if len(value) > MAX_STAGES:
        raise _fail(where, key, f"has {len(value)} rows, more than the {MAX_STAGES} allowed")
    rows = []
    for i, row in enumerate(value):
        if not isinstance(row, list) or len(row) != len(value):
            raise _fail(where, f"{key}[{i}]", f"must be a row of {len(value)} coefficients "
                                              "(the matrix must be square)")
        rows.append([scope.value(v, where, f"{key}[{i}][{j}]") for j, v in enumerate(row)])
    return rows


def _mirror(seq: list) -> list:
    return seq + seq[-2::-1]


def _mirror_splitting(drift: list, kick: list) -> tuple[list, list]:
    ops = []
    for i, a in enumerate(drift):
        ops.append(a)
        if i < len(kick):
            ops.append(kick[i])
    full = _mirror(ops)
    return full[0::2], full[1::2]


def validate_tree(tree: Any, where: str, backend: Backend = FLOAT) -> MethodData:
    """Check a parsed method file against :data:`FIELDS` and evaluate its coefficients."""
    if not isinstance(tree, dict):
        raise _fail(where, "", "a method file must be a mapping of keys to values")
    for key in tree:
        if key not in FIELDS:
            raise _fail(where, str(key), unknown_key(key, list(FIELDS)))
    kind = tree.get("kind")
    if kind not in KINDS:
        raise _fail(where, "kind", f"must be one of {', '.join(KINDS)}, got {kind!r}")
    for key, spec in FIELDS.items():
        if key in tree and kind not in spec.kinds:
            raise _fail(where, key, f"does not apply to kind {kind}")
        if spec.required and kind in spec.kinds and key not in tree:
            raise _fail(where, key, f"missing (required for kind {kind})")
    if kind == "composition" and ("weights" in tree) == ("recipe" in tree):
        raise _fail(where, "weights", "a composition needs exactly one of weights or recipe")
    for key, spec in FIELDS.items():
        if spec.type == "enum" and key != "kind" and key in tree \
                and tree[key] not in spec.choices:
            shown = repr(tree[key]) if len(repr(tree[key])) <= 60 else repr(tree[key])[:57] + "..."
            raise _fail(where, key, f"must be one of {', '.join(spec.choices)}, got {shown}")

    name = _text(tree["name"], where, "name")
    if not name or not all(ch.isalnum() or ch == "-" for ch in name):
        raise _fail(where, "name", "must be letters, digits and '-'")
    aliases = tree.get("aliases", [])
    if not isinstance(aliases, list) or not all(isinstance(a, str) for a in aliases):
        raise _fail(where, "aliases", "must be a list of names")

    scope = _Scope(backend)
    constants = tree.get("constants", {})
    if not isinstance(constants, dict):
        raise _fail(where, "constants", "must be a mapping of names to coefficients")
    if len(constants) > 1000:
        raise _fail(where, "constants", "more than 1000 constants")
    for cname, cvalue in constants.items():
        if cname in ("pi", "sqrt", "cbrt") or not cname.isidentifier() or cname.startswith("_"):
            raise _fail(where, f"constants.{cname}", "is not an allowed constant name")
        scope.define(cname, cvalue, where, f"constants.{cname}")

    coefficients: dict[str, Any] = {}
    for key, spec in FIELDS.items():
        if key not in tree or spec.type not in ("vector", "matrix"):
            continue
        if spec.type == "matrix":
            coefficients[key] = _matrix(tree[key], where, key, scope)
        else:
            limit = MAX_WEIGHTS if key == "weights" else MAX_STAGES
            coefficients[key] = _vector(tree[key], where, key, scope, limit)
    symmetric = _bool(tree["symmetric"], where, "symmetric") if "symmetric" in tree else False
    _check_shapes(kind, coefficients, where, symmetric)
    if "weights" in coefficients and all(float(w) == 0 for w in coefficients["weights"]):
        raise _fail(where, "weights", "all weights are zero: the composition would not move "
                                      "(a zero weight among others is allowed)")
    if symmetric and kind == "splitting":
        if "gradient" in coefficients:  # mirrored with the kicks it belongs to
            coefficients["gradient"] = _mirror_splitting(coefficients["drift"],
                                                         coefficients["gradient"])[1]
        coefficients["drift"], coefficients["kick"] = _mirror_splitting(coefficients["drift"],
                                                                       coefficients["kick"])
    elif symmetric and "weights" in coefficients:
        coefficients["weights"] = _mirror(coefficients["weights"])
    for key, values in coefficients.items():  # every analysis sums them: they must fit
        rows = values if FIELDS[key].type == "matrix" else [values]
        if not all(math.isfinite(sum(abs(float(v)) for v in row)) for row in rows) or \
                not math.isfinite(sum(sum(abs(float(v)) for v in row) for row in rows)):
            raise _fail(where, key, "coefficients too large: their sum overflows float64")

    base = tree.get("base")
    if kind == "composition":
        base = _base_ref(base, where)
    extras: dict[str, Any] = {}
    if kind == "processed":
        extras = {"kernel": _sequence_or_ref(tree["kernel"], where, "kernel", scope, True),
                  "processor": _sequence_or_ref(tree["processor"], where, "processor", scope,
                                                False)}
    if "gradient_form" in tree:
        if "gradient" not in tree:
            raise _fail(where, "gradient_form", "applies only to a method with gradient:")
        extras["gradient_form"] = tree["gradient_form"]
        if tree["gradient_form"] == "displaced-force":
            for i, (b, c) in enumerate(zip(coefficients["kick"], coefficients["gradient"])):
                if float(c) != 0 and float(b) == 0:
                    raise _fail(where, f"gradient[{i}]", "a displaced-force kick needs a "
                                                         "nonzero kick coefficient")
    if kind == "impulse":
        extras = {"outer": _base_ref(tree["outer"], where, "outer"),
                  "inner": _base_ref(tree["inner"], where, "inner"),
                  "substeps": _int(tree["substeps"], where, "substeps", 1, MAX_SUBSTEPS)}
    if kind == "langevin":
        extras = _langevin(tree, where, scope)
    if kind in WRITTEN and backend is FLOAT:  # the symplecticity at the digits' precision
        extras["written"] = {key: _written(tree[key], scope) for key in WRITTEN[kind]}
    stability = tree.get("published_stability")
    if stability is not None:
        if not isinstance(stability, dict) or "value" not in stability:
            raise _fail(where, "published_stability", "must be a mapping with value and source")
        stability = {"value": _Scope(FLOAT).value(stability["value"], where,
                                                  "published_stability.value"),
                     "source": str(stability.get("source", ""))}
    thresholds = _thresholds(tree.get("thresholds"), where)
    evaluations = _int(tree["evaluations"], where, "evaluations", 0) if "evaluations" in tree \
        else None
    return MethodData(
        name=name, kind=kind, title=_text(tree.get("title", name), where, "title"),
        order=_int(tree["order"], where, "order", 0, 100), evaluations=evaluations,
        source=_text(tree["source"], where, "source"), aliases=tuple(aliases),
        coefficients=coefficients, base=base,
        recipe=tree.get("recipe"), published_stability=stability, thresholds=thresholds,
        where=where, extras=extras)


def _langevin(tree: dict, where: str, scope: _Scope) -> dict[str, Any]:
    """``letters`` (A, B and O, each present, O in one run up to a rotation, checked when
    the method is built), ``friction`` (>= 0) and ``kT`` (> 0) of a Langevin splitting."""
    letters = _text(tree["letters"], where, "letters")
    most, known = langevin.MAX_LETTERS, langevin.LETTERS
    if not letters or len(letters) > most or any(ch not in known for ch in letters):
        raise _fail(where, "letters", f"must be a word of at most {most} of the letters "
                                      f"A (drift), B (kick) and O (friction), got "
                                      f"{letters[:40]!r}")
    out: dict[str, Any] = {"letters": letters}
    for key, default in (("friction", 1.0), ("kT", 1.0)):
        value = float(scope.value(tree[key], where, key)) if key in tree else default
        if not math.isfinite(value) or value < 0 or (key == "kT" and value == 0):
            raise _fail(where, key, f"must be a finite number {'> 0' if key == 'kT' else '>= 0'}"
                                    f", got {value!r}")
        out[key] = value
    return out


#: The tableaux whose symplecticity condition is decided on the coefficients as written
#: (:func:`stepsafe.methods.residuals.written_residuals`), by kind.
WRITTEN = {"rk": ("A", "b"), "prk": ("A_q", "b_q", "A_p", "b_p")}


def _written(value: list, scope: _Scope) -> list:
    """A validated vector or matrix of coefficient texts as ``(exact value, allowance)``
    pairs (:meth:`_Scope.written`), in the same nesting."""
    return [_written(v, scope) if isinstance(v, list) else scope.written(v) for v in value]


#: the keys of ``thresholds:`` (harmonic oscillator, z = omega h)
THRESHOLD_KEYS = ("structure", "stability")


def _thresholds(value: Any, where: str) -> dict[str, str] | None:
    """``thresholds:`` as written: positive decimals (digits 0-9 and one point), so the
    number of stated digits is known to whoever compares them."""
    if value is None:
        return None
    if not isinstance(value, dict) or not value:
        raise _fail(where, "thresholds", "must be a mapping with structure and/or stability")
    out = {}
    for key, text in value.items():
        if key not in THRESHOLD_KEYS:
            raise _fail(where, f"thresholds.{key}", unknown_key(key, THRESHOLD_KEYS))
        digits = text.replace(".", "", 1) if isinstance(text, str) else ""
        if not (digits.isascii() and digits.isdigit() and len(text) <= 40) \
                or float(text) <= 0:
            raise _fail(where, f"thresholds.{key}", f"must be a positive decimal such as "
                                                    f"3.1410819, got {text!r}")
        out[key] = text
    return out


def _check_shapes(kind: str, co: dict[str, Any], where: str, symmetric: bool) -> None:
    if kind in ("rk", "prk"):
        key = "b" if kind == "rk" else "b_q"
        if len(co[key]) > MAX_TABLEAU_STAGES:
            raise _fail(where, key, f"has {len(co[key])} stages, more than the "
                                    f"{MAX_TABLEAU_STAGES} an RK/PRK tableau may have (each "
                                    "sample solves a stage system of twice that size)")
    if kind == "rk":
        s = len(co["b"])
        if len(co["A"]) != s:
            raise _fail(where, "A", f"is {len(co['A'])}x{len(co['A'])} but b has {s} entries")
        if "c" in co and len(co["c"]) != s:
            raise _fail(where, "c", f"has {len(co['c'])} entries but b has {s}")
    elif kind == "prk":
        s = len(co["b_q"])
        for key in ("A_q", "A_p", "b_p"):
            if len(co[key]) != s:
                raise _fail(where, key, f"has {len(co[key])} rows/entries but b_q has {s}")
    elif kind == "splitting":
        nd, nk = len(co["drift"]), len(co["kick"])
        if nd not in (nk, nk + 1):
            raise _fail(where, "drift", f"has {nd} entries; it needs as many as kick ({nk}) "
                                        "or one more")
        if "gradient" in co and len(co["gradient"]) != nk:
            raise _fail(where, "gradient", f"has {len(co['gradient'])} entries; it needs one "
                                           f"per kick ({nk})")


def _sequence_or_ref(value: Any, where: str, key: str, scope: _Scope,
                     stages_allowed: bool) -> Any:
    """A method reference (as ``base:``), or an inline drift/kick sequence returned as
    ``{"drift": [...], "kick": [...]}`` (mirrored when ``symmetric: true``), its entries
    named ``key.drift[i]`` in errors."""
    if isinstance(value, str) or (isinstance(value, dict) and "name" in value):
        if isinstance(value, dict) and not stages_allowed:
            raise _fail(where, key, "must be inline {drift:, kick:} or a method name")
        return _base_ref(value, where, key)
    if not isinstance(value, dict):
        raise _fail(where, key, "must be a method name, or inline {drift:, kick:}")
    allowed = ("drift", "kick", "symmetric")
    for sub in value:
        if sub not in allowed:
            raise _fail(where, f"{key}.{sub}", unknown_key(sub, allowed))
    for sub in ("drift", "kick"):
        if sub not in value:
            raise _fail(where, f"{key}.{sub}", "missing (an inline sequence needs drift and "
                                               "kick)")
    drift = _vector(value["drift"], where, f"{key}.drift", scope, MAX_STAGES)
    kick = _vector(value["kick"], where, f"{key}.kick", scope, MAX_STAGES)
    if len(drift) not in (len(kick), len(kick) + 1):
        raise _fail(where, f"{key}.drift", f"has {len(drift)} entries; it needs as many as "
                                           f"kick ({len(kick)}) or one more")
    if "symmetric" in value and _bool(value["symmetric"], where, f"{key}.symmetric"):
        drift, kick = _mirror_splitting(drift, kick)
    for sub, values in (("drift", drift), ("kick", kick)):
        if not math.isfinite(sum(abs(float(v)) for v in values)):
            raise _fail(where, f"{key}.{sub}", "coefficients too large: their sum overflows "
                                               "float64")
    return {"drift": drift, "kick": kick}


def _base_ref(base: Any, where: str, key: str = "base") -> Any:
    if isinstance(base, str) and base:
        return base
    if isinstance(base, dict) and isinstance(base.get("name"), str):
        unknown = set(base) - {"name", "stages"}
        if unknown:
            raise _fail(where, f"{key}.{sorted(unknown)[0]}",
                        unknown_key(sorted(unknown)[0], ("name", "stages")))
        out = {"name": base["name"]}
        if "stages" in base:
            out["stages"] = _int(base["stages"], where, f"{key}.stages", 1, 1000)
        return out
    raise _fail(where, key, "must be a method name or {name:, stages:}")


def build_method(data: MethodData, resolve_base: Callable[[Any], Any]):
    """Float method object for validated ``data``; ``resolve_base`` maps a base reference
    to a method object (compositions only)."""
    import numpy as np

    co = {k: np.array(v, dtype=float) for k, v in data.coefficients.items()}
    common: dict[str, Any] = dict(name=data.name, order=data.order,
                                  evaluations=data.evaluations, title=data.title)
    if data.kind in WRITTEN and "written" in data.extras:
        tableaux = data.extras["written"]
        if data.kind == "rk":
            tableaux = {"A_q": tableaux["A"], "b_q": tableaux["b"], "A_p": tableaux["A"],
                        "b_p": tableaux["b"]}
        common["written"] = written_residuals(
            *(tableaux[key] for key in ("A_q", "b_q", "A_p", "b_p")))
    if data.kind == "rk":
        return m.RungeKutta(co["A"], co["b"], co.get("c"), **common)
    if data.kind == "prk":
        return m.PartitionedRK(co["A_q"], co["b_q"], co["A_p"], co["b_p"], **common)
    if data.kind == "splitting":
        return m.Splitting(co["drift"], co["kick"], gradient=co.get("gradient"),
                           displaced=data.extras.get("gradient_form") == "displaced-force",
                           **common)
    def resolved(ref: Any, key: str):
        """The referenced method, an error naming this file's key otherwise."""
        try:
            return resolve_base(ref)
        except StepsafeError as exc:
            if exc.where:
                raise
            raise StepsafeError(exc.message, f"{data.where}::$.{key}") from None

    if data.kind == "processed":
        def part(key: str, role: str):
            ref = data.extras[key]
            if isinstance(ref, dict) and "drift" in ref:
                return m.Splitting(np.array(ref["drift"], dtype=float),
                                   np.array(ref["kick"], dtype=float),
                                   name=f"{data.name} {role}")
            return resolved(ref, key)

        processor = part("processor", "processor")
        if not isinstance(processor, m.Splitting) or processor.force_gradient:
            what = ("has force-gradient terms" if isinstance(processor, m.Splitting)
                    else f"is a {processor.kind} method")
            raise StepsafeError(f"the processor must be a plain splitting (drift/kick) "
                                f"method; {processor.name} {what}",
                                f"{data.where}::$.processor")
        with _naming_the_key(data.where, ("kernel",)):
            return m.Processed(part("kernel", "kernel"), processor, **common)
    if data.kind == "langevin":
        try:
            return langevin.Langevin(data.extras["letters"], data.extras["friction"],
                            data.extras["kT"], name=data.name, order=data.order,
                            evaluations=data.evaluations, title=data.title)
        except MethodError as exc:
            raise StepsafeError(str(exc), f"{data.where}::$.letters") from None
    if data.kind == "impulse":
        with _naming_the_key(data.where, ("outer", "inner")):
            return m.Impulse(resolved(data.extras["outer"], "outer"),
                             resolved(data.extras["inner"], "inner"), data.extras["substeps"],
                             **common)
    base = resolved(data.base, "base")
    if data.recipe:
        built = RECIPES[data.recipe](base, name=data.name)
        return m.Composition(built.base, built.weights, base_order=built.base_order, **common)
    return m.Composition(base, co["weights"], base_order=getattr(base, "order", None), **common)


@contextmanager
def _naming_the_key(where: str, keys: tuple[str, ...]) -> Iterator[None]:
    """A :class:`MethodError` about one of ``keys`` (``the outer method ...``, ``the kernel
    of ...``) re-raised naming ``file::$.key``."""
    try:
        yield
    except MethodError as exc:
        text = str(exc)
        key = next((k for k in keys if f"the {k} " in text), None)
        if key is None:
            raise
        raise StepsafeError(text, f"{where}::$.{key}") from None


def json_schema() -> dict[str, Any]:
    """The method file format as a JSON Schema (draft 2020-12), generated from FIELDS."""
    coef = {"type": ["number", "string"], "description": "number or restricted expression"}
    types: dict[str, Any] = {
        "text": {"type": "string"}, "int": {"type": "integer", "minimum": 0},
        "bool": {"type": "boolean"}, "coef": coef,
        "vector": {"type": "array", "items": coef, "minItems": 1, "maxItems": MAX_STAGES},
        "matrix": {"type": "array", "items": {"type": "array", "items": coef}, "minItems": 1},
        "names": {"type": "array", "items": {"type": "string"}},
        "ref": {"oneOf": [{"type": "string"}, {"type": "object", "properties": {
            "name": {"type": "string"}, "stages": {"type": "integer", "minimum": 1}},
            "required": ["name"], "additionalProperties": False}]},
        "map": {"type": "object"},
    }
    sequence = {"type": "object", "properties": {
        "drift": types["vector"], "kick": types["vector"], "symmetric": {"type": "boolean"}},
        "required": ["drift", "kick"], "additionalProperties": False}
    types["kernel"] = {"oneOf": [*types["ref"]["oneOf"], sequence]}
    types["processor"] = {"oneOf": [{"type": "string"}, sequence]}
    props = {}
    for key, spec in FIELDS.items():
        schema = {"enum": list(spec.choices)} if spec.type == "enum" else dict(types[spec.type])
        schema["description"] = spec.description + (
            "" if spec.kinds == KINDS else f" (kind: {', '.join(spec.kinds)})")
        props[key] = schema
    branches = []
    for kind in KINDS:
        required = [k for k, s in FIELDS.items() if s.required and kind in s.kinds]
        branches.append({"if": {"properties": {"kind": {"const": kind}}},
                         "then": {"required": required}})
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "stepsafe method file",
        "type": "object",
        "properties": props,
        "required": [k for k, s in FIELDS.items() if s.required and s.kinds == KINDS],
        "additionalProperties": False,
        "allOf": branches,
    }
