"""`dcdi bench`: timings printed, never asserted.

Each benchmark times the real code path and a simple baseline in the same
process and prints the ratio, so that figures from different machines compare.
"""
from __future__ import annotations

import math
import os
import time

import numpy as np


def _best(fn, repeat):
    best = math.inf
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def bench_trace(n_rays: int, repeat: int) -> int:
    """Trace n_rays through the double Gauss (11 surfaces + sensor), field 0.7, depth 2 m,
    at 3 wavelengths; float64 and float32; baseline: the same kernel, unchunked, one thread."""
    from .optics import trace as T
    from .optics.aiming import pupil_rays, sources, stop_grid
    from .optics.lens import load_lens

    lens = load_lens("double-gauss")
    side = int(round(math.sqrt(n_rays / 3 * 4 / math.pi)))
    aimed = sources(lens, [2.0], field=[0.7])
    o, d, status, _ = pupil_rays(lens, aimed, stop_grid(lens, side))
    wl = np.array([486.13, 587.56, 656.27])
    o, d, status = o[0, 0, None], d[0, 0, None], status[0, 0, None]
    wls = wl[:, None]
    n = o.shape[1] * wl.size
    n_int = n * (len(lens.surfaces) + 1)
    print(f"bench trace: lens double-gauss, {len(lens.surfaces)} surfaces + sensor, "
          f"{n:,} rays ({n_int:,} ray-surface intersections), {os.cpu_count()} CPU(s), best of {repeat}")

    def run(dtype):
        return T.trace(lens, o, d, wls, dtype=dtype, status=status)

    results = {}
    for name, dtype in (("float64", np.float64), ("float32", np.float32)):
        t, b = _best(lambda: run(dtype), repeat)
        results[name] = (t, b)
        print(f"  {name}: {t * 1e3:8.1f} ms  {n_int / t / 1e6:7.1f} M ray-surface/s  "
              f"{n / t / 1e6:6.2f} M rays/s")
    # baseline: one chunk, no thread pool (plain vectorised numpy)
    saved = T.CHUNK
    T.CHUNK = n + 1
    try:
        tb, _ = _best(lambda: run(np.float64), repeat)
    finally:
        T.CHUNK = saved
    print(f"  baseline float64 (unchunked, 1 thread): {tb * 1e3:8.1f} ms  "
          f"{n_int / tb / 1e6:7.1f} M ray-surface/s")
    print(f"  speed-up over baseline: float64 x{tb / results['float64'][0]:.2f}, "
          f"float32 x{tb / results['float32'][0]:.2f}")
    b64, b32 = results["float64"][1], results["float32"][1]
    both = b64.valid & b32.valid
    diff = np.abs(b64.position_mm[..., :2] - b32.position_mm[..., :2].astype(np.float64))[both]
    print(f"  float32 vs float64 on the sensor: max |dx,dy| = {diff.max() * 1e3:.4f} um, "
          f"rms = {np.sqrt((diff ** 2).mean()) * 1e3:.4f} um; "
          f"status disagreements: {int((b64.status != b32.status).sum())} of {n:,}")
    return 0


def run(what: str, args) -> int:
    if what == "trace":
        return bench_trace(args.rays, args.repeat)
    raise ValueError(f"unknown benchmark {what!r}")
