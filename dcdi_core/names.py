"""Names read from files are names, never paths.

A sample id in a factory manifest, a DA2T pair id, a lens id in a lens file,
a basis or a model file, a shipped model's key: each becomes part of a file
name (``aif/<id>.exr``, ``pairs/<id>.npy``, ``weights/dfd-refine-<lens>.npz``).
Read from a file, such a value is checked here before it is joined to a
folder, so that an id like ``../../x/escape`` is refused instead of reading
or writing outside that folder.

A name is 1 to :data:`MAX_NAME_CHARS` ASCII letters, digits and ``- _ . ~``,
its first character a letter, a digit or ``_`` (so never ``.``, ``..``, a
hidden file, an option-like ``-x`` or a home-like ``~x``); no ``/``, ``\\``,
``:``, NUL, space or other character. Every id the project writes is one:
lens ids (``mos-s1``), factory samples (``room-000009``), DA2T pairs
(``room-000009~0``), shipped model keys (``radial``).
"""
from __future__ import annotations

import re

from .errors import DatasetError, InputRangeError

MAX_NAME_CHARS = 128
# the rule in words, as the errors give it
NAME_RULE = (f"1-{MAX_NAME_CHARS} ASCII letters, digits, '-', '_', '.', '~', the first a letter, digit or '_' "
             "(a name, not a path)")
_NAME = re.compile(rf"[A-Za-z0-9_][A-Za-z0-9._~-]{{0,{MAX_NAME_CHARS - 1}}}")


def name_problem(value) -> str | None:
    """Why ``value`` is not a name (one phrase), or None if it is one."""
    if not isinstance(value, str):
        return f"a {type(value).__name__}, not a string"
    if not value:
        return "empty"
    if len(value) > MAX_NAME_CHARS:
        return f"{len(value)} characters long"
    if _NAME.fullmatch(value) is None:
        return "not a name (it holds a path separator, starts with '.', '-' or '~', or has another character)"
    return None


def is_name(value) -> bool:
    """Whether ``value`` is a name (:data:`NAME_RULE`)."""
    return name_problem(value) is None


# what a terminal acts on instead of showing: C0 controls, DEL, C1 controls, line and paragraph separators,
# bidirectional marks and overrides (a file's text could otherwise move the cursor, set the window's title, clear
# the screen, or start a line that looks like the program's own)
_CONTROLS = [*range(0x00, 0x20), 0x7F, *range(0x80, 0xA0), 0x061C, 0x200E, 0x200F, 0x2028, 0x2029,
             *range(0x202A, 0x202F), *range(0x2066, 0x206A)]
_ESCAPED = {c: (f"\\x{c:02x}" if c < 0x100 else f"\\u{c:04x}") for c in _CONTROLS}
_ESCAPED.update({0x09: "\\t", 0x0A: "\\n", 0x0D: "\\r"})
# a terminal stream keeps the program's own line breaks, tabs and carriage returns (a progress line redrawn in
# place), and escapes every other control; a file's text reaches it through ``printable``, which escapes those too
_STREAM_ESCAPED = {c: v for c, v in _ESCAPED.items() if c not in (0x09, 0x0A, 0x0D)}


def printable(text, limit: int | None = None) -> str:
    """``text`` read from a file (a lens's name, a capture record's field)
    as a message quotes it: on one line, every control character written as
    its escape (``\\n``, ``\\x1b``, ``\\u202e``), cut to ``limit``
    characters (None: whole). The one function every message that quotes a
    file's content uses."""
    out = str(text).translate(_ESCAPED)
    return out if limit is None or len(out) <= limit else out[:max(limit - 3, 0)] + "..."


def terminal_safe(text: str) -> str:
    """What :class:`TerminalStream` writes for ``text``: the program's line
    breaks, tabs and carriage returns kept, every other control character
    escaped."""
    return text.translate(_STREAM_ESCAPED)


class TerminalStream:
    """A text stream (the command line's stdout and stderr) that writes
    every control character but the line break, the tab and the carriage
    return as its escape: whatever a message quotes, no escape sequence
    reaches the terminal."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        self._stream.write(terminal_safe(text))
        return len(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def shown(value, limit: int = 80) -> str:
    """``value`` as an error message shows it: repr, at most ``limit`` characters (one line)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def check_name(value, what: str, file=None, error=DatasetError) -> str:
    """``value`` if it is a name, else ``error`` naming ``file`` (where the
    value was read; None: not from a file) and ``what`` (the field: 'id',
    'lenses[1]'). ``error``: :class:`DatasetError` (a dataset folder's
    records) or :class:`InputRangeError` (an argument), or any subclass."""
    why = name_problem(value)
    if why is None:
        return value
    where = f"{file}, field '{what}'" if file is not None else what
    if issubclass(error, InputRangeError):
        short = value[:77] + "..." if isinstance(value, str) and len(value) > 80 else value
        raise error(where, short, NAME_RULE)
    raise error(f"{where}: {shown(value)} is {why}; allowed: {NAME_RULE}")
