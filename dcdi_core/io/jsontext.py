"""JSON read from a file, bounded before it is parsed.

Python's ``json`` recurses once per level of nesting: a few kilobytes of
``[[[[...`` end in a RecursionError, not a refusal. Every JSON text this
project reads from a file (capture records, factory manifests and
settings, pair lists, splits, configs, model metadata) goes through
:func:`loads`: its nesting is measured in one linear pass first, and any
failure is a :class:`JsonTextError` (a ``ValueError``, so a caller's
``except ValueError`` still maps it to its own error) naming where the
text came from.
"""
from __future__ import annotations

import json
import re

from ..errors import DcdiError

#: deeper than any JSON this project writes (a manifest line nests 3, a config 4)
MAX_DEPTH = 64
# what matters to the nesting depth: escapes (skipped), quotes, brackets
_TOKEN = re.compile(r'\\.|["\[\]{}]', re.S)


class JsonTextError(DcdiError, ValueError):
    """JSON that cannot be read: not JSON, or nested too deep."""


def nesting(text: str, limit: int = MAX_DEPTH) -> int:
    """The deepest nesting of arrays and objects in ``text`` (outside its
    strings), counted up to ``limit + 1`` at most (then it stops)."""
    depth = deepest = 0
    in_string = False
    for m in _TOKEN.finditer(text):
        t = m.group()
        if t == '"':
            in_string = not in_string
        elif not in_string and t[0] != "\\":
            depth += 1 if t in "[{" else -1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    break
    return deepest


def loads(text, where, *, max_depth: int = MAX_DEPTH):
    """``json.loads(text)``, refused (:class:`JsonTextError` naming
    ``where``: a file, 'FILE line N') when nested deeper than ``max_depth``
    or not JSON."""
    if isinstance(text, (bytes, bytearray)):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as e:
            raise JsonTextError(f"{where}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if not isinstance(text, str):
        raise JsonTextError(f"{where}: not JSON text (a {type(text).__name__})")
    if nesting(text, max_depth) > max_depth:
        raise JsonTextError(f"{where}: JSON nested more than {max_depth} levels deep (what this project writes "
                            "nests a few)")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as e:
        message = " ".join(str(e).split())
        raise JsonTextError(f"{where}: not JSON ({message[:120]})") from None
