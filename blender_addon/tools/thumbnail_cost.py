"""What the lens list's thumbnails cost: ``logic.psf_thumbnail`` of every
shipped lens, timed (wall and CPU seconds; the worker thread makes them
once a session), with the ball-tile's smoothness (the mean deviation of
the widest ball's inside from its 3 x 3 mean: the ray grid's moire).

    python blender_addon/tools/thumbnail_cost.py [--rays-per-px 4]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays-per-px", type=int, default=None, help="pupil rays a pixel across the widest ball")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    import numpy as np
    from scipy.ndimage import uniform_filter
    from blender_addon import logic
    if args.rays_per_px:
        logic.THUMBNAIL_RAYS_PER_PX = args.rays_per_px
    t = logic.THUMBNAIL_TILE_PX
    print("| lens | wall s | CPU s | moire |\n|---|---|---|---|")
    total = 0.0
    for e in logic.lens_catalogue():
        w0, c0 = time.perf_counter(), time.process_time()
        img = logic.psf_thumbnail(logic.load_lens_cached(e.path))
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        total += wall
        near = img[:t, :t].mean(axis=-1)
        inside = uniform_filter((near > 0.2).astype(float), 5) > 0.99
        moire = float(np.abs(near - uniform_filter(near, 3))[inside].mean()) if inside.any() else float("nan")
        print(f"| {e.id} | {wall:.2f} | {cpu:.2f} | {moire:.3f} |")
    print(f"all: {total:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
