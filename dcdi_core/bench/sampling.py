"""`dcdi bench sampling`: the error and time of sampling PSFs for the image
(``psf.sampling``: fields a step in image pixels apart, the focus rounded
within a blur tolerance), on a focus change to a new distance, per lens.

For each lens and image size, a synthetic RGB-D (a checker ramp from 0.8 m
to 10 m) is blurred by ``app.bokeh`` with the lens refocused: first at 2.0
m (cold: the PSF source opened), then at a new distance (the wait of a
focus change), then at a distance within the tolerance of the last (a
focus pull's next step, or an animation's next frame). Each way of sampling
runs in its own disk cache (traced PSFs are traced again); PSNR (peak 1) is
against the full grid with the exact focus on the same frame. Times are
wall seconds with the process's CPU seconds beside them.

    dcdi bench sampling [--quick]
    blender -b --python-expr "import sys; sys.path.insert(0, '.'); from dcdi_core.bench import sampling; sampling.main()"
"""
from __future__ import annotations

import math
import os
import sys
import tempfile
import time

import numpy as np

LENSES = ("6p", "double-gauss", "mos-s1", "mos-s2")
SIZES = ((270, 480), (1080, 1920))
FOCUS = (2.0, 2.9)                    # cold, then a new distance (m)
NUDGE = 1.002                         # the next step of a pull: 0.2 % farther
WAYS = (("full grid, exact focus", {}),
        ("fields 16 px apart", {"field_step_px": 16.0}),
        ("fields 16 px apart, focus within 0.25 px", {"field_step_px": 16.0, "focus_tolerance_px": 0.25}))


def scene(h: int, w: int):
    """A checker (6-px squares, three colours) on a depth ramp 0.8-10 m left to right."""
    y, x = np.mgrid[0:h, 0:w]
    checker = (0.1 + 0.8 * ((x // 6 + y // 6) % 2))[..., None] * np.array([1.0, 0.75, 0.5])
    depth = 0.8 + 9.0 * (x / w) ** 2 + 0.5 * (y / h)
    return checker.astype(np.float32), depth.astype(np.float32)


def _psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def _timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def run_way(lens, img, depth, psf_kw: dict, preview: bool) -> list:
    """[(image, wall s, CPU s, focus used m)] for the cold focus, the new one and the nudged one."""
    from .. import app
    from ..render.request import RenderRequest
    cache = app.SourceCache(6)
    out = []
    with tempfile.TemporaryDirectory() as d:
        old = os.environ.get("DCDI_CACHE_DIR")
        os.environ["DCDI_CACHE_DIR"] = d
        try:
            for focus in (FOCUS[0], FOCUS[1], FOCUS[1] * NUDGE):
                req = app.BokehRequest(img, depth, lens, keep=(focus - 0.1, focus + 0.1), focus_m=focus,
                                       render=RenderRequest(lens, patch=16),
                                       psf=app.PSFRequest(preview=preview, **psf_kw), image_name="the bench scene")
                r, wall, cpu = _timed(lambda: app.bokeh(req, None, cache=cache))
                out.append((r.image, wall, cpu, r.info.get("focus_used_m", focus), r.source))
        finally:
            if old is None:
                os.environ.pop("DCDI_CACHE_DIR", None)
            else:
                os.environ["DCDI_CACHE_DIR"] = old
    return out


def bench_sampling(quick: bool = False, lenses=LENSES, sizes=SIZES, preview: bool = True) -> int:
    from ..optics.lens import load_lens
    if quick:
        lenses, sizes = lenses[:1], ((45, 80),)
    print(f"dcdi bench sampling: a focus change through each lens (app.bokeh, {'preview' if preview else 'full'} "
          f"traces where PSFs are traced); wall s / CPU s; PSNR against the full grid at the exact focus")
    print("| lens | image | sampling | fields | cold 2.0 m | new 2.9 m | next 2.9 m + 0.2 % | focus used | PSNR dB |")
    print("|---|---|---|---|---|---|---|---|---|")
    for lens_id in lenses:
        lens = load_lens(lens_id)
        for h, w in sizes:
            img, depth = scene(h, w)
            ref = None
            for name, kw in WAYS:
                rows = run_way(lens, img, depth, kw, preview)
                if ref is None:
                    ref = rows
                psnr = min(_psnr(a[0], b[0]) for a, b in zip(rows, ref))
                times = " | ".join(f"{wall:.2f} / {cpu:.2f}" for _, wall, cpu, _, _ in rows)
                used = rows[1][3]
                print(f"| {lens_id} | {w} x {h} | {name} | {rows[1][4].library.grid.n_fields} | {times} | "
                      f"{used:.4g} m | {'exact' if psnr == math.inf else f'{psnr:.1f}'} |", flush=True)
    return 0


def main(argv=None) -> int:
    argv = sys.argv[sys.argv.index("--") + 1:] if argv is None and "--" in sys.argv else (argv or [])
    return bench_sampling(quick="--quick" in argv, preview="--full" not in argv)


__all__ = ["bench_sampling", "main", "scene"]
