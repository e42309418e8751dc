"""Write a lens prescription dict (the ``lenses/SCHEMA.md`` layout) as TOML.

Python's ``tomllib`` only reads TOML, so this is a small writer for the subset
the prescriptions use: top-level scalars first, then plain tables (``[sensor]``,
``[stated]``), then arrays of tables (``[[surface]]``). Values are strings,
booleans, integers, floats (written with ``repr`` so they read back bit for
bit; infinities as ``inf`` / ``-inf``), lists and inline tables (model glass
``{ nd = 1.95, vd = 81.6 }``). ``tomllib.loads(dumps_prescription(d)) == d``
holds for every dict made of those types.
"""
from __future__ import annotations

import math
import re

__all__ = ["dumps_prescription"]

# Order of the top-level scalars and tables; other keys follow in dict order.
_SCALAR_ORDER = ("schema_version", "id", "name", "source", "notes", "wavelength_nm")
_TABLE_ORDER = ("sensor", "stated")

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")
_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n",
            "\f": "\\f", "\r": "\\r"}


def dumps_prescription(d: dict) -> str:
    """TOML text for a prescription dict (see the module docstring)."""
    if not isinstance(d, dict):
        raise TypeError(f"a prescription must be a dict, not {type(d).__name__}")
    scalars, tables, arrays = [], [], []
    for key in _ordered(d, _SCALAR_ORDER + _TABLE_ORDER):
        value = d[key]
        if isinstance(value, dict):
            tables.append(key)
        elif _is_array_of_tables(value):
            arrays.append(key)
        else:
            scalars.append(key)

    lines = [f"{_key(k)} = {_value(d[k], k)}" for k in scalars]
    for key in tables:
        lines += ["", f"[{_key(key)}]"]
        lines += [f"{_key(k)} = {_value(v, f'{key}.{k}')}" for k, v in d[key].items()]
    for key in arrays:
        for i, table in enumerate(d[key]):
            lines += ["", f"[[{_key(key)}]]"]
            lines += [f"{_key(k)} = {_value(v, f'{key}[{i}].{k}')}" for k, v in table.items()]
    return "\n".join(lines).lstrip("\n") + "\n"


def _ordered(d: dict, first: tuple) -> list:
    return [k for k in first if k in d] + [k for k in d if k not in first]


def _is_array_of_tables(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _key(key) -> str:
    if not isinstance(key, str):
        raise TypeError(f"TOML keys must be strings, not {key!r}")
    return key if _BARE_KEY.match(key) else _string(key)


def _string(s: str) -> str:
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _float(x: float) -> str:
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(float(x))  # shortest text that reads back to the same double


def _value(v, where: str) -> str:
    """Inline TOML text for one value; ``where`` names it in errors."""
    if isinstance(v, bool):  # before int: bool is an int subclass
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return _float(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x, f"{where}[{i}]") for i, x in enumerate(v)) + "]"
    if isinstance(v, dict):
        if not v:
            return "{}"
        return "{ " + ", ".join(f"{_key(k)} = {_value(x, f'{where}.{k}')}" for k, x in v.items()) + " }"
    raise TypeError(f"{where}: cannot write {type(v).__name__} {v!r} as TOML")
