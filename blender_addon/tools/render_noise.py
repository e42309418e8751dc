"""Render error against time for the dataset factory's Cycles settings.

    python -m blender_addon.tools.render_noise [--recipe room [--recipe street ...]] [--resolution 480 640]

Renders seeded scenes with several settings (sample counts with and without
the denoiser, the denoiser's quality and prefilter, diffuse bounces) and
compares each with a high-sample render of the same scene (``--reference``
samples, denoised, HIGH quality, ACCURATE prefilter, the default bounces):
PSNR in dB on linear values clipped to [0, 1]; with several recipes the mean
of their PSNRs. Times per render: wall seconds and CPU seconds (user +
system of this process, all render threads: unlike wall time it does not
grow when other jobs share the machine). Prints a Markdown table; the
factory's defaults (blender_addon.factory.batch.RenderSettings) are chosen from it.
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from blender_addon.factory.render import RenderSettings, render_rgbd  # noqa: E402

# rows of the full table: (samples, denoise, quality, prefilter, diffuse bounces); None = the default's
FULL = ([(n, True, "HIGH", "ACCURATE", 2) for n in (4, 8, 16)]
        + [(n, False, "HIGH", "ACCURATE", 2) for n in (8, 32)]
        + [(8, True, q, p, 2) for q, p in (("HIGH", "FAST"), ("BALANCED", "ACCURATE"), ("BALANCED", "FAST"),
                                           ("FAST", "FAST"))]
        + [(n, True, "HIGH", "NONE", 2) for n in (6, 8, 12, 16)]
        + [(n, True, "HIGH", "FAST", 2) for n in (12, 16)]
        + [(None, None, None, None, b) for b in (1, 3)])


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _psnr(img, ref) -> float:
    mse = float(((np.clip(img, 0, 1) - np.clip(ref, 0, 1)) ** 2).mean())
    return 10 * math.log10(1.0 / mse) if mse > 0 else math.inf


def render_noise_report(recipes=("room",), height: int = 240, width: int = 320, rows=None,
                        reference: int = 256, seed: int = 0) -> list[dict]:
    """Render error against time for each row (samples, denoise, quality,
    prefilter, diffuse bounces) of ``rows`` (default: FULL), against a
    ``reference``-sample render of the same scenes. Returns dicts with the
    settings, ``psnr_db`` (mean over recipes), ``seconds`` (wall, mean per
    render) and ``cpu_seconds`` (mean per render)."""
    from dcdi_core.optics.lens import load_lens

    lens = load_lens("mos-s1")
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f".dcdi-noise-{os.getpid()}.exr"
    ref_settings = RenderSettings(samples=reference, denoising_quality="HIGH", denoising_prefilter="ACCURATE")
    # one throw-away render first: the first render of a process loads the denoiser's weights
    render_rgbd(recipes[0], lens, seed, min(height, 16), min(width, 16), RenderSettings(samples=1), tmp)
    refs, t_ref, c_ref = {}, 0.0, 0.0
    for r in recipes:
        t, c = time.perf_counter(), _cpu_s()
        refs[r], _ = render_rgbd(r, lens, seed, height, width, ref_settings, tmp)
        t_ref += time.perf_counter() - t
        c_ref += _cpu_s() - c
    out = [{"settings": ref_settings, "seconds": t_ref / len(recipes), "cpu_seconds": c_ref / len(recipes),
            "psnr_db": math.inf}]
    for samples, denoise, quality, prefilter, bounces in (FULL if rows is None else rows):
        d = RenderSettings()
        st = replace(d, samples=d.samples if samples is None else samples,
                     denoise=d.denoise if denoise is None else denoise,
                     denoising_quality=quality or d.denoising_quality,
                     denoising_prefilter=prefilter or d.denoising_prefilter, diffuse_bounces=bounces)
        if st.samples >= reference:
            continue
        psnr, wall, cpu = [], 0.0, 0.0
        for r in recipes:
            t, c = time.perf_counter(), _cpu_s()
            img, _ = render_rgbd(r, lens, seed, height, width, st, tmp)
            wall += time.perf_counter() - t
            cpu += _cpu_s() - c
            psnr.append(_psnr(img, refs[r]))
        out.append({"settings": st, "psnr_db": float(np.mean(psnr)), "seconds": wall / len(recipes),
                    "cpu_seconds": cpu / len(recipes)})
    return out


def parse_row(text: str) -> tuple:
    """'8:BALANCED:FAST' -> (8, True, 'BALANCED', 'FAST', 2); '8:OFF' -> no denoiser."""
    from dcdi_core.errors import InputRangeError
    parts = text.upper().split(":")
    try:
        samples = int(parts[0])
        if parts[1:2] == ["OFF"] and len(parts) == 2:
            return samples, False, None, None, RenderSettings.diffuse_bounces
        quality, prefilter = parts[1], parts[2]
        RenderSettings(samples=samples, denoising_quality=quality, denoising_prefilter=prefilter)
    except (ValueError, IndexError):
        raise InputRangeError("--row", text, "SPP:QUALITY:PREFILTER (QUALITY HIGH, BALANCED or FAST; PREFILTER "
                              "NONE, FAST or ACCURATE), or SPP:OFF") from None
    return samples, True, quality, prefilter, RenderSettings.diffuse_bounces


def main(argv=None) -> int:
    from dcdi_core.errors import DcdiError
    p = argparse.ArgumentParser(prog="python -m blender_addon.tools.render_noise",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--recipe", action="append", default=None, help="scene recipe (repeat for several; default room)")
    p.add_argument("--resolution", type=int, nargs=2, default=[240, 320], metavar=("H", "W"))
    p.add_argument("--reference", type=int, default=256, help="samples of the reference render")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--row", action="append", default=None, metavar="SPP:QUALITY:PREFILTER",
                   help="one setting to measure, e.g. 8:BALANCED:FAST (repeat; default: the full table); "
                        "QUALITY HIGH, BALANCED, FAST or OFF (no denoiser)")
    a = p.parse_args(argv)
    recipes = a.recipe or ["room"]
    try:
        rows = None if a.row is None else [parse_row(x) for x in a.row]
    except DcdiError as e:
        print(f"render_noise: error: {e}", file=sys.stderr)
        return 2
    rows = render_noise_report(recipes, *a.resolution, rows=rows, reference=a.reference, seed=a.seed)
    print(f"render error against time: {', '.join(recipes)}, {a.resolution[0]} x {a.resolution[1]}, "
          f"seed {a.seed}, {os.cpu_count()} CPU(s)")
    print(f"| samples | denoised | quality | prefilter | diffuse bounces | PSNR dB vs {a.reference} samples "
          "| wall s | CPU s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        s = r["settings"]
        psnr = "reference" if math.isinf(r["psnr_db"]) else f"{r['psnr_db']:.1f}"
        q, pf = (s.denoising_quality, s.denoising_prefilter) if s.denoise else ("-", "-")
        print(f"| {s.samples} | {s.denoise} | {q} | {pf} | {s.diffuse_bounces} | {psnr} "
              f"| {r['seconds']:.2f} | {r['cpu_seconds']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
