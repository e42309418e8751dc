"""The panel's settings (per scene) and the running job's readout (per window
manager, not saved). Distances in metres (scene units times the scene's
unit scale), resolutions in pixels."""

import os
import re
import tomllib

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from . import logic, reading, thumbnails, viewport
from .session import SESSION

DEFAULT_LENS = "zeiss-sonnar-50mm-f1-5"      # a standard photographic lens (the paper's phone lens is in the list)


def lens_item_description(entry) -> str:
    """The lens list's tooltip of ``entry``: its file's whole name (figures
    in it said to be its source's: the panel's traced readout can differ
    from them), and the file's name (no folder: the panel shows no paths).
    Read once per file and modification time (the list's items are asked
    for at every draw)."""
    try:
        key = ("tooltip", entry.path, os.stat(entry.path).st_mtime_ns)
    except OSError:
        return f"File: {os.path.basename(entry.path)}"
    if key not in SESSION.lens_names:
        try:
            with open(entry.path, "rb") as f:
                full = str(tomllib.load(f).get("name") or "").strip()
        except (OSError, tomllib.TOMLDecodeError):
            full = ""
        stated = " (figures as its source states them; the panel shows the traced ones)" if re.search(
            r"\bF\s*/\s*\d|\bf\s*=\s*\d", full) else ""
        head = f"{full}{stated}. " if full else ""
        SESSION.lens_names[key] = f"{head}File: {os.path.basename(entry.path)}"
    return SESSION.lens_names[key]


def _lens_items(self, context):
    items = [(e.id, e.name, lens_item_description(e), thumbnails.icon(e) or "CAMERA_DATA", e.number)
             for e in reading.catalogue()]
    if not items:
        items = [("NONE", "No lens files found", "no *.toml in the lens folders", "ERROR", 0)]
    # Blender keeps only references to enum item strings: the session holds them so that Python does not
    # free them while the UI shows them (documented pitfall of dynamic EnumProperty items)
    SESSION.lens_items = items
    return items


def _settings_changed(settings, context):
    """Every setting the viewport preview shows: tell it (a Python assignment
    and a click both run this; neither tags the depsgraph)."""
    viewport.settings_changed(settings, context)


class DCDI_LensBokehSettings(bpy.types.PropertyGroup):
    lens: EnumProperty(update=_settings_changed, name="Lens", description="Lens prescription (lenses/*.toml and imported Zemax files)",
                       items=_lens_items, default=logic.lens_number(DEFAULT_LENS))
    focus_mode: EnumProperty(update=_settings_changed, name="Focus", items=[
        ("DISTANCE", "Distance", "Focus at a distance from the lens"),
        ("OBJECT", "Object", "Focus on an object's origin (its depth along the camera's view axis)"),
        ("CAMERA", "Camera", "The active camera's own Depth of Field focus: its Focus Object, else its Focus "
                             "Distance (animated with the camera)")],
        default="DISTANCE")
    focus_distance: FloatProperty(update=_settings_changed, name="Focus Distance",
                                  description="Distance to focus at, measured from the camera along its view "
                                              "axis as Blender's own Depth of Field measures it, in scene units "
                                              "(metres at unit scale 1)", default=2.0, min=0.01, soft_max=50.0,
                                  subtype="DISTANCE", unit="LENGTH")
    focus_object: PointerProperty(update=_settings_changed, name="Focus Object", type=bpy.types.Object,
                                  description="Focus on this object's origin")
    refocus: BoolProperty(update=_settings_changed, name="Refocus Lens", default=True,
                          description="Move the lens's sensor so that the focus distance is in focus (PSFs traced "
                                      "for each focus, then cached). Off: the lens as its prescription stands, the "
                                      "kept range still sharp; a shipped lens is then served by the bundled "
                                      "Omni-Lens-Field network, with no tracing")
    lens_geometry: BoolProperty(update=_settings_changed, name="Lens Geometry", default=False,
                                description="Move the picture as the lens focused here does: it breathes (the "
                                            "image grows as the lens focuses closer) and it distorts. Your camera's "
                                            "view is read at its own focal length; Match Camera to Lens frames it "
                                            "as the lens at the focus distance. Off: the depth of field on your "
                                            "camera's framing as it stands")
    use_camera_aperture: BoolProperty(update=_settings_changed, name="Camera Aperture", default=False,
                                      description="Stop the lens down to the active camera's F-Stop, shaped by its "
                                                  "Blades and Rotation (Properties > Camera > Depth of Field > "
                                                  "Aperture): the PSFs are traced for that stop, then cached. An "
                                                  "F-Stop wider than the lens's own leaves it wide open. Off: the "
                                                  "lens wide open, its round stop as prescribed, served by the "
                                                  "bundled PSF stores")
    keep_front: FloatProperty(update=_settings_changed, name="In Front",
                              description="Depth kept perfectly sharp in front of the focus, scene units. 0 (the "
                                          "default): none, the lens's own depth of field, as a photograph has it",
                              default=0.0, min=0.0, soft_max=10.0, subtype="DISTANCE", unit="LENGTH")
    keep_behind: FloatProperty(update=_settings_changed, name="Behind",
                               description="Depth kept perfectly sharp behind the focus, scene units. 0 (the "
                                           "default): none, the lens's own depth of field",
                               default=0.0, min=0.0, soft_max=100.0, subtype="DISTANCE", unit="LENGTH")
    preview_size: IntProperty(update=_settings_changed, name="Preview Size", description="Long side of the preview in pixels (the render's "
                              "aspect is kept). PSFs are built at this pixel pitch: larger takes longer the first "
                              "time", default=320, min=16, soft_max=1920, max=8192, subtype="PIXEL")
    preview_quality: FloatProperty(update=_settings_changed, name="Preview Quality",
                                   description="How close the preview's lens stage stays to the render with "
                                               "converged PSFs, in dB PSNR: the PSF work (rays, wavelengths, "
                                               "fields) and the coarse layers are planned from the lens's measured "
                                               "error table. Higher is closer and slower; Apply and F12 take 40",
                                   default=30.0, min=20.0, max=80.0, soft_max=60.0, precision=0)
    apply_render_size: BoolProperty(name="Apply at Render Size", default=False,
                                    description="Apply Lens Bokeh renders at the scene's render resolution (Output > "
                                                "Format, with its percentage) instead of the Preview Size, the "
                                                "large blur included; its render runs in the preview's second "
                                                "Blender where that runs")
    samples: IntProperty(update=_settings_changed, name="Samples", description="Cycles samples per pixel of the all-in-focus render "
                         "(denoised)", default=16, min=1, soft_max=256, max=16384)
    lens_in_renders: BoolProperty(name="Lens in Renders", default=False,
                                  description="Every rendered frame (F12, animations, command-line renders) gets "
                                              "the lens, from the frame's Combined and Z passes; the result is "
                                              "written where Blender writes the frame (image outputs) and shown as "
                                              "the image \"Lens Render\". Focus and kept range follow their "
                                              "animation frame by frame")
    render_effect: EnumProperty(name="Effect", default="DOF", items=[
        ("DOF", "Depth of Field", "The lens's depth of field (as Apply Lens Bokeh: focus, kept range, refocus)"),
        ("LENS", "Whole Lens", "The lens focused at the focus distance with its aberrations and distortion "
                               "(as `dcdi simulate --focus`)")],
        description="What Lens in Renders applies to each frame")
    sensor_noise: BoolProperty(name="Sensor Noise", default=False,
                               description="Simulate Minimalist Lens: also add the engine's sensor noise (shot "
                                           "and read noise, 10000 e- full well, 3 e- read noise, seed 0)")
    correction_method: EnumProperty(name="Method", default="AUTO", items=[
        ("AUTO", "Auto", "The engine's rule: the Correction Model file if one is given, else the lens's "
                         "shipped network where it is recorded better than the deconvolution and learned this "
                         "pixel pitch; else (and where PyTorch is missing) the deconvolution"),
        ("DECONVOLUTION", "Deconvolution", "Undo the blur with the lens's own PSFs at the render's depth (numpy: "
                                           "needs no PyTorch, no training)"),
        ("NETWORK", "Network", "The lens's shipped correction network (DACN), or the Correction Model file; "
                               "needs PyTorch in Blender's Python")],
        description="Correct Simulation: how the lens's blur is undone")
    correction_model: StringProperty(name="Correction Model", default="", subtype="FILE_PATH",
                                     description="Correct Simulation's network: a DACN exported with `dcdi dacn "
                                                 "export` (.npz) or a training run folder; empty: the lens's "
                                                 "shipped network")


def _preview_toggled(status, context):
    viewport.toggle_update(status, context)


class DCDI_LensBokehStatus(bpy.types.PropertyGroup):
    """What the running (or last) Apply Lens Bokeh is doing; not saved."""

    running: BoolProperty(default=False)
    progress: FloatProperty(name="Progress", default=0.0, min=0.0, max=100.0, subtype="PERCENTAGE")
    message: StringProperty(default="")
    job: StringProperty(default="", description="The job the message is about (Lens Bokeh, Lens Simulation, "
                                                "Lens Correction)")
    inputs: StringProperty(default="", description="The settings and camera the last job ran with "
                                                   "(reading.inputs_key): its status shows while they are unchanged")
    psf_source: StringProperty(default="", description="Where the last bokeh's PSFs came from, and why (the "
                                                       "engine's words: the status line's tooltip)")
    psf_words: StringProperty(default="", description="Where the last job's blur came from, in the panel's "
                                                      "words (logic.source_words)")
    correction: StringProperty(default="", description="The method the last Correct Simulation ran, why, and "
                                                      "its time")
    render_message: StringProperty(default="", description="What Lens in Renders did in the last render")
    viewport_preview: BoolProperty(name="Preview in Viewport", default=False, update=_preview_toggled,
                                   description="Draw the lens's result over the 3D viewport's camera view at the "
                                               "Preview Size, refreshed when the camera, focus, lens or scene "
                                               "changes (a low-sample render, then the lens on a worker thread)")


CLASSES = (DCDI_LensBokehSettings, DCDI_LensBokehStatus)


def register_properties():
    bpy.types.Scene.dcdi_lens_bokeh = PointerProperty(type=DCDI_LensBokehSettings)
    bpy.types.WindowManager.dcdi_lens_bokeh_status = PointerProperty(type=DCDI_LensBokehStatus)


def unregister_properties():
    del bpy.types.WindowManager.dcdi_lens_bokeh_status
    del bpy.types.Scene.dcdi_lens_bokeh
