"""Scene files (method, step, margin and modes for ``advise``/``check``) and modes files.

A scene file::

    method: yoshida4            # a name, a path, or {name: lobatto3ab, stages: 4, base: midpoint}
    h: 0.05                     # the step to check (check only)
    margin: 0.9                 # optional, 0 < margin <= 1
    zmax: 10                    # optional, how far in z = beta*h to analyse
    modes:                      # the linearised frequencies
      - {beta: 3.2, model: oscillator}
      - {beta: 1.1, model: inverted}

``system:`` describes a whole system instead (see :mod:`stepsafe.sysfile`).

A modes file (``--modes FILE``) is YAML (a list of ``{beta:, model:}``, or a mapping with
``modes:``) or CSV with a header row naming the columns ``beta`` and optionally ``model``
(default ``oscillator``). CSV files may be large (up to :data:`MAX_CSV_BYTES`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import StepsafeError
from .models import MODELS
from .yamlio import load_yaml, read_text

SCENE_KEYS = ("method", "h", "margin", "zmax", "modes", "system")
MAX_CSV_BYTES = 256 << 20


@dataclass
class MethodRef:
    name: str
    stages: int | None = None
    base: str | None = None


@dataclass
class Scene:
    method: MethodRef | None = None
    h: float | None = None
    margin: float | None = None
    zmax: float | None = None
    modes: dict[str, np.ndarray] | None = None
    system: Any = None  # the raw system: mapping (read by stepsafe.sysfile)
    where: str = ""

    @property
    def folder(self) -> Path:
        return Path(self.where).parent if self.where else Path(".")


def json_schema() -> dict[str, Any]:
    """The scene file format as a JSON Schema (draft 2020-12)."""
    positive = {"type": "number", "exclusiveMinimum": 0}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "stepsafe scene file",
        "type": "object",
        "additionalProperties": False,
        "properties": {
            "method": {"oneOf": [
                {"type": "string", "description": "built-in name or path to a method file"},
                {"type": "object", "additionalProperties": False, "required": ["name"],
                 "properties": {"name": {"type": "string"},
                                "stages": {"type": "integer", "minimum": 1},
                                "base": {"type": "string"}}}]},
            "h": {**positive, "description": "the step to check (check only)"},
            "margin": {"type": "number", "exclusiveMinimum": 0, "maximum": 1,
                       "description": "frequencies may be up to 1/margin times larger"},
            "zmax": {**positive, "description": "analyse z = beta*h up to zmax (default 10)"},
            "modes": {"type": "array", "minItems": 1, "items": {
                "type": "object", "additionalProperties": False, "required": ["beta"],
                "properties": {"beta": {"type": "number", "minimum": 0},
                               "model": {"enum": list(MODELS), "default": "oscillator"},
                               "label": {"type": "string"}}}},
            "system": {"type": "object", "description": "a whole system: {stiffness:, mass:}, "
                       "{hessian:} or {hamiltonian:, parameters:, box: {q:, p:}}"},
        },
    }


def _fail(where: str, path: str, message: str) -> StepsafeError:
    return StepsafeError(message, f"{where}::$.{path}" if path else where)


#: A plain decimal number: ASCII digits, optional sign, point and exponent. Python's
#: float() would also take "1_0", Unicode digits ("٣") and "infinity"; these are refused.
_REAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", re.ASCII)
_NON_FINITE = re.compile(r"[+-]?(?:inf|infinity|nan)", re.ASCII | re.IGNORECASE)


def parse_real(text: str) -> float | None:
    """The value of a plain decimal number (surrounding whitespace allowed); ``inf`` or
    ``nan`` for their spellings (so callers can say "must be finite"); None otherwise."""
    text = text.strip()
    if _REAL.fullmatch(text):
        return float(text)
    if _NON_FINITE.fullmatch(text):
        return float(text)
    return None


def number(value: Any, where: str, path: str) -> float:
    """A finite real from a YAML string or a CLI value (no expressions here)."""
    if isinstance(value, str):
        x = parse_real(value)
        if x is None:
            raise _fail(where, path, f"must be a number, got {value!r}")
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        x = float(value)
    else:
        raise _fail(where, path, f"must be a number, got {value!r}")
    if not np.isfinite(x):
        raise _fail(where, path, f"must be finite, got {value!r}")
    return x


def method_ref(value: Any, where: str, path: str = "method") -> MethodRef:
    if isinstance(value, str) and value.strip():
        return MethodRef(value.strip())
    if isinstance(value, dict):
        unknown = set(value) - {"name", "stages", "base"}
        if unknown:
            raise _fail(where, f"{path}.{sorted(unknown)[0]}",
                        "unknown key (use name, stages, base)")
        if not isinstance(value.get("name"), str):
            raise _fail(where, f"{path}.name", "missing method name")
        stages = None
        if "stages" in value:
            s = value["stages"]
            if not isinstance(s, str) or not s.isdigit():
                raise _fail(where, f"{path}.stages", f"must be a whole number, got {s!r}")
            stages = int(s)
        base = value.get("base")
        if base is not None and not isinstance(base, str):
            raise _fail(where, f"{path}.base", "must be a method name")
        return MethodRef(value["name"], stages, base)
    raise _fail(where, path, "must be a method name or {name:, stages:, base:}")


def _modes_list(items: Any, where: str, path: str) -> dict[str, np.ndarray]:
    if not isinstance(items, list) or not items:
        raise _fail(where, path, "must be a non-empty list of {beta:, model:}")
    grouped: dict[str, list[float]] = {}
    for i, item in enumerate(items):
        if not isinstance(item, dict) or "beta" not in item:
            raise _fail(where, f"{path}[{i}]", "must be a mapping with beta (and model)")
        unknown = set(item) - {"beta", "model", "label"}
        if unknown:
            raise _fail(where, f"{path}[{i}].{sorted(unknown)[0]}", "unknown key")
        model = item.get("model", "oscillator")
        if model not in MODELS:
            raise _fail(where, f"{path}[{i}].model", f"must be one of {', '.join(MODELS)}, "
                                                      f"got {model!r}")
        beta = number(item["beta"], where, f"{path}[{i}].beta")
        if beta < 0:
            raise _fail(where, f"{path}[{i}].beta", f"must be >= 0, got {beta}")
        grouped.setdefault(model, []).append(beta)
    return {m: np.array(v) for m, v in grouped.items()}


def load_scene(path: str | Path) -> Scene:
    where = str(path)
    tree = load_yaml(path)
    if not isinstance(tree, dict):
        raise _fail(where, "", "a scene file must be a mapping (method, h, margin, modes)")
    for key in tree:
        if key not in SCENE_KEYS:
            raise _fail(where, str(key), f"unknown key (scene keys: {', '.join(SCENE_KEYS)})")
    scene = Scene(where=where)
    if "system" in tree:
        scene.system = tree["system"]
    if "method" in tree:
        scene.method = method_ref(tree["method"], where)
    for key in ("h", "margin", "zmax"):
        if key in tree:
            setattr(scene, key, number(tree[key], where, key))
    if "modes" in tree:
        scene.modes = _modes_list(tree["modes"], where, "modes")
    return scene


def load_modes(path: str | Path) -> dict[str, np.ndarray]:
    """Frequencies from a YAML or CSV modes file, grouped by model."""
    where = str(path)
    if str(path).lower().endswith(".csv"):
        return _load_csv(read_text(path, MAX_CSV_BYTES), where)
    tree = load_yaml(path)
    if isinstance(tree, dict) and "modes" in tree:
        return _modes_list(tree["modes"], where, "modes")
    return _modes_list(tree, where, "")


def _load_csv(text: str, where: str) -> dict[str, np.ndarray]:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise _fail(where, "", "empty CSV file")
    header = [h.strip().lower() for h in lines[0].split(",")]
    if "beta" not in header or set(header) - {"beta", "model", "label"}:
        raise _fail(where, "", "the CSV header must name the columns beta and (optionally) "
                               f"model, got {lines[0][:60]!r}")
    ib = header.index("beta")
    im = header.index("model") if "model" in header else None
    rows = [ln.split(",") for ln in lines[1:]]
    for r, row in enumerate(rows):
        if len(row) != len(header):
            raise _fail(where, f"row {r + 2}", f"has {len(row)} columns, the header {len(header)}")
    try:
        betas = np.array([row[ib] for row in rows], dtype=float)
    except ValueError:
        bad = next(r for r, row in enumerate(rows) if not _is_float(row[ib]))
        raise _fail(where, f"row {bad + 2}.beta", f"is not a number: {rows[bad][ib]!r}") from None
    models = (np.array([row[im].strip() for row in rows]) if im is not None
              else np.full(betas.size, "oscillator"))
    bad = ~np.isin(models, MODELS)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise _fail(where, f"row {r + 2}.model", f"must be one of {', '.join(MODELS)}, "
                                                f"got {models[r]!r}")
    wrong = ~np.isfinite(betas) | (betas < 0)
    if wrong.any():
        r = int(np.flatnonzero(wrong)[0])
        raise _fail(where, f"row {r + 2}.beta", f"must be a finite number >= 0, got {betas[r]}")
    if not betas.size:
        raise _fail(where, "", "no rows after the header")
    return {m: betas[models == m] for m in MODELS if np.any(models == m)}


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
