"""A document read again in the same process (a scene read for its method, then for its
frequencies) is the same document, and each reader gets its own copy: changing what one
reader got changes nothing another reads. A document that cannot be read is refused every
time it is read."""

from __future__ import annotations

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from stepsafe.exceptions import StepsafeError
from stepsafe.files.yamlio import QuotedText, load_yaml, parse_yaml

NAMES = st.text(st.characters(min_codepoint=97, max_codepoint=122), min_size=1, max_size=6)
TREES = st.recursive(
    st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(NAMES, inner, max_size=4),
    max_leaves=20)


def _containers(tree) -> list:
    if isinstance(tree, dict):
        return [tree, *(c for v in tree.values() for c in _containers(v))]
    if isinstance(tree, list):
        return [tree, *(c for v in tree for c in _containers(v))]
    return []


def _plain(tree):
    """The tree with quoted texts as plain ones (what safe_load gives)."""
    if isinstance(tree, dict):
        return {k: _plain(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_plain(v) for v in tree]
    return str(tree)


@settings(max_examples=60, deadline=None)
@given(tree=st.dictionaries(NAMES, TREES, min_size=1, max_size=4), where=NAMES)
def test_a_document_read_again_is_equal_and_shares_nothing_mutable(tree, where):
    text = yaml.safe_dump(tree, default_style='"')  # every scalar quoted: text, as written
    first = parse_yaml(text, where)
    assert _plain(first) == tree
    second = parse_yaml(text, where)
    assert second == first
    assert all(isinstance(s, QuotedText) for s in _leaves(second))
    assert not {id(c) for c in _containers(first)} & {id(c) for c in _containers(second)}
    first.clear()  # one reader changes its copy: the next reader still gets the document
    assert _plain(parse_yaml(text, where)) == tree


def _leaves(tree) -> list:
    if isinstance(tree, dict):
        return [x for v in tree.values() for x in _leaves(v)]
    if isinstance(tree, list):
        return [x for v in tree for x in _leaves(v)]
    return [tree]


def test_a_changed_file_is_read_anew(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("h: 0.1\n", encoding="utf-8")
    assert load_yaml(path) == {"h": "0.1"}
    path.write_text("h: 0.2\n", encoding="utf-8")
    assert load_yaml(path) == {"h": "0.2"}


@pytest.mark.parametrize("text, message", [("a: 1\na: 2\n", "duplicate key"),
                                           ("a: &x 1\nb: *x\n", "anchors are not allowed")])
def test_a_refused_document_is_refused_each_time(text, message):
    for _ in range(2):
        with pytest.raises(StepsafeError, match=message) as err:
            parse_yaml(text, "f.yaml")
        assert err.value.where == "f.yaml"
