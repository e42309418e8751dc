"""Render error against time for the dataset factory's Cycles settings.

    python -m blender_addon.render_noise [--recipe room] [--resolution 240 320]

Renders one seeded scene with several sample counts, denoised and not, and
compares each with a 256-sample denoised render (PSNR on linear values
clipped to [0, 1]); prints a Markdown table with the times.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from blender_addon.factory import render_rgbd  # noqa: E402


def render_noise_report(recipe: str = "room", height: int = 240, width: int = 320,
                        samples=(2, 4, 8, 16, 32), reference: int = 256, seed: int = 0) -> list[dict]:
    """Render error against time: each sample count (denoised) against a
    ``reference``-sample render of the same scene; PSNR on linear values
    clipped to [0, 1]."""
    from dcdi_core.optics.lens import load_lens

    lens = load_lens("mos-s1")
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f".dcdi-noise-{os.getpid()}.exr"
    t = time.perf_counter()
    ref, _ = render_rgbd(recipe, lens, seed, height, width, reference, True, tmp)
    t_ref = time.perf_counter() - t
    rows = [{"samples": reference, "seconds": t_ref, "psnr_db": math.inf}]
    for n in samples:
        for denoise in (True, False):
            t = time.perf_counter()
            img, _ = render_rgbd(recipe, lens, seed, height, width, n, denoise, tmp)
            dt = time.perf_counter() - t
            mse = float(((np.clip(img, 0, 1) - np.clip(ref, 0, 1)) ** 2).mean())
            rows.append({"samples": n, "denoise": denoise, "seconds": dt,
                         "psnr_db": 10 * math.log10(1.0 / mse) if mse > 0 else math.inf})
    return rows



def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="render_noise", description=__doc__.split("\n\n")[0])
    p.add_argument("--recipe", default="room")
    p.add_argument("--resolution", type=int, nargs=2, default=[240, 320], metavar=("H", "W"))
    p.add_argument("--reference", type=int, default=256)
    a = p.parse_args(argv)
    rows = render_noise_report(a.recipe, *a.resolution,
                               samples=[n for n in (2, 4, 8, 16, 32) if n < a.reference], reference=a.reference)
    print(f"| samples | denoised | PSNR dB vs {a.reference} samples | seconds |")
    print("|---|---|---|---|")
    for r in rows:
        psnr = "reference" if math.isinf(r["psnr_db"]) else f"{r['psnr_db']:.1f}"
        print(f"| {r['samples']} | {r.get('denoise', True)} | {psnr} | {r['seconds']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
