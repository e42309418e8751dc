"""The viewport preview's Cycles renders in a second Blender, so that the
user's Blender never waits for them.

Blender's render API runs only on the main thread, and a Cycles render of
the preview (480 x 270, a few samples) holds that thread for 0.3-2 s: the
window stops responding. Instead, while the preview is on, a background
Blender (``bpy.app.binary_path -b --factory-startup``, at a low CPU
priority) runs this file as its script: for each request it opens the scene
as the user's Blender wrote it (``bpy.data.libraries.write`` of the scene
and what it uses), renders it with
``bpy_render.render_aif_depth`` (the same all-in-focus colour and planar Z
as Apply Lens Bokeh's) and hands the pixels back as .npy files. A thread of
the user's Blender reads its answers; the preview's timer collects them.

The copy is written only when the scene's data changed (a mesh, a
material, an image, an object added: 0.1 s for a million polygons, 2.6 s
with 600 MB of packed images, on the main thread). Where only objects
moved since (the camera included, and the camera's lens, sensor, shift
and clipping), the request carries their placements instead
(:func:`placements`: each one's ``matrix_basis``, which its parents,
constraints and drivers then place as in the user's Blender) and the
worker applies them to the copy it holds (:func:`apply_placements`); a
copy that lacks a named object answers ``stale`` and is written anew.

What the worker sees is the scene as saved: the objects, their modifiers
and materials, the world, packed images and image files (paths made
absolute); an image painted but not saved, or a mesh in Edit Mode before
:func:`write_scene` flushes it, is what a saved file would hold. No add-on
runs in it (factory settings), nor Python drivers unless the user's Blender
trusts the file's scripts.

Protocol: one JSON object a line on stdin (a request) and, on stdout, lines
that start with ``MARK`` (Blender prints its own lines there too): first,
where the worker was started warm (``$DCDI_RENDER_WORKER_WARM``: a scene to
open, bake the view-transform table of and render a few pixels of before
anything is asked), ``{"warm": true, "table", "steps_per_stop", "bake_s"}``;
then ``{"ready": true}``, then one answer per request, ``{"id", "rgb", "z",
"load_s", "render_s", "save_s"}``, ``{"id", "stale": name}`` or ``{"id",
"error"}``. A request names the copy (``blend``) and, where it was not
written for it, the ``placements`` to apply to it.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

MARK = "DCDI-RENDER-WORKER "
# the worker's CPU priority: the UI's drawing goes a little first, yet other work of the user's (two busy cores
# at nice 0) does not starve it: its first 480 x 270 render took 0.73 s at nice 0, 1.17 at 2, 1.52 at 5, 4.4 at 10
# and 34 s at 19 (Debian's Blender 5.2.2, 2 cores; docs/addon.md)
NICE = 2
HERE = Path(__file__).resolve().parent


# ------------------------------------------------------------------ the user's Blender's side
class RenderWorker:
    """A background Blender rendering the preview's requests, one at a time."""

    def __init__(self):
        self.proc: subprocess.Popen | None = None
        self.dir: Path | None = None
        self.ready = threading.Event()
        self.pending: dict | None = None     # the request in flight (see :meth:`request`)
        self.error = ""                      # why the worker stopped or could not start
        self.started_at = 0.0
        self.ready_s: float | None = None    # how long it took to start
        self.count = 0
        self._lock = threading.Lock()
        self.warm_key = None                 # the view settings the warm-up bakes a table for
        self.warm_table = None               # that table, once baked (view_transform.Table)
        self.copy: Path | None = None        # the scene copy the worker holds (None: write one)

    def _warm_request(self, context, scene) -> dict | None:
        """The warm-up's request (the scene written for it), or None where it cannot be written."""
        from . import view_transform
        blend = self.dir / "warm.blend"
        try:
            write_scene(context, scene, blend)
        except (RuntimeError, OSError):
            return None
        self.warm_key = view_transform.settings_key(scene)
        return {"blend": str(blend), "scene": scene.name, "table": str(self.dir / "warm-table.npz")}

    def start(self, context=None, scene=None) -> bool:
        """Start the worker unless it runs (it takes a second or two to be
        ready; requests sent before wait in its input). False when it cannot.
        With ``scene`` (the warm-up before the preview is turned on), the
        worker first opens it, bakes its view-transform table (kept as
        ``warm_table``) and renders a few pixels (Cycles' start), so that the
        preview's first render finds all of that done."""
        import bpy
        if self.alive():
            return True
        binary = getattr(bpy.app, "binary_path", "")
        if bpy.app.background or not binary or not os.path.exists(binary):
            self.error = "no Blender binary to run the preview's renders in"
            return False
        self.stop()
        self.dir = Path(tempfile.mkdtemp(prefix="dcdi-preview-"))
        from dcdi_core import app           # the folder that holds the engine, for the worker's sys.path
        env = dict(os.environ, DCDI_RENDER_WORKER_PATH=json.dumps([str(Path(app.__file__).parents[2])]))
        self.warm_key = None
        if scene is not None:
            warm = self._warm_request(context, scene)
            if warm is not None:
                env["DCDI_RENDER_WORKER_WARM"] = json.dumps(warm)
        cmd = [binary, "-b", "--factory-startup", "--python-exit-code", "1"]
        if getattr(bpy.app, "autoexec", False):
            cmd.append("--enable-autoexec")          # the user's Blender runs the file's Python drivers: so does this
        cmd += ["--python", str(Path(__file__).resolve())]
        nice = shutil.which("nice") if os.name == "posix" else None
        if nice:
            cmd = [nice, "-n", str(NICE), *cmd]      # every thread of it, Cycles' too
        try:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=subprocess.DEVNULL, text=True, encoding="utf-8", errors="replace",
                                         bufsize=1, env=env)
        except OSError as e:
            self.error = f"the preview's render worker did not start: {e}"
            self.proc = None
            return False
        self.ready.clear()
        self.error = ""
        self.started_at = time.perf_counter()
        threading.Thread(target=self._read, args=(self.proc,), name="dcdi-render-worker-reader",
                         daemon=True).start()
        return True

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def busy(self) -> bool:
        return self.pending is not None and not self.pending["done"].is_set()

    def request(self, context, scene, camera, h: int, w: int, samples: int, view_layer: str,
                bake_key: tuple | None = None, moved=None, seed: int = 0) -> dict:
        """Ask for the scene's render; returns the request: ``done`` (an
        Event), then ``rgb``, ``z``, ``stale`` (the copy lacks that object:
        ask again with ``moved`` None) or ``error``, ``seconds`` (request to
        answer), ``write_s`` (the main thread's share) and ``wrote``.
        ``moved``: the names of the objects moved since the copy was written
        (None: the scene's data changed, write a copy): their placements and
        the camera's are sent instead of a copy. ``bake_key``: also bake the
        scene's view-transform table there (``view_transform.bake``, 0.3-0.6
        s that the main thread is spared), returned as ``table`` under that
        key (None where it failed). ``seed``: Cycles' seed (another pass
        of the same view, whose mean the preview shows)."""
        if not self.alive():
            raise RuntimeError(self.error or "the preview's render worker is not running")
        if self.busy():
            raise RuntimeError("the preview's render worker is busy")
        self.count += 1
        n = self.count
        t0 = time.perf_counter()
        wrote = moved is None or self.copy is None
        if wrote:
            self.copy = None                 # until written whole
            blend = self.dir / f"scene-{n % 2}.blend"
            write_scene(context, scene, blend)
            self.copy = blend
        req = {"id": n, "blend": str(self.copy), "scene": scene.name, "camera": camera.name, "h": h, "w": w,
               "samples": samples, "seed": seed, "view_layer": view_layer, "rgb": str(self.dir / f"rgb-{n % 2}.npy"),
               "z": str(self.dir / f"z-{n % 2}.npy")}
        if not wrote:
            req["placements"] = placements(scene, camera, moved)
        if bake_key is not None:
            req["table"] = str(self.dir / f"table-{n % 2}.npz")
        pending = {"id": n, "done": threading.Event(), "t0": t0, "write_s": time.perf_counter() - t0,
                   "bake_key": bake_key, "wrote": wrote}
        with self._lock:
            self.pending = pending
        try:
            self.proc.stdin.write(json.dumps(req) + "\n")
            self.proc.stdin.flush()
        except (OSError, ValueError) as e:
            self.error = f"the preview's render worker stopped: {e}"
            pending["error"] = self.error
            pending["done"].set()
        return pending

    def _read(self, proc) -> None:
        """The reader thread: the worker's answers, until it ends."""
        import numpy as np
        for line in proc.stdout:
            if not line.startswith(MARK):
                continue
            try:
                msg = json.loads(line[len(MARK):])
            except ValueError:
                continue
            if msg.get("ready"):
                self.ready_s = time.perf_counter() - self.started_at
                self.ready.set()
                continue
            if msg.get("warm"):
                self.warm_table = _read_table(msg, self.warm_key)
                continue
            with self._lock:
                pending = self.pending
            if pending is None or msg.get("id") != pending["id"]:
                continue
            if "error" in msg:
                pending["error"] = msg["error"]
            elif "stale" in msg:
                self.copy = None             # the next request writes the copy whole
                pending["stale"] = msg["stale"]
            else:
                try:
                    pending["rgb"], pending["z"] = np.load(msg["rgb"]), np.load(msg["z"])
                except (OSError, ValueError) as e:
                    pending["error"] = f"the render worker's pixels could not be read: {e}"
                pending["table"] = _read_table(msg, pending.get("bake_key"))
            pending["seconds"] = time.perf_counter() - pending["t0"]
            pending["steps"] = {k: msg[k] for k in ("load_s", "render_s", "save_s") if k in msg}
            pending["done"].set()
        code = proc.wait()
        if proc is self.proc and not self.error:
            self.error = f"the preview's render worker ended (exit {code})"
        with self._lock:
            pending = self.pending
        if proc is self.proc and pending is not None and not pending["done"].is_set():
            pending["error"] = self.error
            pending["done"].set()

    def stop(self) -> None:
        """End the worker (it ends at the end of its input; killed if it
        does not within a few seconds, by a thread) and remove its files."""
        proc, folder, self.proc, self.dir, self.pending = self.proc, self.dir, None, None, None
        self.copy = None
        self.ready.clear()
        self.warm_key = self.warm_table = None
        if proc is not None:
            try:
                proc.stdin.close()
            except OSError:
                pass
            threading.Thread(target=_end, args=(proc,), name="dcdi-render-worker-end", daemon=True).start()
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


def _read_table(msg: dict, key):
    """The view-transform table the worker baked (``view_transform.Table``
    under ``key``), or None (none asked, or it failed: the main thread bakes)."""
    if key is None or "table" not in msg:
        return None
    import numpy as np
    from .view_transform import Table
    try:
        with np.load(msg["table"]) as f:
            values, levels = f["values"].astype(np.float32), f["levels"].astype(np.float64)
        n = len(levels)
        if values.shape != (n, n, n, 3) or not np.isfinite(values).all():
            return None
        return Table(key, values, levels, float(levels[1]), float(levels[-1]), int(msg["steps_per_stop"]),
                     float(msg["bake_s"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _end(proc) -> None:
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def write_scene(context, scene, path: Path) -> None:
    """Write ``scene`` and every data-block it uses to ``path`` (file
    paths made absolute), Edit Mode's changes flushed first."""
    import bpy
    for ob in getattr(context, "objects_in_mode", ()) or ():
        if ob.mode == "EDIT":
            ob.update_from_editmode()
    bpy.data.libraries.write(str(path), {scene}, path_remap="ABSOLUTE", compress=False)


# the camera's data that shapes the render (as ``viewport.inputs``' sharp_key)
CAMERA_DATA = ("lens", "sensor_width", "sensor_height", "sensor_fit", "shift_x", "shift_y", "clip_start", "clip_end")


def placements(scene, camera, moved) -> dict:
    """Where the objects named in ``moved`` and the ``camera`` are now:
    {"objects": {name: matrix_basis as 4 rows}, "camera_data": {CAMERA_DATA}}
    (names not in the scene are left out: a removed object made the copy
    stale by the change that removed it)."""
    objects = scene.objects
    names = set(moved) | {camera.name}
    out = {name: [list(row) for row in objects[name].matrix_basis] for name in sorted(names) if name in objects}
    return {"objects": out, "camera_data": {k: getattr(camera.data, k) for k in CAMERA_DATA}}


def apply_placements(scene, camera_name: str, given: dict) -> str | None:
    """Put the objects of ``given`` (``placements``) where they are in the
    user's Blender; returns the first name the copy lacks (nothing is
    changed then), else None."""
    objects = scene.objects
    missing = next((n for n in list(given["objects"]) + [camera_name] if n not in objects), None)
    if missing is not None:
        return missing
    from mathutils import Matrix
    for name, rows in given["objects"].items():
        objects[name].matrix_basis = Matrix(rows)
    data = objects[camera_name].data
    for k, v in given["camera_data"].items():
        setattr(data, k, v)
    return None


# ------------------------------------------------------------------ the worker's side
def _view_transform():
    """The add-on's ``view_transform`` module, imported in the worker the first
    time a table is asked for (its package: this file's folder)."""
    import importlib
    if str(HERE.parent) not in sys.path:
        sys.path.insert(0, str(HERE.parent))
    return importlib.import_module(f"{HERE.name}.view_transform")


def _reply(msg: dict) -> None:
    sys.stdout.write(MARK + json.dumps(msg) + "\n")
    sys.stdout.flush()


WARM_PX = 8              # the warm-up render's size: what starts Cycles, no more


def _warm_up(req: dict, bpy, bpy_render, np) -> None:
    """Before the first request: open the scene, bake its view-transform
    table and render WARM_PX pixels square (Cycles' first render loads its
    kernels). Whatever fails here is done again by the first request."""
    try:
        bpy.ops.wm.open_mainfile(filepath=req["blend"], load_ui=False)
        scene = bpy.data.scenes[req["scene"]]
        t = _view_transform().bake(scene)
        with open(req["table"], "wb") as f:
            np.savez(f, values=t.values, levels=t.levels)
        _reply({"warm": True, "table": req["table"], "steps_per_stop": t.steps_per_stop, "bake_s": t.bake_s})
        cam = scene.camera
        if cam is not None and cam.type == "CAMERA":
            bpy_render.render_aif_depth(scene, cam, WARM_PX, WARM_PX, 1, scene.view_layers[0].name)
    except Exception:           # noqa: BLE001 - the first request does it all again
        pass


def serve() -> None:
    """The worker's loop: a request a line until its input ends."""
    import importlib.util

    import bpy
    import numpy as np
    for p in json.loads(os.environ.get("DCDI_RENDER_WORKER_PATH", "[]")):
        if p not in sys.path:
            sys.path.insert(0, p)
    spec = importlib.util.spec_from_file_location("dcdi_render_worker_bpy_render", HERE / "bpy_render.py")
    bpy_render = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bpy_render)
    warm = os.environ.get("DCDI_RENDER_WORKER_WARM")
    if warm:
        _warm_up(json.loads(warm), bpy, bpy_render, np)
    _reply({"ready": True})
    held = None                          # (path, modification time) of the copy open now
    for line in sys.stdin:
        try:
            req = json.loads(line)
        except ValueError:
            continue
        t0 = time.perf_counter()
        try:
            stamp = (req["blend"], os.stat(req["blend"]).st_mtime_ns)
            if stamp != held or "placements" not in req:
                held = None
                bpy.ops.wm.open_mainfile(filepath=req["blend"], load_ui=False)
                held = stamp
            scene = bpy.data.scenes[req["scene"]]
            if "placements" in req:
                missing = apply_placements(scene, req["camera"], req["placements"])
                if missing is not None:
                    held = None
                    _reply({"id": req["id"], "stale": missing})
                    continue
            t1 = time.perf_counter()
            rgb, z = bpy_render.render_aif_depth(scene, bpy.data.objects[req["camera"]], req["h"], req["w"],
                                                 req["samples"], req["view_layer"], seed=req.get("seed", 0))
            t2 = time.perf_counter()
            np.save(req["rgb"], rgb)
            np.save(req["z"], z)
            answer = {"id": req["id"], "rgb": req["rgb"], "z": req["z"], "load_s": t1 - t0, "render_s": t2 - t1,
                      "save_s": time.perf_counter() - t2}
            if req.get("table"):
                try:
                    t = _view_transform().bake(scene)
                    with open(req["table"], "wb") as f:
                        np.savez(f, values=t.values, levels=t.levels)
                    answer.update(table=req["table"], steps_per_stop=t.steps_per_stop, bake_s=t.bake_s)
                except Exception:        # noqa: BLE001 - no table: the user's Blender bakes it
                    pass
            _reply(answer)
        except Exception as e:          # noqa: BLE001 - answered: the preview renders itself instead
            _reply({"id": req.get("id"), "error": f"{type(e).__name__}: {e}"})


if __name__ == "__main__":
    serve()
