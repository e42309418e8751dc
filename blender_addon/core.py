"""Where the add-on finds ``dcdi_core``: the copy vendored inside the
extension zip (``<this package>.dcdi_core``, with ``lenses/`` beside it), or
the repository's package when run from a checkout. No bpy here.

Blender installs an extension as ``bl_ext.<repo>.<id>``, so the vendored
engine is a sub-package of the add-on, never a top-level ``dcdi_core``
(which could clash with another copy on ``sys.path``); ``dcdi_core`` itself
uses only relative imports, so it works under either name.
"""
from __future__ import annotations

import importlib
import importlib.util

_PKG = __package__ or "blender_addon"


def _root() -> str:
    try:
        if importlib.util.find_spec(f"{_PKG}.dcdi_core") is not None:
            return f"{_PKG}.dcdi_core"
    except (ImportError, ValueError):
        pass
    return "dcdi_core"


ROOT = _root()


def core(module: str = ""):
    """``dcdi_core.<module>`` from the vendored copy if there is one."""
    return importlib.import_module(f"{ROOT}.{module}" if module else ROOT)
