"""The application layer: both front ends run the same jobs.

The add-on's jobs (``blender_addon.logic``: what its operators call, bpy-free)
and the `dcdi` command on the same inputs give the same images; errors name
the request's fields, shown in each front end's words; a capture made by
`dcdi simulate` remembers its geometry, and `dcdi correct` uses it."""
import json

import numpy as np
import pytest

from dcdi_core.cli import main
from dcdi_core.io.images import read_image, write_depth, write_image
from dcdi_core.optics.lens import load_lens


def scene(h=64, w=96, seed=0):
    """A textured all-in-focus image (H, W, 3) in [0.05, 0.95] and two depth planes (m)."""
    rng = np.random.default_rng(seed)
    img = (0.05 + 0.9 * rng.random((h, w, 3))).astype(np.float32)
    depth = np.where(np.arange(w)[None, :] < w // 2, 0.8, 2.5).astype(np.float32) * np.ones((h, 1), np.float32)
    return img, depth


def cli(capsys, *argv) -> dict:
    assert main([str(a) for a in argv]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture
def files(tmp_path):
    img, depth = scene()
    write_image(tmp_path / "aif.exr", img)
    write_depth(tmp_path / "depth.exr", depth)
    return tmp_path, img, depth


def test_bokeh_agrees(files, capsys):
    from blender_addon import logic
    d, img, depth = files
    lens = load_lens("mos-s1")
    out, info = logic.run_bokeh(img, depth, lens, focus_m=1.0, keep=(0.7, 0.9))
    cli(capsys, "bokeh", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens", "mos-s1",
        "--focus", 1.0, "--keep", 0.7, 0.9, "--field-step", logic.FIELD_STEP_PX,
        "--focus-tolerance", logic.FOCUS_TOLERANCE_PX, "-o", d / "b.exr")
    np.testing.assert_array_equal(read_image(d / "b.exr"), out)
    assert info["psf_source"] in ("basis", "olf", "trace")


def test_simulate_agrees(files, capsys):
    from blender_addon import logic
    d, img, depth = files
    lens = load_lens("mos-s2")
    out, sensor_depth, geometry, info = logic.run_simulation(img, depth, lens, noise=True, seed=3)
    cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
        "--noise", "--seed", 3, "-o", d / "s.exr")
    np.testing.assert_array_equal(read_image(d / "s.exr"), out)
    assert info["record"].pixel_pitch_mm == pytest.approx(geometry.pixel_pitch_mm)


def test_correct_by_network_agrees(files, capsys):
    """The add-on's Correct by Network of the shipped (refining) DACN == `dcdi correct --method dacn`."""
    pytest.importorskip("torch")
    from blender_addon import logic
    from dcdi_core.models.dacn.correct import load_dacn
    from dcdi_core.shipped import NETWORKS
    d, img, depth = files
    lens = load_lens("mos-s1")
    model, _ = load_dacn(NETWORKS["dacn"].shipped_file("mos-s1"))
    assert model.spec.refine                  # the case where the two front ends used to differ
    capture, sensor_depth, geometry, info = logic.run_simulation(img, depth, lens)
    write_image(d / "cap.exr", capture)
    write_depth(d / "sdepth.exr", np.nan_to_num(sensor_depth, nan=0.0))
    choice = logic.choose_correction("network", "mos-s1", geometry.pixel_pitch_mm, lens=lens, record=info["record"])
    out, cinfo = logic.run_correction(capture, np.nan_to_num(sensor_depth, nan=0.0), lens, choice,
                                      record=info["record"])
    got = cli(capsys, "correct", "--image", d / "cap.exr", "--depth", d / "sdepth.exr", "--lens", "mos-s1",
              "--method", "dacn", "-o", d / "c.exr")
    np.testing.assert_array_equal(read_image(d / "c.exr"), out)
    assert got["correction"]["method"] == "dacn" and cinfo["method"] == "network"


def test_capture_remembers_its_geometry(files, capsys):
    """`dcdi correct` on a capture of `dcdi simulate --image-pixel-pitch P --axis R C` gives, without those
    options, what it gives with them."""
    d, img, depth = files
    cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
        "--image-pixel-pitch", 0.0122, "--axis", 20, 30, "--noise", "--seed", 1, "-o", d / "cap.exr")
    plain = cli(capsys, "correct", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
                "--method", "deconv", "-o", d / "plain.exr")
    cli(capsys, "correct", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
               "--method", "deconv", "--image-pixel-pitch", 0.0122, "--axis", 20, 30, "-o", d / "told.exr")
    np.testing.assert_array_equal(read_image(d / "plain.exr"), read_image(d / "told.exr"))
    assert plain["pixel_pitch_mm"] == pytest.approx(0.0122)
    # an explicit option still wins over the record
    other = cli(capsys, "correct", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
                "--method", "deconv", "--image-pixel-pitch", 0.02, "-o", d / "other.exr")
    assert other["pixel_pitch_mm"] == pytest.approx(0.02)


def test_bokeh_and_info_read_the_record(files, capsys):
    """`dcdi bokeh` of a capture takes its recorded pitch and axis too; `dcdi info` shows them."""
    d, img, depth = files
    cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
        "--image-pixel-pitch", 0.0122, "--axis", 20, 30, "-o", d / "cap.exr")
    assert main(["info", str(d / "cap.exr")]) == 0
    out = capsys.readouterr().out
    assert "lens_id: mos-s2" in out and "12.2 um" in out and "row 20, col 30 px" in out and "distortion_applied: True" in out
    plain = cli(capsys, "bokeh", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
                "--keep", 0.7, 0.9, "--psf-source", "basis", "-o", d / "plain.exr")
    cli(capsys, "bokeh", "--image", d / "cap.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
               "--keep", 0.7, 0.9, "--psf-source", "basis", "--image-pixel-pitch", 0.0122, "--axis", 20, 30,
               "-o", d / "told.exr")
    np.testing.assert_array_equal(read_image(d / "plain.exr"), read_image(d / "told.exr"))
    assert plain["pixel_pitch_mm"] == pytest.approx(0.0122)


def test_lens_contradicting_the_capture_is_refused(files, capsys):
    d, img, depth = files
    cli(capsys, "simulate", "--image", d / "aif.exr", "--depth", d / "depth.exr", "--lens", "mos-s2",
        "-o", d / "cap.exr")
    assert main(["correct", "--image", str(d / "cap.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s1",
                 "-o", str(d / "c.exr")]) == 2
    err = capsys.readouterr().err
    assert "--lens" in err and "mos-s1" in err and "mos-s2" in err and "\u2039" not in err
    assert not (d / "c.exr").exists()


def test_errors_in_each_front_ends_words(files, capsys):
    """The engine names the request's field; the CLI shows its option, the add-on its panel label."""
    from blender_addon import logic
    from dcdi_core.errors import InputRangeError
    from dcdi_core.render.request import RenderRequest
    d, img, depth = files
    lens = load_lens("mos-s1")
    with pytest.raises(InputRangeError) as e:
        RenderRequest(lens, patch=15)
    assert e.value.name == "patch" and str(e.value).startswith("patch = 15")
    assert logic.message(e.value).startswith("Patch Size = 15")
    assert main(["bokeh", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "mos-s1",
                 "--focus", "1", "--patch", "15", "-o", str(d / "b.exr")]) == 2
    assert "error: --patch = 15" in capsys.readouterr().err
    # the correction's rule: `dcdi correct` names --model, `dcdi dof` its --dacn, the add-on Correction Model
    from dcdi_core.app.correction_rule import check_correction
    with pytest.raises(InputRangeError) as e:
        check_correction("mos-s1", "deconv", "net.npz")
    assert "Correction Model" in logic.message(e.value) and "Method deconv" in logic.message(e.value)
    assert main(["dof", "--image", str(d / "aif.exr"), "--depth", str(d / "depth.exr"), "--lens", "6p",
                 "--camera", "mos-s1", "--method", "deconv", "--dacn", "net.npz", "--focus", "1",
                 "-o", str(d / "o.exr")]) == 2
    err = capsys.readouterr().err
    assert "--dacn" in err and "--method deconv" in err and "\u2039" not in err


def test_requests_take_no_half_inputs():
    from dcdi_core import app
    from dcdi_core.errors import InputRangeError
    lens = load_lens("mos-s1")
    img, depth = scene(16, 24)
    with pytest.raises(InputRangeError, match="depth_m"):
        app.simulate(app.SimulateRequest(img, None, lens))
    with pytest.raises(InputRangeError, match="image"):
        app.bokeh(app.BokehRequest(img[..., 0], depth, lens, focus_m=1.0))
    with pytest.raises(InputRangeError, match="psf_source"):
        app.PSFRequest(source="olff")


def test_cancel_stops_a_job():
    from dcdi_core import app
    lens = load_lens("mos-s1")
    img, depth = scene(32, 48)
    with pytest.raises(app.Cancelled):
        app.bokeh(app.BokehRequest(img, depth, lens, focus_m=1.0), app.Control(cancelled=lambda: True))


def test_psf_source_always_serves_a_library():
    from dcdi_core import app
    from dcdi_core.render.geometry import ImageGeometry
    lens = load_lens("mos-s1")
    geometry = ImageGeometry.full_sensor(lens, 32, 48)
    for source in ("basis", "trace"):
        src = app.open_source(lens, geometry, app.PSFRequest(source=source))
        assert src.kind == source and src.library is not None and src.library.pixel_pitch_mm > 0


def test_the_readmes_capture_example_works_as_written(tmp_path, capsys, monkeypatch):
    """The README's three lines (simulate at the paper's pitch, info, correct
    without the pitch), run as written on a small scene: the correction
    reads the pitch from the capture, so Auto runs the shipped network."""
    import re
    import shlex
    from pathlib import Path
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = next(b for b in re.findall(r"```\n(.*?)```", readme, re.S) if "dcdi info CAPTURE.exr" in b)
    lines = [shlex.split(x) for x in block.strip().splitlines()]
    assert [x[:2] for x in lines] == [["dcdi", "simulate"], ["dcdi", "info"], ["dcdi", "correct"]]
    img, depth = scene()
    write_image(tmp_path / "AIF.exr", img)
    write_depth(tmp_path / "DEPTH.exr", depth)
    monkeypatch.chdir(tmp_path)
    outputs = []
    for argv in lines:
        assert main(argv[1:]) == 0
        outputs.append(capsys.readouterr().out)
    assert "lens_id: mos-s2" in outputs[1] and "12.2 um" in outputs[1]
    fixed = json.loads(outputs[2])
    assert fixed["pixel_pitch_mm"] == pytest.approx(0.0122)
    from dcdi_core.shipped import network
    if "mos-s2" in network("dacn").shipped_keys() and "mos-s2" in network("dacn").beats_deconvolution:
        assert fixed["correction"]["method"] == "dacn", fixed["correction"]
    assert np.isfinite(read_image(tmp_path / "SHARP.exr")).all()


@pytest.mark.parametrize("occlusion", [True, False])
def test_a_clipping_kernel_is_warned_only_where_the_job_leaves_it_clipped(monkeypatch, occlusion):
    """A bokeh whose kernel (capped at 15 px here) clips the far layer's
    blur: the occlusion-aware job answers it with the large blur and says
    nothing of clipping; the plain blur leaves it clipped, and warns once
    and says so in ``info['clipped']`` (what the add-on's render line shows)."""
    import warnings
    import dcdi_core.psf.library as psf_library
    from dcdi_core import app
    from dcdi_core.psf.compute import KernelTooSmallWarning, PSFSettings
    from dcdi_core.render.request import RenderRequest
    monkeypatch.setattr(psf_library, "MAX_FITTED_KERNEL", 15)
    lens = load_lens("zeiss-jena-tessar-50mm-f2-8")
    img = np.full((48, 72, 3), 0.05, np.float32)
    img[10:13, 10:13] = 20.0
    depth = np.full((48, 72), 10.0, np.float32)
    depth[20:30, 30:45] = 1.2
    settings = PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=15)
    req = app.BokehRequest(img, depth, lens, keep=(1.1, 1.3), focus_m=1.2, occlusion=occlusion, image_name="x",
                           render=RenderRequest(lens, image_pixel_pitch_mm=0.02, patch=8, psf=settings))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = app.bokeh(req)
    told = [str(w.message) for w in caught if issubclass(w.category, KernelTooSmallWarning)]
    if occlusion:
        assert r.info.get("large_blur_factor") and not told and "clipped" not in r.info
    else:
        assert len(told) == 1 and r.info["clipped"] == told[0] and "15 x 15 kernel clips" in told[0]
