"""Every dataclass of the package compared by :func:`stepsafe.comparison.compared` is equal,
unequal and hashed exactly as the same class made by ``@dataclass(eq=True)`` (CPython's
generated ``__eq__`` and ``__hash__``), for field values drawn by hypothesis: equal and
unequal values, values of other types, unhashable ones, and instances of another class."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.comparison import compared

PACKAGE = Path(__file__).resolve().parent.parent / "stepsafe"


def _compared_classes() -> list[type]:
    """The classes of the package whose ``__eq__`` is the one :func:`compared` makes (found
    by its code object, in every module that imports :mod:`stepsafe.comparison`)."""
    probe = compared(dataclasses.make_dataclass("Probe", ["a"], frozen=True, eq=False))
    code = probe.__eq__.__code__
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "stepsafe.comparison import compared" not in path.read_text(encoding="utf-8"):
            continue
        module = importlib.import_module(".".join(
            path.relative_to(PACKAGE.parent).with_suffix("").parts))
        out += [cls for _, cls in inspect.getmembers(module, inspect.isclass)
                if cls.__module__ == module.__name__
                and getattr(cls.__dict__.get("__eq__"), "__code__", None) is code]
    return out


CLASSES = _compared_classes()


def _reference(cls: type) -> type:
    """The same fields (with their compare and hash flags) in a class that CPython's
    ``@dataclass(eq=True)`` makes, frozen as ``cls`` is."""
    specs = [(f.name, f.type, dataclasses.field(compare=f.compare, hash=f.hash))
             for f in dataclasses.fields(cls)]
    return dataclasses.make_dataclass(cls.__name__, specs, eq=True,
                                      frozen=cls.__dataclass_params__.frozen)


def _build(cls: type, values: dict) -> object:
    obj = object.__new__(cls)
    for name, value in values.items():
        object.__setattr__(obj, name, value)
    return obj


VALUES = st.one_of(st.integers(-3, 3), st.sampled_from(["a", "b"]), st.none(),
                   st.floats(allow_nan=True), st.tuples(st.integers(0, 1)),
                   st.lists(st.integers(0, 1), max_size=2))


def test_the_package_has_compared_classes():
    names = {c.__name__ for c in CLASSES}
    assert {"CheckReport", "AdviceReport", "RegionReport", "Modes", "CheckResult"} <= names


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: f"{c.__module__}.{c.__name__}")
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_equality_and_hash_are_those_dataclass_generates(cls, data):
    names = [f.name for f in dataclasses.fields(cls)]
    a = {n: data.draw(VALUES) for n in names}
    b = {n: (a[n] if data.draw(st.booleans()) else data.draw(VALUES)) for n in names}
    ref = _reference(cls)
    x, y = _build(cls, a), _build(cls, b)
    rx, ry = _build(ref, a), _build(ref, b)

    def outcome(f):
        try:
            return ("value", f())
        except TypeError as exc:  # unhashable values hash as in the reference
            return ("error", type(exc))

    assert outcome(lambda: x == y) == outcome(lambda: rx == ry)
    assert outcome(lambda: x != y) == outcome(lambda: rx != ry)
    assert outcome(lambda: hash(x)) == outcome(lambda: hash(rx))
    assert (x == rx) is False and x.__eq__(rx) is NotImplemented  # another class


def test_a_class_that_defines_its_own_equality_keeps_it():
    @compared
    @dataclasses.dataclass(frozen=True, eq=False)
    class Own:
        a: int

        def __eq__(self, other):
            return True

    assert Own(1) == Own(2)
    assert hash(Own(1)) == hash((1,))  # dataclass(eq=True) adds a hash beside a body's __eq__

    @compared
    @dataclasses.dataclass(eq=False)
    class Mutable:
        a: int

    assert Mutable(1) == Mutable(1) and Mutable.__hash__ is None


def test_compared_refuses_a_class_that_has_generated_equality():
    with pytest.raises(TypeError, match="eq=False"):
        compared(dataclasses.make_dataclass("C", ["a"], frozen=True))
