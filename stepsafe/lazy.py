"""Modules of the package that only some inputs reach, named at the top of the module that
uses them and loaded on first use.

A command should load only what its own path needs: ``stepsafe check --beta 1`` runs the
linear analysis and never a molecular-dynamics engine, a thermal ensemble or mpmath, yet the
same ``check`` analyses those when the scene asks for them (a ``system:``, a
``temperature:``, an impulse method, ``--verify``). Such a module is written at the top of
its user, beside the imports, as::

    if TYPE_CHECKING:  # the type checker sees the module itself
        from stepsafe.systems import loader
    else:
        loader = lazy_module("stepsafe.systems.loader")

and is imported when one of its attributes is first read (``loader.analyse_system``). The
dependency stays visible where the imports are, and ``tests/test_layers.py`` holds it to
the same rules as an import: it goes to the same layer or one below, it closes no cycle
between packages, and ``lazy_module`` is called at module level only, with the module's
full name written out. ``tests/test_imports.py`` checks which modules each command loads.
This is the pattern of Scientific Python's SPEC 1 (lazy loading of submodules).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any


class LazyModule:
    """Stands for the module ``name`` until an attribute is read, which imports it."""

    __slots__ = ("_name",)

    def __init__(self, name: str) -> None:
        object.__setattr__(self, "_name", name)

    def __getattr__(self, attribute: str) -> Any:
        return getattr(loaded(self), attribute)

    def __setattr__(self, attribute: str, value: Any) -> None:
        raise AttributeError(f"{self._name} is read through lazy_module, not written")

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


def lazy_module(name: str) -> Any:
    """The module ``name`` (its full dotted name), imported when first used.

    Parameters
    ----------
    name : str
        The full name of a module of the package, ``"stepsafe.systems.loader"``.

    Returns
    -------
    LazyModule
        Reads of its attributes are those of the module.
    """
    return LazyModule(name)


def loaded(module: LazyModule | ModuleType) -> ModuleType:
    """The module a :func:`lazy_module` stands for, imported now (a module: itself).

    Parameters
    ----------
    module : LazyModule or module

    Returns
    -------
    module
    """
    if isinstance(module, ModuleType):
        return module
    return importlib.import_module(object.__getattribute__(module, "_name"))
