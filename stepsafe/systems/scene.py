"""Scene files (method, step, margin and modes for ``advise``/``check``) and modes files.

A scene file::

    method: yoshida4            # a name, a path, or {name: lobatto3ab, stages: 4, base: midpoint}
    h: 0.05                     # the step to check (check only); or with a unit: 0.5 fs
    margin: 0.9                 # optional, 0 < margin <= 1
    zmax: 10                    # optional, how far in z = beta*h to analyse
    modes:                      # the linearised frequencies
      - {beta: 3.2, model: oscillator}
      - {beta: 1.1, model: inverted}

``system:`` describes a whole system instead (see :mod:`stepsafe.systems.loader`).

For an impulse (multiple time stepping) method each mode gives the frequency of its fast
and of its slow force (a number in rad per time unit, or a text with a unit:
``3700 cm-1``, ``100 THz``, ``9 fs``), and ``substeps:`` may override the method's::

    method: respa-verlet
    time_unit: fs
    substeps: 4
    modes:
      - {fast: 3700 cm-1, slow: 300 cm-1, label: O-H stretch}

``system: {stiffness_fast:, stiffness_slow:, mass:}`` splits a stiffness into the two
forces instead (see :mod:`stepsafe.systems.multiple`).

A modes file (``--modes FILE``) is YAML (a list of ``{beta:, model:}``, or a mapping with
``modes:``) or CSV with a header row naming the columns ``beta`` and optionally ``model``
(default ``oscillator``) and ``label`` (names the mode in verdicts; may be empty). CSV
fields are not quoted, ``#`` starts a
comment, and numbers are plain decimals (:func:`parse_real`). CSV files may be large (up to
:data:`MAX_CSV_BYTES` and :data:`MAX_CSV_ROWS` rows); they are parsed by ``np.loadtxt``.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.comparison import compared
from stepsafe.core.models import MODELS
from stepsafe.exceptions import StepsafeError, unknown_key
from stepsafe.files.yamlio import QuotedText, load_yaml, read_bytes
from stepsafe.files.yamlio import load_yaml as _load
from stepsafe.methods.library import _looks_like_path
from stepsafe.units import (
    ENERGY_UNITS,
    FORMS,
    SIGMA_RULE,
    TIME_UNITS,
    angular_frequencies,
    any_frequency,
    duration,
    implied_time_unit,
    parse_quantity,
    quantity,
)

SCENE_KEYS = ("method", "h", "time_unit", "margin", "zmax", "modes", "system", "substeps",
              "temperature", "kT", "energy_unit", "length", "steps", "max_drift",
              "max_failure", "follow_steps")
#: The keys of the analysis at temperature, kept as written and read by
#: :func:`stepsafe.api.temperature.request` (which names the key of a bad value).
THERMAL_KEYS = ("temperature", "kT", "energy_unit", "length", "steps", "max_drift",
                "max_failure", "follow_steps")
MAX_CSV_BYTES = 256 << 20
MAX_CSV_ROWS = 10_000_000  # rows of a modes CSV, counted (newlines) before parsing
#: Modes of an impulse scene: each (fast, slow) pair is a region of its own.
MAX_IMPULSE_MODES = 200


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
    system: Any = None  # the raw system: mapping (read by stepsafe.systems.loader)
    where: str = ""
    labels: dict[str, tuple[str | None, ...]] = field(default_factory=dict)  # per model,
    # in the order of modes[model]: the modes' label: (None where a mode has none)
    time_unit: str | None = None  # the unit of h (and of the modes' beta: rad per unit)
    #: impulse methods: (fast, slow) angular frequencies per mode, rows in file order
    pairs: np.ndarray | None = None
    pair_labels: tuple[str | None, ...] = ()
    substeps: int | None = None
    #: ``temperature:``, ``kT:``, ``energy_unit:``, ``length:`` and ``steps:`` as written
    thermal: dict[str, Any] = field(default_factory=dict)

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
            "h": {"oneOf": [positive, {"type": "string"}],
                  "description": "the step to check (check only): in time_unit, or with a "
                                 "time unit ('0.5 fs', converted)"},
            "time_unit": {"enum": list(TIME_UNITS),
                          "description": "the unit of h; frequencies are converted to rad "
                                         "per time_unit (default: the unit that h: and the "
                                         "periods name, else the unit of 1/beta)"},
            "margin": {"type": "number", "exclusiveMinimum": 0, "maximum": 1,
                       "description": "frequencies may be up to 1/margin times larger"},
            "zmax": {**positive, "description": "analyse z = beta*h up to zmax (default 10)"},
            "substeps": {"type": "integer", "minimum": 1,
                         "description": "inner steps per outer drift (impulse methods)"},
            "temperature": {"type": ["number", "string"],
                            "description": "analyse at this temperature, in kelvin (300 or "
                                           "'300 K'; needs energy_unit:)"},
            "kT": {"type": "number", "minimum": 0,
                   "description": "analyse at this thermal energy, in the energy unit of "
                                  "the system"},
            "energy_unit": {"enum": list(ENERGY_UNITS),
                            "description": "the unit of the Hamiltonian's energy (for "
                                           "temperature:)"},
            "length": {"type": ["number", "string"],
                       "description": "the simulated time of the run analysed at "
                                      "temperature: in time_unit, or with a unit ('10 ps')"},
            "steps": {"type": "integer", "minimum": 1,
                      "description": "or the run's number of steps"},
            "max_drift": {"type": "number", "exclusiveMinimum": 0,
                          "description": "at temperature: the largest acceptable energy "
                                         "drift, energy per time unit"},
            "max_failure": {"type": "number", "minimum": 1e-5, "maximum": 0.1,
                            "description": "at temperature: the largest acceptable "
                                           "probability that a trajectory of the run fails "
                                           "(default 0.001)"},
            "follow_steps": {"type": "integer", "minimum": 1,
                             "description": "at temperature: the most steps the thermal "
                                            "trajectories follow (default 10000); a longer "
                                            "run is refused"},
            "modes": {"type": "array", "minItems": 1, "items": {
                "type": "object", "additionalProperties": False,
                "oneOf": [{"required": [form]} for form in FORMS]
                + [{"required": ["fast", "slow"]}],
                "properties": {
                    "fast": {"type": ["number", "string"],
                             "description": "impulse methods: the fast force's frequency, "
                                            "rad per time unit or with a unit ('3700 cm-1')"},
                    "slow": {"type": ["number", "string"],
                             "description": "impulse methods: the slow force's frequency"},
                    "beta": {"type": "number", "minimum": 0,
                             "description": "angular frequency, rad per time unit"},
                    "frequency": {"type": ["number", "string"],
                                  "description": "cycles per time unit, or with a unit: "
                                                 "'100 THz', '3 ps-1'"},
                    "wavenumber": {"type": ["number", "string"],
                                   "description": "cm-1 (needs time_unit): 3700"},
                    "period": {"type": ["number", "string"],
                               "description": "in time units, or with a unit: '9 fs'"},
                    "sigma": {"type": "number", "exclusiveMinimum": 0,
                              "description": "standard deviation of a Gaussian target "
                                             "(HMC, unit mass): beta = 1/sigma"},
                    "model": {"enum": list(MODELS), "default": "oscillator"},
                    "label": {"type": "string"}}}},
            "system": {"type": "object", "description":
                       "a whole system: {stiffness:, mass:}, with units: {energy:, length:, "
                       "mass:} to convert them to rad per time_unit, with all_modes: true "
                       "to analyse every mode of a stiffness over 2000 "
                       "rows (islands too; a dense eigendecomposition), "
                       "{precision:, mass:} or {covariance:, mass:} (a Gaussian target), "
                       "{hessian:}, {hamiltonian:, parameters:, box: {q:, p:}, starts:} (1 dof), "
                       "{hamiltonian:, q: [names], p: [names], parameters:, box: {name: "
                       "[lo, hi]}, energy_below:, starts:} (n dof; or q: 'q[1..N]' with "
                       "sizes:, fixed: and sum(i, lo, hi, body) in H), or for an impulse "
                       "method "
                       "{stiffness_fast:, stiffness_slow:, mass:}, or an OpenMM system "
                       "{openmm: system.xml, positions: structure.pdb, constraints: "
                       "none|h-bonds|all-bonds|h-angles, hydrogen_mass: 3 amu, minimize: "
                       "true} (pip install 'stepsafe[openmm]')"},
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
    """A finite real from a YAML string or a CLI value (no expressions here); a quoted
    YAML scalar is text, refused as the schema says."""
    if isinstance(value, QuotedText):
        raise _fail(where, path, f"must be a number, got the quoted text {str(value)!r} "
                                 "(write it without quotes)")
    if isinstance(value, str):
        x = parse_real(value)
        if x is None:
            raise _fail(where, path, f"must be a number, got {value!r}")
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        try:
            x = float(value)
        except OverflowError:
            raise _fail(where, path, f"must be a finite number, got {str(value)[:40]}"
                        ) from None
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
                        unknown_key(sorted(unknown)[0], ("name", "stages", "base")))
        if not isinstance(value.get("name"), str):
            raise _fail(where, f"{path}.name", "missing method name")
        stages = None
        if "stages" in value:
            s = value["stages"]
            if not isinstance(s, str) or not (s.isascii() and s.isdigit() and len(s) < 1000):
                raise _fail(where, f"{path}.stages", f"must be a whole number, got {s!r}")
            stages = int(s)
        base = value.get("base")
        if base is not None and not isinstance(base, str):
            raise _fail(where, f"{path}.base", "must be a method name")
        return MethodRef(value["name"], stages, base)
    raise _fail(where, path, "must be a method name or {name:, stages:, base:}")


def _modes_list(items: Any, where: str, path: str, time_unit: str | None = None
                ) -> tuple[dict[str, np.ndarray], dict[str, tuple[str | None, ...]]]:
    """The frequencies of a ``modes:`` list grouped by model (as beta, rad per time unit),
    and their labels. Each item gives one of beta, frequency, wavenumber or period."""
    if not isinstance(items, list) or not items:
        raise _fail(where, path, "must be a non-empty list of {beta:, model:}")
    keys = (*FORMS, "model", "label")
    grouped: dict[str, list[float]] = {}
    labels: dict[str, list[str | None]] = {}
    for i, item in enumerate(items):
        forms = [f for f in FORMS if isinstance(item, dict) and f in item]
        if not isinstance(item, dict) or len(forms) != 1:
            raise _fail(where, f"{path}[{i}]", "must be a mapping with one of beta, "
                                               "frequency, wavenumber, period or sigma (and "
                                               "model)")
        unknown = set(item) - set(keys)
        if unknown:
            raise _fail(where, f"{path}[{i}].{sorted(unknown)[0]}",
                        unknown_key(sorted(unknown)[0], keys))
        model = item.get("model", "oscillator")
        if model not in MODELS:
            raise _fail(where, f"{path}[{i}].model", f"must be one of {', '.join(MODELS)}, "
                                                      f"got {model!r}")
        form = forms[0]
        beta = _frequency(item[form], form, time_unit, where, f"{path}[{i}].{form}")
        label = item.get("label")
        if label is not None and not isinstance(label, str):
            raise _fail(where, f"{path}[{i}].label", f"must be text, got {label!r}")
        grouped.setdefault(model, []).append(beta)
        labels.setdefault(model, []).append(label)
    return ({m: np.array(v) for m, v in grouped.items()},
            {m: tuple(v) for m, v in labels.items() if any(x is not None for x in v)})


def _frequency(value: Any, form: str, time_unit: str | None, where: str, path: str) -> float:
    """beta (rad per time unit) of one mode's value; a text is a number with a unit."""
    if form == "beta" or not isinstance(value, str) or (
            isinstance(value, QuotedText) and parse_real(value) is not None):
        if form == "sigma" and isinstance(value, (int, float)) and \
                not isinstance(value, bool) and not 0 < value < np.inf:  # (nan too)
            raise _fail(where, path, f"must be {SIGMA_RULE}, got {value!r}")
        value = number(value, where, path)
        if value < 0:
            raise _fail(where, path, f"must be >= 0, got {value}")
    try:
        return quantity(value, form, time_unit)
    except StepsafeError as exc:
        raise _fail(where, path, exc.message) from None


def _near_scene(name: str, folder: Path) -> str:
    """A relative method-file path in a scene is read next to the scene file (as a
    composition's ``base`` is next to its method file), never relative to the working
    directory, so a scene means the same from wherever it is checked. Names of built-in
    methods are left alone."""
    if not _looks_like_path(name) or Path(name).is_absolute():
        return name
    return str(folder / name)


def load_scene(path: str | Path, time_unit: str | None = None) -> Scene:
    """A scene file; ``time_unit`` (from the command line) must agree with the file's
    ``time_unit:`` when both are given, since the file's h and modes are in its own."""
    where = str(path)
    tree = load_yaml(path)
    if not isinstance(tree, dict):
        raise _fail(where, "", "a scene file must be a mapping (method, h, margin, modes)")
    for key in tree:
        if key not in SCENE_KEYS:
            raise _fail(where, str(key), unknown_key(key, SCENE_KEYS))
    if "modes" in tree and "system" in tree:
        raise _fail(where, "system", "give either modes: or system:, not both (one would be "
                                     "ignored)")
    scene = Scene(where=where)
    if "system" in tree:
        scene.system = tree["system"]
    if "method" in tree:
        ref = method_ref(tree["method"], where)
        base = None if ref.base is None else _near_scene(ref.base, scene.folder)
        scene.method = MethodRef(_near_scene(ref.name, scene.folder), ref.stages, base)
    scene.time_unit = time_unit
    if "time_unit" in tree:
        unit = tree["time_unit"]
        if not isinstance(unit, str) or unit not in TIME_UNITS:
            raise _fail(where, "time_unit", f"must be one of {', '.join(TIME_UNITS)}, got "
                                            f"{unit!r}")
        if time_unit is not None and unit != time_unit:
            raise _fail(where, "time_unit", f"is {unit}, but --time-unit {time_unit} was "
                                            "given (h and the modes are in the file's unit)")
        scene.time_unit = unit
    elif time_unit is None:
        try:
            scene.time_unit = implied_time_unit(*_durations(tree))
        except StepsafeError as exc:
            raise _fail(where, "time_unit", exc.message) from None
    for key in ("h", "margin", "zmax"):
        if key in tree:
            value = _step(tree[key], where, scene.time_unit) if key == "h" else \
                number(tree[key], where, key)
            if not value > 0:
                raise _fail(where, key, f"must be > 0, got {tree[key]}")
            if key == "margin" and value > 1:
                raise _fail(where, key, f"must be in (0, 1], got {value}")
            setattr(scene, key, value)
    if "substeps" in tree:
        value = number(tree["substeps"], where, "substeps")
        if value != int(value) or not 1 <= value <= 1000:
            raise _fail(where, "substeps", f"must be a whole number from 1 to 1000, got "
                                           f"{tree['substeps']}")
        scene.substeps = int(value)
    scene.thermal = {key: tree[key] for key in THERMAL_KEYS if key in tree}
    if "modes" in tree:
        items = tree["modes"]
        if isinstance(items, list) and any(isinstance(i, dict) and ("fast" in i or "slow" in i)
                                           for i in items):
            scene.pairs, scene.pair_labels = _pairs_list(items, where, scene.time_unit)
        else:
            scene.modes, scene.labels = _modes_list(items, where, "modes", scene.time_unit)
    return scene


def _step(value: Any, where: str, time_unit: str | None) -> float:
    """The scene's ``h:``: a number in its time unit, or a text with a time unit (quoted or
    not: ``h: 0.5 fs``), converted to it."""
    if isinstance(value, str) and _has_unit(value):
        try:
            x = duration(str(value), "h", time_unit, plain_text=True)
        except StepsafeError as exc:
            raise _fail(where, "h", exc.message) from None
        if not np.isfinite(x):
            raise _fail(where, "h", f"must be finite, got {value!r}")
        return x
    return number(value, where, "h")


def _has_unit(text: str) -> bool:
    try:
        return parse_quantity(text)[1] is not None
    except StepsafeError:
        return False


def _durations(tree: dict) -> list[Any]:
    """The values of a scene tree that are durations and may name a time unit: ``h:``, the
    modes' periods (and an impulse method's fast: or slow: given as a period)."""
    items = tree.get("modes")
    found = [tree.get("h")]
    if isinstance(items, list):
        found += [item.get(key) for item in items if isinstance(item, dict)
                  for key in ("period", "fast", "slow")]
    return found


def scene_time_unit(path: Any) -> str | None:
    """The time unit a scene file's values are in: its ``time_unit:``, else the unit its
    ``h:`` and periods name; None where it names none (or cannot be read: loading it
    reports that)."""
    if not isinstance(path, (str, Path)):
        return None
    try:
        tree = _load(path)
        if not isinstance(tree, dict):
            return None
        unit = tree.get("time_unit")
        if unit is not None:
            return unit if isinstance(unit, str) and unit in TIME_UNITS else None
        return implied_time_unit(*_durations(tree))
    except StepsafeError:
        return None


def time_unit_in_force(time_unit: str | None, scene: Any, *values: Any) -> str | None:
    """The time unit of a run: ``time_unit`` when given (``--time-unit``,
    ``time_unit=``), else the scene's (a :class:`Scene` or a file, see
    :func:`scene_time_unit`), else the one the texts among ``values`` name (a step
    ``"0.5 fs"``, a period ``"9 fs"``: :func:`stepsafe.units.implied_time_unit`)."""
    if time_unit is not None:
        return time_unit
    own = scene.time_unit if isinstance(scene, Scene) else scene_time_unit(scene)
    return own or implied_time_unit(*values)


def _pairs_list(items: list, where: str, time_unit: str | None
                ) -> tuple[np.ndarray, tuple[str | None, ...]]:
    """The (fast, slow) angular frequencies of an impulse scene's modes, and their labels."""
    keys = ("fast", "slow", "label")
    pairs, labels = [], []
    for i, item in enumerate(items):
        if not isinstance(item, dict) or "fast" not in item or "slow" not in item:
            raise _fail(where, f"modes[{i}]", "every mode of an impulse scene gives fast: and "
                                              "slow: (write slow: 0 for a fast force alone)")
        unknown = set(item) - set(keys)
        if unknown:
            raise _fail(where, f"modes[{i}].{sorted(unknown)[0]}",
                        unknown_key(sorted(unknown)[0], keys))
        pair = []
        for key in ("fast", "slow"):
            value = item[key]
            if isinstance(value, QuotedText) and parse_real(value) is not None or \
                    not isinstance(value, str):
                value = number(value, where, f"modes[{i}].{key}")
            try:
                pair.append(any_frequency(value, time_unit))
            except StepsafeError as exc:
                message = exc.message.replace("beta must be", "must be")
                raise _fail(where, f"modes[{i}].{key}", message) from None
        if pair[0] == pair[1] == 0:
            raise _fail(where, f"modes[{i}]", "fast and slow are both 0")
        label = item.get("label")
        if label is not None and not isinstance(label, str):
            raise _fail(where, f"modes[{i}].label", f"must be text, got {label!r}")
        pairs.append(pair)
        labels.append(label)
    if len(pairs) > MAX_IMPULSE_MODES:
        raise _fail(where, "modes", f"{len(pairs)} modes; an impulse scene takes at most "
                                    f"{MAX_IMPULSE_MODES} (each is its own region)")
    return np.array(pairs, dtype=float), tuple(labels)


@compared
@dataclass(frozen=True, eq=False)
class ModesFile:
    """A modes file's frequencies grouped by model, and per model the modes' labels in the
    same order (None where a mode has none; a model without labels is absent)."""

    betas: dict[str, np.ndarray]  #: rad per ``time_unit``
    labels: dict[str, tuple[str | None, ...]]
    #: the unit of time the frequencies are per: the one asked for, else the file's
    #: ``time_unit:`` (None if neither names one)
    time_unit: str | None = None


def load_modes(path: str | Path, time_unit: str | None = None) -> ModesFile:
    """Frequencies (and labels) from a YAML or CSV modes file, grouped by model, as beta in
    rad per ``time_unit``. A YAML mapping (a scene file) gives them under ``modes:``, in
    its own ``time_unit:`` when it names one (converted to ``time_unit`` when that is
    another; the scene's other keys are not read here, unknown keys are refused)."""
    where = str(path)
    if str(path).lower().endswith(".csv"):
        return _load_csv(read_bytes(path, MAX_CSV_BYTES), where, time_unit)
    tree = load_yaml(path)
    if not isinstance(tree, dict):
        return ModesFile(*_modes_list(tree, where, "", time_unit), time_unit)
    for key in tree:
        if key not in SCENE_KEYS:
            raise _fail(where, str(key), unknown_key(key, SCENE_KEYS))
    if "modes" not in tree:
        raise _fail(where, "modes", "missing: a modes file lists its frequencies under "
                                    "modes: (a scene's system: is read as SCENE.yaml)")
    own = tree.get("time_unit")
    if own is not None and (not isinstance(own, str) or own not in TIME_UNITS):
        raise _fail(where, "time_unit", f"must be one of {', '.join(TIME_UNITS)}, got "
                                        f"{own!r}")
    betas, labels = _modes_list(tree["modes"], where, "modes", own or time_unit)
    if own is None or time_unit is None or own == time_unit:
        return ModesFile(betas, labels, own or time_unit)
    # rad per file unit to rad per --time-unit: times (seconds per --time-unit) / (seconds
    # per file unit), an exact ratio of powers of ten
    ratio = float(TIME_UNITS[time_unit] / TIME_UNITS[own])
    with np.errstate(over="ignore", under="ignore"):
        converted = {model: values * ratio for model, values in betas.items()}
    for model, values in converted.items():
        if not np.all(np.isfinite(values)) or np.any((values == 0) & (betas[model] != 0)):
            raise _fail(where, "modes", f"a frequency leaves the float range in rad/"
                                        f"{time_unit} (the file's are in rad/{own})")
    return ModesFile(converted, labels, time_unit)


def _load_csv(data: bytes, where: str, time_unit: str | None = None) -> ModesFile:
    """A modes CSV. Parsed by ``np.loadtxt`` (C speed); where it refuses a part of the file,
    that part is bisected down to blocks read row by row by :func:`_csv_rows`, which decides
    and names the first bad line. Memory and time stay linear in the file size."""
    if b"\x00" in data:
        raise _fail(where, "", "binary file (contains NUL bytes), not CSV text")
    if data.startswith(b"\xef\xbb\xbf"):  # UTF-8 byte order mark (spreadsheet exports)
        data = data[3:]
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    lines = data.count(b"\n") + (1 if data and not data.endswith(b"\n") else 0)
    if lines > MAX_CSV_ROWS + 1:
        raise _fail(where, "", f"has {lines} lines, more than the {MAX_CSV_ROWS} rows (and a "
                               "header) allowed")
    if not data.isascii():
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise _fail(where, "", f"not UTF-8 text (byte {exc.start})") from None
    body, first_line, header = _csv_header(data, where)
    rows = _CsvPart(data, body, len(data), first_line)
    form = next(h for h in header if h in FORMS)
    if form != "beta":  # parsed as the beta column, then converted
        header = ["beta" if h == form else h for h in header]
        try:
            values, codes = _csv_parse(rows, header, where, form)
        except StepsafeError as exc:
            raise StepsafeError(exc.message, (exc.where or "").replace(".beta", f".{form}")
                                ) from None
        betas = _converted(values, form, time_unit, rows, where)
    else:
        betas, codes = _csv_parse(rows, header, where)
    if not betas.size:
        raise _fail(where, "", "no rows after the header")
    labels: dict[str, tuple[str | None, ...]] = {}
    if "label" in header:
        column = header.index("label")
        names = np.array([text.split(",")[column].strip() or None
                          for _, text in rows.lines() if text.strip()], dtype=object)
        labels = {m: tuple(names[codes == k]) for k, m in enumerate(MODELS)
                  if np.any(codes == k) and any(names[codes == k])}
    return ModesFile({m: betas[codes == k] for k, m in enumerate(MODELS) if np.any(codes == k)},
                     labels, time_unit)


def _converted(values: np.ndarray, form: str, time_unit: str | None, rows: _CsvPart,
               where: str) -> np.ndarray:
    """beta (rad per time unit) of a column of sigma (1/sigma), wavenumber (cm-1),
    frequency (cycles per time unit) or period (time units), as the same entry of a
    ``modes:`` list gives; an error names the line of the first value that has none."""
    try:
        betas = angular_frequencies(form, values, time_unit)
    except StepsafeError as exc:
        raise _fail(where, form, exc.message) from None
    positive = form != "wavenumber" and form != "frequency"
    bad = np.flatnonzero(~((values > 0) if positive else (values >= 0)) | ~np.isfinite(betas))
    if bad.size:
        rows_seen = -1
        for number, text in rows.lines():
            rows_seen += bool(text.strip())
            if rows_seen == bad[0]:
                value = values[bad[0]]
                need = (SIGMA_RULE if form == "sigma" and not value > 0 else
                        "> 0 with a finite inverse" if positive else
                        ">= 0 with a finite angular frequency")
                raise _fail(where, f"line {number}.{form}", f"must be {need}, got {value:g}")
    return betas


#: Parts of a CSV with at most this many lines are read row by row once np.loadtxt has
#: refused them (about 0.5 s); larger parts are bisected.
_CSV_ROW_BY_ROW = 1 << 16


@dataclass
class _CsvPart:
    data: bytes
    start: int  # byte offsets: the part is data[start:end], whole lines
    end: int
    first_line: int  # line number of its first line

    def lines(self):
        """``(line number, text without comment)`` of each line, without a list of them."""
        stream = io.BytesIO(memoryview(self.data)[self.start:self.end])
        for number, raw in enumerate(stream, self.first_line):
            yield number, raw.decode("utf-8").rstrip("\n").split("#", 1)[0]

    def line(self, index: int) -> _CsvPart:
        """The part's line ``index`` (from 0) alone."""
        start, left, block = self.start, index, 1 << 20
        while left:  # skip whole 1 MiB blocks by counting, then single lines
            count = self.data.count(b"\n", start, min(start + block, self.end))
            if count < left and start + block < self.end:
                start, left = start + block, left - count
                continue
            for _ in range(left):
                start = self.data.find(b"\n", start, self.end) + 1
            left = 0
        end = self.data.find(b"\n", start, self.end)
        return _CsvPart(self.data, start, self.end if end < 0 else end + 1,
                        self.first_line + index)

    def halves(self) -> tuple[_CsvPart, _CsvPart] | None:
        middle = (self.start + self.end) // 2
        cut = self.data.find(b"\n", middle, self.end - 1)
        if cut < 0:
            cut = self.data.rfind(b"\n", self.start, middle)
        if cut < 0:
            return None
        left = _CsvPart(self.data, self.start, cut + 1, self.first_line)
        right = _CsvPart(self.data, cut + 1, self.end,
                         self.first_line + self.data.count(b"\n", self.start, cut + 1))
        return left, right


def _csv_header(data: bytes, where: str) -> tuple[int, int, list[str]]:
    """``(offset of the first row, its line number, column names)``."""
    offset = 0
    for number, text in _CsvPart(data, 0, len(data), 1).lines():
        end = data.find(b"\n", offset)
        offset = len(data) if end < 0 else end + 1
        if not text.strip():
            continue
        header = [h.strip().lower() for h in text.split(",")]
        if sum(h in FORMS for h in header) != 1 or \
                set(header) - {*FORMS, "model", "label"} or \
                len(set(header)) != len(header):
            raise _fail(where, "", "the CSV header must name one frequency column, beta (rad "
                                   "per time unit), sigma (standard deviations of a Gaussian "
                                   "target), wavenumber (cm-1), frequency (cycles per time "
                                   "unit) or period, and optionally model and label, each "
                                   f"once, got {text.strip()[:60]!r}")
        return offset, number + 1, header
    raise _fail(where, "", "empty CSV file")


def _csv_parse(part: _CsvPart, header: list[str], where: str, form: str = "beta"):
    """(betas, model codes) of the part, its frequency column read as ``beta`` (the values
    of ``form``: a sigma column is refused by the rule for standard deviations)."""
    fast = _csv_table(part, header)
    if isinstance(fast, tuple):
        return fast
    if isinstance(fast, int):
        # parsed, but row `fast` failed a check; every line is a row, so it is that line
        bad = part.line(fast)
        _csv_rows(bad, header, where, form)  # raises with the exact message, unless row by row
        # reading accepts what the check refused: then read the whole part that way
    halves = None
    if part.data.count(b"\n", part.start, part.end) > _CSV_ROW_BY_ROW:
        halves = part.halves()
    if halves is None:
        return _csv_rows(part, header, where, form)
    (b1, c1), (b2, c2) = (_csv_parse(half, header, where, form) for half in halves)
    return np.concatenate([b1, b2]), np.concatenate([c1, c2])


def _row_count(part: _CsvPart) -> int:
    count = part.data.count(b"\n", part.start, part.end)
    return count + (1 if part.end > part.start and part.data[part.end - 1] != 10 else 0)


def _csv_table(part: _CsvPart, header: list[str]):
    """``(betas, model codes)`` of the part by ``np.loadtxt``; if anything in it is not
    plainly valid, None (loadtxt refused it) or the index of the first row that failed a
    check, then :func:`_csv_rows` decides. ``model`` is read as bytes longer than any model
    name, so a wrong value can never be truncated into a right one."""
    import warnings

    width = 32
    dtype = [(name, {"beta": "f8", "model": f"S{width}", "label": "S1"}[name])
             for name in header]
    whole = part.end == len(part.data)
    stream = io.BytesIO(part.data if whole else part.data[part.start:part.end])
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data"
            table = np.loadtxt(stream, dtype=dtype, delimiter=",", comments="#", ndmin=1,
                               skiprows=part.first_line - 1 if whole else 0,
                               encoding="utf-8", quotechar=None)
    except (ValueError, TypeError, UnicodeError):
        return None
    betas = np.ascontiguousarray(table["beta"], dtype=float)
    codes = np.zeros(betas.size, dtype=np.int8)
    if "model" in header:
        names = np.char.strip(table["model"])
        codes[:] = -1
        for k, model in enumerate(MODELS):
            codes[names == model.encode()] = k
    wrong = (codes < 0) | ~np.isfinite(betas) | (betas < 0)
    if wrong.any():
        return int(np.argmax(wrong)) if betas.size == _row_count(part) else None
    return betas, codes


def _csv_rows(part: _CsvPart, header: list[str], where: str, form: str = "beta"):
    """The exact reader, row by row: betas and model codes of the part, or an error naming
    its first bad line (``$.line N.beta``). Fields are not quoted; ``#`` starts a comment.
    The values are of ``form``: a sigma column is refused by the rule for standard
    deviations, any other by ``>= 0`` (finite)."""
    from array import array

    ib = header.index("beta")
    im = header.index("model") if "model" in header else None
    betas, codes = array("d"), array("b")
    for number, text in part.lines():
        if not text.strip():
            continue
        fields = text.split(",")
        if len(fields) != len(header):
            raise _fail(where, f"line {number}", f"has {len(fields)} columns, the header "
                                                 f"{len(header)}")
        beta = parse_real(fields[ib])
        if beta is None:
            raise _fail(where, f"line {number}.beta", f"is not a number: {fields[ib].strip()!r}")
        if form == "sigma" and not (np.isfinite(beta) and beta > 0):
            raise _fail(where, f"line {number}.beta", f"must be {SIGMA_RULE}, got "
                                                      f"{fields[ib].strip()}")
        if not np.isfinite(beta) or beta < 0:
            raise _fail(where, f"line {number}.beta", f"must be a finite number >= 0, got "
                                                      f"{fields[ib].strip()}")
        model = fields[im].strip() if im is not None else "oscillator"
        if model not in MODELS:
            raise _fail(where, f"line {number}.model", f"must be one of {', '.join(MODELS)}, "
                                                       f"got {model!r}")
        betas.append(beta)
        codes.append(MODELS.index(model))
    return np.array(betas, dtype=float), np.array(codes, dtype=np.int8)
