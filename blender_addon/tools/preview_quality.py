"""Error against time of the viewport preview's traced PSFs (logic.PREVIEW_TRACE)
against the full trace Apply Lens Bokeh and renders use:

    python -m blender_addon.tools.preview_quality [--size 480 270] [--lenses mos-s1 mos-s2]

For each lens refocused at each distance (no shipped PSF source holds a
refocused minimalist lens, so its PSFs are traced): the bokeh of a
dead-leaves RGB-D frame (metric depth 0.7-20 m) at the preview's size,
with the PSFs traced from a cold cache at the full settings and at each
candidate quality; the wall seconds of each (PSFs and bokeh) and the PSNR
of each preview against the full result (linear, peak 1). Prints a
Markdown table. No bpy: the add-on's logic runs as the preview runs it.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

CANDIDATES = ({"pupil_samples": 16, "n_wavelengths": 7}, {"pupil_samples": 24, "n_wavelengths": 9},
              {"pupil_samples": 32, "n_wavelengths": 11})


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, nargs=2, default=(480, 270), metavar=("W", "H"))
    ap.add_argument("--lenses", nargs="+", default=["mos-s1", "mos-s2"])
    ap.add_argument("--focus", type=float, nargs="+", default=[1.5, 4.0])
    a = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from blender_addon import logic
    from dcdi_core.dataset.leaves import leaves_rgbd
    from dcdi_core.optics.lens import load_lens
    w, h = a.size
    img, depth, _ = leaves_rgbd(0, h, w)
    print(f"preview quality: {w} x {h} dead leaves, depths {np.nanmin(depth):.2f}-{np.nanmax(depth[np.isfinite(depth)]):.1f} m;"
          " cold PSF cache for every row")
    print("| lens | focus m | PSFs | pupil x wavelengths | wall s | PSNR vs full dB |")
    print("|---|---|---|---|---|---|")
    from dcdi_core.psf.compute import PSFSettings
    full_settings = PSFSettings()
    for lens_id in a.lenses:
        lens = load_lens(lens_id)
        for focus in a.focus:
            rows = [("full", {"pupil_samples": full_settings.pupil_samples,
                              "n_wavelengths": full_settings.n_wavelengths})] + [("preview", c) for c in CANDIDATES]
            ref = None
            for name, q in rows:
                with tempfile.TemporaryDirectory() as cache:
                    os.environ["DCDI_CACHE_DIR"] = cache
                    logic.clear_psf_sources()
                    saved = dict(logic.PREVIEW_TRACE)
                    logic.PREVIEW_TRACE.clear()
                    logic.PREVIEW_TRACE.update(q)
                    t = time.perf_counter()
                    out, info = logic.run_bokeh(img, depth, lens, focus_m=focus, keep=(focus, focus),
                                                preview=name == "preview")
                    secs = time.perf_counter() - t
                    logic.PREVIEW_TRACE.clear()
                    logic.PREVIEW_TRACE.update(saved)
                if ref is None:
                    ref = out
                shipped = " (shipped)" if name == "preview" and q == saved else ""
                err = "reference" if name == "full" else f"{psnr(out, ref):.1f}"
                print(f"| {lens_id} | {focus:g} | {info['psf_source']} {info['psf_quality']}{shipped} | "
                      f"{q['pupil_samples']}^2 x {q['n_wavelengths']} | {secs:.2f} | {err} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
