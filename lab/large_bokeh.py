"""Large bokeh at full frame: the goal's case, timed as a whole job.

An 85 mm f/1.4 (the catalogue's Nikkor, wide open) at 1920 x 1080 spanning
its full-frame sensor, focused at 1.5 m on an elliptical subject, the rest
a textured background at 10 m with twenty small lights (40 x brighter) in
it: the background's blur is about 190 px across. ``app.bokeh`` as `dcdi
bokeh --focus 1.5` runs it (the occlusion-aware layers, the PSF work planned
for the CLI's default error budget, ``psf.budget``), PSFs from the lens's
ray map (as the add-on's Apply takes them; ``psf.raymap``).
Prints the wall and CPU seconds (PSFs, bokeh), the process's peak RSS, the
kernel size and what it clips. The goal: <= 4 s whole and <= 3 GB on 2
cores, kernels up to 400 px.

``--compare``: then the same image three ways with traced PSFs (the
PSF cache of the first run's pitch set aside): a reference whose 201-px
kernels hold the blur, every layer at full resolution; the kernels clipped
at 129 px (the renderer before ``BokehOptions.large_blur``); and the
default, the clipped layers at reduced resolution. The table gives time and
PSNR against the reference (its 99.9th percentile as the peak, the lights
clipped there).

Run ``python -m lab large-bokeh [--compare]`` (a minute; with --compare
several more).
"""
from __future__ import annotations

import os
import resource
import tempfile
import time
import warnings

import numpy as np

LENS = "nikkor-85mm-f1-4"
SIZE = (1080, 1920)
FOCUS_M, BACKGROUND_M = 1.5, 10.0


def scene(height: int, width: int, seed: int = 0):
    """(image (H, W, 3) float32 linear, depth (H, W) float32 m): the subject and the lit background."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:height, :width]
    img = (0.2 + 0.6 * rng.random((height, width, 3))).astype(np.float32)
    depth = np.full((height, width), BACKGROUND_M, np.float32)
    subject = ((xx - 0.4 * width) / (0.12 * width)) ** 2 + ((yy - 0.55 * height) / (0.3 * height)) ** 2 < 1
    depth[subject] = FOCUS_M
    for _ in range(20):
        cy, cx = rng.integers(50, height - 50), rng.integers(50, width - 50)
        if not subject[cy, cx]:
            img[cy - 2:cy + 3, cx - 2:cx + 3] = 40.0
    return img, depth


def main(argv=None) -> int:
    import argparse
    from dcdi_core import app
    from dcdi_core.optics.lens import load_lens
    p = argparse.ArgumentParser(prog="python -m lab large-bokeh",
                                description="large bokeh at full frame, timed (module docstring)")
    p.add_argument("--size", type=int, nargs=2, default=SIZE, metavar=("H", "W"))
    p.add_argument("--compare", action="store_true",
                   help="also against a reference with 201-px kernels and the clipped kernel (several minutes)")
    args = p.parse_args(argv)
    img, depth = scene(*args.size)
    lens = load_lens(LENS)
    with tempfile.TemporaryDirectory() as cache:
        os.environ["DCDI_CACHE_DIR"] = cache          # an empty PSF cache: what a first run pays
        t, c = time.perf_counter(), time.process_time()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            r = app.bokeh(app.BokehRequest(img, depth, lens, focus_m=FOCUS_M,
                                           psf=app.PSFRequest(max_error_db=app.DEFAULT_BUDGET_DB["render"])))
        wall, cpu = time.perf_counter() - t, time.process_time() - c
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{LENS} at {args.size[0]} x {args.size[1]}, focus {FOCUS_M} m, background {BACKGROUND_M} m: "
          f"{wall:.1f} s ({cpu:.1f} CPU s: PSFs {r.seconds['psfs']:.1f} s, bokeh {r.seconds['bokeh']:.1f} s), "
          f"peak RSS {peak:.0f} MiB, kernel {r.source.library.kernel_size} px ({r.source.kind})")
    for w in caught:
        print(f"  warning: {w.message}")
    f = r.info.get("large_blur_factor")
    print(f"  layers {r.info.get('layers')}, of which {r.info.get('large_blur_layers', 0)} blurred at 1/{f} of the "
          "resolution (PSFs at that pitch, from the same source)" if f else "  every layer at full resolution")
    if r.info.get("coarse_blur_layers"):
        print(f"  {r.info['coarse_blur_layers']} more layer(s) blurred at a coarser resolution by the error budget")
    if r.info.get("quality"):
        print(f"  plan: {r.info['quality']['plan']}")
    print(f"  goal: <= 4 s ({'met' if wall <= 4 else 'not met'}), <= 3 GB ({'met' if peak <= 3072 else 'not met'})")
    if args.compare:
        compare(img, depth, lens)
    return 0


def compare(img, depth, lens) -> None:
    """The large blur against a reference with a kernel that holds it (201 px,
    every layer at full resolution) and against the kernel clipped at 129 px,
    in this process (PSFs from the cache filled above where the same)."""
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.bokeh import BokehOptions, bokeh
    from dcdi_core.psf.library import MAX_FITTED_KERNEL
    rows = {}
    for name, opts in (("reference: 201-px kernels, full resolution",
                        dict(settings=PSFSettings(kernel_size=201), fit_kernel=False, large_blur=False)),
                       (f"clipped at {MAX_FITTED_KERNEL} px (before)", dict(large_blur=False)),
                       ("large blur at reduced resolution (default)", dict())):
        t, c = time.perf_counter(), time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = bokeh(img, depth, lens, BokehOptions(focus_m=FOCUS_M, **opts)).image
        rows[name] = (out, time.perf_counter() - t, time.process_time() - c)
    ref = next(iter(rows.values()))[0]
    peak = float(np.percentile(ref, 99.9))
    print("| renderer | wall s | CPU s | PSNR vs reference dB (peak: its 99.9th percentile) |\n|---|---|---|---|")
    for name, (out, wall, cpu) in rows.items():
        mse = float(np.mean((np.clip(out, 0, peak) - np.clip(ref, 0, peak)) ** 2))
        psnr = "-" if out is ref else f"{10 * np.log10(peak ** 2 / max(mse, 1e-30)):.2f}"
        print(f"| {name} | {wall:.1f} | {cpu:.1f} | {psnr} |")


if __name__ == "__main__":
    raise SystemExit(main())
