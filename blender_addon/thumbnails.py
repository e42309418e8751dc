"""The lens list's thumbnails: each lens's PSF grid (``logic.psf_thumbnail``:
fields 0 / 0.5 / 0.9 down, 1 m / 3 m / infinity across) as a Blender
preview icon. Made on a worker thread the first time the list is drawn
(about 0.1-0.3 s a lens), handed to the main thread by a timer; until then
a lens shows the plain camera icon. Kept per lens file and modification
time for the session."""
from __future__ import annotations

import os
import threading

import bpy
import numpy as np

from . import logic

_STATE: dict = {"pcoll": None, "ready": {}, "failed": set(), "requested": set(), "thread": None}
_LOCK = threading.Lock()


def _key(entry) -> str:
    return f"{entry.id}:{os.stat(entry.path).st_mtime_ns}" if os.path.exists(entry.path) else entry.id


def icon(entry) -> int:
    """The icon id of ``entry``'s thumbnail, 0 while it is being made (or
    when it cannot be: a broken lens file)."""
    pcoll = _STATE["pcoll"]
    if pcoll is None:
        return 0
    key = _key(entry)
    if key in pcoll:
        return pcoll[key].icon_id
    if key not in _STATE["requested"]:        # made once: reading the lens enum calls this every time
        _STATE["requested"].add(key)
        _make_later(entry, key)
    return 0


def _make_later(entry, key: str) -> None:
    with _LOCK:
        queue = _STATE.setdefault("queue", {})
        queue[key] = entry
        th = _STATE["thread"]
        if th is None or not th.is_alive():
            th = _STATE["thread"] = threading.Thread(target=_work, name="dcdi-thumbnails", daemon=True)
            th.start()
    if not bpy.app.background and not bpy.app.timers.is_registered(_collect):
        bpy.app.timers.register(_collect, first_interval=0.2)


def _work() -> None:
    while True:
        with _LOCK:
            queue = _STATE.get("queue", {})
            if not queue:
                return
            key, entry = queue.popitem()
        try:
            img = logic.psf_thumbnail(logic.load_lens_cached(entry.path))
        except Exception:                 # a broken lens file: its error shows when it is chosen
            _STATE["failed"].add(key)
            continue
        _STATE["ready"][key] = img


def _collect():
    """Timer on the main thread: ready thumbnails into the preview collection."""
    made = collect()
    if made:
        for window in bpy.context.window_manager.windows:
            for area in window.screen.areas:
                area.tag_redraw()
    th = _STATE["thread"]
    return 0.2 if (th is not None and th.is_alive()) or _STATE["ready"] else None


def collect() -> int:
    """Move the finished thumbnails into Blender's previews; returns how many."""
    pcoll = _STATE["pcoll"]
    n = 0
    for key in list(_STATE["ready"]):
        img = _STATE["ready"].pop(key)
        if pcoll is None or key in pcoll:
            continue
        h, w = img.shape[:2]
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = img
        p = pcoll.new(key)
        p.image_size = (w, h)
        p.image_pixels_float = rgba[::-1].ravel()
        p.icon_size = (w, h)
        p.icon_pixels_float = rgba[::-1].ravel()
        n += 1
    return n


def register() -> None:
    import bpy.utils.previews
    _STATE["pcoll"] = bpy.utils.previews.new()


def unregister() -> None:
    if _STATE["pcoll"] is not None:
        import bpy.utils.previews
        bpy.utils.previews.remove(_STATE["pcoll"])
    _STATE.update(pcoll=None, ready={}, failed=set(), requested=set(), queue={})
    if not bpy.app.background and bpy.app.timers.is_registered(_collect):
        bpy.app.timers.unregister(_collect)
