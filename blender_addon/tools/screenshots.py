"""Screenshots of the Lens Bokeh add-on in a real Blender UI, for docs/addon.md.

    python blender_addon/tools/screenshots.py [--blender blender] [--zip dist/dcdi_lens_bokeh-0.1.0.zip] [--out docs]

Runs Blender twice: once in the background to build a demo scene (a row of
spheres at 1.2-10 m on a checker floor) and save it, then with a window
under Xvfb (``xvfb-run``) with that file open: it installs the add-on zip
into a temporary user folder (an extension in Blender 4.2+, a legacy add-on
before), shows the panel in the camera properties and the 3D view's
sidebar, runs Apply Lens Bokeh the way a click does (invoke: worker thread,
progress, modal timer), and saves two screenshots: ``addon-running.png``
(progress readout while the PSFs are built), ``addon-result.png`` (the
"Lens Bokeh" image in an Image Editor), ``addon-preview.png`` (Preview in
Viewport over the camera view) and ``addon-focus-plane.png`` (the focus
plane after a focus change), ``addon-preview-320.png`` and
``addon-preview-640.png`` (the preview through the Sonnar 50/1.5 wide
open at those sizes), each a capture of the X screen (ImageMagick's
``import -window root``: Blender's own screenshot is black under software
OpenGL); ``addon-f12-balls.png``, a crop of an F12 render through the
Mamiya 150 mm with Lens in Renders (the lights' balls, saved through the
scene's view transform); then it runs once more synchronously
(warm cache) and starts a run at another focus distance (a cold library) and
presses Esc during it (Blender's event simulation), printing the panel's
state afterwards. The PSF cache is a fresh temporary folder, so the first run
shows the cold (first-use) time.

Blender's Python must have numpy. Debian's ``blender`` package expects
``python3-numpy``; where that is missing, ``--numpy-path DIR`` puts a folder
holding a numpy built for the same Python version on Blender's sys.path.
"""
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------ driver (plain Python)
def drive(argv):
    import argparse
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--blender", default="blender")
    p.add_argument("--zip", default=None, help="add-on zip (default: build it with build.py addon)")
    p.add_argument("--out", default=str(ROOT / "docs"))
    p.add_argument("--numpy-path", default="", help="folder with a numpy for Blender's Python (see above)")
    p.add_argument("--screen", default="1600x1000")
    a = p.parse_args(argv)
    if a.zip is None:
        sys.path.insert(0, str(ROOT))
        import build
        a.zip = str(build.build_addon())
    work = Path(tempfile.mkdtemp(prefix="dcdi-screenshots-"))
    env = dict(os.environ, BLENDER_USER_SCRIPTS=str(work / "scripts"), BLENDER_USER_CONFIG=str(work / "config"),
               BLENDER_USER_RESOURCES=str(work / "user"), DCDI_CACHE_DIR=str(work / "psf-cache"),
               DCDI_SCREENSHOT_ARGS=json.dumps({"zip": str(Path(a.zip).resolve()), "out": str(Path(a.out).resolve()),
                                                "numpy_path": a.numpy_path, "blend": str(work / "demo.blend")}))
    me = str(Path(__file__).resolve())
    try:
        subprocess.run([a.blender, "-b", "--factory-startup", "--python", me, "--", "scene"], env=env, check=True)
        # a new user's first start shows the splash (Quick Setup) over the viewport: preferences without it
        subprocess.run([a.blender, "-b", "--factory-startup", "--python-expr",
                        "import bpy; bpy.context.preferences.view.show_splash = False; bpy.ops.wm.save_userpref()"],
                       env=env, check=True)
        # event simulation lets the script press Esc during a run (and ignores real input)
        subprocess.run(["xvfb-run", "-a", "-s", f"-screen 0 {a.screen}x24", a.blender,
                        "--enable-event-simulate",
                        str(work / "demo.blend"), "--python", me, "--", "shoot"], env=env, check=True, timeout=900)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


# ------------------------------------------------------------------ inside Blender
def _args():
    return json.loads(os.environ["DCDI_SCREENSHOT_ARGS"])


def _material(bpy, name, color, checker=None):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    if checker:
        chk = nt.nodes.new("ShaderNodeTexChecker")
        chk.inputs["Scale"].default_value = checker
        chk.inputs["Color1"].default_value = color
        chk.inputs["Color2"].default_value = (0.05, 0.05, 0.06, 1.0)
        nt.links.new(chk.outputs["Color"], bsdf.inputs["Base Color"])
    else:
        bsdf.inputs["Base Color"].default_value = color
    return mat


def build_scene():
    """Spheres 1.2 to 10 m from the camera on a checker floor, sun and sky."""
    import bpy
    for coll in (bpy.data.objects, bpy.data.cameras, bpy.data.lights, bpy.data.meshes):
        for x in list(coll):
            coll.remove(x)
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    cam.location = (0.0, 0.0, 0.6)
    cam.rotation_euler = (math.radians(86.0), 0.0, 0.0)     # looking along +Y, slightly down
    scene.camera = cam
    bpy.ops.mesh.primitive_plane_add(size=60.0, location=(0.0, 20.0, 0.0))
    bpy.context.object.data.materials.append(_material(bpy, "floor", (0.8, 0.75, 0.6, 1.0), checker=60.0))
    colours = [(0.8, 0.1, 0.1, 1), (0.9, 0.6, 0.1, 1), (0.2, 0.7, 0.2, 1), (0.1, 0.4, 0.9, 1), (0.6, 0.2, 0.8, 1)]
    for i, (dist, x) in enumerate([(1.2, -0.25), (2.0, 0.3), (3.5, -0.7), (6.0, 1.2), (10.0, -2.0)]):
        r = 0.12 * (1 + 0.5 * i)
        bpy.ops.mesh.primitive_uv_sphere_add(radius=r, location=(x, dist, r), segments=48, ring_count=24)
        bpy.ops.object.shade_smooth()
        ob = bpy.context.object
        ob.name = f"Sphere {dist:g} m"
        ob.data.materials.append(_material(bpy, ob.name, colours[i], checker=8.0))
        ob.color = colours[i]                                 # the solid viewport's object colour
    # a string of small bright lights 9-12 m away: the balls a long lens's F12 shows
    glow = bpy.data.materials.new("bulb")
    glow.use_nodes = True
    nt = glow.node_tree
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Color"].default_value = (1.0, 0.78, 0.45, 1.0)
    emit.inputs["Strength"].default_value = 60.0
    nt.links.new(emit.outputs["Emission"], nt.nodes["Material Output"].inputs["Surface"])
    for k in range(18):
        dist = 9.0 + 3.0 * (k % 6) / 5.0
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.025, location=(-2.2 + 0.26 * k, dist, 1.1 + 0.25 * ((k % 3) - 1)),
                                             segments=12, ring_count=6)
        ob = bpy.context.object
        ob.name = f"Bulb {k}"
        ob.data.materials.append(glow)
        ob.color = (1.0, 0.8, 0.4, 1.0)
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), 0.0, math.radians(30))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("sky")
    world.color = (0.4, 0.5, 0.7)
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.5, 0.7, 1.0)
    scene.world = world
    scene.render.resolution_x, scene.render.resolution_y = 1280, 720
    bpy.ops.wm.save_as_mainfile(filepath=_args()["blend"])


def _install(bpy, zip_path):
    """Extension install (4.2+) or legacy add-on install; returns the module name."""
    if bpy.app.version >= (4, 2, 0):
        bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
        return "bl_ext.user_default.dcdi_lens_bokeh"
    bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
    bpy.ops.preferences.addon_enable(module="dcdi_lens_bokeh")
    return "dcdi_lens_bokeh"


def shoot():
    import bpy
    import numpy as np
    a = _args()
    if a["numpy_path"]:
        sys.path.insert(0, a["numpy_path"])
    out = Path(a["out"])
    out.mkdir(parents=True, exist_ok=True)
    module = _install(bpy, a["zip"])
    print("screenshots: enabled", module, flush=True)
    ctx = bpy.context
    scene = ctx.scene
    s = scene.dcdi_lens_bokeh
    s.lens = "6p"
    s.focus_mode = "OBJECT"
    s.focus_object = bpy.data.objects["Sphere 2 m"]
    s.keep_front, s.keep_behind = 0.25, 0.35
    s.preview_size = 480
    s.samples = 48
    win = ctx.window_manager.windows[0]
    screen = win.screen
    view3d = next(x for x in screen.areas if x.type == "VIEW_3D")
    with ctx.temp_override(window=win, area=view3d, region=view3d.regions[-1]):
        bpy.ops.dcdi.match_camera_to_lens()
    cam = scene.camera
    bpy.ops.object.select_all(action="DESELECT")
    cam.select_set(True)
    ctx.view_layer.objects.active = cam
    # three columns where the 3D view was: camera properties (the panel), the
    # camera view, an Image Editor for the result; the types are set in the
    # first tick, once the split areas have their coordinates
    cols = {}

    def split(factor):
        widest = max((x for x in screen.areas if x.type == "VIEW_3D"), key=lambda x: x.width)
        with ctx.temp_override(window=win, area=widest):
            bpy.ops.screen.area_split(direction="VERTICAL", factor=factor)

    def layout():
        areas = sorted((x for x in screen.areas if x.type == "VIEW_3D"), key=lambda x: x.x)
        cols["props"], cols["view"], cols["image"] = areas
        cols["props"].type = "PROPERTIES"
        cols["image"].type = "IMAGE_EDITOR"
        sp = cols["view"].spaces.active
        sp.region_3d.view_perspective = "CAMERA"
        sp.show_region_ui = False
        sp.shading.type = "SOLID"
        sp.shading.color_type = "OBJECT"
    state = {"t0": None, "phase": "start", "running_shot": False}

    # Screenshots are taken by a modal operator from its own timer, not from a
    # bpy.app timer under ``temp_override``: Blender 3.4 reads a Python context
    # override without the GIL when another Python thread holds it (the bokeh
    # worker), which crashed it (gdb: the main thread in PyDict_GetItemString
    # without the GIL while the worker ran numpy); a modal operator's context
    # is no Python dict.
    wanted = []

    class Shooter(bpy.types.Operator):
        bl_idname = "dcdi_screenshots.shooter"
        bl_label = "Screenshots"

        def invoke(self, context, event):
            self.timer = context.window_manager.event_timer_add(0.1, window=context.window)
            context.window_manager.modal_handler_add(self)
            return {"RUNNING_MODAL"}

        def modal(self, context, event):
            if event.type == "TIMER" and wanted:
                name = wanted.pop(0)
                # the X screen, not bpy.ops.screen.screenshot: Blender's own capture is black under
                # software OpenGL (Mesa's llvmpipe, as under Xvfb)
                subprocess.run(["import", "-window", "root", str(out / name)], check=True, timeout=60)
                print(f"screenshots: wrote {out / name}", flush=True)
            return {"PASS_THROUGH"}

    bpy.utils.register_class(Shooter)
    with ctx.temp_override(window=win, screen=screen, area=screen.areas[0]):
        bpy.ops.dcdi_screenshots.shooter("INVOKE_DEFAULT")

    def shot(name):
        wanted.append(name)

    def tick():
        try:
            return step()
        except Exception:
            import traceback
            traceback.print_exc()
            print("screenshots: failed, quitting", flush=True)
            bpy.ops.wm.quit_blender()
            return None

    def step():
        st = ctx.window_manager.dcdi_lens_bokeh_status
        if wanted:                                  # a screenshot first, then the next step
            return 0.1
        if state["phase"] == "start":
            split(0.3)
            state["phase"] = "split2"
            return 0.5
        if state["phase"] == "split2":
            split(0.42)
            state["phase"] = "layout"
            return 0.5
        if state["phase"] == "layout":
            layout()
            state["phase"] = "context"
            return 1.0
        if state["phase"] == "context":
            # (a new Properties editor knows its tabs only once drawn)
            for area in screen.areas:
                if area.type == "PROPERTIES":
                    area.spaces.active.context = "DATA"       # camera properties: the Lens Bokeh panel
            state["phase"] = "scroll"
            return 1.0
        if state["phase"] == "scroll":
            # scroll the camera properties so that the Lens Bokeh panel is in view
            area = cols["props"]
            region = next(r for r in area.regions if r.type == "WINDOW")
            with ctx.temp_override(window=win, area=area, region=region):
                bpy.ops.view2d.scroll_down(deltax=0, deltay=330)
            left = cols["view"]
            region = next(r for r in left.regions if r.type == "WINDOW")
            with ctx.temp_override(window=win, area=left, region=region):
                bpy.ops.view3d.view_center_camera()
                state["t0"] = time.perf_counter()
                bpy.ops.dcdi.apply_lens_bokeh("INVOKE_DEFAULT")
            state["phase"] = "running"
            return 2.0
        if state["phase"] == "running":
            if st.running:
                if not state["running_shot"] and st.progress > 5.0:
                    shot("addon-running.png")
                    state["running_shot"] = True
                return 0.5
            state["seconds"] = time.perf_counter() - state["t0"]
            print(f"screenshots: Apply Lens Bokeh (cold PSF cache) took {state['seconds']:.1f} s: "
                  f"{st.message}", flush=True)
            for area in screen.areas:
                if area.type == "IMAGE_EDITOR":
                    with ctx.temp_override(window=win, area=area, region=area.regions[-1]):
                        bpy.ops.image.view_all(fit_view=True)
            state["phase"] = "done"
            return 1.5
        if state["phase"] == "done":
            shot("addon-result.png")
            state["phase"] = "preview"
            return 0.5
        if state["phase"] == "preview":
            # Preview in Viewport: the lens's result over the camera view; then a focus change and its plane
            viewport = sys.modules[module + ".viewport"]
            if not st.viewport_preview:
                st.viewport_preview = True
                state["t0"] = time.perf_counter()
                return 0.2
            if not viewport.preview().log:
                return 0.2
            print(f"screenshots: preview first result {time.perf_counter() - state['t0']:.1f} s", flush=True)
            shot("addon-preview.png")
            state["phase"] = "focus-plane"
            return 1.0
        if state["phase"] == "focus-plane":
            viewport = sys.modules[module + ".viewport"]
            n = len(viewport.preview().log)
            # the focus plane is the frustum's section: from the camera it fills the frame, so the third
            # column becomes a 3D view from the side to show where it lies
            from mathutils import Euler
            side = cols["image"]
            side.type = "VIEW_3D"
            sp = side.spaces.active
            sp.shading.type, sp.shading.color_type = "SOLID", "OBJECT"
            sp.show_region_ui = sp.show_region_toolbar = False
            rv3d = sp.region_3d
            rv3d.view_perspective = "PERSP"
            rv3d.view_location = (0.0, 3.5, 0.4)
            rv3d.view_rotation = Euler((math.radians(62.0), 0.0, math.radians(-125.0))).to_quaternion()
            rv3d.view_distance = 9.0
            s.focus_mode, s.focus_distance = "DISTANCE", 3.5
            state["phase"], state["n"], state["t_change"] = "focus-plane-shot", n, time.perf_counter()
            return 0.2
        if state["phase"] == "focus-plane-shot":
            viewport = sys.modules[module + ".viewport"]
            if viewport.preview().focus_changed_at < state["t_change"]:
                return 0.05                       # the refresh has not started yet
            shot("addon-focus-plane.png")         # within FOCUS_PLANE_S of the change: the plane is drawn
            state["phase"] = "focus-plane-done"
            return 0.5
        if state["phase"] == "focus-plane-done":
            viewport = sys.modules[module + ".viewport"]
            if len(viewport.preview().log) <= state["n"]:
                return 0.1
            # the preview through a fast catalogue lens at two sizes: what its bokeh looks like there
            cols["image"].type = "IMAGE_EDITOR"
            s.lens, s.focus_mode, s.focus_object = "zeiss-sonnar-50mm-f1-5", "OBJECT", bpy.data.objects["Sphere 2 m"]
            s.keep_front = s.keep_behind = 0.0
            state["phase"], state["sizes"], state["n"] = "sizes", [320, 640], len(viewport.preview().log)
            return 0.5
        if state["phase"] == "sizes":
            viewport = sys.modules[module + ".viewport"]
            p = viewport.preview()
            if state.get("size") is None:
                state["size"] = state["sizes"].pop(0)
                s.preview_size, state["n"] = state["size"], len(p.log)
                return 0.3
            if len(p.log) <= state["n"] or p.worker is not None or p.changed_at is not None:
                return 0.1
            shot(f"addon-preview-{state['size']}.png")       # taken at the next tick: the preview stays on
            state["size"] = None
            if not state["sizes"]:
                state["phase"] = "f12"
            return 1.0
        if state["phase"] == "f12":
            # F12 through a long lens (Lens in Renders): a crop of the lights' balls, as the render shows them
            st.viewport_preview = False
            scene.cycles.samples = 32
            s.lens, s.focus_object = "mamiya-sekor-sf-150mm-f4", bpy.data.objects["Sphere 3.5 m"]
            s.lens_in_renders = True
            scene.render.use_lock_interface = True
            scene.render.resolution_x, scene.render.resolution_y = 1920, 1080
            t = time.perf_counter()
            bpy.ops.render.render()
            print(f"screenshots: F12 with Lens in Renders took {time.perf_counter() - t:.1f} s: "
                  f"{ctx.window_manager.dcdi_lens_bokeh_status.render_message!r}", flush=True)
            state["phase"], state["t0"] = "f12-crop", time.perf_counter()
            return 0.5
        if state["phase"] == "f12-crop":
            src = bpy.data.images.get("Lens Render")        # made on the main thread after the render
            if src is None and time.perf_counter() - state["t0"] < 30.0:
                return 0.5
            if src is not None:
                w, h = src.size
                px = np.empty(w * h * 4, np.float32)
                src.pixels.foreach_get(px)
                px = px.reshape(h, w, 4)
                y0, x0 = int(0.52 * h), int(0.15 * w)          # the lights' row (rows bottom up), its left part
                crop = np.ascontiguousarray(px[y0:y0 + 360, x0:x0 + 640])
                img = bpy.data.images.new("F12 crop", crop.shape[1], crop.shape[0], float_buffer=True)
                img.pixels.foreach_set(crop.ravel())
                img.save_render(str(Path(a["out"]) / "addon-f12-balls.png"), scene=scene)
                print("screenshots: saved addon-f12-balls.png", flush=True)
            s.lens_in_renders = False
            s.lens = "6p"
            state["phase"] = "warm"
            return 1.0
        if state["phase"] == "warm":
            # warm: the same again with the PSF cache filled
            t = time.perf_counter()
            bpy.ops.dcdi.apply_lens_bokeh()
            print(f"screenshots: Apply Lens Bokeh (warm, synchronous) took {time.perf_counter() - t:.1f} s",
                  flush=True)
            if not hasattr(win, "event_simulate") or not bpy.app.use_event_simulate:
                bpy.ops.wm.quit_blender()
                return None
            # Esc: another focus distance needs another (cold) library; press Esc while it builds
            s.focus_mode, s.focus_distance = "DISTANCE", 3.5
            left = cols["view"]
            region = next(r for r in left.regions if r.type == "WINDOW")
            with ctx.temp_override(window=win, area=left, region=region):
                bpy.ops.dcdi.apply_lens_bokeh("INVOKE_DEFAULT")
            state["phase"], state["t0"] = "esc", time.perf_counter()
            return 3.0
        if state["phase"] == "esc":
            state["esc_s"], state["esc_progress"] = time.perf_counter() - state["t0"], st.progress
            win.event_simulate(type="ESC", value="PRESS")
            win.event_simulate(type="ESC", value="RELEASE")
            state["phase"] = "after-esc"
            return 2.0
        jobs = sys.modules[module + ".session"].SESSION.jobs
        print(f"screenshots: Esc pressed {state['esc_s']:.1f} s into a cold PSF build "
              f"({state['esc_progress']:.0f} %); 2 s later: running={st.running}, message={st.message!r}, "
              f"worker threads left={len(jobs)}", flush=True)
        bpy.ops.wm.quit_blender()
        return None

    bpy.app.timers.register(tick, first_interval=2.0)


if __name__ == "__main__":
    if "bpy" in sys.modules or "--" in sys.argv and any(x in sys.argv for x in ("scene", "shoot")):
        mode = sys.argv[sys.argv.index("--") + 1]
        build_scene() if mode == "scene" else shoot()
    else:
        sys.exit(drive(sys.argv[1:]))
