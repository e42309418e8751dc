"""`dcdi dof` and dcdi_core.app.correction_rule: the pipeline end to end with each depth
backend, and with a sharp input, --camera none and the true depth, exactly
`dcdi bokeh`; the one rule that chooses the correction (choose_correction),
the deconvolution and the network through app.correct() and app.dof()."""
import json
from dataclasses import replace

import numpy as np
import pytest

from conftest import write_rgbd_scene
from conftest import dacn_config as _config

from dcdi_core.cli import main
from lab.cli import main as lab_main
from dcdi_core.io.images import read_image
from support.registry import dacn_recorded_better

FAST = ["--rays", "16", "--wavelengths", "3", "--kernel", "15", "--psf-source", "trace"]


@pytest.fixture
def scene(tmp_path, monkeypatch):
    write_rgbd_scene(tmp_path, monkeypatch, 48, 64)
    return tmp_path


@pytest.fixture(scope="module")
def networks(pairs, tmp_path_factory):  # noqa: F811
    """A tiny DACN and depth network of mos-s2 (a few steps), exported as shipped."""
    pytest.importorskip("torch")
    from dcdi_core.models.dacn.export import export_dacn
    from dcdi_core.models.depth.export import export_depthnet
    from dcdi_core.models.dacn.train import train_dacn
    from dcdi_core.models.depth.config import DepthTrainConfig
    from dcdi_core.models.depth.train import train_depth
    d = tmp_path_factory.mktemp("nets")
    train_dacn(_config(pairs, iters=2, checkpoint_every=2), d / "dacn")
    train_depth(DepthTrainConfig(data=str(pairs), widths=(4, 8), iters=2, batch=1, crop=16, val_fraction=1 / 6,
                                 test_fraction=2 / 6), d / "depth")
    export_dacn(d / "dacn", d / "dacn.npz")
    export_depthnet(d / "depth", d / "depth.npz")
    return d


def _args(d, *extra):
    return ["--image", str(d / "aif.exr"), "--lens", "mos-s1", "--keep", "0.7", "1.5", *FAST, *extra]


def test_sharp_input_camera_none_true_depth_equals_bokeh(scene, capsys):
    d = scene
    assert main(["bokeh", *_args(d, "--depth", str(d / "depth.exr"), "-o", str(d / "b.exr"))]) == 0
    capsys.readouterr()
    assert main(["dof", *_args(d, "--depth", str(d / "depth.exr"), "--camera", "none", "-o", str(d / "p.exr"))]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["camera"], out["depth_source"], out["psf_source"]) == ("none", "given", "trace")
    assert out["correction"]["method"] == "none"
    np.testing.assert_array_equal(read_image(d / "p.exr"), read_image(d / "b.exr"))


def test_without_a_depth_map_the_deconvolution_takes_the_estimated_depth(scene, networks, capsys):
    d = scene
    assert main(["dof", *_args(d, "--camera", "mos-s2", "--method", "deconv", "--depth-checkpoint",
                               str(networks / "depth.npz"), "-o", str(d / "p.exr"), "--save-intermediates",
                               str(d / "mid"))]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["depth_source"] == "dcdi" and out["correction"]["method"] == "deconv"
    from dcdi_core.correct import deconvolve
    from dcdi_core.io.images import read_depth
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.psf.sources import open_library
    from dcdi_core.render.geometry import ImageGeometry
    cam = load_lens("mos-s2")
    capture, depth = read_image(d / "aif.exr"), read_depth(d / "mid" / "depth.exr")
    geom = ImageGeometry.full_sensor(cam, 48, 64)
    lib = open_library(cam, geom, PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=15), fit_depth_m=depth)
    want = deconvolve(capture, depth, cam, geometry=geom, library=lib).image
    np.testing.assert_allclose(read_image(d / "mid" / "corrected.exr"), want, atol=1e-3)


def test_end_to_end_with_the_dcdi_depth_network(scene, networks, capsys):
    d = scene
    assert main(["dof", *_args(d, "--camera", "mos-s2", "--dacn", str(networks / "dacn.npz"), "--depth-checkpoint",
                               str(networks / "depth.npz"), "-o", str(d / "p.exr"), "--save-intermediates",
                               str(d / "mid"), "--side-by-side", str(d / "s.png"))]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["depth_source"] == "dcdi" and {"correction", "depth"} <= set(out["seconds"])
    # a network given with --dacn: auto runs it
    assert out["correction"]["method"] == "dacn" and "--dacn" in out["correction"]["reason"]
    res, cor = read_image(d / "p.exr"), read_image(d / "mid" / "corrected.exr")
    assert res.shape == cor.shape == (48, 64, 3) and np.isfinite(res).all() and (d / "s.png").exists()


@pytest.mark.parametrize("backend", ["depth-anything-v2", "unidepth", "depth-pro"])
def test_end_to_end_with_each_public_estimator_through_a_stand_in(scene, networks, monkeypatch, capsys, backend):
    from support.depth_stand_ins import install_stand_ins

    from dcdi_core.io.images import read_depth
    from dcdi_core.models.depth.estimators import srgb_uint8
    d = scene
    ck = install_stand_ins(monkeypatch, d)[backend]
    assert main(["dof", *_args(d, "--camera", "mos-s2", "--dacn", str(networks / "dacn.npz"), "--depth-backend",
                               backend, "--depth-checkpoint", str(ck), "-o", str(d / "p.exr"),
                               "--save-intermediates", str(d / "mid"))]) == 0
    assert json.loads(capsys.readouterr().out)["depth_source"] == backend
    expected = 1 + 4 * srgb_uint8(read_image(d / "aif.exr")).mean(axis=2) / 255
    np.testing.assert_allclose(read_depth(d / "mid" / "depth.exr"), expected, rtol=1e-5)
    assert np.isfinite(read_image(d / "p.exr")).all()


def test_end_to_end_with_the_depth_from_blur(scene, capsys):
    """--depth-backend blur: the depth read from the capture's own blur
    through --camera (numpy, no checkpoint), finite, within the PSF
    library's range, and the chain finishes (this sharp 48 x 64 frame is no
    capture of mos-s2: its depth is too uncertain for the rule, so the
    chain runs with --uncertain-depth accept and says so)."""
    from dcdi_core.io.images import read_depth
    d = scene
    assert main(["dof", *_args(d, "--camera", "mos-s2", "--method", "deconv", "--depth-backend", "blur",
                               "--uncertain-depth", "accept", "-o", str(d / "p.exr"),
                               "--save-intermediates", str(d / "mid"))]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["depth_source"] == "blur" and any("correction is kept on" in n for n in out["notes"])
    depth = read_depth(d / "mid" / "depth.exr")
    assert np.isfinite(depth).all() and 0.7 <= depth.min() and depth.max() <= 10.0
    assert np.isfinite(read_image(d / "p.exr")).all()


def test_without_depth_the_blur_runs_where_recorded_better_at_that_pitch(scene, capsys, monkeypatch):
    """No --depth and no --depth-backend: the depth from blur runs unasked
    for a lens the registry records 30 % better than a constant, at the
    pixel pitch its shipped refinement learned; at another pitch, --depth is
    asked for, naming the pitch."""
    from dcdi_core import shipped as registry
    monkeypatch.setattr(registry, "REFINEMENT", replace(registry.REFINEMENT, beats_constant_depth=("mos-s1",)))
    d = scene
    assert main(["dof", *_args(d, "--camera", "mos-s1", "--method", "deconv", "--image-pixel-pitch", "0.0122",
                               "--uncertain-depth", "accept", "-o", str(d / "p.exr"))]) == 0
    assert json.loads(capsys.readouterr().out)["depth_source"] == "blur"
    assert main(["dof", *_args(d, "--camera", "mos-s1", "--method", "deconv", "-o", str(d / "q.exr"))]) != 0
    assert "at this pixel pitch" in capsys.readouterr().err and not (d / "q.exr").exists()


def test_what_is_missing_is_said_before_any_work(scene, networks, capsys):
    d = scene
    cases = [(["--camera", "6p", "--method", "dacn", "--depth", str(d / "depth.exr")], "no shipped DACN for lens 6p"),
             (["--camera", "none"], "no depth map"),
             (["--camera", "mos-s1", "--dacn", str(networks / "dacn.npz"), "--depth", str(d / "depth.exr")],
              "trained for lens mos-s2"),
             # a shipped depth network not recorded better than a constant depth is not used unasked
             (["--camera", "mos-s2", "--method", "deconv"], "recorded 30 % better than a constant depth"),
             (["--camera", "mos-s2", "--method", "deconv"], "--depth-backend blur"),
             (["--camera", "none", "--depth-backend", "blur"], "give --camera LENS")]
    for extra, says in cases:
        assert main(["dof", *_args(d, *extra, "-o", str(d / "p.exr"))]) != 0
        assert says in capsys.readouterr().err
    assert not (d / "p.exr").exists()


def test_pipeline_and_depth_reports_on_held_out_pairs(pairs, networks, tmp_path, capsys):  # noqa: F811
    dacn, dep = f"mos-s2={networks / 'dacn.npz'}", f"mos-s2={networks / 'depth.npz'}"
    assert lab_main(["report", "pipeline", "--pairs", f"mos-s2={pairs}", "--dacn", dacn, "--depth-model", dep,
                     "--baseline", dacn, "--target", "mos-s1", "--count", "1", "--quick", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for row in ("no correction", "corrected, true depth", "corrected, estimated depth", "depth-unaware model"):
        assert f"| {row} |" in out
    assert list((tmp_path / "pictures").glob("mos-s2-*.png"))
    assert lab_main(["report", "depth", "--pairs", f"mos-s2={pairs}", "--depth-model", dep, "--count", "2",
                     "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| mos-s2 | 2 | capture |" in out and "| mos-s2 | 2 | sharp |" in out and "constant" not in out
    # the bar: the training pairs' median depth everywhere, scored on the same held-out pairs
    assert lab_main(["report", "depth", "--pairs", f"mos-s2={pairs}", "--depth-model", dep, "--count", "2",
                     "--train-pairs", f"mos-s2={pairs}", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "depth.json").read_text())["mos-s2"]
    assert res["constant_m"] in (0.9, 5.0)                     # the frames hold these two depths only
    from lab.pipeline_report import held_out
    from dcdi_core.models.dacn.data import load_pair, pair_path
    want = []
    for pid in held_out(pairs, [], 2):
        t = np.asarray(load_pair(pair_path(pairs, pid)).depth)
        t = t[np.isfinite(t)]
        want.append(np.mean(np.abs(res["constant_m"] - t) / t))
    assert res["constant"]["abs_rel"] == pytest.approx(np.mean(want), rel=1e-6)
    out = capsys.readouterr().out
    assert f"| constant {res['constant_m']:.2f} m |" in out and " %" in out


# ------------------------------------------------------------------ the one rule
def test_auto_picks_the_network_only_where_it_is_recorded_better_at_its_pitch(monkeypatch):
    from dcdi_core.shipped import network
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.app.correction_rule import choose_correction, trained_pitch_mm
    from dcdi_core.render.geometry import ImageGeometry
    dacn = network("dacn")
    for lens_id in ("mos-s1", "mos-s2", "double-gauss", "6p"):
        pitch = ImageGeometry.full_sensor(load_lens(lens_id), 480, 640).pixel_pitch_mm
        method, why = choose_correction(lens_id, pitch)
        learned = trained_pitch_mm(dacn.shipped_file(lens_id)) if dacn.shipped_file(lens_id) else None
        # the shipped networks learned the paper's 12.2 um: a full-sensor frame (35.2 um) is deconvolved
        assert method == "deconv" and (learned is None or abs(learned - pitch) > 0.01), (lens_id, why)
    for lens_id in dacn.beats_deconvolution:
        method, why = choose_correction(lens_id, trained_pitch_mm(dacn.shipped_file(lens_id)))
        assert method == "dacn" and "recorded better" in why, (lens_id, why)
    dacn_recorded_better(monkeypatch, ())
    for lens_id in dacn.shipped_keys():
        method, why = choose_correction(lens_id, 0.0122)
        assert method == "deconv" and why == (
            f"the shipped DACN of {lens_id} is not recorded better than the deconvolution on held-out "
            "captures, the DACN study (docs/correction.md)")


@pytest.fixture
def recorded_better(monkeypatch):
    """The registry as if the DACN study had found the shipped DACN of mos-s1 (only) better."""
    from dcdi_core import shipped as registry
    if registry.NETWORKS["dacn"].shipped_file("mos-s1") is None:
        pytest.skip("no shipped DACN of mos-s1")
    nets = dacn_recorded_better(monkeypatch, ("mos-s1",))
    from dcdi_core.app.correction_rule import trained_pitch_mm
    return trained_pitch_mm(nets["dacn"].shipped_file("mos-s1"))


def test_auto_picks_a_network_recorded_better_at_the_pitch_it_learned_only(recorded_better):
    from dcdi_core.app.correction_rule import choose_correction
    from dcdi_core.psf.pitch import NETWORK_PITCH_RTOL as PITCH_TOLERANCE
    learned = recorded_better
    assert learned and learned > 0
    method, why = choose_correction("mos-s1", learned * (1 + PITCH_TOLERANCE / 2))
    assert method == "dacn" and "recorded better" in why and "pixel pitch it learned" in why
    method, why = choose_correction("mos-s1", learned * 1.5)
    assert method == "deconv" and f"learned {learned * 1000:.4g} um pixels" in why
    assert choose_correction("mos-s2", learned)[0] == "deconv"          # not recorded for mos-s2
    assert choose_correction("mos-s1", learned, "deconv") == ("deconv", "asked for: \u2039method\u203a deconv")


def test_choose_correction_refuses_what_cannot_run_naming_the_field():
    from dcdi_core.errors import DcdiError, in_words
    from dcdi_core.app.correction_rule import choose_correction
    for args, says in [(("6p", 0.01, "wiener"), "method = 'wiener'"),
                       (("6p", 0.01, "dacn"), "no shipped DACN for lens 6p"),
                       (("6p", 0.01, "dacn"), "give model"),
                       ((None, 0.01, "auto"), "lens is missing"),
                       (("6p", 0.01, "deconv", "net.npz"), "model = 'net.npz'")]:
        with pytest.raises(DcdiError, match=says) as e:
            choose_correction(*args)
        assert "\u2039" not in str(e.value)
    with pytest.raises(DcdiError) as e:
        choose_correction("6p", 0.01, "dacn")
    assert "give Correction Model" in e.value.in_words({"model": "Correction Model"})
    why = choose_correction(None, None, "auto", "net.npz")
    assert why[0] == "dacn" and in_words(why[1], {"model": "--model"}) == "a network was given: --model net.npz"
    assert choose_correction("6p", 0.01, "dacn", "net.npz")[0] == "dacn"


def test_correct_and_dof_deconvolve_with_the_camera_lens(tmp_path, monkeypatch):
    from dcdi_core import app
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.geometry import ImageGeometry
    from dcdi_core.render.request import RenderRequest
    from dcdi_core.render.simulate import LensSimulator, SimulateOptions
    img, depth = write_rgbd_scene(tmp_path, monkeypatch, 48, 64)
    cam, target = load_lens("6p"), load_lens("mos-s1")
    settings = PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=15)
    geom = ImageGeometry.from_pixel_pitch(cam, 48, 64, 0.05)
    r = LensSimulator(cam, SimulateOptions(geometry=geom, settings=settings), fit_depth_m=depth)(img, depth)
    on_sensor = RenderRequest(cam, psf=settings, image_pixel_pitch_mm=0.05)
    request = app.CorrectRequest(r.image, depth, cam, render=on_sensor, psf=app.PSFRequest(source="trace"))
    _, correction, geometry, _ = app.prepare(request, (48, 64))
    assert correction.method == "deconv" and geometry == geom and "no DACN ships" in correction.reason
    fixed = app.correct(request)
    assert fixed.method == "deconv" and fixed.info["psf_source"] == "trace"

    def psnr(a):
        return -10 * np.log10(np.mean((np.clip(a, 0, 1) - np.clip(r.sharp, 0, 1)) ** 2))
    assert psnr(fixed.image) > psnr(r.image) + 2.0
    # the chain with the camera lens: the same rule and the same deconvolution
    bokeh = app.BokehRequest(None, None, target, keep=(1.0, 2.0), psf=app.PSFRequest(source="trace"),
                             render=RenderRequest(target, psf=settings))
    res = app.dof(app.DofRequest(request, bokeh))
    assert res.correction.method == "deconv" and "no DACN ships for lens 6p" in res.correction.reason
    assert res.depth_source == "given"
    np.testing.assert_array_equal(res.corrected, fixed.image)


def test_a_dof_job_decides_its_frame_and_its_target_plan_once(tmp_path, monkeypatch):
    """app.dof makes the capture's frame, the target lens's plan and each
    lens's PSF source once for the whole job (the depth, the correction and
    the bokeh share them), returns the depth estimate's posterior in its
    result, and chooses the depth estimator by the rule where none is given."""
    from dcdi_core import app
    from dcdi_core.app import correction as app_correction, depth as app_depth, pipeline, render as app_render
    from dcdi_core.psf import sources as psf_sources
    from dcdi_core.errors import ModelError
    from dcdi_core.optics.lens import load_lens
    from dcdi_core.psf.compute import PSFSettings
    from dcdi_core.render.request import RenderRequest
    img, depth = write_rgbd_scene(tmp_path, monkeypatch, 48, 64)
    cam, target = load_lens("6p"), load_lens("mos-s1")
    settings = PSFSettings(pupil_samples=16, n_wavelengths=3, kernel_size=15)
    calls = {"frame": 0, "plan": 0}
    chosen, made = [], []

    def counted(name, fn):
        def wrapped(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapped

    def chose(lens, **k):
        chosen.append(lens.id)
        return psf_source(lens, **k)
    psf_source = psf_sources.psf_source
    monkeypatch.setattr(psf_sources, "psf_source", chose)
    from dcdi_core.psf.library import PSFLibrary
    open_library = PSFLibrary.open

    def opened(lens, settings, *a, **k):
        made.append((lens.id, settings.kernel_size))
        return open_library(lens, settings, *a, **k)
    monkeypatch.setattr(PSFLibrary, "open", staticmethod(opened))
    for module in (pipeline, app_correction, app_depth):
        monkeypatch.setattr(module, "capture_frame", counted("frame", module.capture_frame))
    for module in (pipeline, app_render):
        monkeypatch.setattr(module, "bokeh_plan", counted("plan", app_render.bokeh_plan))
    request = app.CorrectRequest(img, depth, cam, render=RenderRequest(cam, psf=settings, image_pixel_pitch_mm=0.05),
                                 psf=app.PSFRequest(source="trace"))
    bokeh = app.BokehRequest(None, None, target, keep=(1.0, 2.0), psf=app.PSFRequest(source="trace"),
                             render=RenderRequest(target, psf=settings))
    res = app.dof(app.DofRequest(request, bokeh))
    assert res.depth_source == "given" and res.depth is None
    assert calls == {"frame": 1, "plan": 1}, calls
    assert sorted(chosen) == ["6p", "mos-s1"], chosen
    # the depth read from the capture's blur: its estimate, the rule on its posterior and the correction
    # on the one frame and the one PSF source of the camera lens (its traced library opened once: the
    # deconvolution's kernel grown from the estimate's), the rule and the bokeh on the one plan
    calls.update(frame=0, plan=0)
    chosen.clear(), made.clear()
    res = app.dof(app.DofRequest(replace(request, depth_m=None), bokeh, depth_backend="blur",
                                 uncertain_depth="accept"))
    assert res.depth_source == "blur" and calls == {"frame": 1, "plan": 1}, calls
    assert sorted(chosen) == ["6p", "mos-s1"], chosen
    assert len(set(made)) == len(made) and ("6p", 15) in made, made     # no library opened twice
    assert res.depth.posterior is not None and res.corrected_share is not None
    np.testing.assert_array_equal(res.depth.depth_m, res.depth_m)
    # no depth map and no backend: the estimator by the rule (here refused: no shipped depth network for
    # the 6P, none recorded for its blur at this pitch), before any correction
    calls.update(frame=0, plan=0)
    with pytest.raises(ModelError, match="no depth map"):
        app.dof(app.DofRequest(replace(request, depth_m=None), bokeh))
    assert calls["frame"] == 1
