"""The strict YAML reader answers the same with libyaml as with PyYAML's pure-Python
scanner alone (:mod:`stepsafe.files.yamlio`): the same document, each scalar's type
(:class:`~stepsafe.files.yamlio.QuotedText` or text) included, or the same refusal with the
same message. Checked on every YAML file the project ships and on drawn documents: valid
trees in block style, those trees with a character inserted or a stretch cut out, and
strings of YAML's punctuation, indicators, tags, directives, escapes, tabs, byte-order
marks, line separators and control characters."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stepsafe.exceptions import StepsafeError
from stepsafe.files import yamlio

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.skipif(yamlio._FastStrictLoader is None,
                                reason="PyYAML without its C extension (libyaml)")


def _typed(tree):
    """The tree with each scalar's type beside it (QuotedText and str differ)."""
    if isinstance(tree, dict):
        return {_typed(k): _typed(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_typed(v) for v in tree]
    if isinstance(tree, (set, frozenset)):
        return ("set", frozenset(_typed(v) for v in tree))
    if isinstance(tree, float) and tree != tree:
        return ("float", "nan")
    return (type(tree).__name__, tree)


def _answer(text: str, monkeypatch, libyaml: bool):
    """What the strict reader answers for ``text`` (a fresh parse: no document reused)."""
    monkeypatch.setattr(yamlio, "_PARSED", {})
    if not libyaml:
        monkeypatch.setattr(yamlio, "_FastStrictLoader", None)
    try:
        return "read", _typed(yamlio.parse_yaml(text, "f.yaml"))
    except StepsafeError as exc:
        return "refused", exc.message, exc.where
    finally:
        monkeypatch.undo()


def _same_answer(text: str) -> None:
    with pytest.MonkeyPatch.context() as monkeypatch:
        assert _answer(text, monkeypatch, True) == _answer(text, monkeypatch, False), text


SHIPPED = sorted(p for pattern in ("methods/*.yaml", "examples/**/*.yaml", "examples/*.yml",
                                   "tests/corpus/**/*.yaml", "tests/corpus/**/*.yml")
                 for p in ROOT.glob(pattern))


def test_every_shipped_file_reads_alike_and_the_method_files_by_libyaml():
    assert len(SHIPPED) > 50
    for path in SHIPPED:
        try:  # (the corpus has binary and non-UTF-8 files: refused before any parsing)
            text = path.read_bytes().decode("utf-8")
        except UnicodeDecodeError:
            continue
        _same_answer(text)
    for path in ROOT.glob("methods/*.yaml"):  # the built-in methods take the fast path
        text = path.read_text(encoding="utf-8")
        assert yamlio.libyaml_reads_alike(text), path
        yamlio._load(yamlio._FastStrictLoader, text)  # reads without a refusal


PIECES = (list("ab01 .:-[]{},#\"'\\|>!&*%@`?\n\n\n  \t\rxyz=+/eE")
          + ["\x85", "\u2028", "\u2029", "\ufeff", "é", "\x7f", "\x1b", "\x9f", "\ud800",
             "\U0001F600", "\uffff", "\\x41", "\\u00e9", "\\/", "\\N", "\\_", "---", "...",
             "!!int ", "!!float ", "!!str ", "!!set ", "!!binary ", "!!timestamp ", "!!null ",
             "!!bool ", "!!omap ", "!!pairs ", "!!map ", "!!seq ", "!!merge ", "!!value ",
             "<<: ", "- ", ": ", "? ", "%YAML 1.1\n", "%YAML 1.2\n---\n", "%YAML 2.0\n---\n",
             "%TAG ! tag:x,2000:\n", "&a ", "*a", "'a''b'", "\"a\\\"b\"", "|\n  x\n",
             ">-\n  x\n  y\n", "\r\n", "{a:1}", "[a:1]", "? a\n: b\n", "- - a\n", "a: b: c\n",
             "!<tag:yaml.org,2002:str> ", "!x ", "k" * 1030 + ": v\n", "[" * 40, "|+\n x\n\n",
             '"\\e\\L\\P\\ \\x85"', "'\n  x'", "a #x\n", "a#x\n", "|#", ">-#x", "|2 #x\n"])
SCALARS = st.one_of(
    st.text(alphabet="ab01.-e+ :#'\"\\é\t", max_size=8),
    st.sampled_from(["1e-3", "0.5", "no", "~", "null", "2/3", "1 - 2*b", "true",
                     "2001-12-14", "0x1F", "'q'", '"d\\tq"', "|\n    lit\n",
                     ">\n    fold\n    ed\n"]))
TREES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=3),
    st.dictionaries(st.text("abk", min_size=1, max_size=3), inner, max_size=3)),
    max_leaves=8)


def _block(tree, indent: int = 0) -> str:
    pad = " " * indent
    if isinstance(tree, dict):
        return "{}" if not tree else "\n" + "\n".join(
            f"{pad}{k}: {_block(v, indent + 2)}" for k, v in tree.items())
    if isinstance(tree, list):
        return "[]" if not tree else "\n" + "\n".join(
            f"{pad}- {_block(v, indent + 2)}" for v in tree)
    return tree


BLOCKS = TREES.map(lambda tree: _block(tree).lstrip("\n") + "\n")
DOCUMENTS = st.one_of(
    st.lists(st.sampled_from(PIECES), max_size=40).map("".join),
    BLOCKS,
    st.tuples(BLOCKS, st.integers(0, 200), st.sampled_from(PIECES)).map(
        lambda t: t[0][:t[1]] + t[2] + t[0][t[1]:]),
    st.tuples(BLOCKS, st.integers(0, 200), st.integers(1, 5)).map(
        lambda t: t[0][:t[1]] + t[0][t[1] + t[2]:]),
)


@settings(max_examples=300, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(DOCUMENTS)
def test_a_drawn_document_reads_alike(text):
    _same_answer(text)


READABLE = {"float": {"nan", "inf", "infinity"},
            "bool": {"yes", "no", "true", "false", "on", "off"}}


@settings(max_examples=60, deadline=None, database=None)
@given(tag=st.sampled_from(["int", "float", "bool", "timestamp"]),
       value=st.text("abcdefghijklmnopqrstuvwxyz", min_size=1, max_size=8),
       before=st.integers(0, 5), nested=st.booleans())
def test_an_explicit_tag_that_cannot_read_its_value_is_refused_with_its_line(tag, value,
                                                                             before, nested):
    """``!!int a`` and the like: a one-line refusal naming the line (as bad input), by
    either reader, never an exception of PyYAML's constructors."""
    if value.lower() in READABLE.get(tag, ()):
        return
    lines = "".join(f"k{i}: v\n" for i in range(before))
    text = lines + (f"x: [1, !!{tag} {value}]\n" if nested else f"x: !!{tag} {value}\n")
    for libyaml in (True, False):
        with pytest.MonkeyPatch.context() as monkeypatch:
            answer = _answer(text, monkeypatch, libyaml)
        assert answer == ("refused", f"line {before + 1}: !!{tag} cannot read {value!r}",
                          "f.yaml")
