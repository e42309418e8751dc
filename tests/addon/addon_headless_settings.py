"""Run by tests/addon/test_viewport_preview.py in a fresh interpreter with the
pip bpy module: every setting of the panel, and of the active camera's
Depth of Field, changed in turn; whether what the preview shows
(``viewport.wanted``: the keys of its render and its lens stage) changed.
Writes OUT_DIR/result.json: {setting: changed}.

    python tests/addon/addon_headless_settings.py ZIP OUT_DIR
"""
import importlib
import json

from headless_start import start

ZIP, OUT = start()

import bpy  # noqa: E402
from addon_scene import MODULE, build_scene, install  # noqa: E402

scene, cam, cube = build_scene()
install(ZIP)
viewport = importlib.import_module(f"{MODULE}.viewport")
s = scene.dcdi_lens_bokeh
s.lens = "zeiss-jena-tessar-50mm-f2-8"
s.focus_mode = "DISTANCE"
dof = cam.data.dof
dof.aperture_fstop, dof.aperture_blades, dof.aperture_rotation = 8.0, 6, 0.0
other = bpy.data.objects.new("other", None)
scene.collection.objects.link(other)
other.location = (0.0, 0.0, -3.0)
ctx = bpy.context


def changed(setup, change) -> bool:
    """Whether ``change()`` after ``setup()`` changes what the preview shows."""
    setup()
    before = viewport.wanted(ctx)
    change()
    return viewport.wanted(ctx) != before


def mode(name, **extra):
    def setup():
        s.focus_mode = name
        for k, v in extra.items():
            setattr(s, k, v)
    return setup


def aperture(on):
    def setup():
        s.focus_mode = "DISTANCE"
        s.use_camera_aperture = on
    return setup


def assign(obj, attr, value):
    return lambda: setattr(obj, attr, value)


PANEL = {
    "lens": (mode("DISTANCE"), assign(s, "lens", "zeiss-sonnar-50mm-f1-5")),
    "focus_mode": (mode("DISTANCE", focus_object=other), assign(s, "focus_mode", "OBJECT")),
    "focus_distance": (mode("DISTANCE"), assign(s, "focus_distance", 3.3)),
    "focus_object": (mode("OBJECT", focus_object=other), assign(s, "focus_object", cube)),
    "refocus": (mode("DISTANCE"), assign(s, "refocus", False)),
    "lens_geometry": (mode("DISTANCE"), assign(s, "lens_geometry", True)),
    "use_camera_aperture": (aperture(False), assign(s, "use_camera_aperture", True)),
    "keep_front": (mode("DISTANCE"), assign(s, "keep_front", 0.05)),
    "keep_behind": (mode("DISTANCE"), assign(s, "keep_behind", 0.07)),
    "preview_size": (mode("DISTANCE"), assign(s, "preview_size", 200)),
    "preview_quality": (mode("DISTANCE"), assign(s, "preview_quality", 45.0)),
    "samples": (mode("DISTANCE"), assign(s, "samples", 7)),
    "lens_in_renders": (mode("DISTANCE"), assign(s, "lens_in_renders", True)),
    "render_effect": (mode("DISTANCE"), assign(s, "render_effect", "LENS")),
    "sensor_noise": (mode("DISTANCE"), assign(s, "sensor_noise", True)),
    "correction_method": (mode("DISTANCE"), assign(s, "correction_method", "DECONVOLUTION")),
    "correction_model": (mode("DISTANCE"), assign(s, "correction_model", "/nowhere/model.npz")),
    "apply_render_size": (mode("DISTANCE"), assign(s, "apply_render_size", True)),
}
CAMERA = {
    "focus_distance": (mode("CAMERA"), assign(dof, "focus_distance", 4.4)),
    "focus_object": (mode("CAMERA"), assign(dof, "focus_object", other)),
    "aperture_fstop": (aperture(True), assign(dof, "aperture_fstop", 11.0)),
    "aperture_blades": (aperture(True), assign(dof, "aperture_blades", 7)),
    "aperture_rotation": (aperture(True), assign(dof, "aperture_rotation", 0.3)),
    "use_dof": (aperture(True), assign(dof, "use_dof", not dof.use_dof)),
    "aperture_ratio": (aperture(True), assign(dof, "aperture_ratio", 1.5)),
}

def agreeing() -> dict:
    """The focus (m from the lens's front) of the panel's Distance 2.0, the
    camera's own Distance 2.0 and an object 2.0 in front of the camera, and
    the lens's entrance pupil (mm behind its front)."""
    reading = importlib.import_module(f"{MODULE}.reading")
    s.use_camera_aperture, dof.focus_object = False, None
    target = bpy.data.objects.new("target", None)
    scene.collection.objects.link(target)
    target.location = cam.matrix_world @ __import__("mathutils").Vector((0.0, 0.0, -2.0))
    out = {}
    for name, setup in (("distance", lambda: (setattr(s, "focus_mode", "DISTANCE"), setattr(s, "focus_distance", 2.0))),
                        ("camera", lambda: (setattr(s, "focus_mode", "CAMERA"), setattr(dof, "focus_distance", 2.0))),
                        ("object", lambda: (setattr(s, "focus_mode", "OBJECT"), setattr(s, "focus_object", target)))):
        setup()
        bpy.context.view_layer.update()
        r = reading.read_scene(scene)
        out[name], out["pupil_mm"] = r.focus_m, r.entrance_pupil_mm
    return out


res = {"panel": {k: changed(*v) for k, v in PANEL.items()},
       "camera": {k: changed(*v) for k, v in CAMERA.items()},
       "panel_properties": sorted(p.identifier for p in s.bl_rna.properties if p.identifier not in ("rna_type", "name")),
       "camera_properties": sorted(p.identifier for p in dof.bl_rna.properties if p.identifier != "rna_type"),
       "not_in_preview": sorted(viewport.NOT_IN_PREVIEW), "camera_not_in_preview": sorted(viewport.CAMERA_DOF_NOT_IN_PREVIEW)}
res["agree"] = agreeing()
# Apply at Render Size: the result at the render's resolution and percentage, not the Preview Size
s.focus_mode, s.lens, s.use_camera_aperture = "DISTANCE", "zeiss-jena-tessar-50mm-f2-8", False
s.preview_size, s.samples, s.apply_render_size = 64, 2, True
scene.render.resolution_percentage = 50
res["apply_render_size"] = sorted(bpy.ops.dcdi.apply_lens_bokeh())
res["apply_image"] = list(bpy.data.images["Lens Bokeh"].size)
res["render_size"] = [scene.render.resolution_x, scene.render.resolution_y]
(OUT / "result.json").write_text(json.dumps(res))
