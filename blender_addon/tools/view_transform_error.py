"""The viewport preview's colours against F12's: the error of the add-on's
baked view transform (blender_addon/view_transform.py) against Blender's
own display of the same image, and its cost:

    python -m blender_addon.tools.view_transform_error [--size 480 270] [--json out.json]
    blender -b --factory-startup --python blender_addon/tools/view_transform_error.py -- [the same options]

For each of the scene view settings in CASES (the factory scene's
settings, then the case's; a setting this Blender lacks skips the case):
the table's bake (wall seconds) and, for two test images at ``--size``,
the table's display values against Blender's own (``Image.save_render`` of
the whole image through the scene's colour management, a 16-bit PNG read
back): the largest and the 99th-percentile absolute difference in 8-bit
display levels (1/255) and the PSNR (peak 1). The images: "random",
independent log-uniform channels over mid grey * 2**-12 to 2**10 (a
twentieth of them 0), saturated colours a render rarely holds; "ramp",
mid grey * 2**-12 to 2**10 left to right, in rows of grey and five hues.
Then the table's apply time at 480 x 270 and 1920 x 1080 (median of five),
and the checks the tests assert (tests/addon/test_view_transform.py; in
the real Blender tests/blender/test_view_transform_real.py): Standard
against the sRGB encoding, grey anchors of Blender's own display,
re-bakes on a change, non-finite inputs, the scene left as it was.
Prints a Markdown table; ``--json`` writes everything.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

# the display first: which view transforms there are depends on it
DEFAULTS = {"display_device": "sRGB", "view_transform": "AgX", "look": "None", "exposure": 0.0, "gamma": 1.0,
            "use_curve_mapping": False}
CASES = (
    ("AgX (Blender 5's default)", {}),
    ("AgX, look Punchy", {"look": "AgX - Punchy"}),
    ("AgX, exposure +1", {"exposure": 1.0}),
    ("AgX, Display P3", {"display_device": "Display P3"}),
    ("Filmic", {"view_transform": "Filmic"}),
    ("Standard", {"view_transform": "Standard"}),
    ("Standard, RGB curves", {"view_transform": "Standard", "use_curve_mapping": True}),
    ("AgX, gamma 0.8", {"gamma": 0.8}),
    ("Khronos PBR Neutral", {"view_transform": "Khronos PBR Neutral"}),
)
GREYS = (0.18, 1.0)                  # the grey anchors of Blender's own display, per case
HUES = ((1.0, 1.0, 1.0), (1.0, 0.2, 0.1), (0.1, 1.0, 0.2), (0.1, 0.2, 1.0), (1.0, 1.0, 0.1), (0.8, 0.1, 1.0))


def test_images(h: int, w: int, seed: int = 0) -> dict[str, np.ndarray]:
    """The two test images (module docstring), (h, w, 3) float32 scene-linear."""
    rng = np.random.default_rng(seed)
    rnd = (0.18 * np.exp2(rng.uniform(-12.0, 10.0, (h, w, 3)))).astype(np.float32)
    rnd[rng.random((h, w, 3)) < 0.05] = 0.0
    rows = np.repeat(np.asarray(HUES, np.float32), h // len(HUES) + 1, axis=0)[:h]
    ramp = (0.18 * np.exp2(np.linspace(-12.0, 10.0, w)))[None, :, None] * rows[:, None, :]
    return {"random": rnd, "ramp": ramp.astype(np.float32)}


def compare(a: np.ndarray, b: np.ndarray) -> dict:
    """max and 99th-percentile |a - b| in 8-bit levels, PSNR (peak 1) in dB."""
    d = np.abs(a.astype(np.float64) - b)
    mse = float(np.mean(d ** 2))
    return {"max": float(d.max() * 255), "p99": float(np.percentile(d, 99) * 255),
            "psnr": float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))}


def set_view(scene, settings: dict) -> bool:
    """The factory view settings, then ``settings``; False when this Blender
    lacks one of them (a view transform, look or display of another name).
    Curves: the combined curve's middle point lifted (a visible change)."""
    view, display = scene.view_settings, scene.display_settings
    for name, value in {**DEFAULTS, **settings}.items():
        try:
            setattr(display if name == "display_device" else view, name, value)
        except (TypeError, ValueError):
            return False
    if view.use_curve_mapping:
        curve = view.curve_mapping.curves[3]                 # C: all channels
        while len(curve.points) > 2:
            curve.points.remove(curve.points[1])
        curve.points.new(0.5, 0.6)
        view.curve_mapping.update()
    return True


def _median_ms(fn, repeat: int = 5) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1000)


def measure(scene, size=(480, 270)) -> dict:
    """Everything the module docstring lists, as a dict (JSON-ready)."""
    import bpy
    from blender_addon import view_transform as vt
    w, h = size
    images = test_images(h, w)
    out = {"blender": bpy.app.version_string, "python": platform.python_version(), "numpy": np.__version__,
           "size": [w, h], "steps_per_stop": vt.STEPS_PER_STOP, "cases": []}
    for name, settings in CASES:
        if not set_view(scene, settings):
            out["cases"].append({"name": name, "settings": settings, "absent": True})
            continue
        table = vt.bake(scene)
        case = {"name": name, "settings": settings, "levels": len(table.levels), "bake_s": table.bake_s,
                "greys": vt.blender_display(scene, np.repeat(np.asarray(GREYS, np.float32), 3)
                                            .reshape(1, -1, 3))[0, :, 0].tolist()}
        for key, img in images.items():
            case[key] = compare(vt.apply(table, img), vt.blender_display(scene, img))
        out["cases"].append(case)
    set_view(scene, {})
    table = vt.bake(scene)
    big = test_images(1080, 1920, seed=1)["random"]
    out["apply_ms"] = {"480x270": _median_ms(lambda: vt.apply(table, big[:270, :480])),
                       "1920x1080": _median_ms(lambda: vt.apply(table, big))}
    out["checks"] = checks(scene, images)
    return out


def checks(scene, images: dict) -> dict:
    """What the tests assert beyond the bound (module docstring)."""
    import bpy
    from blender_addon import view_transform as vt
    from dcdi_core.io.images import linear_to_srgb
    res = {}
    # Standard, no look, exposure 0, gamma 1, sRGB: the sRGB encoding of the colour clipped to [0, 1]
    set_view(scene, {"view_transform": "Standard"})
    res["standard_vs_srgb"] = {k: compare(vt.to_display(img, scene), linear_to_srgb(np.clip(img, 0.0, 1.0)))
                               for k, img in images.items()}
    # a table is baked once per view settings; a change bakes another, whose display differs
    bakes = []
    real_bake = vt.bake
    vt.bake = lambda s, *a, **k: bakes.append(s.view_settings.view_transform) or real_bake(s, *a, **k)
    before = {"scenes": len(bpy.data.scenes), "images": len(bpy.data.images),
              "format": scene.render.image_settings.file_format, "depth": scene.render.image_settings.color_depth,
              "dither": scene.render.dither_intensity}
    try:
        vt.forget()
        ramp = images["ramp"]
        set_view(scene, {})
        agx = vt.to_display(ramp, scene)
        agx_again = vt.to_display(ramp, scene)
        set_view(scene, {"view_transform": "Standard"})
        standard = vt.to_display(ramp, scene)
        set_view(scene, {"exposure": 1.0})
        brighter = vt.to_display(ramp, scene)
        set_view(scene, {"exposure": 1.0})               # the same settings again: kept
        vt.to_display(ramp, scene)
    finally:
        vt.bake = real_bake
    res["rebake"] = {"bakes": bakes, "kept": vt.tables_kept(),
                     "same_output_again": bool(np.array_equal(agx, agx_again)),
                     "agx_vs_standard": compare(agx, standard), "agx_vs_exposure_1": compare(agx, brighter)}
    res["scene_after"] = {"scenes": len(bpy.data.scenes), "images": len(bpy.data.images),
                          "format": scene.render.image_settings.file_format,
                          "depth": scene.render.image_settings.color_depth, "dither": scene.render.dither_intensity}
    res["scene_before"] = before
    # non-finite and negative inputs: as 0, or (+inf and beyond the grid) as its top
    set_view(scene, {})
    t = vt.table(scene)
    bad = np.array([np.nan, np.inf, -np.inf, -1.0, -1e30, 1e30, 0.0, 0.5, 3e38], np.float32)
    taken_as = np.array([0.0, t.high, 0.0, 0.0, 0.0, t.high, 0.0, 0.5, t.high], np.float32)
    ijk = np.stack(np.meshgrid(*[np.arange(len(bad))] * 3, indexing="ij"), axis=-1).reshape(1, -1, 3)
    shown = vt.apply(t, bad[ijk])
    ref = vt.apply(t, taken_as[ijk])
    # the interpolation: exact for a table that is affine in the grid's index (a tetrahedron's corners
    # span it), the index of a value computed here apart from the module's
    rng = np.random.default_rng(2)
    n = len(t.levels)
    coef = rng.uniform(-1.0, 1.0, (3, 3)) / (7 * n)          # values within (0, 1): nothing clipped
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).astype(np.float64)
    affine = vt.Table(t.key, (0.5 + idx @ coef).astype(np.float32), t.levels, t.low, t.high, t.steps_per_stop, 0.0)
    x = np.concatenate([t.levels[rng.integers(0, n, (4000, 3))],
                        np.exp2(rng.uniform(np.log2(t.low) - 3, np.log2(t.high), (20000, 3)))]).astype(np.float32)
    x[rng.random(x.shape) < 0.1] = 0.0
    index = np.where(x < t.low, x / t.low, 1 + (np.log2(np.maximum(x, t.low)) - np.log2(t.low)) * t.steps_per_stop)
    want = 0.5 + index @ coef
    res["affine"] = {"max_abs": float(np.abs(vt.apply(affine, x) - want).max()),
                     "range": [float(want.min()), float(want.max())]}
    res["nonfinite"] = {"finite": bool(np.isfinite(shown).all()), "min": float(shown.min()), "max": float(shown.max()),
                        "as_clipped": bool(np.array_equal(shown, ref)), "shape": list(shown.shape)}
    return res


def table_markdown(m: dict) -> str:
    rows = [f"| view settings (Blender {m['blender']}) | bake s | random colours: max / p99 levels, PSNR | "
            "ramp: max / p99 levels, PSNR |", "|---|---|---|---|"]
    for c in m["cases"]:
        if c.get("absent"):
            rows.append(f"| {c['name']} | not in this Blender | | |")
            continue
        cells = [f"{c[k]['max']:.2f} / {c[k]['p99']:.2f}, {c[k]['psnr']:.1f} dB" for k in ("random", "ramp")]
        rows.append(f"| {c['name']} | {c['bake_s']:.2f} | {cells[0]} | {cells[1]} |")
    a = m["apply_ms"]
    rows.append(f"\napply: {a['480x270']:.1f} ms at 480 x 270, {a['1920x1080']:.0f} ms at 1920 x 1080; "
                f"{m['cases'][0].get('levels')} levels per channel ({m['steps_per_stop']} a stop); "
                f"Python {m['python']}, numpy {m['numpy']}")
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, nargs=2, default=(480, 270), metavar=("W", "H"))
    ap.add_argument("--json", default=None)
    if argv is None and "--" in sys.argv:          # inside a Blender binary: its options end at "--"
        argv = sys.argv[sys.argv.index("--") + 1:]
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))     # the repository's add-on and engine
    import bpy
    m = measure(bpy.context.scene, tuple(args.size))
    print(table_markdown(m), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(m, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
