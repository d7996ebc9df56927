"""A strict, bounded YAML reader for method and scene files.

Every plain scalar stays a **string** (YAML 1.1 would read ``1e-3`` as a string but ``0.5``
as a float and ``no`` as False; here the schema layer decides every type, STYLE.md).
Refused, each with a one-line :class:`~stepsafe.errors.StepsafeError` naming the file:
files over :data:`MAX_BYTES`, binary or non-UTF-8 content, aliases and anchors (no alias
bombs), duplicate keys, nesting deeper than :data:`MAX_DEPTH`, more than :data:`MAX_NODES`
nodes, non-string keys, and anything that is not valid YAML.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from .errors import StepsafeError

MAX_BYTES = 1 << 20
MAX_DEPTH = 32
MAX_NODES = 200_000


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader without implicit typing, aliases or duplicate keys; bounded in size."""

    yaml_implicit_resolvers: dict = {}

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent, index):  # noqa: ANN001 - PyYAML's signature
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise StepsafeError(f"line {event.start_mark.line + 1}: YAML aliases are not allowed")
        event = self.peek_event()
        if getattr(event, "anchor", None):
            raise StepsafeError(f"line {event.start_mark.line + 1}: YAML anchors are not allowed")
        self._nodes += 1
        if self._nodes > MAX_NODES:
            raise StepsafeError(f"more than {MAX_NODES} YAML nodes")
        self._depth += 1
        if self._depth > MAX_DEPTH:
            raise StepsafeError(f"line {event.start_mark.line + 1}: nested deeper than {MAX_DEPTH}")
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):  # noqa: ANN001
        seen: set = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                line = key_node.start_mark.line + 1
                raise StepsafeError(f"line {line}: keys must be plain names")
            if key_node.value in seen:
                raise StepsafeError(f"line {key_node.start_mark.line + 1}: duplicate key "
                                    f"{key_node.value!r}")
            seen.add(key_node.value)
        return super().construct_mapping(node, deep=True)

    def construct_sequence(self, node, deep=False):  # noqa: ANN001
        return super().construct_sequence(node, deep=True)


def read_text(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> str:
    """The file's text; refuses missing, directory, unreadable, huge, binary, non-UTF-8."""
    p = Path(path)
    where = str(path)
    if not p.exists():
        raise StepsafeError("no such file", where)
    if p.is_dir():
        raise StepsafeError("is a directory, not a file", where)
    try:
        size = p.stat().st_size
        if size > max_bytes:
            raise StepsafeError(f"file is {size} bytes, more than the {max_bytes} allowed", where)
        with open(p, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise StepsafeError(f"cannot read: {exc.strerror or exc}", where) from None
    if len(data) > max_bytes:
        raise StepsafeError(f"file is more than the {max_bytes} bytes allowed", where)
    if b"\x00" in data:
        raise StepsafeError("binary file (contains NUL bytes), not YAML text", where)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise StepsafeError(f"not UTF-8 text (byte {exc.start})", where) from None


def load_yaml(path: str | os.PathLike) -> Any:
    """Parse one YAML document strictly; every scalar is a string."""
    text = read_text(path)
    return parse_yaml(text, str(path))


def parse_yaml(text: str, where: str = "<string>") -> Any:
    if not text.strip():
        raise StepsafeError("empty file", where)
    try:
        loader = _StrictLoader(text)
        try:
            data = loader.get_single_data()
        finally:
            loader.dispose()
    except StepsafeError as exc:
        raise StepsafeError(exc.message, where) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or "not valid YAML"
        raise StepsafeError(f"{at}{problem}", where) from None
    except RecursionError:
        raise StepsafeError(f"nested deeper than {MAX_DEPTH}", where) from None
    return data
