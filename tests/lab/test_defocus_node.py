"""Blender's Defocus node beside the lens: the thin lens the lab gives it
(lab/thin_lens.py) against the paraxial lens, and the headless tool
(lab/defocus_node.py, pip bpy) on tiny RGB-D images."""
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.optics.lens import load_lens
from dcdi_core.optics.paraxial import first_order, image_distance_mm
from dcdi_core.render.geometry import ImageGeometry
from lab.thin_lens import NodeDefocus

ROOT = Path(__file__).resolve().parents[2]


def test_node_settings_are_the_paraxial_lens():
    lens = load_lens("6p")
    fo = first_order(lens)
    t = NodeDefocus.for_lens(lens, 1280, 1920, 1.2)
    s = t.blender_settings(np.array([0.8, 3.0, np.inf]))
    assert s["node"]["f_stop"] == pytest.approx(fo.f_number, rel=1e-12)
    assert s["camera"]["lens"] == pytest.approx(fo.effective_focal_length_mm, rel=1e-12)
    assert s["node"]["use_zbuffer"] is True and s["camera"]["sensor_fit"] == "HORIZONTAL"
    # the node's pixels are the lens's: width / sensor width = 1 / pitch
    geom = ImageGeometry.full_sensor(lens, 1280, 1920)
    assert 1920 / s["camera"]["sensor_width"] == pytest.approx(1 / geom.pixel_pitch_mm, rel=1e-12)
    # Z from the front principal plane: the thin lens's image distance (from H') is the
    # thick lens's paraxial one (from its last vertex) up to one constant, at every depth
    f = fo.effective_focal_length_mm
    depths = np.array([0.8, 1.2, 3.0, 10.0])
    z = t.node_z(depths).astype(np.float64) * 1000
    gap = f * z / (z - f) - image_distance_mm(lens, depths)
    assert np.ptp(gap) < 1e-3 * f
    # so the node is sharp where the refocused lens is, and blurs more away from it
    r = t.coc_radius_px(np.array([0.8, 1.2, 3.0, np.inf]))
    assert r[1] < 1e-4 and r[0] > 1 and r[2] > 1 and r[3] > r[2]
    assert s["camera"]["dof_focus_distance"] == pytest.approx(1.2 + t.principal_plane_mm / 1000)
    assert s["node"]["blur_max"] >= r[[0, 2, 3]].max() - 1e-9


def test_node_depth_conventions_and_bad_focus():
    t = NodeDefocus.for_lens(load_lens("6p"), 64, 96, 1.2)
    z = t.node_z(np.array([np.nan, 0.0, -1.0, np.inf, 1e10]))
    assert np.allclose(z[:3], t.focus_z_m) and (z[3:] == np.float32(1e10)).all()
    for bad in (0.0, -1.0, math.nan, math.inf, "1.2"):
        with pytest.raises(InputRangeError, match="focus_m"):
            NodeDefocus.for_lens(load_lens("6p"), 64, 96, bad)


needs_bpy = pytest.mark.skipif(importlib.util.find_spec("bpy") is None, reason="pip bpy is not installed")


def _tool(tmp_path, *args):
    out = tmp_path / "out.npz"
    done = subprocess.run([sys.executable, "-m", "lab.defocus_node", *args, "--lens", "6p",
                           "--focus", "1.2", "--out", str(out), "--json", str(tmp_path / "t.json")],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    with np.load(out) as z:
        return z["image"], json.loads((tmp_path / "t.json").read_text())


@needs_bpy
def test_defocus_node_is_sharp_at_the_focus_and_blurred_away_from_it(tmp_path):
    # the image spans the 6P's sensor: at 256 x 384 its blur is a fifth of the full frame's
    h, w = 256, 384
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    depth = np.full((h, w), 1.2, np.float32)
    depth[:, w // 2:] = 0.4
    np.savez(tmp_path / "rgbd.npz", image=img, depth=depth)
    out, rec = _tool(tmp_path, "--input", str(tmp_path / "rgbd.npz"))
    assert out.shape == (h, w, 3) and np.isfinite(out).all()
    reach = math.ceil(rec["settings"]["node"]["blur_max"]) + 1
    sharp, far = slice(0, w // 2 - reach), slice(w // 2 + reach, w)
    assert np.abs(out[:, sharp] - img[:, sharp]).max() < 1e-5
    assert np.abs(out[:, far] - img[:, far]).mean() > 0.1
    assert out[:, far].std() < 0.7 * img[:, far].std()
    assert rec["blender"].startswith("5.") and all(t > 0 for t in rec["composite_s"])


@needs_bpy
def test_defocus_node_blurs_a_point_to_the_thin_lens_disc(tmp_path):
    # one white pixel at 0.4 m on black: the node spreads it over a disc of the radius dcdi_core computes
    h, w = 256, 384
    img = np.zeros((h, w, 3), np.float32)
    img[128, 192] = 1.0
    depth = np.full((h, w), 0.4, np.float32)
    np.save(tmp_path / "img.npy", img)
    np.save(tmp_path / "depth.npy", depth)
    out, rec = _tool(tmp_path, "--input", str(tmp_path / "img.npy"), "--depth", str(tmp_path / "depth.npy"))
    radius = float(NodeDefocus.for_lens(load_lens("6p"), h, w, 1.2).coc_radius_px(np.array([0.4]))[0])
    assert radius > 4
    lit = out[..., 0] > 1e-6
    assert math.sqrt(lit.sum() / math.pi) == pytest.approx(radius, abs=1.0)
    assert out[..., 0].sum() == pytest.approx(1.0, rel=0.1)         # the point's light, spread


@pytest.mark.slow
@needs_bpy
def test_bench_defocus_quick_prints_the_three_rows(capfd):
    # build.py's orchestration: the engine's rows, then the node's (its own process), then the scores
    import importlib.util as iu
    spec = iu.spec_from_file_location("dcdi_build", ROOT / "build.py")
    build = iu.module_from_spec(spec)
    spec.loader.exec_module(build)
    assert build.bench_defocus(Path(sys.executable), quick=True) == 0
    out = capfd.readouterr().out
    for row in ("dcdi bokeh, 6P PSFs, occlusion-aware", "dcdi bokeh, 6P PSFs, plain", "Defocus node (thin lens)"):
        line = next(x for x in out.splitlines() if row in x)
        assert all(math.isfinite(float(v)) for v in line.split()[-5:]), line
    assert "whole process" in out and "320 x 480" in out
