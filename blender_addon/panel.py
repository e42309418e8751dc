"""The Lens Bokeh panel, in the camera properties and in the 3D view's sidebar
(tab "Lens Bokeh"); both draw the same layout.

Every text is written for the artist: lenses by name (their id only where a
file has none), no file's path, texts wrapped at whole words to the width of
the region they are drawn in (:func:`wrap`), the traced figures of the lens
once (:func:`readout_lines`), and the last job's status only while it
describes the settings as they are (:func:`status_lines`)."""
import re
import textwrap

import bpy

from dcdi_core import app

from . import logic, operators, reading, render_hook, thumbnails, viewport
from .session import SESSION

# the width of a character of the UI font, in pixels at UI scale 1, where the font cannot be measured (blf
# in a background Blender): a little above the average of Blender's UI font so that a line fits
CHAR_PX = 6.5
# pixels at UI scale 1 that a label does not get of its region's width: the panel's margins (MARGIN_PX), the
# sidebar's column of tabs (TABS_PX), a box's (BOX_PX) and an icon before the text with its gap (ICON_PX)
MARGIN_PX = 34
TABS_PX = 24
BOX_PX = 20
ICON_PX = 28
ICON_BUTTON_PX = 22          # a button of an icon alone, in a row
FALLBACK_CHARS = 40          # no region to measure (a script drawing the panel into a stub)


def line_width_px(context, indent_px: float = 0.0) -> float | None:
    """The width, pixels, a label has in the region being drawn, less
    ``indent_px`` (a box, an icon, a neighbour in a row; pixels at UI scale
    1); None where there is no region (a script drawing the panel)."""
    region = getattr(context, "region", None)
    width = getattr(region, "width", 0) or 0
    if width <= 1:
        return None
    scale = _ui_scale(context)
    tabs = TABS_PX if getattr(region, "type", "") == "UI" else 0
    return width - (MARGIN_PX + tabs + indent_px) * scale


def _ui_scale(context) -> float:
    try:
        return float(context.preferences.system.ui_scale) or 1.0
    except (AttributeError, TypeError, ValueError):
        return 1.0


def text_measure(context):
    """A function giving a text's width in pixels in the UI font (blf, where
    Blender has a UI), else an estimate (CHAR_PX a character)."""
    scale = _ui_scale(context)
    if not bpy.app.background:
        try:
            import blf
            points = context.preferences.ui_styles[0].widget.points

            def measure(text: str) -> float:
                blf.size(0, points * scale)
                return blf.dimensions(0, text)[0]
            measure("x")
            return measure
        except (ImportError, AttributeError, IndexError, RuntimeError, TypeError):
            pass
    return lambda text: len(text) * CHAR_PX * scale


def text_chars(context, indent_px: float = 0.0) -> int:
    """How many characters of average UI text fit on one label of the
    region being drawn (:func:`line_width_px`); FALLBACK_CHARS where there
    is no region."""
    width = line_width_px(context, indent_px)
    if width is None:
        return FALLBACK_CHARS
    sample = "Sharp from 1.70 m to 2.50 m, the lens focused at a distance: PSFs traced"
    return max(12, int(width * len(sample) / text_measure(context)(sample)))


def wrap(text: str, chars: int, max_lines: int | None = None) -> list[str]:
    """``text`` over lines of at most ``chars`` characters, broken between
    words (a word longer than a line, a path or a command, gets a line of
    its own, whole: Blender shortens it with an ellipsis where it must);
    at most ``max_lines`` lines, the last ending in an ellipsis after a
    whole word where text is left out."""
    # a number stays on the line of its unit ("2.00 m", "12.2 um", "5.9 s"): joined by a no-break space,
    # which textwrap does not break at, and given back as a space
    glued = " ".join(re.split(r"[ \t\r\n]+", text.strip()))
    glued = re.sub(r"(\d) x (?=\d)", "\\1\N{NO-BREAK SPACE}x\N{NO-BREAK SPACE}", glued)      # "7 x 7 px"
    glued = re.sub(r"(\d) (m|mm|um|\N{MICRO SIGN}m|s|px|%|dB)\b", "\\1\N{NO-BREAK SPACE}\\2", glued)
    lines = textwrap.wrap(glued, width=max(8, chars), break_long_words=False, break_on_hyphens=False) or [""]
    if max_lines is not None and len(lines) > max_lines:
        kept = lines[:max_lines]
        last = kept[-1]
        while last and len(last) + 2 > chars:
            last = last.rsplit(" ", 1)[0] if " " in last else ""
        kept[-1] = (last.rstrip(",;:") + " \N{HORIZONTAL ELLIPSIS}").strip()
        lines = kept
    return [line.replace("\N{NO-BREAK SPACE}", " ") for line in lines]


def wrap_to_region(context, text: str, indent_px: float = 0.0, max_lines: int | None = None) -> list[str]:
    """:func:`wrap` to the width of the region being drawn (less
    ``indent_px``, pixels at UI scale 1), each line measured in the UI
    font; FALLBACK_CHARS a line where there is no region."""
    width = line_width_px(context, indent_px)
    if width is None:
        return wrap(text, FALLBACK_CHARS, max_lines)
    measure = text_measure(context)
    chars = text_chars(context, indent_px)
    lines = wrap(text, chars, max_lines)
    while chars > 8 and any(" " in line and measure(line) > width for line in lines):
        chars -= 1                    # a line of wide letters: shorter lines
        lines = wrap(text, chars, max_lines)
    return lines


def _wrapped(layout, context, text: str, icon: str = "NONE", max_lines: int | None = 6, indent_px: float = 0.0):
    """``text`` as labels wrapped to the region's width, the icon on the
    first line and a blank of the icon's width on the others."""
    lines = wrap_to_region(context, text, indent_px + (ICON_PX if icon != "NONE" else 0), max_lines)
    col = layout.column(align=True)
    for i, line in enumerate(lines):
        col.label(text=line, icon=icon if i == 0 else ("BLANK1" if icon != "NONE" else "NONE"))
    return col


# ------------------------------------------------------------------ the lens
def readout_lines(path: str) -> tuple[str, str]:
    """(the lens's name as the list shows it, its traced figures: focal
    length, F-number and diagonal field of view, from the prescription):
    the panel's one readout of a lens. Raises what ``logic.lens_readout``
    raises for a broken file."""
    ro = logic.lens_readout(path)
    fov = ro["field_of_view_deg"]
    figures = f"f = {ro['focal_length_mm']:.2f} mm, F/{ro['f_number']:.2f}"
    if fov:
        figures += f", FoV {fov:.1f}\N{DEGREE SIGN}"
    return ro.get("title") or ro["name"], figures


THUMBNAIL_NOTE = "A point's blur at 1 m, 3 m and far (across), centre to edge (down)"


def _readout(layout, context, settings):
    """The chosen lens's name and traced figures, its PSFs' thumbnail, or why not."""
    path = reading.lens_file(settings.lens)
    box = layout.box()
    # the lens's name (or what is wrong) with the button that imports a Zemax file beside it
    row = box.row()
    if path is None:
        row.label(text="No lens chosen", icon="ERROR")
        row.operator("dcdi.import_zemax", text="", icon="FILEBROWSER")
        return
    try:
        title, figures = readout_lines(path)
    except (app.errors.DcdiError, ValueError, OSError) as e:
        row.label(text="Broken lens file:", icon="ERROR")
        row.operator("dcdi.import_zemax", text="", icon="FILEBROWSER")
        col = box.column(align=True)
        col.alert = True
        _wrapped(col, context, logic.message(e), max_lines=5, indent_px=BOX_PX)   # it names file, surface and field
        return
    _wrapped(row, context, title, icon="CAMERA_DATA", max_lines=3, indent_px=BOX_PX + ICON_BUTTON_PX)
    row.operator("dcdi.import_zemax", text="", icon="FILEBROWSER")
    box.label(text=figures)
    entry = next((e for e in reading.catalogue() if e.path == path), None)
    icon = thumbnails.icon(entry) if entry is not None else 0
    if icon:
        row = box.row()
        row.template_icon(icon_value=icon, scale=5.0)
        _wrapped(row, context, THUMBNAIL_NOTE, max_lines=5, indent_px=BOX_PX + 70)


def _aperture(layout, context, settings) -> None:
    """Camera Aperture, and when on the camera's own F-Stop, Blades and
    Rotation (what stops the lens down), with a note where its F-Stop is
    wider than the lens's."""
    col = layout.column(align=True)
    col.prop(settings, "use_camera_aperture")
    cam = context.scene.camera
    if not settings.use_camera_aperture or cam is None or cam.type != "CAMERA":
        return
    dof = cam.data.dof
    col.prop(dof, "aperture_fstop", text="F-Stop")
    col.prop(dof, "aperture_blades", text="Blades")
    col.prop(dof, "aperture_rotation", text="Rotation")
    path = reading.lens_file(settings.lens)
    if path is None:
        return
    try:
        lens = logic.load_lens_cached(path)
        _, note = logic.camera_aperture(lens, float(dof.aperture_fstop), int(dof.aperture_blades),
                                        float(dof.aperture_rotation))
    except (app.errors.DcdiError, ValueError, OSError) as e:
        note = logic.message(e)
    if note:
        _wrapped(layout, context, note, "INFO", max_lines=3)


def _sharp_range(scene, s) -> str:
    """The depths kept sharp, as the operator will compute them, in metres
    from the camera as the Distance is (the engine's are from the front of
    the lens, the entrance pupil's depth nearer), or why they cannot be
    computed yet."""
    try:
        r = reading.read_scene(scene)
    except (logic.BokehInputError, app.errors.DcdiError, ValueError, OSError) as e:
        return logic.message(e)
    pupil = r.entrance_pupil_mm / 1000.0
    (near, far), focus = r.keep, r.focus_m
    if far - near < 1e-6:                          # nothing kept: the lens's own depth of field
        return f"Focus {focus + pupil:.2f} m, with the lens's own depth of field"
    return f"Kept sharp from {near + pupil:.2f} m to {far + pupil:.2f} m (focus {focus + pupil:.2f} m)"


def status_lines(context) -> list[tuple[str, str]]:
    """(text, icon) of the last job's status under Apply Lens Bokeh: its
    progress while it runs (drawn as a slider), then what it did ("Lens
    Bokeh: done in 5.9 s") and where its PSFs came from, while the settings
    and camera are those it ran with (``reading.inputs_key``); after a
    change, nothing (it would describe another result)."""
    st = context.window_manager.dcdi_lens_bokeh_status
    if st.running:
        return []
    if not st.message and not st.psf_source:
        return []
    if getattr(st, "inputs", "") != reading.inputs_key(context.scene):
        return []
    out = []
    if st.message:
        out.append((f"{st.job}: {st.message}" if getattr(st, "job", "") else st.message,
                    "ERROR" if st.message.startswith("failed") else "NONE"))
    if st.psf_source:       # in an artist's words where there are some; the engine's are the line's tooltip
        out.append((getattr(st, "psf_words", "") or st.psf_source, "INFO"))
    return out


def draw_lens_bokeh(layout, context, in_viewport: bool = True):
    """The panel's rows. ``in_viewport``: drawn in the 3D view's sidebar, where
    Focus on Click can pick a point (in Properties > Camera it could only fail)."""
    scene = context.scene
    s = scene.dcdi_lens_bokeh
    viewport.warm_up(context)                  # the preview's render worker starts ahead of the toggle
    layout.use_property_split = True
    layout.use_property_decorate = False
    row = layout.row(align=True)
    row.use_property_split = False             # the list at the panel's width: the lens's whole name shows
    row.prop(s, "lens", text="")
    _readout(layout, context, s)
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
    col.prop(s, "lens_geometry")
    _aperture(layout, context, s)
    # a column's heading shows only before a checkbox when properties are split: a label of its own
    layout.label(text="Kept Sharp")
    col = layout.column(align=True)
    col.prop(s, "keep_front", text="In Front")
    col.prop(s, "keep_behind", text="Behind")
    _wrapped(layout, context, _sharp_range(scene, s), max_lines=4)

    col = layout.column(align=True)
    col.prop(s, "preview_size")
    col.prop(s, "preview_quality", text="Quality (dB)")
    col.prop(s, "samples")
    r = scene.render
    try:
        h, w = logic.preview_shape(r.resolution_x, r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y,
                                   s.preview_size)
        col.label(text=f"Preview {w} x {h} px")
    except logic.BokehInputError as e:
        _wrapped(col, context, logic.message(e), "ERROR")

    if scene.camera is None:
        _wrapped(layout, context, "No active camera in the scene", "ERROR")
    st = context.window_manager.dcdi_lens_bokeh_status
    row = layout.row()
    row.scale_y = 1.5
    row.operator("dcdi.apply_lens_bokeh", icon="RENDER_STILL")
    # beside the button, an icon toggle (its tooltip says what): Apply at the render's resolution
    row.prop(s, "apply_render_size", text="", icon="FULLSCREEN_ENTER")
    if st.running:
        # the status bar says "Esc cancels"; the slider keeps to stage and time
        layout.prop(st, "progress", text=(st.message or "working").split(" (")[0], slider=True)
    for text, icon in status_lines(context):
        if text == getattr(st, "psf_words", None):
            # a label that shows the engine's detail as its tooltip (an operator's description) and copies it
            layout.operator("dcdi.status_detail", text=text, icon=icon, emboss=False)
        else:
            _wrapped(layout, context, text, icon, max_lines=6)
    _draw_preview(layout, context, st)
    _draw_renders(layout.box(), context, scene, s, st)
    _draw_round_trip(layout.box(), context, s, st)


def _toggle(layout, data, name: str, icon: str, text: str | None = None):
    """A switch as a wide toggle button with its icon and its name (a split
    layout would put the name in its left column and leave the button an
    icon alone)."""
    row = layout.row()
    row.use_property_split = False
    if text is None:
        row.prop(data, name, icon=icon, toggle=True)
    else:
        row.prop(data, name, text=text, icon=icon, toggle=True)


def _draw_preview(layout, context, status):
    """The viewport preview's toggle and what its last refresh did."""
    _toggle(layout, status, "viewport_preview", "HIDE_OFF" if status.viewport_preview else "HIDE_ON")
    p = viewport.preview()
    if not p.enabled:
        return
    if p.error:
        _wrapped(layout, context, p.error, "ERROR")
        return
    if p.worker is not None or p.result is None:
        layout.label(text="Preview: updating...", icon="TIME")
    else:
        r = p.result
        what = f"render {r['render_s']:.1f} s, lens {r['lens_s']:.2f} s" if r["render_s"] else \
            f"lens {r['lens_s']:.2f} s"
        layout.label(text=f"Preview: {what}", icon="INFO")     # one line: the widgets below stay put
    # the mean of the passes rendered while nothing changed (viewport.ACCUMULATE_PASSES); drawn in every state, so
    # that the widgets below stay where they are while the artist reaches for them
    per_pass = context.scene.dcdi_lens_bokeh.samples
    most = (p.accumulate_passes if p.refines() else 1) * per_pass
    done = p.served_passes * per_pass
    layout.label(text=f"Refining: {done} of {most} samples" if done < most else f"Samples: {done}",
                 icon="TIME" if done < most else "CHECKMARK")


def _draw_renders(layout, context, scene, s, status):
    """Lens in Renders: F12 and animations through the lens."""
    _toggle(layout, s, "lens_in_renders", "RENDER_ANIMATION")
    if not s.lens_in_renders:
        return
    layout.prop(s, "render_effect")
    if not scene.render.use_lock_interface:
        # Blender reads it when F12 starts, before the add-on's handlers run
        _wrapped(layout, context, "Turn Lock Interface on: the lens reads the scene while Blender renders (F12 in "
                                  "the window; command-line renders do not need it)", "ERROR", indent_px=BOX_PX)
        row = layout.row()
        row.use_property_split = False
        row.prop(scene.render, "use_lock_interface", text="Lock Interface")
    why = render_hook.blocker(scene)
    if why:
        _wrapped(layout, context, why, "ERROR", indent_px=BOX_PX)
    if status.render_message:
        _wrapped(layout, context, status.render_message, "INFO", indent_px=BOX_PX)


def _draw_round_trip(layout, context, s, status):
    """Simulate Minimalist Lens and Correct Simulation: the DCDI round trip."""
    _wrapped(layout, context, "DCDI round trip: the chosen lens as prescribed", max_lines=3, indent_px=BOX_PX)
    layout.prop(s, "sensor_noise")
    layout.operator("dcdi.simulate_lens", icon="SHADERFX")
    layout.prop(s, "correction_method")
    if s.correction_method != "DECONVOLUTION":
        col = layout.column(align=True)
        col.use_property_split = False
        col.label(text="Correction Model")          # too long a name for a split's left column
        col.prop(s, "correction_model", text="")
    layout.operator("dcdi.correct_lens_simulation", icon="BRUSH_DATA")
    why = logic.torch_missing() if s.correction_method == "NETWORK" else None
    if why:
        _wrapped(layout, context, why, "ERROR", max_lines=None, indent_px=BOX_PX)     # the install command, whole
    elif SESSION.simulation:
        try:
            choice = operators.correction_choice(context)
            used = f" with {choice.model_path.name}" if choice.model_path else ""
            _wrapped(layout, context, f"{logic.METHOD_NAMES[choice.method]}{used}: {choice.reason}", "INFO",
                     indent_px=BOX_PX)
        except (logic.BokehInputError, app.errors.DcdiError, OSError) as e:
            _wrapped(layout, context, logic.message(e), "ERROR", indent_px=BOX_PX)
    if not status.running and status.correction:
        _wrapped(layout, context, f"Last Correct: {status.correction}", "CHECKMARK", indent_px=BOX_PX)


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
