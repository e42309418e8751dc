"""The all-in-focus render of a Blender recipe's frame: the Cycles settings
(``RenderSettings``, recorded in dataset.json and every manifest line),
the scene set up for them through a lens's pinhole camera
(``setup_render``), and the frame rendered and read back as linear RGB and
metric depth (``render_rgbd``), with a stop while Blender works held until
Blender returns."""
from __future__ import annotations

import signal
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .blender import denoiser_available
from .meters import cpu_seconds


@dataclass(frozen=True)
class RenderSettings:
    """Cycles settings of the all-in-focus render (CPU). The defaults come from
    the error-against-time tables of ``python -m blender_addon.tools.render_noise``
    (docs/factory.md): samples per pixel; the Open Image Denoise pass (quality HIGH,
    BALANCED or FAST; prefilter of its albedo and normal guides NONE, FAST or
    ACCURATE), or none, and why (``no_denoise_reason``: --no-denoise, or a
    Blender without the denoiser); light-path bounces (counts)."""

    samples: int = 8
    denoise: bool = True
    # on the textured scenes at 8 samples (render_noise table, docs/factory.md): BALANCED with the FAST
    # prefilter 36.6 dB against 128 samples in 5.6 s; HIGH without a prefilter (the former default)
    # 35.2 dB in 6.4 s: fine texture makes the albedo guide noisy, and the prefilter cleans it
    denoising_quality: str = "BALANCED"
    denoising_prefilter: str = "FAST"
    max_bounces: int = 4
    diffuse_bounces: int = 2
    glossy_bounces: int = 2
    transmission_bounces: int = 2
    # why the frames are not denoised: "--no-denoise", or blender.NO_DENOISER (this Blender has no
    # OpenImageDenoise); None when they are. Recorded, not compared: render.denoise is
    no_denoise_reason: str | None = None

    def __post_init__(self):
        if not (isinstance(self.samples, int) and 1 <= self.samples <= 65536):
            raise ValueError(f"render samples must be an integer in [1, 65536], got {self.samples!r}")
        if self.denoising_quality not in ("HIGH", "BALANCED", "FAST"):
            raise ValueError(f"denoising quality must be HIGH, BALANCED or FAST, got {self.denoising_quality!r}")
        if self.denoising_prefilter not in ("NONE", "FAST", "ACCURATE"):
            raise ValueError(f"denoising prefilter must be NONE, FAST or ACCURATE, got {self.denoising_prefilter!r}")
        for name in ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces"):
            v = getattr(self, name)
            if not (isinstance(v, int) and 0 <= v <= 1024):
                raise ValueError(f"{name.replace('_', ' ')} must be an integer in [0, 1024], got {v!r}")

    def as_dict(self) -> dict:
        """The settings as recorded (dataset.json, the manifest): the reason
        for undenoised frames only where they are undenoised."""
        d = asdict(self)
        if d["no_denoise_reason"] is None:
            del d["no_denoise_reason"]
        return d



def setup_render(scene, lens, height: int, width: int, render: RenderSettings, seed: int):
    """All-in-focus Cycles render on the CPU through the lens's pinhole
    camera (dcdi_core.render.camera: at the entrance pupil, paraxial focal
    length, the image spanning the sensor diagonal); returns that
    PinholeCamera."""
    import bpy

    from blender_addon.bpy_render import set_area_pixel_filter, set_light_paths, set_multilayer_exr
    from dcdi_core.render.camera import PinholeCamera

    pinhole = PinholeCamera.for_lens(lens, height, width)
    cam = bpy.data.cameras.new("lens")
    for name, value in pinhole.blender_camera_settings().items():
        setattr(cam, name, value)
    cam.dof.use_dof = False
    cam.clip_start = 0.01
    cam.clip_end = 1.0e5
    obj = bpy.data.objects.new("lens", cam)
    scene.collection.objects.link(obj)
    scene.camera = obj
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = render.samples
    c.seed = seed
    c.use_denoising = render.denoise
    if render.denoise:
        if not denoiser_available(scene):
            from dcdi_core.errors import RenderError
            raise RenderError(f"this Blender ({bpy.app.version_string}) has no OpenImageDenoise: render "
                              "undenoised (RenderSettings(denoise=False), the factory's --no-denoise) or use a "
                              "Blender that has it (blender.org's, or the pip bpy module)")
        c.denoiser = "OPENIMAGEDENOISE"
    c.denoising_quality = render.denoising_quality
    c.denoising_prefilter = render.denoising_prefilter
    # a dataset wants many clean images fast: few bounces, no caustics (render_noise's table)
    set_light_paths(c, render.max_bounces, render.diffuse_bounces, render.glossy_bounces,
                    render.transmission_bounces)
    set_area_pixel_filter(c)
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_layers[0].use_pass_z = True
    # the file is a hand-over read back at once and deleted: no compression (measured: no gain, no cost)
    set_multilayer_exr(scene.render.image_settings)
    return pinhole


def empty_scene() -> None:
    """Start each sample from Blender's factory startup file, emptied: the
    same scene settings whatever came before. ``read_homefile`` and not
    ``read_factory_settings``: the latter also resets the preferences and so
    unregisters and re-registers every add-on, which costs 0.05 s a sample
    and, in distributions' builds whose bundled add-ons fail to register
    (Debian's 5.2: bl_pkg without ``cattrs``), prints their traceback for
    every sample."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)


def render_rgbd(recipe: str, lens, seed: int, height: int, width: int, render: RenderSettings, tmp: Path,
                timings: dict | None = None, *, textures=None, scene_info: dict | None = None):
    """Build the scene, render; returns (image (H, W, 3) float32 linear,
    depth (H, W) float32 metres from the lens's first vertex, inf = background).
    ``timings``, if given, receives the wall seconds of each stage: "scene"
    (reset and recipe), "render" (Cycles: sync, BVH, path tracing, denoising,
    the EXR hand-over file), "read" (reading that file back), and their CPU
    seconds as "cpu_scene", "cpu_render", "cpu_read". ``textures``: a
    TextureLibrary for a share of the surfaces; ``scene_info``, if given,
    receives what the scene holds (objects placed, materials by kind, the
    texture sets used).

    A SIGINT or SIGTERM while Blender works (scene and render) stops the job
    once Blender returns (``signals.deferred``: Blender runs Python of its
    own, Cycles' engine and the handlers, and drops an exception raised
    there); the hand-over file ``tmp`` is removed whatever happens."""
    import bpy

    from dcdi_core.io.images import read_depth, read_image
    from dcdi_core.render.camera import depth_from_planar_z
    from dcdi_core.signals import deferred
    from scenes.recipes import build

    t, c = [time.perf_counter()], [cpu_seconds()]
    try:
        with deferred():
            empty_scene()
            scene = bpy.context.scene
            builder = build(recipe, np.random.default_rng(seed), textures)
            if scene_info is not None:
                scene_info.update(scene_summary(builder))
            pinhole = setup_render(scene, lens, height, width, render, seed)
            scene.render.filepath = str(tmp)
            t.append(time.perf_counter()), c.append(cpu_seconds())
            render_still(tmp)
            t.append(time.perf_counter()), c.append(cpu_seconds())
        img = read_image(tmp)
        z = read_depth(tmp)
    finally:
        tmp.unlink(missing_ok=True)        # read, or left behind by a stop or a failure
    t.append(time.perf_counter()), c.append(cpu_seconds())
    if timings is not None:
        timings.update(scene=t[1] - t[0], render=t[2] - t[1], read=t[3] - t[2])
        timings.update({"cpu_" + k: c[i + 1] - c[i] for i, k in enumerate(("scene", "render", "read"))})
    return img, depth_from_planar_z(z, pinhole.entrance_pupil_mm)


def render_still(path: Path) -> None:
    """Render the current scene's frame; Blender writes it to ``path``.
    Raises ``Stopped`` (SIGINT) when Blender's own break event cancelled the
    render (Ctrl-C reaching Blender's handler, where the factory could not
    take SIGINT: Blender then writes no file), and RenderError when Blender
    finished without writing the file."""
    import bpy

    from dcdi_core.errors import RenderError
    from dcdi_core.signals import Stopped
    cancelled = []

    def on_cancel(*_):
        cancelled.append(True)
    bpy.app.handlers.render_cancel.append(on_cancel)
    try:
        bpy.ops.render.render(write_still=True)
    finally:
        bpy.app.handlers.render_cancel.remove(on_cancel)
    if cancelled:
        raise Stopped(signal.SIGINT)
    if not path.is_file():
        raise RenderError(f"{path}: Blender finished the render but wrote no file (see its messages above: "
                          "a full disk?)")


def scene_summary(builder) -> dict:
    """The manifest's short account of a built scene."""
    kinds: dict[str, int] = {}
    for r in builder.records:
        kinds[r.get("kind", "?")] = kinds.get(r.get("kind", "?"), 0) + 1
    sets = sorted({r["set"] for r in builder.records if "set" in r})
    return {"objects": builder.objects, "materials": dict(sorted(kinds.items())), "texture_sets": sets}

