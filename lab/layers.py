"""The layers of docs/design.md's table, read from the page: which layer a
module is in. ``tests/test_import_graph.py`` checks the import graph
against it; `python -m lab walk` follows a job's calls through it."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOP = ("dcdi_core", "blender_addon", "lab")


def layers(design: Path = ROOT / "docs" / "design.md") -> dict[str, int]:
    """{dotted prefix: layer} from the table under '## Layers' in docs/design.md:
    rows '| N | `name`, `name` ... |', names relative to dcdi_core except
    blender_addon and lab."""
    text = design.read_text(encoding="utf-8")
    section = text.split("\n## Layers", 1)[1].split("\n## ", 1)[0]
    out = {}
    for row in re.finditer(r"^\|\s*(\d+)\s*\|(.*)\|\s*$", section, re.M):
        for name in re.findall(r"`([\w.]+)`", row.group(2)):
            full = name if name.split(".")[0] in TOP else "dcdi_core" if name == "dcdi_core" else f"dcdi_core.{name}"
            out[full] = int(row.group(1))
    return out


def within(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def layer_of(name: str, table: dict[str, int]) -> int | None:
    """The layer of a module: its longest prefix in the table ('dcdi_core' alone
    is the package's own __init__, not a prefix: a new package needs a row)."""
    best = max((p for p in table if name == p or (p != "dcdi_core" and within(name, (p,)))), key=len, default=None)
    return None if best is None else table[best]


