"""Lens in Renders: every frame Blender renders (F12, an animation, `blender
--background -f / -a`) through the chosen lens, from the frame's Combined
and Z passes.

How a frame gets the lens, in the handlers' order:

- ``render_init``: the settings the lens needs are set for this render and
  their former values kept: the Z pass on every view layer, the cameras'
  own depth of field off (the lens adds the blur), the interface locked
  (the handlers read the scene while Blender renders), and a compositor of
  ours in place of the scene's, which writes Combined and Depth (and every
  pass the scene's compositor reads) to 32-bit EXRs in a temporary folder
  and passes Combined through unchanged. Where the scene's compositor
  changes the frame, a copy of it is handed to a helper Blender
  (``compositor``), started now.
- ``frame_change_post`` (animations): the frame's focus from the render's
  own evaluated data, so an animated focus distance, focus object or
  camera is followed frame by frame.
- ``render_post``: the lens on the passes (``logic.lens_frame``: the
  bokeh, or the whole lens), the PSFs kept for the next frame with the same
  focus; then the scene's compositor on the lens's frame (the helper), so
  that glare, grading or any node of the user's applies to what the lens
  made; a still's result goes to the image "Lens Render".
- ``render_write``: the lens's frame written over the file Blender just
  wrote, in the scene's format and colour management.
- ``render_complete`` / ``render_cancel``: every changed setting restored,
  our compositor and temporary files removed.

Movie outputs are refused (Blender streams those frames as it renders):
the status line says to render an image sequence. A compositor that cannot
be kept (Render Layers inside a node group, no Blender to run it in) is
said in the render line and the console: the frame is then the lens's
without it.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np
from bpy.app.handlers import persistent

from dcdi_core import app

from . import bpy_render, compositor, logic, reading
from .session import SESSION

RESULT_IMAGE = bpy_render.RESULT_IMAGE_RENDER
GROUP = "dcdi-lens-passes"
MIN_BLENDER = (5, 0, 0)          # scene.compositing_node_group, File Output's file_output_items


class _LensRender:
    """One render through the lens: what was changed (to restore), where
    the passes land, the focus of each frame, and what was done."""

    def __init__(self, scene):
        self.scene_name = scene.name
        self.started_ns = time.time_ns() - 2_000_000_000      # files written from here on (coarse mtimes)
        self.saved: list = []                 # (owner, attribute, former value)
        self.group = None
        self.passes_dir = Path(tempfile.mkdtemp(prefix="dcdi-lens-render-"))
        self.focus_by_frame: dict[int, tuple] = {}      # frame: (focus, kept range), metres
        self.results: dict[int, np.ndarray] = {}
        self.frames: list[dict] = []          # per frame: frame, focus, keep, seconds, PSF source
        self.error: str | None = None
        self.lens = self.lens_path = None
        self.layer = ""                       # the view layer the lens reads (the active one)
        self.sources: list[compositor.Source] = []     # the view layers whose passes are written
        self.compositor: compositor.Compositor | None = None
        self.compositor_note = ""             # why the scene's compositor is not applied ("": kept, or none)

    def set(self, owner, attribute: str, value) -> None:
        """``owner.attribute = value``, the former value kept for restore()."""
        self.saved.append((owner, attribute, getattr(owner, attribute)))
        setattr(owner, attribute, value)

    def restore(self) -> None:
        for owner, attribute, value in reversed(self.saved):
            try:
                setattr(owner, attribute, value)
            except (ReferenceError, AttributeError, TypeError):
                pass                          # the owner was deleted during the render
        self.saved.clear()
        if self.compositor is not None:
            self.compositor.stop()
            self.compositor = None
        if self.group is not None:
            try:
                bpy.data.node_groups.remove(self.group)
            except ReferenceError:
                pass
            self.group = None
        shutil.rmtree(self.passes_dir, ignore_errors=True)


# the render in progress (one at a time, as Blender renders one at a time) is
# the session's ``render_run``; what the last render through the lens did, for
# the panel and for scripts, its ``last_render``


def _status(text: str) -> None:
    wm = bpy.context.window_manager if bpy.context else None
    st = getattr(wm, "dcdi_lens_bokeh_status", None)
    if st is not None:
        st.render_message = text[:400]


def blocker(scene) -> str | None:
    """Why a render of ``scene`` cannot get the lens, or None."""
    if tuple(bpy.app.version) < MIN_BLENDER:
        return (f"Lens in Renders needs Blender {'.'.join(map(str, MIN_BLENDER))} or newer "
                f"(this is {bpy.app.version_string})")
    if scene.render.is_movie_format:
        return ("Lens in Renders writes image files: choose an image sequence output (EXR, PNG, ...) and "
                "encode the movie afterwards (Blender streams movie frames as it renders)")
    try:
        reading.camera(scene)
        reading.chosen_lens(scene.dcdi_lens_bokeh)
    except (logic.BokehInputError, app.errors.DcdiError) as e:
        return logic.message(e)
    return None


# ------------------------------------------------------------------ set-up and restore
def _passes_compositor(run: _LensRender, scene) -> None:
    """A compositor of ours for this render: for each view layer of
    ``run.sources``, Render Layers -> File Output (its passes, 32-bit
    uncompressed EXR in a folder of its own), and the lens's layer's
    Combined -> Group Output (the frame Blender writes, replaced later)."""
    g = bpy.data.node_groups.new(GROUP, "CompositorNodeTree")
    run.group = g
    lens_rl = None
    for i, src in enumerate(run.sources):
        rl = g.nodes.new("CompositorNodeRLayers")
        rl.scene = bpy.data.scenes[src.scene]
        rl.layer = src.layer
        fo = g.nodes.new("CompositorNodeOutputFile")
        fo.directory = str(run.passes_dir / f"layer-{i}") + os.sep
        fo.file_name = "passes"
        bpy_render.set_multilayer_exr(fo.format)
        fo.file_output_items.clear()
        for name, kind in src.passes.items():
            fo.file_output_items.new(compositor.ITEM_TYPE[kind], name)
            g.links.new(rl.outputs[name], fo.inputs[name])
        if i == 0:
            lens_rl = rl
    g.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    out = g.nodes.new("NodeGroupOutput")
    g.links.new(lens_rl.outputs["Image"], out.inputs[0])
    run.set(scene, "compositing_node_group", g)
    run.set(scene.render, "use_compositing", True)


def _sources(run: _LensRender, scene, tree) -> list:
    """The view layers whose passes this render writes: first the lens's
    (Combined and Depth), then those the scene's compositor ``tree`` reads
    (a layer of this scene also gets Combined and Depth: the lens is applied
    to it too)."""
    lens_pass = {"Image": "RGBA", "Depth": "VALUE"}
    first = compositor.Source(scene.name, run.layer, dict(lens_pass))
    out = [first]
    for src in compositor.sources(tree, scene) if tree is not None else ():
        own = src.scene == scene.name
        if (src.scene, src.layer) == (first.scene, first.layer):
            first.passes.update(src.passes)
            continue
        out.append(compositor.Source(src.scene, src.layer, {**src.passes, **(lens_pass if own else {})}))
    return out


def _keep_compositor(run: _LensRender, scene):
    """The scene's compositor tree where it is kept for this render (its
    helper started), else None (``run.compositor_note`` says why, if any)."""
    tree = compositor.user_tree(scene)
    if tree is None:
        return None
    nested = compositor.nested_render_layers(tree)
    if nested:
        run.compositor_note = (f"the scene's compositor is not applied: its node group '{nested}' reads "
                               "Render Layers (place them in the compositor itself)")
        return None
    folder = run.passes_dir / "compositor"
    folder.mkdir()
    try:
        run.compositor = compositor.Compositor.start(scene, tree, folder)
    except (RuntimeError, OSError, ValueError, KeyError) as e:
        run.compositor_note = f"the scene's compositor is not applied: {e}"
        return None
    return tree


def _start(scene) -> _LensRender:
    run = _LensRender(scene)
    try:
        first = reading.read_scene(scene)                 # the lens for this render, and the focus of its frame
        run.lens, run.lens_path = first.lens, first.lens_path
        for vl in scene.view_layers:
            run.set(vl, "use_pass_z", True)
        for cam in {o.data for o in scene.objects if o.type == "CAMERA"}:
            run.set(cam.dof, "use_dof", False)
        run.set(scene.render, "use_lock_interface", True)
        layer = bpy.context.view_layer if bpy.context.view_layer in tuple(scene.view_layers) else None
        run.layer = (layer or next((v for v in scene.view_layers if v.use), scene.view_layers[0])).name
        tree = _keep_compositor(run, scene)
        run.sources = _sources(run, scene, tree)
        _passes_compositor(run, scene)
        run.focus_by_frame[scene.frame_current] = (first.focus_m, first.keep)
    except BaseException:
        run.restore()
        raise
    return run


def _focus(scene, run: _LensRender, depsgraph) -> tuple[float, tuple[float, float]]:
    """(focus, kept range), metres from the lens's first vertex, of the
    frame ``depsgraph`` evaluates (None: the scene as it stands)."""
    r = reading.read_scene(scene, depsgraph=depsgraph, lens_path=run.lens_path)
    return r.focus_m, r.keep


def _request(scene, run: _LensRender, frame: int) -> logic.FrameRequest:
    s = scene.dcdi_lens_bokeh
    focus, keep = run.focus_by_frame.get(frame) or _focus(scene, run, None)
    r = scene.render
    size = (r.resolution_x, r.resolution_y, r.pixel_aspect_x, r.pixel_aspect_y)
    return logic.FrameRequest(s.render_effect.lower(), focus, keep, bool(s.refocus),
                              logic.lens_readout(run.lens_path)["entrance_pupil_mm"], reading.metres_per_unit(scene),
                              lens_geometry=bool(s.lens_geometry),
                              pinhole_focal_length_mm=reading.pinhole_focal_length_mm(
                                  scene.camera, size, logic.load_lens_cached(run.lens_path)))


def _read_passes(run: _LensRender) -> dict:
    """{(scene, layer): {pass: (H, W, k) array}} of the EXRs our compositor
    wrote for this frame (then removed)."""
    out = {}
    for i, src in enumerate(run.sources):
        files = sorted((run.passes_dir / f"layer-{i}").glob("*.exr"), key=lambda p: p.stat().st_mtime_ns)
        if not files:
            raise RuntimeError(f"the compositor wrote no passes of view layer '{src.layer}' for this frame (is "
                               "compositing disabled by the command line, or the render cancelled?)")
        try:
            passes = compositor.split_passes(app.rawexr.read_exr_channels(files[-1]))
        finally:
            for p in files:
                p.unlink(missing_ok=True)
        missing = sorted(set(src.passes) - set(passes))
        if missing:
            raise RuntimeError(f"the passes file of view layer '{src.layer}' lacks {', '.join(missing)} "
                               f"(it has: {', '.join(sorted(passes)[:8])})")
        out[(src.scene, src.layer)] = passes
    return out


def _lens_passes(run: _LensRender, passes: dict, req) -> tuple:
    """The lens on the Combined pass of each of the scene's layers in
    ``passes`` (in place, alpha kept): returns the lens's layer's
    (rgb, z, lens result, info)."""
    first = run.sources[0]
    result = info = None
    for src in run.sources:
        if src.scene != first.scene or "Depth" not in src.passes:
            continue                          # another scene's layer: as rendered
        layer = passes[(src.scene, src.layer)]
        rgb = np.ascontiguousarray(layer["Image"][..., :3], np.float32)
        z = layer["Depth"][..., 0].astype(np.float32)
        out, _, got = logic.lens_frame(rgb, z, run.lens, req)
        if src is first:
            result, info, first_rgb, first_z = out, got, rgb, z
        layer["Image"] = np.concatenate([out, layer["Image"][..., 3:]], axis=-1)
    return first_rgb, first_z, result, info


# ------------------------------------------------------------------ the handlers
@persistent
def on_render_init(scene, *_):
    SESSION.render_run = None
    s = getattr(scene, "dcdi_lens_bokeh", None)
    if s is None or not s.lens_in_renders:
        return
    why = blocker(scene)
    if why:
        SESSION.last_render = {"error": why, "frames": []}
        _status(f"Lens in Renders not applied: {why}")
        print(f"dcdi: Lens in Renders not applied: {why}")
        return
    try:
        SESSION.render_run = _start(scene)
    except (logic.BokehInputError, app.errors.DcdiError, RuntimeError, ValueError, OSError) as e:
        SESSION.last_render = {"error": logic.message(e), "frames": []}
        _status(f"Lens in Renders not applied: {logic.message(e)}")
        print(f"dcdi: Lens in Renders not applied: {logic.message(e)}")
        return
    if SESSION.render_run.compositor_note:
        print(f"dcdi: Lens in Renders: {SESSION.render_run.compositor_note}")
    _status("Lens in Renders: rendering...")


@persistent
def on_frame_change(scene, depsgraph=None):
    run = SESSION.render_run
    if run is None or depsgraph is None or depsgraph.mode != "RENDER" or scene.name != run.scene_name:
        return
    try:
        run.focus_by_frame[scene.frame_current] = _focus(scene, run, depsgraph)
    except (logic.BokehInputError, app.errors.DcdiError) as e:
        run.error = logic.message(e)


@persistent
def on_render_post(scene, *_):
    run = SESSION.render_run
    if run is None or scene.name != run.scene_name:
        return
    frame = scene.frame_current
    t0 = time.perf_counter()
    try:
        passes = _read_passes(run)
        req = _request(scene, run, frame)
        rgb, z, out, info = _lens_passes(run, passes, req)
        if run.compositor is not None:
            out = _composite(run, frame, passes, out)
    except (logic.BokehInputError, app.errors.DcdiError, RuntimeError, ValueError, OSError) as e:
        run.error = f"frame {frame}: {logic.message(e)}"
        print(f"dcdi: Lens in Renders: {run.error}; the frame is left as rendered")
        _status(f"Lens in Renders failed: {run.error}")
        return
    seconds = time.perf_counter() - t0
    run.results = {frame: out}               # one frame held at a time
    run.frames.append({"frame": frame, "focus_m": req.focus_m, "focus_used_m": info.get("focus_used_m", req.focus_m),
                       "keep_m": list(req.keep), "effect": req.effect,
                       "seconds": seconds, "psf_source": info.get("psf_source"),
                       "focus_note": info.get("focus_note", ""), "clipped": info.get("clipped"),
                       "compositor": "applied" if run.compositor is not None else run.compositor_note or None})
    SESSION.last_render = {"frames": run.frames, "error": run.error, "last_image": out, "last_passes": (rgb, z)}
    # a kernel left clipping the blur (no large blur answered it) is said in the render line, not only the console
    clipped = f"; blur clipped: {info['clipped'].split(': ', 1)[-1]}" if info.get("clipped") else ""
    camera_m = req.focus_m + req.entrance_pupil_mm / 1000.0        # from the camera, as the panel's Distance
    comp = "; compositor applied after the lens" if run.compositor is not None else ""
    note = f"; {run.compositor_note}" if run.compositor_note else ""
    _status(f"Lens in Renders: frame {frame}, focus {camera_m:.2f} m, lens {seconds:.1f} s{comp}{clipped}{note}")
    if bpy.app.background:
        bpy_render.put_image(RESULT_IMAGE, out)
    else:                                    # images are made on the main thread
        bpy.app.timers.register(lambda out=out: _show(out), first_interval=0.0)


def _composite(run: _LensRender, frame: int, passes: dict, lens_out: np.ndarray) -> np.ndarray:
    """The scene's compositor on the lens's passes: the frame's RGB. Where
    it fails, the lens's frame without it (said in the render line)."""
    try:
        return run.compositor.composite(frame, passes)[..., :3]
    except (RuntimeError, OSError, ValueError) as e:
        run.compositor_note = f"the scene's compositor is not applied: {e}"
        print(f"dcdi: Lens in Renders: frame {frame}: {run.compositor_note}")
        run.compositor.stop()
        run.compositor = None
        return lens_out


def _show(out):
    img = bpy_render.put_image(RESULT_IMAGE, out)
    bpy_render.show_in_image_editor(bpy.context, img)
    return None


@persistent
def on_render_write(scene, *_):
    run = SESSION.render_run
    if run is None or scene.name != run.scene_name:
        return
    out = run.results.pop(scene.frame_current, None)
    if out is None:
        return                               # the lens failed on this frame: left as rendered
    path = _written_path(scene, run)
    if path is None:
        run.error = f"frame {scene.frame_current}: cannot find the file Blender wrote"
        print(f"dcdi: Lens in Renders: {run.error}")
        return
    try:
        bpy_render.save_as_frame(out, path, scene)
    except (RuntimeError, OSError) as e:
        run.error = f"frame {scene.frame_current}: cannot write {path}: {e}"
        print(f"dcdi: Lens in Renders: {run.error}")


def _written_path(scene, run: _LensRender) -> str | None:
    """The file Blender wrote for this frame: an animation's frame path, or
    a still's output path (no frame number); the one written during this
    render, the newest if both were."""
    r = scene.render
    still = bpy.path.abspath(r.filepath)
    if r.use_file_extension and not still.lower().endswith(r.file_extension.lower()):
        still += r.file_extension
    found = [(os.stat(p).st_mtime_ns, p) for p in {r.frame_path(frame=scene.frame_current), still}
             if os.path.isfile(p) and os.stat(p).st_mtime_ns >= run.started_ns]
    return max(found)[1] if found else None


@persistent
def on_render_end(scene, *_):
    run, SESSION.render_run = SESSION.render_run, None
    if run is None:
        return
    run.restore()
    n = len(run.frames)
    if run.error:
        _status(f"Lens in Renders: {n} frame(s), last error: {run.error}")
    elif n:
        total = sum(f["seconds"] for f in run.frames)
        _status(f"Lens in Renders: {n} frame(s), lens {total:.1f} s in all")


HANDLERS = (("render_init", on_render_init), ("frame_change_post", on_frame_change),
            ("render_post", on_render_post), ("render_write", on_render_write),
            ("render_complete", on_render_end), ("render_cancel", on_render_end))


def register() -> None:
    """Add the handlers; the session takes them back (``SESSION.clear()``,
    which also ends a render in progress, its settings restored)."""
    for name, fn in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if fn not in handlers:
            handlers.append(fn)
    SESSION.hold("render", _remove_handlers)


def _remove_handlers() -> None:
    for name, fn in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        # a reloaded module's functions are new objects: remove ours by name too
        for h in [h for h in handlers if h is fn or getattr(h, "__qualname__", "") == fn.__qualname__
                  and getattr(h, "__module__", "") == fn.__module__]:
            handlers.remove(h)
