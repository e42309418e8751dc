"""bpy helpers: render a camera all-in-focus with planar depth without
touching the user's scene, and put float pixels into an image.

The render runs in a temporary copy of the scene (``Scene.copy()`` links the
same objects, world and collections; render settings, view layers and the
compositor setting are the copy's own) through a temporary copy of the
camera with depth of field off, so the user's scene, render settings and
camera are untouched by construction; the copies are removed afterwards,
also when the render fails. Pixels come back through an uncompressed
multilayer EXR read with numpy (``dcdi_core.io.rawexr``): Blender's image API
exposes only a multilayer file's first pass to Python, and the PyPI
OpenImageIO clashes with Blender's.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import bpy
import numpy as np

from dcdi_core import app


RESULT_IMAGE = "Lens Bokeh"
RESULT_IMAGE_RENDER = "Lens Render"     # a rendered frame through the lens (Lens in Renders)


def set_light_paths(cycles, max_bounces: int = 4, diffuse: int = 2, glossy: int = 2, transmission: int = 2) -> None:
    """Cycles light paths for many clean images fast: few bounces, no caustics,
    no volume bounces; light tree and adaptive sampling off (measured in the
    factory at 480 x 640, 8 samples: 10-15 % faster, same PSNR)."""
    cycles.max_bounces = max_bounces
    cycles.diffuse_bounces = diffuse
    cycles.glossy_bounces = glossy
    cycles.transmission_bounces = transmission
    cycles.volume_bounces = 0
    cycles.caustics_reflective = False
    cycles.caustics_refractive = False
    for name in ("use_light_tree", "use_adaptive_sampling"):       # absent in older Blenders
        if hasattr(cycles, name):
            setattr(cycles, name, False)


def has_denoiser() -> bool:
    """Whether Cycles was built with OpenImageDenoise (Debian's 3.4 was not;
    its ``bpy.app.build_options`` does not say)."""
    try:
        import _cycles
        return bool(_cycles.with_openimagedenoise)
    except (ImportError, AttributeError):
        return bool(getattr(bpy.app.build_options, "openimagedenoise", True))


def set_cycles_preview(scene, samples: int, seed: int = 0) -> None:
    """Cycles on the CPU with few bounces: a quick, clean preview (the same
    light-path budget as the dataset factory, measured there)."""
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = samples
    c.seed = seed
    # the denoiser needs OpenImageDenoise, which some builds lack (Debian's 3.4):
    # render_aif_depth retries without it when the render says so
    c.use_denoising = has_denoiser() and samples > 1
    set_light_paths(c)
    set_area_pixel_filter(c)


def set_area_pixel_filter(cycles) -> None:
    """Each pixel the average of the scene over its own area (a 1-px box), as
    a sensor pixel integrates: the PSF kernels are built for such an image
    (dcdi_core/psf/deposit.py). Cycles' default, a 1.5-px Blackman-Harris,
    is a different pixel aperture."""
    cycles.pixel_filter_type = "BOX"
    cycles.filter_width = 1.0


def set_multilayer_exr(image_settings) -> None:
    """32-bit float multilayer EXR, uncompressed (what rawexr reads)."""
    if hasattr(image_settings, "media_type"):           # Blender 5 groups formats by media type
        image_settings.media_type = "MULTI_LAYER_IMAGE"
    image_settings.file_format = "OPEN_EXR_MULTILAYER"
    image_settings.color_depth = "32"
    image_settings.exr_codec = "NONE"


def render_aif_depth(scene, camera_obj, height: int, width: int, samples: int, view_layer_name: str | None = None,
                     seed: int = 0):
    """Render ``camera_obj`` in ``scene`` all-in-focus at height x width px
    (``seed``: Cycles' noise pattern; renders of other seeds average).

    Returns (image (H, W, 3) float32 linear scene-referred RGB, z (H, W)
    float32 planar distance from the camera in scene units; 1e10 for the
    world background)."""
    tmp_scene = scene.copy()
    tmp_scene.name = "dcdi-lens-bokeh-render"
    settings = getattr(tmp_scene, "dcdi_lens_bokeh", None)
    if settings is not None:
        # the copy carries Lens in Renders: off, or the render hook would put this internal render
        # through the lens too (a render window, a second lens stage, the user's Lens Render replaced)
        settings.lens_in_renders = False
    cam_data = camera_obj.data.copy()
    cam_obj = bpy.data.objects.new("dcdi-lens-bokeh-camera", cam_data)
    workdir = Path(tempfile.mkdtemp(prefix="dcdi-lens-bokeh-"))
    out = workdir / "render.exr"
    try:
        cam_data.dof.use_dof = False                    # all in focus: the lens adds the blur
        cam_obj.matrix_world = camera_obj.matrix_world.copy()
        tmp_scene.collection.objects.link(cam_obj)
        tmp_scene.camera = cam_obj
        r = tmp_scene.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
        r.use_border = False
        r.film_transparent = False
        r.use_motion_blur = False
        r.use_compositing = False                       # the raw passes, not the user's compositor output
        r.use_sequencer = False
        if hasattr(r, "use_single_layer"):
            r.use_single_layer = False
        for vl in tmp_scene.view_layers:
            vl.use_pass_z = True
        set_cycles_preview(tmp_scene, samples, seed)
        set_multilayer_exr(r.image_settings)
        r.use_file_extension = False
        r.filepath = str(out)
        try:
            bpy.ops.render.render(write_still=True, scene=tmp_scene.name)
        except RuntimeError as e:
            if "denois" not in str(e).lower() or not tmp_scene.cycles.use_denoising:
                raise
            tmp_scene.cycles.use_denoising = False
            bpy.ops.render.render(write_still=True, scene=tmp_scene.name)
        if not out.exists():
            raise RuntimeError(f"Cycles wrote no file to {out} (see the console)")
        ch = app.rawexr.read_exr_channels(out)
    finally:
        bpy.data.scenes.remove(tmp_scene)
        bpy.data.objects.remove(cam_obj)
        bpy.data.cameras.remove(cam_data)
        for p in workdir.glob("*"):
            p.unlink()
        os.rmdir(workdir)
    layers = [k[: -len(".Depth.Z")] for k in ch if k.endswith(".Depth.Z")]
    name = view_layer_name if view_layer_name in layers else (layers[0] if layers else None)
    if name is None or f"{name}.Combined.R" not in ch:
        raise RuntimeError(f"the render has no Combined + Depth passes (channels: {sorted(ch)[:8]}...)")
    rgb = np.stack([ch[f"{name}.Combined.{c}"] for c in "RGB"], axis=-1).astype(np.float32)
    return rgb, ch[f"{name}.Depth.Z"].astype(np.float32)


RECORD_PROPERTY = "dcdi_capture"     # the image's custom property holding its capture record (JSON)


def put_image(name: str, rgb: np.ndarray, record=None):
    """Write (H, W, 3) float32 linear RGB into the float image ``name``
    (created, or recreated when the size differs); returns the image.
    ``record``: how it was made (``io.capture_record.CaptureRecord``), kept
    as the image's custom property ``dcdi_capture`` (JSON; removed when
    None), which the .blend file saves with it."""
    h, w = rgb.shape[:2]
    img = bpy.data.images.get(name)
    if img is not None and (tuple(img.size) != (w, h) or not img.is_float):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    rgba = np.empty((h, w, 4), np.float32)
    rgba[..., :3] = rgb[::-1]                           # Blender's rows run bottom to top
    rgba[..., 3] = 1.0
    img.pixels.foreach_set(rgba.ravel())
    img.update()
    if record is not None:
        img[RECORD_PROPERTY] = record.as_json()
    elif RECORD_PROPERTY in img:
        del img[RECORD_PROPERTY]
    return img


def save_as_frame(rgb: np.ndarray, path: str, scene) -> None:
    """Write (H, W, 3) float32 linear RGB to ``path`` as Blender writes a
    rendered frame of ``scene``: its output format, colour depth and colour
    management (through the image "Lens Render")."""
    img = put_image(RESULT_IMAGE_RENDER, rgb)
    img.save_render(filepath=path, scene=scene)


def get_image(name: str) -> np.ndarray:
    """(H, W, 3) float32 RGB of image ``name``, rows top to bottom."""
    img = bpy.data.images[name]
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    return px.reshape(h, w, 4)[::-1, :, :3].copy()


def show_in_image_editor(context, image) -> bool:
    """Show ``image`` in an open Image Editor; if none is open, open Blender's
    render view (a window or area, as the user's preferences say) and show it
    there. False when there is no UI (background mode)."""
    wm = context.window_manager
    if bpy.app.background or context.window is None or not wm.windows:
        return False                                    # no UI (background, pip bpy, a script without window)
    for _ in range(2):
        for window in wm.windows:
            for area in window.screen.areas:
                if area.type == "IMAGE_EDITOR":
                    area.spaces.active.image = image
                    area.tag_redraw()
                    return True
        try:
            bpy.ops.render.view_show("INVOKE_DEFAULT")
        except RuntimeError:
            return False
    return False
