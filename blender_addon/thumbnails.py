"""The lens list's thumbnails: each lens's PSF grid (``logic.psf_thumbnail``:
fields 0 / 0.5 / 0.9 down, 1 m / 3 m / infinity across) as a Blender
preview: its image the grid (the panel draws it large), its icon one ball
of it (``logic.thumbnail_ball``: the list's 16-px icons show a ball's
shape, not nine dots). Made on a worker thread the first time the list is drawn
(about 0.1-0.3 s a lens), handed to the main thread by a timer; until then
a lens shows the plain camera icon. Kept per lens file and modification
time for the session (``SESSION.thumbnails``)."""
from __future__ import annotations

import os
import threading

import bpy
import numpy as np

from . import logic
from .session import SESSION


def _key(entry) -> str:
    return f"{entry.id}:{os.stat(entry.path).st_mtime_ns}" if os.path.exists(entry.path) else entry.id


def icon(entry) -> int:
    """The icon id of ``entry``'s thumbnail, 0 while it is being made (or
    when it cannot be: a broken lens file)."""
    state = SESSION.thumbnails
    if state.pcoll is None:
        return 0
    key = _key(entry)
    if key in state.pcoll:
        return state.pcoll[key].icon_id
    if key not in state.requested:            # made once: reading the lens enum calls this every time
        state.requested.add(key)
        _make_later(state, entry, key)
    return 0


def _make_later(state, entry, key: str) -> None:
    with state.lock:
        state.queue[key] = entry
        th = state.thread
        if th is None or not th.is_alive():
            th = state.thread = threading.Thread(target=_work, args=(state,), name="dcdi-thumbnails", daemon=True)
            th.start()
    if not bpy.app.background and not bpy.app.timers.is_registered(_collect):
        bpy.app.timers.register(_collect, first_interval=0.2)


def _work(state) -> None:
    """The worker: ``state``'s queue made into PSF grids (the session's
    thumbnails when it started: a cleared session's are dropped with it)."""
    while True:
        with state.lock:
            if not state.queue:
                return
            key, entry = state.queue.popitem()
        try:
            img = logic.psf_thumbnail(logic.load_lens_cached(entry.path))
        except Exception:                 # a broken lens file: its error shows when it is chosen
            state.failed.add(key)
            continue
        state.ready[key] = img


def _collect():
    """Timer on the main thread: ready thumbnails into the preview collection."""
    made = collect()
    if made:
        for window in bpy.context.window_manager.windows:
            for area in window.screen.areas:
                area.tag_redraw()
    state = SESSION.thumbnails
    th = state.thread
    return 0.2 if (th is not None and th.is_alive()) or state.ready else None


def collect() -> int:
    """Move the finished thumbnails into Blender's previews; returns how many."""
    state = SESSION.thumbnails
    pcoll = state.pcoll
    n = 0
    for key in list(state.ready):
        img = state.ready.pop(key)
        if pcoll is None or key in pcoll:
            continue
        p = pcoll.new(key)
        # the list's small icon: one ball (readable at 16 px); the panel's large picture: the whole grid
        p.image_size, p.image_pixels_float = _size_pixels(img)
        p.icon_size, p.icon_pixels_float = _size_pixels(logic.thumbnail_ball(img))
        n += 1
    return n


def _size_pixels(img: np.ndarray) -> tuple:
    """(w, h) and the RGBA floats, rows bottom to top, of an (H, W, 3) picture."""
    h, w = img.shape[:2]
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = img
    return (w, h), rgba[::-1].ravel()


def register() -> None:
    """Blender's preview collection for the icons; the session takes it back
    (``SESSION.clear()``), with the collecting timer."""
    import bpy.utils.previews
    pcoll = SESSION.thumbnails.pcoll = bpy.utils.previews.new()
    SESSION.hold("thumbnails", lambda: _remove(pcoll))


def _remove(pcoll) -> None:
    import bpy.utils.previews
    bpy.utils.previews.remove(pcoll)
    if not bpy.app.background and bpy.app.timers.is_registered(_collect):
        bpy.app.timers.unregister(_collect)
