"""`dcdi correct` and `dcdi dof` choose how a capture is corrected: the
deconvolution with the lens's own PSFs for any lens, a network only where the
rule (pipeline.choose_correction) picks one or the user asks; which one ran
and why is said on stderr and in the JSON; what cannot run is refused in one
line before any PSF is traced. No torch needed: the deconvolution is numpy."""
import json

import numpy as np
import pytest

from conftest import write_rgbd_scene

from support.cli import run_cli
from support.registry import dacn_recorded_better
from dcdi_core.io.images import read_image

# tiny traced PSFs, the same for the simulated capture and its correction
FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15", "--psf-source", "trace"]
# the 6P at 50 um pixels: a blur of a few pixels on a 48 x 64 image
PITCH = ["--image-pixel-pitch", "0.05"]

_cli = run_cli

def _psnr(a, b) -> float:
    return float(-10 * np.log10(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2)))

@pytest.fixture
def capture(tmp_path, monkeypatch, capsys):
    """A noise-free 6P capture of the synthetic scene (cap.exr), its sharp
    image on the same grid (sharp.exr) and depth (depth.exr)."""
    write_rgbd_scene(tmp_path, monkeypatch, 48, 64)
    code, _, err = _cli(capsys, "simulate", "--image", tmp_path / "aif.exr", "--depth", tmp_path / "depth.exr",
                        "--lens", "6p", "-o", tmp_path / "cap.exr", "--sharp-out", tmp_path / "sharp.exr",
                        *PITCH, *FAST)
    assert code == 0, err
    return tmp_path

def _correct(capsys, d, *extra, out="out.exr"):
    return _cli(capsys, "correct", "--image", d / "cap.exr", "-o", d / out, *extra)

def test_correct_deconvolves_a_lens_without_a_network_and_gains_psnr(capture, capsys):
    d = capture
    code, out, err = _correct(capsys, d, "--depth", d / "depth.exr", "--lens", "6p", *PITCH, *FAST)
    assert code == 0, err
    info = json.loads(out)
    c = info["correction"]
    assert c["method"] == "deconv" and "no DACN ships for lens 6p" in c["reason"]
    assert c["pixel_pitch_mm"] == 0.05 and c["psf_source"] == "trace" and info["lens"] == "6p"
    assert err.splitlines()[0].startswith("dcdi: correction by the deconvolution: no DACN ships for lens 6p")
    sharp = read_image(d / "sharp.exr")
    before, after = _psnr(read_image(d / "cap.exr"), sharp), _psnr(read_image(d / "out.exr"), sharp)
    # most of this 48 x 64 frame lies within a kernel radius of its edge, where the result fades to the capture
    assert after > before + 1.0, (before, after)

def test_auto_picks_the_deconvolution_over_a_shipped_network_and_says_why(capture, capsys, monkeypatch):
    from dcdi_core.shipped import network
    if "mos-s1" not in network("dacn").shipped_keys():
        pytest.skip("no shipped DACN of mos-s1")
    dacn_recorded_better(monkeypatch, ())          # as if the study had not found it better
    d = capture
    from dcdi_core.io.images import write_image
    write_image(d / "cap.exr", read_image(d / "cap.exr"))   # a capture of unknown origin (no record of the 6P)
    code, out, err = _correct(capsys, d, "--depth", d / "depth.exr", "--lens", "mos-s1", *FAST)
    assert code == 0, err
    c = json.loads(out)["correction"]
    assert c["method"] == "deconv"
    assert "the shipped DACN of mos-s1 is not recorded better than the deconvolution" in c["reason"]
    assert "the DACN study (docs/correction.md)" in c["reason"]
    assert [x for x in err.splitlines() if x.startswith("dcdi: correction by")] == \
        [f"dcdi: correction by the deconvolution: {c['reason']}"]

def test_the_one_depth_baseline_needs_no_depth_map(capture, capsys):
    d = capture
    code, out, err = _correct(capsys, d, "--lens", "6p", "--one-depth", "3", "--method", "deconv", *PITCH, *FAST)
    assert code == 0, err
    c = json.loads(out)["correction"]
    assert c["method"] == "deconv" and c["one_depth_m"] == 3.0 and c["reason"] == "asked for: --method deconv"
    code, out, err = _correct(capsys, d, "--depth", d / "depth.exr", "--lens", "6p", *PITCH, *FAST, out="aware.exr")
    assert code == 0, err
    # one depth for the whole image is not the depth-aware result
    assert not np.array_equal(read_image(d / "out.exr"), read_image(d / "aware.exr"))

def test_given_noise_and_weight_reach_the_deconvolution(capture, capsys):
    d = capture
    code, out, err = _correct(capsys, d, "--depth", d / "depth.exr", "--lens", "6p", "--noise-full-well", "5000",
                              "--deconv-weight", "7", *PITCH, *FAST)
    assert code == 0, err
    c = json.loads(out)["correction"]
    assert c["weight"] == 7.0 and c["noise"]["given"]
    assert c["noise"]["gain"] == pytest.approx(1 / 5000) and c["noise"]["floor"] == pytest.approx((3 / 5000) ** 2)

@pytest.mark.parametrize("extra, says", [
    (["--lens", "6p", "--method", "dacn"], ["no shipped DACN for lens 6p", "--model", "--method deconv"]),
    (["--lens", "6p", "--method", "fast"], ["--method = 'fast'", "auto, deconv, dacn"]),
    (["--lens", "6p", "--deconv-weight", "0"], ["--deconv-weight = 0.0", "> 0"]),
    (["--lens", "6p", "--deconv-weight", "-3"], ["--deconv-weight = -3.0"]),
    (["--lens", "6p", "--noise-full-well", "0"], ["--noise-full-well = 0.0"]),
    (["--lens", "6p", "--noise-read", "-1"], ["--noise-read = -1.0"]),
    (["--lens", "6p", "--method", "deconv", "--model", "net.npz"], ["--model = 'net.npz'", "--method deconv"]),
    (["--lens", "mos-s1", "--method", "dacn", "--deconv-weight", "5"], ["--deconv-weight", "--method deconv"]),
    ([], ["--lens is missing", "--model"]),
    (["--method", "deconv"], ["--lens is missing", "deconvolution"]),
])
def test_what_cannot_run_is_refused_in_one_line_before_any_work(capture, capsys, extra, says):
    d = capture
    for p in (d / "cache").iterdir():
        p.rename(d / f"simulate-{p.name}")           # the capture's PSFs out of the way: none may be traced now
    code, _, err = _correct(capsys, d, "--depth", d / "depth.exr", *extra, *PITCH, *FAST, out="x.exr")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("dcdi: error:"), err
    for s in says:
        assert s in lines[0], lines[0]
    assert not (d / "x.exr").exists() and not any((d / "cache").iterdir())

def test_dacn_correct_is_the_network_alone(capture, capsys):
    d = capture
    code, _, err = _cli(capsys, "dacn", "correct", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "6p",
                        "-o", d / "x.exr")
    assert code == 2 and "no shipped DACN for lens 6p" in err and "dcdi correct --method deconv" in err
    code, _, err = _cli(capsys, "dacn", "correct", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "6p",
                        "--method", "deconv", "-o", d / "x.exr")
    assert code == 2 and "unrecognized arguments: --method" in err

def test_dof_corrects_with_the_same_deconvolution_as_correct(capture, capsys):
    d = capture
    code, out, err = _correct(capsys, d, "--depth", d / "depth.exr", "--lens", "6p", *PITCH, *FAST)
    assert code == 0, err
    code, out, err = _cli(capsys, "dof", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--camera", "6p",
                          "--method", "deconv", "--lens", "mos-s1", "--keep", "1", "2", "-o", d / "dof.exr",
                          "--save-intermediates", d / "mid", *PITCH, *FAST)
    assert code == 0, err
    info = json.loads(out)
    assert info["correction"]["method"] == "deconv" and info["correction"]["reason"] == "asked for: --method deconv"
    assert "dcdi: correction by the deconvolution: asked for: --method deconv" in err.splitlines()
    np.testing.assert_array_equal(read_image(d / "mid" / "corrected.exr"), read_image(d / "out.exr"))
    assert read_image(d / "dof.exr").shape == (48, 64, 3)
    # --method dacn for a camera without a network: refused by name, before any work
    code, _, err = _cli(capsys, "dof", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--camera", "6p",
                        "--method", "dacn", "--lens", "mos-s1", "--keep", "1", "2", "-o", d / "x.exr", *FAST)
    assert code == 2 and "no shipped DACN for lens 6p" in err and "give --dacn (a DACN file" in err
    assert not (d / "x.exr").exists()
