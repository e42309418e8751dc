"""Run by tests/addon/test_viewport_preview.py in a fresh interpreter with the
pip bpy module: the render worker's scene copy kept across moves
(``render_worker.placements`` / ``apply_placements``). A copy written
before objects moved, with their placements applied, against a copy
written after: every object's world matrix, the camera's data and a
render of each; and a copy that lacks a moved object answers its name.
Writes OUT_DIR/result.json (the renders as .npy beside it).

    python tests/addon/addon_headless_placements.py ZIP OUT_DIR
"""
import importlib
import json

from headless_start import start

ZIP, OUT = start()

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from addon_scene import MODULE, build_scene, install  # noqa: E402

res: dict = {}
scene, cam, cube = build_scene()
res["install"], _ = install(ZIP)
worker = importlib.import_module(f"{MODULE}.render_worker")
bpy_render = importlib.import_module(f"{MODULE}.bpy_render")

# a child of the cube and an object constrained to it: placed by it in the copy as in this Blender
child = bpy.data.objects.new("child", cube.data)
scene.collection.objects.link(child)
child.parent, child.location = cube, (0.3, 0.0, 0.0)
follower = bpy.data.objects.new("follower", cube.data)
scene.collection.objects.link(follower)
con = follower.constraints.new("COPY_LOCATION")
con.target, con.use_offset = cube, True
follower.location = (-0.3, 0.1, 0.0)
scene.render.resolution_x, scene.render.resolution_y = 64, 48
before, after = OUT / "before.blend", OUT / "after.blend"


class Context:
    objects_in_mode = ()


worker.write_scene(Context, scene, before)
cube.location = (0.1, -0.05, -1.2)
cube.rotation_euler = (0.2, 0.3, 0.0)
cam.location.x += 0.05
cam.data.lens = 42.0
cam.data.shift_x = 0.02
moved = {"Cube"} if "Cube" in scene.objects else {cube.name}
given = json.loads(json.dumps(worker.placements(scene, cam, moved)))      # as the request carries it
worker.write_scene(Context, scene, after)
scene_name, cam_name = scene.name, cam.name


def state(path, placements=None):
    bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    sc = bpy.data.scenes[scene_name]
    missing = None if placements is None else worker.apply_placements(sc, cam_name, placements)
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    world = {o.name: [list(r) for r in o.evaluated_get(dg).matrix_world] for o in sc.objects}
    c = sc.objects[cam_name]
    data = {k: getattr(c.data, k) for k in worker.CAMERA_DATA}
    rgb, z = bpy_render.render_aif_depth(sc, c, 48, 64, 2, sc.view_layers[0].name)
    return world, data, rgb, z, missing


w_after, d_after, rgb_after, z_after, _ = state(after)
w_moved, d_moved, rgb_moved, z_moved, missing = state(before, given)
w_before, _, rgb_before, _, _ = state(before)
stale = dict(given, objects=dict(given["objects"], ghost=given["objects"][cam_name]))
_, _, _, _, ghost = state(before, stale)
np.save(OUT / "rgb_after.npy", rgb_after)
np.save(OUT / "rgb_moved.npy", rgb_moved)
np.save(OUT / "rgb_before.npy", rgb_before)
res.update(world_error=max(float(np.abs(np.array(w_after[n]) - np.array(w_moved[n])).max()) for n in w_after),
           world_moved=max(float(np.abs(np.array(w_after[n]) - np.array(w_before[n])).max()) for n in w_after),
           names=sorted(w_after) == sorted(w_moved), camera_data=d_after == d_moved, camera_lens=d_moved["lens"],
           z_error=float(np.abs(z_after - z_moved).max()), missing=missing, ghost=ghost,
           sent=sorted(given["objects"]))
(OUT / "result.json").write_text(json.dumps(res))
