"""Pause the dataset factory in one stage of one sample, so that a test can
signal it there. Loaded into the factory's own process before it runs;
DCDI_TEST_STAGE_PAUSE="STAGE N SECONDS" says where: the N-th (from 1)
sample's

- render: inside Blender's render (a render_pre handler: Python that
  Blender itself calls, as Cycles' engine is, where an exception is
  printed and dropped);
- write: between its files (all-in-focus and depth written, the lens
  images not yet);
- simulate: before its simulation (Python and numpy);

then says "stage pause: STAGE N" on stderr and sleeps SECONDS. No hook in
the factory: the old code runs under it too.

    python tests/factory/stage_pause.py run ARGS...            # pip bpy: then runs the factory
    blender --background --python tests/factory/stage_pause.py --python blender_addon/factory/batch.py -- ARGS...
"""
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def install(stage: str, n: int, seconds: float) -> None:
    """Wrap what the factory calls once a sample in ``stage`` with a pause at its ``n``-th call."""
    calls = []

    def pause():
        calls.append(1)
        if len(calls) == n:
            print(f"stage pause: {stage} {n}", file=sys.stderr, flush=True)
            time.sleep(seconds)

    if stage == "render":
        import bpy

        @bpy.app.handlers.persistent                # the factory loads a new scene for every sample
        def before_render(*_):
            pause()
        bpy.app.handlers.render_pre.append(before_render)
    elif stage == "write":
        from dcdi_core.dataset import factory_folder as ff
        real = ff.write_lens_images
        ff.write_lens_images = lambda *a, **k: (pause(), real(*a, **k))[1]
    elif stage == "simulate":
        from dcdi_core.render.simulate import LensSimulator
        real = LensSimulator.__call__
        LensSimulator.__call__ = lambda self, *a, **k: (pause(), real(self, *a, **k))[1]
    else:
        raise SystemExit(f"stage_pause: unknown stage {stage!r} (render, write, simulate)")


stage, n, seconds = os.environ["DCDI_TEST_STAGE_PAUSE"].split()
install(stage, int(n), float(seconds))
if sys.argv[1:2] == ["run"]:
    from blender_addon.factory.batch import run
    sys.exit(run(sys.argv[2:]))
