"""Run by tests/addon/test_render_hook.py in a fresh interpreter with the pip
bpy module: installs the built extension zip, turns on Lens in Renders and
renders a still and two short animations (Cycles, 160 x 120), writing what
it saw to OUT_DIR/result.json (the still's passes as .npy beside it).

    python tests/addon/addon_headless_render.py ZIP OUT_DIR
"""
import importlib
import json
import os
import sys

from headless_start import start

ZIP, OUT = start()

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from addon_scene import MODULE, StubLayout, build_scene, data_counts, diff, install, snapshot  # noqa: E402

res: dict = {}
scene, cam, cube = build_scene()
res["install"], _ = install(ZIP)
logic = sys.modules[f"{MODULE}.logic"]
hook = sys.modules[f"{MODULE}.render_hook"]
reading = sys.modules[f"{MODULE}.reading"]
SESSION = sys.modules[f"{MODULE}.session"].SESSION


def LAST():
    """What the last render through the lens did (the session's)."""
    return SESSION.last_render


runtime = importlib.import_module("dcdi_core.psf.sources")
res["handlers_registered"] = sorted(n for n, fn in hook.HANDLERS if fn in getattr(bpy.app.handlers, n))

# count the PSF sources built (one per lens, pitch and focus)
builds = []
_psf_source = runtime.psf_source


def counting(*a, **k):
    builds.append(k.get("focus_m"))
    return _psf_source(*a, **k)


runtime.psf_source = counting

r = scene.render
r.engine = os.environ.get("DCDI_TEST_RENDER_ENGINE", "CYCLES")     # the real-Blender suite runs EEVEE too
scene.cycles.samples = 4
scene.cycles.use_denoising = False
r.resolution_x, r.resolution_y, r.resolution_percentage = 160, 120, 100
cam.data.dof.use_dof = True                       # the user's own DoF: off during the render, then back
cam.data.dof.aperture_fstop = 2.0
s = scene.dcdi_lens_bokeh
s.lens = "6p"
s.focus_mode = "OBJECT"
s.focus_object = cube
s.keep_front, s.keep_behind = 0.05, 0.05
r.image_settings.file_format = "OPEN_EXR"
r.image_settings.color_depth = "32"

s.lens_in_renders = True
r.filepath = str(OUT / "still.exr")
watched = {"scene": scene, "render": r, "camera_data": cam.data}
before = {k: snapshot(v) for k, v in watched.items()}
before["view_layers"] = [snapshot(v) for v in scene.view_layers]
counts0 = data_counts()

# 1. a still, written (as `blender -b -f`)
bpy.ops.render.render(write_still=True)
res["still"] = {"frames": LAST().get("frames"), "error": LAST().get("error"),
                "builds": list(builds), "image": hook.RESULT_IMAGE in bpy.data.images}
rgb, z = LAST()["last_passes"]
np.save(OUT / "still_rgb.npy", rgb)
np.save(OUT / "still_z.npy", z)
res["entrance_pupil_mm"] = logic.lens_readout(reading.chosen_lens(s)[1])["entrance_pupil_mm"]

after = {k: snapshot(v) for k, v in watched.items()}
after["view_layers"] = [snapshot(v) for v in scene.view_layers]
res["settings_diff"] = diff(before, after)
counts1 = data_counts()
res["new_data"] = {k: counts1[k] - counts0.get(k, 0) for k in counts1 if counts1[k] != counts0.get(k, 0)}
res["images"] = sorted(i.name for i in bpy.data.images)

# 1b. the scene's own compositor, kept: Invert on the lens's frame, and a File Output of the Depth pass
tree = bpy.data.node_groups.new("user compositor", "CompositorNodeTree")
scene.view_layers[0].use_pass_z = True             # the user's tree reads the Depth pass
rl = tree.nodes.new("CompositorNodeRLayers")
rl.scene = scene
inv = tree.nodes.new("CompositorNodeInvert")
tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
gout = tree.nodes.new("NodeGroupOutput")
tree.links.new(rl.outputs["Image"], inv.inputs["Color"])
tree.links.new(inv.outputs[0], gout.inputs[0])
fo = tree.nodes.new("CompositorNodeOutputFile")
fo.directory = str(OUT / "user-files") + os.sep
fo.file_name = "depth"
fo.file_output_items.clear()
fo.file_output_items.new("FLOAT", "Depth")
tree.links.new(rl.outputs["Depth"], fo.inputs["Depth"])
scene.compositing_node_group = tree
r.filepath = str(OUT / "still_comp.exr")
bpy.ops.render.render(write_still=True)
res["comp"] = {"frames": LAST().get("frames"), "error": LAST().get("error"),
               "tree_kept": scene.compositing_node_group == tree, "groups": sorted(g.name for g in bpy.data.node_groups),
               "images": sorted(i.name for i in bpy.data.images),
               "user_files": sorted(p.name for p in (OUT / "user-files").glob("*"))}
# a node group reading Render Layers cannot be fed: said, and the lens's frame written without it
inner = bpy.data.node_groups.new("inner", "CompositorNodeTree")
inner.nodes.new("CompositorNodeRLayers")
grp = tree.nodes.new("CompositorNodeGroup")
grp.node_tree = inner
r.filepath = str(OUT / "still_nested.exr")
bpy.ops.render.render(write_still=True)
res["nested"] = {"frames": LAST().get("frames"), "error": LAST().get("error")}
scene.compositing_node_group = None
for g in (tree, inner):
    bpy.data.node_groups.remove(g)

# 2. an animation whose focus object moves: each frame its own focus
builds.clear()
scene.frame_start, scene.frame_end = 1, 3
for f, zpos in ((1, -1.0), (3, -2.0)):
    scene.frame_set(f)
    cube.location.z = zpos
    cube.keyframe_insert("location", index=2)
want = {}
for f in (1, 2, 3):
    scene.frame_set(f)
    want[f] = reading.focus_metres(scene, cam, s, res["entrance_pupil_mm"])
scene.frame_set(1)
r.filepath = str(OUT / "moving" / "f_")
bpy.ops.render.render(animation=True)
res["moving"] = {"frames": LAST().get("frames"), "error": LAST().get("error"), "want_focus": want,
                 "builds": list(builds), "files": sorted(p.name for p in (OUT / "moving").glob("*.exr"))}

# 3. a fixed focus: the PSFs once for every frame
builds.clear()
s.focus_mode = "DISTANCE"
s.focus_distance = 1.0
r.filepath = str(OUT / "fixed" / "f_")
bpy.ops.render.render(animation=True)
res["fixed"] = {"frames": LAST().get("frames"), "error": LAST().get("error"), "builds": list(builds)}

# 4. a movie output is refused before any work, the render left as it is
try:
    r.image_settings.media_type = "VIDEO"          # Blender 5 groups formats by media type
    r.image_settings.file_format = "FFMPEG"
    res["movie_blocker"] = hook.blocker(scene)
except TypeError as e:                                # a build without FFmpeg
    res["movie_blocker"] = f"no movie format in this build: {e}"
r.image_settings.media_type = "IMAGE"
r.image_settings.file_format = "OPEN_EXR"

# 4b. the add-on's own render (the preview's, Apply's) with Lens in Renders on: the hook leaves it alone
bpy_render = sys.modules[f"{MODULE}.bpy_render"]
last_before = LAST()
lens_render = bpy.data.images.get(hook.RESULT_IMAGE)
size_before = tuple(lens_render.size) if lens_render is not None else None
calls = []
_init = hook.on_render_init


def _spy(sc, *a):
    calls.append((sc.name, bool(getattr(sc, "dcdi_lens_bokeh", None) and sc.dcdi_lens_bokeh.lens_in_renders)))
    return _init(sc, *a)


bpy.app.handlers.render_init.append(_spy)
own_rgb, own_z = bpy_render.render_aif_depth(scene, cam, 24, 32, 2)
bpy.app.handlers.render_init.remove(_spy)
res["own_render_calls"] = calls
lens_render = bpy.data.images.get(hook.RESULT_IMAGE)
res["own_render"] = {"shape": list(own_rgb.shape), "last_unchanged": LAST() is last_before,
                     "run": SESSION.render_run is not None, "lens_render_size": [size_before, tuple(lens_render.size)
                                                                               if lens_render is not None else None]}

# 5. the panel: the switch, the effect, and Lock Interface asked for when it is off
panel = importlib.import_module(f"{MODULE}.panel")


def draw():
    layout = StubLayout()
    panel.draw_lens_bokeh(layout, bpy.context)
    return layout.log


r.use_lock_interface = False
res["panel_unlocked"] = draw()
r.use_lock_interface = True
res["panel_locked"] = draw()
res["panel_operators"] = {where: [x[1] for x in log if x[0] == "operator"] for where, log in (
    ("sidebar", draw()), ("properties", (lambda lay: (panel.draw_lens_bokeh(lay, bpy.context, in_viewport=False),
                                                    lay.log)[1])(StubLayout())))}
res["panel_in_viewport"] = {c.__name__: c.bl_space_type == "VIEW_3D" for c in panel.CLASSES}

# 6. disabling the add-on removes the handlers
bpy.ops.preferences.addon_disable(module=MODULE)
res["handlers_after_disable"] = sorted(
    f"{n}:{getattr(fn, '__module__', '')}" for n in ("render_init", "render_post", "render_write", "render_complete",
                                                     "render_cancel", "frame_change_post")
    for fn in getattr(bpy.app.handlers, n) if "dcdi" in getattr(fn, "__module__", ""))

(OUT / "result.json").write_text(json.dumps(res, indent=1, default=str))
