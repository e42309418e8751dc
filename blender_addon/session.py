"""The add-on's session: everything it holds between calls, in one object.

One Blender session runs the add-on once; what it keeps from one call to
the next (the caches of lens files, readouts, PSF sources and the loaded
network; the running jobs and the last simulation; the viewport preview;
the render in progress and what the last one did; the lens list's
thumbnails and enum items; the handles of what it added to Blender) lives
in ``SESSION``, and nowhere else: ``SESSION.clear()`` (``unregister``)
stops the jobs, the preview and the render, removes every handle and
drops every cache, in one call.

No bpy here (``logic`` keeps its caches here and runs without Blender):
what must be removed from Blender is held as a function that removes it
(``hold``), added by the module that added it.
"""
from __future__ import annotations

import os
import threading
import time

from dcdi_core import app

# how many PSF sources are kept (lens file, pixel pitch, PSF request): the
# frames of an animation with one focus, a preview refreshed after a change
# elsewhere, pay their PSFs once
KEPT_PSF_SOURCES = 6
# a lens folder listed within this long of its modification time is listed
# again next time: a file added in the same tick of the file system's clock
# would not change the folder's time
FOLDER_CLOCK_NS = 3_000_000_000


class Thumbnails:
    """The lens list's thumbnails (``thumbnails.py``): Blender's preview
    collection, the PSF grids made by the worker and waiting for the main
    thread, the keys asked for and those that failed."""

    def __init__(self):
        self.pcoll = None
        self.ready: dict = {}
        self.failed: set = set()
        self.requested: set = set()
        self.queue: dict = {}
        self.thread: threading.Thread | None = None
        self.lock = threading.Lock()

    def stop(self) -> None:
        """The worker makes nothing more (it ends when it next looks at the queue)."""
        with self.lock:
            self.queue.clear()


class LensFolders:
    """The lens files of a list of folders, listed once while none of the
    folders changes (the first file of an id wins)."""

    def __init__(self):
        self.key: tuple | None = None
        self.listed_ns = 0
        self.files: tuple = ()       # (id, path) in catalogue order

    def get(self, folders, lister) -> tuple:
        """(id, path) of the lens files in ``folders`` (``lister(folders)``
        when a folder changed since the last listing, or was listed too soon
        after its change to tell)."""
        key = tuple((str(d), _mtime_ns(d)) for d in folders)
        if key != self.key or any(t is None or self.listed_ns - t < FOLDER_CLOCK_NS for _, t in key):
            listed_ns = time.time_ns()
            self.files, self.key, self.listed_ns = tuple(lister(folders)), key, listed_ns
        return self.files


def _mtime_ns(folder) -> int | None:
    try:
        return os.stat(folder).st_mtime_ns
    except OSError:
        return None


class Session:
    """What the add-on holds in one Blender session (module docstring)."""

    def __init__(self):
        self._handles: dict[str, list] = {}
        self._fresh()

    def _fresh(self) -> None:
        # logic's caches: lens names, Lens objects and readouts by (file, modification time); the lens
        # folders' listing; the PSF sources of the last requests; the last loaded network
        self.lens_names: dict = {}
        self.lenses: dict = {}
        self.readouts: dict = {}
        self.lens_folders = LensFolders()
        self.sources = app.SourceCache(KEPT_PSF_SOURCES)
        self.networks: dict = {}
        # operators: the worker threads still running (unregister tells them to stop) and the last
        # simulation, which Correct works on (empty: none yet)
        self.jobs: set = set()
        self.simulation: dict = {}
        # props: the lens enum's items, held so that Python does not free the strings Blender shows
        # (the documented pitfall of dynamic EnumProperty items)
        self.lens_items: list = []
        # render_hook: the render through the lens in progress (one at a time, as Blender renders), and
        # what the last one did (for the panel and for scripts)
        self.render_run = None
        self.last_render: dict = {}
        # viewport: the preview's state (made by viewport.preview())
        self.preview = None
        self.thumbnails = Thumbnails()
        # view_transform: the display tables of the last view settings (settings key -> table, newest last)
        self.view_tables: dict = {}

    # -------------------------------------------------------------- what was added to Blender
    def hold(self, owner: str, remove) -> None:
        """Keep ``remove()``, which takes back something ``owner`` added to
        Blender (a handler, a draw handler, a timer, a preview collection)."""
        self._handles.setdefault(owner, []).append(remove)

    def holds(self, owner: str) -> bool:
        return bool(self._handles.get(owner))

    def release(self, owner: str) -> None:
        """Take back what ``owner`` added, newest first (all of it, whatever
        one raises; then the first error is raised)."""
        _run_all(reversed(self._handles.pop(owner, [])))

    # -------------------------------------------------------------- the end
    def clear(self) -> None:
        """Stop and drop everything: the running jobs are told to stop, the
        preview and the render in progress end (its settings restored), what
        was added to Blender is removed, every cache is dropped."""
        for worker in list(self.jobs):
            worker.cancel = True
        if self.preview is not None:
            self.preview.stop()
        self.thumbnails.stop()
        run, self.render_run = self.render_run, None
        steps = [run.restore] if run is not None else []
        steps += [lambda owner=owner: self.release(owner) for owner in list(self._handles)[::-1]]
        try:
            _run_all(steps)
        finally:
            self.sources.clear()
            app.clear_caches()              # the engine's own (files kept, tables, the worker pool)
            self._fresh()


def _run_all(steps) -> None:
    """Call each of ``steps``, whatever one raises; then raise the first error."""
    errors = []
    for step in steps:
        try:
            step()
        except Exception as e:          # noqa: BLE001 - raised below, once the rest has run
            errors.append(e)
    if errors:
        raise errors[0]


SESSION = Session()
