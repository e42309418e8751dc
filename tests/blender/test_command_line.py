"""Lens in Renders from the command line, as a render farm runs it:
`blender -b file.blend --addons bl_ext.user_default.dcdi_lens_bokeh -a`
with the add-on installed in the user folders, Cycles and EEVEE as the
scene's engine; each frame equals `dcdi bokeh` of the same frame's own
passes (rendered again without the lens) with that frame's keyframed focus."""
import os
import subprocess
import sys

import numpy as np
import pytest

# the fixtures by import: a conftest.py here would shadow tests/conftest.py's helpers
from realblender_support import ROOT, addon_zip, blender, run_inside, user_folders  # noqa: F401
from blender_addon import logic  # noqa: E402  (the add-on's PSF sampling, given to the command alike)

pytestmark = pytest.mark.realblender


def _blender(blender, work, *args):
    env = dict(os.environ, **user_folders(work))
    p = subprocess.run([blender, "-b", *args], capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    assert p.returncode == 0, (p.stdout + p.stderr)[-4000:]
    return p.stdout + p.stderr


@pytest.mark.parametrize("engine", ["CYCLES", "BLENDER_EEVEE"])
def test_a_command_line_animation_gets_the_lens_frame_by_frame(blender, addon_zip, tmp_path, engine):
    from dcdi_core.io.images import read_depth, read_image, write_depth, write_image
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.optics.paraxial import first_order
    from dcdi_core.render.camera import depth_from_planar_z
    res = run_inside(blender, "anim_scene.py", tmp_path, {"zip": str(addon_zip), "engine": engine})
    log = _blender(blender, tmp_path, str(tmp_path / "lens.blend"), "--addons", res["module"], "-a")
    assert "Lens in Renders" in log or (tmp_path / "lens" / "f_0001.exr").exists(), log[-2000:]
    _blender(blender, tmp_path, str(tmp_path / "passes.blend"), "-a")
    ep = first_order(load_lens("6p")).entrance_pupil_position_mm
    front, behind = res["keep_front_behind"]
    for frame, focus in res["focus_by_frame"].items():
        name = f"f_{int(frame):04d}.exr"
        lens_frame = read_image(tmp_path / "lens" / name)
        rgb = read_image(tmp_path / "passes" / name)
        depth = depth_from_planar_z(read_depth(tmp_path / "passes" / name), ep)
        write_image(tmp_path / f"aif{frame}.exr", rgb)
        write_depth(tmp_path / f"depth{frame}.exr", depth)
        cli = tmp_path / f"cli{frame}.exr"
        cmd = [sys.executable, "-m", "dcdi_core", "bokeh", "--image", str(tmp_path / f"aif{frame}.exr"),
               "--depth", str(tmp_path / f"depth{frame}.exr"), "--lens", "6p", "--focus", repr(focus),
               "--keep", repr(focus - front), repr(focus + behind), "--field-step", repr(logic.FIELD_STEP_PX),
               "--focus-tolerance", repr(logic.FOCUS_TOLERANCE_PX), "-o", str(cli)]
        p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT,
                           env=dict(os.environ, DCDI_CACHE_DIR=str(tmp_path / "psf-cache")))
        assert p.returncode == 0, p.stderr[-2000:]
        want = read_image(cli)
        assert lens_frame.shape == want.shape == (120, 160, 3)
        assert np.abs(lens_frame - want).max() <= 1e-5 * max(1.0, float(want.max())), (engine, frame)
        assert np.abs(lens_frame - rgb).mean() > 1e-3                # the lens, not Blender's frame
    # the two frames have their own focus: they differ
    assert np.abs(read_image(tmp_path / "lens" / "f_0001.exr") - read_image(tmp_path / "lens" / "f_0002.exr")).mean() > 1e-3
