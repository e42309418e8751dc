"""`python -m lab walk`: `dcdi dof` from the command line and Apply Lens
Bokeh each hand their job to ``app`` in one call, and nothing below climbs
back up but what the front end handed down to hear back (the job's
``Control``: progress and notes) and a file cache's loader."""
from __future__ import annotations

import numpy as np

from lab import walk

# who may call up: the job's Control (its progress, notes and cancel are the front end's functions) and the
# engine's file caches (a loader of a higher layer, handed to io.npzfile.FileCache)
CALLBACK_HOLDERS = ("dcdi_core.control", "dcdi_core.io.npzfile")


def test_dof_and_apply_lens_bokeh_cross_into_app_once(tmp_path, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    for name, job in walk.JOBS.items():
        folder = tmp_path / name
        folder.mkdir()
        w = job(folder)
        assert w.count("job") == 1, (name, w.into_app)
        assert w.crossings > 100 and w.climbs, name         # the walk saw the job (its progress climbs)
        callers = {k.split(" -> ")[0].rsplit(".", 1)[0] for k in w.climbs}
        assert callers <= set(CALLBACK_HOLDERS), (name, dict(w.climbs))
    assert "walk | calls between layers" in walk.table([w])


def test_the_walk_counts_a_front_end_that_asks_twice(tmp_path, monkeypatch):
    from blender_addon import logic
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    lens = logic.load_lens_cached(logic.lens_file("6p"))
    img = np.full((24, 32, 3), 0.5, np.float32)
    depth = np.full((24, 32), 2.0, np.float32)

    def twice():
        for _ in range(2):
            logic.run_bokeh(img, depth, lens, focus_m=2.0, keep=(1.8, 2.2))
    assert walk.follow("twice", twice).count("job") == 2
