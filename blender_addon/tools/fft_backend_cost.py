"""The F12 lens stage with numpy's FFT against scipy's, in a Blender's own
Python: whether bundling scipy's wheels in the extension would pay.

    blender -b --factory-startup --python blender_addon/tools/fft_backend_cost.py -- [--scipy DIR] [--repeat 3]

DIR: an unpacked scipy wheel for that Blender's Python (``pip download
scipy --python-version 3.14 --only-binary=:all: --no-deps``, then unzip),
put first on ``sys.path``; without it the engine's FFTs are numpy's.
The scene is addon_waits' (four checker spheres before a wall, 1920 x
1080, the 6P from the shipped Omni-Lens-Field, focus 2.6 m); one F12 with
Lens in Renders makes the passes and warms the PSFs, then the lens stage
(``logic.lens_frame``) runs ``--repeat`` times on them. Prints the backend,
each run's wall and CPU seconds, and a batch of 64 x 4 real 144 x 144
transforms forward and back (the size the 1080p layers' 64-px windows take)
with each backend this Python has.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scipy", default=None, help="an unpacked scipy wheel for this Python")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])
    if args.scipy:
        sys.path.insert(0, str(Path(args.scipy).resolve()))
    here = Path(__file__).resolve()
    sys.path[:0] = [str(here.parents[2]), str(here.parent)]
    import bpy
    import numpy as np
    import blender_addon
    blender_addon.register()
    import addon_waits
    from blender_addon import logic
    from blender_addon.session import SESSION
    from dcdi_core.render import fft
    scene, _ = addon_waits.build(bpy, 16)
    s = scene.dcdi_lens_bokeh
    s.lens = "6p"
    bpy.ops.dcdi.match_camera_to_lens()
    s.focus_mode, s.focus_distance = "DISTANCE", 2.6
    s.keep_front = s.keep_behind = 0.0
    s.lens_in_renders = True
    bpy.ops.render.render(write_still=False)
    frame = SESSION.last_render["frames"][0]
    rgb, z = SESSION.last_render["last_passes"]
    path = logic.lens_file("6p")
    req = logic.FrameRequest("dof", frame["focus_m"], tuple(frame["keep_m"]), True,
                             logic.lens_readout(path)["entrance_pupil_mm"], 1.0)
    lens = logic.load_lens_cached(path)
    print(f"FFT backend: {fft.backend()} (numpy {np.__version__}, Python {sys.version.split()[0]}); "
          f"F12's lens stage, cold PSFs: {frame['seconds']:.2f} s")
    for _ in range(args.repeat):
        t, c = time.perf_counter(), time.process_time()
        logic.lens_frame(rgb, z, lens, req)
        print(f"lens stage 1920 x 1080: {time.perf_counter() - t:.2f} s wall, {time.process_time() - c:.2f} CPU s")
    x = np.random.default_rng(0).random((64, 4, 144, 144), dtype=np.float32)
    for name in fft.available():
        t = time.perf_counter()
        for _ in range(5):
            fft.irfft2(fft.rfft2(x, (144, 144), name), (144, 144), name)
        print(f"{name}: 5 x (64 x 4 transforms of 144 x 144, forward and back) {time.perf_counter() - t:.3f} s")
    blender_addon.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
