"""Run by tests/addon/test_viewport_preview.py in a fresh interpreter with the
pip bpy module: installs the built zip, turns the viewport preview on and
steps its refresh by hand (background Blender runs no timers), through a
focus change, a scene change and a change that cancels a running job;
writes OUT_DIR/result.json (pixels as .npy beside it).

    python tests/addon/addon_headless_preview.py ZIP OUT_DIR
"""
import importlib
import json
import sys
import time

from headless_start import start

ZIP, OUT = start()

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from addon_scene import settle as shared_settle, MODULE, build_scene, install  # noqa: E402

res: dict = {}
scene, cam, cube = build_scene()
res["install"], _ = install(ZIP)
logic = sys.modules[f"{MODULE}.logic"]
viewport = importlib.import_module(f"{MODULE}.viewport")
made_calls = []                                   # the lens list's thumbnails made (asked for at every enum read)
_thumbnail = logic.psf_thumbnail
logic.psf_thumbnail = lambda lens, *a, **k: made_calls.append(lens.id) or _thumbnail(lens, *a, **k)
P = viewport.preview()                            # the session's preview
s = scene.dcdi_lens_bokeh
s.lens = "6p"
s.focus_mode = "DISTANCE"
s.focus_distance = 1.0
s.preview_size = 160
s.samples = 4
st = bpy.context.window_manager.dcdi_lens_bokeh_status


def settle(limit_s=120.0):
    shared_settle(P, limit_s)


def snap(name):
    r = P.result
    np.save(OUT / f"{name}.npy", r["image"])
    return {"render_s": r["render_s"], "lens_s": r["lens_s"], "generation": r["generation"],
            "focus_m": r["info"]["focus_m"], "keep_m": r["info"]["keep_m"], "error": P.error,
            "refreshes": len(P.log)}


st.viewport_preview = True                       # the toggle
res["handler_on"] = viewport.on_depsgraph_update in bpy.app.handlers.depsgraph_update_post
settle()
res["first"] = snap("first")
np.save(OUT / "sharp_rgb.npy", P.sharp["rgb"])
np.save(OUT / "sharp_depth.npy", P.sharp["depth"])

# a focus change: the depsgraph update marks it; only the lens stage runs
s.focus_distance = 2.5
bpy.context.view_layer.update()
res["focus_pending"] = P.changed_at is not None and not P.scene_changed
settle()
res["focus"] = snap("focus")

# nothing changed: no refresh
bpy.context.view_layer.update()
settle()
res["idle_refreshes"] = len(P.log)

# back to the first focus on the same render: from memory, no lens stage
s.focus_distance = 1.0
bpy.context.view_layer.update()
settle()
res["recalled"] = dict(snap("recalled"), log=P.log[-1].get("recalled", False))
s.focus_distance = 2.5
bpy.context.view_layer.update()
settle()

# a scene change (the cube moves): a new sharp render
cube.location.x += 0.2
bpy.context.view_layer.update()
res["scene_pending"] = P.scene_changed
settle()
res["scene"] = snap("scene")

# a change while the lens stage runs: the running job is dropped
s.focus_distance = 4.0
bpy.context.view_layer.update()
P.changed_at -= viewport.DEBOUNCE_S
P.tick()                                          # starts the job
started = P.job["generation"]
s.focus_distance = 6.0
P.changed(scene_changed=False)                   # what the depsgraph handler does on a focus change
settle()
res["cancel"] = snap("cancel")
res["cancel"]["started_generation"] = started

# focus on a point (what a click sets) and on the active object
res["pick"] = sorted(bpy.ops.dcdi.focus_pick(location=(0.0, 0.0, -3.0)))
res["pick_focus"] = {"mode": s.focus_mode, "distance": s.focus_distance}
res["pick_behind"] = None
try:
    bpy.ops.dcdi.focus_pick(location=(0.0, 0.0, 3.0))         # behind the camera
except RuntimeError as e:
    res["pick_behind"] = str(e)
bpy.context.view_layer.objects.active = cube
res["active"] = sorted(bpy.ops.dcdi.focus_active_object())
res["active_focus"] = {"mode": s.focus_mode, "object": s.focus_object.name if s.focus_object else None}

# the lens list's thumbnails: made on a thread, collected on the main thread
thumbs = importlib.import_module(f"{MODULE}.thumbnails")
thumb_state = importlib.import_module(f"{MODULE}.session").SESSION.thumbnails
entries = logic.lens_catalogue()
first = [thumbs.icon(e) for e in entries]
thumb_state.thread.join(120)
for _ in range(5):                                # reading the lens enum asks for the icons each time
    _ = s.lens
    [thumbs.icon(e) for e in entries]
thumb_state.thread.join(120)
made = thumbs.collect()
pcoll = thumb_state.pcoll
res["thumbnails"] = {"lenses": len(entries), "first": first, "made": made, "made_calls": sorted(made_calls),
                     "sizes": [tuple(pcoll[thumbs._key(e)].image_size) for e in entries if thumbs._key(e) in pcoll]}
s.lens = "mos-s1"                                 # the enum still takes lenses by id
res["thumbnails"]["lens_after"] = s.lens

st.viewport_preview = False
res["handler_off"] = viewport.on_depsgraph_update in bpy.app.handlers.depsgraph_update_post
res["result_after_off"] = P.result is not None
(OUT / "result.json").write_text(json.dumps(res, indent=1, default=str))
