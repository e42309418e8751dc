"""`dcdi simulate` and `dcdi bokeh` on files, as a user runs them."""
import json

import numpy as np
import pytest

from dcdi_core.cli import main
from dcdi_core.io.images import read_image, write_depth, write_image
from dcdi_core.render.synthetic import synthetic_rgbd

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    img, depth = synthetic_rgbd(48, 72, seed=1)
    write_image(tmp_path / "aif.exr", img)
    write_depth(tmp_path / "depth.exr", depth)
    return tmp_path, img


def test_simulate_writes_exr_and_reports(scene, capsys):
    d, img = scene
    code = main(["simulate", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s1",
                 "-o", str(d / "sim.exr"), "--sharp-out", str(d / "sharp.exr"), "--noise", "--seed", "3", *FAST])
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert info["depth_aware"] and info["noise"]["seed"] == 3 and info["perturbation"] is None
    out = read_image(d / "sim.exr")
    assert out.shape == img.shape and np.isfinite(out).all()
    assert read_image(d / "sharp.exr").shape == img.shape


def test_simulate_with_perturbed_lens_records_it(scene, capsys):
    d, img = scene
    code = main(["simulate", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s2",
                 "-o", str(d / "p.exr"), "--perturb", "7", "--no-distortion", *FAST])
    assert code == 0
    rec = json.loads(capsys.readouterr().out)["perturbation"]
    assert rec["seed"] == 7 and rec["changes"]


def test_bokeh_focus_distance(scene, capsys):
    d, img = scene
    code = main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--focus", "2", "-o", str(d / "f.exr"), *FAST])
    assert code == 0 and read_image(d / "f.exr").shape == img.shape


def test_bokeh_png_and_side_by_side(scene, capsys):
    d, img = scene
    code = main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--keep", "1.1", "1.3", "-o", str(d / "b.png"), "--side-by-side", str(d / "side.png"), *FAST])
    assert code == 0
    assert (d / "b.png").read_bytes()[:4] == b"\x89PNG" and (d / "side.png").exists()


def test_mismatched_depth_is_a_clear_error(scene, capsys):
    d, img = scene
    write_depth(d / "small.exr", np.ones((10, 10), np.float32))
    code = main(["simulate", "--image", str(d / "aif.exr"), "--depth", str(d / "small.exr"), "--lens", "mos-s1",
                 "-o", str(d / "x.exr"), *FAST])
    assert code == 2 and "small.exr" in capsys.readouterr().err
    assert not (d / "x.exr").exists()


@pytest.mark.slow
def test_simulation_accuracy_report_quick(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    code = main(["report", "simulation-accuracy", "--quick", "--out", str(tmp_path)])
    assert code == 0
    md = (tmp_path / "simulation-accuracy-mos-s1.md").read_text()
    assert "per-pixel reference" in md and "occlusion-aware layers" in md
    assert "Deposit width against rays" in md and "warp, then blur at the real positions" in md


@pytest.mark.slow
def test_bench_render_quick(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DCDI_CACHE_DIR", str(tmp_path / "cache"))
    code = main(["bench", "render", "--quick"])
    assert code == 0
    out = capsys.readouterr().out
    assert "baseline" in out and "peak memory" in out
