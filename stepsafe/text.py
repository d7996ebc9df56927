"""Text from files, shown on a terminal literally.

Titles, sources and names come from method and scene files that stepsafe did not write.
:func:`printable` replaces every control or format character (Unicode categories Cc, Cf,
Cs, Zl, Zp: C0 and C1 controls such as ESC and CSI ``\\x9b``, DEL, bidirectional
overrides, zero-width characters, lone surrogates, line and paragraph separators) by a
visible escape such as ``\\x1b``; only the tab is kept. Rich markup is escaped separately
where text reaches rich (:mod:`stepsafe.cli.report`); ``--json`` output needs neither
(:func:`json.dumps` escapes control characters).
"""

from __future__ import annotations

import unicodedata

_KEEP = {"\t"}
_HIDDEN = ("Cc", "Cf", "Cs", "Zl", "Zp")  # controls, format, surrogates, line separators


def _visible(ch: str) -> str:
    code = ord(ch)
    if code < 0x100:
        return f"\\x{code:02x}"
    if code < 0x10000:
        return f"\\u{code:04x}"
    return f"\\U{code:08x}"


def printable(text: object) -> str:
    """``str(text)`` with control and format characters replaced by visible escapes."""
    s = str(text)
    if s.isprintable():  # the common case: nothing to replace (tab and space aside)
        return s
    return "".join(_visible(ch) if ch not in _KEEP and unicodedata.category(ch) in _HIDDEN
                   else ch for ch in s)


def ascii_whole(text: object, max_digits: int = 1000) -> int | None:
    """The whole number written in ``text`` with ASCII digits 0-9 (an optional leading ``+``
    and surrounding spaces allowed), else None.

    ``str.isdigit`` also accepts superscripts (``"²"``, which ``int`` then rejects) and other
    scripts' digits (``"٣"``, which ``int`` reads as 3); a number in a file or on the
    command line is written in ASCII. More than ``max_digits`` digits is None too (``int``
    refuses strings beyond 4300 digits)."""
    if not isinstance(text, str):
        return None
    s = text.strip()
    s = s[1:] if s.startswith("+") else s
    if not s or len(s) > max_digits or not (s.isascii() and s.isdigit()):
        return None
    return int(s)
