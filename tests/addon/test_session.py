"""The add-on's session (``blender_addon.session``, no bpy): one call ends and
drops everything it holds, and the lens catalogue is listed once while its
folders do not change."""
import os
import time
from types import SimpleNamespace

import pytest

from blender_addon import logic
from blender_addon.session import SESSION, LensFolders, Session

class Worker:
    cancel = False


ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_clear_stops_removes_and_drops_everything():
    s = Session()
    done = []
    worker = Worker()
    s.jobs.add(worker)
    s.preview = SimpleNamespace(stop=lambda: done.append("preview stopped"))
    s.render_run = SimpleNamespace(restore=lambda: done.append("render restored"))
    s.hold("render", lambda: done.append("render handlers"))
    s.hold("preview", lambda: done.append("preview handlers"))
    s.hold("preview", lambda: done.append("draw handlers"))
    s.thumbnails.queue["6p:1"] = object()
    for cache in (s.lens_names, s.lenses, s.readouts, s.networks):
        cache["key"] = "value"
    s.simulation = {"image": 1}
    s.lens_items = [("6p", "6P", "", 0, 1)]
    s.last_render = {"frames": []}
    s.clear()
    assert worker.cancel
    assert done == ["preview stopped", "render restored", "draw handlers", "preview handlers", "render handlers"]
    assert not s.holds("preview") and not s.holds("render") and not s.thumbnails.queue
    assert (s.lens_names, s.lenses, s.readouts, s.networks, s.simulation, s.last_render) == ({},) * 6
    assert s.jobs == set() and s.lens_items == [] and s.preview is None and s.render_run is None


def test_clear_runs_every_removal_when_one_fails():
    s = Session()
    done = []

    def broken():
        raise RuntimeError("gone already")
    s.render_run = SimpleNamespace(restore=broken)
    s.hold("a", lambda: done.append("a"))
    s.hold("b", broken)
    s.hold("b", lambda: done.append("b"))
    s.lenses["key"] = "value"
    with pytest.raises(RuntimeError, match="gone already"):
        s.clear()
    assert done == ["b", "a"] and s.lenses == {} and not s.holds("a") and not s.holds("b")


def test_the_lens_folders_are_listed_again_only_when_one_changes(tmp_path, monkeypatch):
    monkeypatch.setattr(SESSION, "lens_folders", LensFolders())
    listings = []
    real = logic._list_lens_files
    monkeypatch.setattr(logic, "_list_lens_files", lambda dirs: listings.append(1) or real(dirs))
    extra = tmp_path / "imported"
    extra.mkdir()
    old = time.time() - 60
    os.utime(extra, (old, old))                                  # changed long before it is listed
    assert logic.lens_file("mine", [extra]) is None
    n = len(listings)
    assert logic.lens_file("6p", [extra]) == os.path.join(ROOT, "lenses", "6p.toml")
    assert [e.id for e in logic.lens_catalogue([extra])] == [e.id for e in logic.lens_catalogue([extra])]
    assert len(listings) == n                                    # nothing changed: not listed again
    (extra / "mine.toml").write_text('name = "Mine"\n')           # a new lens file
    assert logic.lens_file("mine", [extra]) == str(extra / "mine.toml")
    assert len(listings) == n + 1
    # a folder changed within the file system's clock tick of its listing is listed again, every time
    assert logic.lens_file("mine", [extra]) == str(extra / "mine.toml") and len(listings) == n + 2
    os.utime(extra, (old + 1, old + 1))
    assert logic.lens_file("mine", [extra]) == str(extra / "mine.toml") and len(listings) == n + 3
    assert logic.lens_file("mine", [extra]) == str(extra / "mine.toml") and len(listings) == n + 3
    # another folder list (a new $DCDI_LENS_PATH): listed again
    assert logic.lens_file("mine", []) is None and len(listings) == n + 4


def test_the_catalogue_is_the_folders_first_file_of_each_id(tmp_path, monkeypatch):
    monkeypatch.setattr(SESSION, "lens_folders", LensFolders())
    extra = tmp_path / "imported"
    extra.mkdir()
    (extra / "6p.toml").write_text('name = "a second 6p"\n')
    (extra / "zz.toml").write_text('name = "ZZ"\n')
    cat = logic.lens_catalogue([extra])
    ids = [e.id for e in cat]
    assert len(ids) == len(set(ids)) and ids[-1] == "zz" and cat[-1].name == "ZZ"
    assert dict((e.id, e.path) for e in cat)["6p"] == os.path.join(ROOT, "lenses", "6p.toml")
    assert all(logic.lens_file(e.id, [extra]) == e.path for e in cat)


def test_clear_drops_the_engines_own_caches_too():
    """The engine's process-wide caches (files kept, tables, the pool) are
    one object (``dcdi_core.caches``) that the session's clear() empties:
    after a bokeh fills them, every one holds nothing."""
    import numpy as np
    from dcdi_core import caches
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.spectral import default_response
    from dcdi_core.parallel import thread_pool
    lens = load_lens("zeiss-jena-tessar-50mm-f2-8")
    depth = np.full((24, 32), 3.0, np.float32)
    logic.run_bokeh(np.full((24, 32, 3), 0.5, np.float32), depth, lens, focus_m=1.5, keep=(1.5, 1.5),
                    preview=True)
    default_response()
    thread_pool()
    held = caches.sizes()
    assert held["ray maps"] >= 1 and held["default spectral response"] == 1 and held["worker pool"] == 1, held
    assert sum(held.values()) >= 4
    s = Session()
    s.clear()
    assert set(caches.sizes().values()) == {0}, caches.sizes()
    # filled again on use: nothing broken by the clear
    thread_pool().submit(lambda: 1).result()
