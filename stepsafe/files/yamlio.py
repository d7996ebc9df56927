"""A strict, bounded YAML reader for method and scene files.

Every plain scalar stays a **string** (YAML 1.1 would read ``1e-3`` as a string but ``0.5``
as a float and ``no`` as False; here the schema layer decides every type, STYLE.md).
Refused, each with a one-line :class:`~stepsafe.exceptions.StepsafeError` naming the file:
files over :data:`MAX_BYTES`, binary or non-UTF-8 content, aliases and anchors (no alias
bombs), duplicate keys, nesting deeper than :data:`MAX_DEPTH`, more than :data:`MAX_NODES`
nodes, non-string keys, an explicit tag that cannot read its value (``!!int a``), and
anything that is not valid YAML.

A document is read by libyaml's scanner and parser (PyYAML's C extension) when PyYAML has
it, with the same composing and constructing in Python; a document libyaml does not read,
or one that is refused, is read again by PyYAML's pure-Python scanner and parser, whose
messages every error reports. Where the two scanners are known to differ, libyaml accepts
what PyYAML refuses (a tab after a plain scalar, a byte-order mark inside the text, a
comment right after a block scalar's header), so a text with a tab, a byte-order mark or
``|#`` is read by PyYAML alone; ``tests/test_yaml_readers.py`` compares the two on every
shipped file and on drawn documents.

Every input file of stepsafe is opened through :func:`open_regular`: FIFOs, devices and
sockets are refused before they are opened (reading them could block forever or never end).
"""

from __future__ import annotations

import copy
import os
import re
import stat
from typing import Any

import yaml
from yaml.composer import Composer
from yaml.constructor import SafeConstructor
from yaml.resolver import Resolver

from stepsafe.exceptions import StepsafeError

try:  # libyaml, when PyYAML was built with it
    from yaml._yaml import CParser
except ImportError:  # pragma: no cover - a PyYAML without its C extension
    CParser = None  # type: ignore[assignment,misc]

MAX_BYTES = 1 << 20
MAX_DEPTH = 32
MAX_NODES = 20_000


class QuotedText(str):
    """A scalar written in quotes: text by the author's choice, so a field whose schema
    says "number" can refuse it (``h: "0.1"``), while coefficient fields, which accept
    quoted expressions such as ``"2/3"``, read it like any other string."""


class _Strict:
    """The composing and constructing of the strict reader: no implicit typing, aliases,
    anchors, merge keys or duplicate keys; bounded in size and depth."""

    yaml_implicit_resolvers: dict = {}
    _depth = 0
    _nodes = 0

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
            return super().compose_node(parent, index)  # type: ignore[misc]
        finally:
            self._depth -= 1

    def construct_object(self, node, deep=False):  # noqa: ANN001
        try:
            return super().construct_object(node, deep=deep)  # type: ignore[misc]
        except (ValueError, TypeError, AttributeError, LookupError, ArithmeticError):
            # an explicit tag whose constructor fails on the value (!!int a, !!timestamp x)
            tag = str(node.tag).replace("tag:yaml.org,2002:", "!!")
            shown = node.value if isinstance(node.value, str) else "this node"
            raise StepsafeError(f"line {node.start_mark.line + 1}: {tag} cannot read "
                                f"{str(shown)[:40]!r}") from None

    def construct_scalar(self, node):  # noqa: ANN001
        value = super().construct_scalar(node)  # type: ignore[misc]
        return QuotedText(value) if node.style in ("'", '"') else value

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False
                          ) -> dict[Any, Any]:
        if not isinstance(node, yaml.MappingNode):  # (!!set a): PyYAML's refusal
            return super().construct_mapping(node, deep=True)  # type: ignore[misc]
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                line = key_node.start_mark.line + 1
                raise StepsafeError(f"line {line}: keys must be plain names")
            if key_node.tag == "tag:yaml.org,2002:merge":  # (<< would override keys unseen)
                raise StepsafeError(f"line {key_node.start_mark.line + 1}: YAML merge keys "
                                    "are not allowed")
            if key_node.value in seen:
                raise StepsafeError(f"line {key_node.start_mark.line + 1}: duplicate key "
                                    f"{key_node.value!r}")
            seen.add(key_node.value)
        return super().construct_mapping(node, deep=True)  # type: ignore[misc]

    def construct_sequence(self, node, deep=False):  # noqa: ANN001
        return super().construct_sequence(node, deep=True)  # type: ignore[misc]


class _StrictLoader(_Strict, yaml.SafeLoader):
    """The strict reader on PyYAML's pure-Python scanner and parser: its messages are those
    every error of a file reports."""


#: The strict reader on libyaml's scanner and parser, None without PyYAML's C extension.
_FastStrictLoader: type | None = None
if CParser is not None:
    class _LibyamlStrictLoader(_Strict, Composer, SafeConstructor, Resolver, CParser):
        """The strict reader on libyaml's scanner and parser: the same composing and
        constructing, on the events libyaml reads."""

        def __init__(self, stream: str) -> None:
            CParser.__init__(self, stream)
            Composer.__init__(self)
            SafeConstructor.__init__(self)
            Resolver.__init__(self)

    _FastStrictLoader = _LibyamlStrictLoader


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISDIR, "a directory")):
        if test(mode):
            return name
    return "a special file"


def open_regular(path: str | os.PathLike, max_bytes: int, where: str | None = None):
    """An open binary file object for ``path``, which must be an existing regular file of
    at most ``max_bytes`` bytes.

    The type is checked with ``os.stat`` before opening (a FIFO would block ``open``) and
    again with ``os.fstat`` on the descriptor, opened non-blocking, so a file swapped in
    between is refused too. Errors name ``where`` (default: the path).
    """
    if isinstance(path, bool) or not isinstance(path, (str, os.PathLike)):
        # (not a file descriptor: it may be a terminal)
        raise StepsafeError(f"a file path must be a string or path, got {type(path).__name__}")
    where = str(path) if where is None else where
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise StepsafeError("no such file", where) from None
    except OSError as exc:
        raise StepsafeError(f"cannot read: {exc.strerror or exc}", where) from None
    except ValueError:  # a NUL character: no file can have that name
        raise StepsafeError(f"not a file name: {where[:60]!r}") from None
    if stat.S_ISDIR(info.st_mode):
        raise StepsafeError("is a directory, not a file", where)
    if not stat.S_ISREG(info.st_mode):
        raise StepsafeError(f"not a regular file ({_kind(info.st_mode)})", where)
    if info.st_size > max_bytes:
        raise StepsafeError(f"file is {info.st_size} bytes, more than the {max_bytes} allowed",
                            where)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise StepsafeError(f"cannot read: {exc.strerror or exc}", where) from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise StepsafeError(f"not a regular file ({_kind(mode)})", where)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (see :func:`open_regular`)."""
    where = str(path)
    with open_regular(path, max_bytes, where) as fh:
        try:
            data = fh.read(max_bytes + 1)
        except OSError as exc:
            raise StepsafeError(f"cannot read: {exc.strerror or exc}", where) from None
    if len(data) > max_bytes:
        raise StepsafeError(f"file is more than the {max_bytes} bytes allowed", where)
    return data


def read_text(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> str:
    """The file's text; refuses missing, directory, special (FIFO, device, socket),
    unreadable, huge, binary, non-UTF-8."""
    where = str(path)
    data = read_bytes(path, max_bytes)
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


#: Documents already parsed in this process, by (text, where): one command reads a scene
#: or a method file several times (the method of a scene, its base method, the scene again
#: for its frequencies), and parsing is most of the cost of reading.
_PARSED: dict[tuple[str, str], Any] = {}
#: Only short documents are kept (method and scene files are a few kB), and a few of them.
_PARSED_SIZE, _PARSED_COUNT = 1 << 16, 64


def _copy(tree: Any) -> Any:
    """A parsed document that shares no list or mapping with ``tree`` (strings are
    immutable and shared)."""
    if type(tree) is dict:
        return {key: _copy(value) for key, value in tree.items()}
    if type(tree) is list:
        return [_copy(value) for value in tree]
    if isinstance(tree, str):
        return tree
    return copy.deepcopy(tree)  # what an explicit tag builds (!!set, !!binary, ...)


def parse_yaml(text: str, where: str = "<string>") -> Any:
    """Parse one YAML document strictly (see the module's description); a document parsed
    before in this process is returned again, as a copy the caller may change."""
    key = (text, where)
    if key in _PARSED:
        return _copy(_PARSED[key])
    data = _parse(text, where)
    if len(text) <= _PARSED_SIZE:
        if len(_PARSED) >= _PARSED_COUNT:
            _PARSED.pop(next(iter(_PARSED)))
        _PARSED[key] = _copy(data)
    return data


def _parse(text: str, where: str) -> Any:
    if not text.strip():
        raise StepsafeError("empty file", where)
    if _FastStrictLoader is not None and libyaml_reads_alike(text):
        try:
            return _load(_FastStrictLoader, text)
        except Exception:  # noqa: BLE001 - any refusal: the pure-Python reader says why
            pass
    try:
        data = _load(_StrictLoader, text)
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


def libyaml_reads_alike(text: str) -> bool:
    """Whether ``text`` is read by libyaml first: it has none of :data:`_LIBYAML_APART`.

    Parameters
    ----------
    text : str
        A document.

    Returns
    -------
    bool
    """
    return _LIBYAML_APART.search(text) is None


#: Where libyaml's scanner accepts what PyYAML's refuses: a tab (after a plain scalar), a
#: byte-order mark inside the text, a comment right after a block scalar's header (``|#``).
_LIBYAML_APART = re.compile(r"[\t\ufeff]|[|>][-+0-9]*#")


def _load(loader_class: type, text: str) -> Any:
    loader = loader_class(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()
