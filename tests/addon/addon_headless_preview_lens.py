"""Run by tests/addon/test_viewport_preview.py in a fresh interpreter with the
pip bpy module: the viewport preview on (its refresh stepped by hand), then
the lens changed twice: each change starts its refresh at once (no
debounce), reruns the lens stage on the same sharp render, its planar Z
converted to depth with the new lens's entrance pupil, and renders nothing. Writes OUT_DIR/result.json (pixels as .npy beside it).

    python tests/addon/addon_headless_preview_lens.py ZIP OUT_DIR
"""
import importlib
import json
import time

from headless_start import start

ZIP, OUT = start()

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from addon_scene import settle as shared_settle, MODULE, build_scene, install  # noqa: E402

res: dict = {}
scene, cam, cube = build_scene()
res["install"], _ = install(ZIP)
viewport = importlib.import_module(f"{MODULE}.viewport")
P = viewport.preview()
s = scene.dcdi_lens_bokeh
s.lens = "6p"
s.focus_mode = "DISTANCE"
s.focus_distance = 1.0
s.refocus = False               # each lens as prescribed: its shipped PSFs, no tracing
s.preview_size = 160
s.samples = 4
st = bpy.context.window_manager.dcdi_lens_bokeh_status
calls = []                      # the main thread's sharp renders
_render = viewport.bpy_render.render_aif_depth
viewport.bpy_render.render_aif_depth = lambda *a, **k: calls.append(a[2:4]) or _render(*a, **k)


def settle(limit_s=300.0):
    shared_settle(P, limit_s)


def snap(name):
    r = P.result
    np.save(OUT / f"{name}.npy", r["image"])
    np.save(OUT / f"{name}_depth.npy", P.sharp["depth"])
    return {"renders": P.renders, "render_calls": len(calls), "refreshes": len(P.log), "render_s": r["render_s"],
            "lens": P.served[1][0], "version": P.sharp["version"], "error": P.error,
            "focus_m": r["info"]["focus_m"], "keep_m": r["info"]["keep_m"], "refocus": r["info"]["refocus"]}


st.viewport_preview = True
settle()
res["first"] = snap("first")
np.save(OUT / "sharp_rgb.npy", P.sharp["rgb"])
np.save(OUT / "sharp_z.npy", P.sharp["z"])

for name, lens in (("mos", "mos-s1"), ("back", "6p")):
    s.lens = lens                              # the panel's update: the lens settings changed
    res[f"{name}_pending"] = P.changed_at is not None and not P.scene_changed
    res[f"{name}_at_once"] = P.changed_at is not None and time.perf_counter() - P.changed_at >= viewport.DEBOUNCE_S
    P.changed_at -= viewport.DEBOUNCE_S
    settle()
    res[name] = snap(name)

# Apply Lens Bokeh with the preview on and up to date: the preview's render serves it (no render)
before = len(calls)
bpy.ops.dcdi.apply_lens_bokeh()
res["apply_kept"] = {"render_calls": len(calls) - before, "message": st.message}
np.save(OUT / "apply.npy", np.array(bpy.data.images["Lens Bokeh"].pixels[:], np.float32))
# ... and after an object moved, its own render again
cube.location.x += 0.1
bpy.context.view_layer.update()
viewport.on_depsgraph_update(bpy.context.scene, bpy.context.evaluated_depsgraph_get())
P.scene_changed = True          # what the depsgraph handler marks (background mode: no handler call order)
before = len(calls)
bpy.ops.dcdi.apply_lens_bokeh()
res["apply_moved"] = {"render_calls": len(calls) - before}
st.viewport_preview = False
(OUT / "result.json").write_text(json.dumps(res, indent=1, default=str))
