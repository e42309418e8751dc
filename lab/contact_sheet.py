"""The lens catalogue's contact sheet: one scene through every lens wide
open, and one lens at several f-numbers.

The scene is the engine's synthetic RGB-D (``render.synthetic``: a red disk
at 1.2 m before a striped board at 3 m, a checker ground from 0.8 m, a wall
far away and six small lights at 6 m, made 30 x brighter here so that their
bokeh shows), at ``--size`` (default 240 x 360), spanning each lens's
sensor diagonal. Each lens is focused on the disk (1.2 m) with its PSFs
traced for the image's pitch (fields 16 image pixels apart, as the add-on's) (the occlusion-aware bokeh, `dcdi bokeh
--focus 1.2`); the apertures' sheet stops the Planar 50 mm f/1.4 to f/2.8
and f/8 and gives the f/8 six blades. The images are shown through the
sRGB curve, clipped at 1.

Writes ``contact-sheet.png`` and ``contact-sheet-apertures.png`` into
``--out`` and prints each image's time and PSF kernel. Run ``python -m lab
contact-sheet --out DIR`` (about 5 minutes on 2 cores; lenses/README.md).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

FOCUS_M = 1.2
LIGHT_GAIN = 30.0
FIELD_STEP_PX = 16.0
APERTURE_LENS = "zeiss-planar-50mm-f1-4"
APERTURES = ((None, 0), (2.8, 0), (8.0, 0), (8.0, 6))      # (f-number or wide open, blades)


def scene(height: int, width: int):
    """The synthetic RGB-D with its lights at 6 m made brighter (linear light)."""
    from dcdi_core.render.synthetic import synthetic_rgbd
    img, depth = synthetic_rgbd(height, width, seed=0)
    img = np.where((depth == 6.0)[..., None], img * LIGHT_GAIN, img)
    return img.astype(np.float32), depth


def through(lens, img, depth) -> tuple[np.ndarray, dict]:
    """The image through ``lens`` focused at FOCUS_M: (image, what it cost)."""
    from dcdi_core import app
    t, c = time.perf_counter(), time.process_time()
    psf = app.PSFRequest(field_step_px=FIELD_STEP_PX)      # the add-on's fields: 16 image pixels apart
    r = app.bokeh(app.BokehRequest(img, depth, lens, focus_m=FOCUS_M, psf=psf, image_name="the synthetic scene"))
    return r.image, {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                     "kernel": r.source.library.kernel_size, "source": r.source.kind}


def _srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def sheet(tiles: list[tuple[str, np.ndarray]], path: Path, cols: int) -> None:
    """A grid of labelled images."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = -(-len(tiles) // cols)
    h, w = tiles[0][1].shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(cols * w / 100, rows * (h + 28) / 100), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (label, im) in zip(axes.flat, tiles):
        ax.imshow(_srgb(im))
        ax.set_title(label, fontsize=7)
    fig.tight_layout(pad=0.3)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    import argparse
    from dcdi_core.optics.aperture import Aperture, stopped_down, wide_open_f_number
    from dcdi_core.optics.lens import available_lenses, load_lens
    p = argparse.ArgumentParser(prog="python -m lab contact-sheet",
                                description="the lens catalogue's contact sheet (module docstring)")
    p.add_argument("--out", required=True, help="folder for the two pictures")
    p.add_argument("--size", type=int, nargs=2, default=(240, 360), metavar=("H", "W"))
    p.add_argument("--lens", action="append", default=None, help="lens id (repeat; default: every lens)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    img, depth = scene(*args.size)
    tiles = [("all in focus (the input)", img)]
    print("| lens | f-number | wall s | CPU s | kernel px | PSFs |\n|---|---|---|---|---|---|")
    for lens_id in args.lens or available_lenses():
        lens = load_lens(lens_id)
        im, cost = through(lens, img, depth)
        n = wide_open_f_number(lens)
        tiles.append((f"{lens.name} (f/{n:.2g})", im))
        print(f"| {lens_id} | {n:.3g} | {cost['wall_s']:.1f} | {cost['cpu_s']:.1f} | {cost['kernel']} | "
              f"{cost['source']} |", flush=True)
    sheet(tiles, out / "contact-sheet.png", cols=4)
    lens = load_lens(APERTURE_LENS)
    tiles = []
    for f_number, blades in APERTURES:
        stopped = stopped_down(lens, Aperture(f_number, blades))
        im, cost = through(stopped, img, depth)
        label = stopped.iris or f"f/{wide_open_f_number(lens):.2g}"
        tiles.append((f"{lens.name}: {label}", im))
        print(f"| {APERTURE_LENS} | {label} | {cost['wall_s']:.1f} | {cost['cpu_s']:.1f} | {cost['kernel']} | "
              f"{cost['source']} |", flush=True)
    sheet(tiles, out / "contact-sheet-apertures.png", cols=4)
    print(f"wrote {out / 'contact-sheet.png'} and {out / 'contact-sheet-apertures.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
