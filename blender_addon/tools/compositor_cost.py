"""What keeping the scene's compositor costs a render through the lens (Lens
in Renders): the lens stage of F12 at 1920 x 1080 without a compositor and
with one (Render Layers -> Glare -> Group Output), alternated (the first
builds the PSFs; the later ones compare on a warm process).

    blender -b --factory-startup --python blender_addon/tools/compositor_cost.py -- [--lens 6p] [--samples 1]

The scene: the add-on tests' scene (tests/addon/addon_scene.py), Cycles on
the CPU. Prints, per render, the wall seconds of the whole F12 and of the
lens stage (``frames[i]['seconds']``: the passes read, the lens, and the
compositor's second Blender where kept) and what the compositor did.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", default="6p")
    ap.add_argument("--samples", type=int, default=1)
    if argv is None and "--" in sys.argv:
        argv = sys.argv[sys.argv.index("--") + 1:]
    args = ap.parse_args(argv)
    sys.path[:0] = [str(ROOT), str(ROOT / "tests" / "addon")]
    import bpy
    import blender_addon
    from addon_scene import build_scene
    scene, _, _ = build_scene()
    blender_addon.register()
    from blender_addon.session import SESSION
    r = scene.render
    r.engine, scene.cycles.samples, scene.cycles.use_denoising = "CYCLES", args.samples, False
    r.resolution_x, r.resolution_y, r.resolution_percentage = 1920, 1080, 100
    r.image_settings.file_format = "PNG"
    s = scene.dcdi_lens_bokeh
    s.lens, s.lens_in_renders = args.lens, True
    out = Path(bpy.app.tempdir or "/tmp")

    def once(tag):
        r.filepath = str(out / f"compositor-cost-{tag}.png")
        t = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        f = SESSION.last_render["frames"][-1]
        print(f"{tag}: F12 {time.perf_counter() - t:.2f} s, lens stage {f['seconds']:.2f} s, compositor: "
              f"{f['compositor'] or 'none'}")
    once("plain, first")
    once("plain")
    tree = bpy.data.node_groups.new("user compositor", "CompositorNodeTree")
    rl = tree.nodes.new("CompositorNodeRLayers")
    rl.scene = scene
    glare = tree.nodes.new("CompositorNodeGlare")
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    group_out = tree.nodes.new("NodeGroupOutput")
    tree.links.new(rl.outputs["Image"], glare.inputs[0])
    tree.links.new(glare.outputs[0], group_out.inputs[0])
    scene.compositing_node_group, r.use_compositing = tree, True
    once("glare, first")
    once("glare")
    r.use_compositing = False                         # the compositor off again: the same lens stage without it
    once("plain, again")
    r.use_compositing = True
    once("glare, again")
    blender_addon.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
