"""The add-on's waits, measured headless with the pip bpy module (one
process, the repository's add-on registered in place):

    python -m blender_addon.tools.addon_waits [--frames 24] [--samples 16] [--json out.json]
    blender -b --python blender_addon/tools/addon_waits.py -- [the same options]   # a Blender binary:
                                                             # its own Python (no scipy, numpy 2)

A scene of four checker spheres at 1.7-6 m before a wall at 8 m, 1920 x 1080,
the 6P lens (shipped Omni-Lens-Field), Cycles on the CPU:
- viewport preview at 480 x 270: the toggle's first result (cold: the
  engine's imports, the network, the render and the lens stage), then the
  lens stage after a focus change (warm);
- F12 at 1920 x 1080 with Lens in Renders: the render and the lens stage;
- an animation of ``--frames`` frames with a fixed focus: the lens stage of
  the first frame and of the others (the PSFs are built once).
Times are wall seconds with the process's CPU seconds beside them.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


def build(bpy, samples: int):
    """The add-on tests' scene (tests/addon/addon_scene.py: a camera at the
    origin, a checker wall 8 m away) with four checker spheres at 1.7-6 m
    in place of its cube, 1920 x 1080, Cycles on the CPU."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "addon"))
    from addon_scene import build_scene, emission_checker
    scene, cam, cube = build_scene()
    bpy.data.objects.remove(cube)
    for i, (x, d) in enumerate(((-0.9, 1.7), (-0.2, 2.6), (0.6, 4.0), (1.6, 6.0))):
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.25 * d / 2.0, location=(x * d / 2.0, 0.0, -d))
        bpy.context.object.data.materials.append(emission_checker(f"sphere{i}", 8.0))
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = 1920, 1080, 100
    r.engine = "CYCLES"
    scene.cycles.samples = samples
    scene.cycles.device = "CPU"
    return scene, cam


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--json", default=None)
    if argv is None and "--" in sys.argv:          # inside a Blender binary: its options end at "--"
        argv = sys.argv[sys.argv.index("--") + 1:]
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))     # the repository's add-on and engine
    import bpy
    import blender_addon
    blender_addon.register()
    from blender_addon import viewport
    from blender_addon.session import SESSION
    scene, cam = build(bpy, args.samples)
    s = scene.dcdi_lens_bokeh
    s.lens = "6p"
    bpy.ops.dcdi.match_camera_to_lens()
    s.focus_mode, s.focus_distance = "DISTANCE", 2.6
    s.keep_front = s.keep_behind = 0.0
    s.preview_size, s.samples = 480, args.samples
    out: dict = {"frames": args.frames, "samples": args.samples, "import_s": time.perf_counter() - t_start}
    P = viewport.preview()

    def settle():
        while (nxt := P.tick()) is not None:
            time.sleep(min(nxt, 0.02))

    t, c = time.perf_counter(), time.process_time()
    bpy.context.window_manager.dcdi_lens_bokeh_status.viewport_preview = True
    settle()
    out["preview_cold"] = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                           "render_s": P.result["render_s"], "lens_s": P.result["lens_s"]}
    warm = []
    for f in (1.7, 4.0, 6.0, 2.6):
        s.focus_distance = f
        P.changed(scene_changed=False)
        P.changed_at -= viewport.DEBOUNCE_S
        settle()
        warm.append(P.result["lens_s"])
    out["preview_warm_lens_s"] = warm
    bpy.context.window_manager.dcdi_lens_bokeh_status.viewport_preview = False

    s.lens_in_renders = True
    with tempfile.TemporaryDirectory() as d:
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.filepath = str(Path(d) / "still.exr")
        t, c = time.perf_counter(), time.process_time()
        bpy.ops.render.render(write_still=True)
        out["f12"] = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                      "lens_s": SESSION.last_render["frames"][0]["seconds"]}
        scene.frame_start, scene.frame_end = 1, args.frames
        scene.render.filepath = str(Path(d) / "anim" / "f_")
        t, c = time.perf_counter(), time.process_time()
        bpy.ops.render.render(animation=True)
        lens = [f["seconds"] for f in SESSION.last_render["frames"]]
        out["animation"] = {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                            "lens_first_s": lens[0], "lens_rest_mean_s": sum(lens[1:]) / max(1, len(lens) - 1),
                            "lens_total_s": sum(lens)}
    blender_addon.unregister()
    import numpy as np
    out["python"] = {"version": sys.version.split()[0], "numpy": np.__version__, "blender": bpy.app.version_string,
                     "scipy": _has("scipy"), "threadpoolctl": _has("threadpoolctl")}
    for k, v in out.items():
        print(f"{k}: {json.dumps(v)}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


def _has(module: str) -> bool:
    import importlib.util
    return importlib.util.find_spec(module) is not None


if __name__ == "__main__":
    sys.exit(main())
