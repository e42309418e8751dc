"""The occlusion-aware bokeh's variants: error against the per-pixel reference, and time.

    python -m lab bokeh-variants [--quick]

The bench's scene (``bench_defocus``: 1280 x 1920 synthetic RGB-D, seed 0,
the 6P refocused at 1.2 m, ``--quick`` 320 x 480) rendered by each variant
of ``BokehOptions`` in one process, runs alternated, best of two: the exact
path (every layer at 16-px patches with the tent, the equal-width layers as
they are), the layers of a surface without a depth edge merged
(``seam_tol``), each layer's patches chosen from its kernels' interpolation
error (``interp_eps``), and both (the default). Each row: wall and CPU
seconds, PSNR and mean absolute error against the scattered per-pixel
reference on the five crops of ``bench_defocus`` (every pixel its own PSF),
per crop, and the PSNR against the exact path on the whole frame.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

VARIANTS = (("exact (16-px patches, tent; equal-width layers)", dict(interp_eps=None, seam_tol=None)),
            ("layers merged where no depth edge (seam_tol 0.25)", dict(interp_eps=None, seam_tol=0.25)),
            ("patches chosen per layer (interp_eps 0.002)", dict(interp_eps=0.002, seam_tol=None)),
            ("both: the default (seam_tol 0.25, interp_eps 0.002)", dict()),
            ("both, interp_eps 0.003", dict(interp_eps=0.003)),
            ("both, interp_eps 0.005", dict(interp_eps=0.005)),
            ("both, interp_eps 0.01", dict(interp_eps=0.01)))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab bokeh-variants",
                                description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="320 x 480 instead of 1280 x 1920")
    a = p.parse_args(argv)
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.psf.sources import open_library
    from dcdi_core.render.synthetic import synthetic_rgbd
    from .bench_defocus import FOCUS_M, _crops, _distances, _timed, crop_boxes
    from .bokeh_reference import crop_reference

    h, w = (320, 480) if a.quick else (1280, 1920)
    img, depth = synthetic_rgbd(h, w, seed=0)
    lens = load_lens("6p")
    geom = ImageGeometry.full_sensor(lens, h, w)
    lib = open_library(lens, geom, PSFSettings(focus_distance_m=FOCUS_M), fit_depth_m=depth)
    lib.ensure(depth, clamp_near=True)
    boxes = crop_boxes(depth, 32 if a.quick else 96)
    t = time.perf_counter()
    ref = np.stack([crop_reference(img, depth, lib, geom, b) for b in boxes.values()]).astype(np.float64)
    print(f"bokeh variants: {h} x {w} synthetic RGB-D (seed 0), 6P refocused at {FOCUS_M} m, kernel "
          f"{lib.kernel_size} px, {os.cpu_count()} CPU(s); reference on {len(boxes)} crops ({', '.join(boxes)}) "
          f"in {time.perf_counter() - t:.1f} s", flush=True)
    print(f"| variant | wall s | CPU s | layers | PSNR dB | mean abs | per crop dB | PSNR vs exact dB |")
    print("|---|---|---|---|---|---|---|---|")
    exact = None
    for name, kw in VARIANTS:
        opts = BokehOptions(focus_m=FOCUS_M, **kw)
        wall, cpu, r = _timed(lambda: bokeh(img, depth, lens, opts, library=lib), 2)
        exact = r.image if exact is None else exact
        crops = _crops(r.image, boxes)
        psnr, mae = _distances(crops, ref)
        per = " / ".join(f"{_distances(crops[i], ref[i])[0]:.1f}" for i in range(len(boxes)))
        vs = _distances(r.image, exact.astype(np.float64))[0]
        print(f"| {name} | {wall:.2f} | {cpu:.2f} | {r.info['layers']} | {psnr:.2f} | {mae:.4f} | {per} | "
              f"{'-' if vs == float('inf') else f'{vs:.1f}'} |", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
