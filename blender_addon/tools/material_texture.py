"""How much fine texture each material kind puts in a factory frame.

    python -m blender_addon.tools.material_texture [--kind bricks ...] [--seeds 2] [--resolution 480 640]
        [--textures DIR] [--old] [--png DIR]

For each kind of scenes.materials (``drawn``: each surface's kind drawn at
random, as the recipes do; with ``--old``, the factory's former two-colour
material), renders ``--seeds`` scenes in
which every surface carries that kind: a wall 4 m away filling the frame
and three boxes whose fronts stand at 1.2, 2 and 3 m, lit by a sun and a
grey sky; through the factory's camera (MOS-S1) and render settings (Cycles
CPU, 8 samples, denoised). Prints a Markdown table per kind: the
high-frequency share (dcdi_core.dataset.statistics: luminance spectral
energy above 0.1 cycles/px; pooled over the seeds), the 5th, 50th and 95th
percentiles of linear luminance, the clipped share, and wall and CPU
seconds per render (all threads; the machine may be shared: rough).
``--png DIR`` writes each frame as an sRGB PNG to look at.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_addon.factory.meters import cpu_seconds as _cpu_s  # noqa: E402
from blender_addon.factory.render import RenderSettings, empty_scene, setup_render  # noqa: E402
from blender_addon.factory.samples import sample_seed  # noqa: E402

OLD = "old"                 # the former recipes.material, for comparison
DRAWN = "drawn"             # each surface's kind drawn by surface_material (kind=None), as the recipes do
BOXES = ((-0.45, 1.2, 0.25), (0.5, 2.0, 0.45), (-0.9, 3.0, 0.6))    # (x, front depth, half size) m


def old_material(name: str, rng):
    """The factory's former material, kept here as the reference: one
    procedural texture (noise, Voronoi, checker or wave, 3-40 per unit of
    object coordinates) through a two-colour ramp."""
    import bpy
    kind = str(rng.choice(["noise", "voronoi", "checker", "wave"]))
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    bsdf = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    tex = nt.nodes.new({"noise": "ShaderNodeTexNoise", "voronoi": "ShaderNodeTexVoronoi",
                        "checker": "ShaderNodeTexChecker", "wave": "ShaderNodeTexWave"}[kind])
    tex.inputs["Scale"].default_value = float(rng.uniform(3.0, 40.0))
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    for e in ramp.color_ramp.elements:
        e.color = (*rng.uniform(0.02, 0.9, 3), 1.0)
    nt.links.new(tex.outputs["Distance" if kind == "voronoi" else 0 if kind == "checker" else "Factor"],
                 ramp.inputs["Factor"])
    nt.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = float(rng.uniform(0.3, 0.9))
    return mat


def _material(kind: str, name: str, rng, size_m: float, textures):
    if kind == OLD:
        return old_material(name, rng)
    from scenes.materials import surface_material
    return surface_material(name, rng, kind=None if kind == DRAWN else kind, textures=textures, size_m=size_m)[0]


def _add(kind: str, location, scale, mat, rotation=(0.0, 0.0, 0.0)):
    import bpy
    {"cube": bpy.ops.mesh.primitive_cube_add, "plane": bpy.ops.mesh.primitive_plane_add}[kind](
        location=tuple(float(v) for v in location), rotation=tuple(float(v) for v in rotation))
    obj = bpy.context.active_object
    obj.scale = tuple(float(v) for v in scale)
    obj.data.materials.append(mat)


def build_scene(kind: str, rng, textures=None) -> None:
    """The test scene in the current (empty) bpy scene, every surface of ``kind``."""
    import bpy
    _add("plane", (0, 0, -4.0), (4.0, 3.0, 1), _material(kind, "wall", rng, 8.0, textures))
    for i, (x, z, s) in enumerate(BOXES):
        _add("cube", (x, -0.3 + rng.uniform(-0.2, 0.2), -(z + s)), (s, s, s),
             _material(kind, f"box{i}", rng, 2 * s, textures), rotation=(0, rng.uniform(-0.4, 0.4), 0))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 2.2
    sun.rotation_euler = (0.5, 0.3, 0.2)
    bpy.context.scene.collection.objects.link(sun)
    w = bpy.data.worlds.new("world")
    bg = next(n for n in w.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
    bg.inputs["Color"].default_value = (0.5, 0.55, 0.6, 1.0)
    bg.inputs["Strength"].default_value = 0.35
    bpy.context.scene.world = w


def render_kind(kind: str, seed: int, height: int, width: int, textures=None, render=RenderSettings()):
    """(image (H, W, 3) linear float32, wall s, CPU s) of one scene of ``kind``."""
    import bpy

    from dcdi_core.io.images import read_image
    from dcdi_core.optics.lens import load_lens

    empty_scene()
    scene = bpy.context.scene
    build_scene(kind, np.random.default_rng(seed), textures)
    setup_render(scene, load_lens("mos-s1"), height, width, render, seed)
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f".dcdi-material-{os.getpid()}.exr"
    scene.render.filepath = str(tmp)
    t, c = time.perf_counter(), _cpu_s()
    bpy.ops.render.render(write_still=True)
    wall, cpu = time.perf_counter() - t, _cpu_s() - c
    img = read_image(tmp)
    tmp.unlink()
    return img, wall, cpu


def measure(kinds, seeds: int, height: int, width: int, textures=None, png_dir=None) -> list[dict]:
    """One row per kind: pooled HF share, luminance percentiles, clipped share, mean wall and CPU s."""
    from dcdi_core.dataset.statistics import LUMINANCE, clipped_fraction, spectral_energy
    from dcdi_core.io.images import write_image
    rows = []
    for kind in kinds:
        high = total = 0.0
        lum, clipped, walls, cpus = [], [], [], []
        for i in range(seeds):
            img, wall, cpu = render_kind(kind, sample_seed(0, i), height, width, textures)
            h, t = spectral_energy(img)
            high, total = high + h, total + t
            lum.append(img @ LUMINANCE.astype(np.float32))
            clipped.append(clipped_fraction(img))
            walls.append(wall), cpus.append(cpu)
            if png_dir is not None:
                Path(png_dir).mkdir(parents=True, exist_ok=True)
                write_image(Path(png_dir) / f"{kind}-{i}.png", np.clip(img, 0, 1))
        p5, p50, p95 = np.percentile(np.stack(lum), [5, 50, 95])
        rows.append({"kind": kind, "hf": high / total if total > 0 else 0.0, "p5": p5, "p50": p50, "p95": p95,
                     "clipped": float(np.mean(clipped)), "wall": float(np.mean(walls)), "cpu": float(np.mean(cpus))})
    return rows


def table(rows) -> str:
    lines = ["| kind | HF share | luminance p5 / p50 / p95 | clipped | wall s | CPU s |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['kind']} | {100 * r['hf']:.1f} % | {r['p5']:.3f} / {r['p50']:.3f} / {r['p95']:.3f} | "
                     f"{100 * r['clipped']:.2f} % | {r['wall']:.1f} | {r['cpu']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from scenes.materials import KINDS
    p = argparse.ArgumentParser(prog="material_texture", description=__doc__.split("\n\n")[0])
    p.add_argument("--kind", action="append", choices=[*KINDS, "image", DRAWN],
                   help="material kind (repeat; default: every kind of scenes.materials.KINDS); drawn: each "
                        "surface's kind drawn, as in the recipes")
    p.add_argument("--old", action="store_true", help="also the former two-colour recipes.material")
    p.add_argument("--textures", help="a folder of image textures (for --kind image)")
    p.add_argument("--seeds", type=int, default=2, help="scenes per kind (default 2)")
    p.add_argument("--resolution", type=int, nargs=2, default=[480, 640], metavar=("H", "W"))
    p.add_argument("--png", help="write each frame as an sRGB PNG into this folder")
    a = p.parse_args(argv)
    kinds = list(a.kind or KINDS) + ([OLD] if a.old else [])
    textures = None
    if a.textures or "image" in kinds:
        from dcdi_core.dataset.textures import TextureLibrary
        from dcdi_core.errors import InputRangeError
        if not a.textures:
            missing = InputRangeError("--textures", None, "a folder of images (for --kind image)")
            raise SystemExit(f"material_texture: error: {missing}")
        textures = TextureLibrary.from_folder(a.textures)
    print(table(measure(kinds, a.seeds, *a.resolution, textures=textures, png_dir=a.png)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
