"""The public functions' docstrings: numpydoc Parameters that name every parameter of the
signature and a Returns section, as ``help()`` shows them and as the API reference reads
them from the source (griffe, without importing), the keyword blocks several functions
share (:mod:`stepsafe.api.keywords`) in place in both."""

from __future__ import annotations

import inspect
import re
import sys
from pathlib import Path

import pytest

import stepsafe
from stepsafe.api import keywords

ROOT = Path(__file__).resolve().parent.parent

#: The public functions of ``stepsafe``.
PUBLIC = sorted(name for name in stepsafe.__all__
                if inspect.isfunction(getattr(stepsafe, name)))

#: Those whose docstring, as written, names a shared block.
SHARED = [name for name in PUBLIC
          if "<keywords:" in (inspect.getsource(inspect.unwrap(getattr(stepsafe, name))))]


def documented(doc: str) -> list[str]:
    """The parameter names of a numpydoc Parameters section (``a, b : type`` names two)."""
    section = doc.split("Parameters\n----------\n", 1)[1]
    section = re.split(r"\n\n?[A-Z][A-Za-z ]+\n-{3,}\n", section)[0]
    names = []
    for line in section.split("\n"):
        head = re.match(r"([A-Za-z_][\w]*(?:, [A-Za-z_][\w]*)*)( :.*)?$", line)
        if head:
            names.extend(n.strip() for n in head.group(1).split(","))
    return names


def test_shared_blocks_are_named_by_several_functions_each():
    """Each block serves at least two functions (else it belongs in the one docstring)."""
    sources = [inspect.getsource(inspect.unwrap(getattr(stepsafe, name))) for name in SHARED]
    for block in keywords.BLOCKS:
        assert sum(f"<keywords: {block}>" in s for s in sources) >= 2, block
    assert {"problem", "advise", "check", "check_scenes", "hmc", "design"} <= set(SHARED)


@pytest.mark.parametrize("name", PUBLIC)
def test_public_function_documents_every_parameter_and_what_it_returns(name):
    """``help()``'s docstring has Parameters naming each parameter of the signature once,
    in order of kind only (no stray marker), and a Returns section."""
    func = getattr(stepsafe, name)
    doc = inspect.getdoc(func) or ""
    assert "Parameters\n----------" in doc and "Returns\n-------" in doc, name
    assert "<keywords:" not in doc
    names = documented(doc)
    assert sorted(names) == sorted(inspect.signature(func).parameters), name


#: The public methods of the public classes (``Class.method``), those a class defines itself.
METHODS = sorted(
    f"{name}.{attr}" for name in stepsafe.__all__ if inspect.isclass(getattr(stepsafe, name))
    for attr, member in vars(getattr(stepsafe, name)).items()
    if not attr.startswith("_") and inspect.isfunction(member))


@pytest.mark.parametrize("qualname", METHODS)
def test_public_method_documents_its_parameters_and_what_it_returns(qualname):
    """A public class's own method: a Returns section, and Parameters naming each parameter
    after ``self`` when it has any (context managers, which return nothing, excepted)."""
    cls_name, attr = qualname.split(".")
    func = vars(getattr(stepsafe, cls_name))[attr]
    doc = inspect.getdoc(func) or ""
    params = list(inspect.signature(func).parameters)[1:]
    if params:
        assert sorted(documented(doc)) == sorted(params), qualname
    if "contextmanager" not in inspect.getsource(func).split("def ", 1)[0]:
        assert "Returns\n-------" in doc, qualname


def test_expanding_puts_each_block_at_its_marker_with_the_marker_indentation():
    doc = "Intro.\n\n    Parameters\n    ----------\n    x : int\n        An x.\n" \
          "    <keywords: scene>\n    y : int\n        A y.\n"
    out = keywords.expand(doc)
    lines = out.split("\n")
    assert lines[:6] == doc.split("\n")[:6] and out.endswith("    y : int\n        A y.\n")
    block = [line[4:] for line in lines[6:-3]]
    assert "\n".join(block) == keywords.SCENE
    with pytest.raises(KeyError):
        keywords.expand("    <keywords: nothing>")


@pytest.fixture(scope="module")
def static_package():
    """The package as griffe reads it from the source, with the docs' extension."""
    griffe = pytest.importorskip("griffe")
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        from shared_keywords import SharedKeywords
    finally:
        sys.path.remove(str(ROOT / "docs" / "hooks"))
    return griffe.load("stepsafe", search_paths=[str(ROOT)], resolve_aliases=False,
                       extensions=griffe.load_extensions(SharedKeywords()))


@pytest.mark.parametrize("name", SHARED)
def test_the_api_reference_reads_the_parameters_help_shows(static_package, name):
    """griffe, reading the source as mkdocstrings does with the docs' extension
    (``docs/hooks/shared_keywords.py``), finds the same parameters, with the same
    descriptions, as ``help()``."""
    import griffe

    func = getattr(stepsafe, name)
    module = inspect.unwrap(func).__module__.removeprefix("stepsafe.")
    static = static_package[f"{module}.{name}"].docstring
    runtime = griffe.Docstring(inspect.getdoc(func))

    def parameters(docstring):
        (section,) = [s for s in docstring.parse("numpy") if s.kind.value == "parameters"]
        return [(p.name, p.description) for p in section.value]

    assert parameters(static) == parameters(runtime)
    assert [p for p, _ in parameters(static)] == documented(inspect.getdoc(func))
