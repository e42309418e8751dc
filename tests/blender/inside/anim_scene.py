"""Run in the background by tests/blender/test_command_line.py: the add-on
installed from its zip into the user folders, the test scene (a checker
cube 1 m away before a wall at 8 m, 160 x 120) with the panel's focus
distance keyframed (1.0 m on frame 1, 2.0 m on frame 2) and Lens
in Renders on, saved as OUT/lens.blend for `blender -b lens.blend -a` to
render through the lens; and the same scene without the lens, writing
multilayer EXRs with the Z pass, as OUT/passes.blend: the frames' own
passes, from which `dcdi bokeh` makes what each frame should be.

Arguments (DCDI_TEST_ARGS): zip, out, engine ('CYCLES' or 'BLENDER_EEVEE').
"""
import importlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ARGS, MODULE, OUT, RESULT, build_scene, install, write_result  # noqa: E402

import bpy  # noqa: E402

scene, cam, cube = build_scene()
RESULT["install"], _ = install(ARGS["zip"])
r = scene.render
r.engine = ARGS["engine"]
r.resolution_x, r.resolution_y, r.resolution_percentage = 160, 120, 100
scene.cycles.samples = 4
scene.cycles.use_denoising = False
scene.cycles.seed = 0
scene.frame_start, scene.frame_end = 1, 2
s = scene.dcdi_lens_bokeh
s.lens = "6p"
s.focus_mode = "DISTANCE"
for frame, focus in ((1, 1.0), (2, 2.0)):
    s.focus_distance = focus
    scene.keyframe_insert("dcdi_lens_bokeh.focus_distance", frame=frame)
s.keep_front, s.keep_behind = 0.3, 0.5
RESULT["focus_by_frame"] = {1: 1.0, 2: 2.0}
RESULT["keep_front_behind"] = [0.3, 0.5]
RESULT["module"] = MODULE

r.image_settings.file_format = "OPEN_EXR"
r.image_settings.color_depth = "32"
r.filepath = str(OUT / "lens" / "f_")
s.lens_in_renders = True
bpy.ops.wm.save_as_mainfile(filepath=str(OUT / "lens.blend"))

s.lens_in_renders = False
scene.view_layers[0].use_pass_z = True
importlib.import_module(f"{MODULE}.bpy_render").set_multilayer_exr(r.image_settings)   # Blender 5's way
r.filepath = str(OUT / "passes" / "f_")
bpy.ops.wm.save_as_mainfile(filepath=str(OUT / "passes.blend"))
write_result()
