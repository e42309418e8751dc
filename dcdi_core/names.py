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
