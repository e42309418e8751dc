"""Run by tests/addon/test_addon.py in a fresh interpreter (BLENDER_USER_RESOURCES
must be set before bpy is imported): installs the built extension zip into a
temporary user folder, enables it, runs Apply Lens Bokeh on a small scene,
and writes what it saw to a JSON file (pixels as .npy beside it).

    python tests/addon/addon_headless.py ZIP OUT_DIR
"""
import json
import os
import sys
import time
from pathlib import Path

from headless_start import start

ZIP, OUT = start()         # the add-on must work in Blender's own Python: none of its missing modules needed

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from addon_scene import MODULE, build_scene, data_counts, diff, error_of, install, snapshot  # noqa: E402

res: dict = {"errors": {}}


def check(name, fn):
    res["errors"][name] = error_of(fn)


scene, cam, cube = build_scene()
counts0 = data_counts()
images0 = {i.name for i in bpy.data.images}        # a real Blender's startup file may hold some
res["install"], res["install_s"] = install(ZIP)
res["enabled"] = MODULE in bpy.context.preferences.addons
logic = sys.modules[f"{MODULE}.logic"]
reading = sys.modules[f"{MODULE}.reading"]
res["engine_file"] = sys.modules["dcdi_core"].__file__
res["lenses"] = {e.id: e.path for e in logic.lens_catalogue()}
res["user_folder"] = os.environ["BLENDER_USER_RESOURCES"]

s = scene.dcdi_lens_bokeh
res["default_lens"] = s.lens
s.lens = "6p"
s.focus_mode = "OBJECT"
s.focus_object = cube
s.keep_front, s.keep_behind = 0.3, 0.3
s.preview_size = 128
s.samples = 4
res["lens_geometry_default"] = s.lens_geometry
s.lens_geometry = True
res["match_camera"] = sorted(bpy.ops.dcdi.match_camera_to_lens())
res["camera_lens_mm"] = cam.data.lens
res["match_focus_m"] = reading.read_scene(scene).focus_m
s.lens_geometry = False                          # the camera's framing as it stands: the lens's focal length
bpy.ops.dcdi.match_camera_to_lens()
res["camera_lens_mm_no_geometry"] = cam.data.lens
size = (scene.render.resolution_x, scene.render.resolution_y, 1.0, 1.0)
res["camera_pinhole_mm"] = reading.pinhole_focal_length_mm(cam, size, logic.load_lens_cached(res["lenses"]["6p"]))
# a lens whose sensor is below Blender's 1 mm minimum, then back to the 6p
s.lens = "double-gauss"
res["double_gauss_camera"] = {"match": sorted(bpy.ops.dcdi.match_camera_to_lens()), "angle": cam.data.angle,
                              "lens": cam.data.lens, "sensor_width": cam.data.sensor_width,
                              "sensor_fit": cam.data.sensor_fit}
s.lens = "6p"
bpy.ops.dcdi.match_camera_to_lens()
res["readout"] = logic.lens_readout(res["lenses"]["6p"])

before = {"scene": snapshot(scene), "camera": snapshot(cam), "camera_data": snapshot(cam.data)}
counts1 = data_counts()
for run in ("cold", "warm"):
    t = time.perf_counter()
    res[f"apply_{run}"] = sorted(bpy.ops.dcdi.apply_lens_bokeh(store_inputs=True))
    res[f"apply_{run}_s"] = time.perf_counter() - t
after = {"scene": snapshot(scene), "camera": snapshot(cam), "camera_data": snapshot(cam.data)}
res["settings_diff"] = diff(before, after)
# the comparison can fail: a changed setting shows up
scene.render.resolution_percentage += 1
res["snapshot_detects_a_change"] = bool(diff(before["scene"], snapshot(scene)))
scene.render.resolution_percentage -= 1
counts2 = data_counts()
res["new_data"] = {k: counts2[k] - counts1[k] for k in counts2 if counts2[k] != counts1[k]}
res["images"] = sorted(i.name for i in bpy.data.images if i.name not in images0)
img = bpy.data.images["Lens Bokeh"]
res["result_float"] = bool(img.is_float)
res["result_colorspace"] = img.colorspace_settings.name
bpy_render = sys.modules[f"{MODULE}.bpy_render"]
for name, key in (("Lens Bokeh", "out"), ("Lens Bokeh AiF", "aif"), ("Lens Bokeh Depth", "depth")):
    np.save(OUT / f"{key}.npy", bpy_render.get_image(name))
res["keep_m"] = [s.keep_front, s.keep_behind]
ep = res["readout"]["entrance_pupil_mm"] / 1000.0
res["focus_m"] = 1.0 - ep

# Lens Geometry: the camera matched at the focus, the picture moved as the lens at its focus moves it;
# the add-on's result is the engine's bokeh with the distortion, reading the render at the camera's focal length
s.lens_geometry = True
bpy.ops.dcdi.match_camera_to_lens()
res["geometry_apply"] = sorted(bpy.ops.dcdi.apply_lens_bokeh(store_inputs=True))
geo = {k: bpy_render.get_image(n) for k, n in (("out", "Lens Bokeh"), ("aif", "Lens Bokeh AiF"),
                                                ("depth", "Lens Bokeh Depth"))}
r_geo = reading.read_scene(scene)
want, _ = logic.run_bokeh(geo["aif"][..., :3], geo["depth"][..., 0].astype(np.float64), r_geo.lens,
                          focus_m=r_geo.focus_m, keep=r_geo.keep, lens_geometry=True,
                          pinhole_focal_length_mm=r_geo.pinhole_focal_length_mm)
res["geometry_engine_diff"] = float(np.abs(geo["out"][..., :3] - want).max())
res["geometry_pinhole_mm"] = r_geo.pinhole_focal_length_mm
res["geometry_vs_plain"] = float(np.abs(geo["out"][..., :3] - np.load(OUT / "out.npy")[..., :3]).mean())
s.lens_geometry = False
bpy.ops.dcdi.match_camera_to_lens()

# a shipped lens with the lens as prescribed (Refocus Lens off): served by the
# bundled Omni-Lens-Field; the tracer raises, so a finished run traced nothing
engine = "dcdi_core"
tracers = {m: sys.modules[f"{engine}.{m}"].compute_sources for m in ("psf.library", "psf.compute")}


def no_tracing(*a, **k):
    raise RuntimeError("the ray tracer was called")


for m in tracers:
    sys.modules[f"{engine}.{m}"].compute_sources = no_tracing
s.refocus = False
res["olf_apply"] = {}
for lens_id in ("6p", "mos-s1"):
    s.lens = lens_id
    st = bpy.context.window_manager.dcdi_lens_bokeh_status
    st.psf_source = ""
    t = time.perf_counter()
    res["olf_apply"][lens_id] = {"result": sorted(bpy.ops.dcdi.apply_lens_bokeh()), "status": st.psf_source,
                                 "seconds": time.perf_counter() - t}
    np.save(OUT / f"olf-{lens_id}.npy", bpy_render.get_image("Lens Bokeh"))
# Refocus Lens on (the default), the focus inside the range the shipped OLF
# learned the 6P across: served by it too, tracing nothing
s.refocus = True
s.lens = "6p"
st.psf_source = ""
t = time.perf_counter()
res["olf_apply_refocus"] = {"result": sorted(bpy.ops.dcdi.apply_lens_bokeh()), "status": st.psf_source,
                            "seconds": time.perf_counter() - t}
np.save(OUT / "olf-6p-refocus.npy", bpy_render.get_image("Lens Bokeh"))
# a catalogue lens refocused and stopped down by the camera's aperture: served by
# its ray map, tracing nothing
s.lens = "zeiss-jena-tessar-50mm-f2-8"
s.use_camera_aperture = True
fstop0 = cam.data.dof.aperture_fstop
cam.data.dof.aperture_fstop, cam.data.dof.aperture_blades = 5.6, 6
st.psf_source = ""
t = time.perf_counter()
res["raymap_apply"] = {"result": sorted(bpy.ops.dcdi.apply_lens_bokeh()), "status": st.psf_source,
                       "seconds": time.perf_counter() - t}
np.save(OUT / "raymap-tessar.npy", bpy_render.get_image("Lens Bokeh"))
s.use_camera_aperture = False
cam.data.dof.aperture_fstop, cam.data.dof.aperture_blades = fstop0, 0
for m, fn in tracers.items():
    sys.modules[f"{engine}.{m}"].compute_sources = fn
s.refocus = True
s.lens = "6p"

# Camera Aperture: the camera's F-Stop and blades stop the lens down (traced: the
# shipped stores hold it wide open); an F-Stop wider than the lens's: wide open, said
reading = sys.modules[f"{MODULE}.reading"]
res["matched_fstop"] = cam.data.dof.aperture_fstop
s.use_camera_aperture = True
cam.data.dof.aperture_fstop, cam.data.dof.aperture_blades, cam.data.dof.aperture_rotation = 4.0, 6, 0.0
st.psf_source = ""
res["aperture_apply"] = {"iris": reading.read_scene(scene).lens.iris, "result": sorted(bpy.ops.dcdi.apply_lens_bokeh()),
                         "status": st.psf_source}
np.save(OUT / "aperture-f4.npy", bpy_render.get_image("Lens Bokeh"))
cam.data.dof.aperture_fstop = 1.2
wide = reading.read_scene(scene)
res["aperture_wide"] = {"iris": wide.lens.iris, "note": wide.aperture_note}
s.use_camera_aperture = False
cam.data.dof.aperture_fstop, cam.data.dof.aperture_blades = res["matched_fstop"], 0

# a focus on empty space: nothing between 3.7 and 4.3 m (the cube is nearer,
# the wall farther), so everything is out of focus
s.focus_mode = "DISTANCE"
s.focus_distance = 4.0
res["empty_focus"] = sorted(bpy.ops.dcdi.apply_lens_bokeh(store_inputs=True))
np.save(OUT / "empty-focus.npy", bpy_render.get_image("Lens Bokeh"))
np.save(OUT / "empty-focus-aif.npy", bpy_render.get_image("Lens Bokeh AiF"))

# what cannot work gives a clear message
broken = OUT / "lenses" / "broken-lens.toml"
broken.parent.mkdir(exist_ok=True)
broken.write_text(Path(res["lenses"]["6p"]).read_text().replace("semi_diameter_mm", "semi_diameter_mmm", 1))
os.environ["DCDI_LENS_PATH"] = str(broken.parent)
s.lens = "broken-lens"
check("broken_lens", lambda: bpy.ops.dcdi.apply_lens_bokeh())
s.lens = "6p"
scene.camera = None
check("no_camera", lambda: bpy.ops.dcdi.apply_lens_bokeh())
scene.camera = cam

# an uncompressed multilayer EXR as the add-on writes it, for the reader test
scene.render.engine = "CYCLES"
scene.cycles.samples = 1
scene.render.resolution_percentage = 5
scene.view_layers[0].use_pass_z = True
bpy_render.set_multilayer_exr(scene.render.image_settings)
scene.render.use_file_extension = False
scene.render.filepath = str(OUT / "multilayer.exr")
bpy.ops.render.render(write_still=True)

# what the add-on holds (one session), with the preview on, before and after the disable
SESSION = sys.modules[f"{MODULE}.session"].SESSION
viewport = sys.modules[f"{MODULE}.viewport"]
bpy.context.window_manager.dcdi_lens_bokeh_status.viewport_preview = True


def held():
    return {"lens_names": len(SESSION.lens_names), "lenses": len(SESSION.lenses), "readouts": len(SESSION.readouts),
            "lens_items": len(SESSION.lens_items), "lens_folders": len(SESSION.lens_folders.files),
            "handles": [o for o in ("preview", "render", "thumbnails") if SESSION.holds(o)],
            "preview_on": SESSION.preview is not None and SESSION.preview.enabled,
            "thumbnails": SESSION.thumbnails.pcoll is not None}


res["session_before_disable"] = held()

# disable: nothing of the add-on stays registered
res["disable"] = sorted(bpy.ops.preferences.addon_disable(module=MODULE))
res["session_after_disable"] = held()
res["preview_handler_left"] = viewport.on_depsgraph_update in bpy.app.handlers.depsgraph_update_post
res["leftovers"] = [n for n in dir(bpy.types) if n.startswith("DCDI_")]
res["scene_prop_left"] = hasattr(bpy.types.Scene, "dcdi_lens_bokeh")
res["wm_prop_left"] = hasattr(bpy.types.WindowManager, "dcdi_lens_bokeh_status")
res["operator_left"] = "apply_lens_bokeh" in dir(bpy.ops.dcdi)
res["still_enabled"] = MODULE in bpy.context.preferences.addons
res["data_counts_start"] = counts0

(OUT / "result.json").write_text(json.dumps(res, indent=1, default=str))
