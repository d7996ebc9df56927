"""Frozen records compared by one shared routine: the dataclasses of the reports, methods and
scenes that every command builds when its modules load.

``@dataclass`` writes the source of ``__eq__`` and ``__hash__`` for each class and compiles
it when the class is made, with ``__init__``, ``__repr__`` and the frozen ``__setattr__``;
for the reports, method tableaux and scenes that made about half of the cost of their
classes, and those classes most of the package's own start-up. A class written as::

    @compared
    @dataclass(frozen=True, eq=False)
    class CheckReport: ...

gets the ``__eq__`` and ``__hash__`` that ``@dataclass(frozen=True)`` would generate (and
keeps those its body defines, as ``@dataclass`` does), from closures made here: two
instances of the same class are equal when the tuples of their fields with
``compare=True``, in order, are equal (another class: ``NotImplemented``), and a frozen
instance hashes as the tuple of its fields with ``hash=True``, or with ``compare=True`` and
``hash=None``; a class that is not frozen is unhashable, as with ``eq=True``.
``tests/test_comparison.py`` compares both with the methods CPython generates.
"""

from __future__ import annotations

from dataclasses import MISSING, fields
from typing import Any, TypeVar

T = TypeVar("T", bound=type)


def compared(cls: T) -> T:
    """``cls`` (a dataclass made with ``eq=False``) with the ``__eq__`` and ``__hash__`` that
    ``eq=True`` gives it.

    Parameters
    ----------
    cls : type
        A dataclass made with ``eq=False``.

    Returns
    -------
    type
        ``cls``, changed in place.
    """
    params = cls.__dataclass_params__  # type: ignore[attr-defined]
    if params.eq:
        raise TypeError(f"{cls.__name__}: compared() is for a dataclass made with eq=False")
    names = tuple(f.name for f in fields(cls) if f.compare)
    hashed = tuple(f.name for f in fields(cls) if (f.compare if f.hash is None else f.hash))

    def __eq__(self: Any, other: Any) -> Any:
        if other.__class__ is self.__class__:
            return (tuple(getattr(self, n) for n in names)
                    == tuple(getattr(other, n) for n in names))
        return NotImplemented

    def __hash__(self: Any) -> int:
        return hash(tuple(getattr(self, n) for n in hashed))

    body_hash = cls.__dict__.get("__hash__", MISSING)  # as dataclass() tells it
    explicit_hash = not (body_hash is MISSING or (body_hash is None and "__eq__" in cls.__dict__))
    if "__eq__" not in cls.__dict__:
        __eq__.__qualname__ = f"{cls.__qualname__}.__eq__"
        cls.__eq__ = __eq__  # type: ignore[assignment]
    if not explicit_hash:
        __hash__.__qualname__ = f"{cls.__qualname__}.__hash__"
        cls.__hash__ = __hash__ if params.frozen else None  # type: ignore[assignment]
    return cls
