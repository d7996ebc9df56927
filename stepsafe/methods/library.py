"""Finding methods by name: the built-in YAML files, the families and method-file paths.

``resolve("pefrl")`` loads ``methods/pefrl.yaml`` (or a file that lists ``pefrl`` among
its aliases); ``resolve("gauss", stages=3)`` builds a family member; ``resolve("my.yaml")``
loads a file; ``base=`` swaps the base method of a composition. Unknown names raise
:class:`~stepsafe.exceptions.StepsafeError` with the closest known names.

The built-in files live in the top-level ``methods/`` folder of the source tree, which the
wheel installs as the package data folder ``stepsafe/methods``; both locations are searched
so that editable installs and wheels behave alike.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path
from typing import Any, NamedTuple

from stepsafe.exceptions import MethodError, StepsafeError
from stepsafe.files.expressions import FLOAT
from stepsafe.files.yamlio import load_yaml
from stepsafe.methods.families import gauss, is_symmetric, lobatto3ab
from stepsafe.methods.fileformat import build_method, validate_tree
from stepsafe.methods.protocol import Exact
from stepsafe.methods.tableaux import Composition

FAMILIES = {
    "gauss": ("Gauss–Legendre collocation (order 2s)", 1),
    "lobatto3ab": ("Lobatto IIIA (q) – IIIB (p) pair (order 2s-2)", 2),
}


class Entry(NamedTuple):
    """What is known about a method besides its coefficients."""

    name: str
    kind: str
    title: str
    order: int | None
    source: str
    aliases: tuple[str, ...] = ()
    path: str | None = None
    evaluations: int | None = None
    published_stability: dict[str, Any] | None = None


def builtin_dir() -> Path:
    """Folder holding the built-in method files (package data, or the source checkout)."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "builtin", here.parent.parent / "methods"):
        if candidate.is_dir() and any(candidate.glob("*.yaml")):
            return candidate
    raise StepsafeError("the built-in method files are missing from this installation")


@lru_cache(maxsize=1)
def _alias_index() -> dict[str, Path]:
    """Every name and alias of every built-in file (parses them all; used only on a miss)."""
    index: dict[str, Path] = {}
    for path in sorted(builtin_dir().glob("*.yaml")):
        tree = load_yaml(path)
        index[path.stem] = path
        if isinstance(tree, dict):
            for alias in tree.get("aliases", []) or []:
                index.setdefault(str(alias), path)
    return index


#: Kinds of built-in files that are not one-force Hamiltonian integrators: impulse methods
#: need a fast and a slow force, Langevin splittings are stochastic (analysed by their mean
#: map and covariance on vibrations only).
NOT_SINGLE_FORCE = ("impulse", "langevin")


def builtin_names(single_force: bool = False) -> list[str]:
    """Names of the built-in method files and families; with ``single_force`` only the
    one-force Hamiltonian integrators (without the kinds of :data:`NOT_SINGLE_FORCE`)."""
    files = [p.stem for p in builtin_dir().glob("*.yaml")]
    if single_force:
        files = [name for name in files if _file_kinds().get(name) not in NOT_SINGLE_FORCE]
    return sorted(files + list(FAMILIES))


@lru_cache(maxsize=1)
def _file_kinds() -> dict[str, str]:
    """The ``kind:`` of every built-in file, by name."""
    kinds = {}
    for path in builtin_dir().glob("*.yaml"):
        tree = load_yaml(path)
        kinds[path.stem] = str(tree.get("kind")) if isinstance(tree, dict) else ""
    return kinds


def _looks_like_path(name: str) -> bool:
    return name.endswith((".yaml", ".yml")) or "/" in name or "\\" in name


def load_file(path: str | Path, backend=None):
    """Validated :class:`~stepsafe.methods.fileformat.MethodData` of a method file."""
    return validate_tree(load_yaml(path), str(path), backend or FLOAT)


def _entry(data, path: Path | None) -> Entry:
    return Entry(data.name, data.kind, data.title, data.order, data.source, data.aliases,
                 str(path) if path else None, data.evaluations, data.published_stability)


def resolve(name: str, stages: int | None = None, base: str | None = None,
            _depth: int = 0):
    """``(method, entry)`` for a built-in name, a family with ``stages`` or a file path."""
    if _depth > 8:
        raise StepsafeError(f"method {name!r}: base methods nested too deeply (a cycle?)")
    if not isinstance(name, str) or not name.strip():
        raise StepsafeError("the method name is empty")
    name = name.strip()
    if name in FAMILIES:
        method, entry = _family(name, stages)
    else:
        if stages is not None:
            raise StepsafeError(f"-s/--stages applies only to the families "
                                f"{', '.join(FAMILIES)}, not to {name!r}")
        path = _find_file(name)
        data = load_file(path)
        method = replace(_build(data, _depth, Path(path).parent),
                         exact=Exact("file", str(path), None, None))
        entry = _entry(data, path)
    if base is not None:
        method, entry = _swap_base(method, entry, base, _depth)
        method = replace(method, exact=Exact("file", name, stages, base))
    return method, entry


def _find_file(name: str) -> Path:
    if _looks_like_path(name) or Path(name).is_file():
        return Path(name)
    path = builtin_dir() / f"{name}.yaml"
    if path.is_file():
        return path
    index = _alias_index()
    if name in index:
        return index[name]
    import difflib  # (only for a name that is not found)

    known = sorted(set(index) | set(FAMILIES))
    close = difflib.get_close_matches(name, known, n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else "; see 'stepsafe methods'"
    raise StepsafeError(f"unknown method {name!r}{hint}")


def _family(name: str, stages: int | None):
    title, smallest = FAMILIES[name]
    if stages is None:
        raise StepsafeError(f"{name} is a family: give the stage count with -s N (N >= {smallest})")
    try:
        method = gauss(stages) if name == "gauss" else lobatto3ab(stages)
    except MethodError as exc:
        raise StepsafeError(str(exc)) from None
    source = ("Hairer & Wanner, Solving ODEs II, Sec. IV.5 (W-transformation); "
              "Sun Geng (1993) for the IIIA-IIIB pair" if name == "lobatto3ab"
              else "Hairer & Wanner, Solving ODEs II, Sec. IV.5")
    entry = Entry(method.name, method.kind, method.title, method.order, source,
                  evaluations=method.evaluations)
    return method, entry


def _build(data, depth: int, folder: Path):
    """Float method of a validated file; a base given as a relative path is found next to
    the file that names it."""
    def local(name: str) -> str:
        return str(folder / name) if _looks_like_path(name) and not Path(name).is_absolute() \
            else name

    def resolve_base(ref):
        if isinstance(ref, dict):
            return resolve(local(ref["name"]), ref.get("stages"), _depth=depth + 1)[0]
        return resolve(local(ref), _depth=depth + 1)[0]

    try:
        return build_method(data, resolve_base)
    except MethodError as exc:
        raise StepsafeError(str(exc), data.where) from None


def _swap_base(method, entry: Entry, base: str, depth: int):

    if not isinstance(method, Composition):
        raise StepsafeError(f"--base applies to compositions; {entry.name} is a "
                            f"{entry.kind} method")
    name, _, stages = base.partition(":")
    if name in FAMILIES and not stages:
        raise StepsafeError(f"--base {name} is a family: write it as {name}:N (e.g. {name}:3)")
    if stages and not (stages.isascii() and stages.isdigit() and len(stages) <= 30):
        raise StepsafeError(f"--base {base!r}: the stage count after ':' must be a whole "
                            "number written with the digits 0-9")
    new_base, base_entry = resolve(name, int(stages) if stages else None, _depth=depth + 1)
    same_order = (method.base_order is not None and new_base.order == method.base_order
                  and is_symmetric(new_base))
    order = method.order if same_order else None
    swapped = Composition(new_base, method.weights, name=f"{method.name}[{new_base.name}]",
                          order=order, evaluations=None,
                          title=f"{method.title or method.name} over {base_entry.name}",
                          base_order=new_base.order)
    return swapped, entry._replace(name=swapped.name, title=swapped.title, order=order,
                                   evaluations=None)
