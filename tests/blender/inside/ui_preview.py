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

A heartbeat (``common.Heartbeat``: a timer every 20 ms on the main
thread) runs throughout; each change records the longest gap between its
beats from the change to the new result drawn (``heartbeat``), the
longest single call of the add-on's timers, handlers and draw callbacks
in that time (``addon_call``), and the seconds from the change to the
refresh (``seconds``) and to the new result drawn in the 3D view
(``drawn_s``). At the end (the preview off) the planar Z drawn on the GPU
(``gpu_capture``, beside this script) is compared with a Cycles render's
Z pass of the same camera (``depth_check``), on the test scene with a
subdivided sphere and a tilted plane added.

Arguments (DCDI_TEST_ARGS): zip, out, lens, preview_size, resolution [w, h],
shading (the 3D view's, default SOLID), viewport_aa (the preferences'
Viewport Anti-Aliasing, default OFF).
"""
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (ARGS, MODULE, OUT, RESULT, CallTimer, Heartbeat, build_scene, install, run_steps,  # noqa: E402
                    wait_until)
import gpu_capture  # noqa: E402
import uidrive  # noqa: E402

import bpy  # noqa: E402
import numpy as np  # noqa: E402

REFRESH_LIMIT_S = float(ARGS.get("refresh_limit_s", 60.0))
DRAWN_LIMIT_S = 10.0         # the longest from a refresh to its result drawn in the 3D view
SHADING = ARGS.get("shading", "SOLID")
HEART = Heartbeat()
HEART.start()
CALLS = CallTimer()

scene, cam, cube = build_scene()
scene.render.resolution_x, scene.render.resolution_y = ARGS.get("resolution", (1920, 1080))
# the Solid view's anti-aliasing draws the view again 8 times after every change of the scene, each 0.2-0.3 s
# of the main thread on llvmpipe: Blender's cost, whatever the add-on does; off, the heartbeat sees the add-on's
bpy.context.preferences.system.viewport_aa = RESULT["viewport_aa"] = ARGS.get("viewport_aa", "OFF")
RESULT["install"], RESULT["install_s"] = install(ARGS["zip"])
viewport = importlib.import_module(f"{MODULE}.viewport")
operators = importlib.import_module(f"{MODULE}.operators")
P = viewport.preview()
# the add-on's functions that run on the main thread, timed (before the toggle registers them)
# (and the result's texture: ``_texture``, seen apart, below)
TIMED = ("_tick", "_watch", "draw_preview", "draw_focus_plane", "on_depsgraph_update", "on_frame_change",
         "settings_changed", "_texture")
for _name in TIMED[:-1]:
    setattr(viewport, _name, CALLS.wrap(getattr(viewport, _name), _name))
viewport._APP_HANDLERS = tuple((_hook, getattr(viewport, _fn.__name__)) for _hook, _fn in viewport._APP_HANDLERS)
DRAWS: list = []             # when a 3D view drew the preview's texture
STARTS: list = []            # (time, change) of each change
ACTED: list = [None]         # when a change through the UI sent its input (after finding its widget)
MADE: list = [0.0]           # when the preview's textures were made
_made_texture = viewport._texture


MADE_OF: list = [None]       # the image the last texture was made of


def _timed_texture(image, *display):
    tex = _made_texture(image, *display)
    MADE.append(time.perf_counter())
    MADE_OF[0] = image
    return tex


viewport._texture = CALLS.wrap(_timed_texture, "_texture")


def _seen_draw():
    if P.enabled and P.texture is not None:
        DRAWS.append(time.perf_counter())


bpy.types.SpaceView3D.draw_handler_add(_seen_draw, (), "WINDOW", "POST_PIXEL")
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
    (OUT/<name>.npy, linear) with the texture drawn of it (OUT/<name>_texture.npy:
    the display values the add-on made of it, as drawn)."""
    area = view3d()
    region = region_of(area)
    with ctx.temp_override(window=win, area=area, region=region):
        x0, y0, x1, y1 = viewport._camera_frame_px(bpy.context)
    subprocess.run(["import", "-window", "root", str(OUT / f"{name}.png")], check=True, timeout=60)
    np.save(OUT / f"{name}.npy", P.result["image"])
    h, w = P.result["image"].shape[:2]
    drawn = np.asarray(P.texture.read(), np.float32).reshape(h, w, -1)[::-1, :, :3]   # the texture's rows: bottom up
    np.save(OUT / f"{name}_texture.npy", drawn)
    top = win.height + win.y
    return {"png": f"{name}.png", "npy": f"{name}.npy", "texture": f"{name}_texture.npy",
            "texture_of_result": MADE_OF[0] is not None and np.array_equal(MADE_OF[0], P.result["image"]),
            "window": [win.x, win.y, win.width, win.height],
            "box": [win.x + region.x + x0, top - (region.y + y1), win.x + region.x + x1, top - (region.y + y0)]}


def shown() -> dict:
    r = P.result
    return {"focus_m": r["info"]["focus_m"], "keep_m": r["info"]["keep_m"], "refocus": r["info"]["refocus"],
            "pupil_mm": P.last_pupil_mm,
            "shape": list(r["image"].shape), "psf_source": r["info"].get("psf_source")}


def change(name, via, fn):
    """A sub-generator: make the change, wait for the refresh and its
    result drawn, record them with the heartbeat's longest gap."""
    n, renders = len(P.log), P.renders
    main = getattr(P, "main_renders", None)
    ACTED[0] = None
    t = time.perf_counter()
    yield from fn()
    t = ACTED[0] or t                # the UI's input, not the search for its widget, starts the wait
    STARTS.append((t, f"{via} {name}"))
    waited = yield from wait_until(lambda: len(P.log) > n and P.worker is None and P.changed_at is None,
                                   REFRESH_LIMIT_S)
    rec = {"change": name, "via": via, "refreshed": waited is not None, "error": P.error}
    t_end = time.perf_counter()
    if waited is not None:
        log = P.log[-1]
        refreshed_at = time.perf_counter()
        made = MADE[-1]                   # the shown result's texture (made when the refresh was collected)
        drawn = yield from wait_until(lambda: bool(DRAWS) and DRAWS[-1] >= made, DRAWN_LIMIT_S)
        t_end = time.perf_counter()
        first_draw = next((d for d in DRAWS if d >= made), None)
        # (an add-on build without ``wanted``, run to show this test failing on it, is judged by refreshes)
        asked = viewport.wanted(ctx) if hasattr(viewport, "wanted") else (None, P.served and P.served[1])
        rec.update(seconds=round(refreshed_at - t, 3), refreshes=len(P.log) - n,
                   drawn_s=None if drawn is None or first_draw is None else round(first_draw - t, 3),
                   rendered=P.renders > renders, render_s=round(log["render_s"], 3),
                   main_render=None if main is None else P.main_renders > main, source=log.get("source"),
                   main_s=log.get("main_s"), render_steps=log.get("render_steps"),
                   lens_s=round(log["lens_s"], 3), display_ahead=log.get("display_ahead"), current=P.served is not None and asked[1] == P.served[1],
                   shown=shown())
    rec["heartbeat"] = HEART.longest(t, t_end)
    rec["addon_call"] = CALLS.longest(t, t_end, names=TIMED[:-1])
    rec["texture_call"] = CALLS.longest(t, t_end, names=("_texture",))
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
    sp.shading.type = SHADING
    sp.show_region_toolbar = sp.show_region_ui = False
    yield 0.3
    with ctx.temp_override(window=win, area=area, region=region_of(area)):
        bpy.ops.view3d.view_center_camera()
    yield 0.5
    t = time.perf_counter()
    yield from wait_until(lambda: not gpu_capture.compiling(), 120.0, 0.1)     # the viewport's shaders
    yield 2.0
    RESULT["shading"], RESULT["shaders_s"] = SHADING, round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    yield 2.0
    RESULT["idle_heartbeat"] = HEART.longest(t)                # nothing changing: the baseline
    t = time.perf_counter()
    for _ in range(4):                                         # what one drawing of the 3D view costs
        area.tag_redraw()
        yield 0.6
    RESULT["redraw_heartbeat"] = HEART.longest(t)

    # what drawing the panel does before its switch can be clicked: the render worker starts warm
    viewport.warm_up(bpy.context)
    t = time.perf_counter()
    yield from wait_until(lambda: P.worker_renders.ready.is_set(), 60.0, 0.05)
    RESULT["warm_s"] = round(time.perf_counter() - t, 3)
    RESULT["warm_table"] = P.worker_renders.warm_table is not None
    yield 1.0

    def toggle():
        status.viewport_preview = True
        yield 0.0
    yield from change("toggle", "python", toggle)
    t = time.perf_counter()
    yield 2.0
    RESULT["idle_on_heartbeat"] = HEART.longest(t)             # the preview on, nothing changing
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
    yield from change("lens again", "python", python_set(s, "lens", "6p"))

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

    yield from accumulation()
    yield from ui_changes()
    yield from blade_rotation()
    yield from worker_fails()
    status.viewport_preview = False
    yield 0.2
    RESULT["after_off"] = {"enabled": P.enabled, "handlers": [viewport.on_depsgraph_update in
                                                              bpy.app.handlers.depsgraph_update_post]}
    yield from depth_check()
    timeline()


def timeline():
    """OUT/timeline.json: the heartbeat's gaps over 0.1 s, the add-on's
    calls over 0.01 s, the preview's draws and the changes' starts (seconds
    since the first change), to see what a gap overlapped."""
    t0 = STARTS[0][0] if STARTS else 0.0
    (OUT / "timeline.json").write_text(json.dumps({
        "gaps": [(round(a - t0, 3), round(b - a, 3), round(c, 3), round(q, 3)) for a, b, c, q in HEART.gaps
                 if b - a > 0.1],
        "calls": [(round(a - t0, 3), round(d, 3), n, round(o, 3)) for a, d, n, o in CALLS.calls if d > 0.01],
        "draws": [round(d - t0, 3) for d in DRAWS], "starts": [(round(a - t0, 3), n) for a, n in STARTS]}))


def accumulation():
    """Left alone, the preview asks the worker for more passes of the same
    view (other seeds) and shows the lens on their mean: closer to a
    render of as many samples than its first pass was."""
    def moved():
        cube.location.x -= 0.1
        yield 0.0
    yield from change("object moved back", "python", moved)
    first = P.sharp["rgb"].copy() if P.sharp is not None and P.sharp["passes"] == 1 else None
    t = time.perf_counter()
    done = yield from wait_until(lambda: P.served_passes >= P.accumulate_passes and P.worker is None,
                                 120.0, 0.1)
    rec = {"passes": P.served_passes, "wanted": P.accumulate_passes, "first_pass_kept": first is not None,
           "seconds": None if done is None else round(time.perf_counter() - t, 3),
           "heartbeat": HEART.longest(t), "renders_counted": P.renders, "accumulated": P.accumulated}
    if first is not None and done is not None:
        bpy_render = importlib.import_module(f"{MODULE}.bpy_render")
        h, w = first.shape[:2]
        ref, _ = bpy_render.render_aif_depth(scene, cam, h, w, s.samples * P.accumulate_passes,
                                              ctx.view_layer.name, seed=1000)
        rec["first_rms"] = float(np.sqrt(np.mean((first - ref) ** 2)))
        rec["mean_rms"] = float(np.sqrt(np.mean((P.sharp["rgb"] - ref) ** 2)))
        rec["shown_passes"] = P.result is not None and P.served_passes
    RESULT["accumulation"] = rec
    print(f"ui_preview: accumulation {rec}", flush=True)

    def moved_again():                   # the scene as the steps after this one (and the depth check) expect it
        cube.location.x += 0.1
        yield 0.0
    yield from change("object moved again", "python", moved_again)


def blade_rotation():
    """A catalogue lens stopped down to the camera's F-Stop with six blades,
    then the blades turned: each refreshes the preview."""
    def stopped_down():
        s.lens = "zeiss-jena-tessar-50mm-f2-8"
        cam.data.dof.aperture_fstop, cam.data.dof.aperture_blades = 8.0, 6
        s.use_camera_aperture = True
        yield 0.0
    yield from change("camera aperture, 6 blades", "python", stopped_down)
    yield from change("blade rotation", "python", python_set(cam.data.dof, "aperture_rotation", 0.5))


def worker_fails():
    """The render worker answers a render with an error: the preview renders
    in this Blender instead (and from then on, until the toggle)."""
    worker = getattr(P, "worker_renders", None)
    if worker is None:                       # an add-on build without the worker
        return
    request = worker.request

    def failing(*a, **k):
        pending = request(*a, **k)
        pending["done"].wait(60)
        pending["error"] = "a failure made by the test"
        return pending
    worker.request = failing

    def move():
        cube.location.x -= 0.1
        yield 0.0
    try:
        yield from change("object moved, the worker failing", "python", move)
    finally:
        worker.request = request
    RESULT["worker_failed"] = P.worker_failed
    yield from change("object moved after", "python", move)


def depth_check():
    """The GPU's planar Z and colour against a Cycles render of the same
    camera, on the test scene with a subdivided sphere and a tilted plane."""
    bpy_render = importlib.import_module(f"{MODULE}.bpy_render")
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5, location=(0.7, 0.3, -3.0))
    sphere = bpy.context.object
    sphere.modifiers.new("subd", "SUBSURF").levels = 2
    sphere.data.materials.append(bpy.data.materials["cube"])
    bpy.ops.mesh.primitive_plane_add(size=3.0, location=(-1.2, -0.4, -4.0), rotation=(1.1, 0.3, 0.0))
    bpy.context.object.data.materials.append(bpy.data.materials["wall"])
    yield 0.5
    h, w = 270, 480
    where = gpu_capture.camera_view(ctx)
    g = gpu_capture.GPUCapture()
    yield from wait_until(lambda: not gpu_capture.compiling(), 120.0, 0.1)
    t = time.perf_counter()
    rgb_g, z_g, _ = g.capture(ctx, scene, cam, h, w, where=where)
    first_s = time.perf_counter() - t
    t = time.perf_counter()
    rgb_g, z_g, _ = g.capture(ctx, scene, cam, h, w, where=where)
    again_s = time.perf_counter() - t
    t = time.perf_counter()
    rgb_c, z_c = bpy_render.render_aif_depth(scene, cam, h, w, 16, ctx.view_layer.name)
    cycles_s = time.perf_counter() - t
    np.save(OUT / "depth_gpu.npy", z_g)
    np.save(OUT / "depth_cycles.npy", z_c)
    np.save(OUT / "colour_gpu.npy", rgb_g)
    np.save(OUT / "colour_cycles.npy", rgb_c)
    bg_g, bg_c = z_g >= 1e9, z_c >= 1e9
    both = ~bg_g & ~bg_c
    rel = np.abs(z_g[both] - z_c[both]) / z_c[both]
    # silhouettes: pixels with a neighbour more than 5 % nearer or farther (in the Cycles Z)
    zc = np.where(bg_c, 1e10, z_c)
    pad = np.pad(zc, 1, mode="edge")
    nb = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    edge = (np.abs(nb - zc) > 0.05 * zc).any(axis=0)
    off = np.zeros_like(bg_g)
    off[both] = rel > 0.01
    RESULT["depth_check"] = {
        "shape": [h, w], "shading": SHADING, "gpu_first_s": round(first_s, 3), "gpu_s": round(again_s, 3),
        "cycles_s": round(cycles_s, 3), "background_mismatch": int((bg_g != bg_c).sum()),
        "median_rel": float(np.median(rel)), "p99_rel": float(np.percentile(rel, 99)),
        "p999_rel": float(np.percentile(rel, 99.9)), "over_1pct": int(off.sum()),
        "over_1pct_interior": int((off & ~edge).sum()), "edge_pixels": int(edge.sum()),
        "interior_max_rel": float(np.max(np.abs(z_g - z_c)[both & ~edge] / z_c[both & ~edge])),
        "colour_mean_abs": float(np.abs(rgb_g - rgb_c).mean()),
        "colour_p99_abs": float(np.percentile(np.abs(rgb_g - rgb_c), 99))}
    print(f"ui_preview: depth check {RESULT['depth_check']}", flush=True)


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
        panel up and looks again while it is out of view, and scans again
        where the panel moved since the last scan (Blender scrolls a field
        being edited at the region's edge into view)."""
        key = f"dcdi_lens_bokeh.{path}"
        for _ in range(4):
            if key in w:
                xy = w[key][len(w[key]) // 2]    # the middle of the widget: a line's shift above keeps it there
                if (yield from uidrive.path_at(win, *xy)) == key:
                    return xy
                w.clear()
                w.update((yield from widgets()))
                if key in w:
                    continue
            yield from uidrive.hover(win, region.x + region.width / 2, region.y + region.height / 2)
            uidrive._xdo("click", "--repeat", "6", "--delay", "10", "4")
            yield 0.3
            w.clear()
            w.update((yield from widgets()))
        assert key in w, f"the panel shows no {key} where it was looked for; found {sorted(w)}"
        return w[key][len(w[key]) // 2]

    def typed(path, text):
        def fn():
            xy = yield from at(path)
            ACTED[0] = time.perf_counter()
            yield from uidrive.type_value(win, *xy, text)
        return fn

    def clicked(path):
        def fn():
            xy = yield from at(path)
            ACTED[0] = time.perf_counter()
            yield from uidrive.click(win, *xy)
        return fn

    def wheeled(path):
        def fn():
            xy = yield from at(path)
            ACTED[0] = time.perf_counter()
            yield from uidrive.ctrl_wheel(win, *xy)
        return fn

    yield from change("focus distance", "ui", typed("focus_distance", "3"))
    yield from change("kept range", "ui", typed("keep_front", "0.4"))
    yield from change("refocus off", "ui", clicked("refocus"))
    RESULT["ui_preview_size_before"] = s.preview_size
    yield from change("preview size", "ui", typed("preview_size", "300"))
    RESULT["ui_preview_size"] = s.preview_size

    yield from change("lens", "ui", wheeled("lens"))
    RESULT["ui_lens"] = s.lens
    w.clear()              # another lens: the panel's lines about it differ, the widgets below it moved
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
        ACTED[0] = time.perf_counter()
        yield from uidrive.keys(win, cx, cy, "g", "x", "period", "1", "Return")
    yield from change("object moved", "ui", grab)
    RESULT["ui_moved_by"] = cube.location.x - x0

    def distance_mode():
        s.focus_mode = "DISTANCE"                # the keyframed focus is the panel's distance
        yield 0.0
    yield from change("focus mode distance", "python", distance_mode)

    def first_frame():
        ACTED[0] = time.perf_counter()
        yield from uidrive.keys(win, cx, cy, "shift+Left")     # Jump to Endpoint: the first frame
    yield from change("frame change", "ui", first_frame)
    RESULT["ui_frame"] = scene.frame_current


run_steps(steps())
