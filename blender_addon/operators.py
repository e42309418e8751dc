"""Operators: Apply Lens Bokeh, Simulate Minimalist Lens, Correct Simulation,
Match Camera to Lens, Import Zemax File.

Apply Lens Bokeh renders the active camera all-in-focus with depth (Cycles,
preview resolution, in a temporary scene copy), then applies the lens's
depth-aware bokeh with dcdi_core and shows the image "Lens Bokeh" (linear
float) in the Image Editor. In the UI (invoke) the render runs first, in the
preview's render worker (a second Blender, ``render_worker``) where it runs,
else on the main thread (about a second at the default preview size); the
PSF build and the convolution run on a worker thread while a modal timer
shows progress, Esc cancels. In background mode, and when called from a
script with execute(), it all runs synchronously.

Simulate Minimalist Lens renders the same way and shows the render as the
chosen lens (as prescribed) would have taken it ("Lens Simulation",
dcdi_core's depth-aware simulation); Correct Simulation undoes the lens's
blur on that image with the render's depth on the sensor ("Lens
Corrected"): by deconvolution with the lens's own PSFs (numpy, no torch
needed) or with a trained DACN where torch imports (the panel's Method;
Auto follows the engine's rule). Both run as Apply Lens Bokeh does
(worker thread, progress, Esc), and one job runs at a time.
"""
import os
import threading
import time

import bpy
from bpy.props import BoolProperty, StringProperty

from dcdi_core import app

from . import bpy_render, logic, reading, viewport
from .session import SESSION

AIF_IMAGE = "Lens Bokeh AiF"
RENDER_WAIT_S = 60.0         # the longest a job waits for the render worker before rendering on the main thread
DEPTH_IMAGE = "Lens Bokeh Depth"


def _user_errors():
    """Errors whose message is meant for the user (shown as is)."""
    return (logic.BokehInputError, app.errors.DcdiError, ValueError, OSError, RuntimeError)


# how the last job's sharp render came ("kept": the preview's; "worker": the preview's render worker, a
# second Blender; "main": this Blender's main thread), with its seconds: for the status and the UI tests
LAST_RENDER: dict = {}


def render_inputs(context, scene_reading: "reading.SceneReading", rendered=None, render_size: bool = False):
    """The active camera rendered all-in-focus at the preview size: (rgb,
    depth in metres from the lens's first vertex, seconds, how). The viewport
    preview's render where it is the scene's now (``viewport.kept_render``):
    no render then, nothing on the main thread; ``rendered``: (rgb, planar
    Z, seconds) the render worker made for this job (:func:`ask_render`);
    else rendered here, on the main thread. ``render_size``: at the scene's
    render resolution (Apply at Render Size), not the preview's."""
    r = scene_reading
    h, w = r.job_shape(render_size)
    t0 = time.perf_counter()
    kept = None if render_size else viewport.kept_render(context)
    if kept is not None:
        (rgb, z), how = kept, "kept"
    elif rendered is not None:
        rgb, z, seconds = rendered
        how = "worker"
    else:
        rgb, z = bpy_render.render_aif_depth(context.scene, r.camera, h, w, r.samples, context.view_layer.name)
        how = "main"
    depth = app.camera.depth_from_planar_z(z, r.entrance_pupil_mm, r.metres_per_unit)
    seconds = rendered[2] if how == "worker" else time.perf_counter() - t0
    LAST_RENDER.clear()
    LAST_RENDER.update(how=how, seconds=seconds)
    return rgb, depth, seconds, how


def ask_render(context, render_size: bool = False):
    """Ask the preview's render worker (a second Blender, ``render_worker``)
    for this job's sharp render, so that the main thread does not hold
    Blender for it: the request (``done``, then ``rgb``, ``z`` or
    ``error``), 'busy' while the worker renders for the preview, or None
    where it cannot (background, no worker running, the preview's render
    is current: none is needed)."""
    if bpy.app.background or (not render_size and viewport.kept_render(context) is not None):
        return None
    worker = viewport.preview().worker_renders
    if not (worker.alive() and worker.ready.is_set()):
        return None
    if worker.busy():
        return "busy"
    r = reading.read_scene(context.scene)
    h, w = r.job_shape(render_size)
    try:
        return worker.request(context, context.scene, r.camera, h, w, r.samples, context.view_layer.name)
    except (RuntimeError, OSError):
        return None


def _render_words(job) -> str:
    """How a job's sharp render came: 'render 1.2 s', or the preview's kept."""
    how = job.get("render_how")
    if how == "kept":
        return "the preview's render"
    return f"render {job['render_s']:.1f} s" + (" in a second Blender" if how == "worker" else "")


def prepare(context, rendered=None):
    """Check the settings, render AiF + depth (``render_inputs``: at the
    render's size where Apply at Render Size asks); returns the bokeh job's inputs."""
    r = reading.read_scene(context.scene)
    rgb, depth, seconds, how = render_inputs(context, r, rendered, context.scene.dcdi_lens_bokeh.apply_render_size)
    return {"rgb": rgb, "depth": depth, "lens": r.lens, "focus_m": r.focus_m, "keep": r.keep,
            "refocus": r.refocus, "render_s": seconds, "render_how": how, "lens_geometry": r.lens_geometry,
            "pinhole_mm": r.pinhole_focal_length_mm}


def bokeh_of(job, **kw):
    """logic.run_bokeh on a prepared job (kw: progress, cancelled)."""
    return logic.run_bokeh(job["rgb"], job["depth"], job["lens"], focus_m=job["focus_m"], keep=job["keep"],
                           refocus=job["refocus"], lens_geometry=job["lens_geometry"],
                           pinhole_focal_length_mm=job["pinhole_mm"], **kw)


def finish(op, context, job, out, info, seconds: float, store_inputs: bool):
    img = bpy_render.put_image(bpy_render.RESULT_IMAGE, out)
    if store_inputs:
        bpy_render.put_image(AIF_IMAGE, job["rgb"])
        bpy_render.put_image(DEPTH_IMAGE, job["depth"][..., None].repeat(3, axis=-1))
    bpy_render.show_in_image_editor(context, img)
    h, w = out.shape[:2]
    st = context.window_manager.dcdi_lens_bokeh_status
    st.psf_source, st.psf_words = info["psf_source_message"], logic.source_words(info)
    note = f"; {info['focus_note']}" if info.get("focus_note") else ""
    op.report({"INFO"}, f"Lens Bokeh: {w} x {h} px, kept sharp {job['keep'][0]:.2f}-{job['keep'][1]:.2f} m "
                        f"({info['kept_pixels']} px), {_render_words(job)}, bokeh {seconds:.1f} s; "
                        f"{info['psf_source_message']}{note}")


class _Worker:
    """A job on a thread: numpy (and torch) release the GIL in their heavy
    loops, so the UI stays responsive; bpy is never touched from here.
    ``compute(progress, cancelled)`` returns the result."""

    def __init__(self, job, compute):
        self.job, self.compute = job, compute
        self.stage, self.fraction = "starting", 0.0
        self.cancel = False
        self.result = self.error = None
        self.t0 = time.perf_counter()
        self.seconds = 0.0
        self.thread = threading.Thread(target=self._run, name="dcdi-lens-job", daemon=True)

    def _progress(self, stage, fraction):
        self.stage, self.fraction = stage, fraction

    def _run(self):
        try:
            self.result = self.compute(self.job, progress=self._progress, cancelled=lambda: self.cancel)
        except logic.Cancelled:
            pass
        except Exception as e:           # handed to the main thread, which reports it
            self.error = e
        finally:
            self.seconds = time.perf_counter() - self.t0
            SESSION.jobs.discard(self)


class _JobOperator:
    """What Apply Lens Bokeh, Simulate and Correct share: check and render on
    the main thread (``prepare(context)``), the heavy part
    (``compute(job, progress=, cancelled=)``) synchronously in background
    and from execute(), else on a worker thread while a modal timer shows
    progress and Esc cancels; ``finish(context, job, result, seconds)`` puts
    the pixels back. One job runs at a time (the status says which)."""

    job_label = "Lens job"
    first_message = "rendering all-in-focus..."
    renders = False                  # its prepare renders the camera (the render worker can, off the main thread)

    def renders_at_render_size(self, context) -> bool:
        """Whether its render is at the scene's render resolution (else the preview's)."""
        return False

    @classmethod
    def poll(cls, context):
        st = getattr(context.window_manager, "dcdi_lens_bokeh_status", None)
        return st is not None and not st.running

    def execute(self, context):
        st = getattr(context.window_manager, "dcdi_lens_bokeh_status", None)
        if st is not None:               # the status is this job's from now on (the last one's is stale)
            st.job, st.inputs, st.message, st.psf_source = self.job_label, reading.inputs_key(context.scene), "", ""
            st.psf_words = ""
        t_start = time.perf_counter()
        try:
            job = self.prepare(context)
            t0 = time.perf_counter()
            result = self.compute(job)
        except _user_errors() as e:
            if st is not None:
                st.message = "failed"
            self.report({"ERROR"}, logic.message(e))
            return {"CANCELLED"}
        self.finish(context, job, result, time.perf_counter() - t0)
        if st is not None:
            st.message = f"done in {time.perf_counter() - t_start:.1f} s"
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        st = context.window_manager.dcdi_lens_bokeh_status
        st.message, st.progress = self.first_message, 0.0
        # the status is this job's from now on: its name and the settings it runs with (the last job's is stale)
        st.job, st.inputs, st.psf_source, st.psf_words = self.job_label, reading.inputs_key(context.scene), "", ""
        # the click returns at once: the status ("rendering all-in-focus...") and the released button are
        # drawn before the first timer event prepares the job (its render, where one is needed, holds the
        # main thread: with Preview in Viewport on and current, none is; see render_inputs)
        self._worker = None
        self._asked = None                   # the render worker's request for this job's render, while it runs
        self._asked_at = time.perf_counter()
        st.running = True
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        if context.workspace is not None:
            context.workspace.status_text_set(f"{self.job_label}: {self.first_message} (Esc cancels)")
        _redraw(context)
        return {"RUNNING_MODAL"}

    def _start(self, context):
        """A timer event before the job runs: its sharp render asked of the
        render worker (a second Blender: the main thread is not held) and
        waited for; then check and render (``prepare``, with that render, or
        on the main thread where the worker cannot), then the heavy part on
        its thread. Returns None, or the modal's answer where the job could
        not start."""
        st = context.window_manager.dcdi_lens_bokeh_status
        rendered = None
        try:
            if self.renders:
                if self._asked is None or self._asked == "busy":
                    waited = time.perf_counter() - self._asked_at
                    full = self.renders_at_render_size(context)
                    self._asked = ask_render(context, full) if waited < RENDER_WAIT_S else None
                    if self._asked is not None:
                        return None                 # asked (or the preview's render first): the next events wait
                elif not self._asked["done"].is_set():
                    if time.perf_counter() - self._asked["t0"] < RENDER_WAIT_S:
                        return None
                    self._asked = None              # no answer: rendered here
                elif "rgb" in self._asked:
                    rendered = (self._asked["rgb"], self._asked["z"], self._asked["seconds"])
            job = self.prepare(context, rendered) if self.renders else self.prepare(context)
        except _user_errors() as e:
            self._end(context)
            st.message = ""
            self.report({"ERROR"}, logic.message(e))
            return {"CANCELLED"}
        self._worker = _Worker(job, self.compute)
        SESSION.jobs.add(self._worker)
        self._worker.thread.start()
        return None

    def _end(self, context):
        self._ended = True
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        st = wm.dcdi_lens_bokeh_status
        st.running = False
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        _redraw(context)

    def modal(self, context, event):
        if getattr(self, "_ended", False):
            # Blender 5.2 was seen calling a finished job's modal once more (its operator invoked from a
            # timer, the next job running): ending it again would mark that next job as not running
            return {"CANCELLED"}
        w = self._worker
        st = context.window_manager.dcdi_lens_bokeh_status
        if event.type == "ESC":
            if w is not None:
                w.cancel = True
            self._end(context)
            st.message, st.progress = "cancelled", 0.0
            self.report({"WARNING"}, f"{self.job_label} cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if w is None:                        # before the job runs: the click's status is drawn by now
            answer = self._start(context)
            if answer is None and self._worker is None:
                text = f"rendering all-in-focus in a second Blender, {time.perf_counter() - self._asked_at:.0f} s"
                if text != st.message:           # redrawn once a second: the drawing's CPU goes to the render
                    st.message = text
                    _redraw(context)
            return answer or {"RUNNING_MODAL"}
        if w.thread.is_alive():
            pct = 100.0 * w.fraction
            st.progress = pct
            st.message = f"{w.stage} {pct:.0f} %, {time.perf_counter() - w.t0:.0f} s (Esc cancels)"
            context.window_manager.progress_update(int(pct))
            if context.workspace is not None:
                context.workspace.status_text_set(f"{self.job_label}: {st.message}")
            _redraw(context)
            return {"RUNNING_MODAL"}
        self._end(context)
        if w.error is not None:
            st.message = "failed"
            self.report({"ERROR"}, logic.message(w.error))
            return {"CANCELLED"}
        st.progress, st.message = 100.0, f"done in {w.job.get('render_s', 0.0) + w.seconds:.1f} s"
        self.finish(context, w.job, w.result, w.seconds)
        return {"FINISHED"}


class DCDI_OT_apply_lens_bokeh(_JobOperator, bpy.types.Operator):
    """Render the active camera all-in-focus with depth and apply the chosen lens's depth of field"""

    bl_idname = "dcdi.apply_lens_bokeh"
    bl_label = "Apply Lens Bokeh"
    bl_options = {"REGISTER"}
    job_label = "Lens Bokeh"

    store_inputs: BoolProperty(name="Keep Inputs", default=False, options={"SKIP_SAVE"},
                               description=f"Also keep the all-in-focus render ({AIF_IMAGE!r}) and the depth in "
                                           f"metres ({DEPTH_IMAGE!r}) as images")

    renders = True

    def renders_at_render_size(self, context) -> bool:
        return bool(context.scene.dcdi_lens_bokeh.apply_render_size)

    def prepare(self, context, rendered=None):
        return prepare(context, rendered)

    def compute(self, job, **kw):
        return bokeh_of(job, **kw)

    def finish(self, context, job, result, seconds):
        out, info = result
        finish(self, context, job, out, info, seconds, self.store_inputs)


# ------------------------------------------------------------------ the DCDI round trip
SIMULATION_IMAGE = "Lens Simulation"
CORRECTED_IMAGE = "Lens Corrected"
# the last simulation (render, simulated image, depth and geometry on the
# sensor, lens, whether it has sensor noise), which Correct works on, is the
# session's (SESSION.simulation: in memory only, dropped at unregister)


def prepare_simulation(context, rendered=None):
    """Check the settings and render AiF + depth for Simulate (``render_inputs``)."""
    r = reading.read_scene(context.scene, focus=False)
    rgb, depth, seconds, how = render_inputs(context, r, rendered)
    return {"rgb": rgb, "depth": depth, "lens": r.lens, "noise": bool(context.scene.dcdi_lens_bokeh.sensor_noise),
            "render_s": seconds, "render_how": how, "pinhole_mm": r.pinhole_focal_length_mm}


class DCDI_OT_simulate_lens(_JobOperator, bpy.types.Operator):
    """Render the active camera all-in-focus with depth and show it as the chosen lens (as prescribed, with its aberrations and distortion; a minimalist lens such as MOS-S1) would have taken it"""

    bl_idname = "dcdi.simulate_lens"
    bl_label = "Simulate Minimalist Lens"
    bl_options = {"REGISTER"}
    job_label = "Lens Simulation"

    renders = True

    def prepare(self, context, rendered=None):
        return prepare_simulation(context, rendered)

    def compute(self, job, **kw):
        return logic.run_simulation(job["rgb"], job["depth"], job["lens"], noise=job["noise"],
                                    pinhole_focal_length_mm=job["pinhole_mm"], **kw)

    def finish(self, context, job, result, seconds):
        out, sensor_depth, geometry, info = result
        SESSION.simulation = dict(rgb=job["rgb"], depth=job["depth"], image=out, sensor_depth=sensor_depth,
                                  geometry=geometry, lens=job["lens"], lens_id=job["lens"].id,
                                  pixel_pitch_mm=info["pixel_pitch_mm"], sensor_noise=job["noise"],
                                  record=info["record"])
        bpy_render.show_in_image_editor(context, bpy_render.put_image(SIMULATION_IMAGE, out, info["record"]))
        st = context.window_manager.dcdi_lens_bokeh_status
        st.psf_source, st.psf_words = info["psf_source_message"], logic.source_words(info)
        st.correction = ""                   # the last correction was of another simulation
        h, w = out.shape[:2]
        noise = ", sensor noise" if job["noise"] else ""
        self.report({"INFO"}, f"Lens Simulation: {job['lens'].id}, {w} x {h} px{noise}, {_render_words(job)}, "
                              f"simulation {seconds:.1f} s; {info['psf_source_message']}")


def correction_blocker(context) -> str | None:
    """Why Correct cannot run now (no simulation yet; Network chosen and no
    torch), or None."""
    if not SESSION.simulation:
        return f"run {DCDI_OT_simulate_lens.bl_label} first: Correct works on its image"
    if context.scene.dcdi_lens_bokeh.correction_method == "NETWORK":
        return logic.torch_missing()
    return None


def correction_choice(context) -> "logic.CorrectionChoice":
    """The method Correct runs on the last simulation, and why (the panel's
    Correction Method; Auto by the engine's rule)."""
    s = context.scene.dcdi_lens_bokeh
    sim = SESSION.simulation
    given = bpy.path.abspath(s.correction_model) if s.correction_model else ""
    return logic.choose_correction(s.correction_method.lower(), sim["lens_id"], sim["pixel_pitch_mm"], given,
                                   lens=sim["lens"], record=sim.get("record"))


def prepare_correction(context):
    """The last simulation and how to correct it."""
    why = correction_blocker(context)
    if why:
        raise logic.BokehInputError(why)
    return dict(SESSION.simulation, choice=correction_choice(context), render_s=0.0)


class DCDI_OT_correct_simulation(_JobOperator, bpy.types.Operator):
    """Correct the last Lens Simulation with the render's true depth on the sensor: deconvolution with the lens's own PSFs (no PyTorch needed), or the lens's shipped DACN (or the Correction Model file) where PyTorch is installed; Auto picks by the engine's rule"""

    bl_idname = "dcdi.correct_lens_simulation"
    bl_label = "Correct Simulation"
    bl_options = {"REGISTER"}
    job_label = "Lens Correction"
    first_message = "correcting..."

    @classmethod
    def poll(cls, context):
        if not super().poll(context):
            return False
        why = correction_blocker(context)
        if why:
            cls.poll_message_set(why)
        return why is None

    def prepare(self, context):
        return prepare_correction(context)

    def compute(self, job, **kw):
        return logic.run_correction(job["image"], job["sensor_depth"], job["lens"], job["choice"],
                                    geometry=job["geometry"], sensor_noise=job["sensor_noise"],
                                    record=job.get("record"), **kw)

    def finish(self, context, job, result, seconds):
        out, info = result
        bpy_render.show_in_image_editor(context, bpy_render.put_image(CORRECTED_IMAGE, out))
        context.window_manager.dcdi_lens_bokeh_status.correction = logic.correction_line(info, seconds)
        self.report({"INFO"}, logic.correction_report(info, seconds, out.shape))


def _redraw(context):
    for window in context.window_manager.windows:
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PROPERTIES"):
                area.tag_redraw()


class DCDI_OT_match_camera(bpy.types.Operator):
    """Set the active camera's focal length, sensor and F-Stop to the lens's: the camera frames what the lens focused at the focus distance shows (with Lens Geometry and Refocus Lens; the lens breathes and distorts, so its framing changes with the focus), else the lens's paraxial focal length; the sensor's diagonal spans the render; both scaled up together where Blender's 1 mm minimum sensor would change the field of view; the F-Stop wide open"""

    bl_idname = "dcdi.match_camera_to_lens"
    bl_label = "Match Camera to Lens"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        try:
            cam = reading.camera(scene)
            lens, _ = reading.chosen_lens(scene.dcdi_lens_bokeh)
            r = scene.render
            s = scene.dcdi_lens_bokeh
            # with Lens Geometry the lens moves the picture: frame as it does at the focus distance
            focus_m = _framing_focus(scene) if s.refocus and s.lens_geometry else None
            pinhole = app.camera.PinholeCamera.for_lens(lens, r.resolution_y, r.resolution_x, focus_m=focus_m)
        except _user_errors() as e:
            self.report({"ERROR"}, logic.message(e))
            return {"CANCELLED"}
        c = pinhole.blender_camera_settings()
        for name, value in c.items():
            setattr(cam.data, name, value)
        # the lens wide open: Camera Aperture then stops it down from there
        cam.data.dof.aperture_fstop = app.lenses.wide_open_f_number(lens)
        scale = pinhole.blender_scale()
        scaled = (f" (the lens's {pinhole.focal_length_mm:.3g} mm and its sensor scaled x{scale:.3g} to Blender's "
                  "1 mm minimum; the field of view is the lens's)" if scale > 1 else "")
        framing = ""
        if focus_m is not None:
            efl = logic.lens_readout(reading.chosen_lens(scene.dcdi_lens_bokeh)[1])["focal_length_mm"]
            framing = (f", framing as {lens.id} focused at {focus_m:.3g} m (its {efl:.3g} mm breathes to "
                       f"{pinhole.focal_length_mm:.4g} mm there; match again after a refocus)")
        self.report({"INFO"}, f"{cam.name}: focal length {c['lens']:.2f} mm{framing}, sensor "
                              f"{c['sensor_width']:.2f} x {c['sensor_height']:.2f} mm{scaled}, "
                              f"F-Stop {cam.data.dof.aperture_fstop:.3g} (wide open)")
        return {"FINISHED"}


def _framing_focus(scene) -> float | None:
    """The focus distance (m from the lens's first vertex) Match Camera frames
    at, or None where the scene gives none (then the lens's focal length)."""
    try:
        return reading.read_scene(scene).focus_m
    except _user_errors():
        return None


class DCDI_OT_import_zemax(bpy.types.Operator):
    """Import a Zemax OpticStudio sequential lens file (.zmx) as a lens"""

    bl_idname = "dcdi.import_zemax"
    bl_label = "Import Zemax File..."
    bl_options = {"REGISTER"}

    filepath: StringProperty(subtype="FILE_PATH", options={"SKIP_SAVE"})
    filter_glob: StringProperty(default="*.zmx;*.ZMX", options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        try:
            out = logic.import_zemax(self.filepath, reading.user_lens_dir(create=True))
        except _user_errors() as e:
            self.report({"ERROR"}, f"cannot import {self.filepath}: {logic.message(e)}")
            return {"CANCELLED"}
        lens_id = os.path.splitext(os.path.basename(out))[0]
        context.scene.dcdi_lens_bokeh.lens = lens_id
        self.report({"INFO"}, f"imported {self.filepath} as lens {lens_id!r} ({out})")
        return {"FINISHED"}


def focus_on_point(scene, point) -> float:
    """Set the panel's focus to the depth of the world ``point`` (scene
    units) along the active camera's view axis: Distance mode, the distance
    from the camera (as Blender's depth of field measures it). Returns the
    focus in metres from the lens's first vertex."""
    s = scene.dcdi_lens_bokeh
    r = reading.read_scene(scene, focus=False)
    focus = reading.point_depth_m(scene, r.camera, point, r.entrance_pupil_mm)
    logic.keep_range(focus, 0.0, 0.0)              # in front of the lens, or a message saying it is not
    s.focus_mode = "DISTANCE"
    s.focus_distance = -(r.camera.matrix_world.inverted() @ point).z     # camera space looks down -Z
    return focus


class DCDI_OT_focus_pick(bpy.types.Operator):
    """Focus on what is under the mouse: click in the 3D viewport (Esc or right click cancels); the focus distance becomes that point's depth along the camera's axis"""

    bl_idname = "dcdi.focus_pick"
    bl_label = "Focus on Click"
    bl_options = {"REGISTER", "UNDO"}

    location: bpy.props.FloatVectorProperty(name="Point", subtype="TRANSLATION", size=3, options={"SKIP_SAVE"},
                                            description="World point to focus on (set by the click)")

    def execute(self, context):
        try:
            from mathutils import Vector
            focus = focus_on_point(context.scene, Vector(self.location))
        except _user_errors() as e:
            self.report({"ERROR"}, logic.message(e))
            return {"CANCELLED"}
        distance = context.scene.dcdi_lens_bokeh.focus_distance
        self.report({"INFO"}, f"Lens Bokeh: focus {distance:.3f} (from the camera)")
        return {"FINISHED"}

    def invoke(self, context, event):
        if context.area is None or context.area.type != "VIEW_3D":
            self.report({"ERROR"}, "Focus on Click works in a 3D viewport: use it from the sidebar's Lens Bokeh tab")
            return {"CANCELLED"}
        context.window.cursor_modal_set("EYEDROPPER")
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type in ("ESC", "RIGHTMOUSE"):
            context.window.cursor_modal_restore()
            return {"CANCELLED"}
        if event.type != "LEFTMOUSE" or event.value != "PRESS":
            return {"RUNNING_MODAL"}
        context.window.cursor_modal_restore()
        hit = _ray_cast(context, event)
        if hit is None:
            self.report({"WARNING"}, "nothing under the mouse to focus on")
            return {"CANCELLED"}
        self.location = hit
        return self.execute(context)


def _ray_cast(context, event):
    """The first surface under the mouse in the 3D viewport (world point), or None."""
    from bpy_extras import view3d_utils
    for region in context.area.regions:
        if region.type != "WINDOW":
            continue
        x, y = event.mouse_x - region.x, event.mouse_y - region.y
        if not (0 <= x < region.width and 0 <= y < region.height):
            continue
        rv3d = region.data
        origin = view3d_utils.region_2d_to_origin_3d(region, rv3d, (x, y))
        direction = view3d_utils.region_2d_to_vector_3d(region, rv3d, (x, y))
        hit, location, *_ = context.scene.ray_cast(context.evaluated_depsgraph_get(), origin, direction)
        return location if hit else None
    return None


class DCDI_OT_focus_active(bpy.types.Operator):
    """Focus on the active object (Object mode, its origin)"""

    bl_idname = "dcdi.focus_active_object"
    bl_label = "Focus on Active Object"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        ob = context.active_object
        return ob is not None and ob is not context.scene.camera

    def execute(self, context):
        s = context.scene.dcdi_lens_bokeh
        s.focus_mode = "OBJECT"
        s.focus_object = context.active_object
        self.report({"INFO"}, f"Lens Bokeh: focus on {context.active_object.name}")
        return {"FINISHED"}


class DCDI_OT_status_detail(bpy.types.Operator):
    """The last job's blur line: its tooltip says in the engine's words where
    the PSFs came from; a click copies that to the clipboard"""
    bl_idname = "dcdi.status_detail"
    bl_label = "Details"
    bl_options = {"INTERNAL"}

    @classmethod
    def description(cls, context, properties):
        return context.window_manager.dcdi_lens_bokeh_status.psf_source or "No job has run yet"

    def execute(self, context):
        detail = context.window_manager.dcdi_lens_bokeh_status.psf_source
        context.window_manager.clipboard = detail
        self.report({"INFO"}, f"Copied: {detail}")
        return {"FINISHED"}


CLASSES = (DCDI_OT_apply_lens_bokeh, DCDI_OT_simulate_lens, DCDI_OT_correct_simulation, DCDI_OT_match_camera,
           DCDI_OT_import_zemax, DCDI_OT_focus_pick, DCDI_OT_focus_active, DCDI_OT_status_detail)
