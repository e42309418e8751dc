"""What the preview's render worker costs the main thread on a production-size
scene: writing its scene copy (``render_worker.write_scene``) against
sending the placements of moved objects (``render_worker.placements``).

    blender -b --factory-startup --python blender_addon/tools/scene_copy_cost.py -- [--polygons 1000000]
        [--image-mb 200] [--repeat 3] [--json out.json]

The scene: the polygons as four textured grids, each material an image
file (float EXR of noise, ``--image-mb`` in all, written once to a
temporary folder), a camera. Timed: the copy written with the images as
files (their paths only), the copy written with the images packed into
the .blend (what a file with packed textures writes), and the placements
of one moved object and the camera, each ``--repeat`` times (the best
and the first kept; wall and CPU seconds; the copy goes to the same file
each time, as the worker's two files alternate). Prints a table and writes
``--json``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path


def build(bpy, np, polygons: int, image_mb: float, folder: Path):
    """Four grids of ``polygons`` in all, each with an image-textured material
    (an EXR file of ``image_mb`` / 4 MB of float RGBA); returns (scene, camera, grids)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    side = int(math.sqrt(image_mb * 1e6 / 4 / 16))             # float RGBA: 16 bytes a pixel
    cuts = int(math.sqrt(polygons / 4))
    grids = []
    for k in range(4):
        path = folder / f"texture{k}.exr"
        img = bpy.data.images.new(f"texture{k}", side, side, alpha=True, float_buffer=True)
        img.pixels.foreach_set(np.random.default_rng(k).random(side * side * 4, dtype=np.float32))
        img.filepath_raw, img.file_format = str(path), "OPEN_EXR"
        img.save()
        bpy.ops.mesh.primitive_grid_add(x_subdivisions=cuts, y_subdivisions=cuts, size=2,
                                        location=(2.2 * k - 3.3, 0.0, -4.0))
        ob = bpy.context.object
        mat = bpy.data.materials.new(f"material{k}")
        if not mat.node_tree:               # Blender 5 makes a material's nodes with it
            mat.use_nodes = True
        tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
        tex.image = img
        mat.node_tree.links.new(tex.outputs[0], mat.node_tree.nodes["Principled BSDF"].inputs[0])
        ob.data.materials.append(mat)
        grids.append(ob)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    return scene, cam, grids


def timed(fn, repeat: int) -> dict:
    """``repeat`` runs of ``fn()``: the first's and the best's wall seconds,
    and the best's CPU seconds."""
    runs = []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        runs.append((time.perf_counter() - t, time.process_time() - c))
    best = min(runs)
    return {"first_s": round(runs[0][0], 4), "wall_s": round(best[0], 4), "cpu_s": round(best[1], 4)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--polygons", type=int, default=1_000_000)
    ap.add_argument("--image-mb", type=float, default=200.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])
    import bpy
    import numpy as np
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from blender_addon.render_worker import placements, write_scene

    class Context:
        objects_in_mode = ()

    with tempfile.TemporaryDirectory(prefix="dcdi-scene-copy-") as tmp:
        folder = Path(tmp)
        scene, cam, grids = build(bpy, np, args.polygons, args.image_mb, folder)
        copy = folder / "copy.blend"
        out = {"polygons": sum(len(g.data.polygons) for g in grids),
               "image_mb": round(sum(os.path.getsize(folder / f"texture{k}.exr") for k in range(4)) / 1e6, 1)}
        out["write_files"] = timed(lambda: write_scene(Context, scene, copy), args.repeat)
        out["write_files"]["copy_mb"] = round(os.path.getsize(copy) / 1e6, 1)
        grids[0].location.x += 0.1
        out["placements"] = timed(lambda: json.dumps(placements(scene, cam, {grids[0].name})), args.repeat)
        for img in bpy.data.images:
            img.pack()
        out["write_packed"] = timed(lambda: write_scene(Context, scene, copy), args.repeat)
        out["write_packed"]["copy_mb"] = round(os.path.getsize(copy) / 1e6, 1)
    print(f"scene: {out['polygons']} polygons, {out['image_mb']} MB of image files")
    print("| the main thread's share | first, wall s | best, wall s | best, CPU s | copy MB |\n|---|---|---|---|---|")
    for key, what in (("write_files", "the copy written, images as files"),
                      ("write_packed", "the copy written, images packed"),
                      ("placements", "placements of a moved object and the camera")):
        r = out[key]
        print(f"| {what} | {r['first_s']:.3f} | {r['wall_s']:.3f} | {r['cpu_s']:.3f} | {r.get('copy_mb', '-')} |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)
