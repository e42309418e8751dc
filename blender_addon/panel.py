"""The Lens Bokeh panel, in the camera properties and in the 3D view's sidebar
(tab "Lens Bokeh"); both draw the same layout."""
import bpy

from dcdi_core import errors as dcdi_errors

from . import logic, operators, reading, render_hook, thumbnails, viewport
from .session import SESSION


def _readout(layout, settings):
    """Focal length, F-number, field of view of the chosen lens, or why not."""
    path = reading.lens_file(settings.lens)
    box = layout.box()
    if path is None:
        box.label(text="No lens chosen", icon="ERROR")
        return
    try:
        ro = logic.lens_readout(path)
    except (dcdi_errors.DcdiError, ValueError, OSError) as e:
        col = box.column(align=True)
        col.alert = True
        col.label(text="Broken lens file:", icon="ERROR")
        # the message names file, surface and field; wrap it over a few lines
        msg = logic.message(e)
        for i in range(0, min(len(msg), 240), 48):
            col.label(text=msg[i:i + 48])
        return
    fov = ro["field_of_view_deg"]
    entry = next((e for e in reading.catalogue() if e.path == path), None)
    icon = thumbnails.icon(entry) if entry is not None else 0
    if icon:
        row = box.row()
        row.template_icon(icon_value=icon, scale=5.0)
        row.label(text="PSFs: fields 0 / 0.5 / 0.9 down, 1 m / 3 m / inf across")
    col = box.column(align=True)
    col.label(text=ro["name"][:48], icon="CAMERA_DATA")
    col.label(text=f"f = {ro['focal_length_mm']:.2f} mm   F/{ro['f_number']:.2f}   "
                   f"FoV {fov:.1f}\N{DEGREE SIGN}" if fov else
                   f"f = {ro['focal_length_mm']:.2f} mm   F/{ro['f_number']:.2f}")


def _sharp_range(scene, s) -> str:
    """The depths kept sharp, as the operator will compute them (metres from
    the lens's first vertex), or why they cannot be computed yet."""
    try:
        r = reading.read_scene(scene)
    except (logic.BokehInputError, dcdi_errors.DcdiError, ValueError, OSError) as e:
        return logic.message(e)[:60]
    (near, far), focus = r.keep, r.focus_m
    return f"Sharp from {near:.2f} m to {far:.2f} m (focus {focus:.2f} m)"


def draw_lens_bokeh(layout, context, in_viewport: bool = True):
    """The panel's rows. ``in_viewport``: drawn in the 3D view's sidebar, where
    Focus on Click can pick a point (in Properties > Camera it could only fail)."""
    scene = context.scene
    s = scene.dcdi_lens_bokeh
    layout.use_property_split = True
    layout.use_property_decorate = False
    row = layout.row(align=True)
    row.prop(s, "lens")
    row.operator("dcdi.import_zemax", text="", icon="FILEBROWSER")
    _readout(layout, s)
    layout.operator("dcdi.match_camera_to_lens", icon="CAMERA_DATA")

    col = layout.column(align=True)
    col.prop(s, "focus_mode", expand=True)
    if s.focus_mode == "DISTANCE":
        col.prop(s, "focus_distance", text="Distance")
    elif s.focus_mode == "OBJECT":
        col.prop(s, "focus_object", text="Object")
    elif scene.camera is not None and scene.camera.type == "CAMERA":
        dof = scene.camera.data.dof
        col.prop(dof, "focus_object", text="Camera Object")
        if dof.focus_object is None:
            col.prop(dof, "focus_distance", text="Camera Distance")
    row = col.row(align=True)
    if in_viewport:
        row.operator("dcdi.focus_pick", icon="EYEDROPPER")
    row.operator("dcdi.focus_active_object", text="Active", icon="OBJECT_DATA")
    col.prop(s, "refocus")
    col = layout.column(align=True, heading="Kept Sharp")
    col.prop(s, "keep_front")
    col.prop(s, "keep_behind")
    layout.label(text=_sharp_range(scene, s))

    col = layout.column(align=True)
    col.prop(s, "preview_size")
    col.prop(s, "samples")
    r = scene.render
    try:
        h, w = logic.preview_shape(r.resolution_x, r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y,
                                   s.preview_size)
        col.label(text=f"Preview {w} x {h} px")
    except logic.BokehInputError as e:
        col.label(text=logic.message(e), icon="ERROR")

    if scene.camera is None:
        layout.label(text="No active camera in the scene", icon="ERROR")
    st = context.window_manager.dcdi_lens_bokeh_status
    row = layout.row()
    row.scale_y = 1.5
    row.operator("dcdi.apply_lens_bokeh", icon="RENDER_STILL")
    _draw_preview(layout, st)
    if st.running:
        # the status bar says "Esc cancels"; the slider keeps to stage and time
        layout.prop(st, "progress", text=(st.message or "working").split(" (")[0], slider=True)
    elif st.message:
        layout.label(text=st.message)
    if not st.running and st.psf_source:
        layout.label(text=st.psf_source[:72], icon="INFO")
    _draw_renders(layout.box(), scene, s, st)
    _draw_round_trip(layout.box(), context, s, st)


def _draw_preview(layout, status):
    """The viewport preview's toggle and what its last refresh did."""
    layout.prop(status, "viewport_preview", icon="HIDE_OFF" if status.viewport_preview else "HIDE_ON")
    p = viewport.preview()
    if not p.enabled:
        return
    if p.error:
        _wrapped(layout, p.error, 192, "ERROR")
    elif p.worker is not None:
        layout.label(text="Preview: updating...", icon="TIME")
    elif p.result is not None:
        r = p.result
        what = f"render {r['render_s']:.1f} s + lens {r['lens_s']:.2f} s" if r["render_s"] else \
            f"lens {r['lens_s']:.2f} s"
        layout.label(text=f"Preview: {what} (camera view)", icon="INFO")


def _draw_renders(layout, scene, s, status):
    """Lens in Renders: F12 and animations through the lens."""
    layout.prop(s, "lens_in_renders", icon="RENDER_ANIMATION")
    if not s.lens_in_renders:
        return
    layout.prop(s, "render_effect")
    if not scene.render.use_lock_interface:
        # Blender reads it when F12 starts, before the add-on's handlers run
        _wrapped(layout, "Turn Lock Interface on: the lens reads the scene while Blender renders (F12 in the "
                         "window; command-line renders do not need it)", 192, "ERROR")
        layout.prop(scene.render, "use_lock_interface")
    why = render_hook.blocker(scene)
    if why:
        _wrapped(layout, why, 240, "ERROR")
    if status.render_message:
        _wrapped(layout, status.render_message, 192, "INFO")


def _draw_round_trip(layout, context, s, status):
    """Simulate Minimalist Lens and Correct Simulation: the DCDI round trip."""
    layout.label(text="DCDI round trip (the chosen lens as prescribed)")
    layout.prop(s, "sensor_noise")
    layout.operator("dcdi.simulate_lens", icon="SHADERFX")
    layout.prop(s, "correction_method")
    if s.correction_method != "DECONVOLUTION":
        layout.prop(s, "correction_model")
    layout.operator("dcdi.correct_lens_simulation", icon="BRUSH_DATA")
    why = logic.torch_missing() if s.correction_method == "NETWORK" else None
    if why:
        _wrapped(layout, why, 400, "ERROR")               # the install command
    elif SESSION.simulation:
        try:
            choice = operators.correction_choice(context)
            used = f" with {choice.model_path.name}" if choice.model_path else ""
            _wrapped(layout, f"{logic.METHOD_NAMES[choice.method]}{used}: {choice.reason}", 240, "INFO")
        except (logic.BokehInputError, dcdi_errors.DcdiError, OSError) as e:
            _wrapped(layout, logic.message(e), 144, "ERROR")
    if not status.running and status.correction:
        _wrapped(layout, f"Last Correct: {status.correction}", 240, "CHECKMARK")


def _wrapped(layout, text: str, limit: int, icon: str, width: int = 48):
    """``text`` (at most ``limit`` characters) over lines of ``width``, the icon on the first."""
    for i in range(0, min(len(text), limit), width):
        layout.label(text=text[i:i + width], icon=icon if i == 0 else "BLANK1")


class _LensBokehPanel:
    """The one panel, drawn in two places (subclasses say where)."""
    bl_label = "Lens Bokeh"

    def draw(self, context):
        draw_lens_bokeh(self.layout, context, in_viewport=self.bl_space_type == "VIEW_3D")


class DCDI_PT_lens_bokeh_camera(_LensBokehPanel, bpy.types.Panel):
    bl_idname = "DCDI_PT_lens_bokeh_camera"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "data"

    @classmethod
    def poll(cls, context):
        return context.camera is not None


class DCDI_PT_lens_bokeh_sidebar(_LensBokehPanel, bpy.types.Panel):
    bl_idname = "DCDI_PT_lens_bokeh_sidebar"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Lens Bokeh"


CLASSES = (DCDI_PT_lens_bokeh_camera, DCDI_PT_lens_bokeh_sidebar)
