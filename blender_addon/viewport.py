"""The viewport preview: the lens's result drawn over the 3D viewport's
camera view, refreshed when the camera, the focus, the lens or the scene
changes; and the focus plane drawn while the focus is adjusted.

How a refresh runs (``Preview.tick``, a ``bpy.app.timers`` function on the
main thread):

- a change marks the preview stale; the refresh starts once changes have
  stopped for ``DEBOUNCE_S``. Changes reach it four ways, because Blender
  tells no single handler about all of them: the panel's settings call
  :func:`settings_changed` from their ``update`` (a Python assignment runs
  it too; neither tags the depsgraph); ``depsgraph_update_post`` reports
  the scene's edits (an object moved, a material edited); a frame change
  (``frame_change_post``) evaluates keyframed focus and animated objects;
  and a watcher timer compares, every ``WATCH_S``, what the preview shows
  with what the scene asks for now (the camera's own focus, a focus
  object's drivers: whatever changed without telling anyone);
- the sharp image and its planar Z (camera-space depth, scene units): a
  low-sample Cycles render at the preview size (``bpy_render.render_aif_depth``,
  as Apply Lens Bokeh's), redone only when something other than the lens
  settings changed. A focus, kept-range or lens change converts the same Z
  to metres with the lens's entrance pupil and reruns the lens stage alone.
  Blender's render API runs on the main thread only, and the render holds
  it 0.3-2 s; so, where Blender has a window, a second Blender renders it
  (``render_worker``: started with the preview, at a low CPU priority; the
  main thread only writes the scene for it, a few ms) and the timer
  collects its answer. Where that worker cannot run (background mode, no
  Blender binary, it failed), the main thread renders;
- the lens stage (``logic.run_bokeh``, PSFs that must be traced at the
  preview's quality ``logic.PREVIEW_TRACE``) on a worker thread; a newer change
  cancels it (the worker's ``cancelled()`` compares generations) and its
  result is dropped;
- the result becomes a GPU texture that a ``POST_PIXEL`` draw handler
  draws over the camera's frame.

Colours: the linear result goes through the scene's colour management
(view transform, look, exposure, gamma, curves, display: ``view_transform``,
a table Blender bakes once per setting) before it becomes the texture.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from collections import OrderedDict

import bpy
import numpy as np

from dcdi_core import app

from . import bpy_render, logic, reading, render_worker, view_transform
from .session import SESSION

DEBOUNCE_S = 0.25         # a refresh waits until changes have stopped this long
POLL_S = 0.05             # the timer's period while a job runs
FOCUS_PLANE_S = 2.0       # the focus plane stays drawn this long after a focus change
# the panel's settings that do not change the preview (the others all do: tests/addon/test_viewport_preview.py),
# and Blender's camera Depth of Field settings the lens's own replace
NOT_IN_PREVIEW = {"lens_in_renders": "what F12 does", "render_effect": "what F12 applies",
                  "sensor_noise": "Simulate Minimalist Lens's", "correction_method": "Correct Simulation's",
                  "correction_model": "Correct Simulation's", "apply_render_size": "Apply's size"}
CAMERA_DOF_NOT_IN_PREVIEW = {"use_dof": "the lens's depth of field replaces Blender's",
                             "aperture_ratio": "an anamorphic bokeh's squeeze: the lens's own stop is round or "
                                               "bladed"}
RECENT_RESULTS = 8        # results kept to come back at once (480 x 270: 1.6 MB each, 2 MB more as shown)
# while nothing changes, the worker renders the same view again with other seeds and the preview shows the
# mean: 16 samples a pass, 8 passes are 128 (a 1-2 px ball's shape is then the lens's, not the noise's)
ACCUMULATE_PASSES = 8
ACCUMULATE_IDLE_S = 1.0   # how long a shown result stays untouched before the next pass is asked
WATCH_S = 0.2             # the watcher's period: what changed without a handler is seen this late
LENS_NICE = 2             # the lens stage's thread's CPU priority (Linux): Blender's drawing goes a little first
                          # (as the render worker's, ``render_worker.NICE``: more starves it beside other work)
RENDER_LIMIT_S = 300.0    # the longest a render by the worker may take before it is given up (then the main thread's)
# data-block types whose change needs a new sharp render (a lens or focus change
# does not; the camera's data that shapes the render is in ``inputs``' sharp_key,
# so a change of its focus alone reruns the lens stage only)
SCENE_TYPES = ("Mesh", "Material", "World", "Light", "Curve", "Image", "NodeTree",
               "Texture", "GreasePencil", "Volume", "PointCloud", "Curves", "MetaBall")
# data-block collections whose animation moves or changes what the sharp render shows
ANIMATED_SCENE_DATA = ("objects", "meshes", "materials", "worlds", "lights", "shape_keys", "node_groups",
                       "curves", "textures")


class Preview:
    """The preview's state: one per Blender session, held by the session (:func:`preview`)."""

    def __init__(self):
        self.enabled = False
        self.generation = 0            # bumped by every change: older jobs are cancelled, their results dropped
        self.changed_at: float | None = None
        self.scene_changed = True
        # the render worker's scene copy: written again after a change of the scene's data; objects only
        # moved since it was written go to it as placements (``render_worker``)
        self.data_changed = True
        self.moved: set[str] = set()
        # the last results by what they show (the sharp render's version, the request): a focus, lens or
        # setting seen before on the same render comes back without a lens stage
        self.recent: OrderedDict = OrderedDict()
        self.sharp: dict | None = None       # key, rgb, depth, version, passes of the last sharp render
        self.served: tuple | None = None     # the (sharp render, request) of the shown result
        self.served_passes = 0               # how many passes of that render the shown result averaged
        self.accumulate_passes = ACCUMULATE_PASSES
        self.accumulated = 0                 # passes added to sharp renders so far (not in ``renders``)
        self.result_at = 0.0                 # when the shown result was made
        self.asked: tuple | None = None      # what the last refresh was started for (see ``wanted``)
        self.renders = 0                     # sharp renders so far
        self.worker: threading.Thread | None = None
        self.job: dict | None = None
        self.result: dict | None = None      # image, info, generation, render_s, lens_s
        self.texture = None
        self.error = ""
        self.focus_changed_at = 0.0
        self.last_focus: float | None = None
        self.last_pupil_mm = 0.0             # the entrance pupil of the lens the last refresh read (the focus plane)
        self.log: list[dict] = []            # per refresh: render_s, lens_s, cold, source (for the bench and tests)
        self.worker_renders = render_worker.RenderWorker()   # the second Blender that renders (module docstring)
        self.rendering: dict | None = None   # the render asked of it and not yet collected
        self.main_renders = 0                # of the sharp renders, those made on the main thread
        self.worker_failed = ""              # why the worker failed a render: this Blender renders until the toggle
        self.panel_seen_at = 0.0             # when the panel was last drawn (the warm-up's idle limit)
        self.warm_tried = False              # the warm-up started a worker (again only after it ended idle)

    # -------------------------------------------------------------- changes
    def changed(self, scene_changed: bool, at_once: bool = False) -> None:
        """Something the preview shows changed (``scene_changed``: more than
        the lens settings): cancel the running job, refresh after the
        debounce (``at_once``: without it, the toggle's first refresh)."""
        if not self.enabled:
            return
        self.generation += 1
        self.scene_changed |= scene_changed
        self.changed_at = time.perf_counter() - (DEBOUNCE_S if at_once else 0.0)
        if bpy.app.background:
            return
        if at_once and bpy.app.timers.is_registered(_tick):
            bpy.app.timers.unregister(_tick)
        if not bpy.app.timers.is_registered(_tick):
            bpy.app.timers.register(_tick, first_interval=0.0 if at_once else DEBOUNCE_S)

    def stop(self) -> None:
        self.enabled = False
        self.generation += 1
        self.changed_at = None
        self.result = self.texture = self.sharp = self.served = self.asked = None
        self.served_passes = 0
        self.recent.clear()
        self.error = ""
        self.rendering = None
        self.worker_renders.stop()

    def check(self, context=None) -> None:
        """Mark the preview stale when what the scene asks for now differs
        from what the last refresh was started for (no-op while one is
        pending: it reads the settings when it starts)."""
        if not self.enabled or self.changed_at is not None:
            return
        now = wanted(context or bpy.context)
        if now != self.asked:
            self.changed(scene_changed=False, at_once=_switched(self.asked, now))

    # -------------------------------------------------------------- the refresh
    def tick(self, context=None) -> float | None:
        """One step (the timer's body): collect a finished job, or start one
        once the changes have settled. Returns the seconds to the next step,
        None when there is nothing left to do."""
        context = context or bpy.context
        if not self.enabled:
            return None
        if self.worker is not None:
            if self.worker.is_alive():
                return POLL_S
            self._collect()
        if self.rendering is not None:
            if not self.rendering["done"].is_set() and \
                    time.perf_counter() - self.rendering["t0"] < RENDER_LIMIT_S:
                return POLL_S
            started = self._collect_render(context)
            if started is not None:
                return started
        if self.changed_at is None:
            return self._refine(context)
        wait = DEBOUNCE_S - (time.perf_counter() - self.changed_at)
        if wait > 0:
            return wait
        self.changed_at = None
        self.asked = wanted(context)
        return self._run(lambda: self._start(context), context)

    def _run(self, step, context) -> float | None:
        """Run a step of the refresh; its error is shown in the panel."""
        try:
            step()
        except (logic.BokehInputError, app.errors.DcdiError, RuntimeError, ValueError, OSError) as e:
            self.error = logic.message(e)
            _redraw(context)
            return None
        busy = self.worker is not None or self.rendering is not None or self.changed_at is not None
        return POLL_S if busy else None

    def _start(self, context) -> None:
        a = inputs(context)
        scene, cam, focus, sharp_key = a["scene"], a["camera"], a["focus"], a["sharp_key"]
        s = scene.dcdi_lens_bokeh
        if self.last_focus is not None and focus != self.last_focus:
            self.focus_changed_at = time.perf_counter()
        self.last_focus, self.last_pupil_mm = focus, a["entrance_pupil_mm"]
        if self.scene_changed or self.sharp is None or self.sharp["key"] != sharp_key:
            if self.rendering is None and self.worker_renders.busy():
                # the worker renders for a job (Apply, Simulate): this refresh waits for it, not the main thread
                self.changed_at = time.perf_counter() - DEBOUNCE_S + POLL_S
                return
            if self._ask_worker(context, scene, cam, a["h"], a["w"], s.samples, sharp_key):
                self.scene_changed = False           # what changes from now on needs another render
                return                               # the lens stage starts when the render is collected
            t0 = time.perf_counter()
            rgb, z = bpy_render.render_aif_depth(scene, cam, a["h"], a["w"], s.samples, context.view_layer.name)
            self._keep_sharp(sharp_key, rgb, z, time.perf_counter() - t0, "main")
            self.scene_changed = False
        self._start_lens(a)

    def _ask_worker(self, context, scene, cam, h: int, w: int, samples: int, sharp_key) -> bool:
        """Ask the render worker for the sharp render; False where it cannot
        (background mode, it does not run, it failed: the main thread renders)."""
        worker = self.worker_renders
        if bpy.app.background or self.worker_failed or not (worker.alive() or worker.start()):
            return False
        if worker.warm_table is not None:            # baked by the warm-up (warm_up)
            view_transform.keep(worker.warm_table)
            worker.warm_table = None
        try:
            bake = None if view_transform.has_table(scene) else view_transform.settings_key(scene)
            pending = worker.request(context, scene, cam, h, w, samples, context.view_layer.name, bake_key=bake,
                                     moved=None if self.data_changed else set(self.moved))
        except (RuntimeError, OSError) as e:
            print(f"Lens Bokeh preview: {e}; rendering in this Blender")
            return False
        if pending["wrote"]:
            self.data_changed = False
            self.moved.clear()
        pending.update(key=sharp_key, generation=self.generation, cold=self.sharp is None)
        self.rendering = pending
        return True

    def _collect_render(self, context) -> float | None:
        """The worker's render is in (or given up): keep it and, when nothing
        changed meanwhile, start the lens stage on it. Returns what
        :meth:`tick` returns when it started something, else None."""
        r, self.rendering = self.rendering, None
        if r["done"].is_set() and "stale" in r:     # the copy lacks a moved object: write it whole, ask again
            self.data_changed = self.scene_changed = True
            if self.changed_at is None:
                self.changed_at = time.perf_counter() - DEBOUNCE_S
            return None
        if not r["done"].is_set() or "error" in r:
            why = r.get("error") or f"no answer in {RENDER_LIMIT_S:.0f} s"
            print(f"Lens Bokeh preview: the render worker failed ({why}); rendering in this Blender")
            self.worker_renders.stop()
            self.worker_failed = why
            self.scene_changed = True                # render it again, here
            if self.changed_at is None:
                self.changed_at = time.perf_counter() - DEBOUNCE_S
            return None
        if r.get("table") is not None:              # the display table baked there: none to bake here
            view_transform.keep(r["table"])
        if r.get("accumulate"):
            self._add_pass(r)
            return None
        self._keep_sharp(r["key"], r["rgb"], r["z"], r["seconds"], "worker", cold=r["cold"],
                         main_s=r["write_s"], steps=dict(r.get("steps", {}), write_s=r["write_s"], wrote=r["wrote"],
                                                         started_s=self.worker_renders.ready_s,
                                                         baked=r.get("bake_key") is not None))
        if r["generation"] != self.generation or self.changed_at is not None:
            return None                              # a newer change's refresh is pending: it uses this render
        return self._run(lambda: self._start_lens(inputs(context)), context)

    # -------------------------------------------------------------- accumulation, while nothing changes
    def refines(self) -> bool:
        """Whether passes are added to the shown render while nothing changes
        (the worker renders it: this Blender's own renders would hold its window)."""
        sharp = self.sharp
        return sharp is not None and sharp["source"] == "worker" and not bpy.app.background \
            and not self.worker_failed

    def _refine(self, context) -> float | None:
        """Idle: the lens stage on passes added since the shown result, or
        the next pass asked of the worker once the result has stood
        ``ACCUMULATE_IDLE_S``. Returns the seconds to the next step, None
        when there is nothing left to refine."""
        sharp = self.sharp
        if sharp is None or self.result is None or self.error or self.served is None \
                or self.served[0] != sharp["version"]:
            return None
        if self.served_passes < sharp["passes"]:
            return self._run(lambda: self._start_lens(inputs(context)), context)
        worker = self.worker_renders
        if sharp["passes"] >= self.accumulate_passes or not self.refines() or not worker.alive():
            return None
        wait = ACCUMULATE_IDLE_S - (time.perf_counter() - self.result_at)
        if wait > 0 or worker.busy():
            return max(wait, POLL_S)
        try:
            a = inputs(context)
        except (logic.BokehInputError, app.errors.DcdiError, RuntimeError, ValueError, OSError):
            return None                              # the next refresh says why
        if a["sharp_key"] != sharp["key"] or self.data_changed:
            return None                              # a change the watcher reports: its refresh renders anew
        try:
            pending = worker.request(context, a["scene"], a["camera"], a["h"], a["w"],
                                     a["scene"].dcdi_lens_bokeh.samples, context.view_layer.name,
                                     moved=set(self.moved), seed=sharp["passes"])
        except (RuntimeError, OSError):
            return None
        pending.update(key=sharp["key"], generation=self.generation, cold=False, accumulate=True,
                       version=sharp["version"])
        self.rendering = pending
        return POLL_S

    def _add_pass(self, r: dict) -> None:
        """A pass of the worker's, rendered with another seed: into the kept
        sharp render's mean (where the render it refines is still kept)."""
        sharp = self.sharp
        if sharp is None or sharp["version"] != r["version"] or sharp["key"] != r["key"] \
                or r["rgb"].shape != sharp["rgb"].shape:
            return
        n = sharp["passes"]
        sharp["rgb"] = (sharp["rgb"] * (n / (n + 1.0)) + r["rgb"] * (1.0 / (n + 1.0))).astype(np.float32)
        sharp["passes"] = n + 1
        self.accumulated += 1

    def _keep_sharp(self, key, rgb, z, render_s: float, source: str, cold: bool | None = None,
                    main_s: float | None = None, steps: dict | None = None) -> None:
        self.sharp = {"key": key, "rgb": rgb, "z": z, "depth": None, "depth_of": None, "version": self.renders,
                      "passes": 1,
                      "render_s": render_s, "source": source, "main_s": render_s if main_s is None else main_s,
                      "cold": (self.renders == 0) if cold is None else cold, "fresh": True, "steps": steps or {}}
        self.renders += 1
        self.main_renders += source == "main"

    def _start_lens(self, a: dict) -> None:
        """The lens stage on the kept sharp render, on a thread."""
        lens, ep, mpu, focus, keep = a["lens"], a["entrance_pupil_mm"], a["mpu"], a["focus"], a["keep"]
        sharp = self.sharp
        if sharp["depth_of"] != (ep, mpu):           # the lens's pupil or the scene's unit changed: Z -> metres
            sharp["depth"] = app.camera.depth_from_planar_z(sharp["z"], ep, mpu)
            sharp["depth_of"] = (ep, mpu)
        served = (sharp["version"], a["request"])
        if self.served == served and self.result is not None and self.served_passes == sharp["passes"]:
            return                                   # nothing the preview shows has changed
        if served in self.recent and self.served != served:     # shown before on this render: from memory
            self._recall(served)
            if self.served_passes == sharp["passes"]:
                return                               # else the lens stage on the passes added since
        fresh, sharp["fresh"] = sharp["fresh"], False    # the render is counted by the first refresh using it
        gen = self.generation
        job = self.job = {"generation": gen, "key": served, "render_s": sharp["render_s"] if fresh else 0.0,
                          "main_s": sharp["main_s"] if fresh else 0.0, "cold": sharp["cold"] and fresh,
                          "source": sharp["source"] if fresh else None, "steps": sharp["steps"] if fresh else {},
                          "t0": time.perf_counter(), "passes": sharp["passes"]}
        rgb, depth, refocus = sharp["rgb"], sharp["depth"], bool(a["scene"].dcdi_lens_bokeh.refocus)
        quality, geometry, pinhole = a["quality"], a["lens_geometry"], a["pinhole_mm"]
        # the display table applied on the thread: the texture is all the main thread makes
        table = None if bpy.app.background else view_transform.kept(a["scene"])

        def run():
            _lower_thread_priority()
            try:
                out, info = logic.run_bokeh(rgb, depth, lens, focus_m=focus, keep=keep,
                                            refocus=refocus, cancelled=lambda: self.generation != gen,
                                            preview=True, max_error_db=quality, lens_geometry=geometry,
                                            pinhole_focal_length_mm=pinhole)
                job["out"], job["info"] = out, info
                if table is not None and self.generation == gen:
                    job["display"] = view_transform.display_rows(table, out)
            except logic.Cancelled:
                job["cancelled"] = True
            except Exception as e:               # handed to the main thread
                job["error"] = e
            job["lens_s"] = time.perf_counter() - job["t0"]

        self.worker = threading.Thread(target=run, name="dcdi-viewport-preview", daemon=True)
        self.worker.start()

    def _recall(self, served) -> None:
        """Show a result kept in ``recent`` again (no lens stage; logged with ``recalled``)."""
        self.recent.move_to_end(served)
        kept = self.recent[served]
        self.error = ""
        self.result = {"image": kept["image"], "info": kept["info"], "generation": self.generation,
                       "render_s": 0.0, "lens_s": 0.0}
        self.served, self.served_passes, self.result_at = served, kept["passes"], time.perf_counter()
        self.log.append({"render_s": 0.0, "lens_s": 0.0, "cold": False, "source": None, "main_s": 0.0,
                         "render_steps": {}, "recalled": True})
        self.texture = _texture(kept["image"], kept.get("display"))
        _redraw(bpy.context)

    def _collect(self) -> None:
        job, self.worker = self.job, None
        if job is None or job["generation"] != self.generation or job.get("cancelled"):
            return                                   # a newer change came: its refresh is pending
        if "error" in job:
            self.error = logic.message(job["error"])
            return
        self.error = ""
        self.result = {"image": job["out"], "info": job["info"], "generation": job["generation"],
                       "render_s": job["render_s"], "lens_s": job["lens_s"]}
        self.served, self.served_passes, self.result_at = job["key"], job["passes"], time.perf_counter()
        self.recent[job["key"]] = {"image": job["out"], "info": job["info"], "passes": job["passes"],
                                   "display": job.get("display")}
        self.recent.move_to_end(job["key"])
        while len(self.recent) > RECENT_RESULTS:
            self.recent.popitem(last=False)
        self.log.append({"render_s": job["render_s"], "lens_s": job["lens_s"], "cold": job["cold"],
                         "source": job["source"], "main_s": job["main_s"], "render_steps": job["steps"],
                         "passes": job["passes"], "display_ahead": job.get("display") is not None})
        self.texture = _texture(job["out"], job.get("display"))
        _redraw(bpy.context)


def _lower_thread_priority() -> None:
    """The calling thread at a lower CPU priority (Linux: a thread's own nice
    value), so that Blender's drawing, and the software rasteriser's threads
    where OpenGL runs on the CPU, go before the lens stage."""
    if sys.platform.startswith("linux"):
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, max(LENS_NICE, os.getpriority(os.PRIO_PROCESS, tid)))
        except (AttributeError, OSError):
            pass


def preview() -> Preview:
    """The session's preview (made the first time it is asked for)."""
    if SESSION.preview is None:
        SESSION.preview = Preview()
    return SESSION.preview


def kept_render(context):
    """The preview's last sharp render (rgb, planar Z) where it is what a
    render of the scene now would give (the preview on, nothing changed
    since: the same camera, size, samples and scene), else None: Apply Lens
    Bokeh then runs the lens stage alone, rendering nothing."""
    p = SESSION.preview
    if p is None or not p.enabled or p.sharp is None or p.scene_changed or p.rendering is not None:
        return None
    try:
        key = inputs(context)["sharp_key"]
    except (logic.BokehInputError, app.errors.DcdiError, ValueError, OSError):
        return None
    return (p.sharp["rgb"], p.sharp["z"]) if p.sharp["key"] == key else None


def inputs(context) -> dict:
    """What a refresh works from: the camera, the lens, the preview's size,
    the focus and kept range (m), and the keys that say when the sharp
    render (``sharp_key``) or the lens stage (``request``) must be redone."""
    scene = context.scene
    r = reading.read_scene(scene)
    h, w = r.preview_shape()
    cam, lens, path, ep, mpu = r.camera, r.lens, r.lens_path, r.entrance_pupil_mm, r.metres_per_unit
    d = cam.data
    # the sharp image and its planar Z depend on the camera, not on the lens (its pupil converts the Z to
    # metres at the lens stage) nor on the scene's unit
    sharp_key = (cam.name, tuple(map(tuple, cam.matrix_world)), h, w, r.samples, d.lens,
                 d.sensor_width, d.sensor_height, d.sensor_fit, d.shift_x, d.shift_y, d.clip_start, d.clip_end)
    return {"scene": scene, "camera": cam, "lens": lens, "path": path, "entrance_pupil_mm": ep, "h": h, "w": w,
            "mpu": mpu, "focus": r.focus_m, "keep": r.keep, "sharp_key": sharp_key,
            "quality": r.preview_quality, "lens_geometry": r.lens_geometry, "pinhole_mm": r.pinhole_focal_length_mm,
            "request": (lens.id, path, r.focus_m, r.keep, r.refocus, round(ep, 9), mpu, lens.iris,
                        round(r.preview_quality, 6), r.lens_geometry, round(r.pinhole_focal_length_mm, 9))}


def wanted(context) -> tuple:
    """What the preview should show now: (sharp_key, request) of
    :func:`inputs`, or ('error', message) when the settings cannot make one
    (the refresh shows that message; the same error is not retried)."""
    try:
        a = inputs(context)
    except (logic.BokehInputError, app.errors.DcdiError, ValueError, OSError) as e:
        return ("error", logic.message(e))
    return a["sharp_key"], a["request"]


def _switched(before, now) -> bool:
    """Whether only a switch changed between two :func:`wanted` values: the
    lens or Refocus Lens (one click, no slider's stream of values to wait
    out: the refresh starts at once)."""
    if before is None or before[0] == "error" or now[0] == "error" or before[0] != now[0]:
        return False
    (lens0, path0, focus0, keep0, refocus0, ep0, *rest0), (lens1, path1, focus1, keep1, refocus1, ep1, *rest1) = \
        before[1], now[1]

    def from_camera(focus, keep, ep_mm):   # the focus and kept range as the artist set them: from the camera
        return [round(v + ep_mm / 1000.0, 9) for v in (focus, *keep)]
    return from_camera(focus0, keep0, ep0) == from_camera(focus1, keep1, ep1) and \
        (lens0, path0, refocus0, rest0) != (lens1, path1, refocus1, rest1)


def _tick():
    return preview().tick()


def _watch():
    """The watcher (module docstring): runs while the preview is on."""
    p = preview()
    if not p.enabled:
        return None
    try:
        p.check()
    except Exception as e:                # never let the watcher die silently: show why
        p.error = f"preview watcher: {type(e).__name__}: {e}"
    return WATCH_S


def settings_changed(settings, context) -> None:
    """The panel's settings' ``update``: refresh the preview if it shows
    something else now."""
    preview().check(context)


def _texture(image: np.ndarray, display: tuple | None = None):
    """A GPU texture of the linear (H, W, 3) image as the scene's colour
    management displays a render (``view_transform``: display values, drawn
    as they are); None without a GPU (background). ``display``: the values
    made ahead (``view_transform.display_rows``), used when the scene's view settings are
    still those of its table. Should Blender fail to bake the view transform,
    the sRGB encoding, and the console says why."""
    if bpy.app.background:
        return None
    import gpu

    h, w = image.shape[:2]
    scene = bpy.context.scene
    if display is not None and display[0] == view_transform.settings_key(scene):
        rgba = display[1]
    else:
        rgba = np.ones((h, w, 4), np.float32)
        try:
            rgba[..., :3] = view_transform.to_display(image, scene)
        except (RuntimeError, OSError, ValueError, TypeError) as e:
            print(f"Lens Bokeh preview: the scene's view transform could not be baked ({e}); showing sRGB")
            rgba[..., :3] = app.images.linear_to_srgb(np.clip(np.nan_to_num(image), 0.0, 1.0))
        rgba = rgba[::-1]
    buf = gpu.types.Buffer("FLOAT", h * w * 4, rgba.ravel())
    tex = gpu.types.GPUTexture((w, h), format="RGBA16F", data=buf)
    if hasattr(tex, "filter_mode"):         # drawn over a larger frame: interpolated, not in blocks
        tex.filter_mode(True)
    return tex


def _redraw(context) -> None:
    wm = getattr(context, "window_manager", None)
    for window in (wm.windows if wm else ()):
        for area in window.screen.areas:
            if area.type in ("VIEW_3D", "PROPERTIES"):
                area.tag_redraw()


# ------------------------------------------------------------------ drawing
def _camera_frame_px(context):
    """The active camera's frame in the region's pixels (x0, y0, x1, y1), or
    None outside the camera view."""
    from bpy_extras.view3d_utils import location_3d_to_region_2d
    rv3d, region, scene = context.region_data, context.region, context.scene
    if rv3d is None or rv3d.view_perspective != "CAMERA" or scene.camera is None:
        return None
    cam = scene.camera
    pts = [location_3d_to_region_2d(region, rv3d, cam.matrix_world @ p) for p in cam.data.view_frame(scene=scene)]
    if any(p is None for p in pts):
        return None
    xs, ys = [p.x for p in pts], [p.y for p in pts]
    return min(xs), min(ys), max(xs), max(ys)


def draw_preview():
    """POST_PIXEL: the last result over the camera's frame."""
    p = preview()
    if not p.enabled or p.texture is None:
        return
    frame = _camera_frame_px(bpy.context)
    if frame is None:
        return
    from gpu_extras.presets import draw_texture_2d
    x0, y0, x1, y1 = frame
    draw_texture_2d(p.texture, (x0, y0), x1 - x0, y1 - y0)


def focus_plane_corners(scene, focus_m: float, entrance_pupil_mm: float):
    """World positions of the camera frustum's section at the focus
    (metres from the lens's first vertex): 4 corners (scene units)."""
    cam = scene.camera
    frame = cam.data.view_frame(scene=scene)             # camera space, on the plane z = -d
    d = -frame[0].z
    z = (focus_m + entrance_pupil_mm / 1000.0) / float(scene.unit_settings.scale_length)
    return [cam.matrix_world @ (p * (z / d)) for p in frame]


def draw_focus_plane():
    """POST_VIEW: the focus plane, translucent, for FOCUS_PLANE_S after a focus change."""
    p = preview()
    if not p.enabled or time.perf_counter() - p.focus_changed_at > FOCUS_PLANE_S:
        return
    scene = bpy.context.scene
    if scene.camera is None or p.last_focus is None:
        return
    import gpu
    from gpu_extras.batch import batch_for_shader
    corners = [tuple(c) for c in focus_plane_corners(scene, p.last_focus, p.last_pupil_mm)]
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    batch = batch_for_shader(shader, "TRIS", {"pos": corners}, indices=((0, 1, 2), (0, 2, 3)))
    gpu.state.blend_set("ALPHA")
    shader.uniform_float("color", (1.0, 0.55, 0.1, 0.25))
    batch.draw(shader)
    gpu.state.blend_set("NONE")


# ------------------------------------------------------------------ changes and the toggle
def on_depsgraph_update(scene, depsgraph):
    p = preview()
    if not p.enabled:
        return
    changes = [u for u in depsgraph.updates if _changes_the_render(u)]
    if not changes:
        p.check()                                   # the lens settings, the focus, the camera, the size
        return
    for u in changes:
        if _only_moved(u):
            p.moved.add(u.id.name)
        else:
            p.data_changed = True
    p.changed(scene_changed=True)


def _only_moved(update) -> bool:
    """Whether an update that changes the render only moved an object (its
    placement goes to the render worker's copy; anything else writes the
    copy again)."""
    return type(update.id).__name__ == "Object" and update.is_updated_transform and not update.is_updated_geometry


def on_undo(scene, *args):
    """Undo and redo replace the scene's data: the render worker's copy is written again."""
    p = preview()
    if p.enabled:
        p.data_changed = True
        p.changed(scene_changed=True)


def on_frame_change(scene, depsgraph=None):
    """A new frame: animated objects (or their materials, lights...) need a
    new sharp render; keyframed focus or lens settings the lens stage only."""
    p = preview()
    if not p.enabled:
        return
    if _scene_animated():
        p.data_changed = True                       # the copy is written at the new frame
        p.changed(scene_changed=True)
    else:
        p.check()


def _scene_animated() -> bool:
    """Whether anything the sharp render shows is animated (an action or drivers)."""
    for name in ANIMATED_SCENE_DATA:
        for block in getattr(bpy.data, name, ()):
            ad = getattr(block, "animation_data", None)
            if ad is not None and (ad.action is not None or len(ad.drivers)):
                return True
    return False


def _changes_the_render(update) -> bool:
    """Whether a depsgraph update can change the sharp render: an object
    moved or reshaped, or a mesh, material, light, world... edited. A
    property of the scene (the lens settings) tags every object's shading
    only, and the preview's own render (a temporary scene) tags the
    collections: neither counts; nor does a camera (its change of focus tags
    its geometry: ``inputs``' sharp_key says when it changes the render)."""
    kind = type(update.id).__name__
    if kind == "Object":
        if update.id.type == "CAMERA":     # its placement and the data that shape the render are in sharp_key
            return False
        return update.is_updated_transform or update.is_updated_geometry
    return kind in SCENE_TYPES


# (handler list, function) pairs the preview adds while it is on
_APP_HANDLERS = (("depsgraph_update_post", on_depsgraph_update), ("frame_change_post", on_frame_change),
                 ("undo_post", on_undo), ("redo_post", on_undo))


def set_enabled(enabled: bool, context=None) -> None:
    """Turn the preview on (draw handlers, the first refresh) or off."""
    context = context or bpy.context
    p = preview()
    if enabled == p.enabled:
        return
    if not enabled:
        p.stop()
        SESSION.release("preview")
        _redraw(context)
        return
    p.enabled = True
    p.scene_changed = p.data_changed = True
    p.worker_failed = ""
    if not bpy.app.background:
        p.worker_renders.start()                    # ready in a second or two; the first render waits for it
    for name, fn in _APP_HANDLERS:
        if fn not in getattr(bpy.app.handlers, name):
            getattr(bpy.app.handlers, name).append(fn)
    if not bpy.app.background and not bpy.app.timers.is_registered(_watch):
        bpy.app.timers.register(_watch, first_interval=WATCH_S, persistent=True)
    if not SESSION.holds("preview"):
        draw = () if bpy.app.background else (
            bpy.types.SpaceView3D.draw_handler_add(draw_preview, (), "WINDOW", "POST_PIXEL"),
            bpy.types.SpaceView3D.draw_handler_add(draw_focus_plane, (), "WINDOW", "POST_VIEW"))
        SESSION.hold("preview", lambda: _remove_handlers(draw))
    p.changed(scene_changed=True, at_once=True)      # the toggle's own refresh starts at once


def _remove_handlers(draw) -> None:
    """Take back what the preview added: its draw handlers ``draw``, the app handlers, the timers."""
    for handle in reversed(draw):
        bpy.types.SpaceView3D.draw_handler_remove(handle, "WINDOW")
    for name, fn in _APP_HANDLERS:
        if fn in getattr(bpy.app.handlers, name):
            getattr(bpy.app.handlers, name).remove(fn)
    for timer in (_tick, _watch):
        if not bpy.app.background and bpy.app.timers.is_registered(timer):
            bpy.app.timers.unregister(timer)


# ------------------------------------------------------------------ the warm-up
# While the panel is drawn and the preview is off, the render worker starts
# ahead of the toggle (a background Blender's start, 0.8 s; the scene's
# view-transform table, 0.4 s; Cycles' first render): the toggle's first
# picture then waits for its render and the lens stage only. A worker the
# preview never used ends WARM_IDLE_S after the panel was last drawn.
WARM_IDLE_S = 300.0
WARM_CHECK_S = 10.0


def warm_up(context) -> None:
    """The panel's drawing calls this: start the warm-up (a timer: a draw
    callback starts no process) unless the preview is on or it ran."""
    if bpy.app.background:
        return
    p = preview()
    p.panel_seen_at = time.perf_counter()
    if p.enabled or p.warm_tried or p.worker_failed or p.worker_renders.alive():
        return
    if not bpy.app.timers.is_registered(_warm):
        bpy.app.timers.register(_warm, first_interval=0.0)
        if not SESSION.holds("warm-up"):
            SESSION.hold("warm-up", _stop_warm_timer)


def _stop_warm_timer() -> None:
    if bpy.app.timers.is_registered(_warm):
        bpy.app.timers.unregister(_warm)


def _warm() -> float | None:
    """The warm-up's timer: start the worker once, then end it when the panel
    has not been drawn for WARM_IDLE_S while the preview stayed off."""
    p = preview()
    if p.enabled:
        return None                                  # the preview has the worker now
    worker = p.worker_renders
    if not p.warm_tried:
        p.warm_tried = True
        context = bpy.context
        scene = getattr(context, "scene", None)
        if scene is None or not worker.start(context, scene):
            return None
        return WARM_CHECK_S
    if not worker.alive():
        return None
    if time.perf_counter() - p.panel_seen_at > WARM_IDLE_S:
        worker.stop()
        p.warm_tried = False                         # the panel drawn again warms up again
        return None
    return WARM_CHECK_S


def toggle_update(status, context) -> None:
    """The status's ``viewport_preview`` property's update."""
    set_enabled(bool(status.viewport_preview), context)
