"""Run with a window (xvfb-run) by tests/blender/test_ui.py: the add-on
installed from its zip, the test scene in the camera view, Preview in
Viewport toggled on, then one change after another, each made through
Python (``via: python``) or through the UI (``via: ui``: Blender's event
simulation clicking and scrolling the panel's widgets). For each change:
whether and when the preview refreshed, whether it rendered anew or ran
the lens stage only, and whether what it shows is what the scene asks
for now. At two points the screen is captured (ImageMagick's ``import
-window root``: Blender's own screenshot is black under software OpenGL)
with the camera frame's box and the shown result, for the driver to
compare.

Arguments (DCDI_TEST_ARGS): zip, out, lens, preview_size, resolution [w, h].
"""
import importlib
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ARGS, MODULE, OUT, RESULT, build_scene, install, run_steps, wait_until  # noqa: E402
import uidrive  # noqa: E402

import bpy  # noqa: E402
import numpy as np  # noqa: E402

REFRESH_LIMIT_S = float(ARGS.get("refresh_limit_s", 60.0))

scene, cam, cube = build_scene()
scene.render.resolution_x, scene.render.resolution_y = ARGS.get("resolution", (1920, 1080))
RESULT["install"], RESULT["install_s"] = install(ARGS["zip"])
viewport = importlib.import_module(f"{MODULE}.viewport")
operators = importlib.import_module(f"{MODULE}.operators")
P = viewport.preview()
s = scene.dcdi_lens_bokeh
s.lens = ARGS.get("lens", "6p")
s.focus_mode = "DISTANCE"
s.focus_distance = 1.0
s.preview_size = ARGS.get("preview_size", 480)
s.samples = 4
ctx = bpy.context
win = ctx.window_manager.windows[0]
status = ctx.window_manager.dcdi_lens_bokeh_status
RESULT["changes"] = []


def view3d():
    return max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width)


def region_of(area, kind="WINDOW"):
    return next(r for r in area.regions if r.type == kind)


def capture(name: str) -> dict:
    """The screen as OUT/<name>.png, the camera frame's box on it (left, top,
    right, bottom in screen pixels, top-left origin) and the shown result
    (OUT/<name>.npy, linear)."""
    area = view3d()
    region = region_of(area)
    with ctx.temp_override(window=win, area=area, region=region):
        x0, y0, x1, y1 = viewport._camera_frame_px(bpy.context)
    subprocess.run(["import", "-window", "root", str(OUT / f"{name}.png")], check=True, timeout=60)
    np.save(OUT / f"{name}.npy", P.result["image"])
    top = win.height + win.y
    return {"png": f"{name}.png", "npy": f"{name}.npy", "window": [win.x, win.y, win.width, win.height],
            "box": [win.x + region.x + x0, top - (region.y + y1), win.x + region.x + x1, top - (region.y + y0)]}


def shown() -> dict:
    r = P.result
    return {"focus_m": r["info"]["focus_m"], "keep_m": r["info"]["keep_m"], "refocus": r["info"]["refocus"],
            "shape": list(r["image"].shape), "psf_source": r["info"].get("psf_source")}


def change(name, via, fn):
    """A sub-generator: make the change, wait for the refresh, record it."""
    n, renders = len(P.log), P.renders
    t = time.perf_counter()
    yield from fn()
    waited = yield from wait_until(lambda: len(P.log) > n and P.worker is None and P.changed_at is None,
                                   REFRESH_LIMIT_S)
    rec = {"change": name, "via": via, "refreshed": waited is not None, "error": P.error}
    if waited is not None:
        log = P.log[-1]
        # (an add-on build without ``wanted``, run to show this test failing on it, is judged by refreshes)
        asked = viewport.wanted(ctx) if hasattr(viewport, "wanted") else (None, P.served and P.served[1])
        rec.update(seconds=round(time.perf_counter() - t, 3), refreshes=len(P.log) - n,
                   rendered=P.renders > renders, render_s=round(log["render_s"], 3),
                   lens_s=round(log["lens_s"], 3), current=P.served is not None and asked[1] == P.served[1],
                   shown=shown())
    RESULT["changes"].append(rec)
    print(f"ui_preview: {rec}", flush=True)


def python_set(obj, attr, value):
    def fn():
        setattr(obj, attr, value)
        yield 0.0
    return fn


def steps():
    area = view3d()
    sp = area.spaces.active
    sp.region_3d.view_perspective = "CAMERA"
    sp.shading.type = "SOLID"
    sp.show_region_toolbar = sp.show_region_ui = False
    yield 0.3
    with ctx.temp_override(window=win, area=area, region=region_of(area)):
        bpy.ops.view3d.view_center_camera()
    yield 0.5

    def toggle():
        status.viewport_preview = True
        yield 0.0
    yield from change("toggle", "python", toggle)
    RESULT["first_capture"] = capture("first")

    yield from change("focus distance", "python", python_set(s, "focus_distance", 2.5))
    RESULT["focus_capture"] = capture("focus")
    yield from change("focus distance again", "python", python_set(s, "focus_distance", 1.2))

    def focus_object():
        s.focus_object = cube
        s.focus_mode = "OBJECT"
        yield 0.0
    yield from change("focus object", "python", focus_object)

    def camera_focus():
        cam.data.dof.focus_distance = 3.0
        s.focus_mode = "CAMERA"
        yield 0.0
    yield from change("camera focus mode", "python", camera_focus)
    yield from change("camera focus distance", "python", python_set(cam.data.dof, "focus_distance", 5.0))

    def back_to_distance():
        s.focus_mode = "DISTANCE"
        yield 0.0
    yield from change("focus mode distance", "python", back_to_distance)
    yield from change("kept range", "python", python_set(s, "keep_behind", 1.5))
    yield from change("refocus off", "python", python_set(s, "refocus", False))
    yield from change("refocus on", "python", python_set(s, "refocus", True))
    yield from change("preview size", "python", python_set(s, "preview_size", s.preview_size // 2))
    yield from change("lens", "python", python_set(s, "lens", "mos-s2"))

    def move():
        cube.location.x += 0.1
        yield 0.0
    yield from change("object moved", "python", move)

    def keyframed_focus():
        s.focus_distance = 1.0
        scene.keyframe_insert("dcdi_lens_bokeh.focus_distance", frame=1)
        s.focus_distance = 4.0
        scene.keyframe_insert("dcdi_lens_bokeh.focus_distance", frame=10)
        scene.frame_set(1)
        yield 0.0
    yield from change("keyframed focus, frame 1", "python", keyframed_focus)

    def frame_10():
        scene.frame_set(10)
        yield 0.0
    yield from change("frame change", "python", frame_10)
    RESULT["frame_10_focus"] = s.focus_distance

    yield from ui_changes()
    status.viewport_preview = False
    yield 0.2
    RESULT["after_off"] = {"enabled": P.enabled, "handlers": [viewport.on_depsgraph_update in
                                                              bpy.app.handlers.depsgraph_update_post]}


def ui_changes():
    """The same kinds of change made through the panel's widgets and the 3D
    view's shortcuts with real input (``uidrive``)."""
    bpy.ops.object.select_all(action="DESELECT")
    cam.select_set(True)
    ctx.view_layer.objects.active = cam              # the camera's properties show the Lens Bokeh panel
    props = next(a for a in win.screen.areas if a.type == "PROPERTIES")
    props.spaces.active.context = "DATA"
    yield 0.5
    region = region_of(props)
    yield from uidrive.hover(win, region.x + region.width / 2, region.y + region.height / 2)
    uidrive._xdo("click", "--repeat", "40", "--delay", "10", "5")      # scrolled to the panel at the end
    yield 0.5

    def widgets():
        found = yield from uidrive.scan(win, region)
        RESULT.setdefault("ui_widgets", []).append(sorted(found))
        return found

    w = yield from widgets()

    def at(path):
        """A sub-generator: where the widget of ``path`` is; scrolls the
        panel up and looks again while it is out of view."""
        key = f"dcdi_lens_bokeh.{path}"
        for _ in range(4):
            if key in w:
                break
            yield from uidrive.hover(win, region.x + region.width / 2, region.y + region.height / 2)
            uidrive._xdo("click", "--repeat", "6", "--delay", "10", "4")
            yield 0.3
            w.clear()
            w.update((yield from widgets()))
        assert key in w, f"the panel shows no {key} where it was looked for; found {sorted(w)}"
        return w[key][0]

    def typed(path, text):
        def fn():
            xy = yield from at(path)
            yield from uidrive.type_value(win, *xy, text)
        return fn

    def clicked(path):
        def fn():
            xy = yield from at(path)
            yield from uidrive.click(win, *xy)
        return fn

    def wheeled(path):
        def fn():
            xy = yield from at(path)
            yield from uidrive.ctrl_wheel(win, *xy)
        return fn

    yield from change("focus distance", "ui", typed("focus_distance", "3"))
    yield from change("kept range", "ui", typed("keep_front", "0.4"))
    yield from change("refocus off", "ui", clicked("refocus"))
    yield from change("preview size", "ui", typed("preview_size", "300"))

    yield from change("lens", "ui", wheeled("lens"))
    RESULT["ui_lens"] = s.lens
    # focus mode (an expanded enum): Ctrl + wheel over it steps to the next item
    yield from change("focus mode next", "ui", wheeled("focus_mode"))
    RESULT["ui_focus_mode_1"] = s.focus_mode
    yield from change("focus mode next again", "ui", wheeled("focus_mode"))
    RESULT["ui_focus_mode"] = s.focus_mode

    view = view3d()
    vr = region_of(view)
    cx, cy = vr.x + vr.width / 2, vr.y + vr.height / 2
    bpy.ops.object.select_all(action="DESELECT")
    cube.select_set(True)
    ctx.view_layer.objects.active = cube
    x0 = cube.location.x

    def grab():
        yield from uidrive.keys(win, cx, cy, "g", "x", "period", "1", "Return")
    yield from change("object moved", "ui", grab)
    RESULT["ui_moved_by"] = cube.location.x - x0

    def distance_mode():
        s.focus_mode = "DISTANCE"                # the keyframed focus is the panel's distance
        yield 0.0
    yield from change("focus mode distance", "python", distance_mode)

    def first_frame():
        yield from uidrive.keys(win, cx, cy, "shift+Left")     # Jump to Endpoint: the first frame
    yield from change("frame change", "ui", first_frame)
    RESULT["ui_frame"] = scene.frame_current


run_steps(steps())
